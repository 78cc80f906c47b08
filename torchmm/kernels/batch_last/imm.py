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

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief, ModeBelief
from torchmm.kernels.batch_last.algebra import (
    collapse_entries,
    collapse_modes,
    mix_entries,
    mixing,
    mode_update,
    stack_upper,
)
from torchmm.kernels.batch_last.bank import LinearBank
from torchmm.kernels.batch_last.frame import Frame
from torchmm.kernels.batch_last.plan import described, planned, why_not
from torchmm.typing import StepOutput

__all__ = ["BATCH_LAST", "LARGE_BATCH", "LARGE_STATE", "MAX_STATE", "BatchLastIMM", "BatchLastKernel"]

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


class BatchLastIMM(Frame):
    """One IMM (GPB1) step in the batch-last layout (module docstring): the :class:`Frame` of the kernel and
    the step, over a mode bank's model algebra.

    Args:
        model: the filter's :class:`~torchmm.kernels.linear.LinearGaussian` description (rule ``"mix"``
            or ``"collapse"``) for which :func:`~torchmm.kernels.batch_last.plan.why_not` is None (or, with
            ``bank``, any description of the rule with a ``transition``).
        M: the number of modes.
        batch_dims: the number of batch axes ``len(B)``.
        like: a tensor of the run's dtype and device.
        bank: the modes' algebra (its ``predict``, ``update`` and ``innovation``); by default the linear
            Kalman modes of ``model`` (:class:`~torchmm.kernels.batch_last.bank.LinearBank`).
    """

    def __init__(self, model, M: int, batch_dims: int, like: Tensor, bank=None):
        self.bank = LinearBank(model, M, batch_dims, like) if bank is None else bank
        self.traceable = self.bank.traceable
        super().__init__(model, M, self.bank.n, self.bank.m, batch_dims, like)

    def broadcast_layout(self, runs: int, itemsize: int) -> bool:
        """Whether the state of a run of ``runs`` runs takes the broadcast layout (``X (n, M, *B)``, ``P``
        whole) rather than one tensor per entry: while the mixing's temporaries stay within the cache."""
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
        omitted, bank = self.omitted, self.bank
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
        xp, Pp = bank.predict(xs, Cm, cbar)
        xu, Cu, ll, singular, s_first = bank.update(xp, Pp, zc, ob, nhob, cbar, "extras" not in omitted)
        log_cbar, new_log_mu, total = mode_update(ll, cbar, anyob, self.lowest, self.zero, self.M,
                                                  self.tiny_t)
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
                nu_out, S_out = bank.innovation(zraw, xp, Pp, s_first)
        return (
            X, P, X_out, P_out, new_log_mu, mu, total, Xp, Ppt, log_cbar,
            ll if keep_extras else None, singular,
            Xm if keep_extras else None, Pm if keep_extras else None,
            nu_out, S_out,
        )

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


class BatchLastKernel:
    """The registered kernel (:mod:`torchmm.kernels`) of the batch-last IMM, GPB1 and GPB2 step: a filter
    that describes itself as linear-Gaussian with the ``"mix"``, ``"collapse"`` or ``"pairs"`` rule
    (GPB2: :mod:`torchmm.kernels.batch_last.pairs`), a run without
    ``update_first``; any size (the small linear kernel takes small problems first), any device,
    ``compile`` and ``record`` functions included."""

    name = "batch_last"
    smooths_padding = True  # plan_smooth takes padding= and ends= (runs that end early: two-filter passes)

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

        return plan_two_filter(filter, trajectory, method, inputs.get("measurements"),
                               inputs.get("prior_log"), padding=inputs.get("padding"),
                               ends=inputs.get("ends", ()))


BATCH_LAST = BatchLastKernel()  # (registered by torchmm.kernels.TABLE)
