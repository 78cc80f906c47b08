"""What the multi-rate estimators share: the target/source streams and the mode filters' models.

Paper 000's estimators (:mod:`.transfer`: IMM-TF, IF-TF; :mod:`.source_baselines`: IMM-SU, IMM-FU,
VSIMM) run over any bank; these helpers reach each mode's motion and sensor models (one call for a
vectorised bank, one per filter for a list bank) and check the two measurement streams.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from torchmm.beliefs import Belief, GaussianBelief
from torchmm.models.base import MeasurementModel
from torchmm.models.streams import MultiRate, split_streams
from torchmm.multimodel.bank import FilterBank, ListBank, VectorizedBank
from torchmm.multimodel.imm import IMM, mode_batch
from torchmm.validation import check_measurement

__all__ = ["bank_members", "check_source_sensor", "gaussian_moments", "member_models", "mode_param",
           "multirate_streams", "per_mode", "split_streams"]


def multirate_streams(imm: IMM, belief, z: Any, source: MeasurementModel) -> tuple[Tensor, Tensor]:
    """The target and source data of one step, shape-checked (``z.target`` against the bank's
    sensor, ``z.source`` against ``source``, both against the belief's batch)."""
    y, ys = split_streams(z)
    target_belief = getattr(belief, "target", belief)  # a SourceTrackBelief's target side
    y = imm._measurement(target_belief, y, "z.target")
    ys = check_measurement(ys, source.meas_dim, mode_batch(target_belief), target_belief.mode_log_probs,
                           "z.source")
    return y, ys


def check_source_sensor(source, state_dim: int) -> MeasurementModel:
    if not isinstance(source, MeasurementModel):
        raise TypeError(f"source: expected a MeasurementModel (the source sensor), got {type(source).__name__}")
    if source.state_dim != state_dim:
        raise ValueError(f"source: state_dim {source.state_dim} differs from the bank's {state_dim}")
    return source


def bank_members(bank: FilterBank, who: str) -> list:
    """``[(filter, mode)]``: the filter computing each mode of ``bank`` and that mode's index in its
    models' parameter batch (``None`` for a list bank's unbatched filters)."""
    if isinstance(bank, VectorizedBank):
        return [(bank.filter, j) for j in range(bank.num_modes)]
    if isinstance(bank, ListBank):
        return [(f, None) for f in bank.filters]
    raise ValueError(f"bank: {who} needs a vectorised or list bank of filters with motion and measurement "
                     f"models, got {type(bank).__name__}")


def member_models(filter, who: str):
    motion, sensor = filter._modules.get("motion"), filter._modules.get("measurement")
    if motion is None or sensor is None:
        raise ValueError(f"bank: {who} needs mode filters with motion and measurement models, got "
                         f"{type(filter).__name__}")
    return motion, sensor


def per_mode(bank: FilterBank, fn, x: Tensor, u: Tensor | None, who: str) -> Tensor:
    """``fn(motion, sensor, x, u)`` evaluated with each mode's models on ``x (*B, M, d)`` (``u``
    ``(*B, 1 or M, k)``) -> ``(*B, M, d')``: one call for a vectorised bank (its models carry the
    mode axis), one per filter for a list bank."""
    members = bank_members(bank, who)
    if isinstance(bank, VectorizedBank):
        return fn(*member_models(bank.filter, who), x, u)
    return torch.stack([fn(*member_models(f, who), x[..., j, :], None if u is None else u.select(-2, 0 if u.shape[-2] == 1
                                                                                        else j))
                        for j, (f, _) in enumerate(members)], dim=-2)


def gaussian_moments(belief: Belief) -> GaussianBelief:
    """The Gaussian moments of a mode filter's belief (the belief itself for Gaussians)."""
    return belief if type(belief) is GaussianBelief else belief.estimate()


def mode_param(value: Tensor, j: int | None) -> Tensor:
    """Mode ``j``'s entry of a model parameter evaluated with batch ``(*B, 1)`` (or shared; ``j = None``:
    a list bank's filter, evaluated with batch ``(*B,)``)."""
    if j is None:
        return value
    if value.dim() >= 3 and value.shape[-3] > 1:
        return value.select(-3, j)
    return value.squeeze(-3) if value.dim() >= 3 else value
