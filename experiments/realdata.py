r"""Models of the shipped real data (``experiments/data``): builders that a study or a test can use.

* :func:`fedfunds_imm` - the two-regime Markov-switching mean and variance model of the quarterly
  federal funds rate (statsmodels' ``MarkovRegression(y, k_regimes=2, trend="c",
  switching_variance=True)``) as an IMM over a constant state.
* :func:`local_level` - the local-level (random walk plus noise) model of the Nile flow
  (statsmodels' ``UnobservedComponents(y, "llevel")``) as a one-state Kalman filter.
* :func:`load_fedfunds`, :func:`load_nile` - the series as float tensors ``(T, 1)``.

The cross-checks against statsmodels are in ``tests/learn/test_real_data.py``; the measured
figures in ``docs/reproduction-learn.md`` ("Real data: Fed funds and Nile").
"""

from __future__ import annotations

import csv
from collections.abc import Sequence

import torch
from torch import Tensor

from experiments.data import path
from torchmm.beliefs import GaussianBelief, ModeBelief
from torchmm.filters import KalmanFilter
from torchmm.models import LinearMeasurement, LinearMotion
from torchmm.multimodel import IMM

__all__ = ["fedfunds_imm", "load_fedfunds", "load_nile", "local_level", "local_level_start"]


def _column(name: str, column: str, dtype: torch.dtype) -> Tensor:
    with path(name).open(newline="") as handle:
        values = [float(row[column]) for row in csv.DictReader(handle)]
    return torch.tensor(values, dtype=dtype).unsqueeze(-1)


def load_fedfunds(dtype: torch.dtype = torch.float64) -> Tensor:
    """The effective federal funds rate 1954Q3-2010Q4 (per cent), ``(226, 1)``."""
    return _column("fedfunds.csv", "rate", dtype)


def load_nile(dtype: torch.dtype = torch.float64) -> Tensor:
    """The annual Nile flow at Aswan 1871-1970 (10^8 m^3), ``(100, 1)``."""
    return _column("nile.csv", "flow", dtype)


def fedfunds_imm(mu: Sequence[float], sigma2: Sequence[float], transition,
                 dtype: torch.dtype = torch.float64, *, mode_probs=None) -> tuple[IMM, ModeBelief]:
    r"""A Markov-switching mean and variance, ``y_t = mu_{s_t} + e_t``, ``e_t ~ N(0, sigma2_{s_t})``,
    as an IMM over a constant state.

    The state is ``x = [1]``, known exactly (covariance 0) and constant (``F = [[1]]``, ``Q = [[0]]``);
    regime ``s`` measures it with ``H = [[mu_s]]``, ``R = [[sigma2_s]]``. Every Kalman step then has
    gain 0, the mixing has no spread, and the innovation density of regime ``s`` is exactly
    ``N(y_t; mu_s, sigma2_s)``: the IMM is Hamilton's filter, and Kim's smoother
    (``torchmm.smooth(traj, method="kim")``) is Kim's.

    Args:
        mu, sigma2: the regimes' means and variances (``M`` each).
        transition: ``(M, M)``, rows = from (``transition[i, j] = P(s_t = j | s_{t-1} = i)``; the
            transpose of statsmodels' ``regime_transition_matrix``).
        dtype: of the filter and the belief.
        mode_probs: the mode probabilities of the start belief: the regime one step before the
            first observation (every step, the first included, predicts with ``transition``);
            default uniform. statsmodels' ``MarkovRegression`` propagates its
            ``initial_probabilities`` ``pi_0`` *twice* before the first observation (its Hamilton
            filter runs on the joint ``(s_t, s_{t-1})`` and starts the joint from ``pi_0``), so
            its numbers are matched with ``mode_probs = pi_0 @ transition``; for its default, the
            ergodic probabilities, that is ``pi_0`` itself.

    Returns:
        ``(imm, belief0)``: run with ``run_filter(imm, belief0, y)`` (``update_first=False``: every
        step predicts the regime, then updates).
    """
    mu = torch.as_tensor(mu, dtype=dtype)
    sigma2 = torch.as_tensor(sigma2, dtype=dtype)
    if mu.dim() != 1 or sigma2.shape != mu.shape:
        raise ValueError(f"sigma2: expected one variance per mean ({tuple(mu.shape)}), "
                         f"got {tuple(sigma2.shape)}")
    one = torch.ones(1, 1, dtype=dtype)
    filters = [KalmanFilter(LinearMotion(one, torch.zeros(1, 1, dtype=dtype)),
                            LinearMeasurement(m.reshape(1, 1), s.reshape(1, 1)))
               for m, s in zip(mu, sigma2)]
    imm = IMM(filters, torch.as_tensor(transition, dtype=dtype))
    start = GaussianBelief(torch.ones(1, dtype=dtype), torch.zeros(1, 1, dtype=dtype))
    probs = None if mode_probs is None else torch.as_tensor(mode_probs, dtype=dtype)
    return imm, imm.initial_belief(start, probs)


