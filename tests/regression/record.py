"""Record every study's results at small sizes, the reference the regression tests compare against.

Run ``python -m tests.regression.record`` (from the repository root, in the test environment) only
when a change is *meant* to change a study's numbers, and say so in the commit message; the records
in ``tests/regression/records/`` are otherwise never rewritten. Timing columns are left out.

Each record carries a fingerprint of the seeded random streams of the machine it was made on
(:func:`rng_fingerprint`): on a CPU whose seeded streams differ, the comparison of the studies that
draw random numbers inside the estimators (particle filters) falls back to Monte Carlo tolerance.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

RECORDS = Path(__file__).with_name("records")

#: the sizes of the recorded runs: the study's conf/debug sizes (4 Monte Carlo runs), added per study
COMMON = ["mc_runs=4", "progress=false", "logger=none"]

#: studies whose estimators draw random numbers themselves (particle filters): bit-identical while the
#: random streams are kept, Monte Carlo tolerance otherwise
STOCHASTIC = {"mevsmm"}


def is_timing(name: str) -> bool:
    """Columns and metrics that measure time, not estimation (never compared)."""
    name = name.lower()
    return "second" in name or "time" in name


def numbers(results: dict) -> dict:
    """The comparable part of a results.json: every table without its timing columns, the metrics."""
    tables = {}
    for key, table in results["tables"].items():
        keep = [i for i, c in enumerate(table["columns"]) if not is_timing(str(c))]
        tables[key] = {"columns": [table["columns"][i] for i in keep],
                       "rows": [[row[i] for i in keep] for row in table["rows"]]}
    metrics = {name: {k: v for k, v in values.items() if not is_timing(k)} if isinstance(values, dict) else values
               for name, values in results["metrics"].items()}
    return {"tables": tables, "metrics": metrics}


def rng_fingerprint() -> str:
    """A hash of seeded torch draws (normal, uniform, multinomial; float32 and float64)."""
    import torch

    g = torch.Generator().manual_seed(1234)
    parts = [torch.randn(4099, generator=g, dtype=torch.float64), torch.randn(4099, generator=g, dtype=torch.float32),
             torch.rand(4099, generator=g, dtype=torch.float64),
             torch.multinomial(torch.rand(64, generator=g, dtype=torch.float32), 500, replacement=True, generator=g).double()]
    digest = hashlib.sha256()
    for part in parts:
        digest.update(part.numpy().tobytes())
    return digest.hexdigest()[:16]


def run(name: str, out_dir: Path) -> dict:
    from tests.experiments.test_studies import FAST, _compose
    from experiments.run import run_study

    run_study(_compose(name, *COMMON, *FAST.get(name, [])), out_dir)
    return json.loads((out_dir / "results.json").read_text())


def main(names: list[str]) -> None:
    import tempfile

    from tests.experiments.test_studies import EXPERIMENTS

    RECORDS.mkdir(exist_ok=True)
    for name in names or EXPERIMENTS:
        with tempfile.TemporaryDirectory() as tmp:
            results = run(name, Path(tmp))
        record = {"experiment": name, "rng_fingerprint": rng_fingerprint(), **numbers(results)}
        (RECORDS / f"{name}.json").write_text(json.dumps(record, indent=1) + "\n")
        print(f"recorded {name}")


if __name__ == "__main__":
    import torch

    torch.set_default_dtype(torch.float64)  # as the test session (tests/conftest.py)
    main(sys.argv[1:])
