"""The particle stages (torchmm.kernels.particle, fused Numba loops) against the eager torch steps they replace.

The integer work (interaction indices, tournament winners) must equal the eager path exactly on any
machine: it is the same IEEE arithmetic and comparisons. The propagation and likelihood add in the
order of torch's kernels as measured here; on another BLAS the last bit may differ, so the filter
steps are compared to 1e-12 (on the development machines they are bit-identical, docs/performance.md).
"""

from __future__ import annotations

import contextlib
import math

import pytest
import torch

import torchmm.kernels.particle as cpu_kernels
from torchmm import GaussianBelief
from torchmm import kernels as seam
from torchmm.filters.particle import cached_noise_factor
from torchmm.models import ConstantVelocity, LinearMotion, PositionMeasurement
from torchmm.multimodel.mevsmm import ChallengeMatch, EqMAParticleFilter, MinimumEntropyVSMM, uniform_transition
from torchmm.multimodel.particle import MultipleModelParticleFilter, mixing_indices
from torchmm.multimodel.policies import challenge_match
from torchmm.runtime import no_host_sync


@contextlib.contextmanager
def kernels(flag: bool | None):
    """The particle stages on (True, or None: as by default), or off, at the seam."""
    previous = seam.enabled(cpu_kernels.NAME)
    seam.set_enabled(cpu_kernels.NAME, flag is not False)
    try:
        yield
    finally:
        seam.set_enabled(cpu_kernels.NAME, previous)


@pytest.fixture
def spy(monkeypatch):
    """Counts the calls of each kernel entry point (and still runs it)."""
    calls = {"two_stage_indices": 0, "propagate_log_likelihood": 0, "challenge_pass": 0}
    for name in calls:
        original = getattr(cpu_kernels, name)

        def counted(*args, _name=name, _original=original, **kwargs):
            calls[_name] += 1
            return _original(*args, **kwargs)

        monkeypatch.setattr(cpu_kernels, name, counted)
    return calls


def _both(fn):
    """``fn()`` with the kernels off and on, each from a generator seeded alike; the generators'
    states after the call are returned too (the kernels must draw exactly what the eager path draws)."""
    out = []
    for flag in (False, True):
        gen = torch.Generator().manual_seed(7)
        with kernels(flag):
            out.append((fn(gen), gen.get_state()))
    return out


def test_numba_is_there_and_on_by_default():
    assert cpu_kernels.available()  # a dependency of torchmm: CI must run the kernels, not skip them
    with kernels(None):
        assert cpu_kernels.enabled()


def test_switches(monkeypatch):
    with pytest.raises(ValueError, match="name: no kernel named 'particle'"):
        seam.set_enabled("particle", False)
    assert cpu_kernels.NAME in seam.names()
    with seam.switched_off(cpu_kernels.NAME):
        assert not cpu_kernels.enabled()
    assert cpu_kernels.enabled()
    with kernels(None):
        monkeypatch.setenv("TORCHMM_CPU_KERNELS", "0")
        assert not cpu_kernels.enabled()
        monkeypatch.setenv("TORCHMM_CPU_KERNELS", "1")
        assert cpu_kernels.enabled()
    with kernels(False):
        assert not cpu_kernels.applies(torch.zeros(3))
    with kernels(True):
        assert cpu_kernels.applies(torch.zeros(3))
        assert not cpu_kernels.applies(torch.zeros(3, requires_grad=True))
        with torch.no_grad():
            assert cpu_kernels.applies(torch.zeros(3, requires_grad=True))
        with no_host_sync():  # the device form is what that block checks
            assert not cpu_kernels.applies(torch.zeros(3))


