"""Filter banks: ``M`` mode-conditioned filters applied along the last batch axis of a belief.

Two kinds, one interface (and :class:`IndexedBank`, a selection of another bank's modes):

* :class:`VectorizedBank` - one filter whose models carry a mode axis (``F: (M, n, n)`` ...); a single
  call predicts/updates every mode of every run.
* :class:`ListBank` - a list of arbitrary filters (e.g. a KF mode next to a UKF mode); one call per
  *distinct filter*, results stacked on the mode axis.

:func:`make_bank` builds the right one, fusing a list of stackable filters (e.g. Kalman filters
with linear models) into a vectorised bank automatically.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchmm.beliefs import Belief, stack
from torchmm.contract import Indices, Int, Of, entry_point
from torchmm.filters.base import Filter, StepOutput, call_with
from torchmm.linalg import any_observed
from torchmm.validation import broadcast_shape

__all__ = ["FilterBank", "IndexedBank", "ListBank", "VectorizedBank", "make_bank", "motion_reads_inputs"]


class FilterBank(nn.Module):
    """Interface of a bank of ``num_modes`` filters.

    Shapes:
        beliefs have batch ``(*B, M)`` (any leading dims, mode axis last); ``z`` and ``u`` are
        broadcastable to ``(*B, M, m)`` / ``(*B, M, k)`` (pass ``z.unsqueeze(-2)``).
    """

    num_modes: int

    @property
    def meas_dim(self) -> int | None:
        """The measurement dimension every mode filter expects (None if a filter does not say)."""
        return None

    def _first_filter(self) -> Filter | None:
        """A mode filter (the modes of a bank share their measurement); None for a bank without one."""
        return None

    def members(self) -> list[Filter]:
        """The bank's mode filters, each once (a vectorised bank's one filter; none for a bank without)."""
        return []

    @property
    def measurement_rank(self) -> int:
        """The trailing axes of one measurement of the mode filters (:attr:`Filter.measurement_rank`)."""
        first = self._first_filter()
        return 1 if first is None else first.measurement_rank

    def informative(self, z: Tensor) -> Tensor:
        """``(*B,)`` bool: where ``z`` informs the modes (:meth:`Filter.informative` of a mode filter)."""
        first = self._first_filter()
        return any_observed(z) if first is None else first.informative(z)

    def check_measurements(self, measurements: Tensor, batch: torch.Size, name: str = "measurements", *,
                           time: bool = True) -> None:
        """A mode filter's :meth:`~torchmm.filters.Filter.check_measurements` (the modes share their
        measurement), with the combinator's batch ``(*B,)`` (without the mode axis)."""
        first = self._first_filter()
        if first is not None:
            first.check_measurements(measurements, batch, name, time=time)

    @property
    def state_dim(self) -> int | None:
        """The state dimension the modes share (None if a filter does not say)."""
        return None

    @property
    def uses_generator(self) -> bool:
        """Whether a mode filter draws random numbers (then ``generator=`` is passed to it)."""
        return False

    def with_sensor(self, sensor) -> FilterBank:
        """This bank with every mode filter's sensor replaced (:meth:`~torchmm.filters.Filter.with_sensor`)."""
        raise NotImplementedError(f"{type(self).__name__} cannot replace its sensor")

    def with_motion(self, motion) -> FilterBank:
        """This bank with the motion models replaced (a mode bank model; a list bank: one per mode)."""
        raise NotImplementedError(f"{type(self).__name__} cannot replace its motion models")

    def initial_belief(self, belief, *, generator=None):
        """Every mode filter's belief at time 0 from ``belief`` with batch ``(*B, M)`` (e.g. a
        particle filter samples its particles; a Kalman filter keeps the Gaussian)."""
        return belief

    def predict(self, belief, *, u: Tensor | None = None, motion=None, generator=None):
        """Every mode's time update; ``motion`` replaces the models for this call (a mode bank model,
        or for a :class:`ListBank` one model per mode)."""
        raise NotImplementedError

    def update(self, belief, z: Tensor, *, sensor=None, generator=None) -> StepOutput:
        """Every mode's measurement update; ``sensor`` replaces the measurement model for this call."""
        raise NotImplementedError

    def update_each(self, belief, zs: Tensor) -> StepOutput:
        """Every mode's update by each of ``D`` measurements (:meth:`Filter.update_each`): belief batch
        ``(*B, M)``, zs ``(D, *B, M, m)`` (broadcasting) -> batch ``(D, *B, M)``. The default repeats the
        prior."""
        return self.update(belief.unsqueeze(0).expand(zs.shape[0], *belief.batch_shape), zs)


