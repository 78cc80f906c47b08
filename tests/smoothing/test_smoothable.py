"""One rule for which runs ``torchmm.smooth`` has a backward pass: ``why_not_smoothable`` (what a study asks
before it filters, experiments/estimators.py) says None exactly where ``smooth`` returns, and otherwise
the reason ``smooth`` raises. Before it, a study with ``smooth: true`` over an IMM of particle modes or a
variable-structure IMM filtered every run, made its folder and then failed with a traceback."""

from __future__ import annotations

import pytest
import torch

from torchmm import (
    GPB2,
    IMM,
    ExtendedKalmanFilter,
    GaussianBelief,
    KalmanFilter,
    ParticleFilter,
    UnscentedKalmanFilter,
    VariationalIMM,
    run_filter,
    smooth,
)
from torchmm.filters.variational import StudentTVBFilter
from torchmm.models import LinearMeasurement, LinearMotion
from torchmm.multimodel import VariableStructureIMM
from torchmm.multimodel.bank import IndexedBank, make_bank
from torchmm.multimodel.mevsmm import ExactMinimumEntropy
from torchmm.smooth_checks import why_not_smoothable

D = torch.float64
F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=D)
Q = torch.tensor([[0.3, 0.1], [0.1, 0.4]], dtype=D)  # positive definite: FFBSm has a density
P = torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=D)


def _filters():
    motion, bank = LinearMotion(F, Q), LinearMotion(F.expand(2, 2, 2), torch.stack([Q, 4 * Q]))
    sensor = LinearMeasurement(torch.tensor([[1.0, 0.0]], dtype=D), torch.eye(1, dtype=D))
    kf_bank = KalmanFilter(bank, sensor)
    pf = ParticleFilter(bank, sensor, num_particles=30, generator=torch.Generator().manual_seed(0))
    return {
        "KF": KalmanFilter(motion, sensor),
        "EKF": ExtendedKalmanFilter(motion, sensor),
        "UKF": UnscentedKalmanFilter(motion, sensor),
        "PF": ParticleFilter(motion, sensor, generator=torch.Generator().manual_seed(0)),
        "IMM": IMM(kf_bank, P),
        "GPB2": GPB2(kf_bank, P),
        "IMM-UKF": IMM([UnscentedKalmanFilter(motion, sensor), UnscentedKalmanFilter(LinearMotion(F, 4 * Q), sensor)],
                       P),
        "IMM indexed": IMM(IndexedBank(make_bank(kf_bank, 2), [0, 1]), P),
        "IMM-PF": IMM(pf, P),
        "VSIMM": VariableStructureIMM(kf_bank, P, ExactMinimumEntropy()),
        "IMM-VB": VariationalIMM(StudentTVBFilter(bank, sensor), P),
        "VB": StudentTVBFilter(motion, sensor),
    }


REFUSED = {"IMM-PF", "VSIMM", "IMM-VB", "VB", "IMM indexed"}
MULTIPLE = {"IMM", "GPB2", "IMM-UKF", "IMM indexed", "IMM-PF", "VSIMM", "IMM-VB"}


@pytest.mark.parametrize(("name", "method"), [(name, None) for name in _filters()]
                         + [(name, "kim") for name in sorted(MULTIPLE)])
def test_why_not_smoothable_is_what_smooth_does(name, method):
    filter = _filters()[name]
    prior = GaussianBelief(torch.zeros(3, 2, dtype=D), torch.eye(2, dtype=D).expand(3, 2, 2))
    options = {"generator": torch.Generator().manual_seed(1)} if filter.uses_generator else {}
    belief0 = (filter.initial_belief(prior, 40, **options) if isinstance(filter, ParticleFilter)
               else filter.initial_belief(prior, **options) if hasattr(filter, "initial_belief") else prior)
    z = torch.randn(8, 3, 1, generator=torch.Generator().manual_seed(2), dtype=D).cumsum(0)
    traj = run_filter(filter, belief0, z, **options)
    why = why_not_smoothable(filter)
    if why is None:
        out = smooth(filter, traj, method=method)
        assert out.belief.batch_shape[:2] == (8, 3)
    else:  # the same reason, whichever method is asked for
        with pytest.raises(TypeError) as caught:
            smooth(filter, traj, method=method)
        assert str(caught.value) == f"filter: {why}"
    assert (why is not None) == (name in REFUSED), why
