"""Common random numbers across dtypes: a float32 run of a study filters the float64 run's data, cast down."""

from __future__ import annotations

import pytest
import torch

from experiments.run import run_study
from tests.experiments.test_studies import _compose_numbers as _compose


def _capture(monkeypatch, module, name, pick):
    seen = []
    original = getattr(module, name)

    def wrapper(*args, **kwargs):
        seen.append(pick(args, kwargs))
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, wrapper)
    return seen


CASES = {
    # study: (module, function to wrap, which argument is the simulated data)
    "imm_baseline": ("experiments.studies.imm_baseline", "evaluate_runs", lambda a, k: a[3]),
    "imm_tf": ("experiments.studies.imm_tf", "evaluate_runs", lambda a, k: a[3].target),
    "mevsmm": ("experiments.studies.mevsmm", "_run", lambda a, k: a[2]),
    "fusion_radar": ("experiments.studies.fusion_radar", "local_estimates", lambda a, k: a[1]),
    "vbakf_huang": ("experiments.studies.vbakf_huang", "run_filter", lambda a, k: a[2]),
}


@pytest.mark.parametrize("study", sorted(CASES))
def test_float32_and_float64_runs_see_the_same_data(study, tmp_path, monkeypatch):
    import importlib

    module_name, function, pick = CASES[study]
    module = importlib.import_module(module_name)
    data = {}
    for dtype in ("float64", "float32"):
        with monkeypatch.context() as m:
            seen = _capture(m, module, function, pick)
            run_study(_compose(study, f"debug={study}", "logger=none", f"dtype={dtype}", "mc_runs=3"),
                      tmp_path / dtype)
        assert seen, f"{function} was not called"
        data[dtype] = seen[0]
    assert data["float32"].dtype == torch.float32 and data["float64"].dtype == torch.float64
    # the float32 data are the float64 data, rounded: the same draws (NaN = missing in both)
    torch.testing.assert_close(data["float32"], data["float64"].to(torch.float32), rtol=0, atol=0, equal_nan=True)