@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
@pytest.mark.parametrize("M, num_prev, num", [(1, 5, 5), (3, 40, 17), (5, 9, 64)])
@pytest.mark.parametrize("normalised", [True, False])
def test_two_stage_indices_equal_the_eager_ones(batch, M, num_prev, num, normalised, spy):
    g = torch.Generator().manual_seed(M * 100 + num)
    mode = torch.randn(*batch, M, generator=g, dtype=torch.float64) * 2
    if M > 2:
        mode[..., 1] = -math.inf  # an inactive model: no point may land in it
    mode = mode.log_softmax(-1)
    within = torch.randn(*batch, M, num_prev, generator=g, dtype=torch.float64) * 3
    within[..., 0, :2] = -math.inf  # particles of zero weight
    within = within.log_softmax(-1) if normalised else within + 50.0  # not normalised: the shifted exp
    log_transition = (torch.rand(M, M, generator=g, dtype=torch.float64) + 0.1).log().log_softmax(-1)

    (eager, eager_state), (fused, fused_state) = _both(
        lambda gen: mixing_indices(mode, log_transition, within, num, "two_stage", generator=gen))
    assert spy["two_stage_indices"] == 1
    assert torch.equal(eager[0], fused[0]) and eager[0].dtype == fused[0].dtype == torch.int64
    assert eager[0].shape == (*batch, M, num)
    assert torch.equal(eager[1], fused[1])
    assert torch.equal(eager_state, fused_state)
    if M > 2:  # nothing drawn from the inactive model
        assert not ((fused[0] // num_prev) == 1).any()


def test_two_stage_indices_with_shared_particles(spy):
    """Within-model weights without the batch axes (broadcast over the runs)."""
    g = torch.Generator().manual_seed(3)
    mode = torch.randn(4, 3, generator=g, dtype=torch.float64).log_softmax(-1)
    within = torch.randn(3, 11, generator=g, dtype=torch.float64).log_softmax(-1)
    log_transition = torch.full((3, 3), 1 / 3, dtype=torch.float64).log()
    (eager, _), (fused, _) = _both(lambda gen: mixing_indices(mode, log_transition, within, 11, "two_stage",
                                                               generator=gen))
    assert spy["two_stage_indices"] == 1
    assert torch.equal(eager[0], fused[0])


@pytest.mark.parametrize("P, N", [(60, 12), (61, 12), (40, 39), (1000, 420)])
@pytest.mark.parametrize("batch", [(), (4,), (2, 3)])
def test_challenge_pass_equals_the_eager_tournament(P, N, batch, spy):
    g = torch.Generator().manual_seed(P + N)
    scores = torch.randn(*batch, P, generator=g, dtype=torch.float64).mul_(2).round_()  # many ties
    scores[..., : P // 7] = -math.inf
    (eager, eager_state), (fused, fused_state) = _both(lambda gen: challenge_match(scores, N, generator=gen))
    assert spy["challenge_pass"] == 1
    assert torch.equal(eager, fused) and fused.shape == (*batch, N)
    assert torch.equal(eager_state, fused_state)


def test_challenge_pass_with_nan_scores_as_torch_max(spy):
    """A NaN challenger makes torch's max NaN, and the holder stays: the kernel does the same."""
    g = torch.Generator().manual_seed(5)
    scores = torch.randn(6, 90, generator=g, dtype=torch.float64)
    scores[:, 5::11] = math.nan
    (eager, _), (fused, _) = _both(lambda gen: challenge_match(scores, 20, generator=gen))
    assert spy["challenge_pass"] == 1
    assert torch.equal(eager, fused)


def test_challenge_match_more_passes_stays_eager(spy):
    scores = torch.randn(3, 50, dtype=torch.float64)
    (eager, _), (fused, _) = _both(lambda gen: challenge_match(scores, 10, passes=2, generator=gen))
    assert spy["challenge_pass"] == 0
    assert torch.equal(eager, fused)


def _scenario(batch, M=3, dtype=torch.float64):
    acc = torch.linspace(-1.0, 1.0, M, dtype=dtype).unsqueeze(-1).expand(M, 2) * torch.tensor([1.0, -0.5], dtype=dtype)
    motion = ConstantVelocity(2, q=0.3, acceleration=acc, dtype=dtype)
    measurement = PositionMeasurement(4, [0, 2], 0.5, dtype=dtype)
    g = torch.Generator().manual_seed(11)
    prior = GaussianBelief(torch.zeros(*batch, 4, dtype=dtype), torch.eye(4, dtype=dtype).expand(*batch, 4, 4))
    zs = torch.randn(6, *batch, 2, generator=g, dtype=dtype).cumsum(0)
    return motion, measurement, prior, zs


def _run(make, prior, zs, steps=5, around_steps=contextlib.nullcontext):
    """A few steps of a filter, from a seeded generator; returns everything a step outputs."""
    gen = torch.Generator().manual_seed(1)
    filt = make(gen)
    belief = filt.update(filt.initial_belief(prior), zs[0]).belief
    outs = []
    for k in range(1, steps + 1):
        with around_steps():
            out = filt.step(belief, zs[k])
        belief = out.belief
        outs.append(out)
    return outs, gen.get_state()


def _assert_steps_close(eager, fused):
    (e_outs, e_state), (f_outs, f_state) = eager, fused
    assert torch.equal(e_state, f_state)  # the same draws
    for e, f in zip(e_outs, f_outs):
        torch.testing.assert_close(f.belief.components.particles, e.belief.components.particles, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(f.belief.components.log_weights, e.belief.components.log_weights,
                                   rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(f.belief.mode_log_probs, e.belief.mode_log_probs, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(f.log_likelihood, e.log_likelihood, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(f.extras["ess"], e.extras["ess"], rtol=1e-10, atol=1e-10)
        if hasattr(e.belief, "active"):
            assert torch.equal(f.belief.active, e.belief.active)
        assert f.belief.components.particles.shape == e.belief.components.particles.shape


@pytest.mark.parametrize("batch", [(), (4,), (2, 3)])
@pytest.mark.parametrize("mixing", ["two_stage", "systematic"])
def test_mevsmm_steps_equal_the_eager_steps(batch, mixing, spy):
    motion, measurement, prior, zs = _scenario(batch, M=5)

    def make(gen):
        return MinimumEntropyVSMM(motion, measurement, uniform_transition(5, 0.8, dtype=torch.float64), 60,
                                  selection=ChallengeMatch(40, 6), generator=gen, innovation_stats=False,
                                  noise_dtype=torch.float32, mixing=mixing)

    with kernels(False):
        eager = _run(make, prior, zs)
    with kernels(True):
        fused = _run(make, prior, zs)
    assert spy["propagate_log_likelihood"] == 5
    assert spy["challenge_pass"] == 6  # the first update selects too
    assert spy["two_stage_indices"] == (5 if mixing == "two_stage" else 0)
    _assert_steps_close(eager, fused)


def test_mmpf_with_a_shared_offset_and_float64_noise(spy):
    """A plain LinearMotion (one offset for every mode) and normals drawn in the state's dtype."""
    _, measurement, prior, zs = _scenario((3,))
    F = torch.eye(4, dtype=torch.float64) + torch.diag(torch.ones(3, dtype=torch.float64), 1) * 0.5
    motion = LinearMotion(F, 0.2 * torch.eye(4, dtype=torch.float64), offset=torch.tensor([0.1, 0.0, -0.2, 0.05]))
    pi = torch.full((2, 2), 0.1, dtype=torch.float64) + 0.8 * torch.eye(2, dtype=torch.float64)

    def make(gen):
        return MultipleModelParticleFilter(motion, measurement, pi, 30, generator=gen, innovation_stats=False,
                                           mixing="two_stage")

    with kernels(False):
        eager = _run(make, prior, zs)
    with kernels(True):
        fused = _run(make, prior, zs)
    assert spy["propagate_log_likelihood"] == 5
    _assert_steps_close(eager, fused)


class _OwnForward(LinearMotion):
    """A linear motion that computes its own forward (here: the same map, through its own code)."""

    def forward(self, x, *, u=None):
        return super().forward(x, u=u)


class _OwnWeights(MultipleModelParticleFilter):
    """A filter that overrides the weighting step: it leaves the linear_particles family."""

    def _weigh(self, prior, z, loglik=None):
        return super()._weigh(prior, z, loglik)


def test_the_filter_describes_itself_at_the_seam():
    motion, measurement, _, _ = _scenario((3,), dtype=torch.float64)
    pi = uniform_transition(3, 0.8, dtype=torch.float64)
    plain = MultipleModelParticleFilter(motion, measurement, pi, 5, innovation_stats=False)
    described = seam.describe(plain, "linear_particles")
    assert isinstance(described, cpu_kernels.LinearParticles) and torch.equal(described.F, motion.F)
    assert "innovation_stats" in seam.describe(MultipleModelParticleFilter(motion, measurement, pi, 5), "linear_particles")
    own = _OwnForward(motion.F, motion.Q, motion.offset)
    assert "LinearMotion" in seam.describe(MultipleModelParticleFilter(own, measurement, pi, 5, innovation_stats=False),
                                           "linear_particles")
    assert "has not joined" in seam.describe(_OwnWeights(motion, measurement, pi, 5, innovation_stats=False),
                                             "linear_particles")


@pytest.mark.parametrize("case", ["innovation_stats", "missing", "float32", "eqma", "grad", "no_host_sync",
                                  "own_forward", "own_weights"])
def test_the_eager_path_where_the_kernel_does_not_apply(case, spy):
    dtype = torch.float32 if case == "float32" else torch.float64
    motion, measurement, prior, zs = _scenario((3,), dtype=dtype)
    if case == "own_forward":  # the fused pass would skip its forward: the steps run it
        motion = _OwnForward(motion.F, motion.Q, motion.offset)
    if case == "missing":
        zs = zs.clone()
        zs[2, 1, 0] = math.nan
    if case == "grad":
        prior = GaussianBelief(prior.mean.clone().requires_grad_(), prior.cov)
    pi = uniform_transition(3, 0.8, dtype=dtype)

    def make(gen):
        if case == "eqma":
            gain = torch.tensor([[0.5, 0.0], [1.0, 0.0], [0.0, 0.5], [0.0, 1.0]], dtype=dtype)
            return EqMAParticleFilter(motion.F, gain, torch.tensor([[0.5, 0.0], [0.0, -0.5], [0.3, 0.3]], dtype=dtype), 0.3 * torch.eye(2, dtype=dtype),
                                      measurement, 25, transition=uniform_transition(4, 0.8, dtype=dtype),
                                      generator=gen)
        cls = _OwnWeights if case == "own_weights" else MultipleModelParticleFilter
        return cls(motion, measurement, pi, 25, generator=gen, innovation_stats=case == "innovation_stats",
                   mixing="systematic")

    around = contextlib.nullcontext
    if case == "no_host_sync":  # the device form, for both runs
        cached_noise_factor(motion.noise_cov())  # Q's rank is read once, at its first use (cached)
        around = no_host_sync
    with kernels(True):
        fused = _run(make, prior, zs, around_steps=around)
    # with a missing datum only that step is eager (step 2 of 5)
    assert spy["propagate_log_likelihood"] == (4 if case == "missing" else 0), case
    with kernels(False):
        eager = _run(make, prior, zs, around_steps=around)
    if case == "missing":  # the other four steps ran the kernels
        _assert_steps_close(eager, fused)
        return
    for e, f in zip(eager[0], fused[0]):  # the same code ran: the same numbers
        assert torch.equal(e.belief.components.particles, f.belief.components.particles)
        assert torch.equal(e.log_likelihood, f.log_likelihood)


def test_the_first_compile_is_announced(tmp_path, monkeypatch, caplog):
    """Issue 30: the first run on a machine was a minute of silence while Numba compiled."""
    import logging

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert not cpu_kernels.compiled_before()  # an empty cache
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "particle_loops.propagate-94.py311.nbi").write_bytes(b"")
    assert cpu_kernels.compiled_before()
    monkeypatch.setattr(cpu_kernels, "_ANNOUNCED", [])
    monkeypatch.setattr(cpu_kernels, "compiled_before", lambda: False)
    with caplog.at_level(logging.INFO, logger="torchmm.kernels.particle"):
        cpu_kernels._kernels()
        cpu_kernels._kernels()
    assert [r.getMessage() for r in caplog.records].count(
        "compiling the particle filters' fused CPU kernels (Numba, once per machine: about a minute, then a few "
        "seconds per new problem size; cached on disk)") == 1
