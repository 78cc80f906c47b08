"""Training utilities: the loss, a learning test that recovers parameters, TBPTT, checkpoints."""

from __future__ import annotations

import math

import pytest
import torch

from torchmm import (
    IMM,
    ConstantVelocity,
    GaussianBelief,
    KalmanFilter,
    ModeTransition,
    PositionMeasurement,
    run_filter,
)
from torchmm.learn import (
    Trainer,
    load_checkpoint,
    negative_log_likelihood,
    save_checkpoint,
    truncated_segments,
)
from torchmm.models import learnable_noise
from torchmm.simulate import simulate_jump_system, simulate_measurements


def _kf(q: float, r: float) -> KalmanFilter:
    motion = learnable_noise(ConstantVelocity(1, q=q), "Q", "scale")
    sensor = learnable_noise(PositionMeasurement(2, [0], r), "R", "log_diagonal")
    return KalmanFilter(motion, sensor)


def _data(runs: int, steps: int, q: float, r: float, seed: int):
    g = torch.Generator().manual_seed(seed)
    prior = GaussianBelief.create([0.0, 1.0], torch.eye(2))
    one_mode = torch.ones(1, 1)
    truth = simulate_jump_system(ConstantVelocity(1, q=q), one_mode, prior, steps, (runs,), generator=g)
    z = simulate_measurements(PositionMeasurement(2, [0], r), truth.states, generator=g)
    return prior.expand(runs), z


def test_reductions_are_consistent():
    kf = _kf(0.5, 2.0)
    prior, z = _data(6, 15, 0.5, 2.0, seed=0)
    per_run = negative_log_likelihood(kf, prior, z, reduction="none")
    total = -run_filter(kf, prior, z).total_log_likelihood()
    torch.testing.assert_close(per_run, total)
    torch.testing.assert_close(negative_log_likelihood(kf, prior, z, reduction="sum"), total.sum())
    torch.testing.assert_close(negative_log_likelihood(kf, prior, z), total.sum() / (6 * 15))
    with pytest.raises(ValueError, match="reduction"):
        negative_log_likelihood(kf, prior, z, reduction="avg")


def test_maximum_likelihood_recovers_process_and_measurement_noise():
    """The KF likelihood is exact, so ML from 200 runs x 60 steps lands near the truth."""
    q_true, r_true = 0.5, 4.0
    prior, z = _data(200, 60, q_true, r_true, seed=1)
    kf = _kf(5.0, 40.0)  # start an order of magnitude off
    initial_loss = negative_log_likelihood(kf, prior, z).item()
    optimizer = torch.optim.LBFGS(kf.parameters(), max_iter=50, line_search_fn="strong_wolfe")
    history = Trainer(kf, optimizer).fit(prior, z, 2)
    q_hat = 5.0 * kf.motion.parametrizations.Q.original.exp().item()
    r_hat = kf.measurement.R.item()
    assert abs(math.log(q_hat / q_true)) < 0.15, q_hat
    assert abs(math.log(r_hat / r_true)) < 0.1, r_hat
    assert history[-1].loss < initial_loss
    assert history[-1].grad_norm < 1e-3  # a stationary point


def test_transition_matrix_is_learned_towards_the_truth():
    motion = ConstantVelocity(1, q=0.01, acceleration=[[1.0], [-1.0]])  # well separated modes
    sensor = PositionMeasurement(2, [0], 1.0)
    P_true = torch.tensor([[0.95, 0.05], [0.1, 0.9]])
    g = torch.Generator().manual_seed(2)
    prior = GaussianBelief.create([0.0, 0.0], torch.eye(2))
    truth = simulate_jump_system(motion, P_true, prior, 60, (100,), generator=g)
    z = simulate_measurements(sensor, truth.states, generator=g)
    imm = IMM(KalmanFilter(motion, sensor), ModeTransition(torch.full((2, 2), 0.5), learnable=True))
    optimizer = torch.optim.LBFGS(imm.parameters(), max_iter=30, line_search_fn="strong_wolfe")
    Trainer(imm, optimizer).fit(prior.expand(100), z, 1)
    learned = imm.transition.matrix().detach()
    assert (learned - P_true).abs().max() < 0.05, learned


