"""Which kernel ran (issue 47): every trajectory's provenance names the kernel that computed it and why the
kernels before it declined; a study's results.json counts its runs by kernel."""

from __future__ import annotations

import json

import torch

from torchmm import IMM, GaussianBelief, KalmanFilter, kernels, run_filter
from torchmm.models import ConstantVelocity, LinearMeasurement, LinearMotion, PositionMeasurement

D = torch.float64


def _kf():
    eye = torch.eye(1, dtype=D)
    return KalmanFilter(LinearMotion(eye, eye), LinearMeasurement(eye, eye))


def test_the_trajectory_names_its_kernel_and_the_reasons_of_the_others():
    kf = _kf()
    z = torch.randn(10, 3, 1, generator=torch.Generator().manual_seed(0), dtype=D)
    b0 = GaussianBelief(torch.zeros(3, 1, dtype=D), torch.eye(1, dtype=D))
    small = run_filter(kf, b0, z)
    assert small.provenance.kernel == "linear_gaussian" and small.provenance.declined == ""
    eager = run_filter(kf, b0, z, fast_path=False)
    assert eager.provenance.kernel == kernels.EAGER and eager.provenance.declined == "fast_path=False"
    with kernels.switched_off("linear_gaussian"):
        off = run_filter(kf, b0, z)
    assert off.provenance.kernel == kernels.EAGER
    assert "linear_gaussian: switched off" in off.provenance.declined
    assert torch.allclose(small.log_likelihood, eager.log_likelihood, rtol=1e-12, atol=1e-12)
    # many runs of an IMM: the serial loop declines, the batch-last kernel takes it
    imm = IMM(KalmanFilter(ConstantVelocity(1, q=1.0, acceleration=[[0.0], [0.5]], dtype=D),
                           PositionMeasurement(2, [0], 4.0, dtype=D)), torch.tensor([[0.9, 0.1], [0.1, 0.9]], dtype=D))
    start = imm.initial_belief(GaussianBelief(torch.zeros(500, 2, dtype=D), torch.eye(2, dtype=D)))
    big = run_filter(imm, start, torch.randn(5, 500, 1, generator=torch.Generator().manual_seed(1), dtype=D))
    assert big.provenance.kernel == "batch_last"
    assert big.provenance.declined.startswith("linear_gaussian: 500 runs: more than the serial loop's 128")
    # fast_path=True takes that same kernel (it forced the serial loop past its 128 runs before); a Kalman
    # filter of 500 runs, which no kernel takes unasked, is forced onto the serial loop
    z = torch.randn(5, 500, 1, generator=torch.Generator().manual_seed(1), dtype=D)
    forced = run_filter(imm, start, z, fast_path=True)
    assert forced.provenance.kernel == "batch_last"
    assert torch.equal(forced.log_likelihood, big.log_likelihood)
    kf_start = GaussianBelief(torch.zeros(500, 1, dtype=D), torch.eye(1, dtype=D))
    assert run_filter(kf, kf_start, z).provenance.kernel == kernels.EAGER
    assert run_filter(kf, kf_start, z, fast_path=True).provenance.kernel == "linear_gaussian"
    assert "kernel='batch_last'" in repr(big.provenance)


def test_counting_counts_each_run_by_its_kernel():
    kf = _kf()
    z = torch.randn(4, 1, dtype=D)
    b0 = GaussianBelief(torch.zeros(1, dtype=D), torch.eye(1, dtype=D))
    with kernels.counting() as outer:
        run_filter(kf, b0, z)
        with kernels.counting() as inner:
            run_filter(kf, b0, z, fast_path=False)
            run_filter(kf, b0, z, fast_path=False)
    run_filter(kf, b0, z)  # (outside: not counted)
    assert outer == {"linear_gaussian": 1, kernels.EAGER: 2} and inner == {kernels.EAGER: 2}


def test_results_json_counts_the_study_runs_by_kernel(tmp_path):
    from experiments.run import run_study
    from tests.experiments.test_studies import _compose
    from tests.regression.record import COMMON

    run_study(_compose("quickstart", *COMMON, "debug=quickstart", "figures=false"), tmp_path)
    provenance = json.loads((tmp_path / "results.json").read_text())["provenance"]
    assert provenance["kernels"] and all(isinstance(v, int) and v > 0 for v in provenance["kernels"].values())
    assert set(provenance["kernels"]) <= {k.name for k in kernels.registered()} | {kernels.EAGER}
    assert "kernels_note" not in provenance
    assert "Runs by kernel (torchmm.kernels): " in (tmp_path / "results.md").read_text()


def test_a_record_function_is_applied_to_the_numba_kernels_outputs():
    """A callable record (issue 47) no longer turns the Numba kernel off: it runs, and the record applied
    to each step of its outputs gives what the eager steps give with the same record (1e-12), missing
    data included, for a Kalman filter and an IMM."""
    from torchmm.filters import StepOutput

    g = torch.Generator().manual_seed(3)
    imm = IMM(KalmanFilter(ConstantVelocity(1, q=1.0, acceleration=[[0.0], [0.5]], dtype=D),
                           PositionMeasurement(2, [0], 4.0, dtype=D)), torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=D))
    z = torch.randn(15, 4, 1, generator=g, dtype=D) * 3
    z[3, 1] = z[7, 0] = float("nan")
    cases = {"kf": (_kf(), GaussianBelief(torch.zeros(4, 1, dtype=D), torch.eye(1, dtype=D))),
             "imm": (imm, imm.initial_belief(GaussianBelief(torch.zeros(4, 2, dtype=D), torch.eye(2, dtype=D))))}
    records = [lambda o: o._replace(prior=None),
               lambda o: StepOutput(o.belief.estimate(), None, o.log_likelihood)]
    for name, (filt, start) in cases.items():
        for record in records:
            fast = run_filter(filt, start, z, record=record)
            slow = run_filter(filt, start, z, record=record, fast_path=False)
            assert fast.provenance.kernel == "linear_gaussian", (name, fast.provenance.declined)
            assert slow.provenance.kernel == kernels.EAGER
            assert fast.prior is None and slow.prior is None
            a, b = fast.belief.estimate(), slow.belief.estimate()
            assert torch.allclose(a.mean, b.mean, rtol=1e-12, atol=1e-12), name
            assert torch.allclose(a.cov, b.cov, rtol=1e-12, atol=1e-12), name
            assert torch.allclose(fast.log_likelihood, slow.log_likelihood, rtol=1e-12, atol=1e-12), name
