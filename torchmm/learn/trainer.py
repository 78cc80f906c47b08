"""A small training loop for filters: full or truncated BPTT, logging hooks and checkpoints.

The library does not import TensorBoard (or any experiment framework): pass a ``logger`` - any
object with ``scalar(tag, value, step)`` such as the studies' TensorBoard logger - and/or
``callbacks`` (callables receiving each :class:`TrainRecord`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from torchmm.contract import (
    BeliefArg,
    FilePath,
    Flag,
    Gen,
    Int,
    Of,
    Real,
    Text,
    Unchecked,
    Values,
    entry_point,
)
from torchmm.learn.loss import as_start_belief, negative_log_likelihood, truncated_segments
from torchmm.runtime import entries, one_thread_when_small

__all__ = ["TrainRecord", "Trainer", "load_checkpoint", "save_checkpoint"]  # (and NonFiniteLossError, below)


class NonFiniteLossError(ValueError, FloatingPointError):
    """:class:`Trainer` stopped: the loss or the parameters went non-finite. One line naming the
    iteration and the non-finite parameter(s), or saying that they are all finite (then the filter
    itself diverged, e.g. a learning rate too large). A ``ValueError`` (and, as before, a
    ``FloatingPointError``)."""


@dataclass
class TrainRecord:
    """One training iteration (one pass over the sequences, possibly several optimiser steps).

    Attributes:
        iteration: 1-based iteration count (continues across resumed runs).
        loss: the iteration's mean per-step negative log-likelihood (segments weighted by length)
            at the parameters the iteration started from (the optimiser's first closure
            evaluation; line-search probes of LBFGS are not reported).
        grad_norm: total gradient 2-norm before clipping, from the same evaluation.
        parameters: values reported by the trainer's ``track`` function after the update.
        seconds: wall time of the iteration.
    """

    iteration: int
    loss: float
    grad_norm: float
    parameters: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0


@entry_point(path=FilePath(), module=Of(nn.Module),
             optimizer=Of(torch.optim.Optimizer, methods=("step", "zero_grad", "state_dict"),
                          what="a torch.optim optimizer", optional=True))
def save_checkpoint(path, module: nn.Module, optimizer: torch.optim.Optimizer | None = None,
                    **extra: Any) -> Path:
    """Write ``module`` (and ``optimizer``) state and any ``extra`` picklable data to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {"model": module.state_dict(), "extra": extra}
    if optimizer is not None:
        state["optimizer"] = optimizer.state_dict()
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(state, tmp)
    tmp.replace(path)
    return path


@entry_point(path=FilePath(), module=Of(nn.Module),
             optimizer=Of(torch.optim.Optimizer, methods=("step", "zero_grad", "state_dict"),
                          what="a torch.optim optimizer", optional=True))
def load_checkpoint(path, module: nn.Module, optimizer: torch.optim.Optimizer | None = None) -> dict:
    """Restore ``module`` (and ``optimizer``) from :func:`save_checkpoint`; returns the ``extra`` dict.

    The module must have the same structure (including parametrised noise) as when saved.
    """
    path = Path(path)
    if not path.exists():
        raise ValueError(f"path: no checkpoint at {path}")
    state = torch.load(path, map_location="cpu", weights_only=False)
    module.load_state_dict(state["model"])
    if optimizer is not None:
        if "optimizer" not in state:
            raise ValueError(f"path: checkpoint {path} holds no optimizer state")
        optimizer.load_state_dict(state["optimizer"])
    return state.get("extra", {})