class VectorizedBank(FilterBank):
    """A single filter whose model parameters broadcast over the mode axis (batch ``(M,)``)."""

    @entry_point(filter=Of(Filter), num_modes=Int(1))
    def __init__(self, filter: Filter, num_modes: int):
        super().__init__()
        if not isinstance(filter, Filter):
            raise TypeError(f"bank: expected a Filter, got {type(filter).__name__}")
        filter.check_bank_member("bank", num_modes)
        shape = getattr(filter, "param_batch_shape", None)
        if shape is not None and len(shape) and tuple(shape) not in {(1,), (num_modes,)}:
            raise ValueError(
                f"bank: model parameter batch {tuple(shape)} does not match {num_modes} modes "
                f"(expected () or ({num_modes},))"
            )
        self.filter = filter
        self.num_modes = num_modes

    @property
    def meas_dim(self) -> int | None:
        return getattr(self.filter, "meas_dim", None)

    def _first_filter(self) -> Filter:
        return self.filter

    def members(self) -> list[Filter]:
        return [self.filter]

    @property
    def state_dim(self) -> int | None:
        return getattr(self.filter, "state_dim", None)

    @property
    def uses_generator(self) -> bool:
        return bool(getattr(self.filter, "uses_generator", False))

    def linear_gaussian(self):
        """The filter's description for the linear-Gaussian kernel (its parameters' batch is ``()`` or
        the modes'), or the reason there is none."""
        describe = getattr(self.filter, "linear_gaussian", None)
        return describe() if describe is not None else f"{type(self.filter).__name__} is not linear-Gaussian"

    def nonlinear_gaussian(self):
        """The filter's description for the nonlinear-Gaussian kernel (:mod:`torchmm.kernels.nonlinear`),
        or the reason there is none."""
        describe = getattr(self.filter, "nonlinear_gaussian", None)
        return describe() if describe is not None else f"{type(self.filter).__name__} is not nonlinear-Gaussian"

    def with_sensor(self, sensor) -> VectorizedBank:
        f = self.filter.with_sensor(sensor)
        return self if f is self.filter else VectorizedBank(f, self.num_modes)

    def with_motion(self, motion) -> VectorizedBank:
        if isinstance(motion, (list, tuple)):  # one model per mode, as for a list bank: stacked (once per list)
            motion = self._stacked(motion)
        f = self.filter.with_motion(motion)
        return self if f is self.filter else VectorizedBank(f, self.num_modes)

    def _stacked(self, models):
        cache = self.__dict__.setdefault("_stacked_models", {})
        hit = cache.get(id(models))
        if hit is None or hit[0] is not models:
            stack = getattr(type(getattr(self.filter, "motion", None)), "stack", None)
            if stack is None or len(models) != self.num_modes:
                raise TypeError(f"motion: expected a mode-bank model or {self.num_modes} stackable models, "
                                f"got a list of {len(models)}")
            hit = cache[id(models)] = (models, stack(list(models)))
        return hit[1]

    def initial_belief(self, belief, *, generator=None):
        if type(self.filter).initial_belief is Filter.initial_belief:
            return belief  # the prior is the mode filters' belief (validated by the combinator)
        return call_with(self.filter, "initial_belief", belief, generator=generator)

    def predict(self, belief, *, u: Tensor | None = None, motion=None, generator=None):
        if isinstance(motion, (list, tuple)):
            motion = self._stacked(motion)
        f = self.filter if motion is None else self.filter.with_motion(motion)
        if generator is None:  # the common case, without the dispatch
            return f.predict(belief, u=u)
        return call_with(f, "predict", belief, u=u, generator=generator)

    def update(self, belief, z: Tensor, *, sensor=None, generator=None) -> StepOutput:
        f = self.filter if sensor is None else self.filter.with_sensor(sensor)
        if generator is None:
            return f.update(belief, z)
        return call_with(f, "update", belief, z, generator=generator)

    def update_each(self, belief, zs: Tensor) -> StepOutput:
        return self.filter.update_each(belief, zs)


