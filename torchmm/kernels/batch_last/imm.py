r"""The IMM (and GPB1) over linear Kalman modes in the batch-last layout: the engine's fast path (issue 17).

:func:`~torchmm.run_filter` runs an :class:`~torchmm.IMM` over one :class:`~torchmm.KalmanFilter`
with mode-bank linear models through this kernel (docs/performance.md); also GPB2 (its step in
:mod:`torchmm.kernels.batch_last.pairs`) and the variable-structure IMM, whose model-set policy
runs after each step as the description's ``post_update`` (:meth:`BatchLastIMM.step`). The public layout stays
batch-first; inside, the state is kept with the batch axes *last*: the mode probabilities ``(M, *B)``
and, for large batches, one tensor ``(M, *B)`` per entry: the mode means ``x[a]`` and the
covariances' upper triangle ``C[a][c]`` (``a <= c``); for small batches, where each operation
costs its dispatch more than its arithmetic, ``X (n, M, *B)`` and an exactly symmetric
``P (n, n, M, *B)``, so that the mixing and the estimate's moments take every entry in one
broadcast operation (:meth:`BatchLastIMM.prepare` chooses by the size of the mixing's
temporaries; docs/performance.md). Model matrices are classified entry by entry once per run
(exactly 0 or 1 in every mode: skipped or added, bit-identical; one number shared by the modes; a
tensor per mode).

Every small matrix product (``F C F^T``, ``P h``, the mixing sums) is then a short sum of
elementwise products, each one contiguous pass over all runs and modes, where the batch-first
engine calls ``bmm`` on ``2 x 2`` matrices and broadcasts over a trailing ``(n, n)``. The step
computes what :meth:`IMM.step` does, in the same order:

- mixing ``mu_{i|j} = pi_ij mu_i / c_j`` and the moment-matched start beliefs (centred spread);
  for :class:`~torchmm.GPB1` the collapse with weights ``mu_i``, one start belief for every mode;
- each mode's prediction ``F_j m + b_j``, ``F_j C F_j^T + Q_j``;
- the update one measurement component after the other, exact for a diagonal ``R`` (the only case
  taken; anything else runs the batch-first engine): ``s = h P h^T + r``, ``K = P h^T / s``,
  ``P+ = P - K (P h^T)^T`` (one triangle: symmetric by construction), ``s`` clamped at the
  smallest normal number and flagged as in :func:`torchmm.linalg.condition`. A component whose
  datum is non-finite is skipped (missing data, exact; the masks are computed once per run);
- the mode posterior in log space (:func:`~torchmm.multimodel.imm.mode_posterior`, in fewer passes).

Once a structure of the kernel has run 1,000 steps in a process, its steps run as a ``torch.fx`` graph of
:meth:`BatchLastIMM.core` (the same operations, bit for bit, 10-20 % faster a step):
:mod:`torchmm.kernels.batch_last.traced`.

Every :class:`~torchmm.filters.StepOutput` field (prior, innovations, ``extras``: ``mixed``,
``mode_log_likelihood``, ``modes.singular``) is returned as a batch-first *view* of the batch-last
tensors, so the outputs equal the batch-first engine's to rounding (tests/multimodel/test_batch_last.py)
and cost nothing until :func:`~torchmm.run.stack_outputs` stacks what ``record`` keeps.
"""

from __future__ import annotations

import logging
import math

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief, ModeBelief
from torchmm.kernels.batch_last.algebra import (
    ZERO,
    coefficients,
    collapse_entries,
    collapse_modes,
    combine,
    log_normalized,
    mix_entries,
    mixing,
    sandwich,
    stack_upper,
)
from torchmm.kernels.batch_last.plan import described, planned, why_not
from torchmm.kernels.batch_last.traced import select
from torchmm.typing import StepOutput

__all__ = ["BATCH_LAST", "LARGE_BATCH", "LARGE_STATE", "MAX_STATE", "BatchLastIMM", "BatchLastKernel"]

