r"""The IMM over linear Kalman modes with the batch axis last: ``torchmm.soa.filter(imm, belief0, z)``.

An opt-in kernel of issue 17's route (docs/performance.md, ``benchmarks/imm_layout.py``). Inside,
every matrix entry is its own ``(M, B)`` tensor ("structure of arrays"), and the Kalman algebra is
written as Python loops over the small state and measurement indices. Every operation is then one
contiguous elementwise pass over all runs and modes, where the batch-first engine spends its time in
``bmm`` of 2 x 2 matrices and in broadcast passes. The loops unroll when the step is traced, so
``compile=True`` (``torch.compile``) fuses a step into a few kernels.

What it computes is :class:`~torchmm.IMM` over :class:`~torchmm.KalmanFilter` mode filters, step for
step:

- mixing ``mu_{i|j} = pi_ij mu_i / c_j``;
- each mode's prediction ``F_j m + b_j``, ``F_j C F_j^T + Q_j``;
- the measurement update, one component after the other: exact for a diagonal ``R``, the only case
  accepted. A NaN component is skipped, so missing data are exact;
- the mode probabilities in log space.

It returns the :class:`~torchmm.run.Trajectory` of filtered beliefs (batch-first ``ModeBelief``) and
the log-likelihood, without priors or innovations. It equals :func:`~torchmm.run_filter` to rounding
(tested).

Supported: an ``IMM`` (moment mixing) whose bank is one :class:`~torchmm.KalmanFilter` with mode-bank
models (:class:`~torchmm.LinearMotion` without a control input, a linear measurement with a diagonal
``R``), a batch of one axis ``(B,)``, float32 or float64. Anything else raises a ``TypeError`` or
``ValueError`` that names the argument.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief, ModeBelief
from torchmm.filters.kalman import KalmanFilter
from torchmm.models.linear import LinearMotion
from torchmm.multimodel.bank import VectorizedBank
from torchmm.multimodel.imm import IMM, MomentMixing
from torchmm.run import Trajectory

__all__ = ["filter"]


def _entries(t: Tensor, M: int, event: int) -> list:
    """A mode-bank parameter ``(M or none, *event)`` as nested lists of ``(M, 1)`` (or ``(1, 1)``) tensors."""
    t = t if t.dim() > event else t.unsqueeze(0)  # (P, *event), P in {1, M}
    if event == 1:
        return [t[:, a].unsqueeze(-1) for a in range(t.shape[-1])]
    return [[t[:, a, c].unsqueeze(-1) for c in range(t.shape[-1])] for a in range(t.shape[-2])]


def _check(imm, belief0, z) -> tuple:
    if not isinstance(imm, IMM) or not isinstance(imm.interaction, MomentMixing):
        raise TypeError(f"imm: torchmm.soa.filter runs an IMM (moment mixing), got {type(imm).__name__}")
    bank = imm.bank
    if not isinstance(bank, VectorizedBank) or type(bank.filter) is not KalmanFilter:
        raise TypeError("imm: torchmm.soa.filter needs a bank of one KalmanFilter with mode-bank models "
                        f"(got {type(bank).__name__})")
    kf = bank.filter
    if not isinstance(kf.motion, LinearMotion) or kf.motion.input_matrix is not None:
        raise ValueError("imm: torchmm.soa.filter needs LinearMotion mode models without a control input")
    if kf.joseph:
        raise ValueError("imm: torchmm.soa.filter has no Joseph-form update; use run_filter")
    R = kf.measurement.R
    if bool((R - torch.diag_embed(R.diagonal(dim1=-2, dim2=-1))).abs().amax() > 0):  # once, at the entry point
        raise ValueError("imm: torchmm.soa.filter updates one measurement component at a time, which needs a "
                         "diagonal R; use run_filter")
    if type(belief0) is not ModeBelief or not isinstance(belief0.components, GaussianBelief):
        raise TypeError(f"belief0: expected the ModeBelief of imm.initial_belief, got {type(belief0).__name__}")
    if belief0.mode_log_probs.dim() != 2:
        raise ValueError(f"belief0: torchmm.soa.filter takes one batch axis (B,), got batch "
                         f"{tuple(belief0.mode_log_probs.shape[:-1])}")
    B, n, m = belief0.mode_log_probs.shape[0], kf.state_dim, kf.meas_dim
    if not isinstance(z, Tensor) or z.dim() != 3 or tuple(z.shape[1:]) != (B, m):
        raise ValueError(f"z: expected shape (T, {B}, {m}), got {tuple(getattr(z, 'shape', ()))}")
    if z.dtype != belief0.mode_log_probs.dtype:
        raise TypeError(f"z: dtype {z.dtype} differs from belief0's {belief0.mode_log_probs.dtype}")
    return kf, B, n, m


def _sum(terms) -> Tensor:
    """The sum of tensors, without the ``0 +`` of the builtin ``sum``."""
    terms = list(terms)
    out = terms[0]
    for t in terms[1:]:
        out = out + t
    return out


def _step_function(kf: KalmanFilter, matrix: Tensor, M: int, n: int, m: int, estimate_only: bool):
    F, Q = _entries(kf.motion.F, M, 2), _entries(kf.motion.Q, M, 2)
    b = _entries(kf.motion.offset, M, 1)
    H = _entries(kf.measurement.H, M, 2)
    r = _entries(kf.measurement.R.diagonal(dim1=-2, dim2=-1), M, 1)
    PiT = matrix.mT.contiguous()
    tiny = torch.finfo(matrix.dtype).tiny
    half_log2pi = 0.5 * math.log(2 * math.pi)

    def step(xs: Tensor, Ps: Tensor, log_mu: Tensor, zk: Tensor):
        """One IMM step: ``xs (n, M, B)``, ``Ps (n, n, M, B)``, ``log_mu (M, B)``, ``zk (m, B)`` -> the
        same, and the step's log-likelihood ``(B,)``. Stacked in and out, so that a compiled step
        also writes the record."""
        x = list(xs.unbind(0))
        P = [list(row.unbind(0)) for row in Ps.unbind(0)]
        mu = log_mu.exp()
        cbar = PiT @ mu  # (j, B)
        w = matrix[:, :, None] * mu[:, None, :] / cbar.clamp_min(tiny)[None]  # (i, j, B)
        mean = [(w * x[a][:, None]).sum(0) for a in range(n)]
        diff = [x[a][:, None] - mean[a][None] for a in range(n)]
        C = [[None] * n for _ in range(n)]
        for a in range(n):
            for c in range(a, n):
                C[a][c] = C[c][a] = (w * (P[a][c][:, None] + diff[a] * diff[c])).sum(0)
        xp = [_sum(F[a][e] * mean[e] for e in range(n)) + b[a] for a in range(n)]
        A = [[_sum(F[a][e] * C[e][c] for e in range(n)) for c in range(n)] for a in range(n)]
        Pp = [[None] * n for _ in range(n)]
        for a in range(n):
            for c in range(a, n):
                Pp[a][c] = Pp[c][a] = _sum(A[a][e] * F[c][e] for e in range(n)) + Q[a][c]
        ll = torch.zeros_like(cbar)
        for k in range(m):  # one measurement component at a time (diagonal R)
            g = [_sum(Pp[a][c] * H[k][c] for c in range(n)) for a in range(n)]  # P- h^T
            s = _sum(H[k][a] * g[a] for a in range(n)) + r[k]
            observed = torch.isfinite(zk[k])  # (B,)
            nu = torch.where(observed, zk[k], 0.0) - _sum(H[k][a] * xp[a] for a in range(n))
            gain = [torch.where(observed, g[a] / s, 0.0) for a in range(n)]
            xp = [xp[a] + gain[a] * nu for a in range(n)]
            new = [[None] * n for _ in range(n)]
            for a in range(n):
                for c in range(a, n):
                    new[a][c] = new[c][a] = Pp[a][c] - gain[a] * g[c]
            Pp = new
            ll = ll + torch.where(observed, -0.5 * nu * nu / s - 0.5 * s.log() - half_log2pi, 0.0)
        joint = ll + cbar.clamp_min(tiny).log()
        total = torch.logsumexp(joint, 0)  # (B,)
        log_mu = joint - total
        total = torch.where(torch.isfinite(zk).any(0), total, 0.0)  # exactly 0 without a datum
        xs, Ps = torch.stack(xp), torch.stack([torch.stack(row) for row in Pp])
        if not estimate_only:
            return xs, Ps, log_mu, total, xs, Ps
        mu = log_mu.exp()  # the collapsed estimate, (n, B) and (n, n, B)
        est = (mu * xs).sum(-2)
        spread = xs - est.unsqueeze(-2)  # (n, M, B)
        est_cov = (mu * (Ps + spread.unsqueeze(1) * spread.unsqueeze(0))).sum(-2)
        return xs, Ps, log_mu, total, est, est_cov

    return step


def filter(imm: IMM, belief0: ModeBelief, z: Tensor, *, compile: bool = False,  # noqa: A001
           output: str = "beliefs") -> Trajectory:
    """Filter ``z`` with ``imm`` in the batch-last layout (module docstring).

    Args:
        imm: an :class:`~torchmm.IMM` over one :class:`~torchmm.KalmanFilter` with mode-bank models.
        belief0: ``imm.initial_belief(prior)``, batch ``(B,)``.
        z: ``(T, B, m)``, NaN for a missing component.
        compile: run the step under ``torch.compile`` (seconds to compile, then fused kernels).
        output: ``"beliefs"`` (default): the filtered ``ModeBelief`` of every step; ``"estimate"``:
            only the collapsed estimate, computed inside the step (``M`` times less to record).

    Returns:
        a :class:`~torchmm.run.Trajectory` whose ``belief`` is the filtered ``ModeBelief``, batch
        ``(T, B)`` (``output="estimate"``: the ``GaussianBelief`` estimate, ``(T, B, n)``), and whose
        ``log_likelihood`` is ``(T, B)``; no priors, innovations or extras.

    Shapes:
        belief0: batch ``(B,)``, components ``(B, M)``; z ``(T, B, m)`` -> belief batch ``(T, B)``

    Examples:
        >>> from torchmm import IMM, GaussianBelief, KalmanFilter, soa
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> bank = ConstantVelocity(1, q=1.0, acceleration=[[0.25], [0.0], [-0.25]])
        >>> imm = IMM(KalmanFilter(bank, PositionMeasurement(2, [0], 100.0)), torch.full((3, 3), 1 / 3))
        >>> belief0 = imm.initial_belief(GaussianBelief(torch.zeros(5, 2), 100 * torch.eye(2)))
        >>> out = soa.filter(imm, belief0, torch.randn(20, 5, 1))
        >>> out.belief.mode_probs.shape, out.estimate().mean.shape
        (torch.Size([20, 5, 3]), torch.Size([20, 5, 2]))
    """
    kf, B, n, m = _check(imm, belief0, z)
    if output not in ("beliefs", "estimate"):
        raise ValueError(f"output: expected 'beliefs' or 'estimate', got {output!r}")
    M = imm.num_modes
    comps = belief0.components.materialize()
    matrix = imm.transition.matrix().to(comps.mean)
    step = _step_function(kf, matrix, M, n, m, output == "estimate")
    if compile:
        step = torch.compile(step, dynamic=False)
    x = comps.mean.permute(2, 1, 0).contiguous()  # (n, M, B)
    P = comps.cov.permute(2, 3, 1, 0).contiguous()  # (n, n, M, B)
    log_mu = belief0.mode_log_probs.mT.contiguous()
    zt = z.permute(0, 2, 1)  # (T, m, B)
    means, covs, logs, lls = [], [], [], []
    for k in range(z.shape[0]):  # the time loop
        x, P, log_mu, total, keep_mean, keep_cov = step(x, P, log_mu, zt[k])
        means.append(keep_mean)
        covs.append(keep_cov)
        logs.append(log_mu)
        lls.append(total)
    if output == "estimate":
        belief = GaussianBelief(torch.stack(means).permute(0, 2, 1), torch.stack(covs).permute(0, 3, 1, 2))
    else:
        mean = torch.stack(means).permute(0, 3, 2, 1)  # (T, B, M, n)
        cov = torch.stack(covs).permute(0, 4, 3, 1, 2)  # (T, B, M, n, n)
        belief = ModeBelief(torch.stack(logs).mT, GaussianBelief(mean, cov))
    return Trajectory(belief=belief, prior=None, log_likelihood=torch.stack(lls), innovation=None,
                      innovation_cov=None, extras={})