def test_truncated_bptt_windows():
    assert truncated_segments(7, None) == [slice(0, 7)]
    assert truncated_segments(7, 3) == [slice(0, 3), slice(3, 6), slice(6, 7)]
    with pytest.raises(ValueError, match="window"):
        truncated_segments(7, 0)
    prior, z = _data(8, 20, 0.5, 2.0, seed=3)
    # window = T is plain BPTT: identical parameters after the same steps
    a, b = _kf(2.0, 8.0), _kf(2.0, 8.0)
    Trainer(a, torch.optim.SGD(a.parameters(), lr=0.1)).fit(prior, z, 3)
    Trainer(b, torch.optim.SGD(b.parameters(), lr=0.1), window=20).fit(prior, z, 3)
    for pa, pb in zip(a.parameters(), b.parameters()):
        torch.testing.assert_close(pa, pb)
    # short windows: one optimiser step per segment, and the loss still goes down
    c = _kf(2.0, 8.0)
    steps = []

    def count_steps(trainer, record):
        steps.append(trainer.optimizer.state_dict()["state"][0]["step"].item())

    trainer = Trainer(c, torch.optim.Adam(c.parameters(), lr=0.05), window=6, callbacks=[count_steps])
    history = trainer.fit(prior, z, 5)
    assert steps == [4.0 * k for k in range(1, 6)]  # ceil(20 / 6) = 4 segments per iteration
    assert history[-1].loss < history[0].loss
    # the segment start carries over (a detached posterior, not a restart from the prior)
    loss, final = negative_log_likelihood(c, prior, z[:6], return_final=True)
    assert not final.mean.requires_grad and final.mean.shape == (8, 2)


class _RecordingLogger:
    def __init__(self):
        self.calls = []

    def scalar(self, tag, value, step=0):
        self.calls.append((tag, value, step))


def test_logger_tracking_and_checkpoint_round_trip(tmp_path):
    prior, z = _data(10, 25, 0.5, 2.0, seed=4)
    logger = _RecordingLogger()

    def make():
        kf = _kf(2.0, 8.0)
        return kf, torch.optim.Adam(kf.parameters(), lr=0.05)

    kf, opt = make()
    trainer = Trainer(kf, opt, logger=logger, track=lambda: {"R": kf.measurement.R.item()},
                      checkpoint_path=tmp_path / "ckpt.pt", checkpoint_every=2)
    trainer.fit(prior, z, 3)
    tags = {t for t, _, _ in logger.calls}
    assert tags == {"train/loss", "train/grad_norm", "train/param/R"}
    assert [s for t, _, s in logger.calls if t == "train/loss"] == [1, 2, 3]
    assert (tmp_path / "ckpt.pt").exists()
    # restore into fresh modules: same parameters, optimiser state and history
    kf2, opt2 = make()
    restored = Trainer(kf2, opt2)
    restored.load(tmp_path / "ckpt.pt")
    assert restored.iteration == 3 and [r.loss for r in restored.history] == [r.loss for r in trainer.history]
    for p, p2 in zip(kf.parameters(), kf2.parameters()):
        torch.testing.assert_close(p, p2)
    # continuing either one gives the same next iterations
    more = trainer.fit(prior, z, 2)
    more2 = restored.fit(prior, z, 2)
    assert [r.iteration for r in more2] == [4, 5]
    assert [r.loss for r in more] == pytest.approx([r.loss for r in more2], rel=1e-12)
    # the module-level helpers round-trip extra data too
    path = save_checkpoint(tmp_path / "plain.pt", kf, note="hello")
    kf3, _ = make()
    assert load_checkpoint(path, kf3) == {"note": "hello"}
    torch.testing.assert_close(kf3.measurement.R, kf.measurement.R)
    with pytest.raises(ValueError, match="path"):
        load_checkpoint(tmp_path / "missing.pt", kf3)


