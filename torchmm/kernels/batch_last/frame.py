"""What every batch-last multiple-model kernel holds besides its step (issue 47: the kernels compose one
algebra instead of subclassing one kernel): the sizes, the interaction, the constants, the permutations
between the layouts, the record options, the run's prepared data, the step's runner (traced, compiled or
eager) and the assembly of its :class:`~torchmm.filters.StepOutput` as batch-first views.

Each kernel is a :class:`Frame` with a step of its own - the IMM and GPB1
(:class:`~torchmm.kernels.batch_last.imm.BatchLastIMM`), GPB2 (:mod:`~torchmm.kernels.batch_last.pairs`),
IMM-TF (:mod:`~torchmm.kernels.batch_last.transfer`) - written with the Gaussian algebra's free functions
(:mod:`~torchmm.kernels.batch_last.algebra`) and a mode bank's model algebra: the linear one
(:class:`~torchmm.kernels.batch_last.bank.LinearBank`) or the extended / unscented one
(:class:`~torchmm.kernels.batch_last.nonlinear.NonlinearBank`)."""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief, ModeBelief
from torchmm.kernels.batch_last.algebra import stack_upper
from torchmm.kernels.batch_last.traced import select
from torchmm.typing import StepOutput

__all__ = ["Frame", "measurement_data"]

log = logging.getLogger("torchmm")


def measurement_data(measurements: Tensor) -> list:
    """Once per run: the measurements ``(T, *B, m)`` as one tuple a step of ``(m, *B)`` tensors - the data with
    missing (non-finite) components set to 0, the observed mask (1/0), ``-0.5`` times it, whether any
    component is present ``(*B,)`` and the data as given - so that no step tests its data."""
    z = measurements.movedim(-1, 1)
    observed = torch.isfinite(z)
    ob = observed.to(z.dtype)  # 1 observed, 0 missing
    # the step's tensors, split once per run (indexing them is a dispatch each, every step)
    return list(zip(torch.where(observed, z, 0.0).unbind(0), ob.unbind(0), ob.mul(-0.5).unbind(0),
                    observed.any(1).unbind(0), z.unbind(0)))