def local_level_start(kf: KalmanFilter, first: Tensor | float) -> GaussianBelief:
    r"""The start belief of the *exact diffuse* initialisation of the local level: the filtered level
    after the first observation, ``N(y_1, r)`` with ``r`` the filter's own (differentiable) ``R``.

    With a diffuse prior on the level (``P_1 -> inf``) the first observation carries no likelihood
    and leaves ``a_{2} = y_1``, ``P_2 = r + q``; so the exact diffuse log-likelihood is the
    prediction-error decomposition over ``t = 2..T`` of a filter started from ``N(y_1, r)`` that
    predicts, then updates (``update_first=False``), which is statsmodels' diffuse ``llf`` (and
    Durbin and Koopman's). Rebuild it whenever ``R`` changes (e.g. in each L-BFGS closure).
    """
    R = kf.measurement.R
    mean = torch.as_tensor(first, dtype=R.dtype, device=R.device).reshape(1)
    return GaussianBelief(mean, R.reshape(1, 1))


def local_level(q: float, r: float, dtype: torch.dtype = torch.float64, *, first=None,
                known: tuple[float, float] | None = None,
                learnable: bool = False) -> tuple[KalmanFilter, GaussianBelief | None]:
    r"""The local-level model ``mu_{t+1} = mu_t + eta_t``, ``y_t = mu_t + eps_t``,
    ``eta ~ N(0, q)``, ``eps ~ N(0, r)``: a one-state Kalman filter and its start belief.

    Args:
        q, r: the level and irregular variances (statsmodels' ``sigma2.level``, ``sigma2.irregular``).
        dtype: of the filter and the belief.
        first: ``y_1``: the start belief is the exact diffuse one (:func:`local_level_start`,
            ``N(y_1, r)``); filter ``y_2..y_T`` with ``update_first=False``.
        known: ``(a_1, P_1)``: the start belief is the known prior of ``mu_1`` (statsmodels'
            ``initialization="known"``), the prior of the *first* measurement: filter ``y_1..y_T``
            with ``update_first=True``.
        learnable: ``Q`` and ``R`` log-parameterised learnable variances
            (``learnable_noise(..., "log_diagonal")``: the parameters are ``log q``, ``log r``).

    Returns:
        ``(kf, belief0)``; ``belief0`` is None when neither ``first`` nor ``known`` is given.
    """
    from torchmm.models import learnable_noise

    if first is not None and known is not None:
        raise ValueError("known: give either first (exact diffuse start) or known (a known prior), not both")
    one = torch.ones(1, 1, dtype=dtype)
    motion = LinearMotion(one, torch.full((1, 1), float(q), dtype=dtype))
    sensor = LinearMeasurement(one, torch.full((1, 1), float(r), dtype=dtype))
    if learnable:
        learnable_noise(motion, "Q", "log_diagonal")
        learnable_noise(sensor, "R", "log_diagonal")
    kf = KalmanFilter(motion, sensor)
    if first is not None:
        return kf, local_level_start(kf, first)
    if known is not None:
        a1, p1 = known
        return kf, GaussianBelief(torch.full((1,), float(a1), dtype=dtype),
                                  torch.full((1, 1), float(p1), dtype=dtype))
    return kf, None
