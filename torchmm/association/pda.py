r"""Probabilistic data association (PDA; Bar-Shalom & Tse, Automatica 11, 1975; Bar-Shalom, Daum &
Huang, IEEE Control Systems 29(6), 2009) over any Gaussian filter of the contract.

At a scan with detections ``z_1 .. z_D`` (a padded set, ``(*B, D, m)``, NaN rows absent), the filter's
own update is run for every detection at once (the detection axis leftmost, so that model banks keep
broadcasting), giving each one's innovation ``nu_k``, its covariance ``S`` and Kalman posterior. A
detection is *validated* when ``nu_k^T S^{-1} nu_k <= gamma``, the ``chi^2_m`` quantile of the gate
probability ``P_G`` (no gate: ``P_G = 1``). The association weights are

.. math::
    \beta_0 \propto 1 - P_D P_G, \qquad
    \beta_k \propto \frac{P_D\, \mathcal N(\nu_k; 0, S)}{\lambda}\ \ (k\ \text{validated}),

``lambda`` the clutter spatial density (false detections per unit volume of measurement space), and
the posterior is the moment-matched collapse of the prior (weight ``beta_0``: the target was not
detected) and the ``D`` detection-conditioned posteriors: mean ``x + K sum_k beta_k nu_k`` and
covariance ``beta_0 P + (1 - beta_0) P^c + K (sum_k beta_k nu_k nu_k^T - nu nu^T) K^T`` for a Kalman
filter, the standard PDA update (Stone Soup's ``PDAUpdater``, tests/test_pda.py).

The log-likelihood of the scan is that of the target hypothesis against "every detection is clutter",
``log(1 - P_D P_G + sum_k P_D N(nu_k; 0, S) / lambda)``: the factors common to every hypothesis about
the target (the clutter's Poisson law) are left out, so it compares models (modes, parameters) of the
target, not scans. A scan without any detection gives ``log(1 - P_D P_G)`` and leaves the belief as it
was; a scan of size 0, ``(*B, 0, m)``, is one (exactly the result of a scan whose rows are all missing).

A track whose innovation covariance ``S`` (of some mode, over an IMM) is not numerically positive
definite - a prediction whose covariance is not positive semi-definite, e.g. ``-I`` - has no gate and
no likelihood ``N(nu; 0, S)``: its run *fails* (``extras["failed"]``, a NaN log-likelihood, weights
and posterior), as a NaN prediction does, the other runs untouched (docs/robustness.md).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchmm.beliefs import GaussianBelief, ModeBelief, ModelSetBelief
from torchmm.contract import Of, Real, entry_point
from torchmm.filters.base import Filter, StepOutput
from torchmm.filters.particle import ParticleFilter
from torchmm.linalg import cholesky, solve_lower, sum_last
from torchmm.validation import check_filter_dtype

__all__ = ["PDA", "chi2_gate"]


@entry_point(probability=Real(0.0, 1.0), dim=Real(minimum=1.0))
def chi2_gate(probability: float, dim: int) -> float:
    """The ``chi^2`` quantile with ``dim`` degrees of freedom at ``probability``: the squared
    Mahalanobis radius of the ellipsoidal gate that holds a Gaussian innovation with that probability
    (``inf`` for probability 1). By bisection on the regularised incomplete gamma function, float64,
    to a relative 1e-15."""
    if probability >= 1.0:
        return math.inf
    if probability <= 0.0:
        return 0.0
    a = torch.tensor(float(dim) / 2, dtype=torch.float64)

    def cdf(x: float) -> float:
        return float(torch.special.gammainc(a, torch.tensor(x / 2, dtype=torch.float64)))

    lo, hi = 0.0, 1.0
    while cdf(hi) < probability:
        hi *= 2
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if cdf(mid) < probability:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-15 * hi:
            break
    return 0.5 * (lo + hi)


class DetectionSets(Filter):
    """The filter contract of an association over a wrapped filter ``self.filter``: a padded set of
    detections per scan (``measurement_rank = 2``: a combinator's mode axes go before ``(D, m)``),
    every scan informative (an empty one too), the wrapped filter's state, start and prediction."""

    #: a set of detections per scan, (*B, D, m)
    measurement_rank = 2
    #: the belief's last batch axis holds a run's tracks, which share each scan (JPDA and its kin)
    joint: bool = False

    @property
    def state_dim(self) -> int | None:
        return self.filter.state_dim

    def informative(self, z: Tensor) -> Tensor:
        """Every scan informs, an empty one too (nothing was detected: weight ``1 - P_D P_G``)."""
        return torch.ones(z.shape[:-2], dtype=torch.bool, device=z.device)

    @property
    def meas_dim(self) -> None:
        return None  # a set of detections, (*B, D, m): not a single measurement of the sensor

    @property
    def detections_dim(self) -> int:
        """``m`` of each detection."""
        return self.filter.meas_dim

    def check_measurements(self, measurements: Tensor, batch: torch.Size, name: str = "measurements", *,
                           time: bool = True) -> None:
        """Scans of detections ``(T, *B, D, m)`` (``time``; one scan ``(*B, D, m)`` without) against the
        belief's ``batch`` (a joint association's: the runs, its tracks last): :func:`check_scans`."""
        check_scans(measurements, self.detections_dim, batch, name, time=time, joint=self.joint)

    def check_bank_member(self, name: str, num_modes: int) -> None:
        """A joint association cannot be a mode filter: the combinator's mode axis, last, would be taken
        for its tracks (each mode a track competing for the detections, each track a run). The
        association over the multiple-model filter is the joint IMM form (``JPDA(IMM(...))``)."""
        if self.joint:
            cls = type(self).__name__
            raise TypeError(f"{name}: {cls} cannot be a mode filter (the modes would be taken for its tracks); "
                            f"associate over the multiple-model filter instead: {cls}(IMM(...), ...)")

    def initial_belief(self, belief, **kwargs):
        return self.filter.initial_belief(belief, **kwargs)

    def predict(self, belief, *, u: Tensor | None = None):
        return self.filter.predict(belief, u=u)


class PDA(DetectionSets):
    r"""Probabilistic data association over a Gaussian filter: the update takes a padded set of
    detections per scan (see the module docstring for the equations).

    Args:
        filter: a filter whose belief is a :class:`~torchmm.GaussianBelief` (Kalman, extended or
            unscented), or an IMM over such filters (a :class:`~torchmm.ModeBelief` of Gaussian
            components: the association weighs the mode-mixed likelihoods, a detection is validated
            in some mode's gate, and each mode is collapsed with weights ``beta_k mu_k^r``; Blom &
            Bloem 2000); its ``predict`` is used as it is, its ``update`` once per detection.
        detection_probability: ``P_D`` in (0, 1].
        clutter_density: ``lambda`` > 0, false detections per unit volume of measurement space.
        gate_probability: ``P_G`` in (0, 1]; 1 (default 0.99): no gate, every detection weighs.

    Shapes:
        belief: :class:`~torchmm.GaussianBelief` (or the IMM's ``ModeBelief``) with batch ``(*B,)``;
        ``z``: ``(*B, D, m)`` (a row with a non-finite entry is no detection; the set's batch broadcasts to
        ``*B``; ``D = 0``: nothing detected, as an all-NaN scan). ``extras``:
        ``"association"`` ``(*B, D + 1)`` the weights ``beta_0, beta_1 .. beta_D`` (missed detection
        first), ``"validated"`` ``(*B, D)`` bool, ``"failed"`` ``(*B,)`` bool: the update was not finite
        (a NaN prediction) or the track's innovation covariance not positive definite (a covariance
        that is not PSD): its log-likelihood, weights and posterior are NaN, the other runs untouched.

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> pda = PDA(KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0)),
        ...           detection_probability=0.9, clutter_density=0.01)
        >>> prior = GaussianBelief(torch.zeros(4, 2), torch.eye(2))
        >>> detections = torch.tensor([[0.5], [8.0], [float("nan")]]).expand(4, 3, 1)
        >>> out = pda.update(prior, detections)
        >>> out.belief.mean.shape, out.extras["association"].shape
        (torch.Size([4, 2]), torch.Size([4, 4]))
    """

    @entry_point(filter=Of(Filter), detection_probability=Real(0.0, 1.0), clutter_density=Real(positive=True),
                 gate_probability=Real(0.0, 1.0))
    def __init__(self, filter: Filter, *, detection_probability: float, clutter_density: float,
                 gate_probability: float = 0.99):
        super().__init__()
        set_association(self, filter, detection_probability, clutter_density, gate_probability)

    def update(self, belief, z: Tensor) -> StepOutput:
        check_gaussian(belief, "PDA")
        check_filter_dtype(self.filter, belief, "belief")
        batch = belief.batch_shape
        z = check_detections(z, self.detections_dim, batch, belief.dtype)
        D = z.shape[-2]
        hyp, validated, log_detected, S, singular = detection_hypotheses(self, belief, z)
        log_missed = missed_log_weight(self)
        log_weights = torch.cat([torch.full((1, *batch), log_missed, dtype=belief.dtype, device=belief.device),
                                 log_detected], dim=0)  # (1 + D, *B): the missed detection first
        # a track without a positive definite S has no gate and no likelihood: its run fails (below)
        log_likelihood = torch.where(singular, torch.nan, torch.logsumexp(log_weights, dim=0))
        weights = (log_weights - log_likelihood).exp().nan_to_num(0.0).movedim(0, -1)  # (*B, 1 + D)
        # an impossible scan (P_D P_G = 1 and no validated detection): likelihood 0, the prior kept
        impossible = torch.isneginf(log_likelihood).unsqueeze(-1)
        weights = torch.where(impossible, (torch.arange(D + 1, device=weights.device) == 0).to(weights.dtype), weights)
        # a failed update (a NaN prediction or likelihood) fails its run visibly, as every filter's does
        failed = torch.isnan(log_likelihood)
        weights = torch.where(failed.unsqueeze(-1), torch.nan, weights)
        posterior, combined = mix_hypotheses(missed_hypothesis(self, belief, hyp), hyp, weights)
        return StepOutput(posterior, belief, log_likelihood, combined, S,
                          {"association": weights, "validated": validated.movedim(0, -1), "failed": failed})


def check_detections(z, m: int, batch: torch.Size, dtype: torch.dtype, *, tracks: torch.Size | None = None
                     ) -> Tensor:
    """A scan of detections ``(*B', D, m)`` (``D`` may be 0) whose batch broadcasts to the belief's
    ``batch`` (a joint association's runs: its ``tracks`` batch without the tracks): real numbers,
    cast to ``dtype`` and expanded to ``(*batch, D, m)``. Shapes and dtypes only (no value is read).
    ``ValueError``/``TypeError`` naming ``z``."""
    what = "a scan of detections" if tracks is not None else "a padded set of detections"
    if not isinstance(z, Tensor):
        raise TypeError(f"z: expected {what} (*B, D, {m}), got {type(z).__name__}")
    if z.dim() < 2 or z.shape[-1] != m:
        raise ValueError(f"z: expected {what} (*B, D, {m}), got {tuple(z.shape)}")
    if z.is_complex() or z.dtype == torch.bool:
        raise TypeError(f"z: expected real detections, got dtype {z.dtype}")
    try:
        return z.to(dtype).expand(*batch, z.shape[-2], m)
    except RuntimeError:
        if tracks is not None:
            raise ValueError(f"z: the scan's batch {tuple(z.shape[:-2])} does not broadcast to the runs "
                             f"{tuple(batch)} of the belief's batch {tuple(tracks)} (tracks last)") from None
        raise ValueError(f"z: the detections' batch {tuple(z.shape[:-2])} does not broadcast to the belief's "
                         f"{tuple(batch)}") from None


def check_scans(z, m: int, batch: torch.Size, name: str = "measurements", *, time: bool = True,
                joint: bool = False) -> None:
    """The scans of detections given to an association, checked in the shape the caller passed (a
    combinator adds its mode axes only after): ``(T, *B', D, m)`` (``time``) or one scan
    ``(*B', D, m)``, real, ``*B'`` broadcasting to the belief's ``batch`` without enlarging it (a joint
    association's ``batch`` ends with the run's tracks, which share the scan: ``*B'`` broadcasts to the
    runs). Shapes and dtypes only (no value is read). ``ValueError``/``TypeError`` naming ``name``."""
    form = f"(T, *B, D, {m})" if time else f"(*B, D, {m})"
    what = "scans of detections" if time else "a scan of detections"
    if not isinstance(z, Tensor):
        raise TypeError(f"{name}: expected {what} {form}, got {type(z).__name__}")
    lead = 1 if time else 0
    shape = tuple(z.shape)
    if z.dim() < lead + 2 or z.shape[-1] != m:
        raise ValueError(f"{name}: expected {what} {form}, got {shape}")
    if z.is_complex() or z.dtype == torch.bool:
        raise TypeError(f"{name}: expected real detections, got dtype {z.dtype}")
    runs = batch[:-1] if joint and len(batch) else batch
    given = z.shape[lead:-2]
    try:
        fits = torch.broadcast_shapes(given, runs) == runs
    except RuntimeError:
        fits = False
    if not fits:
        where = (f"the runs {tuple(runs)} of the belief's batch {tuple(batch)} (tracks last)" if joint
                 else f"the belief's batch {tuple(batch)}")
        whose = "the scans'" if time else "the scan's"
        raise ValueError(f"{name}: {whose} batch {tuple(given)} does not broadcast to {where}; {name} {shape} are "
                         f"{form.replace(str(m), 'm')}")


def set_association(assoc, filter: Filter, detection_probability: float, clutter_density: float,
                    gate_probability: float) -> None:
    """Check and keep the association's filter and parameters (PDA, JPDA and their kin), and its
    chi-square gate."""
    if not 0.0 < detection_probability <= 1.0:
        raise ValueError(f"detection_probability: expected a probability in (0, 1], got {detection_probability}")
    if not 0.0 < gate_probability <= 1.0:
        raise ValueError(f"gate_probability: expected a probability in (0, 1], got {gate_probability}")
    name = type(assoc).__name__
    # the filter's family, at construction (its beliefs were checked only at the first step, naming belief)
    if any(isinstance(module, ParticleFilter) for module in filter.modules()):  # an IMM over them, an MM-PF
        instead = "ParticleJPDA" if getattr(assoc, "joint", False) else "ParticlePDA"
        raise TypeError(f"filter: {name} needs a filter with Gaussian beliefs (Kalman, extended, unscented, or an "
                        f"IMM/GPB over them); {type(filter).__name__} draws particles: for a ParticleFilter use "
                        f"{instead}")
    m = filter.meas_dim
    if m is None:
        raise ValueError(f"filter: {name} needs a filter with a sensor (meas_dim), got {type(filter).__name__}")
    assoc.filter = filter
    assoc.detection_probability = float(detection_probability)
    assoc.clutter_density = float(clutter_density)
    assoc.gate_probability = float(gate_probability)
    assoc.gate = chi2_gate(assoc.gate_probability, m)


def check_gaussian(belief, who: str) -> None:
    """A :class:`~torchmm.GaussianBelief`, or a :class:`~torchmm.ModeBelief` of Gaussian components."""
    inner = belief.components if isinstance(belief, ModeBelief) else belief
    if not isinstance(inner, GaussianBelief):
        raise TypeError(f"belief: {who} needs a GaussianBelief (or a ModeBelief of Gaussian components), got "
                        f"{type(belief).__name__}")


def detection_hypotheses(assoc, belief: GaussianBelief, z: Tensor):
    """Every detection's update by ``assoc.filter`` at once, its gate and its association log-weight.

    An empty scan (``D = 0``) asks the filter for the update of one absent row, which is the prior
    itself, for the track's innovation covariance (what an all-missing scan of any size gives: the
    same ``S`` and the same failure flag), and returns no hypothesis.

    Shapes:
        belief: batch ``(*B,)``; z: ``(*B, D, m)`` (non-finite rows absent) -> the update's
        :class:`StepOutput` with batch ``(D, *B)`` (detections leftmost), ``validated`` ``(D, *B)``
        bool, the log-weights ``log(P_D N(nu; 0, S) / lambda)`` ``(D, *B)`` (``-inf`` where not
        validated), the track's innovation covariance ``(*B, *E, m, m)`` (``E`` the mode axes of a
        multiple-model filter, if any; the first row's where the filter gives one per row) and
        ``singular`` ``(*B,)`` bool: an innovation covariance (of some mode) is not numerically
        positive definite (:func:`~torchmm.linalg.cholesky`'s flag), so the track has no gate and no
        likelihood (a covariance that is not PSD): the association fails its run.
    """
    batch = belief.batch_shape
    D, m = z.shape[-2:]
    present = torch.isfinite(z).all(-1)  # (*B, D)
    zs = torch.where(present.unsqueeze(-1), z, torch.nan).movedim(-2, 0)  # (D, *B, m): detections leftmost
    if D == 0:  # a shape, not a value: one absent row, the track's S (dropped below)
        zs = torch.full((1, *zs.shape[1:]), math.nan, dtype=zs.dtype, device=zs.device)
    hyp = assoc.filter.update_each(belief, zs)  # every detection's update at once (a Kalman gain once)
    if isinstance(hyp.belief, ModelSetBelief):  # a type test, no host read
        raise TypeError(f"filter: {type(assoc).__name__} over a variable-structure IMM is not supported (its policy "
                        "would select a model set in every detection hypothesis, before the association weighs "
                        "them); use an IMM over the total model set")
    nu = hyp.innovation  # (D, *B, *E, m): E the mode axes of a multiple-model filter (an IMM's M), if any
    # S broadcasts against nu: a Kalman-type filter's one S a track (update_each), factorised once
    L, singular = cholesky(hyp.innovation_cov, with_flag=True)
    white = solve_lower(L, nu.nan_to_num(0.0).unsqueeze(-1)).squeeze(-1)
    inside = sum_last(white.square()) <= assoc.gate  # (D, *B, *E)
    singular = singular.expand(inside.shape)
    modes = inside.dim() - 1 - len(batch)
    if modes:  # in some mode's gate; a singular S in some mode
        inside, singular = inside.flatten(-modes).any(-1), singular.flatten(-modes).any(-1)
    singular = singular.any(0)  # (*B,)
    S = hyp.innovation_cov.expand(*nu.shape, m)[0]  # (*B, *E, m, m): the track's (the first row's)
    if D == 0:
        hyp = StepOutput(hyp.belief[:0], hyp.prior, hyp.log_likelihood[:0], nu[:0], hyp.innovation_cov, hyp.extras)
        inside = inside[:0]
    validated = present.movedim(-1, 0) & inside  # (D, *B)
    neg_inf = torch.full((), -math.inf, dtype=belief.dtype, device=belief.device)
    log_detected = torch.where(validated, hyp.log_likelihood + math.log(assoc.detection_probability)
                               - math.log(assoc.clutter_density), neg_inf)
    return hyp, validated, log_detected, S, singular


def missed_log_weight(assoc) -> float:
    """``log(1 - P_D P_G)``, ``-inf`` when ``P_D P_G = 1``."""
    pd, pg = assoc.detection_probability, assoc.gate_probability
    return math.log1p(-pd * pg) if pd * pg < 1 else -math.inf


def _stack_gaussians(prior: GaussianBelief, hyp: GaussianBelief) -> GaussianBelief:
    """The prior and the ``D`` hypotheses ``(D, *B)`` as one belief with batch ``(*B, 1 + D)``."""
    batch = prior.batch_shape
    return GaussianBelief(torch.cat([prior.mean.expand(*batch, prior.mean.shape[-1]).unsqueeze(0), hyp.mean],
                                    0).movedim(0, -2),
                          torch.cat([prior.cov.expand(*batch, *prior.cov.shape[-2:]).unsqueeze(0), hyp.cov],
                                    0).movedim(0, -3))


def missed_hypothesis(assoc, belief, hyp: StepOutput):
    """The belief under "no detection is the target's": the prior itself, or, for a combinator whose
    update changes the set of modes (GPB2: the ``M^2`` pair hypotheses in, ``M`` modes out), its update
    without a datum (a shape test, no host read)."""
    if not isinstance(belief, ModeBelief) or hyp.belief.mode_log_probs.shape[-1] == belief.num_modes:
        return belief
    batch = belief.batch_shape
    nothing = torch.full((*batch, assoc.detections_dim), math.nan, dtype=belief.dtype, device=belief.device)
    return assoc.filter.update(belief, nothing).belief


def mix_hypotheses(belief, hyp: StepOutput, weights: Tensor):
    """The moment-matched collapse of the prior (weight ``weights[..., 0]``; :func:`missed_hypothesis`)
    and the detection hypotheses ``hyp`` (batch ``(D, *B)``), and the combined innovation
    ``sum_k beta_k nu_k``.

    For a :class:`~torchmm.ModeBelief` of Gaussian components (a filter over an IMM), mode by mode:
    the posterior probability of mode ``r`` is ``sum_k beta_k mu_k^r`` (``mu_k^r`` its probability
    under hypothesis ``k``, the prior's for ``k = 0``) and its component the collapse of the
    hypotheses' with weights ``beta_k mu_k^r`` (Blom & Bloem, IEEE TAC 45(2), 2000).

    Shapes:
        weights: ``(*B, 1 + D)`` -> a belief with batch ``(*B,)`` and ``(*B, *E, m)``.
    """
    nu = hyp.innovation.nan_to_num(0.0)  # (D, *B, *E, m)
    w = weights[..., 1:].movedim(-1, 0)
    combined = (w.reshape(*w.shape, *[1] * (nu.dim() - w.dim())) * nu).sum(0)
    if isinstance(belief, GaussianBelief):
        return _stack_gaussians(belief, hyp.belief).collapse(weights), combined
    M = belief.num_modes
    log_p = torch.cat([belief.mode_log_probs.expand(*belief.batch_shape, M).unsqueeze(0),
                       hyp.belief.mode_log_probs], 0)  # (1 + D, *B, M)
    joint = weights.movedim(-1, 0).unsqueeze(-1) * log_p.exp()  # beta_k mu_k^r
    mode_p = joint.sum(0)  # (*B, M)
    within = (joint / mode_p.clamp_min(torch.finfo(joint.dtype).tiny)).movedim(0, -1)  # (*B, M, 1 + D)
    components = _stack_gaussians(belief.components, hyp.belief.components).collapse(within)
    return ModeBelief(mode_p.log(), components), combined
