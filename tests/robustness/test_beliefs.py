"""Defect 3: beliefs built with the plain constructor are validated at the entry points.

The plain constructors check shapes (always, at no cost); values - finite entries, symmetric PSD
covariances, normalised probabilities and weights - are checked once where a user hands a belief
in: ``initial_belief`` and the start of :func:`~torchmm.run_filter` (never per step).
"""

from __future__ import annotations

import math

import pytest
import torch

from torchmm.filters.base import Filter

from tests.robustness.cases import CASES
from torchmm import (
    IMM,
    ConstantVelocity,
    GaussianBelief,
    KalmanFilter,
    ModeBelief,
    MultipleModelParticleFilter,
    ParticleBelief,
    ParticleFilter,
    PositionMeasurement,
    UnscentedKalmanFilter,
    run_filter,
)
from torchmm.filters.variational import AdaptiveGaussianBelief

NAN, INF = float("nan"), float("inf")
BAD_COVS = {
    "nan": ([[NAN, 0.0], [0.0, 1.0]], "NaN or infinite"),
    "inf": ([[INF, 0.0], [0.0, 1.0]], "NaN or infinite"),
    "non-symmetric": ([[1.0, 0.5], [0.0, 1.0]], "not symmetric"),
    "indefinite": ([[1.0, 2.0], [2.0, 1.0]], "not positive semi-definite"),
    "negative": ([[-1.0, 0.0], [0.0, 1.0]], "not positive semi-definite"),
}
KF = KalmanFilter(ConstantVelocity(1, dtype=torch.float64), PositionMeasurement(2, [0], 1.0, dtype=torch.float64))
Z = torch.zeros(3, 2, 1, dtype=torch.float64)


@pytest.mark.parametrize("kind", BAD_COVS)
def test_run_filter_rejects_a_bad_prior_covariance(kind):
    cov, message = BAD_COVS[kind]
    prior = GaussianBelief(torch.zeros(2, 2), torch.tensor(cov).expand(2, 2, 2))
    with pytest.raises(ValueError, match=f"belief0.cov: .*{message}"):
        run_filter(KF, prior, Z)


@pytest.mark.parametrize("mean", [[NAN, 0.0], [0.0, INF]])
def test_run_filter_rejects_a_non_finite_prior_mean(mean):
    with pytest.raises(ValueError, match="belief0.mean: contains NaN or infinite"):
        run_filter(KF, GaussianBelief(torch.tensor(mean), torch.eye(2)), Z[:, :1])


@pytest.mark.parametrize("case", [c for c in CASES if c.name not in ("ekf", "ukf")], ids=lambda c: c.name)
@pytest.mark.parametrize("kind", ["nan", "indefinite"])
def test_initial_belief_and_run_filter_reject_a_bad_prior_for_every_filter(case, kind):
    """Every family; the UKF and the PF used to clamp an indefinite covariance silently."""
    f = case.make()
    good = case.start(f, 2)
    cov = torch.tensor(BAD_COVS[kind][0])
    n = _state_dim(good)
    bad_cov = torch.eye(n).clone()
    bad_cov[:2, :2] = cov
    bad = GaussianBelief(torch.zeros(2, n), bad_cov.expand(2, n, n))
    if type(f).initial_belief is not Filter.initial_belief:  # the case starts through initial_belief
        with pytest.raises(ValueError, match=r"belief(0)?\.cov"):
            case.start(_Replace(f, bad), 2)
    else:  # the base's initial_belief validates the prior
        with pytest.raises(ValueError, match=r"belief\.cov"):
            f.initial_belief(bad)
    if isinstance(good, GaussianBelief):
        with pytest.raises(ValueError, match=r"belief0\.cov"):
            run_filter(f, bad, case.data(2, 2))


def _state_dim(belief) -> int:
    while not hasattr(belief, "mean") and not hasattr(belief, "particles"):
        belief = belief.components if hasattr(belief, "components") else belief.target
    return belief.mean.shape[-1] if hasattr(belief, "mean") else belief.particles.shape[-1]


class _Replace:
    """The filter, with every prior handed to ``initial_belief`` replaced by ``bad``."""

    def __init__(self, f, bad):
        self.f, self.bad = f, bad

    def initial_belief(self, belief, *args, **kwargs):
        return self.f.initial_belief(self.bad, *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self.f, name)


@pytest.mark.parametrize("kind", ["nan", "indefinite"])
def test_ukf_does_not_clamp_an_indefinite_or_nan_prior_silently(kind):
    ukf = UnscentedKalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0))
    with pytest.raises(ValueError, match="belief0.cov"):
        run_filter(ukf, GaussianBelief(torch.zeros(2), torch.tensor(BAD_COVS[kind][0])), Z[:, :1])


