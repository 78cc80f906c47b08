"""The fusion studies' keys (paper 002's radar example, fusion_radar; the UPS example, fusion_ups), split from
:mod:`experiments.schemas_papers` by study, with their sizes checked against each other before anything runs:
the same rules as :mod:`experiments.schemas` (a key the YAML sets has no default here, ``MISSING``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, List, Optional

from omegaconf import MISSING

from experiments.checks import (
    ConfigError,
    each,
    non_negative,
    positive,
    positive_int,
    spec,
)
from experiments.checks import (
    matrix as matrix_check,
)


@dataclass
class Radar:
    steps: int = spec(MISSING, positive_int)
    T: float = spec(MISSING, positive)
    rho: List[float] = spec(MISSING, check=lambda v: None if len(v) == 2 else
                            "expected 2 numbers (the x and y acceleration correlations)")
    tau: float = spec(MISSING, positive)
    h_sign: int = spec(MISSING, lambda v: None if v in (-1, 1) else "expected -1 or 1")
    h_factor: List[float] = MISSING
    sigma_r: List[float] = spec(MISSING, check=each(non_negative))
    Qr0: Optional[List[float]] = MISSING
    eta_std: List[Any] = spec(MISSING, check=matrix_check)
    Qw_diag: List[float] = spec(MISSING, check=each(non_negative))
    x0: List[float] = MISSING
    P0_diag: List[float] = spec(MISSING, check=each(non_negative))
    position_index: int = spec(MISSING, non_negative)
    C: List[Any] = MISSING
    Ct: List[Any] = MISSING
    d: List[Any] = MISSING

    def config_check(self):  # the 6-state model's vectors (issue 30: a short one failed in the study)
        for key in ("x0", "P0_diag", "Qw_diag"):
            if len(getattr(self, key)) != 6:
                return key, getattr(self, key), "expected 6 numbers (one per state)"
        sensors = len(self.sigma_r)
        if len(self.h_factor) != sensors:
            return "h_factor", self.h_factor, f"expected {sensors} numbers (one per sensor, as sigma_r)"
        if not 0 <= self.position_index < 6:
            return "position_index", self.position_index, "must be a state index in [0, 6)"
        rows = len(self.C[0]) if self.C and isinstance(self.C[0], list) else 0
        for key in ("C", "Ct", "d"):  # (sensors, m, 6): each sensor's m x 6 matrix
            value = getattr(self, key)
            if len(value) != sensors or any(not isinstance(M, list) or len(M) != rows or not rows or any(
                    not isinstance(r, list) or len(r) != 6 for r in M) for M in value):
                return key, value, (f"expected {sensors} matrices (one per sensor, as sigma_r) of "
                                    f"{rows or 'm'} rows (as C's first) of 6 numbers (one per state)")
        if len(self.eta_std) != sensors or any(len(r) != rows for r in self.eta_std):
            return "eta_std", self.eta_std, (f"expected {sensors} rows (one per sensor) of {rows} numbers "
                                             "(one per measurement component)")
        return None


@dataclass
class FusionRadar:
    radar: Radar = field(default_factory=Radar)


@dataclass
class Ups:
    steps: int = spec(MISSING, positive_int)
    burn_in: int = spec(MISSING, non_negative)
    horizons: List[int] = spec(MISSING, check=lambda v: None if 0 in v else
                               "must include 0 (the filter; negative: smoothing lags, positive: predictions)")
    ss_tol: float = spec(MISSING, positive)
    cf_ss_steps: int = spec(MISSING, positive_int)
    A: List[Any] = spec(MISSING, check=matrix_check)
    Gamma: List[Any] = spec(MISSING, check=matrix_check)
    Qw: float = spec(MISSING, non_negative)
    C: List[float] = MISSING
    Ct: List[Any] = spec(MISSING, check=matrix_check)
    h: List[float] = MISSING
    Qp: List[float] = spec(MISSING, check=each(non_negative))
    d: List[float] = MISSING
    Q_eta: List[float] = spec(MISSING, check=each(positive))
    mu0: List[float] = MISSING
    P0_scale: float = spec(MISSING, non_negative)
    Qr0: Optional[List[float]] = MISSING

    def config_check(self):  # sizes (issue 30: a short vector failed in the study, with a traceback)
        n, sensors = len(self.A), len(self.Ct)
        if any(len(row) != n for row in self.A):
            return "A", self.A, f"expected a square matrix ({n} x {n})"
        if len(self.Gamma) != n or len({len(row) for row in self.Gamma}) != 1 or not self.Gamma[0]:
            return "Gamma", self.Gamma, (f"expected {n} rows (one per state) of p numbers "
                                         "(one per noise component)")
        if any(len(row) != n for row in self.Ct):
            return "Ct", self.Ct, f"expected rows of {n} numbers (one per state), one row per sensor"
        for key, size in (("C", n), ("mu0", n), ("h", sensors), ("Qp", sensors), ("d", sensors),
                          ("Q_eta", sensors)):
            if len(getattr(self, key)) != size:
                unit = "state" if key in ("C", "mu0") else "sensor"
                return key, getattr(self, key), f"expected {size} numbers (one per {unit})"
        return None


@dataclass
class FusionUps:
    ups: Ups = field(default_factory=Ups)

    @staticmethod
    def check(data: dict) -> None:
        ups = data["ups"]
        if ups["burn_in"] >= ups["steps"]:
            raise ConfigError("ups.burn_in", ups["burn_in"], f"must be below ups.steps = {ups['steps']}")

