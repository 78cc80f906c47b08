"""Batched Markov-jump simulator: statistics against the model, reproducibility, masks."""

from __future__ import annotations

import math
from functools import partial

import pytest
import torch

from torchmm import ConstantVelocity, GaussianBelief, LinearMeasurement, PositionMeasurement
from torchmm.models import MotionModel
from torchmm.simulate import (
    bernoulli_mask,
    periodic_mask,
    simulate_jump_system,
    simulate_measurements,
    simulate_modes,
    simulate_multirate,
)

close = partial(torch.testing.assert_close, rtol=0, atol=1e-12)
PI = torch.tensor([[0.8, 0.15, 0.05], [0.1, 0.7, 0.2], [0.3, 0.3, 0.4]])


def test_mode_transition_frequencies_match_the_matrix():
    g = torch.Generator().manual_seed(0)
    modes, first = simulate_modes(PI, 60, (2000,), generator=g)
    prev = torch.cat([first[None], modes[:-1]])
    for i in range(3):
        from_i = modes[prev == i]
        counts = torch.bincount(from_i, minlength=3).double()
        freq = counts / counts.sum()
        se = (PI[i] * (1 - PI[i]) / counts.sum()).sqrt()
        assert bool(((freq - PI[i]).abs() < 5 * se).all()), (i, freq, PI[i])


def test_reproducible_with_explicit_generator():
    motion = ConstantVelocity(1, acceleration=[[0.25], [0.0], [-0.25]])
    x0 = GaussianBelief(torch.tensor([10.0, 10.0]), torch.tensor([[100.0, 1.0], [1.0, 100.0]]))
    a = simulate_jump_system(motion, PI, x0, 20, (5,), generator=torch.Generator().manual_seed(3))
    b = simulate_jump_system(motion, PI, x0, 20, (5,), generator=torch.Generator().manual_seed(3))
    c = simulate_jump_system(motion, PI, x0, 20, (5,), generator=torch.Generator().manual_seed(4))
    close(a.states, b.states)
    assert torch.equal(a.modes, b.modes)
    assert not torch.equal(a.states, c.states)
    assert a.states.shape == (20, 5, 2) and a.modes.shape == (20, 5) and a.initial_state.shape == (5, 2)


def test_state_increments_follow_the_active_mode():
    """x_k - F x_{k-1} - G a_{r_k} must be N(0, q G G^T) whatever the mode."""
    g = torch.Generator().manual_seed(1)
    acc = torch.tensor([[2.0], [0.0], [-2.0]])
    motion = ConstantVelocity(1, q=1.0, acceleration=acc)
    x0 = GaussianBelief(torch.zeros(2), torch.eye(2))
    sim = simulate_jump_system(motion, PI, x0, 30, (4000,), generator=g)
    prev = torch.cat([sim.initial_state[None], sim.states[:-1]])
    gain = torch.tensor([0.5, 1.0])
    resid = sim.states - prev @ motion.F.mT - acc[sim.modes] * gain
    # the residual lies on G: resid = G w, w ~ N(0, 1)
    w = resid[..., 1]
    close(resid[..., 0], 0.5 * w)
    n = w.numel()
    assert abs(w.mean().item()) < 5 / math.sqrt(n)
    assert abs(w.var().item() - 1.0) < 5 * math.sqrt(2 / n)


def test_initial_state_distribution():
    g = torch.Generator().manual_seed(2)
    cov = torch.tensor([[100.0, 1.0], [1.0, 100.0]])
    x0 = GaussianBelief(torch.tensor([10.0, 10.0]), cov)
    sim = simulate_jump_system(ConstantVelocity(1), torch.ones(1, 1), x0, 1, (20000,), generator=g)
    mean = sim.initial_state.mean(0)
    emp_cov = torch.cov(sim.initial_state.T)
    assert bool(((mean - 10).abs() < 5 * 10 / math.sqrt(20000)).all())
    assert bool(((emp_cov - cov).abs() < 5 * 100 * math.sqrt(2 / 20000)).all())