class Frame:
    """The sizes, interaction, constants, layouts, record options and output assembly of a batch-last kernel
    (module docstring); a kernel adds ``core`` (its arithmetic, tensors in and out), ``initial_state`` and
    ``step``.

    Args:
        model: the filter's description (its ``transition``, ``rule`` and optional ``post_update``).
        M, n, m: the numbers of modes, state and measurement components.
        batch_dims: ``len(B)``.
        like: a tensor of the run's dtype and device.
    """

    #: what the kernel computes, for messages
    kind = "IMM"
    #: whether its steps run as a traced graph of ``core`` once its structure has run enough steps
    #: (:mod:`~torchmm.kernels.batch_last.traced`: a ``core`` of the IMM's arguments over a linear bank)
    traceable = False

    def __init__(self, model, M: int, n: int, m: int, batch_dims: int, like: Tensor):
        from torchmm.beliefs.ops import safe_log_normalize

        d = batch_dims
        self.normalize, self.collapse = safe_log_normalize, model.rule == "collapse"
        self.broadcast = False  # the state's layout (prepare chooses it by the batch size)
        self.M, self.n, self.m, self.d = M, n, m, d
        self.matrix = model.transition.reshape(M, M, *([1] * d))  # (i, j, 1...)
        self.tiny = torch.finfo(like.dtype).tiny
        # constants as 0-dim tensors (an operation with a Python number costs more dispatch)
        self.tiny_t = torch.full((), self.tiny, dtype=like.dtype, device=like.device)
        self.lowest = torch.full((), torch.finfo(like.dtype).min, dtype=like.dtype, device=like.device)
        # batch-last -> batch-first as one permute each (movedim costs twice the dispatch, every step)
        self._to_front1 = (*range(1, d + 1), 0)  # (k, *B) -> (*B, k)
        self._to_front2 = (*range(2, d + 2), 0, 1)  # (a, c, *B) -> (*B, a, c)
        self._to_front_x = (*range(2, d + 2), 1, 0)  # (n, M, *B) -> (*B, M, n)
        self._to_front_p = (*range(3, d + 3), 2, 0, 1)  # (n, n, M, *B) -> (*B, M, n, n)
        self._to_back1 = (d, *range(d))  # (*B, M) -> (M, *B)
        self.omitted: frozenset = frozenset()
        self.estimate_only = False
        #: the filter's work after each update (a model-set policy: LinearGaussian.post_update), its
        #: generator, and whether the estimate is taken after it (record="estimate" with a post-update)
        self.post_update = getattr(model, "post_update", None)
        self.generator, self.estimate_after = None, False
        self._core = self.core
        self._compiled = False
        self._key = None  # the structure the untraced steps are counted for (None: not counting)
        self._steps_done = 0

    def compile(self) -> None:
        """Run ``core`` under ``torch.compile`` (fused kernels after seconds of compiling;
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
        """The steps to come on the traced graph of this kernel's structure, or on ``core``
        (:func:`torchmm.kernels.batch_last.traced.select`) where the kernel is ``traceable``; else ``core``
        (compiled with ``compile=True``)."""
        if self.traceable:
            select(self)
        elif not self._compiled:
            self._core = self.core

    def core(self, *args) -> tuple:  # pragma: no cover (each kernel's own)
        raise NotImplementedError

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
        """Batch-first views ``(*B, M, n)`` and ``(*B, M, n, n)`` of batch-last ``X (n, M, *B)`` and
        ``P (n, n, M, *B)``."""
        return GaussianBelief(X.permute(self._to_front_x), P.permute(self._to_front_p))

    def modes(self, t: Tensor) -> Tensor:
        """``(M, *B)`` -> ``(*B, M)`` (a view)."""
        return t.permute(self._to_front1)

    def initial_state(self, belief: ModeBelief) -> tuple:
        """The state of ``step`` at time 0 from the batch-first ``belief``: the means and covariances (``X (n, M,
        *B)`` and ``P (n, n, M, *B)``, the upper triangle mirrored, or the per-entry lists: :meth:`prepare`'s
        layout), the mode probabilities ``(M, *B)`` and the step index."""
        X, P, log_mu = self.to_batch_last(belief)
        n = self.n
        C = [[P[a, c] if c >= a else None for c in range(n)] for a in range(n)]
        if self.broadcast:
            return X, stack_upper(C), log_mu.exp(), 0
        return list(X.unbind(0)), C, log_mu.exp(), 0

    # -- the run ----------------------------------------------------------------------------------
    def prepare(self, measurements: Tensor) -> None:
        """Once per run: the measurements' per-step data (:func:`measurement_data`) and the state's layout
        (``self.broadcast``) for this batch size."""
        self.data = measurement_data(measurements)
        # the layout of the state: every entry in one broadcast operation while the temporaries of the
        # mixing (n^2 M^2 values a run) stay within the cache (the step is bound by dispatch there),
        # one operation per stored entry beyond (bound by memory)
        self.broadcast = self.broadcast_layout(measurements.shape[1:-1].numel(), measurements.element_size())
        self.zero = torch.zeros((), dtype=measurements.dtype, device=measurements.device)
        self._steps_done = 0
        self._select()

    def broadcast_layout(self, runs: int, itemsize: int) -> bool:
        """Whether the state of a run of ``runs`` runs takes the broadcast layout (``X (n, M, *B)``, ``P``
        whole) rather than one tensor per entry (:meth:`prepare`): never, unless the kernel says otherwise."""
        return False

    def run_core(self, args: tuple, k: int) -> tuple:
        """``core`` (traced or compiled where chosen) on ``args``, the arguments of step ``k``; a compiler failure
        runs it eagerly from then on, said once."""
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

    # -- the outputs ------------------------------------------------------------------------------
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
