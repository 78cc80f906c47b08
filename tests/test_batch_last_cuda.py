"""The batch-last kernels on CUDA (runs where a GPU is present; benchmarks/gpu_session.sh runs it):
GPB2's, the variable-structure IMM's, IMM-TF's, the two-filter smoother's and the extended and unscented
banks' kernel runs equal the CPU's,
and their steps run under ``torch.cuda.set_sync_debug_mode("error")`` (no host synchronisation)."""

from __future__ import annotations

import pytest
import torch

from tests.multimodel.test_batch_last_nonlinear import _turn
from tests.multimodel.test_transfer import paper_setup
from torchmm import GPB2, IMM, kernels, run_filter, smooth
from torchmm.multimodel import TransferIMM, VariableStructureIMM
from torchmm.kernels.batch_last.imm import BATCH_LAST
from torchmm.kernels.batch_last.nonlinear import NONLINEAR
from torchmm.kernels.batch_last.transfer import TRANSFER
from torchmm.multimodel.mevsmm import ExactMinimumEntropy

DT = torch.float64
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (runs where a GPU is present)")


def _runs(dev: str, runs: int = 6, steps: int = 20) -> dict:
    """Every new kernel's run on ``dev`` (estimates, log-likelihoods, the smoothed means)."""
    kf, P, source, prior, z, _ = paper_setup(runs=runs, steps=steps)
    kf, P, source, prior = kf.to(dev), P.to(dev), source.to(dev), prior.to(dev)
    y, z = z.target.to(dev), type(z)(z.target.to(dev), z.source.to(dev))
    out = {}
    for name, filt in (("GPB2", GPB2(kf, P)), ("VSIMM", VariableStructureIMM(kf, P, ExactMinimumEntropy())),
                       ("IMM-TF", TransferIMM(kf, P, source))):
        data = z if name == "IMM-TF" else y
        traj = run_filter(filt, filt.initial_belief(prior), data, record="estimate", fast_path=True)
        out[name] = (traj.belief.mean, traj.log_likelihood)
    imm = IMM(kf, P)
    traj = run_filter(imm, imm.initial_belief(prior), y)
    out["two-filter"] = (smooth(imm, traj, y).belief.components.mean, traj.log_likelihood)
    for kind in ("ekf", "ukf"):  # the nonlinear banks' kernel (batch_last_nonlinear.py)
        mm, belief0, data = _turn(kind, steps=steps)
        traj = run_filter(mm.to(dev), belief0.to(dev), data.to(dev), record="estimate", fast_path=True)
        out[kind] = (traj.belief.mean, traj.log_likelihood)
    return out


def _no_sync_steps(dev: str) -> None:
    """Each kernel's steps (after the plan, which reads R once) under the sync debug mode."""
    kf, P, source, prior, z, _ = paper_setup(runs=4, steps=6)
    kf, P, source, prior = kf.to(dev), P.to(dev), source.to(dev), prior.to(dev)
    z = type(z)(z.target.to(dev), z.source.to(dev))
    request = kernels.Request(estimate=True, keep=frozenset({"belief", "log_likelihood"}))
    plans = [BATCH_LAST.plan(GPB2(kf, P), GPB2(kf, P).initial_belief(prior), z.target, request),
             TRANSFER.plan(TransferIMM(kf, P, source), TransferIMM(kf, P, source).initial_belief(prior), z, request)]
    vs = VariableStructureIMM(kf, P, ExactMinimumEntropy())
    plans.append(BATCH_LAST.plan(vs, vs.initial_belief(prior), z.target, request))
    for kind in ("ekf", "ukf"):
        mm, belief0, data = _turn(kind, steps=6)
        plans.append(NONLINEAR.plan(mm.to(dev), belief0.to(dev), data.to(dev),
                                    kernels.Request(estimate=True, keep=request.keep, forced=True)))
    assert all(callable(p) for p in plans), plans
    if dev == "cuda":
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")
    try:
        for plan in plans:
            plan()
    finally:
        if dev == "cuda":
            torch.cuda.set_sync_debug_mode("default")


@needs_cuda
def test_the_new_kernels_on_cuda_equal_the_cpu_and_do_not_synchronise():
    cpu, gpu = _runs("cpu"), _runs("cuda")
    for name in cpu:
        for a, b in zip(gpu[name], cpu[name]):
            torch.testing.assert_close(a.cpu(), b, rtol=1e-9, atol=1e-9, msg=name)
    _no_sync_steps("cuda")


def test_the_cuda_tests_logic_on_the_cpu():
    """The same functions CPU against CPU (what this machine can check of the CUDA test)."""
    first, second = _runs("cpu"), _runs("cpu")
    assert set(first) == {"GPB2", "VSIMM", "IMM-TF", "two-filter", "ekf", "ukf"}
    for name in first:
        for a, b in zip(first[name], second[name]):
            assert torch.equal(a, b), name
    _no_sync_steps("cpu")