class ListBank(FilterBank):
    """Heterogeneous filters, mode ``j`` handled by ``filters[j]`` (one call per filter)."""

    @entry_point(filters=Of((list, tuple), what="a list of filters"))
    def __init__(self, filters: Sequence[Filter]):
        super().__init__()
        filters = list(filters)
        if not filters:
            raise ValueError("bank: needs at least one filter")
        for j, f in enumerate(filters):
            if not isinstance(f, Filter):
                raise TypeError(f"bank[{j}]: expected a Filter, got {type(f).__name__}")
            f.check_bank_member(f"bank[{j}]", len(filters))
        for attr in ("state_dim", "meas_dim", "measurement_rank"):
            dims = [getattr(f, attr, None) for f in filters]
            if len({d for d in dims if d is not None}) > 1:
                hint = (" (modes with different state dimensions: wrap each in torchmm.multimodel.Embedded, "
                        "which maps it into a common state space, docs/architecture.md)" if attr == "state_dim" else "")
                raise ValueError(f"bank: the mode filters have different {attr}s {dims}; the modes of one bank "
                                 f"share the state and the measurement{hint}")
        self.filters = nn.ModuleList(filters)
        self.num_modes = len(self.filters)

    @property
    def meas_dim(self) -> int | None:
        return getattr(self.filters[0], "meas_dim", None)

    def _first_filter(self) -> Filter:
        return self.filters[0]

    def members(self) -> list[Filter]:
        return list(self.filters)

    @property
    def state_dim(self) -> int | None:
        return getattr(self.filters[0], "state_dim", None)

    @property
    def uses_generator(self) -> bool:
        return any(getattr(f, "uses_generator", False) for f in self.filters)

    def _members(self, models, replace: str, name: str) -> list[Filter]:
        """The mode filters, with ``models`` (one for all, or a sequence of one per mode) swapped in."""
        if models is None:
            return list(self.filters)
        if isinstance(models, Sequence):
            if len(models) != self.num_modes:
                raise ValueError(f"{name}: expected one model per mode ({self.num_modes}), got {len(models)}")
            return [getattr(f, replace)(m) for f, m in zip(self.filters, models)]
        return [getattr(f, replace)(models) for f in self.filters]

    def linear_gaussian(self):
        """The members' descriptions for the linear-Gaussian kernel, stacked over the modes
        (differentiable: learnable members keep their gradients), or the reason there is none."""
        models = []
        for j, member in enumerate(self.filters):
            describe = getattr(member, "linear_gaussian", None)
            model = describe() if describe is not None else f"{type(member).__name__} is not linear-Gaussian"
            if isinstance(model, str):
                return f"mode {j}: {model}"
            if model.G is not None:
                return f"mode {j}: a control input (input_matrix) in a list bank"
            models.append(model)
        events = (2, 1, 2, 2, 2)  # F, b, Q, H, R
        fields = []
        for parts, event in zip(zip(*(tuple(m)[:5] for m in models)), events):
            if any(p.dim() != event for p in parts) or len({p.shape for p in parts}) > 1:
                return "the modes' matrices are batched or differ in shape"
            fields.append(torch.stack(parts))
        return type(models[0])(*fields)

    def with_sensor(self, sensor) -> ListBank:
        return ListBank(self._members(sensor, "with_sensor", "sensor"))

    def with_motion(self, motion) -> ListBank:
        return ListBank(self._members(motion, "with_motion", "motion"))

    def initial_belief(self, belief, *, generator=None):
        if all(type(f).initial_belief is Filter.initial_belief for f in self.filters):
            return belief
        starts = [f.initial_belief(belief.select(-1, j)) if type(f).initial_belief is Filter.initial_belief
                  else call_with(f, "initial_belief", belief.select(-1, j), generator=generator)
                  for j, f in enumerate(self.filters)]
        return stack(starts, dim=-1)

    def predict(self, belief, *, u: Tensor | None = None, motion=None, generator=None):
        priors = [
            call_with(f, "predict", belief.select(-1, j), u=None if u is None else _select_mode(u, j),
                      generator=generator)
            for j, f in enumerate(self._members(motion, "with_motion", "motion"))
        ]
        return stack(priors, dim=-1)

    def update(self, belief, z: Tensor, *, sensor=None, generator=None) -> StepOutput:
        members = self._members(sensor, "with_sensor", "sensor")
        outs = [call_with(f, "update", belief.select(-1, j), _select_mode(z, j), generator=generator)
                for j, f in enumerate(members)]
        log_likelihood = torch.stack([o.log_likelihood for o in outs], dim=-1)
        return StepOutput(
            belief=stack([o.belief for o in outs], dim=-1),
            prior=belief,
            log_likelihood=log_likelihood,
            innovation=_stack_optional([o.innovation for o in outs], event=1),
            innovation_cov=_stack_optional([o.innovation_cov for o in outs], event=2),
            extras=_stack_extras([o.extras for o in outs], log_likelihood.dim() - 1),
        )


