r"""The two-filter smoother of a multiple-model run over linear Kalman modes in the batch-last layout
(issue 31, goal 3).

:func:`~torchmm.smooth` runs the two-filter IMM smoother (docs/smoothing.md; ``torchmm/smooth.py``:
``backward_predict``, ``two_filter_step``, ``backward_imm_update``) through this kernel where the
filter describes itself as linear-Gaussian (an IMM, GPB1 or GPB2 over one
:class:`~torchmm.KalmanFilter` with mode-bank linear models, a diagonal ``R``), the state has at most
six components, and the run has no controls, per-step models or sensors. It computes what the eager
smoother computes, in the same order, with every quantity one tensor per entry and the batch axes
last: ``(M, *B)`` per mode, ``(j, i, *B)`` per pair of modes (mode ``j`` at ``k``, ``i`` at ``k + 1``):

- the backward filter's start: the last collapsed estimate, its covariance times
  :func:`~torchmm.smooth.diffuse_factor`, for every mode, updated with the last datum;
- the backward prediction ``x_k = F_i^{-1} (m - b_i)``, ``P_k = F_i^{-1} (P + Q_i) F_i^{-T}`` (the
  eager form linearises at the filtered estimate, ``at + F^{-1}(m - F at - b)``: equal for linear
  models, to rounding); ``F_i^{-1}`` is inverted once per mode;
- the fusion of every pair: ``D = P_j + B_i`` and its regularised factor in closed form
  (:func:`torchmm.linalg.cholesky`'s for ``n <= 2``; beyond,
  :func:`~torchmm.kernels.batch_last.algebra.factor`),
  ``V = L^{-1} P_j``, ``w = L^{-1} (b_i - x_j)``,
  ``x_ji = x_j + V^T w``, the overlap ``N(b_i - x_j; 0, D)``, the pair weights and their
  normalisations (as ``safe_log_normalize``), and mode ``j``'s collapse
  ``P_j - sum_i w_ji V_ji^T V_ji + spread``;
- the backward IMM's mixing with the backward transition and its update, one measurement component
  after the other (:meth:`~torchmm.kernels.batch_last.bank.LinearBank.update`).

The smoothed beliefs are returned batch-first (views of batch-last memory), equal to the eager
smoother's to rounding (tests/smoothing/test_two_filter_kernel.py).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief, ModeBelief
from torchmm.beliefs.ops import live_log
from torchmm.kernels.batch_last.algebra import (
    ONE,
    ZERO,
    coefficients,
    collapse_entries,
    combine,
    factor,
    log_normalized,
    mix_entries,
    sandwich,
    solve_lower,
    stack_upper,
    sum_terms,
)
from torchmm.kernels.batch_last.bank import LinearBank
from torchmm.kernels.batch_last.frame import measurement_data
from torchmm.kernels.batch_last.imm import LARGE_BATCH, LARGE_STATE, MAX_STATE
from torchmm.kernels.batch_last.plan import why_not

__all__ = ["LARGE_SMOOTHER", "BatchLastTwoFilter", "LargeStateSmoother", "plan_two_filter", "why_not_smooth"]

_LOG_2PI = math.log(2 * math.pi)


def why_not_smooth(model, trajectory, measurements, prior_log, max_state: int = MAX_STATE) -> str | None:
    """Why the two-filter smoother of ``trajectory`` (a run of the linear-Gaussian description ``model``)
    cannot run on this kernel (states of at most ``max_state`` components), or None. Shapes and types
    only, and :func:`why_not`'s one look at ``R``."""
    if model.rule not in ("mix", "collapse", "pairs"):
        return f"the {model.rule!r} rule"
    if model.post_update is not None:
        return "a post-update (a model-set policy)"
    belief = trajectory.belief
    if type(belief) is not ModeBelief or type(belief.components) is not GaussianBelief:
        return "the trajectory's beliefs are not a ModeBelief of Gaussians"
    if not isinstance(measurements, Tensor) or not isinstance(prior_log, Tensor):
        return "no measurements (or prior mode probabilities) given"
    n, M = model.F.shape[-1], model.transition.shape[-1]
    if n > max_state:
        return f"a state of {n} components (more than {max_state}: the factor entry by entry costs n^3 operations)"
    steps = belief.mode_log_probs.shape[0]
    start = ModeBelief(belief.mode_log_probs[0], GaussianBelief(belief.components.mean[0], belief.components.cov[0]))
    reason = why_not(model, M, start, measurements)
    if reason is not None:
        return reason
    if measurements.shape[0] != steps:
        return "the measurements' steps differ from the trajectory's"
    return None


