"""Particle filters: PF ~ KF on linear-Gaussian models (Monte Carlo error), shapes, missing data,
the all-underflow guard, IMM over a PF bank, and the multiple-model PF's interaction step."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchmm import IMM, GaussianBelief, KalmanFilter, run_filter
from torchmm.beliefs import ParticleBelief
from torchmm.filters.particle import ParticleFilter, gaussian_log_likelihood, noise_factor
from torchmm.multimodel.particle import MultipleModelParticleFilter, mixing_indices
from torchmm.models import ConstantVelocity, PositionMeasurement
from torchmm.simulate import simulate_jump_system, simulate_measurements

PI3 = (torch.full((3, 3), 0.05) + 0.85 * torch.eye(3)).double()


def _linear_data(steps: int, runs: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    prior = GaussianBelief.create([0.0, 1.0], [[4.0, 0.0], [0.0, 1.0]])
    truth = simulate_jump_system(ConstantVelocity(1, q=0.5, acceleration=[[0.0]]), torch.ones(1, 1), prior,
                                 steps, (runs,), generator=g)
    sensor = PositionMeasurement(2, [0], 1.0)
    return prior, sensor, simulate_measurements(sensor, truth.states, generator=g)


@pytest.mark.parametrize("noise_dtype", [None, "float32"])
def test_pf_matches_kalman_filter_within_monte_carlo_error(noise_dtype):
    """64 independent PFs (2000 particles) on the same data: their average posterior mean is the
    KF mean within 6 standard errors; the likelihood estimate is unbiased in linear space. Also
    with float32 process-noise draws (the particles stay float64)."""
    steps, reps = 10, 64
    prior, sensor, z = _linear_data(steps, 2)
    motion = ConstantVelocity(1, q=0.5)
    kf = run_filter(KalmanFilter(motion, sensor), prior.expand(2), z)
    pf = ParticleFilter(motion, sensor, generator=torch.Generator().manual_seed(5), noise_dtype=noise_dtype)
    traj = run_filter(pf, pf.initial_belief(prior.expand(reps, 2), 2000), z.unsqueeze(1).expand(steps, reps, 2, 1))
    assert traj.belief.particles.dtype == torch.float64
    ek, ep = kf.estimate(), traj.estimate()
    se = ep.mean.std(1) / math.sqrt(reps)
    zscore = (ep.mean.mean(1) - ek.mean) / se
    assert float(zscore.abs().max()) < 6.0
    var_ratio = ep.cov.diagonal(dim1=-2, dim2=-1).mean(1) / ek.cov.diagonal(dim1=-2, dim2=-1)
    assert float((var_ratio - 1).abs().max()) < 0.1
    ratio = torch.exp(traj.log_likelihood.sum(0) - kf.log_likelihood.sum(0))  # (reps, 2), E = 1
    zl = (ratio.mean(0) - 1) / (ratio.std(0) / math.sqrt(reps))
    assert float(zl.abs().max()) < 6.0
    assert bool(traj.extras["resampled"].any()) and traj.extras["ess"].shape == (steps, reps, 2)


@pytest.mark.parametrize("batch", [(), (4,), (3, 2)], ids=str)
@pytest.mark.parametrize("scheme", ["systematic", "residual"])
def test_shapes_and_float32(batch, scheme):
    g = torch.Generator().manual_seed(0)
    for dtype in (torch.float64, torch.float32):
        motion = ConstantVelocity(2, q=0.1, dtype=dtype)
        sensor = PositionMeasurement(4, [0, 2], 1.0, dtype=dtype)
        pf = ParticleFilter(motion, sensor, resampling=scheme, generator=g)
        prior = GaussianBelief(torch.zeros(*batch, 4, dtype=dtype), torch.eye(4, dtype=dtype).expand(*batch, 4, 4))
        belief = pf.initial_belief(prior, 64)
        assert belief.particles.shape == (*batch, 64, 4) and belief.particles.dtype == dtype
        traj = run_filter(pf, belief, torch.randn(5, *batch, 2, generator=g).to(dtype))
        assert traj.belief.particles.shape == (5, *batch, 64, 4)
        assert traj.log_likelihood.shape == (5, *batch)
        assert traj.innovation.shape == (5, *batch, 2) and traj.innovation_cov.shape == (5, *batch, 2, 2)
        assert torch.isfinite(traj.estimate().mean).all() and torch.isfinite(traj.log_likelihood).all()


def test_missing_measurements_are_skipped_exactly():
    g = torch.Generator().manual_seed(1)
    motion = ConstantVelocity(2, q=0.1)
    sensor = PositionMeasurement(4, [0, 2], torch.tensor([[2.0, 0.5], [0.5, 1.0]]))
    pf = ParticleFilter(motion, sensor, ess_threshold=0.0, generator=g)
    belief = pf.initial_belief(GaussianBelief(torch.zeros(3, 4), torch.eye(4).expand(3, 4, 4)), 50)
    z = torch.tensor([[float("nan"), float("nan")], [0.3, float("nan")], [0.3, -0.2]])
    out = pf.update(belief, z)
    torch.testing.assert_close(out.belief.log_weights[0], belief.log_weights[0])
    assert out.log_likelihood[0] == 0.0
    # partially observed: the marginal likelihood of the observed component (variance 2)
    x = belief.particles[1, :, 0]
    ll = -0.5 * ((0.3 - x) ** 2 / 2.0 + math.log(2 * math.pi * 2.0))
    expected = torch.log_softmax(ll + belief.log_weights[1], -1)
    torch.testing.assert_close(out.belief.log_weights[1], expected)
    assert torch.isfinite(out.belief.estimate().mean).all()


def test_gaussian_log_likelihood_matches_scipy():
    stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(0)
    cov = np.array([[2.0, 0.3], [0.3, 0.5]])
    resid = rng.normal(size=(3, 7, 2))
    got = gaussian_log_likelihood(torch.tensor(resid), torch.tensor(cov))
    want = stats.multivariate_normal(np.zeros(2), cov).logpdf(resid)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-12)


def test_all_underflow_guard_reports_and_stays_finite(caplog):
    for dtype in (torch.float32, torch.float64):
        g = torch.Generator().manual_seed(0)
        motion = ConstantVelocity(1, q=0.1, dtype=dtype)
        sensor = PositionMeasurement(2, [0], 1.0, dtype=dtype)
        pf = ParticleFilter(motion, sensor, generator=g)
        belief = pf.initial_belief(GaussianBelief(torch.zeros(2, 2, dtype=dtype), torch.eye(2, dtype=dtype).expand(2, 2, 2)), 100)
        # run 0: so far out that every particle's likelihood underflows to 0 (an infinite datum would
        # be missing data, docs/robustness.md)
        far = 1e200 if dtype == torch.float64 else 1e30
        z = torch.tensor([[far], [0.1]], dtype=dtype)
        out = pf.step(belief, z)  # the step only flags it (no host read in a step)
        assert out.extras["degenerate"].tolist() == [True, False]
        with caplog.at_level("WARNING", logger="torchmm"):
            run_filter(pf, belief, z[None])  # the run reports it, once
        assert "1 of 2 particle updates had every weight vanish" in caplog.text
        assert not torch.isnan(out.belief.log_weights).any()
        assert torch.isfinite(out.belief.estimate().mean).all()
        assert out.log_likelihood[0] == -math.inf and torch.isfinite(out.log_likelihood[1])


def test_imm_accepts_particle_filters():
    """IMM over a one-mode PF bank is the PF itself (same random stream); over three modes it
    tracks the IMM-KF's mode probabilities."""
    prior, sensor, z = _linear_data(10, 4, seed=2)
    motion1 = ConstantVelocity(1, q=0.5, acceleration=[[0.0]])
    pf_a = ParticleFilter(motion1, sensor, generator=torch.Generator().manual_seed(3), ess_threshold=2.0)
    pf_b = ParticleFilter(motion1, sensor, generator=torch.Generator().manual_seed(3), ess_threshold=2.0)
    single = run_filter(pf_a, pf_a.initial_belief(prior.expand(4), 300), z)
    imm1 = IMM(pf_b, torch.ones(1, 1))
    start = pf_b.initial_belief(prior.expand(4), 300)
    traj = run_filter(imm1, imm1.initial_belief(start), z)
    torch.testing.assert_close(traj.estimate().mean, single.estimate().mean)
    torch.testing.assert_close(traj.log_likelihood, single.log_likelihood)

    bank = ConstantVelocity(1, q=0.5, acceleration=[[0.5], [0.0], [-0.5]])
    g = torch.Generator().manual_seed(4)
    imm_pf = IMM(ParticleFilter(bank, sensor, num_particles=2000, generator=g), PI3)
    imm_kf = IMM(KalmanFilter(bank, sensor), PI3)
    b0 = imm_pf.initial_belief(ParticleFilter(bank, sensor, generator=g).initial_belief(prior.expand(4), 2000))
    t_pf, t_kf = run_filter(imm_pf, b0, z), run_filter(imm_kf, imm_kf.initial_belief(prior.expand(4)), z)
    assert t_pf.belief.components.particles.shape == (10, 4, 3, 2000, 2)
    assert float((t_pf.belief.mode_probs - t_kf.belief.mode_probs).abs().mean()) < 0.05


