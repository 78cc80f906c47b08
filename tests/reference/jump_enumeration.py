"""The exact smoother of a jump-Markov linear system by enumeration, on torchmm's own Kalman filter and RTS
smoother (each checked against statsmodels and FilterPy elsewhere): the reference of the multiple-model
smoothers' accuracy (tests/smoothing/test_two_filter_info.py, benchmarks/smoother_accuracy.py). A NumPy
version independent of torchmm: tests/reference/jump_numpy.py."""

from __future__ import annotations

import torch

from torchmm import GaussianBelief, KalmanFilter, LinearMotion, run_filter, smooth


def exact_moments(motion, sensor, transition, mu0, belief0, z):
    """The exact posterior mean ``(T, runs, n)``, covariance ``(T, runs, n, n)`` and mode probabilities
    ``(T, runs, M)`` of a jump-Markov linear system (``motion`` a bank of ``M`` linear motions, one ``sensor``),
    enumerating every mode sequence (``M^T``): each sequence's Kalman (RTS) smoother, weighted by its prior
    (``mu0`` one step before the first datum, as the IMM's) and marginal likelihood. ``z`` ``(T, runs, m)``."""
    steps, runs = z.shape[:2]
    M, n = transition.shape[0], belief0.state_dim
    seqs = torch.cartesian_prod(*[torch.arange(M)] * steps)
    S = seqs.shape[0]
    log_prior = torch.logsumexp(mu0.log().unsqueeze(1) + transition.log()[:, seqs[:, 0]], 0)
    for k in range(1, steps):
        log_prior = log_prior + transition.log()[seqs[:, k - 1], seqs[:, k]]
    F, Q, off = motion.F.expand(M, n, n), motion.Q.expand(M, n, n), motion.offset.expand(M, n)
    motions = [LinearMotion(F[s].unsqueeze(1), Q[s].unsqueeze(1), off[s].unsqueeze(1)) for s in seqs.T]
    kf = KalmanFilter(motions[0], sensor)
    b0 = GaussianBelief(belief0.mean.expand(S, runs, n), belief0.cov.expand(S, runs, n, n))
    traj = run_filter(kf, b0, z.unsqueeze(1).expand(steps, S, runs, z.shape[-1]), motions=motions)
    post = (log_prior.unsqueeze(1) + traj.log_likelihood.sum(0)).softmax(0)  # (S, runs)
    sm = smooth(kf, traj, motions=motions).belief
    mean = (post.unsqueeze(-1) * sm.mean).sum(1)
    d = sm.mean - mean.unsqueeze(1)
    cov = (post[..., None, None] * (sm.cov + d.unsqueeze(-1) * d.unsqueeze(-2))).sum(1)
    probs = torch.stack([(post.unsqueeze(0) * (seqs.T.unsqueeze(-1) == j)).sum(1) for j in range(M)], -1)
    return mean, cov, probs