def test_measurements_noise_and_availability():
    g = torch.Generator().manual_seed(5)
    states = torch.randn(50, 400, 2, generator=g)
    sensor = PositionMeasurement(2, [0], 4.0)
    avail = bernoulli_mask(50, (400,), 0.6, generator=g)
    z = simulate_measurements(sensor, states, available=avail, generator=g)
    assert z.shape == (50, 400, 1)
    assert torch.equal(torch.isnan(z[..., 0]), ~avail)
    noise = (z[..., 0] - states[..., 0])[avail]
    assert abs(noise.var().item() - 4.0) < 5 * 4.0 * math.sqrt(2 / noise.numel())
    frac = avail.double().mean().item()
    assert abs(frac - 0.6) < 5 * math.sqrt(0.24 / avail.numel())


def test_mode_dependent_sensor():
    g = torch.Generator().manual_seed(6)
    H = torch.tensor([[[1.0, 0.0]], [[0.0, 1.0]]])
    sensor = LinearMeasurement(H, torch.full((2, 1, 1), 1e-12))
    states = torch.randn(4, 3, 2, generator=g)
    modes = torch.randint(0, 2, (4, 3), generator=g)
    z = simulate_measurements(sensor, states, modes=modes, generator=g)
    expected = torch.where(modes == 0, states[..., 0], states[..., 1])
    torch.testing.assert_close(z[..., 0], expected, atol=1e-4, rtol=0)


def test_periodic_mask():
    mask = periodic_mask(10, (2,), 3)
    assert mask.shape == (10, 2)
    assert mask[:, 0].nonzero().squeeze(-1).tolist() == [2, 5, 8]  # steps 3, 6, 9
    with pytest.raises(ValueError, match="period"):
        periodic_mask(10, (2,), 0)
    with pytest.raises(ValueError, match="probability"):
        bernoulli_mask(10, (2,), 1.5)


def test_a_list_of_motion_models_is_one_model_per_mode():
    """``simulate_jump_system([m_1, .., m_M], ...)`` (as IMM takes its modes) draws the same
    trajectories as the equivalent mode bank, and a wrong list is refused naming ``motion``."""
    P = torch.tensor([[0.9, 0.1], [0.2, 0.8]])
    x0 = GaussianBelief(torch.zeros(2), torch.eye(2))
    bank = ConstantVelocity(1, acceleration=[[0.25], [-0.25]])
    models = [ConstantVelocity(1, acceleration=[[0.25]]), ConstantVelocity(1, acceleration=[[-0.25]])]
    a = simulate_jump_system(bank, P, x0, 20, (5,), generator=torch.Generator().manual_seed(3))
    b = simulate_jump_system(models, P, x0, 20, (5,), generator=torch.Generator().manual_seed(3))
    assert torch.equal(a.modes, b.modes)
    close(a.states, b.states)
    with pytest.raises(ValueError, match=r"^motion: 1 models for the 2 modes"):
        simulate_jump_system(models[:1], P, x0, 3, (2,))
    with pytest.raises(TypeError, match=r"^motion\[1\]"):
        simulate_jump_system([models[0], "CT"], P, x0, 3, (2,))
    with pytest.raises(ValueError, match=r"^motion\[1\]: state_dim"):
        simulate_jump_system([models[0], ConstantVelocity(2)], P, x0, 3, (2,))
    with pytest.raises(TypeError, match=r"^batch_shape"):
        simulate_jump_system(models, P, x0, 3, 5)


class _ShiftBank(MotionModel):
    """A bank of ``len(shifts)`` modes ``x + shift_j`` that does not declare its parameter batch (the
    simulator learns its mode axis from its output)."""

    def __init__(self, shifts):
        super().__init__()
        self.state_dim = 2
        self.register_buffer("shifts", torch.as_tensor(shifts, dtype=torch.float64))

    def forward(self, x, *, u=None):
        return x + self.shifts

    def noise_cov(self, x=None):
        return 1e-12 * torch.eye(2)


