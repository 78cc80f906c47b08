"""The record comparison itself: exact on the recording machine, Monte Carlo tolerance elsewhere,
for counts as for floats (a count follows the data: on another processor the data differ)."""

from __future__ import annotations

import pytest

from tests.regression import compare


def _results(count: int, value: float) -> dict:
    return {"tables": {"t": {"columns": ["runs", "rmse"], "rows": [[count, value]]}}, "metrics": {}}


@pytest.fixture
def record(monkeypatch):
    monkeypatch.setattr(compare, "load", lambda name: {"machine_fingerprint": "recorder", **_results(100, 1.0)})
    return monkeypatch


@pytest.mark.parametrize("machine, count, value, ok", [
    ("recorder", 100, 1.0, True),
    ("recorder", 101, 1.0, False),  # counts exact where the data are the recorded ones
    ("recorder", 100, 1.0 + 1e-6, False),
    ("other", 103, 1.2, True),  # elsewhere: within the Monte Carlo tolerance, counts included
    ("other", 200, 1.0, False),
    ("other", 100, 2.0, False),
])
def test_counts_and_floats_on_the_recording_and_other_machines(record, machine, count, value, ok):
    record.setattr(compare, "machine_fingerprint", lambda: machine)
    assert (not compare.mismatches("imm_analysis", _results(count, value))) == ok


def test_a_bool_or_a_string_is_never_a_count(record):
    record.setattr(compare, "machine_fingerprint", lambda: "other")
    record.setattr(compare, "load", lambda name: {"machine_fingerprint": "recorder", **_results(True, 1.0)})
    assert compare.mismatches("imm_analysis", _results(False, 1.0))
