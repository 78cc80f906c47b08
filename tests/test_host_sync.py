"""No host synchronisation inside a step (the rule that lets a step run asynchronously on a GPU).

Every estimator family of the robustness suite (tests/robustness/cases.py), the IMM fast path and
the smoothers run under :func:`torchmm.runtime.no_host_sync`, which refuses every read of tensor
values by the host (``item``, ``bool``, ``tolist``, ``numpy``, boolean masks, data-sized outputs)
and makes the code take its device (GPU) form on the CPU. Where CUDA is present, the same steps run
under ``torch.cuda.set_sync_debug_mode("error")``.
"""

from __future__ import annotations

import pytest
import torch

from tests.robustness.cases import CASES
from torchmm import (
    GPB2,
    IMM,
    ConstantVelocity,
    GaussianBelief,
    KalmanFilter,
    PositionMeasurement,
    kernels,
    run_filter,
    smooth,
)
from torchmm.multimodel import MultiRate, VariableStructureIMM
from torchmm.kernels.batch_last.imm import BATCH_LAST
from torchmm.multimodel.mevsmm import ExactMinimumEntropy
from torchmm.runtime import HostSyncError, host_reads_ok, no_host_sync


def _at(z, k):
    return MultiRate(*(t[k] for t in z)) if isinstance(z, MultiRate) else z[k]


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_steps_never_read_values_on_the_host(case):
    f = case.make()
    belief = case.start(f, 4)
    z = case.data(4, 4)
    belief = f.step(belief, _at(z, 0)).belief  # the first call fills per-model caches (e.g. noise factors)
    with no_host_sync(f"{case.name}.step"):
        for k in (1, 2):
            belief = f.step(belief, _at(z, k)).belief
    assert torch.isfinite(belief.estimate().mean).all()


def _imm(runs=5, steps=6):
    dtype = torch.float64
    motion = ConstantVelocity(1, q=1.0, acceleration=torch.tensor([[0.25], [0.0], [-0.25]], dtype=dtype), dtype=dtype)
    imm = IMM(KalmanFilter(motion, PositionMeasurement(2, [0], 4.0, dtype=dtype)),
              torch.tensor([[0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]], dtype=dtype))
    belief0 = imm.initial_belief(GaussianBelief(torch.zeros(runs, 2, dtype=dtype), 10 * torch.eye(2, dtype=dtype)))
    z = torch.randn(steps, runs, 1, generator=torch.Generator().manual_seed(0), dtype=dtype)
    z[2, 1] = float("nan")
    return imm, belief0, z


@pytest.mark.parametrize("estimate", [False, True])
@pytest.mark.parametrize("combinator", ["IMM", "GPB2", "VSIMM"])
def test_fast_path_steps_never_read_values_on_the_host(estimate, combinator):
    """The batch-last kernel's steps (torchmm/kernels/batch_last/imm.py, behind torchmm.kernels): the
    IMM's, GPB2's (batch_last_pairs.py) and the variable-structure IMM's (the IMM's and its policy's)."""
    imm, belief0, z = _imm()
    if combinator == "GPB2":
        imm = GPB2(imm.bank.filter, imm.transition.matrix())
    elif combinator == "VSIMM":
        imm = VariableStructureIMM(imm.bank.filter, imm.transition.matrix(), ExactMinimumEntropy())
        start = GaussianBelief(torch.zeros(5, 2, dtype=z.dtype), 10 * torch.eye(2, dtype=z.dtype))
        belief0 = imm.initial_belief(start)
    request = kernels.Request(estimate=estimate,  # (as run_filter asks for record="estimate")
                              keep=frozenset({"belief", "log_likelihood"}) if estimate else None)
    run = BATCH_LAST.plan(imm, belief0, z, request)  # the plan (its one look at R's values)
    assert callable(run), run
    kernel = run.kernel
    assert (kernel.estimate_only or kernel.estimate_after) == estimate
    state = kernel.initial_state(belief0)
    with no_host_sync("the IMM fast path"):
        for _ in range(z.shape[0]):
            state, out = kernel.step(state, None)  # (the kernel holds the prepared measurements)
    assert torch.isfinite(out.log_likelihood).all()
    run = BATCH_LAST.plan(imm, belief0, z, request)
    with no_host_sync("the IMM fast path's whole run"):  # the start state, the steps, the stacking
        fields = run()
    torch.testing.assert_close(fields[2][-1], out.log_likelihood, rtol=0, atol=0)


@pytest.mark.parametrize("name", ["kf", "ekf", "ukf", "imm", "gpb2"])
def test_smoother_passes_never_read_values_on_the_host(name):
    case = next(c for c in CASES if c.name == name)
    f = case.make()
    z = case.data(5, 4)
    traj = run_filter(f, case.start(f, 4), z)
    with no_host_sync(f"smooth({name})"):
        out = smooth(f, traj, method="kim") if name in ("imm", "gpb2") else smooth(f, traj)
    assert torch.isfinite(out.estimate().mean).all()


def test_no_host_sync_refuses_every_kind_of_read():
    t = torch.tensor([1.0, -2.0, 3.0])
    assert host_reads_ok(t)
    reads = [lambda: bool(t.sum() > 0), lambda: t.sum().item(), lambda: float(t[0]), lambda: t.tolist(),
             lambda: t.numpy(), lambda: t[t > 0], lambda: torch.nonzero(t), lambda: torch.unique(t),
             lambda: torch.equal(t, t), lambda: int(t.argmax())]
    for read in reads:
        with pytest.raises(HostSyncError, match="host synchronisation in the test"):
            with no_host_sync("the test"):
                read()
    with no_host_sync("the test"):
        inside = host_reads_ok(t)  # False: CPU code takes its device form inside
        doubled = torch.where(t > 0, t, 0.0) * 2  # tensor operations are fine
    assert inside is False and doubled.tolist() == [2.0, 0.0, 6.0]
    assert host_reads_ok(t) and t.tolist() == [1.0, -2.0, 3.0]  # everything restored


GAUSSIAN = [c for c in CASES if not c.particles and not c.multirate]  # (particle cases draw from a CPU generator)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (runs where a GPU is present)")
@pytest.mark.parametrize("case", GAUSSIAN, ids=[c.name for c in GAUSSIAN])
def test_cuda_steps_do_not_synchronise(case):
    f = case.make()
    belief = case.start(f, 4).to("cuda")  # built on the CPU, then moved with the filter
    f = f.to("cuda")
    z = case.data(3, 4).cuda()
    belief = f.step(belief, _at(z, 0)).belief
    torch.cuda.set_sync_debug_mode("error")
    try:
        for k in (1, 2):
            belief = f.step(belief, _at(z, k)).belief
    finally:
        torch.cuda.set_sync_debug_mode("default")
    torch.cuda.synchronize()
    assert torch.isfinite(belief.estimate().mean).all()
