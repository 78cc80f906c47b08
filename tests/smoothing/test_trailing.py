"""Steps after a run's last measurement carry nothing about its earlier steps: ``smooth`` ends each run at
its last step with a finite datum (docs/smoothing.md, "Runs of different lengths"), so trailing all-NaN steps
leave every smoother's numbers at the data steps as they are without them. Kim's smoother used to run back
through them: 18 steps of data and 32 missing ones moved IMM-Kim's estimate by 7.3 from the exact
smoother's (0.19 without them)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchmm import (GPB1, GPB2, IMM, GaussianBelief, KalmanFilter, LinearMotion, ParticleFilter, run_filter,
                     smooth)
from torchmm.learn import Objective
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.run import Trajectory
from torchmm.runtime import no_host_sync

from tests.smoothing.test_padding import _fields  # (a belief's compared fields)

D = torch.float64
PI = np.array([[0.9, 0.1], [0.15, 0.85]])
ACC = (0.0, 1.5)
Q, R = 0.5, 4.0
P0 = np.diag([20.0, 5.0])
#: data steps of each run, then missing steps up to T (run 3: none at all; run 1: an interior gap too)
LENGTHS = (12, 9, 5, 0)
T = 20


def _models():
    bank = ConstantVelocity(1, q=Q, acceleration=[[a] for a in ACC], dtype=D)
    return bank, PositionMeasurement(2, [0], R, dtype=D)


def _data(lengths=LENGTHS, steps=T, seed=5):
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(steps, dtype=D).view(steps, 1, 1)
    z = 0.4 * t.square() * (t > 4) + 2.0 * torch.randn(steps, len(lengths), 1, generator=g, dtype=D)
    for r, length in enumerate(lengths):
        z[length:, r] = torch.nan
    if len(lengths) > 1:
        z[3, 1] = z[5, 1] = torch.nan  # missing data inside a run change nothing here
    return z


def _filters():
    bank, sensor = _models()
    pi = torch.tensor(PI, dtype=D)
    cv = bank.select_mode(0)
    return {
        "kalman": (KalmanFilter(cv, sensor), {}),
        "particle": (ParticleFilter(LinearMotion(cv.F, torch.diag(torch.tensor([0.05, 0.1], dtype=D))),
                                    sensor, num_particles=40), {}),
        **{f"{c.__name__}-{m}": (c(KalmanFilter(bank, sensor), pi), {"method": m})
           for c in (IMM, GPB1, GPB2) for m in ("two_filter", "kim")},
    }


def _run(filt, z):
    runs = z.shape[1]
    prior = GaussianBelief(torch.zeros(runs, 2, dtype=D), torch.tensor(P0, dtype=D).expand(runs, 2, 2))
    generator = torch.Generator().manual_seed(0) if filt.uses_generator else None
    start = filt.initial_belief(prior, generator=generator) if generator is not None \
        else filt.initial_belief(prior)
    return run_filter(filt, start, z, generator=generator)


def _alone(traj: Trajectory, r: int, length: int) -> Trajectory:
    """Run ``r``'s first ``length`` steps of ``traj`` as a trajectory of one run (built by hand: smoothed as
    given, with the data passed)."""
    def cut(b):
        return None if b is None else b[:length, r:r + 1]
    return Trajectory(belief=cut(traj.belief), prior=cut(traj.prior),
                      log_likelihood=traj.log_likelihood[:length, r:r + 1], innovation=None,
                      innovation_cov=None, extras={})


@pytest.mark.parametrize("name", list(_filters()))
def test_trailing_missing_steps_change_nothing_before_them(name):
    """Each run with its trailing missing steps smoothed as its filtered beliefs cut at its last datum (RTS,
    FFBSm; IMM, GPB1, GPB2 with Kim's and the two-filter smoother); the trailing steps keep the filtered
    beliefs (no data after them: the filter's belief is the smoothed one). Run 3 has no datum at all: the
    filter's beliefs."""
    filt, options = _filters()[name]
    z = _data()
    traj = _run(filt, z)
    out = smooth(traj, **options).belief
    for r, length in enumerate(LENGTHS):
        if length:
            alone = smooth(filt, _alone(traj, r, length), z[:length, r:r + 1], **options).belief
            # the two-filter smoother's flat start costs ~1e-8 of rounding between batch sizes
            tol = 1e-6 if options.get("method") == "two_filter" else 1e-10
            for got, want in zip(_fields(out), _fields(alone)):
                torch.testing.assert_close(got[:length, r], want[:, 0], rtol=tol, atol=tol)
        for got, kept in zip(_fields(out), _fields(traj.belief)):  # (FFBSm's weights: normalised again)
            torch.testing.assert_close(got[length:, r], kept[length:, r], rtol=1e-12, atol=1e-12)


def _exact(z):
    """E[x_k | z_{1:L}] (L, n) of one series by enumerating every mode sequence (float64 NumPy): a Kalman
    filter and RTS smoother per sequence, weighted by its posterior probability. torchmm's convention: the
    prior ``N(0, P0)`` and uniform mode probabilities one step before the first, which is a prediction."""
    L = len(z)
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Qm = Q * np.array([[0.25, 0.5], [0.5, 1.0]])
    b = np.array([[0.5 * a, a] for a in ACC])
    H = np.array([[1.0, 0.0]])
    seqs = (np.arange(2 ** L)[:, None] >> np.arange(L)[::-1]) & 1  # (S, L)
    S = len(seqs)
    lw = np.log((np.full(2, 0.5) @ PI)[seqs[:, 0]]) + np.log(PI[seqs[:, :-1], seqs[:, 1:]]).sum(1)
    m, P = np.zeros((S, 2)), np.repeat(P0[None], S, 0)
    xf, Pf, xp, Pp = [], [], [], []
    for k in range(L):
        m = m @ F.T + b[seqs[:, k]]
        P = F @ P @ F.T + Qm
        xp.append(m)
        Pp.append(P)
        if np.isfinite(z[k]).all():
            s = (H @ P @ H.T)[:, 0, 0] + R
            nu = z[k, 0] - m[:, 0]
            lw = lw - 0.5 * (nu ** 2 / s + np.log(2 * np.pi * s))
            K = (P @ H.T)[:, :, 0] / s[:, None]
            m = m + K * nu[:, None]
            P = P - s[:, None, None] * K[:, :, None] * K[:, None, :]
        xf.append(m)
        Pf.append(P)
    xs, out = xf[-1], [xf[-1]]
    for k in range(L - 2, -1, -1):
        G = Pf[k] @ F.T @ np.linalg.inv(Pp[k + 1])
        xs = xf[k] + np.einsum("sij,sj->si", G, xs - xp[k + 1])
        out.append(xs)
    w = np.exp(lw - np.logaddexp.reduce(lw))
    return np.einsum("s,skn->kn", w, np.stack(out[::-1], 1))


@pytest.mark.parametrize("combinator", [IMM, GPB2])
@pytest.mark.parametrize("method", ["kim", "two_filter"])
def test_against_the_exact_smoother_with_trailing_missing_steps(combinator, method):
    """10 steps of data and 30 missing ones, against all 2^10 mode sequences of the data steps (the exact
    smoother's means there do not depend on the missing steps after them). The smoother's error is the one it
    has without the missing steps, and well below the filter's (Kim's smoother run back through the missing
    steps was 10 times the filter's error here)."""
    L, K = 10, 30
    z = _data((L,), L + K, seed=2)
    exact = torch.as_tensor(_exact(z[:L, 0].numpy()))
    bank, sensor = _models()
    mm = combinator(KalmanFilter(bank, sensor), torch.tensor(PI, dtype=D))

    def error(z):
        traj = _run(mm, z)
        smoothed = smooth(traj, method=method).estimate().mean[:L, 0]
        filtered = traj.estimate().mean[:L, 0]
        return float((smoothed - exact).norm(dim=-1).max()), float((filtered - exact).norm(dim=-1).max())

    with_tail, filtered = error(z)
    without, _ = error(z[:L])
    assert math.isclose(with_tail, without, rel_tol=1e-6, abs_tol=1e-9), (with_tail, without)
    assert with_tail < 0.5 * filtered, (with_tail, filtered)


def test_kim_reads_nothing_on_the_host_for_the_trailing_steps():
    """The trailing steps' mask is one batched computation on the device: under no_host_sync (the device form)
    Kim's smoother gives the numbers of the CPU form, which reads whether any run ends early."""
    filt, options = _filters()["IMM-kim"]
    traj = _run(filt, _data())
    want = smooth(traj, **options).belief
    with no_host_sync("Kim's smoother of runs with trailing missing steps"):
        got = smooth(traj, **options).belief
    for a, b in zip(_fields(got), _fields(want)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_a_trajectory_without_its_data_is_smoothed_as_given_and_with_them_ends_each_run():
    """A trajectory built by hand carries no measurements: smoothed as given (through the missing steps)
    unless they are passed, when each run ends at its last datum again."""
    import dataclasses

    filt, options = _filters()["IMM-kim"]
    z = _data()
    traj = _run(filt, z)
    bare = dataclasses.replace(traj, provenance=None)
    ends = smooth(traj, **options).estimate().mean
    torch.testing.assert_close(smooth(filt, bare, z, **options).estimate().mean, ends, rtol=0, atol=0)
    through = smooth(filt, bare, **options).estimate().mean
    assert float((through[:LENGTHS[0], 0] - ends[:LENGTHS[0], 0]).abs().max()) > 1e-3


def test_objective_smoothed_ends_each_run_too():
    """Objective.smoothed() (the prepared filter-and-Kim loops) ends each run at its last datum too: it
    equals run_filter + smooth."""
    filt, options = _filters()["IMM-kim"]
    z = _data()
    runs = z.shape[1]
    prior = GaussianBelief(torch.zeros(runs, 2, dtype=D), torch.tensor(P0, dtype=D).expand(runs, 2, 2))
    start = filt.initial_belief(prior)
    objective = Objective(filt, start, z)
    got = objective.smoothed()
    assert objective.why == ""  # (the prepared loops' plan: its Kim ends each run at its last datum)
    with torch.no_grad():
        want = smooth(run_filter(filt, start, z), **options).belief
    for a, b in zip(_fields(got), _fields(want)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("name", ["IMM-kim", "GPB1-kim", "kalman"])
def test_the_compiled_loop_ends_each_run_as_the_eager_steps(monkeypatch, name):
    """The linear kernel's Kim (and RTS) loop takes each run's last step: equal to the eager smoother's
    (kernel switched off), and it ran."""
    import torchmm.kernels.linear as linear
    from torchmm import kernels

    calls = []
    kim = linear._kim
    monkeypatch.setattr(linear, "_kim", lambda *a, **k: calls.append(1) or kim(*a, **k))
    filt, options = _filters()[name]
    traj = _run(filt, _data())
    got = smooth(traj, **options).belief
    assert calls, "the compiled loop did not run"
    with kernels.switched_off("linear_gaussian"):
        want = smooth(traj, **options).belief
    for a, b in zip(_fields(got), _fields(want)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