_LOG_2PI = math.log(2 * math.pi)
#: the largest state whose n x n factors the kernels form entry by entry (the two-filter smoother's pairs,
#: IMM-TF's transfer smoothing): n^3 operations a factor
MAX_STATE = 6
#: larger states, up to this many components, take the two-filter smoother's kernel from ``LARGE_BATCH``
#: runs x modes (a kernel of its own, ``"batch_last_smooth_large"``, chosen by the batch size:
#: torchmm.kernels.batch_last.smooth.LargeStateSmoother)
LARGE_STATE = 10
LARGE_BATCH = 900
#: the largest mixing temporary (bytes) for which the step takes every matrix entry in one broadcast
#: operation (docs/performance.md: 400 runs of n = 2, M = 3 gain 10 %, 4,000 lose 18 %)
_BROADCAST_BYTES = 1 << 18

log = logging.getLogger("torchmm")


class BatchLastIMM:
    """One IMM step in the batch-last layout (module docstring), and the conversions.

    Args:
        model: the filter's :class:`~torchmm.kernels.linear.LinearGaussian` description (rule ``"mix"``
            or ``"collapse"``) for which :func:`~torchmm.kernels.batch_last.plan.why_not` is None.
        M: the number of modes.
        batch_dims: the number of batch axes ``len(B)``.
        like: a tensor of the run's dtype and device.
    """

    #: what the kernel computes, for messages
    kind = "IMM"

    def __init__(self, model, M: int, batch_dims: int, like: Tensor):
        d = batch_dims
        self.setup(model, M, model.F.shape[-1], model.H.shape[-2], d, like)
        self.F = coefficients(model.F, M, 2, d)
        self.Q = coefficients(model.Q, M, 2, d)
        self.b = coefficients(model.b, M, 1, d)
        self.H = coefficients(model.H, M, 2, d)
        self.r = coefficients(model.R.diagonal(dim1=-2, dim2=-1), M, 1, d)
        R = model.R
        self.R_front = (R if R.dim() == 3 else R.unsqueeze(0)).movedim(0, -1).reshape(
            self.m, self.m, -1, *([1] * d))  # (m, m, P, 1...), for the recorded S only

    def setup(self, model, M: int, n: int, m: int, d: int, like: Tensor) -> None:
        """What every batch-last IMM kernel holds besides its models: the sizes, the interaction (from
        ``model.transition`` and ``model.rule``), the constants, the permutations between the layouts,
        the record options and the filter's ``post_update``."""
        from torchmm.beliefs.ops import safe_log_normalize

        self.normalize, self.collapse = safe_log_normalize, model.rule == "collapse"
        self.broadcast = True  # the state's layout (prepare chooses it by the batch size)
        self.M, self.n, self.m, self.d = M, n, m, d
        matrix = model.transition
        self.matrix = matrix.reshape(M, M, *([1] * d))  # (i, j, 1...)
        self.tiny = torch.finfo(like.dtype).tiny
        # constants as 0-dim tensors (an operation with a Python number costs more dispatch)
        constant = lambda value: torch.full((), value, dtype=like.dtype, device=like.device)  # noqa: E731
        self.tiny_t, self.lowest = constant(self.tiny), constant(torch.finfo(like.dtype).min)
        self.log_2pi = constant(_LOG_2PI)
        # batch-last -> batch-first as one permute each (movedim costs twice the dispatch, every step)
        self._to_front1 = (*range(1, d + 1), 0)  # (k, *B) -> (*B, k)
        self._to_front2 = (*range(2, d + 2), 0, 1)  # (a, c, *B) -> (*B, a, c)
        self._to_front_x = (*range(2, d + 2), 1, 0)  # (n, M, *B) -> (*B, M, n)
        self._to_front_p = (*range(3, d + 3), 2, 0, 1)  # (n, n, M, *B) -> (*B, M, n, n)
        self.omitted: frozenset = frozenset()
        self.estimate_only = False
        #: the filter's work after each update (a model-set policy: LinearGaussian.post_update), its
        #: generator, and whether the estimate is taken after it (record="estimate" with a post-update)
        self.post_update = getattr(model, "post_update", None)
        self.generator, self.estimate_after = None, False
        self._to_back1 = (d, *range(d))  # (*B, M) -> (M, *B)
        self._core = self.core
        self._compiled = False
        self._key = None  # the structure the untraced steps are counted for (None: not counting)
        self._steps_done = 0

    def compile(self) -> None:
        """Run :meth:`core` under ``torch.compile`` (fused kernels after seconds of compiling;
        docs/performance.md). Every model, shape and record option is its own compiled graph of
        this one method; dynamo's per-function limit (8, after which it runs eagerly) is raised
        to 64 so that a study's estimators all stay compiled."""
        import torch._dynamo.config as dynamo_config  # noqa: PLC0415

        if getattr(dynamo_config, "recompile_limit", 64) < 64:
            dynamo_config.recompile_limit = 64
        self._core = torch.compile(self.core, dynamic=False)
        self._compiled = True

    def omit(self, fields, estimate: bool = False) -> None:
        """The :class:`StepOutput` fields ``record`` discards (returned as None from now on);
        ``estimate``: return the belief's point estimate (computed inside the step) in its place."""
        self.omitted = frozenset(fields)
        self.estimate_only = estimate
        self._select()

    def _select(self) -> None:
        """The steps to come on the traced graph of this kernel's structure, or on :meth:`core`
        (:func:`torchmm.kernels.batch_last.traced.select`)."""
        select(self)

    # -- layout -----------------------------------------------------------------------------------
    def to_batch_last(self, belief: ModeBelief) -> tuple[Tensor, Tensor, Tensor]:
        """``ModeBelief`` (batch-first) -> ``X (n, M, *B)``, ``P (n, n, M, *B)``, ``log_mu (M, *B)``."""
        d = self.d
        comps = belief.components
        X = comps.mean.movedim((d, d + 1), (1, 0))
        P = comps.cov.movedim((d, d + 1, d + 2), (2, 0, 1))
        log_mu = belief.mode_log_probs.movedim(d, 0)
        return X, P, log_mu

    def entries(self, P: Tensor) -> list:
        """``P (n, n, ...)`` as nested lists of views ``C[a][c]``."""
        n = self.n
        flat = P.flatten(0, 1).unbind(0)
        return [flat[a * n:(a + 1) * n] for a in range(n)]

    def gaussian(self, X: Tensor, P: Tensor) -> GaussianBelief:
        """Batch-first views ``(*B, M, n)`` and ``(*B, M, n, n)`` of batch-last ``X (n, M, *B)``, ``P (n, n, M, *B)``."""
        return GaussianBelief(X.permute(self._to_front_x), P.permute(self._to_front_p))

    def modes(self, t: Tensor) -> Tensor:
        """``(M, *B)`` -> ``(*B, M)`` (a view)."""
        return t.permute(self._to_front1)

    # -- the step ---------------------------------------------------------------------------------
    def prepare(self, measurements: Tensor) -> None:
        """Once per run: the measurements ``(T, *B, m)`` as ``(T, m, *B)``, with missing components
        (non-finite) set to 0 and their masks, so that no step tests its data; and the state's
        layout (``self.broadcast``) for this batch size."""
        z = measurements.movedim(-1, 1)
        # the layout of the state: every entry in one broadcast operation while the temporaries of the
        # mixing (n^2 M^2 values a run) stay within the cache (the step is bound by dispatch there),
        # one operation per stored entry beyond (bound by memory)
        self.broadcast = self.broadcast_layout(z.shape[2:].numel(), z.element_size())
        observed = torch.isfinite(z)
        ob = observed.to(z.dtype)  # 1 observed, 0 missing
        # the step's tensors, split once per run (indexing them is a dispatch each, every step)
        self.data = list(zip(torch.where(observed, z, 0.0).unbind(0), ob.unbind(0), ob.mul(-0.5).unbind(0),
                             observed.any(1).unbind(0), z.unbind(0)))
        self.zero = torch.zeros((), dtype=z.dtype, device=z.device)
        self._steps_done = 0
        self._select()

    def broadcast_layout(self, runs: int, itemsize: int) -> bool:
        """Whether the state of a run of ``runs`` runs takes the broadcast layout (``X (n, M, *B)``, ``P``
        whole) rather than one tensor per entry (:meth:`prepare`)."""
        return self.n * self.n * self.M * self.M * runs * itemsize <= _BROADCAST_BYTES

    def core(self, X: Tensor, P: Tensor, mu: Tensor, zc: Tensor, ob: Tensor, nhob: Tensor, anyob: Tensor,
             zraw: Tensor) -> tuple:
        """The step's arithmetic, tensors in and out (what ``compile=True`` compiles).

        Shapes:
            X: the mode means ``(n, M, *B)``; P: their covariances ``(n, n, M, *B)`` (exactly
            symmetric) - or, where ``self.broadcast`` is False, ``n`` tensors ``(M, *B)`` and nested
            lists ``P[a][c]`` for ``a <= c`` (as returned: the next state); mu: the mode
            probabilities ``(M, *B)``; zc, ob, nhob, zraw ``(m, *B)`` (the data with 0 where
            missing, the observed mask, ``-0.5`` times it, the data); anyob
            ``(*B,)`` -> the new ``X, P, log_mu, mu``, the log-likelihood ``(*B,)``, then (None where
            not needed) the predicted ``X, P``, ``log c (M, *B)``, the mode log-likelihoods and
            singular flags ``(M, *B)``, the mixed ``X0, P0``, the innovations ``(m, M, *B)`` and
            their covariances ``(m, m, M, *B)`` (``estimate_only``: the estimate ``(n, *B)``,
            ``(n, n, *B)`` in these two).
        """
        omitted = self.omitted
        # interaction: c_j = sum_i mu_i pi_ij and the weights: mu_{i|j} (IMM) or mu_i (GPB1: every mode starts
        # from the one collapsed posterior)
        cbar, w = mixing(mu, self.matrix, self.tiny_t, self.collapse)
        if self.broadcast:
            # every entry at once: the mixed means and sum_i w_ij (P_i + d_ij d_ij^T), d_ij = x_i - x0_j
            # (d d^T is exactly symmetric, so the sum is)
            Xm, Pm = collapse_modes(X.unsqueeze(2), P.unsqueeze(3), w)  # (n, j, *B), (n, n, j, *B)
            if self.collapse:  # the one start belief, seen by every mode (views)
                Xm, Pm = Xm.expand_as(X), Pm.expand_as(P)
            xs, Cm = Xm.unbind(0), self.entries(Pm)
        else:
            # entry by entry (X, P: lists), each one pass over (i, j, *B)
            xs, Cm = mix_entries(X, P, w, self.n)
            if self.collapse:  # the one start belief, seen by every mode (views)
                xs = [t.expand_as(cbar) for t in xs]
                Cm = [[None if t is None else t.expand_as(cbar) for t in row] for row in Cm]
            Xm = Pm = None
            if "extras" not in omitted:
                Xm, Pm = torch.stack(xs), stack_upper(Cm)
        w = None  # freed (not del: a name a comprehension reads is a cell, and torch.compile breaks its graph at
        # DELETE_DEREF); X and P: the caller's state holds them
        xp, Pp = self.predict_entries(xs, Cm, cbar)
        xu, Cu, ll, singular, s_first = self.update_components(xp, Pp, zc, ob, nhob, cbar, "extras" not in omitted)
        log_cbar, new_log_mu, total = self.mode_update(ll, cbar, anyob)
        keep_extras = "extras" not in omitted
        Xp = Ppt = nu_out = S_out = None
        mu = new_log_mu.exp()  # for the estimate and the next step
        if self.broadcast:
            X, P = torch.stack(xu), stack_upper(Cu)  # the next state, and the posterior
        else:
            X, P = xu, Cu  # the next state
        if self.estimate_only:  # the moment-matched collapse, (n, *B) and (n, n, *B) (exactly symmetric)
            if self.broadcast:
                nu_out, S_out = collapse_modes(X, P, mu)  # returned in the innovation slots
            else:
                nu_out, S_out = collapse_entries(xu, Cu, mu, self.n)
        X_out = P_out = None
        if not self.estimate_only:
            X_out, P_out = (X, P) if self.broadcast else (torch.stack(xu), stack_upper(Cu))
            if "prior" not in omitted:
                Xp, Ppt = torch.stack(xp), stack_upper(Pp)
            if "innovation" not in omitted or "innovation_cov" not in omitted:
                nu_out, S_out = self._innovation(zraw, xp, Pp, s_first)
        return (
            X, P, X_out, P_out, new_log_mu, mu, total, Xp, Ppt, log_cbar,
            ll if keep_extras else None, singular,
            Xm if keep_extras else None, Pm if keep_extras else None,
            nu_out, S_out,
        )

    def predict_entries(self, xs: list, Cs: list, like: Tensor) -> tuple[list, list]:
        """Every mode's prediction of per-entry beliefs (any shapes broadcasting with the modes' ``(M, *B)``):
        ``F m + b``, ``F C F^T + Q`` (upper triangle). ``like``: the shape of an all-zero entry."""
        n, F, b = self.n, self.F, self.b
        xp = [combine([(F[a][e], xs[e]) for e in range(n)], b[a], like) for a in range(n)]
        return xp, sandwich(F, Cs, self.Q, like)

    def mode_update(self, ll: Tensor, cbar: Tensor, anyob: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The mode posterior ``log mu_j = ell_j + log c_j - logsumexp_l(ell_l + log c_l)``, as
        torch.logsumexp and safe_log_normalize compute it (all ``-inf``: ``-inf`` and uniform), in fewer
        passes: ``log c (M, *B)``, ``log mu (M, *B)`` and the log-likelihood ``(*B,)`` (exactly 0 without
        a datum)."""
        log_cbar = cbar.log()
        joint = ll + log_cbar
        top = torch.maximum(joint.amax(0), self.lowest)
        shifted = joint - top
        log_sum = shifted.exp().sum(0).log()
        new_log_mu = log_normalized(shifted, log_sum, self.M)
        return log_cbar, new_log_mu, torch.where(anyob, top + log_sum, self.zero)

    def update_components(self, xp: list, Pp: list, zc: Tensor, ob: Tensor, nhob: Tensor, like: Tensor,
                          flags: bool) -> tuple:
        """The Kalman update of per-entry beliefs ``xp[a]``, ``Pp[a][c]`` (``a <= c``, any broadcastable
        shapes ``(..., *B)``), one measurement component after the other (diagonal ``R``): ``s = h P h^T +
        r``, ``K = P h^T / s``, ``P+ = P - K (P h^T)^T``, ``s`` clamped at the smallest normal number; a
        missing component has ``ob = 0``, ``zc = 0`` and is skipped exactly. ``like``: a tensor of the
        result's shape for an all-zero sum. Returns the posterior ``xu``, ``Cu``, the log-likelihood, the
        singular flags (None unless ``flags``) and the first component's ``s``."""
        n, m, tiny = self.n, self.m, self.tiny
        H, r = self.H, self.r
        upper = [(a, c) for a in range(n) for c in range(a, n)]
        sym = lambda T, a, c: T[min(a, c)][max(a, c)]  # noqa: E731
        xu, Cu = xp, Pp
        ll = singular = s_first = None
        for k in range(m):
            g = [combine([(H[k][c], sym(Cu, a, c)) for c in range(n)], ZERO, like) for a in range(n)]  # P h^T
            s_raw = combine([(H[k][a], g[a]) for a in range(n)], r[k], like)
            nu = zc[k] - combine([(H[k][a], xu[a]) for a in range(n)], ZERO, like)
            s = torch.maximum(s_raw, self.tiny_t)
            ratio = ob[k] / s
            gain = [g[a] * ratio for a in range(n)]
            xu = [torch.addcmul(xu[a], gain[a], nu) for a in range(n)]
            new = [[None] * n for _ in range(n)]
            for a, c in upper:
                new[a][c] = torch.addcmul(Cu[a][c], gain[a], g[c], value=-1.0)
            Cu = new
            term = torch.addcdiv(s.log().add_(self.log_2pi), nu * nu, s).mul_(nhob[k])
            ll = term if ll is None else ll + term
            if flags:
                flag = (s_raw <= tiny) & (ob[k] > 0)
                singular = flag if singular is None else singular | flag
            if k == 0:
                s_first = s_raw
        return xu, Cu, ll, singular, s_first

    def initial_state(self, belief: ModeBelief) -> tuple:
        """The state of :meth:`step` at time 0 from the batch-first ``belief``: the means and
        covariances (``X (n, M, *B)`` and ``P (n, n, M, *B)``, the upper triangle mirrored, or the
        per-entry lists: :meth:`prepare`'s layout), the mode probabilities ``(M, *B)`` and the step
        index."""
        X, P, log_mu = self.to_batch_last(belief)
        n = self.n
        C = [[P[a, c] if c >= a else None for c in range(n)] for a in range(n)]
        if self.broadcast:
            return X, stack_upper(C), log_mu.exp(), 0
        return list(X.unbind(0)), C, log_mu.exp(), 0

    def step(self, state: tuple, z: Tensor) -> tuple[tuple, StepOutput]:
        """One IMM step: :meth:`core` (compiled with ``compile=True``) on the prepared data of the
        state's step, its outputs as a :class:`StepOutput` of batch-first views (batch ``(*B,)``),
        and the next state. ``z`` is the step's measurement, which :meth:`prepare` holds."""
        X, P, mu, k = state
        out = self.run_core((X, P, mu, *self.data[k]), k)
        (X, P, X_out, P_out, log_mu, mu, total, Xp, Pp, log_cbar, ll, singular, Xm, Pm, nu, S) = out
        state = (X, P, mu, k + 1)
        modes, gaussian = self.modes, self.gaussian
        if self.estimate_only:  # (a failed run: a NaN log-likelihood, as in the engine)
            return state, self.estimate_output(nu, S, total)
        out = self.output(log_mu, X_out, P_out, None if Xp is None else ModeBelief(modes(log_cbar), gaussian(Xp, Pp)),
                          total, nu, S, None if ll is None else self.failures(modes, ll, singular, total, k))
        if self.post_update is not None:  # the filter's own work after the update (a model-set policy)
            out = self.post_update(out, self.generator)
            # carried on, batch-last in memory as the state (a policy's batch-first tensors would make
            # every operation of the next step a strided gather)
            state = (X, P, out.belief.mode_log_probs.permute(self._to_back1).contiguous().exp(), k + 1)
            if self.estimate_after:  # the belief's estimate: its Gaussians' collapse with its output weights
                belief = out.belief
                if isinstance(belief, ModeBelief) and type(belief.components) is GaussianBelief:
                    w = belief.output_log_weights().permute(self._to_back1).contiguous().exp()
                    est, cov = collapse_modes(X, P, w) if self.broadcast else collapse_entries(X, P, w, self.n)
                    return state, self.estimate_output(est, cov, out.log_likelihood)
                return state, StepOutput(belief.estimate(), None, out.log_likelihood)
        if ll is not None:
            out.extras["mixed"] = ModeBelief(modes(log_cbar), gaussian(Xm, Pm))
        return state, out

    def estimate_output(self, est: Tensor, cov: Tensor, total: Tensor) -> StepOutput:
        """A step's output with ``record="estimate"``: the estimate ``(n, *B)``, ``(n, n, *B)`` as a batch-first
        belief, and the log-likelihood ``(*B,)``."""
        return StepOutput(GaussianBelief(est.permute(self._to_front1), cov.permute(self._to_front2)), None, total)

    def failures(self, modes, ll: Tensor, singular: Tensor, total: Tensor, k: int) -> dict:
        """The ``extras`` failures as the engine flags them (docs/robustness.md), in its key order: a run's
        where its log-likelihood is NaN, a hypothesis's (``modes``: its batch-first view) where a datum is
        present at step ``k`` and its likelihood is NaN (a missing component of a NaN mode gives NaN * 0 here,
        0 in the engine), with the mode log-likelihoods and singular flags."""
        return {
            "mode_log_likelihood": modes(ll),
            "modes": {"singular": modes(singular), "failed": modes(torch.isnan(ll) & self.data[k][3])},
            "failed": torch.isnan(total),
        }

    def output(self, log_mu: Tensor, X: Tensor, P: Tensor, prior, total: Tensor, nu, S, extras: dict | None,
               to_x: tuple | None = None, to_p: tuple | None = None) -> StepOutput:
        """A step's :class:`StepOutput` of batch-first views: the posterior from ``log_mu (M, *B)``, ``X (n, M,
        *B)``, ``P (n, n, M, *B)``, the ``prior`` (a belief or None), the log-likelihood, the innovations and
        their covariances batch-last (None, or dropped where ``record`` omits them; ``to_x``, ``to_p``: their
        permutations to batch-first, the modes' by default) and ``extras``."""
        omitted = self.omitted
        return StepOutput(
            belief=ModeBelief(self.modes(log_mu), self.gaussian(X, P)),
            prior=prior,
            log_likelihood=total,
            innovation=None if nu is None or "innovation" in omitted else nu.permute(to_x or self._to_front_x),
            innovation_cov=None if S is None or "innovation_cov" in omitted else S.permute(to_p or self._to_front_p),
            extras=extras,
        )

    def run_core(self, args: tuple, k: int) -> tuple:
        """:meth:`core` (traced or compiled where chosen) on ``args``, the arguments of step ``k``; a
        compiler failure runs it eagerly from then on, said once."""
        self._steps_done = k + 1
        try:
            return self._core(*args)
        except Exception as error:  # noqa: BLE001 (a compiler failure: run eagerly, say so once)
            if not self._compiled:
                raise
            log.warning("compile: torch.compile failed for the %s fast path (%s: %s); running it eagerly",
                        self.kind, type(error).__name__, str(error).splitlines()[0][:200] if str(error) else "")
            self._core, self._compiled = self.core, False
            return self._core(*args)

    def _innovation(self, zraw, xp, Pp, s_first) -> tuple[Tensor, Tensor]:
        """The step's record of ``z - H x-`` ``(m, M, *B)`` (non-finite where missing) and
        ``S = H P- H^T + R`` ``(m, m, M, *B)``."""
        m, n, H = self.m, self.n, self.H
        nu = torch.stack([zraw[k] - combine([(H[k][a], xp[a]) for a in range(n)], ZERO, xp[0]) for k in range(m)])
        if m == 1:
            return nu, s_first.unsqueeze(0).unsqueeze(0)
        sym = lambda T, a, c: T[min(a, c)][max(a, c)]  # noqa: E731
        HP = [[combine([(H[k][e], sym(Pp, e, c)) for e in range(n)], ZERO, xp[0]) for c in range(n)]
              for k in range(m)]
        S = torch.stack([torch.stack([combine([(H[j][c], HP[k][c]) for c in range(n)], ZERO, xp[0])
                                      for j in range(m)]) for k in range(m)])
        return nu, S + self.R_front


class BatchLastKernel:
    """The registered kernel (:mod:`torchmm.kernels`) of the batch-last IMM, GPB1 and GPB2 step: a filter
    that describes itself as linear-Gaussian with the ``"mix"``, ``"collapse"`` or ``"pairs"`` rule
    (GPB2: :mod:`torchmm.kernels.batch_last.pairs`), a run without
    ``update_first``; any size (the small linear kernel takes small problems first), any device,
    ``compile`` and ``record`` functions included."""

    name = "batch_last"

    def plan(self, filter, belief0, measurements, request: kernels.Request):
        model = described(filter, request, "linear_gaussian", ("mix", "collapse", "pairs"), "IMM, GPB1 and GPB2",
                          belief0, measurements, why_not)
        if isinstance(model, str):
            return model
        M = model.transition.shape[-1]
        like = belief0.mode_log_probs
        if model.rule == "pairs":
            from torchmm.kernels.batch_last.pairs import BatchLastGPB2

            kernel = BatchLastGPB2(model, M, like.dim() - 1, like)
        else:
            kernel = BatchLastIMM(model, M, like.dim() - 1, like)
        if request.compile:
            kernel.compile()
        kernel.prepare(measurements)
        return planned(kernel, belief0, request)

    def plan_smooth(self, filter, trajectory, method, **inputs):
        """The two-filter smoother of a run of an IMM, GPB1 or GPB2 over linear Kalman modes (``n <= 6``,
        diagonal ``R``): ``run() -> ModeBelief`` (batch ``(T, *B)``), or the reason not."""
        from torchmm.kernels.batch_last.smooth import plan_two_filter  # (smooth.py imports this module)

        return plan_two_filter(filter, trajectory, method, inputs.get("measurements"), inputs.get("prior_log"))


BATCH_LAST = BatchLastKernel()  # (registered by torchmm.kernels.TABLE)