class IndexedBank(FilterBank):
    """The modes ``index`` of another bank, repeats allowed: mode ``i`` of this bank is mode
    ``index[i]`` of ``bank`` (e.g. VSIMM's fixed modes plus one more copy of the CV mode).

    Works for any bank: the components are laid out in rounds of at most one slot per mode of
    ``bank`` (a mode listed ``r`` times costs ``r`` rounds, each one batched call of ``bank``).

    Shapes:
        beliefs with batch ``(*B, K)``, ``K = len(index)``; ``z``/``u`` broadcastable to
        ``(*B, K, m)`` / ``(*B, K, k)`` (a size-1 mode axis, as ``z.unsqueeze(-2)``).
    """

    @entry_point(bank=Of(FilterBank), index=Indices())
    def __init__(self, bank: FilterBank, index: Sequence[int]):
        super().__init__()
        index = [int(i) for i in index]
        if not index or not all(0 <= i < bank.num_modes for i in index):
            raise ValueError(f"index: expected mode indices in [0, {bank.num_modes}), got {index}")
        self.bank, self.index, self.num_modes = bank, index, len(index)
        rounds: list[dict[int, int]] = []  # round -> {mode of bank: slot of this bank}
        for slot, mode in enumerate(index):
            for r in rounds:
                if mode not in r:
                    r[mode] = slot
                    break
            else:
                rounds.append({mode: slot})
        M = bank.num_modes
        # per round, the slot each bank mode reads (an unused mode reads the round's first slot)
        self._gather = [torch.tensor([r.get(j, next(iter(r.values()))) for j in range(M)]) for r in rounds]
        # slot i of the result is entry round * M + index[i] of the rounds laid end to end
        position = {}
        for r_i, r in enumerate(rounds):
            for mode, slot in r.items():
                position[slot] = r_i * M + mode
        self._scatter = torch.tensor([position[i] for i in range(len(index))])

    @property
    def meas_dim(self) -> int | None:
        return self.bank.meas_dim

    def _first_filter(self) -> Filter | None:
        return self.bank._first_filter()

    def members(self) -> list[Filter]:
        return self.bank.members()

    @property
    def state_dim(self) -> int | None:
        return self.bank.state_dim

    @property
    def uses_generator(self) -> bool:
        return self.bank.uses_generator

    def _rounds(self, belief, value: Tensor | None, event: int):
        for gather in self._gather:
            g = gather.to(belief.device)
            comps = belief.map_tensors(lambda t, e: t.index_select(t.dim() - e - 1, g)
                                       if t.shape[t.dim() - e - 1] > 1 else t)
            v = value
            if value is not None and value.shape[-1 - event] > 1:
                v = value.index_select(value.dim() - event - 1, g)
            yield comps, v

    def _assemble(self, parts: list, batch_dim: int):
        """Concatenate per-round results on the mode axis (left-indexed ``batch_dim - 1``) and pick the slots."""
        first = parts[0]
        if first is None:
            return None
        axis = batch_dim - 1
        scatter = self._scatter
        if isinstance(first, Tensor):
            if first.dim() < batch_dim or any(p.shape[axis] != self.bank.num_modes for p in parts):
                return None
            full = torch.cat(parts, dim=axis)
            return full.index_select(axis, scatter.to(full.device))
        if isinstance(first, dict):
            out = {}
            for key in first:
                value = self._assemble([p.get(key) for p in parts], batch_dim)
                if value is not None:
                    out[key] = value
            return out
        if isinstance(first, Belief):
            from torchmm.beliefs import cat

            full = cat(parts, dim=-1)
            return full.map_tensors(lambda t, e: t.index_select(t.dim() - e - 1, scatter.to(t.device)))
        return None

    def predict(self, belief, *, u: Tensor | None = None, motion=None, generator=None):
        parts = [self.bank.predict(c, u=v, motion=motion, generator=generator) for c, v in self._rounds(belief, u, 1)]
        return self._assemble(parts, belief.batch_dim)

    def update(self, belief, z: Tensor, *, sensor=None, generator=None) -> StepOutput:
        outs = [self.bank.update(c, v, sensor=sensor, generator=generator) for c, v in self._rounds(belief, z, 1)]
        bd = belief.batch_dim
        return StepOutput(
            belief=self._assemble([o.belief for o in outs], bd),
            prior=belief,
            log_likelihood=self._assemble([o.log_likelihood for o in outs], bd),
            innovation=self._assemble([o.innovation for o in outs], bd),
            innovation_cov=self._assemble([o.innovation_cov for o in outs], bd),
            extras=self._assemble([o.extras or {} for o in outs], bd) or None,
        )