class BatchLastTwoFilter:
    """The two-filter smoother's passes in the batch-last layout (module docstring).

    Args:
        model: the filter's linear-Gaussian description (:func:`why_not_smooth` None).
        M: the number of modes; batch_dims: ``len(B)``; like: a tensor of the run's dtype and device.
    """

    def __init__(self, model, M: int, batch_dims: int, like: Tensor):
        self.bank = bank = LinearBank(model, M, batch_dims, like)
        self.M, self.n, self.d = M, bank.n, batch_dims
        d = batch_dims
        self.Finv = coefficients(torch.linalg.inv(model.F), M, 2, d)
        log_pi = live_log(model.transition, 0.0)  # [j, i] (a zero entry: no NaN gradient)
        self.log_pi = log_pi.reshape(M, M, *([1] * d))  # (j, i, 1...)
        self.log_pi_t = log_pi.mT.reshape(M, M, *([1] * d))  # (i, j, 1...)
        self.diffuse = torch.finfo(like.dtype).eps ** -0.5  # torchmm.smooth.diffuse_factor

    # -- layout ---------------------------------------------------------------------------------
    def entries(self, mean: Tensor, cov: Tensor) -> tuple[list, list]:
        """Batch-first ``(*B, M, n)``, ``(*B, M, n, n)`` -> ``x[a]``, ``C[a][c]`` (``a <= c``), each ``(M, *B)``."""
        d, n = self.d, self.n
        X = mean.movedim((d, d + 1), (1, 0))
        P = cov.movedim((d, d + 1, d + 2), (2, 0, 1))
        return list(X.unbind(0)), [[P[a, c] if c >= a else None for c in range(n)] for a in range(n)]

    def modes_last(self, t: Tensor) -> Tensor:
        """``(*B, M)`` (or ``(M,)``) -> ``(M, *B)`` (or ``(M, 1...)``)."""
        if t.dim() == 1:
            return t.reshape(-1, *([1] * self.d))
        return t.movedim(-1, 0)

    # -- the passes ---------------------------------------------------------------------------------
    def start(self, log_mu: Tensor, X: list, C: list, data) -> tuple:
        """The backward filter at the last step: the collapsed estimate with a diffuse covariance, for
        every mode, updated with the last datum; mode log-probabilities from ``prior`` (``data[-1]``)."""
        n = self.n
        mu = log_mu.exp()
        est, est_cov = collapse_entries(X, C, mu, n)  # (n, *B), (n, n, *B)
        like = log_mu
        xs = [est[a].unsqueeze(0).expand_as(like) for a in range(n)]
        Cs = [[(self.diffuse * est_cov[a, c]).unsqueeze(0).expand_as(like) if c >= a else None for c in range(n)]
              for a in range(n)]
        zc, ob, nhob, _, _ = data[0]
        xu, Cu, ll, _, _ = self.bank.update(xs, Cs, zc, ob, nhob, like, False)
        return self.posterior(ll, data[1]), xu, Cu

    def posterior(self, ll: Tensor, prior: Tensor) -> Tensor:
        """``mode_posterior``'s mode log-probabilities ``(M, *B)`` from log-likelihoods and a prior."""
        joint = ll + prior
        total = torch.logsumexp(joint, 0)
        return log_normalized(joint, total.unsqueeze(0), self.M)

    def predict(self, x: list, C: list) -> tuple[list, list]:
        """The backward prediction of every mode: ``F^{-1} (m - b)``, ``F^{-1} (P + Q) F^{-T}``."""
        n = self.n
        Finv, Q, b = self.Finv, self.bank.Q, self.bank.b
        like = x[0]
        diff = [_minus(x[a], b[a]) for a in range(n)]  # m - b
        mean = [combine([(Finv[a][e], diff[e]) for e in range(n)], ZERO, like) for a in range(n)]
        S = [[combine([(ONE, C[a][c])], Q[a][c], like) if c >= a else None for c in range(n)]
             for a in range(n)]  # P + Q (upper triangle)
        return mean, sandwich(Finv, S, [[ZERO] * n for _ in range(n)], like)

    def fuse(self, log_mu: Tensor, x: list, P: list, log_mu_b: Tensor, b: list, B: list,
             prior_next: Tensor) -> tuple[Tensor, list, list]:
        """``two_filter_step``: the smoothed mode log-probabilities ``(M, *B)``, means and covariance
        entries of step ``k`` from the filtered ``(log_mu, x, P)`` and the backward-predicted
        ``(log_mu_b, b, B)``."""
        n, M = self.n, self.M
        sym = lambda T, a, c: T[min(a, c)][max(a, c)]  # noqa: E731
        Pj = [[None if t is None else t.unsqueeze(1) for t in row] for row in P]  # (j, 1, *B)
        D = [[None if P[a][c] is None else Pj[a][c] + B[a][c].unsqueeze(0) for c in range(n)]
             for a in range(n)]  # (j, i, *B)
        delta = [b[a].unsqueeze(0) - x[a].unsqueeze(1) for a in range(n)]
        # torchmm.linalg.cholesky's regularised factor; V = L^{-1} P_j, w = L^{-1} delta (solve_lower)
        L = factor(D)
        diag = [L[a][a] for a in range(n)]
        V = solve_lower(L, [[sym(Pj, e, c) for c in range(n)] for e in range(n)])
        w = [row[0] for row in solve_lower(L, [[delta[e]] for e in range(n)])]
        # x_ji = x_j + V^T w; log N(b_i - x_j; 0, D)
        mean = [x[a].unsqueeze(1) + sum_terms([V[e][a] * w[e] for e in range(n)]) for a in range(n)]
        squares = sum_terms([w[e] * w[e] for e in range(n)])
        half_log_det = sum_terms([d.log() for d in diag])
        log_overlap = -0.5 * (squares + n * _LOG_2PI) - half_log_det
        evidence = log_mu_b - prior_next  # (i, *B)
        log_pair = log_mu.unsqueeze(1) + self.log_pi + log_overlap + evidence.unsqueeze(0)  # (j, i, *B)
        norm = torch.logsumexp(log_pair.flatten(0, 1), 0)
        log_pair = log_normalized(log_pair, norm, M * M)
        log_mode = torch.logsumexp(log_pair, 1)  # (j, *B)
        weights = log_normalized(log_pair, log_mode.unsqueeze(1), M).exp()  # P(s_{k+1} = i | s_k = j)
        merged = [(weights * mean[a]).sum(1) for a in range(n)]
        diff = [mean[a] - merged[a].unsqueeze(1) for a in range(n)]
        wdiff = [weights * diff[a] for a in range(n)]
        cov = [[None] * n for _ in range(n)]
        for a in range(n):
            for c in range(a, n):
                vv = sum_terms([V[e][a] * V[e][c] for e in range(n)])  # (V^T V)_ac
                cov[a][c] = P[a][c] - (weights * vv).sum(1) + (wdiff[a] * diff[c]).sum(1)
        return log_mode, merged, cov

    def backward_update(self, log_mu_b: Tensor, b: list, B: list, prior: Tensor, data) -> tuple:
        """``backward_imm_update``: the backward transition's mixing and every mode's update with ``z_k``."""
        M = self.M
        log_back = self.log_pi_t + prior.unsqueeze(0)  # (i, j, *B): log pi_ji p_k(j)
        log_back = log_back - torch.logsumexp(log_back, 1, keepdim=True)
        log_joint = log_mu_b.unsqueeze(1) + log_back  # (i, j, *B)
        log_a = torch.logsumexp(log_joint, 0)  # (j, *B)
        w = log_normalized(log_joint, log_a.unsqueeze(0), M).exp()
        xs, Cm = mix_entries(b, B, w, self.n)  # the mixed beliefs (j, *B)
        zc, ob, nhob, _, _ = data
        xu, Cu, ll, _, _ = self.bank.update(xs, Cm, zc, ob, nhob, log_a, False)
        return self.posterior(ll, log_a), xu, Cu

    @staticmethod
    def keep(mask: Tensor, a: tuple, b: tuple) -> tuple:
        """``a`` where ``mask (*B)`` is True, else ``b``: mode log-probabilities ``(M, *B)``, mean and
        covariance entries (each ``(M, *B)``; None below the diagonal)."""
        m = mask.unsqueeze(0)
        pick = lambda x, y: None if x is None else torch.where(m, x, y)  # noqa: E731
        return (pick(a[0], b[0]), [pick(x, y) for x, y in zip(a[1], b[1])],
                [[pick(x, y) for x, y in zip(ra, rb)] for ra, rb in zip(a[2], b[2])])

    def run(self, trajectory, measurements: Tensor, prior_log: Tensor, padding: Tensor | None = None,
            ends: Any = ()) -> ModeBelief:
        """The smoothed beliefs, batch ``(T, *B)`` (components ``(T, *B, M)``). ``padding (T, *B)`` bool: True
        at the steps after a run's last one (they keep the filtered beliefs, and the run's backward filter
        starts at its last step, as :func:`~torchmm.smooth`'s); ``ends``: the steps at which some run ends."""
        d = self.d
        filtered = trajectory.belief
        steps = filtered.mode_log_probs.shape[0]
        data = measurement_data(measurements)
        log_mus = [self.modes_last(filtered.mode_log_probs[k]) for k in range(steps)]
        entries = [self.entries(filtered.components.mean[k], filtered.components.cov[k]) for k in range(steps)]
        priors = [self.modes_last(prior_log[k]) for k in range(steps)]
        last = steps - 1
        out_mode, out_x, out_C = [None] * steps, [None] * steps, [None] * steps
        out_mode[last], (out_x[last], out_C[last]) = log_mus[last], entries[last]
        if steps > 1:
            log_mu_b, b, B = self.start(log_mus[last], *entries[last], (data[last], priors[last]))
        for k in range(steps - 2, -1, -1):
            pb, PB = self.predict(b, B)
            fused = self.fuse(log_mus[k], *entries[k], log_mu_b, pb, PB, priors[k + 1])
            if padding is not None:  # a run whose step k+1 is padding ends at k: its filtered belief
                fused = self.keep(padding[k + 1], (log_mus[k], *entries[k]), fused)
            out_mode[k], out_x[k], out_C[k] = fused
            if k > 0:
                log_mu_b, b, B = self.backward_update(log_mu_b, pb, PB, priors[k], data[k])
                if k in ends:  # the runs whose last step is k start their backward filter here
                    restart = self.start(log_mus[k], *entries[k], (data[k], priors[k]))
                    log_mu_b, b, B = self.keep(padding[k + 1], restart, (log_mu_b, b, B))
        mode = torch.stack(out_mode)  # (T, M, *B)
        X = torch.stack([torch.stack(x) for x in out_x])  # (T, n, M, *B)
        C = torch.stack([stack_upper(c) for c in out_C])  # (T, n, n, M, *B)
        return ModeBelief(mode.movedim(1, -1),
                          GaussianBelief(X.permute(0, *range(3, d + 3), 2, 1),
                                         C.permute(0, *range(4, d + 4), 3, 1, 2)))


