"""Examples of the entry points of torchmm.fusion, torchmm.parallel and torchmm.smooth (see
tests/robustness/api_examples.py). Small set-ups: a 2-state, 2-sensor fusion system over 4 steps
and 3 runs; a constant-velocity Kalman filter over 5 steps and 3 runs."""

from __future__ import annotations

import torch

from tests.robustness.api_examples import call, example
from torchmm import GaussianBelief, KalmanFilter, fusion, models, parallel, run_filter
from torchmm.fusion.augmented import augmented_system
from torchmm.smooth import smooth

_F = "torchmm.fusion."
STEPS = 4


# -- shared set-ups (built inside the examples, so in float64) ----------------------------------------
def _gen():
    return torch.Generator().manual_seed(0)


def _system():
    return fusion.MultiSensorSystem.from_correlation(**_correlation())


def _correlation():
    return dict(A=[[0.8, 0.1], [0.0, 0.5]], Gamma=[[1.0, 0.0], [0.3, 1.0]], Qw=[[1.0, 0.2], [0.2, 0.5]],
                C=[[[1.0, 0.0]], [[0.5, 1.0]]], Ct=[[[0.5, 0.0]], [[0.0, 0.2]]], h=[0.6, 0.7], Qp=[0.1, 0.2],
                d=[[[0.0, 0.3]], [[0.2, 0.0]]], Q_eta=[[[1.0]], [[2.0]]], mu0=[0.5, -0.5],
                P0=[[1.0, 0.2], [0.2, 0.8]])


def _y(system=None):
    return fusion.simulate_fusion(system or _system(), STEPS, (3,), _gen()).y  # (T, 3, L, m)


def _present():
    present = torch.ones(STEPS, 2, 1, dtype=torch.bool)
    present[1, 0, 0] = False  # sensor 0 misses step 1 (in every run)
    return present


def _stats(system):
    return fusion.local_predictor_stats(system, STEPS)


def _cross(system, stats):
    return fusion.cross_predictor_stats(system, stats)


# -- the system -----------------------------------------------------------------------------------------
def _init():
    s = _system()
    return call(fusion.MultiSensorSystem, s.A, s.Gamma, s.Qw, s.C, s.Ct, s.h, s.Qp, s.Qr0, s.R, s.Qv, s.mu0,
                s.P0)


def _create():
    s = _system()
    return call(fusion.MultiSensorSystem.create, s.A, s.Gamma, s.Qw, s.C, s.Ct, s.h, s.Qp, s.R, s.Qv, s.mu0,
                s.P0, None, dtype=torch.float64, device="cpu")


example(_F + "system.MultiSensorSystem")(_init)
example(_F + "system.MultiSensorSystem.create")(_create)
example(_F + "system.MultiSensorSystem.from_correlation")(
    lambda: call(fusion.MultiSensorSystem.from_correlation, **_correlation(), Qr0=None, dtype=torch.float64,
                 device=None))
example(_F + "system.simulate_fusion")(
    lambda: call(fusion.simulate_fusion, _system(), STEPS, (3,), generator=_gen()))
example(_F + "system.measurement_sequence")(
    lambda: call(fusion.measurement_sequence, _system(), STEPS, _present()))


def _pattern():
    y = _y()
    y[1, :, 0, 0] = float("nan")  # the same missing component in every run
    return call(fusion.measurement_pattern, _system(), y)


example(_F + "system.measurement_pattern")(_pattern)

# -- local estimators and cross-covariances ---------------------------------------------------------
example(_F + "local.local_predictor_stats")(
    lambda: call(fusion.local_predictor_stats, _system(), STEPS, _present()))


def _local(name, *args, **kwargs):
    """``fn(system, stats, ...)``: the example with the system's own statistics."""
    def build():
        system = _system()
        return call(getattr(fusion, name), system, _stats(system), *args, **kwargs)
    return build


example(_F + "local.local_one_step")(lambda: _local("local_one_step", _y())())
example(_F + "local.local_covariances")(_local("local_covariances", 1, steps=STEPS))
example(_F + "cross.cross_predictor_stats")(_local("cross_predictor_stats", steps=STEPS))


def _local_estimates():
    system = _system()
    return call(fusion.local_estimates, system, _y(system), 1, stats=_stats(system))


def _pairs(name, N, **kwargs):
    def build():
        system = _system()
        stats = _stats(system)
        return call(getattr(fusion, name), system, stats, _cross(system, stats), N, **kwargs)
    return build


