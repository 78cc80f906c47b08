r"""Banks whose modes have different state dimensions: each mode filter seen from a common space.

The textbook IMM mixes a constant-velocity mode (state ``[x, vx, y, vy]``) with a
constant-acceleration mode (``[x, vx, ax, y, vy, ay]``). Mixing needs one space, so every mode's
belief is kept in the *common* state space (here the CA one) and :class:`Embedded` maps it to the
mode's own space and back:

* **project** ``x_j = x[index]``, ``P_j = P[index][:, index]``: the mode filter predicts and
  updates in its own space;
* **embed** the result back: its components at ``index``; the components the mode does not model
  set to ``fill_mean`` with variance ``fill_cov`` and no correlation with the modelled ones.

With the default fill (mean 0, variance 0) the CV mode is the CA model with its acceleration held
at zero, the classical reading (Bar-Shalom, Li and Kirubarajan 2001, section 11.6.6): a mode
posterior that enters the CA mode's mixture brings zero acceleration, with the spread of the
mixture carrying the disagreement. The mixing itself is the unchanged IMM / GPB interaction.

Examples:
    >>> from torchmm import IMM, ConstantAcceleration, ConstantVelocity, KalmanFilter, PositionMeasurement
    >>> cv = KalmanFilter(ConstantVelocity(2, q=0.1), PositionMeasurement(4, [0, 2], 1.0))
    >>> ca = KalmanFilter(ConstantAcceleration(2, q=0.1), PositionMeasurement(6, [0, 3], 1.0))
    >>> imm = IMM([Embedded(cv, kinematic_index(2, 3, ndim=2), 6), ca], torch.tensor([[0.95, 0.05], [0.05, 0.95]]))
    >>> belief = imm.initial_belief(GaussianBelief(torch.zeros(5, 6), torch.eye(6)))
    >>> imm.step(belief, torch.randn(5, 2)).belief.estimate().mean.shape
    torch.Size([5, 6])
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchmm.contract import Finite, Indices, Int, Of, entry_point
from torchmm.beliefs import GaussianBelief
from torchmm.filters.base import Filter, StepOutput, call_with
from torchmm.validation import as_tensor, check_shape, gaussian_batch

__all__ = ["Embedded", "kinematic_index"]


@entry_point(order=Int(1), common_order=Int(1), ndim=Int(1))
def kinematic_index(order: int, common_order: int, *, ndim: int = 1) -> list[int]:
    """Positions of a per-axis kinematic state of ``order`` derivatives inside one of
    ``common_order`` (torchmm's layout: per axis, position first).

    Examples:
        >>> kinematic_index(2, 3, ndim=2)  # [x, vx, y, vy] inside [x, vx, ax, y, vy, ay]
        [0, 1, 3, 4]
    """
    if not 1 <= order <= common_order:
        raise ValueError(f"order: expected 1 <= order <= common_order ({common_order}), got {order}")
    return [axis * common_order + i for axis in range(ndim) for i in range(order)]


class Embedded(Filter):
    """A mode filter over a sub-state of a common state space (see the module docstring).

    Args:
        filter: the mode filter, in its own state space of dimension ``n`` (Gaussian beliefs).
        index: the ``n`` positions of its state components in the common state (distinct).
        common_dim: ``N``, the common state dimension.
        fill_mean: ``(N,)`` values of the components the mode does not model (default 0);
            only the entries outside ``index`` are used.
        fill_cov: ``(N,)`` their variances (default 0).

    Shapes:
        belief: :class:`~torchmm.beliefs.GaussianBelief` with ``mean (*B, N)``; ``z (*B, m)``; the
        step's ``innovation`` and ``extras`` are the mode filter's.
    """

    @entry_point(filter=Of(Filter), index=Indices(), common_dim=Int(1),
                 fill_mean=Finite(optional=True, check=False), fill_cov=Finite(optional=True, check=False))
    def __init__(self, filter: Filter, index: Sequence[int], common_dim: int, *, fill_mean=None, fill_cov=None):
        super().__init__()
        index = [int(i) for i in index]
        n = filter.state_dim
        if n is not None and len(index) != n:
            raise ValueError(f"index: the filter's state has {n} components, index lists {len(index)}")
        if len(set(index)) != len(index) or min(index, default=0) < 0:
            raise ValueError(f"index: expected distinct non-negative positions, got {index}")
        N = int(common_dim)
        if max(index) >= N:
            raise ValueError(f"common_dim: {N} is smaller than the largest position in index ({max(index)})")
        self.filter, self.index, self.common_dim = filter, index, N
        dtype = torch.get_default_dtype()
        for name, value in (("fill_mean", fill_mean), ("fill_cov", fill_cov)):
            t = torch.zeros(N, dtype=dtype) if value is None else as_tensor(value, name)
            check_shape(t, name, (N,))
            if name == "fill_cov" and bool((t < 0).any()):
                raise ValueError("fill_cov: variances must be non-negative")
            self.register_buffer(name, t)
        self.register_buffer("_index", torch.tensor(index), persistent=False)
        free = torch.ones(N, dtype=torch.bool)
        free[index] = False
        self.register_buffer("_free", free, persistent=False)

    @property
    def state_dim(self) -> int:
        return self.common_dim

    @property
    def meas_dim(self) -> int | None:
        return self.filter.meas_dim

    @property
    def uses_generator(self) -> bool:
        return self.filter.uses_generator

    def check_bank_member(self, name: str, num_modes: int) -> None:
        self.filter.check_bank_member(name, num_modes)

    def with_sensor(self, sensor):
        return self._wrap(self.filter.with_sensor(sensor))

    def with_motion(self, motion):
        return self._wrap(self.filter.with_motion(motion))

    def _wrap(self, inner: Filter) -> Embedded:
        if inner is self.filter:
            return self
        clone = Embedded.__new__(Embedded)
        clone.__dict__.update(self.__dict__)
        clone.__dict__["_modules"] = {**self._modules, "filter": inner}
        return clone

    def project(self, belief: GaussianBelief) -> GaussianBelief:
        """The mode's own components: ``(*B, N) -> (*B, n)``."""
        gaussian_batch(belief, self.common_dim)
        idx = self._index
        return GaussianBelief(belief.mean.index_select(-1, idx), belief.cov.index_select(-1, idx).index_select(-2, idx))

    def embed(self, belief: GaussianBelief) -> GaussianBelief:
        """Back to the common space, unmodelled components filled: ``(*B, n) -> (*B, N)``."""
        batch, N, idx = belief.batch_shape, self.common_dim, self._index
        like = belief.mean
        mean = self.fill_mean.to(like.dtype).expand(*batch, N).index_copy(-1, idx, like)
        free = self.fill_cov.to(like.dtype) * self._free
        cov = torch.diag_embed(free).expand(*batch, N, N)
        block = torch.zeros(*batch, len(self.index), N, dtype=like.dtype, device=like.device)
        block = block.index_copy(-1, idx, belief.cov)
        cov = cov.index_copy(-2, idx, block)
        return GaussianBelief(mean, cov)

    def initial_belief(self, belief, **kwargs):
        return self.embed(call_with(self.filter, "initial_belief", self.project(belief.validate("belief")), **kwargs))

    def predict(self, belief: GaussianBelief, *, u: Tensor | None = None, generator=None) -> GaussianBelief:
        return self.embed(call_with(self.filter, "predict", self.project(belief), u=u, generator=generator))

    def update(self, belief: GaussianBelief, z: Tensor, *, generator=None) -> StepOutput:
        out = call_with(self.filter, "update", self.project(belief), z, generator=generator)
        return out._replace(belief=self.embed(out.belief), prior=belief)