def _minus(t: Tensor, coef) -> Tensor:
    """``t - coef`` for a :func:`~torchmm.kernels.batch_last.algebra.coefficients` entry (zero: ``t`` itself)."""
    if coef.kind == "zero":
        return t
    return t - (1.0 if coef.kind == "one" else coef.value)


class LargeStateSmoother:
    """The registered kernel of the two-filter smoother for states of ``MAX_STATE + 1`` to ``LARGE_STATE``
    components (:class:`BatchLastTwoFilter`, as :meth:`~torchmm.kernels.batch_last.imm.BatchLastKernel.plan_smooth`
    runs it up to ``MAX_STATE``), from ``LARGE_BATCH`` runs x modes: below, its entry-by-entry factors
    (``n^3`` passes) are bound by dispatch and the eager passes are faster (docs/performance.md). Its
    choice depends on the batch size (``by_size``: studies switch it off). It smooths only."""

    name = "batch_last_smooth_large"
    by_size = True

    def plan(self, filter, belief0, measurements, request):
        return "a smoother's kernel only"

    smooths_padding = True  # plan_smooth takes padding= and ends= (runs that end early)

    def plan_smooth(self, filter, trajectory, method, measurements=None, prior_log=None, **inputs):
        return plan_two_filter(filter, trajectory, method, measurements, prior_log, large=True,
                               padding=inputs.get("padding"), ends=inputs.get("ends", ()))