def test_mixing_indices_are_unbiased_and_respect_the_transition():
    """Ancestor (a, b) of target model i is drawn with probability mu_a pi_ai w_{b|a} / c_i."""
    g = torch.Generator().manual_seed(0)
    M, Np, reps = 3, 6, 20_000
    mode_lp = torch.log(torch.tensor([0.5, 0.3, 0.2]))
    within = torch.log_softmax(torch.randn(M, Np, generator=g), -1)
    for scheme in ("systematic", "stratified", "multinomial", "two_stage"):
        flat, log_cbar = mixing_indices(mode_lp.expand(reps, M), PI3.log(), within.expand(reps, M, Np), Np,
                                        scheme, generator=g)
        torch.testing.assert_close(log_cbar[0], torch.log(mode_lp.exp() @ PI3))
        counts = torch.zeros(reps, M, M * Np).scatter_add_(-1, flat, torch.ones_like(flat, dtype=torch.float64))
        joint = (mode_lp.exp()[:, None] * PI3)  # (a, i)
        expected = Np * (joint / joint.sum(0)).T[:, :, None] * within.exp()[None]  # (i, a, b)
        mean, se = counts.mean(0), counts.std(0) / math.sqrt(reps)
        zs = (mean - expected.reshape(M, M * Np)) / se.clamp_min(1e-12)
        big = expected.reshape(M, M * Np) > 0.05
        assert float(zs[big].abs().max()) < 5.0, scheme
    # identity transition: every model draws only from itself
    for scheme in ("systematic", "two_stage"):
        flat, _ = mixing_indices(mode_lp.expand(4, M), torch.eye(M).log(), within.expand(4, M, Np), 50, scheme,
                                 generator=g)
        assert torch.equal(torch.div(flat, Np, rounding_mode="floor"), torch.arange(M).view(1, M, 1).expand(4, M, 50))