def _select_mode(value: Tensor, j: int) -> Tensor:
    """Pick mode ``j`` from a tensor whose mode axis (size 1 or M) sits just left of the event."""
    return value.select(-2, 0 if value.shape[-2] == 1 else j)


def _stack_extras(extras, axis: int) -> dict | None:
    """The mode filters' diagnostics, stacked on the mode axis: every key that all of them report as
    a tensor (e.g. ``singular``); a key only some of them report (a particle filter's ``ess`` beside a
    Kalman mode) is kept per mode as ``extras["by_mode"][j]``."""
    if not any(extras):
        return None
    present = [e or {} for e in extras]
    keys = [k for k in present[0] if all(isinstance(e.get(k), Tensor) for e in present)]
    out = {}
    for key in keys:
        values = [e[key] for e in present]
        try:
            shape = broadcast_shape(*[v.shape for v in values])
        except RuntimeError:
            continue  # e.g. per-mode tensors of different sizes: not stackable
        out[key] = torch.stack([v.expand(shape) for v in values], dim=axis)
    if any(set(e) - set(out) for e in present):
        out["by_mode"] = present  # the rest, as each mode filter reported it
    return out or None


def _stack_optional(values, event: int):
    if any(v is None for v in values):
        return None
    shape = broadcast_shape(*[v.shape for v in values])
    return torch.stack([v.expand(shape) for v in values], dim=-1 - event)


@entry_point(bank=Of((Filter, FilterBank, list, tuple), what="a Filter, a list of filters or a FilterBank"),
             num_modes=Int(1))
def make_bank(bank, num_modes: int) -> FilterBank:
    """Build a :class:`FilterBank` for ``num_modes`` modes.

    Args:
        bank: a :class:`FilterBank`; a single :class:`Filter` whose models are banks (vectorised);
            or a sequence of ``num_modes`` filters. A sequence of filters of one class that
            provides ``stack`` (e.g. :class:`~torchmm.filters.KalmanFilter`) and holds no
            ``nn.Parameter`` is fused into a vectorised bank; otherwise (heterogeneous filters,
            learned models) it becomes a :class:`ListBank`, which keeps every mode's own module.
    """
    if num_modes < 1:
        raise ValueError(f"transition: needs at least one mode, got {num_modes}")
    if isinstance(bank, FilterBank):
        if bank.num_modes != num_modes:
            raise ValueError(f"bank: has {bank.num_modes} modes, the transition matrix {num_modes}")
        return bank
    if isinstance(bank, Filter):
        return VectorizedBank(bank, num_modes)
    if isinstance(bank, Sequence) and not isinstance(bank, str):
        for j, f in enumerate(bank):
            if not isinstance(f, Filter):
                raise TypeError(f"bank[{j}]: expected a Filter, got {type(f).__name__}")
        if len(bank) != num_modes:
            raise ValueError(f"bank: has {len(bank)} filters, the transition matrix {num_modes} modes")
        kinds = {type(f) for f in bank}
        # Fusing copies the models' current tensors into new stacked ones, which would cut learnable
        # parameters (nn.Parameters, parametrised noise) off from the bank: keep those as a list.
        learnable = any(True for f in bank for _ in f.parameters())
        if len(kinds) == 1 and hasattr(type(bank[0]), "stack") and not learnable:
            try:
                return VectorizedBank(type(bank[0]).stack(list(bank)), num_modes)
            except ValueError:
                pass  # e.g. different state dims or options: fall back to a list bank
        return ListBank(bank)
    raise TypeError(f"bank: expected a Filter, a sequence of Filters or a FilterBank, got {type(bank).__name__}")


def motion_reads_inputs(bank: FilterBank, motion=None) -> bool:
    """Whether the mode filters' motion models (``motion``: the step's, where given) read controls ``u``:
    False only where every one is a linear motion without ``input_matrix``
    (:class:`~torchmm.models.LinearMotion`); other models may read them (tests/multimodel/test_imm.py)."""
    if motion is not None:
        motions = list(motion) if isinstance(motion, (list, tuple)) else [motion]
    else:
        motions = [getattr(f, "motion", None) for f in bank.members()] or [None]
    return not all(m is not None and hasattr(m, "input_matrix") and m.input_matrix is None for m in motions)
