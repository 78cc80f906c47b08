"""``update_first`` of the loss and the trainer: ``belief0`` as the prior of the first measurement.

The reference is a hand-written float64 NumPy Kalman filter whose first step is an update only
(the convention of statsmodels, pykalman and Durbin and Koopman: ``a_1, P_1`` is the prior of
``y_1``), independent of torchmm's filter code.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchmm import GaussianBelief, KalmanFilter
from torchmm.learn import Trainer, negative_log_likelihood
from torchmm.models import LinearMeasurement, LinearMotion, learnable_noise

F = np.array([[1.0, 0.5], [0.0, 0.9]])
Q = np.array([[0.3, 0.05], [0.05, 0.2]])
H = np.array([[1.0, 0.0], [0.5, 1.0]])
R = np.array([[0.7, 0.1], [0.1, 0.4]])
A1 = np.array([0.4, -1.2])
P1 = np.array([[2.0, 0.3], [0.3, 1.5]])


def _numpy_loglik(z: np.ndarray, update_first: bool) -> float:
    """The prediction-error decomposition, written out: step 0 predicts unless ``update_first``."""
    a, P, total = A1.copy(), P1.copy(), 0.0
    for t, y in enumerate(z):
        if t > 0 or not update_first:
            a, P = F @ a, F @ P @ F.T + Q
        v = y - H @ a
        S = H @ P @ H.T + R
        total += -0.5 * (len(y) * np.log(2 * np.pi) + np.log(np.linalg.det(S)) + v @ np.linalg.solve(S, v))
        K = P @ H.T @ np.linalg.inv(S)
        a, P = a + K @ v, P - K @ S @ K.T
    return total


def _filter():
    return KalmanFilter(LinearMotion(torch.tensor(F), torch.tensor(Q)),
                        LinearMeasurement(torch.tensor(H), torch.tensor(R)))


@pytest.mark.parametrize("update_first", [True, False])
def test_negative_log_likelihood_matches_a_numpy_filter(update_first):
    z = np.random.default_rng(3).normal(size=(25, 2)) * 2.0
    prior = GaussianBelief(torch.tensor(A1), torch.tensor(P1))
    nll = negative_log_likelihood(_filter(), prior, torch.tensor(z), reduction="sum",
                                  update_first=update_first)
    expected = _numpy_loglik(z, update_first)
    assert abs(-nll.item() - expected) <= 1e-12 * abs(expected)
    # the two conventions differ on these data, so the comparison tells them apart
    assert abs(_numpy_loglik(z, not update_first) - expected) > 1e-3


def test_trainer_passes_update_first_to_the_loss():
    z = torch.tensor(np.random.default_rng(4).normal(size=(12, 3, 2)))
    prior = GaussianBelief(torch.tensor(A1).expand(3, 2), torch.tensor(P1).expand(3, 2, 2))
    seen = []

    def loss_fn(filter, belief0, measurements, **kwargs):
        seen.append(kwargs.get("update_first", False))
        return negative_log_likelihood(filter, belief0, measurements, **kwargs)

    for update_first in (True, False):
        kf = _filter()
        learnable_noise(kf.motion, "Q", "cholesky")
        seen.clear()
        trainer = Trainer(kf, torch.optim.SGD(kf.parameters(), lr=0.0), loss_fn=loss_fn,
                          update_first=update_first)
        record = trainer.fit(prior, z, 1)[0]
        assert seen == [update_first]
        expected = -sum(_numpy_loglik(z[:, b].numpy(), update_first) for b in range(3)) / (3 * 12)
        assert abs(record.loss - expected) <= 1e-12 * abs(expected)


def test_trainer_update_first_applies_to_the_first_tbptt_segment_only():
    z = torch.tensor(np.random.default_rng(5).normal(size=(10, 1, 2)))
    prior = GaussianBelief(torch.tensor(A1).expand(1, 2), torch.tensor(P1).expand(1, 2, 2))
    seen = []

    def loss_fn(filter, belief0, measurements, **kwargs):
        seen.append(kwargs.get("update_first", False))
        return negative_log_likelihood(filter, belief0, measurements, **kwargs)

    kf = _filter()
    learnable_noise(kf.motion, "Q", "cholesky")
    trainer = Trainer(kf, torch.optim.SGD(kf.parameters(), lr=0.0), window=4, loss_fn=loss_fn, update_first=True)
    trainer.fit(prior, z, 1)
    assert seen == [True, False, False]


def test_update_first_is_a_flag():
    prior = GaussianBelief(torch.tensor(A1), torch.tensor(P1))
    with pytest.raises(TypeError, match="^update_first"):
        negative_log_likelihood(_filter(), prior, torch.zeros(3, 2, dtype=torch.float64), update_first="yes")
    kf = _filter()
    learnable_noise(kf.motion, "Q", "cholesky")
    with pytest.raises(TypeError, match="^update_first"):
        Trainer(kf, torch.optim.SGD(kf.parameters(), lr=0.1), update_first=1)


def test_update_first_runs_an_imm():
    """An IMM with ``update_first``: step 0 is the IMM's update of ``belief0`` (no mixing, no prediction),
    then ordinary steps from its posterior; its extras are those every step has."""
    import torch

    from torchmm import IMM, ConstantVelocity, GaussianBelief, KalmanFilter, PositionMeasurement, run_filter

    motion = ConstantVelocity(1, q=0.1, acceleration=[[0.0], [1.0]], dtype=torch.float64)
    imm = IMM(KalmanFilter(motion, PositionMeasurement(2, [0], 1.0, dtype=torch.float64)),
              torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=torch.float64))
    belief0 = imm.initial_belief(GaussianBelief.create([0.0, 1.0], torch.eye(2, dtype=torch.float64)).expand(3))
    z = torch.randn(8, 3, 1, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    traj = run_filter(imm, belief0, z, update_first=True)
    first = imm.update(belief0, z[0])
    rest = run_filter(imm, first.belief, z[1:])
    torch.testing.assert_close(traj.log_likelihood[0], first.log_likelihood, rtol=0, atol=0)
    torch.testing.assert_close(traj.log_likelihood[1:], rest.log_likelihood, rtol=1e-14, atol=1e-14)
    assert "mixed" not in traj.extras and "failed" in traj.extras
    assert not torch.allclose(traj.log_likelihood, run_filter(imm, belief0, z).log_likelihood)