def test_multiple_model_pf_tracks_imm():
    prior, sensor, z = _linear_data(10, 4, seed=3)
    bank = ConstantVelocity(1, q=0.5, acceleration=[[0.5], [0.0], [-0.5]])
    mm = MultipleModelParticleFilter(bank, sensor, PI3, 3000, generator=torch.Generator().manual_seed(0))
    traj = run_filter(mm, mm.initial_belief(prior.expand(4)), z)
    kf = run_filter(IMM(KalmanFilter(bank, sensor), PI3), IMM(KalmanFilter(bank, sensor), PI3).initial_belief(prior.expand(4)), z)
    assert traj.belief.components.particles.shape == (10, 4, 3, 3000, 2)
    torch.testing.assert_close(traj.belief.mode_probs.sum(-1), torch.ones(10, 4))
    assert float((traj.belief.mode_probs - kf.belief.mode_probs).abs().mean()) < 0.05
    sd = kf.estimate().cov.diagonal(dim1=-2, dim2=-1).sqrt()
    assert float(((traj.estimate().mean - kf.estimate().mean) / sd).abs().max()) < 0.5
    assert torch.allclose(traj.log_likelihood.sum(0), kf.log_likelihood.sum(0), atol=0.5)


def test_noise_factor_rank_and_reconstruction():
    motion = ConstantVelocity(2, q=0.3)
    Q = motion.noise_cov()
    L = noise_factor(Q)
    torch.testing.assert_close(L @ L.mT, Q, atol=1e-12, rtol=0)
    eig = noise_factor(torch.diag(torch.tensor([1.0, 0.0, 2.0])))
    assert eig.shape == (3, 2)
    torch.testing.assert_close(eig @ eig.mT, torch.diag(torch.tensor([1.0, 0.0, 2.0])))


