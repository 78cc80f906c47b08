"""docs/tutorial-estimation.md runs as written (every python block, in order, in a temporary folder), and
its numbers are the ones it states."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_tutorial_estimation_runs(tmp_path, monkeypatch):
    text = (ROOT / "docs" / "tutorial-estimation.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.DOTALL)
    assert len(blocks) >= 5
    monkeypatch.chdir(tmp_path)  # the tutorial writes its CSVs and outputs/ into the working directory
    ns: dict = {"__name__": "tutorial"}
    for i, block in enumerate(blocks):
        exec(compile(block, f"tutorial-estimation.md[block {i}]", "exec"), ns)  # noqa: S102 - the doc's own code
    # section 2-3: the maximum likelihood fit and statsmodels' figures the text quotes
    assert ns["summary"]["loglik"] == pytest.approx(-504.403, abs=1e-3)
    assert ns["summary"]["k"] == 6 and ns["summary"]["nobs"] == 226
    assert ns["theirs"].llf == pytest.approx(-505.702, abs=1e-3)
    assert ns["recipe"].table("fit").iloc[0]["loglik"] == pytest.approx(ns["theirs"].llf, abs=1e-6)
    # section 4: EM from config, every iteration raising the likelihood
    names = list(ns["em_run"].table("learned")["parameter"])
    assert {"modes[0].Q[0,0]", "sensors[0].R[0,0]", "initial_mean[0]", "initial_cov[0,0]"} <= set(names)
    import numpy as np

    values = np.load(tmp_path / ns["em_run"].dir / "curves.npz")["learn/em_loglik/KF"]
    assert len(values) == 201
    assert all(b >= a - 1e-9 * abs(a) for a, b in zip(values, values[1:]))
    # section 5: EM from Python
    assert ns["out"].monotone and float(ns["out"].loglik[-1]) > float(ns["out"].loglik[0])
    Q, R = ns["kfs"].motion.Q, ns["kfs"].measurement.R
    assert Q.shape == (1000, 1, 1)
    assert 30 < float(Q.median()) ** 0.5 < 50 and 110 < float(R.median()) ** 0.5 < 130
