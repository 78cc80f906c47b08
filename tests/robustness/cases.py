"""One small, valid set-up per estimator family of torchmm, for the robustness suite.

Every :class:`Case` builds a fresh filter (particle filters get a freshly seeded generator, so two
builds give the same random stream), its start belief for ``B`` runs and valid data ``(T, B, m)``
(a :class:`~torchmm.multimodel.MultiRate` pair for the multi-rate IMMs). The data come from NumPy's
``default_rng`` (platform-independent); tests assert properties, never the exact values.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torchmm import (
    GPB1,
    GPB2,
    IMM,
    VBAKFPR,
    ConstantVelocity,
    EqMAParticleFilter,
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    MinimumEntropyVSMM,
    MultipleModelParticleFilter,
    NonlinearCoordinatedTurn,
    ParticleFilter,
    PositionMeasurement,
    RangeBearing,
    SkewTIWVBFilter,
    SkewTVBFilter,
    StudentTVBFilter,
    UnscentedKalmanFilter,
    gimmaf,
    imm_vbt,
)
from torchmm.multimodel import (
    FusionIMM,
    InfluenceGate,
    MultiRate,
    SourceModeVSIMM,
    SourceUpdateIMM,
    TransferIMM,
)
from torchmm.multimodel.mevsmm import ChallengeMatch, uniform_transition

P3 = [[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]]


@dataclass
class Case:
    name: str
    make: Callable[[], Any]
    start: Callable[[Any, int], Any]  # (filter, runs) -> belief0 with batch (runs,)
    meas_dim: int
    multirate: bool = False
    source_dim: int = 0
    particles: bool = False
    #: a typical measurement (the data are unit noise around it)
    level: tuple = (0.0,)
    noise: float = 1.0

    def data(self, steps: int, runs: int, seed: int = 0, dtype=torch.float64) -> Any:
        rng = np.random.default_rng(seed)
        level = np.asarray(self.level)
        y = torch.tensor(level + self.noise * rng.normal(size=(steps, runs, self.meas_dim)), dtype=dtype)
        if not self.multirate:
            return y
        ys = torch.tensor(level + rng.normal(size=(steps, runs, self.source_dim)), dtype=dtype)
        ys[rng.uniform(size=(steps, runs)) < 0.4] = float("nan")
        return MultiRate(y, ys)


def _gen() -> torch.Generator:
    return torch.Generator().manual_seed(7)


def _cv1(dtype=torch.float64):
    return ConstantVelocity(1, q=0.5, dtype=dtype)


def _bank1(dtype=torch.float64):
    return ConstantVelocity(1, q=0.5, acceleration=torch.tensor([[0.5], [0.0], [-0.5]], dtype=dtype), dtype=dtype)


def _pos1(r=4.0, dtype=torch.float64):
    return PositionMeasurement(2, [0], torch.tensor(r, dtype=dtype), dtype=dtype)


def _cv2(dtype=torch.float64):
    return ConstantVelocity(2, q=0.5, dtype=dtype)


def _pos2(r=4.0, dtype=torch.float64):
    return PositionMeasurement(4, [0, 2], torch.tensor(r, dtype=dtype), dtype=dtype)


def _prior(n: int, runs: int, dtype=torch.float64, scale=10.0) -> GaussianBelief:
    return GaussianBelief(torch.zeros(runs, n, dtype=dtype), scale * torch.eye(n, dtype=dtype).expand(runs, n, n))


def _ct_prior(runs: int, dtype=torch.float64) -> GaussianBelief:
    mean = torch.tensor([100.0, 5.0, 50.0, -2.0, 0.0], dtype=dtype).expand(runs, 5)
    cov = torch.diag(torch.tensor([4.0, 1.0, 4.0, 1.0, 1e-3], dtype=dtype)).expand(runs, 5, 5)
    return GaussianBelief(mean, cov)


def _plain(n):
    return lambda f, runs: _prior(n, runs)


def _mm(n):
    return lambda f, runs: f.initial_belief(_prior(n, runs))


def _adaptive(n):
    return lambda f, runs: f.initial_belief(_prior(n, runs))


def _pf(n, Np=64):
    return lambda f, runs: f.initial_belief(_prior(n, runs), Np)


def _imm_pf(n, Np=64):
    def start(f, runs):
        pf = f.bank.filter
        return f.initial_belief(pf.initial_belief(_prior(n, runs), Np))
    return start


def _rb() -> RangeBearing:
    return RangeBearing(5, torch.diag(torch.tensor([1.0, 1e-4])))


def _multirate(cls, **kwargs):
    return lambda: cls(KalmanFilter(_bank1(), _pos1(100.0)), torch.tensor(P3), _pos1(10.0), **kwargs)


CASES = [
    Case("kf", lambda: KalmanFilter(_cv2(), _pos2()), _plain(4), 2),
    Case("kf_joseph", lambda: KalmanFilter(_cv2(), _pos2(), joseph=True), _plain(4), 2),
    Case("ekf", lambda: ExtendedKalmanFilter(NonlinearCoordinatedTurn(q=0.1), _rb()), lambda f, r: _ct_prior(r), 2,
         level=(111.8, 0.4636), noise=0.01),
    Case("ukf", lambda: UnscentedKalmanFilter(NonlinearCoordinatedTurn(q=0.1), _rb()), lambda f, r: _ct_prior(r), 2,
         level=(111.8, 0.4636), noise=0.01),
    Case("imm", lambda: IMM(KalmanFilter(_bank1(), _pos1()), torch.tensor(P3)), _mm(2), 1),
    Case("imm_list", lambda: IMM([KalmanFilter(_cv1(), _pos1()), ExtendedKalmanFilter(_cv1(), _pos1())],
                                 torch.tensor([[0.9, 0.1], [0.1, 0.9]])), _mm(2), 1),
    Case("gpb1", lambda: GPB1(KalmanFilter(_bank1(), _pos1()), torch.tensor(P3)), _mm(2), 1),
    Case("gpb2", lambda: GPB2(KalmanFilter(_bank1(), _pos1()), torch.tensor(P3)), _mm(2), 1),
    Case("student_t", lambda: StudentTVBFilter(_cv2(), _pos2(), df=5.0, iterations=3), _plain(4), 2),
    Case("skew_t", lambda: SkewTVBFilter(_cv2(), _pos2(), skewness=1.0, df=5.0, iterations=3), _plain(4), 2),
    Case("skew_t_iw", lambda: SkewTIWVBFilter(_cv2(), _pos2(), skewness=1.0, df=5.0, iterations=3), _plain(4), 2),
    Case("vbakf", lambda: VBAKFPR(_cv2(), _pos2(), iterations=3), _adaptive(4), 2),
    Case("gimmaf", lambda: gimmaf(ConstantVelocity(2, q=0.5, acceleration=torch.tensor([[0.5, 0.0], [0.0, 0.0],
                                                                                         [-0.5, 0.0]])),
                                  _pos2(), torch.tensor(P3), skewness=1.0, df=5.0, iterations=3), _mm(4), 2),
    Case("imm_vbt", lambda: imm_vbt(ConstantVelocity(2, q=0.5, acceleration=torch.tensor([[0.5, 0.0], [0.0, 0.0],
                                                                                           [-0.5, 0.0]])),
                                    _pos2(), torch.tensor(P3), df=5.0, iterations=3), _mm(4), 2),
    Case("pf", lambda: ParticleFilter(_cv1(), _pos1(), generator=_gen()), _pf(2), 1, particles=True),
    Case("imm_pf", lambda: IMM(ParticleFilter(_bank1(), _pos1(), num_particles=64, generator=_gen()),
                               torch.tensor(P3)), _imm_pf(2), 1, particles=True),
    Case("mmpf", lambda: MultipleModelParticleFilter(_bank1(), _pos1(), torch.tensor(P3), 64, generator=_gen()),
         _mm(2), 1, particles=True),
    Case("mevsmm", lambda: MinimumEntropyVSMM(_bank1(), _pos1(), uniform_transition(3), 64,
                                              selection=ChallengeMatch(20, 3), generator=_gen()), _mm(2), 1,
         particles=True),
    Case("eqma", lambda: EqMAParticleFilter(_cv1().F, torch.tensor([[0.5], [1.0]]), torch.tensor([[0.5], [-0.5]]),
                                            torch.eye(1), _pos1(), 64, generator=_gen()), _mm(2), 1, particles=True),
    Case("imm_tf", _multirate(TransferIMM), _mm(2), 1, multirate=True, source_dim=1),
    Case("if_tf", _multirate(TransferIMM, gate=InfluenceGate()), _mm(2), 1, multirate=True, source_dim=1),
    Case("imm_su", _multirate(SourceUpdateIMM), _mm(2), 1, multirate=True, source_dim=1),
    Case("imm_fu", _multirate(FusionIMM), _mm(2), 1, multirate=True, source_dim=1),
    Case("vsimm", _multirate(SourceModeVSIMM, extra_model=1), _mm(2), 1, multirate=True, source_dim=1),
]

BY_NAME = {c.name: c for c in CASES}
GAUSSIAN = [c for c in CASES if not c.particles]