def test_bad_arguments_raise():
    motion, sensor = ConstantVelocity(1), PositionMeasurement(2, [0], 1.0)
    with pytest.raises(ValueError, match="resampling"):
        ParticleFilter(motion, sensor, resampling="bogus")
    with pytest.raises(ValueError, match="ess_threshold"):
        ParticleFilter(motion, sensor, ess_threshold=-1)
    with pytest.raises(ValueError, match="num_particles"):
        ParticleFilter(motion, sensor).initial_belief(GaussianBelief(torch.zeros(2), torch.eye(2)))
    with pytest.raises(TypeError, match="belief"):
        ParticleFilter(motion, sensor).update(GaussianBelief(torch.zeros(2), torch.eye(2)), torch.zeros(1))
    with pytest.raises(ValueError, match="mixing"):
        MultipleModelParticleFilter(motion, sensor, torch.ones(1, 1), 10, mixing="residual")
    with pytest.raises(ValueError, match="motion"):
        MultipleModelParticleFilter(ConstantVelocity(1, acceleration=[[1.0], [0.0]]), sensor, PI3, 10)
    with pytest.raises(ValueError, match="measurement"):
        ParticleFilter(motion, PositionMeasurement(4, [0], 1.0))
    assert isinstance(ParticleFilter(motion, sensor).initial_belief(GaussianBelief(torch.zeros(2), torch.eye(2)), 3),
                      ParticleBelief)