example(_F + "local.local_estimates")(_local_estimates)
example(_F + "cross.cross_covariances")(_pairs("cross_covariances", 1, steps=STEPS))
example(_F + "cross.theorem6_cross_covariances")(_pairs("theorem6_cross_covariances", 1, xi_term=True))

# -- augmented and centralized ----------------------------------------------------------------------
example(_F + "augmented.augmented_cross_predictor")(
    lambda: call(fusion.augmented_cross_predictor, _system(), STEPS))
example(_F + "augmented.augmented_local_estimates")(
    lambda: call(fusion.augmented_local_estimates, _system(), _y(), 1))
example(_F + "augmented.centralized_estimates")(
    lambda: call(fusion.centralized_estimates, _system(), _y(), N=0))


def _correlated_kf():
    system = _system()
    Phi, G, Q, S, Qv, H, x0, P0 = augmented_system(system, STEPS)
    return call(fusion.correlated_kf, Phi, G, Q, S, Qv, H, x0, P0, _y(system))


example(_F + "augmented.correlated_kf")(_correlated_kf)

# -- steady state ---------------------------------------------------------------------------------------
example(_F + "steady.steady_moments")(lambda: call(fusion.steady_moments, _system(), tol=1e-14, max_iter=200))
example(_F + "steady.steady_state")(lambda: call(fusion.steady_state, _system(), 1e-10, max_iter=5000))


def _steady(name, **kwargs):
    def build():
        system = _system()
        return call(getattr(fusion, name), system, fusion.steady_state(system), _y(system), 1, **kwargs)
    return build


example(_F + "steady.steady_local_estimates")(_steady("steady_local_estimates"))
example(_F + "steady.steady_fused_estimates")(_steady("steady_fused_estimates", method="scalar"))

# -- weights --------------------------------------------------------------------------------------------


def _joint():
    """The filters' joint error covariances ``(T, L, L, n, n)`` and their estimates ``(T, 3, L, n)``."""
    system = _system()
    stats = _stats(system)
    P = fusion.cross_covariances(system, stats, _cross(system, stats), 0)
    mean, _ = fusion.local_estimates(system, _y(system), 0, stats=stats)
    return mean, P


example(_F + "weights.fusion_weights")(lambda: call(fusion.fusion_weights, _joint()[1], "diagonal"))
example(_F + "weights.fuse")(lambda: call(fusion.fuse, *_joint(), "matrix", components=[0]))


def _fuse_tracks():
    a = GaussianBelief(torch.tensor([0.0, 1.0]), torch.tensor([[1.0, 0.1], [0.1, 1.2]]))
    b = GaussianBelief(torch.tensor([0.5, 0.8]), torch.tensor([[1.1, -0.1], [-0.1, 0.9]]))
    cross = torch.zeros(2, 2, 2, 2)
    cross[0, 0], cross[1, 1] = a.cov, b.cov
    cross[0, 1] = cross[1, 0] = 0.2 * torch.eye(2)
    return call(fusion.fuse_tracks, [a, b], cross, method="matrix")


example(_F + "weights.fuse_tracks")(_fuse_tracks)


# -- parallel and smooth -----------------------------------------------------------------------------------
def _kf_run():
    kf = KalmanFilter(models.ConstantVelocity(1, q=0.1, dtype=torch.float64),
                      models.PositionMeasurement(2, [0], 1.0, dtype=torch.float64))
    z = torch.randn(5, 3, 1, generator=_gen())
    belief0 = GaussianBelief(torch.zeros(3, 2), 4 * torch.eye(2).expand(3, 2, 2))
    return kf, belief0, z


example("torchmm.parallel.filter")(lambda: call(parallel.filter, *_kf_run()))
example("torchmm.parallel.smooth")(lambda: call(parallel.smooth, *_kf_run()))
example("torchmm.parallel.associative_scan")(
    lambda: call(parallel.associative_scan, lambda a, b: (a[0] + b[0], torch.maximum(a[1], b[1])),
                 (torch.arange(5.0).reshape(5, 1), torch.randn(5, 2, generator=_gen()))))


def _smooth():
    kf, belief0, z = _kf_run()
    traj = run_filter(kf, belief0, z)
    return call(smooth, kf, traj, z, controls=None, motions=None, sensors=None, lag=None, method=None)


example("torchmm.smooth.smooth")(_smooth)
