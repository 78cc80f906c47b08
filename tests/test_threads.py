"""The thread rule (torchmm.runtime.thread_policy): a small problem runs on one thread, a large one at
torch's setting, and torch's setting is restored after the call, also after an error."""

from __future__ import annotations

import pytest
import torch

from torchmm import GaussianBelief, KalmanFilter, LinearMotion, PositionMeasurement, run_filter, smooth
from torchmm.learn import Trainer
from torchmm.models import learnable_noise
from torchmm.runtime import SMALL_PROBLEM, thread_policy


class Spy(LinearMotion):
    """A constant-velocity motion that records the thread count of each prediction."""

    seen: list[int]

    def forward(self, x, *, u=None):
        self.seen.append(torch.get_num_threads())
        return super().forward(x, u=u)

    def jacobian(self, x, *, u=None):
        self.seen.append(torch.get_num_threads())
        return super().jacobian(x, u=u)


def _kf():
    motion = Spy(torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=torch.float64), 0.1 * torch.eye(2, dtype=torch.float64))
    motion.seen = []
    return KalmanFilter(motion, PositionMeasurement(2, [0], 1.0, dtype=torch.float64))


def _prior(runs):
    return GaussianBelief(torch.zeros(runs, 2, dtype=torch.float64), torch.eye(2, dtype=torch.float64).expand(runs, 2, 2))


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)
    thread_policy("auto")


def test_small_problems_run_on_one_thread_large_ones_at_torchs_setting(two_threads):
    kf = _kf()
    small = 10  # 10 runs x (2 + 4) entries
    run_filter(kf, _prior(small), torch.zeros(3, small, 1, dtype=torch.float64))
    assert set(kf.motion.seen) == {1} and torch.get_num_threads() == 2
    kf.motion.seen.clear()
    large = SMALL_PROBLEM // 6 + 1  # just above the rule's size
    run_filter(kf, _prior(large), torch.zeros(2, large, 1, dtype=torch.float64))
    assert set(kf.motion.seen) == {2}
    kf.motion.seen.clear()
    assert thread_policy("torch") == "torch"
    run_filter(kf, _prior(small), torch.zeros(3, small, 1, dtype=torch.float64))
    assert set(kf.motion.seen) == {2}


def test_smooth_and_trainer_follow_the_rule_and_restore_after_errors(two_threads):
    kf = _kf()
    traj = run_filter(kf, _prior(4), torch.randn(5, 4, 1, dtype=torch.float64))
    kf.motion.seen.clear()
    smooth(kf, traj)
    assert set(kf.motion.seen) == {1} and torch.get_num_threads() == 2
    learnable_noise(kf.measurement, "R", "log_diagonal")
    kf.motion.seen.clear()
    Trainer(kf, torch.optim.Adam(kf.parameters(), lr=0.01)).fit(_prior(4), torch.randn(5, 4, 1, dtype=torch.float64), 1)
    assert set(kf.motion.seen) == {1} and torch.get_num_threads() == 2
    with pytest.raises(ValueError):
        run_filter(kf, _prior(4), torch.randn(5, 3, 1, dtype=torch.float64))  # runs of another batch
    assert torch.get_num_threads() == 2
    with pytest.raises(ValueError, match="^policy"):
        thread_policy("fast")