@pytest.mark.parametrize("winners", ["20", "25"])  # the pool 820 = 41 x 20 windows; 815 / 25: a short last one
def test_pf_throughput_benchmark_runs_and_agrees_with_numpy(winners):
    """benchmarks/pf_throughput.py at tiny size: same random numbers -> same step as NumPy."""
    import re
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    proc = subprocess.run(
        [sys.executable, str(root / "benchmarks" / "pf_throughput.py"), "--runs", "3", "--particles", "40",
         "--winners", winners, "--threshold", "2", "--steps", "1", "--repeats", "1", "--bandwidth-mb", "8"],
        capture_output=True, text=True, timeout=300, env={"OMP_NUM_THREADS": "1", "PATH": ""},
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.strip().splitlines()
    assert re.fullmatch(r"particle_steps_per_s=\S+ speedup_vs_numpy=[0-9.]+ fraction_of_bandwidth=[0-9.]+ "
                        r"fraction_of_rng_cap=[0-9.]+", lines[-1]), lines[-1]
    diffs = dict(re.findall(r"(\w+)=([0-9.e+-]+)", next(line for line in lines if "difference" in line)))
    assert float(diffs["particles"]) < 1e-12 and float(diffs["estimate"]) < 1e-12
    assert float(diffs["log_weights"]) < 1e-9 and float(diffs["model_sets"]) == 0


def test_singular_process_noise_gives_finite_gradients():
    """noise_factor drops the null directions before the square root (no NaN through sqrt(0))."""
    from torchmm.filters.particle import noise_factor

    q = torch.tensor(0.5, requires_grad=True)
    G = torch.tensor([[0.5], [1.0]])
    Q = q * (G @ G.T)  # rank one
    factor = noise_factor(Q)
    assert factor.shape == (2, 1)
    torch.testing.assert_close(factor @ factor.T, Q, rtol=1e-10, atol=1e-12)
    (factor.square().sum()).backward()
    assert torch.isfinite(q.grad) and q.grad > 0


def _reference_mixing(mode_lp, log_pi, within, Np, u0):
    """The interaction of MultipleModelParticleFilter with plain searchsorted calls (no counting)."""
    joint = mode_lp.unsqueeze(-1) + log_pi
    mix = (joint.mT - torch.logsumexp(joint, -2).unsqueeze(-1)).exp()
    cdf = torch.cumsum(mix, -1)
    cdf = cdf / cdf[..., -1:]
    cdf[..., -1] = 1.0
    u = (torch.arange(Np, dtype=torch.float64) + u0) / Np
    anc = torch.searchsorted(cdf, u, right=True).clamp_max(cdf.shape[-1] - 1)
    low = torch.cat([torch.zeros_like(cdf[..., :1]), cdf[..., :-1]], -1)
    lo, hi = torch.gather(low, -1, anc), torch.gather(cdf, -1, anc)
    inner = ((u - lo) / (hi - lo)).clamp(0, 1 - 2.0**-52)
    w = (within - torch.logsumexp(within, -1, keepdim=True)).exp()
    cw = torch.cumsum(w, -1)
    cw = cw / cw[..., -1:]
    cw[..., -1] = 1.0
    M = cdf.shape[-1]
    cw = (cw + torch.arange(M, dtype=torch.float64).unsqueeze(-1)).flatten(-2)
    flat = torch.searchsorted(cw, (anc + inner).flatten(-2), right=True).clamp_max(cw.shape[-1] - 1)
    return flat.view(anc.shape)


def test_systematic_mixing_by_counting_equals_plain_searchsorted():
    g = torch.Generator().manual_seed(3)
    B, M, Np = 7, 4, 300
    mode_lp = torch.log_softmax(torch.randn(B, M, generator=g, dtype=torch.float64) * 2, -1)
    mode_lp[0, 1] = -math.inf  # an inactive model
    within = torch.randn(B, M, Np, generator=g, dtype=torch.float64) * 3
    within[..., ::5] = -math.inf  # zero-weight particles are never drawn
    log_pi = PI3.new_full((M, M), 0.1).fill_diagonal_(0.7).log()
    state = g.get_state()
    flat, _ = mixing_indices(mode_lp, log_pi, within, Np, "systematic", generator=g)
    g.set_state(state)
    u0 = torch.rand((B, M, 1), dtype=torch.float64, generator=g)
    assert torch.equal(flat, _reference_mixing(mode_lp, log_pi, within, Np, u0))
    assert bool(torch.isfinite(torch.gather(within.flatten(-2), -1, flat.flatten(-2))).all())
    # two_stage: the same ancestor models (same points), never a zero-weight particle, and each
    # (run, model a) contributes particles of its own systematic resample only
    g.set_state(state)
    two, _ = mixing_indices(mode_lp, log_pi, within, Np, "two_stage", generator=g)
    assert torch.equal(torch.div(two, Np, rounding_mode="floor"), torch.div(flat, Np, rounding_mode="floor"))
    assert bool(torch.isfinite(torch.gather(within.flatten(-2), -1, two.flatten(-2))).all())
    g.set_state(state)
    torch.rand((B, M, 1), dtype=torch.float64, generator=g)  # u0
    v0 = torch.rand((B, M, 1), dtype=torch.float64, generator=g)
    w = within.exp()
    cdf = torch.cumsum(w, -1) / w.sum(-1, keepdim=True)
    cdf[..., -1] = 1.0
    resample = torch.searchsorted(cdf, (torch.arange(Np, dtype=torch.float64) + v0) / Np, right=True)
    allowed = torch.zeros(B, M * Np, dtype=torch.bool)
    allowed.scatter_(1, (resample + Np * torch.arange(M).view(1, M, 1)).flatten(-2), True)
    assert bool(torch.gather(allowed, 1, two.flatten(-2)).all())


def test_linear_fast_paths_equal_the_generic_formulas():
    from torchmm.filters.particle import particle_log_likelihood, propagate_particles
    from torchmm.models import LinearMotion

    g = torch.Generator().manual_seed(0)
    cv = ConstantVelocity(2, q=0.3, acceleration=[[1.0, 0.0], [0.0, -1.0], [0.5, 0.5]])
    motion = LinearMotion(cv.F, cv.Q, offset=cv.offset)  # offset per mode (3, 4)
    x = torch.randn(5, 3, 40, 4, generator=g, dtype=torch.float64)
    state = g.get_state()
    out = propagate_particles(motion, x, generator=g)
    g.set_state(state)
    factor = noise_factor(motion.noise_cov())
    eps = torch.randn(5, 3, 40, factor.shape[-1], generator=g, dtype=torch.float64)
    expected = x @ motion.F.mT + motion.offset.unsqueeze(-2) + eps @ factor.mT
    torch.testing.assert_close(out, expected, rtol=1e-12, atol=1e-12)
    # float32 normals: the same draws as a float32 randn, cast
    g.set_state(state)
    out32 = propagate_particles(motion, x, generator=g, noise_dtype=torch.float32)
    g.set_state(state)
    eps32 = torch.randn(5, 3, 40, factor.shape[-1], generator=g, dtype=torch.float32).double()
    assert out32.dtype == torch.float64
    torch.testing.assert_close(out32, x @ motion.F.mT + motion.offset.unsqueeze(-2) + eps32 @ factor.mT,
                               rtol=1e-12, atol=1e-12)
    # whitened likelihood without predicted measurements == the generic residual form
    sensor = PositionMeasurement(4, [0, 2], [[4.0, 1.0], [1.0, 9.0]])
    z = torch.randn(5, 3, 2, generator=g, dtype=torch.float64)
    fast, none = particle_log_likelihood(sensor, z, x, False, need_predicted=False)
    slow, predicted = particle_log_likelihood(sensor, z, x, False)
    assert none is None and predicted.shape == (5, 3, 40, 2)
    torch.testing.assert_close(fast, slow, rtol=1e-12, atol=1e-10)


def test_noise_dtype_must_be_a_float_dtype():
    with pytest.raises(TypeError, match="^noise_dtype: expected a floating dtype"):  # a dtype is a TypeError
        ParticleFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0), noise_dtype=torch.int32)