def test_minibatches_and_bad_arguments():
    prior, z = _data(12, 10, 0.5, 2.0, seed=5)
    kf = _kf(1.0, 3.0)
    trainer = Trainer(kf, torch.optim.Adam(kf.parameters(), lr=0.01))
    history = trainer.fit(prior, z, 2, batch_size=4, generator=torch.Generator().manual_seed(0))
    assert len(history) == 2 and all(math.isfinite(r.loss) for r in history)
    with pytest.raises(ValueError, match="batch_size"):
        trainer.fit(prior, z, 1, batch_size=13)
    # a belief0 batch of neither 1 nor the 12 sequences: a ValueError naming belief0 with batch_size
    # too (it was a raw RuntimeError from expand); 1 sequence is shared by all
    bad = GaussianBelief(prior.mean[:5], prior.cov[:5])
    for size in (None, 4):
        with pytest.raises(ValueError, match="belief0" if size else "measurements"):
            trainer.fit(bad, z, 1, batch_size=size)
    one = GaussianBelief(prior.mean[:1], prior.cov[:1])
    records = trainer.fit(one, z, 1, batch_size=4, generator=torch.Generator().manual_seed(1))
    assert math.isfinite(records[0].loss)
    with pytest.raises(ValueError, match="window"):
        Trainer(kf, torch.optim.Adam(kf.parameters()), window=0)
    with pytest.raises(ValueError, match="clip_grad_norm"):
        Trainer(kf, torch.optim.Adam(kf.parameters()), clip_grad_norm=-1.0)
    clipped = Trainer(kf, torch.optim.SGD(kf.parameters(), lr=0.0), clip_grad_norm=1e-3)
    record = clipped.fit(prior, z, 1)[0]
    assert record.grad_norm > 1e-3  # the reported norm is the one before clipping


def test_a_callback_returning_true_stops_training():
    prior, z = _data(6, 10, 0.5, 2.0, seed=6)
    kf = _kf(1.0, 3.0)
    trainer = Trainer(kf, torch.optim.Adam(kf.parameters(), lr=0.01),
                      callbacks=[lambda t, r: r.iteration >= 2])
    assert [r.iteration for r in trainer.fit(prior, z, 5)] == [1, 2]


def test_fit_shows_a_progress_bar_with_the_loss(capsys):
    """Issue 30: 40 iterations ran 206 s with no output. A bar on a terminal by default (tqdm's
    ``disable=None``: not in captured output), on request anywhere, with the last loss."""
    prior, z = _data(4, 8, 0.5, 2.0, seed=7)
    kf = _kf(1.0, 3.0)
    trainer = Trainer(kf, torch.optim.Adam(kf.parameters(), lr=0.01))
    trainer.fit(prior, z, 2)
    assert "Trainer.fit" not in capsys.readouterr().err  # not a terminal: quiet by default
    records = trainer.fit(prior, z, 3, progress="training the noise")
    err = capsys.readouterr().err
    assert "training the noise" in err and "3/3" in err and f"loss={records[-1].loss:.5g}" in err
    with pytest.raises(TypeError, match=r"^progress: expected None, True, False or the bar's description"):
        trainer.fit(prior, z, 1, progress=3)
    # Trainer(progress=...) sets the default of every fit; fit's own argument overrides it
    quiet = Trainer(kf, torch.optim.Adam(kf.parameters(), lr=0.01), progress="every fit")
    quiet.fit(prior, z, 2)
    assert "every fit" in capsys.readouterr().err
    quiet.fit(prior, z, 2, progress=False)
    assert "every fit" not in capsys.readouterr().err
    with pytest.raises(TypeError, match=r"^progress: expected None, True, False or the bar's description"):
        Trainer(kf, torch.optim.Adam(kf.parameters(), lr=0.01), progress=3)
