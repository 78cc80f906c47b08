"""Runs of different lengths in one batch (recorded series padded at the end): ``smooth(..., present=)``
smooths each run over its own steps, exactly as if it were alone (issue 44: padding moved the two-filter
IMM smoother's estimates and Kim's by up to 33 at the last real step)."""

from __future__ import annotations

import pytest
import torch

from torchmm import (GPB1, GPB2, IMM, ExtendedKalmanFilter, GaussianBelief, KalmanFilter, LinearMotion,
                     ParticleFilter, UnscentedKalmanFilter, run_filter, smooth)
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.run import Trajectory

#: run 0 long, so that the others are padded over many steps (the two-filter smoother's flat start at
#: the padded end then loses ~1e-3 of its precision by step 18; ~1e-8 from its own end)
LENGTHS = (300, 18, 1, 7)
T = max(LENGTHS)


def _data(m_runs=len(LENGTHS)):
    g = torch.Generator().manual_seed(5)
    t = torch.arange(T, dtype=torch.float64).view(T, 1, 1)
    z = 0.5 * t.square() * (t > 10) + 5.0 * torch.randn(T, m_runs, 1, generator=g, dtype=torch.float64)
    present = torch.zeros(T, m_runs, dtype=torch.bool)
    for r, length in enumerate(LENGTHS):
        present[:length, r] = True
        z[length:, r] = torch.nan  # padding: no datum
    return z, present


def _alone(traj: Trajectory, r: int, length: int) -> Trajectory:
    """Run ``r``'s own steps of ``traj``, as a trajectory of one run (built by hand: smoothed as given)."""
    def cut(b):
        return None if b is None else b[:length, r:r + 1]
    return Trajectory(belief=cut(traj.belief), prior=cut(traj.prior), log_likelihood=traj.log_likelihood[:length, r:r + 1],
                      innovation=None, innovation_cov=None, extras={})


def _fields(belief):
    if hasattr(belief, "mode_log_probs"):
        return [belief.mode_probs, belief.components.mean, belief.components.cov]
    if hasattr(belief, "log_weights"):
        return [belief.log_weights.exp()]
    return [belief.mean, belief.cov]


def _models():
    bank = ConstantVelocity(1, q=0.1, acceleration=[[0.0], [1.0]], dtype=torch.float64)
    return bank, PositionMeasurement(2, [0], 25.0, dtype=torch.float64)


def _filters():
    bank, sensor = _models()
    cv = bank.select_mode(0)
    pi = torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=torch.float64)
    return {
        "kalman": (KalmanFilter(cv, sensor), {}),
        "extended": (ExtendedKalmanFilter(cv, sensor), {}),
        "unscented": (UnscentedKalmanFilter(cv, sensor), {}),
        "particle": (ParticleFilter(LinearMotion(cv.F, torch.diag(torch.tensor([0.05, 0.1], dtype=torch.float64))),
                                    sensor, num_particles=40), {}),
        **{f"{c.__name__}-{m}": (c(KalmanFilter(bank, sensor), pi), {"method": m})
           for c in (IMM, GPB1, GPB2) for m in ("two_filter", "kim")},
    }


@pytest.mark.parametrize("name", list(_filters()))
def test_each_run_is_smoothed_over_its_own_steps(name):
    filt, options = _filters()[name]
    z, present = _data()
    prior = GaussianBelief(torch.zeros(len(LENGTHS), 2, dtype=torch.float64),
                           torch.diag(torch.tensor([100.0, 10.0], dtype=torch.float64)).expand(len(LENGTHS), 2, 2))
    generator = torch.Generator().manual_seed(0) if filt.uses_generator else None
    start = filt.initial_belief(prior, generator=generator) if generator is not None else filt.initial_belief(prior)
    traj = run_filter(filt, start, z, generator=generator)
    out = smooth(traj, present=present, **options).belief
    filtered = traj.belief
    for r, length in enumerate(LENGTHS):
        alone = smooth(filt, _alone(traj, r, length), z[:length, r:r + 1], **options).belief
        # the two-filter smoother's flat start (6.7e7 times the covariance) costs ~1e-8 of rounding between
        # batch sizes; the others agree to the last bits
        tol = 1e-6 if options.get("method") == "two_filter" else 1e-10
        for got, want in zip(_fields(out), _fields(alone)):
            torch.testing.assert_close(got[:length, r], want[:, 0], rtol=tol, atol=tol)
        for got, kept in zip(_fields(out), _fields(filtered)):  # padding keeps the filter's beliefs
            torch.testing.assert_close(got[length:, r], kept[length:, r], rtol=0, atol=0)


