"""Compare a study's results.json with its record (tests/regression/records, see record.py)."""

from __future__ import annotations

import json
import math

from tests.regression.record import RECORDS, STOCHASTIC, machine_fingerprint, numbers

#: deterministic studies (the same data give the same numbers): relative tolerance
DETERMINISTIC_RTOL = 1e-9
#: on a machine that draws or rounds differently from the recording one (record.machine_fingerprint) the
#: data can differ too; the numbers then agree only within the Monte Carlo error of 4 runs
FOREIGN_RTOL = 0.6


def _count(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def load(name: str) -> dict:
    return json.loads((RECORDS / f"{name}.json").read_text())


def mismatches(name: str, results: dict) -> list[str]:
    """Every recorded number the new results miss; empty when they agree."""
    record = load(name)
    got = numbers(results)
    same_machine = record["machine_fingerprint"] == machine_fingerprint()
    if not same_machine:
        rtol, atol = FOREIGN_RTOL, 1e-6
    elif name in STOCHASTIC:
        rtol, atol = 0.0, 0.0  # bit-identical while the random streams are kept
    else:
        rtol, atol = DETERMINISTIC_RTOL, 1e-12
    out: list[str] = []

    def check(path: str, want, have):
        if isinstance(want, dict):
            if not isinstance(have, dict) or set(want) != set(have):
                out.append(f"{path}: keys {sorted(want)} != {sorted(have) if isinstance(have, dict) else have}")
                return
            for key in want:
                check(f"{path}.{key}", want[key], have[key])
        elif isinstance(want, list):
            if not isinstance(have, list) or len(want) != len(have):
                out.append(f"{path}: {want!r} != {have!r}")
                return
            for i, (w, h) in enumerate(zip(want, have)):
                check(f"{path}[{i}]", w, h)
        elif isinstance(want, float) or isinstance(have, float) or (
                not same_machine and _count(want) and _count(have)):
            # counts (e.g. runs where a conclusion holds) follow the data as the floats do: exact on
            # the recording machine, within the Monte Carlo tolerance elsewhere
            if want is None or have is None or isinstance(want, str) or isinstance(have, str):
                out.append(f"{path}: {want!r} != {have!r}")
            elif math.isnan(want) or math.isnan(have):
                if not (math.isnan(want) and math.isnan(have)):
                    out.append(f"{path}: {want!r} != {have!r}")
            elif not abs(want - have) <= atol + rtol * abs(want):
                out.append(f"{path}: recorded {want!r}, got {have!r}")
        elif want != have:
            out.append(f"{path}: recorded {want!r}, got {have!r}")

    check(name, {"tables": record["tables"], "metrics": record["metrics"]}, got)
    return out
