"""One home and one table for the whole-run kernels (issue 47): every kernel lives under torchmm/kernels/,
the table registers them in its order, importing a kernel's module registers nothing."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import torchmm
from torchmm import kernels


def test_the_table_is_the_registration_order_and_names_its_thresholds():
    names = [name for name, *_ in kernels.TABLE]
    assert [k.name for k in kernels.registered()][:len(names)] == names
    rows = {name: (module, values) for name, module, values in kernels.table()}
    assert rows["linear_gaussian"][1] == {"MAX_RUNS": 128, "LONG_RUN": 1}
    assert rows["batch_last_nonlinear"][1] == {"MIN_BATCH": 300}
    root = Path(torchmm.__file__).parent
    for module, _ in rows.values():  # every whole-run kernel under torchmm/kernels/
        assert module.startswith("torchmm.kernels."), module
        assert (root.parent / (module.replace(".", "/") + ".py")).exists(), module


def test_importing_a_kernel_module_registers_nothing():
    code = ("import torchmm, torchmm.kernels as k, torchmm.kernels.batch_last.imm, torchmm.kernels.linear; "
            "print(len(k.__dict__['_KERNELS'])); print(len(k.registered()))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    before, after = (int(v) for v in out.stdout.split())
    assert before == 0 and after == len(kernels.TABLE)


def test_the_batch_last_kernels_compose_one_algebra_instead_of_extending_a_kernel():
    """Issue 47, item 2: each batch-last step extends only the frame (sizes, layouts, outputs) and holds its
    modes' algebra as an object (a linear or a nonlinear bank); no kernel's step is another kernel's subclass
    (the nonlinear IMM is the IMM's step over another bank: its class adds nothing but the bank)."""
    from torchmm.kernels.batch_last.bank import LinearBank
    from torchmm.kernels.batch_last.frame import Frame
    from torchmm.kernels.batch_last.imm import BatchLastIMM
    from torchmm.kernels.batch_last.nonlinear import BatchLastNonlinear, NonlinearBank
    from torchmm.kernels.batch_last.pairs import BatchLastGPB2
    from torchmm.kernels.batch_last.transfer import BatchLastTransfer

    for step in (BatchLastIMM, BatchLastGPB2, BatchLastTransfer):
        assert step.__mro__[1:] == (Frame, object), step
    assert BatchLastNonlinear.__mro__[1] is BatchLastIMM
    assert set(vars(BatchLastNonlinear)) <= {"__module__", "__doc__", "__init__", "kind", "__qualname__",
                                              "__firstlineno__", "__static_attributes__"}
    for bank in (LinearBank, NonlinearBank):
        assert bank.__mro__[1:] == (object,)
        assert all(callable(getattr(bank, name)) for name in ("predict", "update", "innovation"))