@pytest.mark.parametrize("name", ["IMM-kim", "IMM-two_filter"])
def test_without_present_padding_is_found_from_the_data(name):
    """Without ``present`` the padding (steps with no datum after a run's last one) is found from the
    measurements the trajectory carries: each run equals the run alone, as with ``present``. Without the data
    (a trajectory built by hand, smoothed without them: nothing to find it from) Kim's backward pass runs from
    the padded end and moves the short runs' estimates (relative error over 1e-2; the two-filter smoother
    always has the data): the defect both mend."""
    filt, options = _filters()[name]
    z, present = _data()
    prior = GaussianBelief(torch.zeros(len(LENGTHS), 2, dtype=torch.float64),
                           torch.diag(torch.tensor([100.0, 10.0], dtype=torch.float64)).expand(len(LENGTHS), 2, 2))
    traj = run_filter(filt, filt.initial_belief(prior), z)
    r, length = 1, LENGTHS[1]
    alone = smooth(filt, _alone(traj, r, length), z[:length, r:r + 1], **options).estimate().mean[:, 0]
    found = smooth(traj, **options).estimate().mean[:length, r]
    torch.testing.assert_close(found, alone, rtol=1e-6, atol=1e-6)
    if options["method"] == "kim":
        bare = Trajectory(belief=traj.belief, prior=traj.prior, log_likelihood=traj.log_likelihood,
                          innovation=None, innovation_cov=None, extras={})
        padded = smooth(filt, bare, **options).estimate().mean[:length, r]
        assert float(((padded - alone).abs() / (alone.abs() + 1)).max()) > 1e-2


def test_fixed_lag_needs_no_mask_for_gaussian_filters():
    """A padded step's filtered belief is its prediction, which the RTS step returns unchanged: fixed-lag
    smoothing of a padded batch equals each run's own (the reason ``lag`` ignores padding)."""
    bank, sensor = _models()
    kf = KalmanFilter(bank.select_mode(0), sensor)
    z, _ = _data()
    prior = GaussianBelief(torch.zeros(len(LENGTHS), 2, dtype=torch.float64),
                           torch.eye(2, dtype=torch.float64).expand(len(LENGTHS), 2, 2) * 100)
    traj = run_filter(kf, prior, z)
    out = smooth(traj, lag=4).belief
    for r, length in enumerate(LENGTHS):
        alone = smooth(kf, _alone(traj, r, length), lag=4).belief
        torch.testing.assert_close(out.mean[:length, r], alone.mean[:, 0], rtol=1e-12, atol=1e-12)


def test_padding_with_a_measurement_is_refused():
    """``present`` False at a step that holds a datum would drop it silently: refused, naming present."""
    bank, sensor = _models()
    kf = KalmanFilter(bank.select_mode(0), sensor)
    z, present = _data()
    traj = run_filter(kf, GaussianBelief(torch.zeros(len(LENGTHS), 2, dtype=torch.float64),
                                         torch.eye(2, dtype=torch.float64).expand(len(LENGTHS), 2, 2)), z)
    shorter = present.clone()
    shorter[10:, 0] = False  # run 0 has data up to step 299
    with pytest.raises(ValueError, match=r"present: run \(0,\) has a measurement at step 10, marked as padding"):
        smooth(traj, present=shorter)


@pytest.mark.parametrize("bad, message", [
    (lambda p: p[:, :2], r"present: expected shape \(300, 4\)"),
    (lambda p: p.double(), "present: expected a boolean tensor"),
    (lambda p: torch.cat([p[:3], ~p[3:4], p[4:]]), r"present: run \(\d+,\) has a present step \d+ after a padding step"),
])
def test_present_is_checked(bad, message):
    bank, sensor = _models()
    kf = KalmanFilter(bank.select_mode(0), sensor)
    z, present = _data()
    traj = run_filter(kf, GaussianBelief(torch.zeros(len(LENGTHS), 2, dtype=torch.float64),
                                         torch.eye(2, dtype=torch.float64).expand(len(LENGTHS), 2, 2)), z)
    with pytest.raises((ValueError, TypeError), match=message):
        smooth(traj, present=bad(present))


def test_present_without_a_recorded_log_likelihood():
    """A run recorded without log-likelihoods (``record=Keep("belief", "prior")``) takes ``present`` too: the
    batch shape is the beliefs' (it raised AttributeError reading ``trajectory.log_likelihood.shape``)."""
    from torchmm.run import Keep

    bank, sensor = _models()
    kf = KalmanFilter(bank.select_mode(0), sensor)
    z, present = _data()
    prior = GaussianBelief(torch.zeros(len(LENGTHS), 2, dtype=torch.float64),
                           torch.eye(2, dtype=torch.float64).expand(len(LENGTHS), 2, 2) * 100)
    lean = run_filter(kf, prior, z, record=Keep("belief", "prior"))
    assert lean.log_likelihood is None
    got = smooth(lean, present=present).belief
    want = smooth(run_filter(kf, prior, z), present=present).belief
    torch.testing.assert_close(got.mean, want.mean, rtol=0, atol=0)
    torch.testing.assert_close(got.cov, want.cov, rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"present: expected shape \(300, 4\)"):
        smooth(lean, present=present[:, :2])