@pytest.mark.parametrize("M", [2, 4])
def test_a_transition_of_another_size_than_the_motion_bank_is_refused(M):
    """A 3-mode bank with a 2x2 transition never moved as mode 2; with a 4x4 one the unchecked gather
    drew a mode 3 the bank does not have. Both are refused naming ``transition`` and the bank's size,
    for a bank that declares its parameter batch and for one that only shows it in its output."""
    x0 = GaussianBelief(torch.zeros(2), 1e-12 * torch.eye(2))
    cv = ConstantVelocity(1, q=0.0, acceleration=[[1.0], [0.0], [-1.0]])
    shift = _ShiftBank([[1.0, 0.0], [0.0, 0.0], [-1.0, 0.0]])
    for motion in (cv, shift):
        with pytest.raises(ValueError, match=r"^transition: .*bank of 3 modes"):
            simulate_jump_system(motion, torch.eye(M), x0, 3, (8,))
        # the matching transition: each run moves as its own mode (an identity: step 1's mode throughout)
        g = torch.Generator().manual_seed(1)
        sim = simulate_jump_system(motion, torch.eye(3), x0, 3, (60,), generator=g)
        assert set(sim.modes[0].tolist()) == {0, 1, 2}
        step = torch.tensor([1.0, 0.0, -1.0])[sim.modes[0]]  # mode j's velocity (position) change a step
        close(sim.states[-1, :, 1 if motion is cv else 0], 3 * step, atol=1e-4, rtol=0)


def test_an_initial_belief_of_another_batch_than_batch_shape_is_refused():
    motion = ConstantVelocity(1, acceleration=[[0.25], [0.0], [-0.25]])
    x0 = GaussianBelief(torch.zeros(2), torch.eye(2))
    with pytest.raises(ValueError, match=r"^initial: batch \(5,\) does not broadcast to batch_shape \(4,\)"):
        simulate_jump_system(motion, PI, x0.expand(5), 4, (4,))
    for batch in ((), (1,), (4,)):  # what broadcasts to (4,) is accepted, each run its own draw
        g = torch.Generator().manual_seed(0)
        sim = simulate_jump_system(motion, PI, x0.expand(*batch), 4, (4,), generator=g)
        assert sim.states.shape == (4, 4, 2) and sim.initial_state.unique(dim=0).shape[0] == 4


def test_a_sensor_of_another_dtype_is_named_as_such():
    """A float32 sensor over float64 states read "the sensor's parameter batch () do not broadcast to the
    states' batch (50, 3)" (a bank of sensors needs modes=): the dtype is named instead."""
    sensor = PositionMeasurement(2, [0], 1.0, dtype=torch.float32)
    states = torch.zeros(5, 3, 2, dtype=torch.float64)
    with pytest.raises(TypeError, match=r"^measurement: the sensor.s \w+ is torch.float32, the states"):
        simulate_measurements(sensor, states)
    with pytest.raises(TypeError, match=r"^target: the sensor's \w+ is torch.float32"):
        simulate_multirate(sensor, sensor, states, period=2)
    assert simulate_measurements(sensor.to(torch.float64), states).dtype == torch.float64


def test_a_sensor_bank_is_checked_against_the_modes_and_the_batch():
    """Mode 2 of a 2-sensor bank read past the bank (no bounds check); a bank without ``modes`` paired
    runs with sensors (or failed deep inside). Both are refused naming the argument."""
    sensor = LinearMeasurement(torch.tensor([[1.0, 0.0]]).expand(2, 1, 2), torch.stack([1e-12 * torch.eye(1),
                                                                                         torch.eye(1)]))
    states = torch.zeros(3, 4, 2)
    with pytest.raises(ValueError, match=r"^modes: mode 2 out of range for a bank of 2 sensors"):
        simulate_measurements(sensor, states, modes=torch.tensor([0, 1, 2, 0]).expand(3, 4))
    with pytest.raises(ValueError, match=r"^measurement: the sensor's parameter batch \(2,\)"):
        simulate_measurements(sensor, states)
    with pytest.raises(ValueError, match=r"^target: the sensor's parameter batch \(2,\)"):
        simulate_multirate(sensor, PositionMeasurement(2, [0], 1.0), states, period=2)
    # a shared sensor takes any mode index, and a bank its own modes
    shared = PositionMeasurement(2, [0], 1.0)
    assert simulate_measurements(shared, states, modes=torch.full((3, 4), 5)).shape == (3, 4, 1)
    z = simulate_measurements(sensor, states, modes=torch.tensor([0, 1, 0, 1]).expand(3, 4),
                              generator=torch.Generator().manual_seed(0))
    assert bool((z[:, [0, 2]].abs() < 1e-4).all()) and bool((z[:, [1, 3]].abs() > 1e-4).all())
