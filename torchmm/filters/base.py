"""The filter interface shared by every single- and multiple-model filter."""

from __future__ import annotations

from typing import Any, NamedTuple

from torch import Tensor, nn

__all__ = ["Filter", "StepOutput"]


class StepOutput(NamedTuple):
    """What every ``update``/``step`` returns.

    Attributes:
        belief: the posterior belief, batch ``(*B,)``.
        prior: the predicted belief the update started from, batch ``(*B,)``.
        log_likelihood: ``log p(z_k | z_{1:k-1})``, ``(*B,)``; exactly 0 where ``z_k`` is
            entirely missing (every component non-finite: NaN or ``+-inf``).
        innovation: ``z_k - E[z_k | z_{1:k-1}]``, ``(*B, m)`` (``(*B, M, m)`` per mode for
            multiple-model filters); non-finite where the measurement is missing.
        innovation_cov: its covariance ``S``, ``(*B, m, m)`` (per mode likewise).
        extras: filter-specific diagnostics (e.g. ``"mixed"`` beliefs of the IMM,
            ``"singular"`` flags of regularised innovation covariances, docs/robustness.md); a
            dict of tensors/beliefs with batch ``(*B, ...)``.
    """

    belief: Any
    prior: Any
    log_likelihood: Tensor
    innovation: Tensor | None = None
    innovation_cov: Tensor | None = None
    extras: dict | None = None


class Filter(nn.Module):
    """Stateless recursive filter: belief in, belief out.

    The module holds models and options only; nothing changes between calls, so one filter can
    serve any number of independent batches. Subclasses implement :meth:`predict` and
    :meth:`update`; :meth:`step` is predict-then-update.
    """

    @property
    def state_dim(self) -> int | None:
        """The state dimension ``n`` of the filter's motion model (None if it has none)."""
        return getattr(self._modules.get("motion"), "state_dim", None)

    @property
    def meas_dim(self) -> int | None:
        """The measurement dimension ``m`` of the filter's sensor (None if it has none)."""
        return getattr(self._modules.get("measurement"), "meas_dim", None)

    def predict(self, belief: Any, *, u: Tensor | None = None) -> Any:
        """Time update. Returns the prior belief for the next measurement."""
        raise NotImplementedError

    def check_bank_member(self, name: str, num_modes: int) -> None:
        """Raise if this filter, as configured, cannot be a mode filter of a bank of ``num_modes``.

        Called by the banks of IMM / GPB at construction (``name`` is the argument to blame). The
        default accepts; e.g. a :class:`~torchmm.filters.ParticleFilter` needs a fixed
        ``num_particles`` when ``num_modes > 1`` because mixing merges the particle sets.
        """

    def update(self, belief: Any, z: Any) -> StepOutput:
        """Measurement update of a prior ``belief`` with ``z`` (NaN = missing)."""
        raise NotImplementedError

    def step(self, belief: Any, z: Any, *, u: Tensor | None = None) -> StepOutput:
        """One predict/update cycle from the posterior at ``k-1`` to the posterior at ``k``."""
        return self.update(self.predict(belief, u=u), z)

    def forward(self, belief: Any, z: Any, *, u: Tensor | None = None) -> StepOutput:
        return self.step(belief, z, u=u)
