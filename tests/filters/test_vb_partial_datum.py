"""The variational-Bayes filters skip a datum with any missing component (docs/robustness.md): a partly
missing datum must then be the same as a wholly missing one, bit for bit, for the filters themselves and for
multiple-model filters over them. The IMMs' engine asked the mode filters' ``informative`` (default: some
component finite) and scored the partly missing step ``logsumexp(log c_j)``, about 4e-16, not 0."""

from __future__ import annotations

import pytest
import torch

from tests.robustness.cases import BY_NAME
from torchmm import run_filter

NAMES = ["student_t", "skew_t", "skew_t_iw", "vbakf", "gimmaf", "imm_vbt"]


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("fast_path", [None, False], ids=["default", "eager"])
def test_a_partly_missing_datum_is_a_missing_datum(name, fast_path):
    case = BY_NAME[name]
    f = case.make()
    b0 = case.start(f, 3)
    z = case.data(5, 3, seed=2)
    partly, wholly = z.clone(), z.clone()
    partly[2, 0, 1] = float("nan")
    wholly[2, 0, :] = float("nan")
    a = run_filter(f, b0, partly, fast_path=fast_path)
    b = run_filter(f, b0, wholly, fast_path=fast_path)
    assert float(a.log_likelihood[2, 0]) == 0.0
    assert torch.equal(a.log_likelihood, b.log_likelihood)
    for x, y in zip(torch.utils._pytree.tree_leaves(a.belief), torch.utils._pytree.tree_leaves(b.belief)):
        assert torch.equal(x, y)