def test_retain_freed_memory_is_idempotent():
    """In a child process: the setting is process-wide and must not leak into the test session."""
    import subprocess
    import sys

    code = ("from torchmm.runtime import retain_freed_memory as r; import torch; a = r(); b = r(); "
            "x = torch.ones(1 << 23) * 2; print(a, b, float(x.sum()))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    first, second, total = proc.stdout.split()
    assert first == second and first in ("True", "False") and float(total) == 2.0 * (1 << 23)


@pytest.mark.parametrize("num", [1, 5, 16, 17, 33, 1000])
@pytest.mark.parametrize("d", [1, 2, 4, 7, 70])
def test_repeat_rows_and_affine_rows_are_exact(num, d):
    """The tiled broadcast copy and the in-place batched GEMM give the bits of a plain broadcast
    copy and of torch.baddbmm with the stride-0 offset."""
    from torchmm.filters.particle_ops import _affine_rows, _repeat_rows

    g = torch.Generator().manual_seed(num * 100 + d)
    c = torch.randn(6, 1, d, dtype=torch.float64, generator=g)
    out = _repeat_rows(c, num)
    assert out.is_contiguous() and torch.equal(out, c.expand(6, num, d))
    x = torch.randn(2, 3, num, 3, dtype=torch.float64, generator=g)
    A = torch.randn(d, 3, dtype=torch.float64, generator=g)
    offset = c.view(2, 3, 1, d)
    expected = torch.baddbmm(offset.reshape(6, 1, d).expand(6, num, d), x.reshape(6, num, 3), A.mT.expand(6, 3, d))
    got = _affine_rows(x, A, offset, (2, 3, num, d))
    assert got.shape == (2, 3, num, d) and torch.equal(got, expected.view(2, 3, num, d))


def test_linear_model_subclasses_with_their_own_forward_are_called():
    """A LinearMotion / LinearMeasurement subclass that overrides ``forward`` is called by the particle
    operations, not replaced by its matrices (before: ``F x`` and ``H x`` were used, the override ignored
    silently; torchmm.models.linear.plain_linear)."""
    from torchmm.filters.particle_ops import particle_log_likelihood, propagate_particles
    from torchmm.models.linear import LinearMeasurement, LinearMotion

    class Shifted(LinearMotion):
        def forward(self, x, *, u=None):
            return super().forward(x, u=u) + 1.0

    class Offset(LinearMeasurement):
        def forward(self, x):
            return super().forward(x) + 2.0

    F, Q = torch.tensor([[1.0, 0.5], [0.0, 1.0]]), 0.1 * torch.eye(2)
    particles = torch.randn(3, 20, 2, generator=torch.Generator().manual_seed(0))
    plain = propagate_particles(LinearMotion(F, Q), particles, generator=torch.Generator().manual_seed(1))
    shifted = propagate_particles(Shifted(F, Q), particles, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(shifted, plain + 1.0)
    H, R = torch.tensor([[1.0, 0.0]]), torch.eye(1)
    z = torch.randn(3, 1, generator=torch.Generator().manual_seed(2))
    for need in (False, True):
        want = particle_log_likelihood(LinearMeasurement(H, R), z - 2.0, particles, False, need_predicted=need)[0]
        got = particle_log_likelihood(Offset(H, R), z, particles, False, need_predicted=need)[0]
        torch.testing.assert_close(got, want)