class Trainer:
    """Fit a filter's parameters by minimising the negative marginal log-likelihood.

    Every iteration filters all (or a random ``batch_size`` subset of the) sequences; with
    ``window`` set it does truncated back-propagation through time: the sequence is cut into
    segments of ``window`` steps, each segment is filtered from the previous one's final belief
    (detached) and gets its own optimiser step.

    Args:
        filter: the module to train (its ``parameters()`` are what ``optimizer`` holds).
        optimizer: any ``torch.optim`` optimiser (``step(closure)`` is used, so LBFGS works).
        window: TBPTT segment length in steps; ``None`` = full sequences.
        clip_grad_norm: clip the total gradient norm to this value (``None`` = no clipping).
        loss_fn: ``loss_fn(filter, belief0, measurements, controls=..., return_final=...)``;
            default :func:`~torchmm.learn.negative_log_likelihood` (``reduction="mean"``).
        track: returns ``{name: value}`` of quantities to record and log each iteration (e.g.
            transition-matrix entries, noise levels).
        logger: object with ``scalar(tag, value, step)``; logs ``<prefix>/loss``,
            ``<prefix>/grad_norm`` and ``<prefix>/param/<name>``.
        callbacks: callables ``callback(trainer, record)`` run after every iteration; one that
            returns ``True`` stops :meth:`fit` after that iteration (early stopping).
        checkpoint_path, checkpoint_every: save a checkpoint every ``checkpoint_every``
            iterations (and at the end of :meth:`fit`) when a path is given.
        prefix: tag prefix for the logger.
        update_first: ``belief0`` of :meth:`fit` is the prior of the first measurement: the first
            segment's step 0 is an update only (``update_first=True`` is passed to ``loss_fn``, which
            must then accept it, as :func:`~torchmm.learn.negative_log_likelihood` does). Later
            TBPTT segments start from the previous segment's posterior and always predict first.
        progress: the default of :meth:`fit`'s ``progress`` (a tqdm bar over the iterations with the
            last loss; None: on a terminal only; a string is the bar's description).

    Shapes:
        :meth:`fit`: ``belief0`` batch ``(N,)`` (or ``(N, ...)``), ``measurements (T, N, ..., m)``,
        ``controls (T, N, ..., k)``; mini-batches index the first batch axis ``N``.

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement, learnable_noise
        >>> motion = learnable_noise(ConstantVelocity(1, q=1.0), "Q", "scale")
        >>> kf = KalmanFilter(motion, PositionMeasurement(2, [0], 1.0))
        >>> trainer = Trainer(kf, torch.optim.Adam(kf.parameters(), lr=0.1))
        >>> history = trainer.fit(GaussianBelief(torch.zeros(8, 2), torch.eye(2)), torch.randn(30, 8, 1), 3)
        >>> [r.iteration for r in history]
        [1, 2, 3]
    """

    @entry_point(filter=Of(nn.Module),
                 optimizer=Of(torch.optim.Optimizer, methods=("step", "zero_grad", "state_dict"),
                              what="a torch.optim optimizer"),
                 window=Int(1, optional=True), clip_grad_norm=Real(positive=True, optional=True),
                 loss_fn=Of(callable_ok=True, optional=True, what="a callable loss_fn(filter, belief0, z)"),
                 track=Of(callable_ok=True, optional=True, what="a callable returning {name: value}"),
                 logger=Of(methods=("scalar",), optional=True, what="an object with scalar(tag, value, i)"),
                 callbacks=Unchecked("any iterable of callables; each is called with (trainer, record)"),
                 checkpoint_path=FilePath(optional=True), checkpoint_every=Int(0), prefix=Text(),
                 update_first=Flag(),
                 progress=Unchecked("None, True, False or the bar's description (any string)"))
    def __init__(
        self,
        filter: nn.Module,
        optimizer: torch.optim.Optimizer,
        *,
        window: int | None = None,
        clip_grad_norm: float | None = None,
        loss_fn: Callable | None = None,
        track: Callable[[], Mapping[str, float]] | None = None,
        logger: Any = None,
        callbacks: Iterable[Callable[[Trainer, TrainRecord], None]] = (),
        checkpoint_path: str | Path | None = None,
        checkpoint_every: int = 0,
        prefix: str = "train",
        update_first: bool = False,
        progress: bool | str | None = None,
    ):
        if progress is not None and not isinstance(progress, (bool, str)):
            raise TypeError(f"progress: expected None, True, False or the bar's description, got {progress!r}")
        if window is not None and int(window) < 1:
            raise ValueError(f"window: must be a positive number of steps, got {window}")
        if clip_grad_norm is not None and not clip_grad_norm > 0:
            raise ValueError(f"clip_grad_norm: must be positive, got {clip_grad_norm}")
        if checkpoint_every < 0:
            raise ValueError(f"checkpoint_every: must be >= 0, got {checkpoint_every}")
        self.filter = filter
        self.optimizer = optimizer
        self.window = None if window is None else int(window)
        self.clip_grad_norm = clip_grad_norm
        self.loss_fn = loss_fn or negative_log_likelihood
        self.track = track
        self.logger = logger
        self.callbacks = list(callbacks)
        self.checkpoint_path = None if checkpoint_path is None else Path(checkpoint_path)
        self.checkpoint_every = int(checkpoint_every)
        self.prefix = prefix
        self.update_first = bool(update_first)
        self.progress = progress
        self.history: list[TrainRecord] = []

    @property
    def iteration(self) -> int:
        return self.history[-1].iteration if self.history else 0

    def _params(self) -> list[Tensor]:
        return [p for group in self.optimizer.param_groups for p in group["params"]]

    def _segment_step(self, belief, z: Tensor, u: Tensor | None,
                      update_first: bool = False) -> tuple[float, float, Any]:
        """One optimiser step on one segment; returns (loss, grad_norm, final belief detached).

        The belief handed on is the one filtered with the parameters before the step (the first
        closure evaluation), as in standard truncated BPTT.
        """
        state: dict[str, Any] = {}
        params = self._params()
        # only when asked, so that a custom loss_fn without the keyword keeps working
        extra = {"update_first": True} if update_first else {}

        def closure():
            self.optimizer.zero_grad()
            loss, final = self.loss_fn(self.filter, belief, z, controls=u, return_final=True, **extra)
            if not bool(torch.isfinite(loss.detach())):
                raise NonFiniteLossError(
                    f"Trainer: the loss went non-finite ({loss.item()}) at iteration {self.iteration + 1}; "
                    + self._diagnosis(params))
            loss.backward()
            max_norm = self.clip_grad_norm if self.clip_grad_norm is not None else math.inf
            norm = torch.nn.utils.clip_grad_norm_(params, max_norm)
            if "loss" not in state:  # the first evaluation: at the parameters before the update
                state.update(loss=loss.item(), grad_norm=float(norm), final=final)
            return loss

        self.optimizer.step(closure)
        if not all(bool(torch.isfinite(p.detach()).all()) for p in params):
            raise NonFiniteLossError(
                f"Trainer: the parameters went non-finite in the update of iteration {self.iteration + 1} "
                f"(loss {state['loss']:.6g} before it); " + self._diagnosis(params))
        return state["loss"], state["grad_norm"], state["final"]

    def _diagnosis(self, params: list[Tensor]) -> str:
        """The rest of the one-line error: the non-finite parameters by name (the filter's
        ``named_parameters``; others as ``param_groups[g][i]``), or that all are finite."""
        names = ({id(p): name for name, p in self.filter.named_parameters()}
                 if isinstance(self.filter, nn.Module) else {})
        bad = []
        for g, group in enumerate(self.optimizer.param_groups):
            for i, p in enumerate(group["params"]):
                if not bool(torch.isfinite(p.detach()).all()):
                    bad.append(repr(names.get(id(p), f"param_groups[{g}][{i}]")))
        if bad:
            shown = ", ".join(bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
            return (f"parameter{'s' if len(bad) > 1 else ''} {shown} "
                    f"{'are' if len(bad) > 1 else 'is'} non-finite; "
                    "lower the learning rate or clip gradients (clip_grad_norm=)")
        return ("every parameter is finite, so the filter diverged at these parameters (e.g. a learning rate "
                "too large, or a model whose outputs overflow); lower the learning rate, clip gradients "
                "(clip_grad_norm=) or bound the model's outputs")

    @entry_point(belief0=BeliefArg(validate=True), measurements=Values(), iterations=Int(0),
                 controls=Values(optional=True), batch_size=Int(1, optional=True), generator=Gen(),
                 progress=Unchecked("None, True, False or the bar's description (any string)"))
    @one_thread_when_small(lambda self, belief0, *args, **kwargs: entries(belief0))
    def fit(self, belief0, measurements: Tensor, iterations: int, *, controls: Tensor | None = None,
            batch_size: int | None = None, generator: torch.Generator | None = None,
            progress: bool | str | None = None) -> list[TrainRecord]:
        """Run ``iterations`` more iterations; returns the records of this call.

        Args:
            belief0: initial belief of every sequence, batch ``(N, ...)`` (a Gaussian belief for
                a multiple-model filter is started with uniform mode probabilities).
            measurements: ``(T, N, ..., m)``, NaN = missing.
            iterations: number of iterations to run now.
            controls: optional ``(T, N, ..., k)``.
            batch_size: sequences per iteration, drawn without replacement with ``generator``;
                default all ``N``.
            generator: randomness of the mini-batches.
            progress: a tqdm bar over the iterations with the last loss; None (default): the
                trainer's ``progress`` (whose default None is: on a terminal only, not in logs, CI or
                notebooks' captured output); a string is its description.
        """
        progress = self.progress if progress is None else progress
        if progress is not None and not isinstance(progress, (bool, str)):
            raise TypeError(f"progress: expected None, True, False or the bar's description, got {progress!r}")
        if iterations < 0:
            raise ValueError(f"iterations: must be >= 0, got {iterations}")
        steps, runs = measurements.shape[0], measurements.shape[1]
        if batch_size is not None and not 0 < batch_size <= runs:
            raise ValueError(f"batch_size: must lie in 1..{runs}, got {batch_size}")
        belief0 = as_start_belief(self.filter, belief0)
        batch = belief0.batch_shape
        if batch_size is not None and len(batch) and batch[0] not in (1, runs):
            raise ValueError(f"belief0: batch shape {tuple(batch)}, but measurements have {runs} sequences "
                             f"(axis 1); with batch_size its first batch axis must be 1 or {runs}")
        segments = truncated_segments(steps, self.window)
        records = []
        bar = tqdm(total=iterations, desc=progress if isinstance(progress, str) else "Trainer.fit", leave=False,
                   disable=None if progress is None else not progress)
        try:
            for _ in range(iterations):
                tic = time.perf_counter()
                if batch_size is None or batch_size == runs:
                    start, z, u = belief0, measurements, controls
                else:
                    index = torch.randperm(runs, generator=generator, device=measurements.device)[:batch_size]
                    start = belief0.expand(runs, *belief0.batch_shape[1:])[index]
                    z = measurements[:, index]
                    u = None if controls is None else controls[:, index]
                total, norm, belief = 0.0, 0.0, start
                for seg in segments:
                    loss, norm, belief = self._segment_step(belief, z[seg], None if u is None else u[seg],
                                                            self.update_first and seg.start == 0)
                    total += loss * (seg.stop - seg.start)
                record = TrainRecord(self.iteration + 1, total / steps, norm,
                                     {k: float(v) for k, v in (self.track() if self.track else {}).items()},
                                     time.perf_counter() - tic)
                self.history.append(record)
                records.append(record)
                self._log(record)
                bar.update(1)
                bar.set_postfix(loss=f"{record.loss:.5g}")  # (a refresh per iteration: they take seconds)
                stop = False
                for callback in self.callbacks:
                    stop = bool(callback(self, record)) or stop
                if self.checkpoint_path is not None and self.checkpoint_every and \
                        record.iteration % self.checkpoint_every == 0:
                    self.save(self.checkpoint_path)
                if stop:
                    break
        finally:
            bar.close()
        if self.checkpoint_path is not None and records:
            self.save(self.checkpoint_path)
        return records

    def _log(self, record: TrainRecord) -> None:
        if self.logger is None:
            return
        self.logger.scalar(f"{self.prefix}/loss", record.loss, record.iteration)
        self.logger.scalar(f"{self.prefix}/grad_norm", record.grad_norm, record.iteration)
        for name, value in record.parameters.items():
            self.logger.scalar(f"{self.prefix}/param/{name}", value, record.iteration)

    # -- checkpoints ---------------------------------------------------------------------------
    def save(self, path) -> Path:
        """Checkpoint the filter, the optimiser and the history."""
        return save_checkpoint(path, self.filter, self.optimizer, history=[asdict(r) for r in self.history])

    def load(self, path) -> None:
        """Restore the filter, the optimiser and the history saved by :meth:`save`."""
        extra = load_checkpoint(path, self.filter, self.optimizer)
        self.history = [TrainRecord(**r) for r in extra.get("history", [])]
