"""Record every study's results at small sizes, the reference the regression tests compare against.

Run ``python -m tests.regression.record`` (from the repository root, in the test environment) only
when a change is *meant* to change a study's numbers, and say so in the commit message; the records
in ``tests/regression/records/`` are otherwise never rewritten. Timing columns are left out.

Each record carries a fingerprint of the machine it was made on (:func:`machine_fingerprint`: its
seeded random streams and the rounding of the kernels the studies use). On a machine whose fingerprint
differs (another processor, another torch build) the data themselves can differ, and every comparison
falls back to the Monte Carlo tolerance of 4 runs.
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


def machine_fingerprint() -> str:
    """A hash of what makes a study's numbers machine-specific: seeded torch draws (normal, uniform,
    multinomial; float32 and float64) and the arithmetic of the kernels the studies lean on.

    Two machines with the same seeded streams can still round differently: vectorised ``exp``/``log``
    and matrix products (AVX-512 against AVX2, fused multiply-add), and so whether the Cholesky factor
    of a singular process noise ``q G G^T`` "succeeds" with a pivot of rounding size or falls back to
    an eigendecomposition (``torchmm.linalg.psd_sqrt``), which draws other random vectors. Both are in
    the hash, so a record compares exactly only on a machine that computes as the recording one did.
    """
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the kernels' rounding, not the thread split's
    try:
        return _fingerprint()
    finally:
        torch.set_num_threads(threads)


def _fingerprint() -> str:
    import torch

    from torchmm.linalg import psd_sqrt
    from torchmm.models import ConstantVelocity

    g = torch.Generator().manual_seed(1234)
    parts = [torch.randn(4099, generator=g, dtype=torch.float64), torch.randn(4099, generator=g, dtype=torch.float32),
             torch.rand(4099, generator=g, dtype=torch.float64),
             torch.multinomial(torch.rand(64, generator=g, dtype=torch.float32), 500, replacement=True, generator=g).double()]
    x = torch.rand(1031, generator=g, dtype=torch.float64) + 0.5
    a = torch.randn(37, 53, generator=g, dtype=torch.float64)
    b = torch.randn(53, 29, generator=g, dtype=torch.float64)
    parts += [x.exp(), x.log(), x.float().exp().double(), x.float().log().double(), a @ b, (a.float() @ b.float()).double(),
              torch.linalg.eigh(a[:6, :8] @ a[:6, :8].mT)[1]]
    for ndim, q in ((1, 0.1), (1, 1.0), (1, 0.01), (2, 0.5)):
        Q = ConstantVelocity(ndim, q=q, dtype=torch.float64).Q
        parts += [psd_sqrt(Q), psd_sqrt(Q.float()).double()]
    digest = hashlib.sha256()
    for part in parts:
        digest.update(part.contiguous().numpy().tobytes())
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
        record = {"experiment": name, "machine_fingerprint": machine_fingerprint(), **numbers(results)}
        (RECORDS / f"{name}.json").write_text(json.dumps(record, indent=1) + "\n")
        print(f"recorded {name}")


if __name__ == "__main__":
    import torch

    torch.set_default_dtype(torch.float64)  # as the test session (tests/conftest.py)
    main(sys.argv[1:])
