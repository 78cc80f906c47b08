"""run.stack_outputs: its flattening (a cheaper walk than pytree.tree_flatten at every step) gives
pytree's leaves and structure, and refuses outputs whose structure changes between steps."""

from __future__ import annotations

import collections

import pytest
import torch
import torch.utils._pytree as pytree

from torchmm.beliefs import GaussianBelief, ModeBelief
from torchmm.filters.base import StepOutput
from torchmm.kernels import _flatten
from torchmm.run import stack_outputs


def _output(seed: int, extras=None) -> StepOutput:
    g = torch.Generator().manual_seed(seed)
    comps = GaussianBelief(torch.randn(4, 3, 2, generator=g), torch.randn(4, 3, 2, 2, generator=g))
    return StepOutput(ModeBelief(torch.randn(4, 3, generator=g), comps), None, torch.randn(4, generator=g),
                      torch.randn(4, 3, 1, generator=g), None,
                      {"a": torch.randn(4, generator=g), "b": {"c": torch.randn(4, 3, generator=g)}}
                      if extras is None else extras)


def test_leaves_and_stack_match_pytree():
    outputs = [_output(k) for k in range(5)]
    leaves, structure = [], []
    _flatten(outputs[0], leaves, structure)
    expected, _ = pytree.tree_flatten(outputs[0])
    assert len(leaves) == len(expected) and all(a is b for a, b in zip(leaves, expected, strict=True))
    stacked = stack_outputs(outputs)
    flat = [pytree.tree_flatten(o)[0] for o in outputs]
    for got, column in zip(pytree.tree_flatten(stacked)[0], zip(*flat, strict=True), strict=True):
        if column[0] is None:
            assert got is None
        else:
            assert torch.equal(got, torch.stack(column))
    assert pytree.tree_structure(stacked) == pytree.tree_structure(outputs[0])


def test_structure_change_is_refused():
    outputs = [_output(0), _output(1, extras={"a": torch.zeros(4)})]
    with pytest.raises(ValueError, match="outputs: step outputs differ in structure"):
        stack_outputs(outputs)
    # the same keys but a leaf turning into None
    odd = _output(1)._replace(log_likelihood=None)
    with pytest.raises(ValueError, match="differ in structure"):
        stack_outputs([_output(0), odd])


def test_plain_containers_and_namedtuples():
    Pair = collections.namedtuple("Pair", "x y")
    outputs = [Pair(torch.full((2,), float(k)), [torch.ones(3) * k, (torch.zeros(1), None)]) for k in range(3)]
    stacked = stack_outputs(outputs)
    assert isinstance(stacked, Pair)
    assert torch.equal(stacked.x, torch.tensor([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]))
    assert torch.equal(stacked.y[0], torch.stack([torch.ones(3) * k for k in range(3)]))
    assert stacked.y[1][1] is None
    with pytest.raises(ValueError, match="differ in structure"):
        stack_outputs([Pair(torch.zeros(1), torch.zeros(1)), (torch.zeros(1), torch.zeros(1))])