def plan_two_filter(filter, trajectory, method, measurements=None, prior_log=None, *, large: bool = False,
                    padding: Tensor | None = None, ends: Any = ()):
    """The plan of the two-filter smoother's passes batch-last (:class:`BatchLastTwoFilter`): states of at
    most ``MAX_STATE`` components (:meth:`~torchmm.kernels.batch_last.imm.BatchLastKernel.plan_smooth`), or with
    ``large``, of ``MAX_STATE + 1`` to ``LARGE_STATE`` from ``LARGE_BATCH`` runs x modes
    (:class:`LargeStateSmoother`): ``run() -> ModeBelief`` (batch ``(T, *B)``), or the reason not."""
    if method != "two_filter":
        return "only the two-filter smoother"
    model = kernels.describe(filter, "linear_gaussian")
    if isinstance(model, str):
        return model
    if large:
        n = model.F.shape[-1]
        if not MAX_STATE < n <= LARGE_STATE:
            return f"states of {MAX_STATE + 1} to {LARGE_STATE} components only"
        batch = trajectory.belief.mode_log_probs[0].numel()
        if batch < LARGE_BATCH:
            return f"a small batch ({batch} runs x modes < {LARGE_BATCH}: the eager passes are faster)"
    reason = why_not_smooth(model, trajectory, measurements, prior_log, LARGE_STATE if large else MAX_STATE)
    if reason is not None:
        return reason
    like = trajectory.belief.mode_log_probs
    passes = BatchLastTwoFilter(model, model.transition.shape[-1], like.dim() - 2, like)
    return lambda: passes.run(trajectory, measurements, prior_log, padding, ends)


LARGE_SMOOTHER = LargeStateSmoother()  # (registered by torchmm.kernels.TABLE)