def test_particle_filter_rejects_a_bad_prior_and_bad_weights():
    pf = ParticleFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0), num_particles=10)
    with pytest.raises(ValueError, match="belief.cov: .*not positive semi-definite"):
        pf.initial_belief(GaussianBelief(torch.zeros(2), torch.tensor(BAD_COVS["indefinite"][0])))
    good = pf.initial_belief(GaussianBelief(torch.zeros(2, 2), torch.eye(2)))
    for weights, message in ((torch.full((2, 10), NAN), "NaN"), (torch.full((2, 10), INF), r"\+inf"),
                             (torch.full((2, 10), -INF), "no particle of positive weight")):
        with pytest.raises(ValueError, match=f"belief0.log_weights: .*{message}"):
            run_filter(pf, ParticleBelief(good.particles, weights), Z[:, :2])
    with pytest.raises(ValueError, match="belief0.particles"):
        run_filter(pf, ParticleBelief(good.particles * NAN, good.log_weights), Z[:, :2])
    # -inf log-weights are legitimate zero weights
    some_zero = good.log_weights.clone()
    some_zero[:, :5] = -INF
    assert torch.isfinite(run_filter(pf, ParticleBelief(good.particles, some_zero), Z[:, :2]).estimate().mean).all()


@pytest.mark.parametrize("probs", [[NAN, 0.5, 0.5], [0.5, 0.6, 0.2], [-0.1, 0.6, 0.5], [0.5, 0.5]])
def test_mode_probabilities_are_validated(probs):
    """MultipleModelParticleFilter.initial_belief(mode_probs=[nan, .5, .5]) passed its own check."""
    bank = ConstantVelocity(1, acceleration=[[0.5], [0.0], [-0.5]])
    sensor = PositionMeasurement(2, [0], 1.0)
    P = torch.full((3, 3), 1 / 3)
    prior = GaussianBelief(torch.zeros(2), torch.eye(2))
    for f in (MultipleModelParticleFilter(bank, sensor, P, 10), IMM(KalmanFilter(bank, sensor), P)):
        with pytest.raises(ValueError, match="mode_probs"):
            f.initial_belief(prior, probs)


def test_run_filter_rejects_nan_or_unnormalised_mode_probabilities():
    bank = ConstantVelocity(1, acceleration=[[0.5], [0.0], [-0.5]])
    imm = IMM(KalmanFilter(bank, PositionMeasurement(2, [0], 1.0)), torch.full((3, 3), 1 / 3))
    good = imm.initial_belief(GaussianBelief(torch.zeros(2, 2), torch.eye(2)))
    for lp, message in ((torch.full((2, 3), NAN), "NaN"), (torch.zeros(2, 3), "sum to 1")):
        with pytest.raises(ValueError, match=f"belief0.mode_log_probs: .*{message}"):
            run_filter(imm, ModeBelief(lp, good.components), Z[:, :2])
    with pytest.raises(ValueError, match="belief0.components.cov"):
        comps = GaussianBelief(good.components.mean, -good.components.cov)
        run_filter(imm, ModeBelief(good.mode_log_probs, comps), Z[:, :2])


def test_plain_constructors_check_shapes_and_convert_lists():
    with pytest.raises(ValueError, match=r"cov: expected shape \(\*B, n, n\)"):
        GaussianBelief(torch.zeros(3), torch.eye(2))
    with pytest.raises(ValueError, match=r"cov: expected shape"):
        GaussianBelief(torch.tensor(1.0), torch.eye(1))
    with pytest.raises(ValueError, match="log_weights: expected shape"):
        ParticleBelief(torch.zeros(4, 10, 2), torch.zeros(4, 9))
    with pytest.raises(ValueError, match="mode_log_probs"):
        ModeBelief(torch.tensor(0.0), GaussianBelief(torch.zeros(2), torch.eye(2)))
    with pytest.raises(TypeError, match="components"):
        ModeBelief(torch.zeros(2), torch.zeros(2))
    with pytest.raises(ValueError, match="cov: expected shape"):
        AdaptiveGaussianBelief(torch.zeros(2), torch.eye(3), torch.tensor(5.0), torch.eye(1))
    belief = GaussianBelief([1, 2], [[1, 0], [0, 1]])  # lists and integers: floating tensors
    assert belief.mean.dtype == torch.get_default_dtype() and belief.cov.dtype == belief.mean.dtype
    with pytest.raises(ValueError, match="do not broadcast"):
        GaussianBelief(torch.zeros(3, 2), torch.eye(2).expand(4, 2, 2)).batch_shape


def test_validate_returns_the_belief_and_accepts_legitimate_values():
    singular = GaussianBelief(torch.zeros(2), torch.diag(torch.tensor([1.0, 0.0])))  # PSD, singular: fine
    assert singular.validate() is singular
    lp = torch.log(torch.tensor([1.0, 0.0]))  # a zero-probability mode (-inf) is legitimate
    ModeBelief(lp, GaussianBelief(torch.zeros(2, 2), torch.eye(2))).validate()
    assert math.isinf(lp[1].item())
