"""Filter banks: ``M`` mode-conditioned filters applied along the last batch axis of a belief.

Two kinds, one interface:

* :class:`VectorizedBank` - one filter whose models carry a mode axis (``F: (M, n, n)`` ...);
  a single call predicts/updates every mode of every run.
* :class:`ListBank` - a list of arbitrary filters (e.g. a KF mode next to a UKF mode); one call
  per *distinct filter*, results stacked on the mode axis.

:func:`make_bank` builds the right one, fusing a list of stackable filters (e.g. Kalman filters
with linear models) into a vectorised bank automatically.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchmm.beliefs import stack
from torchmm.filters.base import Filter, StepOutput
from torchmm.validation import broadcast_shape

__all__ = ["FilterBank", "ListBank", "VectorizedBank", "make_bank"]


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

    def predict(self, belief, *, u: Tensor | None = None):
        raise NotImplementedError

    def update(self, belief, z: Tensor) -> StepOutput:
        raise NotImplementedError


class VectorizedBank(FilterBank):
    """A single filter whose model parameters broadcast over the mode axis (batch ``(M,)``)."""

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

    def predict(self, belief, *, u: Tensor | None = None):
        return self.filter.predict(belief, u=u)

    def update(self, belief, z: Tensor) -> StepOutput:
        return self.filter.update(belief, z)


class ListBank(FilterBank):
    """Heterogeneous filters, mode ``j`` handled by ``filters[j]`` (one call per filter)."""

    def __init__(self, filters: Sequence[Filter]):
        super().__init__()
        filters = list(filters)
        if not filters:
            raise ValueError("bank: needs at least one filter")
        for j, f in enumerate(filters):
            if not isinstance(f, Filter):
                raise TypeError(f"bank[{j}]: expected a Filter, got {type(f).__name__}")
            f.check_bank_member(f"bank[{j}]", len(filters))
        for attr in ("state_dim", "meas_dim"):
            dims = [getattr(f, attr, None) for f in filters]
            if len({d for d in dims if d is not None}) > 1:
                raise ValueError(f"bank: the mode filters have different {attr}s {dims}; the modes of one bank "
                                 "share the state and the measurement")
        self.filters = nn.ModuleList(filters)
        self.num_modes = len(self.filters)

    @property
    def meas_dim(self) -> int | None:
        return getattr(self.filters[0], "meas_dim", None)

    def predict(self, belief, *, u: Tensor | None = None):
        priors = [
            f.predict(belief.select(-1, j), u=None if u is None else _select_mode(u, j))
            for j, f in enumerate(self.filters)
        ]
        return stack(priors, dim=-1)

    def update(self, belief, z: Tensor) -> StepOutput:
        outs = [f.update(belief.select(-1, j), _select_mode(z, j)) for j, f in enumerate(self.filters)]
        log_likelihood = torch.stack([o.log_likelihood for o in outs], dim=-1)
        return StepOutput(
            belief=stack([o.belief for o in outs], dim=-1),
            prior=belief,
            log_likelihood=log_likelihood,
            innovation=_stack_optional([o.innovation for o in outs], event=1),
            innovation_cov=_stack_optional([o.innovation_cov for o in outs], event=2),
            extras=_stack_extras([o.extras for o in outs], log_likelihood.dim() - 1),
        )


def _select_mode(value: Tensor, j: int) -> Tensor:
    """Pick mode ``j`` from a tensor whose mode axis (size 1 or M) sits just left of the event."""
    return value.select(-2, 0 if value.shape[-2] == 1 else j)


def _stack_extras(extras, axis: int) -> dict | None:
    """The mode filters' diagnostics that every filter reports as a tensor, stacked on the mode axis."""
    if not all(extras):
        return None
    keys = [k for k in extras[0] if all(isinstance(e.get(k), Tensor) for e in extras)]
    out = {}
    for key in keys:
        values = [e[key] for e in extras]
        try:
            shape = broadcast_shape(*[v.shape for v in values])
        except RuntimeError:
            continue  # e.g. per-mode tensors of different sizes: not stackable
        out[key] = torch.stack([v.expand(shape) for v in values], dim=axis)
    return out or None


def _stack_optional(values, event: int):
    if any(v is None for v in values):
        return None
    shape = torch.broadcast_shapes(*[v.shape for v in values])
    return torch.stack([v.expand(shape) for v in values], dim=-1 - event)


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
    raise TypeError(
        f"bank: expected a Filter, a sequence of Filters or a FilterBank, got {type(bank).__name__}"
    )
