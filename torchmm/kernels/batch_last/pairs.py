r"""GPB2 over linear Kalman modes in the batch-last layout (issue 31, goal 3).

:func:`~torchmm.run_filter` runs a :class:`~torchmm.GPB2` over one :class:`~torchmm.KalmanFilter` with
mode-bank linear models through this kernel (:class:`~torchmm.kernels.batch_last.imm.BatchLastKernel`,
the ``"pairs"`` rule of the linear-Gaussian description). It is the batch-last IMM kernel
(:mod:`torchmm.kernels.batch_last.imm`) with the step of :meth:`GPB2.step <torchmm.GPB2.step>` in place of
the IMM's, in the same order:

- the pair hypotheses: pair ``(i, j)`` starts from mode ``i``'s posterior with prior weight
  ``log mu_i + log pi_ij``;
- pair ``(i, j)``'s prediction with mode ``j``'s model and its update, one measurement component
  after the other (a diagonal ``R``), as the IMM kernel's;
- ``log w_ij = ell_ij + log mu_i + log pi_ij``, ``log mu_j`` and the log-likelihood by ``logsumexp``
  over ``i`` and then ``j``, the merge weights ``w_ij / sum_i w_ij`` (normalised as
  :func:`~torchmm.beliefs.ops.safe_log_normalize` does), and mode ``j``'s posterior the
  moment-matched collapse over ``i`` (centred spread).

The state is kept one tensor per entry: the means ``x[a]`` and the covariances' upper triangle
``C[a][c]``, each ``(M, *B)``; the pairs' tensors are ``(i, j, *B)``. A model entry shared by the modes
(exactly 0 or 1, or one number) is applied once per ``i`` - shape ``(i, 1, *B)`` - and broadcast over
``j`` only where a per-mode entry meets it. Where every mode shares ``F``, ``Q``, ``H`` and ``R`` (the
modes differing in their input ``b``, paper 000's accelerations) the ``M^2`` pair covariances are the
``M`` predicted from each ``i``: the batch-first engine computes all ``M^2``.

Every :class:`~torchmm.filters.StepOutput` field is returned as in the engine (the prior over the
``M^2`` pairs with mode axis ``i * M + j``, innovations ``(*B, M, M, m)``, ``extras``:
``mode_log_likelihood`` and ``modes.singular``/``modes.failed`` ``(*B, M, M)``), as batch-first views of
the batch-last tensors; equal to the engine's to rounding (tests/multimodel/test_batch_last_pairs.py).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief, ModeBelief
from torchmm.beliefs.ops import dead_safe_logsumexp, live_log
from torchmm.typing import StepOutput
from torchmm.kernels.batch_last.algebra import collapse_entries, log_normalized, moments, stack_upper
from torchmm.kernels.batch_last.bank import LinearBank
from torchmm.kernels.batch_last.frame import Frame

__all__ = ["BatchLastGPB2"]


class BatchLastGPB2(Frame):
    """One GPB2 step in the batch-last layout (module docstring): the :class:`~torchmm.kernels.batch_last.frame.Frame`
    of the kernel, the pairs' step over the linear bank (:class:`~torchmm.kernels.batch_last.bank.LinearBank`).
    ``matrix`` holds ``log pi_ij`` ``(i, j, 1...)``; the state's third item is the mode log-probabilities
    ``(M, *B)``; the state is always one tensor per entry (the pairs' temporaries are ``M`` times the IMM's).

    Args: as :class:`~torchmm.kernels.batch_last.imm.BatchLastIMM` (a description with the ``"pairs"`` rule).
    """

    kind = "GPB2"
    traceable = True

    def __init__(self, model, M: int, batch_dims: int, like: Tensor):
        self.bank = bank = LinearBank(model, M, batch_dims, like)
        super().__init__(model, M, bank.n, bank.m, batch_dims, like)
        self.matrix = live_log(self.matrix, 0.0)  # (i, j, 1...): the pairs' prior weights (a zero: no NaN gradient)
        bank.R_front = bank.R_front.unsqueeze(2)  # (m, m, 1, P, 1...): mode j's R for the pair (i, j)
        d = batch_dims
        self._to_front_pairs_x = (*range(3, d + 3), 1, 2, 0)  # (n, i, j, *B) -> (*B, i, j, n)
        self._to_front_pairs_p = (*range(4, d + 4), 2, 3, 0, 1)  # (n, n, i, j, *B) -> (*B, i, j, n, n)

    def initial_state(self, belief: ModeBelief) -> tuple:
        """``(x[a] (M, *B), C[a][c] (M, *B) for a <= c, log_mu (M, *B), 0)``."""
        X, P, log_mu = self.to_batch_last(belief)
        n = self.n
        C = [[P[a, c] if c >= a else None for c in range(n)] for a in range(n)]
        return list(X.unbind(0)), C, log_mu, 0

    def core(self, X: list, C: list, log_mu: Tensor, zc: Tensor, ob: Tensor, nhob: Tensor, anyob: Tensor,
             zraw: Tensor) -> tuple:
        """The GPB2 step's arithmetic, tensors in and out.

        Shapes:
            X: ``n`` mode means ``(M, *B)``; C: nested lists ``C[a][c]`` ``(M, *B)`` for ``a <= c``;
            log_mu ``(M, *B)``; zc, ob, nhob, zraw ``(m, *B)``; anyob ``(*B,)`` (as the IMM's core)
            -> the next ``X, C``, the posterior means ``(n, M, *B)`` and covariances ``(n, n, M, *B)``
            (None with ``estimate_only``), ``log_mu``, ``mu (M, *B)``, the log-likelihood ``(*B,)``,
            then (None where not needed) the pairs' predicted means ``(n, M, M, *B)`` and covariances
            ``(n, n, M, M, *B)``, their prior log-weights, mode log-likelihoods and singular flags
            ``(M, M, *B)``, the innovations ``(m, M, M, *B)`` and their covariances ``(m, m, M, M, *B)``
            (``estimate_only``: the estimate ``(n, *B)``, ``(n, n, *B)`` in these two).
        """
        n, omitted, bank = self.n, self.omitted, self.bank
        # pair hypotheses: (i, j) starts from mode i's posterior, log weight log mu_i + log pi_ij
        prior_joint = log_mu.unsqueeze(1) + self.matrix  # (i, j, *B)
        # (by index, not iteration: the traced step's arguments are proxies)
        xs = [X[a].unsqueeze(1) for a in range(n)]  # (i, 1, *B)
        Cs = [[C[a][c].unsqueeze(1) if c >= a else None for c in range(n)] for a in range(n)]
        like = prior_joint
        # prediction with mode j's model: x- = F_j x_i + b_j, P- = F_j C_i F_j^T + Q_j
        xp, Pp = bank.predict(xs, Cs, like)
        xs = Cs = None  # freed as soon as dead (assignment, not del: see BatchLastIMM.core)
        keep_extras = "extras" not in omitted
        xu, Cu, ll, singular, s_first = bank.update(xp, Pp, zc, ob, nhob, like, keep_extras)
        # log w_ij, log mu_j (unnormalised), the log-likelihood, merge weights and mode posterior
        joint = ll + prior_joint  # (i, j, *B)
        log_mode = dead_safe_logsumexp(joint, 0)  # (j, *B) (a dead j: no NaN gradient)
        total = torch.logsumexp(log_mode, 0)  # (*B,)
        merge = log_normalized(joint, log_mode.unsqueeze(0), self.M).exp()
        new_log_mu = log_normalized(log_mode, total.unsqueeze(0), self.M)
        total = torch.where(anyob, total, self.zero)  # exactly 0 without a datum
        joint = log_mode = None
        # mode j's posterior: the collapse over i, sum_i w_ij (P_ij + d_ij d_ij^T), d_ij = x_ij - x_j
        xn, Cn = moments(xu, Cu, merge, n)  # (j, *B)
        merge = None
        mu = new_log_mu.exp()
        Xp = Ppt = nu_out = S_out = X_out = P_out = None
        if self.estimate_only:  # the moment-matched collapse over the modes, as the IMM kernel's
            nu_out, S_out = collapse_entries(xn, Cn, mu, n)
        else:
            X_out, P_out = torch.stack(xn), stack_upper(Cn)
            shape = prior_joint.shape
            if "prior" not in omitted:
                Xp = torch.stack([t.expand(shape) for t in xp])
                Ppt = stack_upper([[None if t is None else t.expand(shape) for t in row] for row in Pp])
            if "innovation" not in omitted or "innovation_cov" not in omitted:
                nu_out, S_out = bank.innovation(
                    zraw, [t.expand(shape) for t in xp],
                    [[None if t is None else t.expand(shape) for t in row] for row in Pp], s_first.expand(shape))
        shape = prior_joint.shape
        return (
            xn, Cn, X_out, P_out, new_log_mu, mu, total, Xp, Ppt,
            prior_joint if "prior" not in omitted else None,
            ll.expand(shape) if keep_extras else None,
            singular.expand(shape) if keep_extras else None,
            nu_out, S_out,
        )

    def step(self, state: tuple, z: Tensor) -> tuple[tuple, StepOutput]:
        """One GPB2 step: :meth:`core` on the prepared data of the state's step, its outputs as a
        :class:`StepOutput` of batch-first views (batch ``(*B,)``; pairs ``(*B, M * M)``), and the next
        state. ``z`` is the step's measurement, which :meth:`prepare` holds."""
        X, C, log_mu, k = state
        out = self.run_core((X, C, log_mu, *self.data[k]), k)
        (X, C, X_out, P_out, log_mu, mu, total, Xp, Pp, prior_joint, ll, singular, nu, S) = out
        state = (X, C, log_mu, k + 1)
        if self.estimate_only:
            return state, self.estimate_output(nu, S, total)
        pairs = lambda t: t.permute(self._to_front2)  # noqa: E731  (i, j, *B) -> (*B, i, j)
        prior = None
        if Xp is not None:
            d = self.d
            prior = ModeBelief(pairs(prior_joint).flatten(d, d + 1),
                               GaussianBelief(Xp.permute(self._to_front_pairs_x).flatten(d, d + 1),
                                              Pp.permute(self._to_front_pairs_p).flatten(d, d + 1)))
        out = self.output(log_mu, X_out, P_out, prior, total, nu, S,
                          None if ll is None else self.failures(pairs, ll, singular, total, k),
                          self._to_front_pairs_x, self._to_front_pairs_p)
        return state, out
