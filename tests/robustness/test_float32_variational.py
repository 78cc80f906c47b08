"""Defect 6 for the variational families (VB Student-t, skew-t, skew-t/IW, VBAKF-PR, GIMMAF,
IMM-VBT): the check of test_float32.py, in a file of its own so that the suite's processes share
the long runs (they take whole files)."""

from __future__ import annotations

import pytest

from tests.robustness.test_float32 import VARIATIONAL, check_family, lengths


@pytest.mark.parametrize(("name", "steps"), lengths(VARIATIONAL))
def test_float32_covariances_stay_finite_symmetric_psd_over_long_runs(name, steps):
    check_family(name, steps)
