r"""Multiple-model estimation with slow, irregular *source* measurements (paper 000).

System (1)-(3) of Gao, Luan, Zhao, Liu (2023): a Markov-jump linear target measured every step
by a fast, inaccurate sensor ``y_k`` (noise ``R``) and, when a Bernoulli ``gamma_k = 1``, by an
accurate slow sensor ``y_{S,k}`` (noise ``R_S < R``). Both arrive as one pytree of streams,
:class:`MultiRate` ``(target (T, *B, m), source (T, *B, m_S))``, the source being NaN where
``gamma_k = 0``; nothing else marks "no source": every estimator here masks per run and step.

Estimators (all modes and runs in one batched call per step, loops only over time):

* :class:`TransferIMM` - **IMM-TF** (paper 000, section 2): mixing (16)-(17), prediction
  (18)-(19), source-filter posterior ``N(m_k^j, D_k^j)``, transfer smoothing (13)-(14) (an RTS step,
  :func:`~torchmm.filters.rts_step`), transferred knowledge ``u_S = H_j F_j m_{k-1}^j``,
  correction (20)-(21), update (22)-(23), mode probabilities (24)-(26), output (27)-(28). With
  an :class:`InfluenceGate` it is **IF-TF**: the transfer is skipped where the influence value
  (29)-(36) marks the source datum as harmful.
* :class:`SourceUpdateIMM` - **IMM-SU**: every mode updated sequentially with ``y_S`` (noise
  ``R_S``) when present, then with ``y`` (the Bayes-optimal use of an undelayed source datum).
* :class:`FusionIMM` - **IMM-FU**: a separate source-only IMM track, fused into every mode's
  posterior when a source datum arrives (docs/baselines.md §3.2).
* :class:`SourceModeVSIMM` - **VSIMM**: the source track's estimate enters as an extra mode
  (docs/baselines.md §3.3).

The target-only baseline is the plain :class:`~torchmm.multimodel.IMM` on the ``target`` stream.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, ClassVar

import torch
from torch import Tensor

from torchmm.beliefs import Belief, GaussianBelief, ModeBelief, cat, where
from torchmm.beliefs.base import register_belief
from torchmm.filters.base import StepOutput
from torchmm.linalg import any_observed, cholesky, cholesky_solve, condition
from torchmm.filters.smoother import rts_step
from torchmm.models.base import MeasurementModel
from torchmm.models.linear import LinearMeasurement, matvec
from torchmm.models.streams import MultiRate
from torchmm.multimodel.bank import FilterBank, IndexedBank, ListBank, VectorizedBank
from torchmm.multimodel.imm import IMM, mode_batch, safe_log_normalize
from torchmm.validation import check_measurement

__all__ = [
    "FusionIMM",
    "InfluenceGate",
    "MultiRate",
    "SourceModeVSIMM",
    "SourceTrackBelief",
    "SourceUpdateIMM",
    "TransferIMM",
    "influence_value",
]


def _split(z: Any) -> tuple[Tensor, Tensor]:
    if isinstance(z, MultiRate):
        return z.target, z.source
    if isinstance(z, dict) and {"target", "source"} <= set(z):
        return z["target"], z["source"]
    if isinstance(z, (tuple, list)) and len(z) == 2:
        return z[0], z[1]
    raise TypeError(
        "z: expected MultiRate(target, source), a (target, source) pair or a dict with keys "
        f"'target' and 'source', got {type(z).__name__}"
    )


def _streams(imm: IMM, belief, z: Any, source: MeasurementModel) -> tuple[Tensor, Tensor]:
    """The target and source data of one step, shape-checked (``z.target`` against the bank's
    sensor, ``z.source`` against ``source``, both against the belief's batch)."""
    y, ys = _split(z)
    target_belief = belief.target if isinstance(belief, SourceTrackBelief) else belief
    y = imm._measurement(target_belief, y, "z.target")
    ys = check_measurement(ys, source.meas_dim, mode_batch(target_belief), target_belief.mode_log_probs,
                           "z.source")
    return y, ys


def _source_sensor(source, state_dim: int) -> MeasurementModel:
    if not isinstance(source, MeasurementModel):
        raise TypeError(f"source: expected a MeasurementModel (the source sensor), got {type(source).__name__}")
    if source.state_dim != state_dim:
        raise ValueError(f"source: state_dim {source.state_dim} differs from the bank's {state_dim}")
    return source


def _members(bank: FilterBank, who: str) -> list:
    """``[(filter, mode)]``: the filter computing each mode of ``bank`` and that mode's index in its
    models' parameter batch (``None`` for a list bank's unbatched filters)."""
    if isinstance(bank, VectorizedBank):
        return [(bank.filter, j) for j in range(bank.num_modes)]
    if isinstance(bank, ListBank):
        return [(f, None) for f in bank.filters]
    raise ValueError(f"bank: {who} needs a vectorised or list bank of filters with motion and measurement "
                     f"models, got {type(bank).__name__}")


def _models(filter, who: str):
    motion, sensor = filter._modules.get("motion"), filter._modules.get("measurement")
    if motion is None or sensor is None:
        raise ValueError(f"bank: {who} needs mode filters with motion and measurement models, got "
                         f"{type(filter).__name__}")
    return motion, sensor


def _per_mode(bank: FilterBank, fn, x: Tensor, u: Tensor | None, who: str) -> Tensor:
    """``fn(motion, sensor, x, u)`` evaluated with each mode's models on ``x (*B, M, d)`` (``u``
    ``(*B, 1 or M, k)``) -> ``(*B, M, d')``: one call for a vectorised bank (its models carry the
    mode axis), one per filter for a list bank."""
    members = _members(bank, who)
    if isinstance(bank, VectorizedBank):
        return fn(*_models(bank.filter, who), x, u)
    return torch.stack([fn(*_models(f, who), x[..., j, :], None if u is None else u.select(-2, 0 if u.shape[-2] == 1
                                                                                        else j))
                        for j, (f, _) in enumerate(members)], dim=-2)


def _moments(belief: Belief) -> GaussianBelief:
    """The Gaussian moments of a mode filter's belief (the belief itself for Gaussians)."""
    return belief if type(belief) is GaussianBelief else belief.estimate()


def _linearised_predict(bank: FilterBank, belief: GaussianBelief, u: Tensor | None, who: str):
    """``f_j(x)``, ``F_j P F_j^T + Q_j`` and ``F_j`` per mode (the extended Kalman prediction; the
    Kalman prediction for linear models), batch ``(*B, M)``."""
    members = _members(bank, who)

    def predict(motion, sensor, mean, cov, uj):
        F = motion.jacobian(mean, u=uj)
        return motion(mean, u=uj), F @ cov @ F.mT + motion.noise_cov(mean), F

    if isinstance(bank, VectorizedBank):
        return predict(*_models(bank.filter, who), belief.mean, belief.cov, u)
    outs = [predict(*_models(f, who), belief.mean[..., j, :], belief.cov[..., j, :, :],
                    None if u is None else u.select(-2, 0 if u.shape[-2] == 1 else j))
            for j, (f, _) in enumerate(members)]
    return tuple(torch.stack([o[i] for o in outs], dim=-1 - (1 if i == 0 else 2)) for i in range(3))


def _transfer_smoothing(reference: GaussianBelief, mean_pred: Tensor, cov_pred: Tensor, F: Tensor,
                        source_post: GaussianBelief) -> GaussianBelief:
    """The RTS step (13)-(14) from ``reference`` at ``k-1`` to the source posterior at ``k``:
    ``G = P F^T (P^-)^{-1}`` with the motion Jacobian ``F`` (:func:`~torchmm.filters.rts_step`)."""
    P = reference.cov
    gain_t = cholesky_solve(cholesky(cov_pred), F @ P)
    mean = reference.mean + (gain_t.mT @ (source_post.mean - mean_pred).unsqueeze(-1)).squeeze(-1)
    cov = P + gain_t.mT @ (source_post.cov - cov_pred) @ gain_t
    return GaussianBelief(mean, (cov + cov.mT) * 0.5)


# --------------------------------------------------------------------------------------------
# influence function (29)-(36)
# --------------------------------------------------------------------------------------------
def influence_value(estimate: Tensor, prior_mean: Tensor, z: Tensor, H: Tensor, R: Tensor,
                    weight_cov: Tensor) -> Tensor:
    r"""Influence value (33) of a datum on the loss (29) at an estimate.

    .. math::
        F(x, y) = (y - Hx)^\top R^{-1} (y - Hx) + (x - \hat x^-)^\top W^{-1} (x - \hat x^-)

        L^\top = -\Psi\,\Phi\,\Theta,\quad
        \Psi = \big(W^{-1}(\hat x - \hat x^-) - H^\top R^{-1}(y - H\hat x)\big)^\top,\quad
        \Phi = (W^{-1} + H^\top R^{-1} H)^{-1},\quad \Theta = H^\top R^{-1}

    (34)-(36) with the weight ``W`` in place of the paper's ``Q_k``. ``L`` is the sensitivity of
    ``F`` to a shift ``y -> y + rho`` (31) of the datum, through the estimate's response
    ``d x / d rho = Phi Theta``: (33) equals half of (D1), ``1/2 dF/dx (d^2F/dx^2)^{-1}
    d^2F/dxdy`` (the printed ``F`` has no factor 1/2). With ``x* = argmin_x F(x, y)`` it reduces to
    ``L^T = -(H(x - x*))^T R^{-1}``: the shift of the estimate's predicted measurement away from
    the datum-only optimum, in units of ``R``; this identity is how it is computed (``x*`` is the
    Kalman update of ``N(x^-, W)`` with ``y``: no inverse of ``W``). Missing (NaN) components are
    conditioned out of ``x*`` and give 0.

    Args:
        estimate: ``x_k`` (the estimator's output), ``(*B, n)``.
        prior_mean: ``x_k^-`` (paper: the mode-1 prediction), ``(*B, n)``.
        z: the datum ``y_k``, ``(*B, m)``.
        H: ``(*B, m, n)``; R: ``(*B, m, m)``; weight_cov: ``W``, ``(*B, n, n)`` positive definite.

    Returns:
        ``L`` as a vector, ``(*B, m)``.

    Examples:
        >>> H, R, W = torch.tensor([[1.0, 0.0]]), torch.eye(1), torch.eye(2)
        >>> x_star = torch.tensor([0.5, 0.0])  # argmin of F for prior 0 and datum 1
        >>> influence_value(x_star, torch.zeros(2), torch.ones(1), H, R, W).abs().max().item() < 1e-7
        True
    """
    # L^T = -Psi Phi Theta = -(H(x - x*))^T R^{-1} with x* = argmin F: the Kalman update of the
    # prior (x^-, W) with z (exact identity, tested against autograd); no inverse of W needed, and
    # missing components are conditioned out by the shared update
    observed = torch.isfinite(z)
    cross = weight_cov @ H.mT  # W H^T
    x_star, _, _ = condition(prior_mean, weight_cov, z - matvec(H, prior_mean), H @ cross + R, cross)
    shift = matvec(H, estimate - x_star).unsqueeze(-1)
    value = -cholesky_solve(cholesky(R), shift).squeeze(-1)  # R^{-1} shift (regularised if R is singular)
    return torch.where(observed, value, 0.0)


@dataclass(frozen=True)
class InfluenceGate:
    r"""IF-TF's rule: skip the transfer where the influence value marks the source datum harmful.

    The influence value ``L_k`` (33) is evaluated at the transferred output ``x_k`` (27) with the
    target datum ``y_k``, ``x^- = `` the prediction of mode ``mode`` (the paper uses ``j = 1``) and
    ``W = `` that mode's predicted covariance (``weight="prior"``) or its process noise
    (``weight="process"``, needs a non-singular ``Q``). The transfer at step ``k`` is judged harmful
    when ``L_k . nu_k > threshold``, with ``nu_k = y_k - H x^-`` the target innovation.

    Why this rule: ``L_k^T = -(H(x_k - x*))^T R^{-1}`` where ``x*`` is the target-only optimum of
    (29). A source datum that adds information moves ``x_k`` towards the truth, and the error of
    ``x*`` is orthogonal to the innovation, so ``E[L . nu] = 0``. A transfer that only pulls the
    estimate back towards the prediction against the fresh target datum - what an uninformative
    source (``R_S >> R``) does through the correction (20)-(21), which always uses ``R`` - gives
    ``L . nu >= 0`` at every step. ``threshold = 0`` is the sign test of that harm (negative
    transfer); larger values accept more transfers.

    Args:
        threshold: dimensionless threshold on ``L . nu`` (default 0).
        mode: index of the mode whose prediction anchors (29) (0-based; the paper's ``j = 1``).
        weight: ``"prior"`` (default) or ``"process"``.
    """

    threshold: float = 0.0
    mode: int = 0
    weight: str = "prior"

    def __post_init__(self):
        if self.weight not in {"prior", "process"}:
            raise ValueError(f"weight: expected 'prior' or 'process', got {self.weight!r}")


# --------------------------------------------------------------------------------------------
# IMM-TF / IF-TF
# --------------------------------------------------------------------------------------------
class TransferIMM(IMM):
    r"""Transfer IMM (IMM-TF, paper 000) and, with ``gate``, IF-TF.

    Per step ``k`` and mode ``j`` (all modes and runs at once):

    1. mixing and prediction as the IMM: ``x_k^{j-}, P_k^{j-}`` (16)-(19);
    2. source filter posterior ``N(m_k^j, D_k^j)``: the mode-``j`` prediction updated with
       ``y_{S,k}`` (noise ``R_S``);
    3. transfer smoothing (13)-(14): an RTS step from the target filter's estimate at ``k-1``
       (``smoothing_reference="combined"``: the output (27)-(28); ``"mixed"``: mode ``j``'s mixed
       start ``x^{0j}_{k-1}``) to ``m_{k-1}^j``, ``D_{k-1}^j``;
    4. transferred knowledge ``u_S^j = h(f_j(m_{k-1}^j))`` (``H_j F_j m`` for linear models; the
       mode's offset ``G a_j`` included) in the target sensor's space;
    5. correction (20)-(21): ``x̄ = x^- + K̄ (u_S - H x^-)``, ``P̄ = P^- - K̄ H P^-`` with
       ``K̄ = P^- H^T (H P^- H^T + R)^{-1}`` (the printed (21) has ``P̄`` on both sides; this is the
       consistent reading);
    6. update (22)-(23) of ``(x̄, P̄)`` with ``y_k``;
    7. mode probabilities (24)-(26) with ``Lambda_j = N(y_k; H x^{j-}, H P^{j-} H^T + R)``
       (``mode_likelihood="prior"``, as printed; ``"corrected"`` uses ``(x̄, P̄)`` instead);
       output (27)-(28) is ``belief.estimate()``.

    Where ``gamma_k = 0`` (source NaN) the step *is* the IMM step (bit for bit).

    Args:
        bank: one :class:`~torchmm.filters.KalmanFilter` (or EKF) whose models are mode banks.
        transition: ``(M, M)`` matrix or :class:`~torchmm.multimodel.ModeTransition`.
        source: the source sensor model (noise ``R_S``), e.g. ``PositionMeasurement(2, [0], 10.0)``.
        smoothing_reference: ``"combined"`` (default) or ``"mixed"``.
        mode_likelihood: ``"prior"`` (default, (25) as printed) or ``"corrected"``.
        gate: an :class:`InfluenceGate` (IF-TF) or None (IMM-TF).

    Shapes:
        belief: :class:`ModeBelief` (components batch ``(*B, M)``); ``z``: :class:`MultiRate`
        with ``target (*B, m)``, ``source (*B, m_S)``. ``extras``: ``"influence"`` ``(*B, m)``,
        ``"transfer_used"`` ``(*B,)`` bool, ``"source_present"`` ``(*B,)`` bool,
        ``"mode_log_likelihood"`` ``(*B, M)``, ``"mixed"``, ``"smoothed"`` (``m_{k-1}^j``,
        ``D_{k-1}^j``: batch ``(*B, M)``), ``"transferred_knowledge"`` ``u_S`` ``(*B, M, m)`` (NaN
        where no source datum).

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> motion = ConstantVelocity(1, q=1.0, acceleration=[[0.25], [0.0], [-0.25]])
        >>> tf = TransferIMM(KalmanFilter(motion, PositionMeasurement(2, [0], 100.0)),
        ...                  torch.full((3, 3), 1 / 3), PositionMeasurement(2, [0], 10.0))
        >>> belief = tf.initial_belief(GaussianBelief(torch.zeros(8, 2), 100 * torch.eye(2)))
        >>> source = torch.where(torch.rand(8, 1) < 0.6, torch.randn(8, 1), torch.nan)
        >>> out = tf.step(belief, MultiRate(torch.randn(8, 1), source))
        >>> out.belief.estimate().mean.shape, out.extras["influence"].shape
        (torch.Size([8, 2]), torch.Size([8, 1]))
    """

    def __init__(self, bank, transition, source: MeasurementModel, *, smoothing_reference: str = "combined",
                 mode_likelihood: str = "prior", gate: InfluenceGate | None = None):
        super().__init__(bank, transition)
        if smoothing_reference not in {"combined", "mixed"}:
            raise ValueError(f"smoothing_reference: expected 'combined' or 'mixed', got {smoothing_reference!r}")
        if mode_likelihood not in {"prior", "corrected"}:
            raise ValueError(f"mode_likelihood: expected 'prior' or 'corrected', got {mode_likelihood!r}")
        if gate is not None and not isinstance(gate, InfluenceGate):
            raise ValueError(f"gate: expected an InfluenceGate or None, got {type(gate).__name__}")
        _members(self.bank, type(self).__name__)
        self.source = _source_sensor(source, self.bank.state_dim)
        if gate is not None and not 0 <= gate.mode < self.num_modes:
            raise ValueError(f"gate: mode {gate.mode} out of range for {self.num_modes} modes")
        self.smoothing_reference = smoothing_reference
        self.mode_likelihood = mode_likelihood
        self.gate = gate

    def update(self, belief, z, **kwargs):
        raise NotImplementedError("TransferIMM: the transfer needs the posterior at k-1; call step()")

    def step(self, belief: ModeBelief, z, *, u: Tensor | None = None, generator=None) -> StepOutput:
        who = type(self).__name__
        y, ys = _streams(self, belief, z, self.source)
        uj = None if u is None else u.unsqueeze(-2)
        mixed = self.mix(belief)
        prior = self._predict(mixed, u=u, generator=generator)
        plain = self._update_modes(prior, y, generator=generator)  # the IMM update, Lambda_j from (25)
        present = torch.isfinite(ys).all(-1)  # gamma_k, (*B,)

        # source filter posterior N(m_k^j, D_k^j): the mode-j prediction updated with y_S, R_S
        source_post = _moments(self.bank.update(prior.components, ys.unsqueeze(-2), sensor=self.source,
                                                generator=generator).belief)
        # transfer smoothing (13)-(14) from the target filter's estimate at k-1
        if self.smoothing_reference == "combined":
            reference = belief.estimate().unsqueeze(-1).expand(*belief.batch_shape, self.num_modes)
        else:
            reference = _moments(mixed.components)
        mean_pred, cov_pred, F = _linearised_predict(self.bank, reference, uj, who)  # f_j(x_{k-1}), F P F^T + Q
        smoothed = _transfer_smoothing(reference, mean_pred, cov_pred, F, source_post)
        # transferred knowledge u_S = h(f_j(m_{k-1}^j)) (H_j F_j m for linear models), absent where gamma_k = 0
        u_s = _per_mode(self.bank, lambda motion, sensor, x, uk: sensor(motion(x, u=uk)), smoothed.mean, uj, who)
        u_s = torch.where(present[..., None, None], u_s, torch.nan)
        corrected = self.bank.update(prior.components, u_s, generator=generator)  # (20)-(21), gain from P^-
        transferred = self.bank.update(corrected.belief, y.unsqueeze(-2), generator=generator)  # (22)-(23)

        mode_log_probs = plain.belief.mode_log_probs
        if self.mode_likelihood == "corrected":
            ll = torch.where(present.unsqueeze(-1), transferred.log_likelihood, plain.extras["mode_log_likelihood"])
            joint = ll + prior.mode_log_probs
            norm = torch.logsumexp(joint, dim=-1)
            mode_log_probs = safe_log_normalize(joint, norm.unsqueeze(-1))
            log_likelihood = torch.where(any_observed(y), norm, 0.0)  # exactly 0 without a datum
        else:
            log_likelihood = plain.log_likelihood

        tentative = ModeBelief(mode_log_probs, transferred.belief).estimate()  # (27) with transfer
        influence, harmful = self._influence(tentative.mean, prior.components, y)
        used = present & ~harmful if self.gate is not None else present
        components = where(used.unsqueeze(-1), transferred.belief, plain.belief.components)
        extras = dict(plain.extras)
        extras.update(mixed=mixed, influence=influence, transfer_used=used, source_present=present,
                      smoothed=smoothed, transferred_knowledge=u_s)
        return StepOutput(ModeBelief(mode_log_probs, components), prior, log_likelihood,
                          plain.innovation, plain.innovation_cov, extras)

    def _influence(self, estimate: Tensor, prior: Belief, y: Tensor) -> tuple[Tensor, Tensor]:
        """Influence value (33) at the transferred output and the gate's harm flag."""
        gate = self.gate or InfluenceGate()
        j = gate.mode
        anchor = _moments(prior.select(-1, j))
        filter, index = _members(self.bank, type(self).__name__)[j]
        motion, sensor = _models(filter, type(self).__name__)
        at = anchor.mean.unsqueeze(-2) if index is not None else anchor.mean
        H = _mode_param(sensor.jacobian(at), index)
        R = _mode_param(sensor.noise_cov(at), index)
        if gate.weight == "prior":
            W = anchor.cov
        else:
            W = _mode_param(motion.noise_cov(at), index)
            if bool((torch.linalg.cholesky_ex(W)[1] != 0).any()):
                raise ValueError("gate: weight='process' needs a non-singular process noise Q of the "
                                 f"anchor mode {j}; use weight='prior'")
        H = H.expand(*estimate.shape[:-1], *H.shape[-2:])
        R = R.expand(*estimate.shape[:-1], *R.shape[-2:])
        value = influence_value(estimate, anchor.mean, y, H, R, W.expand(*estimate.shape[:-1], *W.shape[-2:]))
        innovation = torch.where(torch.isnan(y), 0.0, y - matvec(H, anchor.mean))
        harmful = (value * innovation).sum(-1) > gate.threshold
        return value, harmful


def _mode_param(value: Tensor, j: int | None) -> Tensor:
    """Mode ``j``'s entry of a model parameter evaluated with batch ``(*B, 1)`` (or shared; ``j = None``:
    a list bank's filter, evaluated with batch ``(*B,)``)."""
    if j is None:
        return value
    if value.dim() >= 3 and value.shape[-3] > 1:
        return value.select(-3, j)
    return value.squeeze(-3) if value.dim() >= 3 else value


# --------------------------------------------------------------------------------------------
# IMM-SU
# --------------------------------------------------------------------------------------------
class SourceUpdateIMM(IMM):
    """IMM-SU: each mode updated with the source datum (``R_S``) when present, then with ``y_k``.

    Mode likelihoods are the product of both updates' likelihoods (the exact joint likelihood of
    the two conditionally independent data); where the source is NaN the step is the IMM step.

    Args:
        bank: one Kalman/EKF filter with mode-bank models.
        transition: ``(M, M)`` matrix or :class:`~torchmm.multimodel.ModeTransition`.
        source: the source sensor model (noise ``R_S``).

    Shapes:
        as :class:`TransferIMM` (``extras["source_log_likelihood"]`` ``(*B, M)``).
    """

    def __init__(self, bank, transition, source: MeasurementModel):
        super().__init__(bank, transition)
        self.source = _source_sensor(source, self.bank.state_dim)

    def update(self, belief: ModeBelief, z, *, sensor=None, generator=None) -> StepOutput:
        if sensor is not None:
            raise TypeError("sensor: SourceUpdateIMM's sensors are the bank's (target) and source=")
        y, ys = _streams(self, belief, z, self.source)
        first = self.bank.update(belief.components, ys.unsqueeze(-2), sensor=self.source, generator=generator)
        intermediate = ModeBelief(belief.mode_log_probs + first.log_likelihood, first.belief)
        out = self._update_modes(intermediate, y, observed=any_observed(y) | any_observed(ys), generator=generator)
        # log p(y, y_S | past): the source factor is folded into the prior weights above
        out.extras["source_log_likelihood"] = first.log_likelihood
        out.extras["mode_log_likelihood"] = out.extras["mode_log_likelihood"] + first.log_likelihood
        return out._replace(prior=belief)


# --------------------------------------------------------------------------------------------
# beliefs carrying a separate source-only track (IMM-FU, VSIMM)
# --------------------------------------------------------------------------------------------
@register_belief
@dataclass(frozen=True)
class SourceTrackBelief(Belief):
    """A target-side mode belief and the separate source-only IMM track, same batch ``(*B,)``.

    ``estimate()``, ``mode_log_probs`` and ``mode_probs`` are the target side's.

    Shapes:
        target: :class:`ModeBelief`, batch ``(*B,)``; source: :class:`ModeBelief`, batch ``(*B,)``
    """

    target: ModeBelief
    source: ModeBelief

    event_dims: ClassVar[dict[str, int]] = {}

    def map_tensors(self, fn: Callable[[Tensor, int], Tensor]) -> SourceTrackBelief:
        return SourceTrackBelief(self.target.map_tensors(fn), self.source.map_tensors(fn))

    @property
    def mode_log_probs(self) -> Tensor:
        return self.target.mode_log_probs

    @property
    def mode_probs(self) -> Tensor:
        return self.target.mode_probs

    def estimate(self) -> GaussianBelief:
        return self.target.estimate()


class _SourceTrackIMM(IMM):
    """Shared set-up: the target IMM plus an independent source-only IMM over the same modes."""

    def __init__(self, bank, transition, source: MeasurementModel):
        super().__init__(bank, transition)
        self.source = _source_sensor(source, self.bank.state_dim)

    def initial_belief(self, belief: Belief, mode_probs=None, *, generator=None) -> SourceTrackBelief:
        """Both tracks start from ``belief`` (batch ``(*B,)``) -> :class:`SourceTrackBelief`."""
        start = super().initial_belief(belief, mode_probs, generator=generator)
        return SourceTrackBelief(start, start)

    def _source_step(self, belief: ModeBelief, ys: Tensor, u, generator) -> ModeBelief:
        """The source-only IMM track: the same bank and transition, updated with ``y_S`` alone."""
        prior = self._predict(self.mix(belief), u=u, generator=generator)
        return self._update_modes(prior, ys, sensor=self.source, generator=generator).belief

    def update(self, belief, z, **kwargs):
        raise NotImplementedError(f"{type(self).__name__}: call step()")


class FusionIMM(_SourceTrackIMM):
    r"""IMM-FU: track-to-track fusion of a source-only IMM track into the target IMM's modes.

    The source track is an IMM over the same mode bank driven by the source stream alone
    (prediction only between source data). When a source datum arrives, each mode's posterior is
    fused with the source track's combined estimate ``(x_s, P_s)`` by information fusion
    (``P_js = 0``): ``P_f = (P_j^{-1} + P_s^{-1})^{-1}``, ``x_f = P_f (P_j^{-1} x_j + P_s^{-1} x_s)``
    (docs/baselines.md §3.2 default), computed as the equivalent update with ``z = x_s``, ``R = P_s``.
    The fused mode estimates are what the next mixing uses (fusion inside the IMM); mode
    probabilities use the target likelihood only.

    Args:
        bank, transition: as :class:`TransferIMM`; source: the source sensor model.

    Shapes:
        belief: :class:`SourceTrackBelief`; ``z``: :class:`MultiRate`.
    """

    def step(self, belief: SourceTrackBelief, z, *, u: Tensor | None = None, generator=None) -> StepOutput:
        _check_track(belief, type(self).__name__)
        y, ys = _streams(self, belief, z, self.source)
        source = self._source_step(belief.source, ys, u, generator)
        mixed = self.mix(belief.target)
        out = self._update_modes(self._predict(mixed, u=u, generator=generator), y, generator=generator)
        present = torch.isfinite(ys).all(-1)
        track = source.estimate().unsqueeze(-1).expand(*present.shape, self.num_modes)
        comps = out.belief.components
        if type(comps) is GaussianBelief:  # information fusion in closed form
            mean, cov, _ = condition(comps.mean, comps.cov, track.mean - comps.mean, comps.cov + track.cov, comps.cov)
            fused = GaussianBelief(mean, cov)
        else:  # any other mode filter: the track's estimate as a datum x_s with noise P_s
            eye = torch.eye(track.mean.shape[-1], dtype=track.mean.dtype, device=track.mean.device)
            pseudo = LinearMeasurement.unchecked(eye, track.cov)
            fused = self.bank.update(comps, track.mean, sensor=pseudo, generator=generator).belief
        fused = where(present.unsqueeze(-1), fused, comps)
        target = ModeBelief(out.belief.mode_log_probs, fused)
        out.extras["source_present"] = present
        return out._replace(belief=SourceTrackBelief(target, source), prior=belief)


class SourceModeVSIMM(_SourceTrackIMM):
    r"""VSIMM with a mode built from the source estimate (docs/baselines.md §3.3).

    The fixed set of ``M`` modes runs as an IMM on ``y``; mode ``e`` (index ``M``, dynamics of
    mode ``extra_model``) is active per run while its probability is at least ``drop_below``.
    When a source datum arrives, mode ``e``'s prediction at ``k`` is replaced by the source
    track's combined estimate at ``k`` (time-aligned: it includes ``y_{S,k}``) with predicted
    probability ``p_new`` (default ``1/(M+1)``), the fixed modes' predicted probabilities scaled to
    ``1 - p_new``. Transition matrix over ``M + {e}``: the fixed block, ``p_ee``,
    ``p_ei = (1 - p_ee)/M``, ``p_ie = eps``, rows renormalised; over a run's active set rows are
    renormalised again (``pi_ij = p_ij / sum_{l active} p_il``).

    Args:
        bank, transition, source: as :class:`FusionIMM`.
        extra_model: index of the fixed mode whose dynamics mode ``e`` uses (e.g. the CV mode).
        p_new, p_ee, eps, drop_below: as above (defaults ``1/(M+1)``, 0.9, 0.01, 1e-3).

    Shapes:
        belief: :class:`SourceTrackBelief` whose ``target`` has ``M + 1`` modes (inactive: log
        probability ``-inf``); ``z``: :class:`MultiRate`.
    """

    def __init__(self, bank, transition, source: MeasurementModel, *, extra_model: int = 0,
                 p_new: float | None = None, p_ee: float = 0.9, eps: float = 0.01, drop_below: float = 1e-3):
        super().__init__(bank, transition, source)
        M = self.num_modes
        if not 0 <= extra_model < M:
            raise ValueError(f"extra_model: expected an index in [0, {M}), got {extra_model}")
        p_new = 1.0 / (M + 1) if p_new is None else float(p_new)
        for name, value in {"p_new": p_new, "p_ee": p_ee, "eps": eps, "drop_below": drop_below}.items():
            if not 0.0 <= value < 1.0:
                raise ValueError(f"{name}: must lie in [0, 1), got {value}")
        self.extra_model, self.p_new, self.drop_below = extra_model, p_new, drop_below
        self.p_ee, self.eps = p_ee, eps
        # the fixed modes plus mode e (a second copy of extra_model's filter), over any bank; not a
        # registered submodule: it shares self.bank's modules (no duplicate state_dict entries)
        object.__setattr__(self, "extended", IndexedBank(self.bank, [*range(M), extra_model]))

    def extended_transition(self) -> Tensor:
        """``(M + 1, M + 1)`` matrix over the fixed modes and mode ``e`` (rows sum to one)."""
        P = self.transition.matrix()
        M = self.num_modes
        top = torch.cat([P, torch.full((M, 1), self.eps, dtype=P.dtype, device=P.device)], dim=-1)
        bottom = torch.cat([torch.full((1, M), (1 - self.p_ee) / M, dtype=P.dtype, device=P.device),
                            torch.full((1, 1), self.p_ee, dtype=P.dtype, device=P.device)], dim=-1)
        full = torch.cat([top, bottom], dim=-2)
        return full / full.sum(-1, keepdim=True)

    def initial_belief(self, belief: Belief, mode_probs=None, *, generator=None) -> SourceTrackBelief:
        start = IMM.initial_belief(self, belief, mode_probs, generator=generator)
        batch = belief.batch_shape
        log_probs = torch.cat([start.mode_log_probs,
                               torch.full((*batch, 1), -torch.inf, dtype=belief.dtype, device=belief.device)], -1)
        extra = start.components.select(-1, self.extra_model).unsqueeze(-1)  # mode e: inactive until a source datum
        comps = cat([start.components, extra], dim=-1)
        return SourceTrackBelief(ModeBelief(log_probs, comps), start)

    def step(self, belief: SourceTrackBelief, z, *, u: Tensor | None = None, generator=None) -> StepOutput:
        _check_track(belief, type(self).__name__)
        y, ys = _streams(self, belief, z, self.source)
        M = self.num_modes
        source = self._source_step(belief.source, ys, u, generator)
        present = torch.isfinite(ys).all(-1)  # (*B,)
        target = belief.target
        mu = target.mode_probs  # (*B, M+1)
        active = torch.cat([torch.ones_like(mu[..., :M], dtype=torch.bool), mu[..., M:] > 0], -1)
        P = self.extended_transition() * active.unsqueeze(-2).to(mu.dtype)  # restrict to active set
        P = P / P.sum(-1, keepdim=True)
        cbar = (mu.unsqueeze(-2) @ P).squeeze(-2)  # (*B, M+1)
        weights = mu.unsqueeze(-1) * P / cbar.clamp_min(torch.finfo(mu.dtype).tiny).unsqueeze(-2)
        mixed = target.components.mix(weights)
        uj = None if u is None else u.unsqueeze(-2)
        predicted = self.extended.predict(mixed, u=uj, generator=generator)
        # a source datum: mode e restarts from the source track's estimate at k
        arrival = present.unsqueeze(-1) & (torch.arange(M + 1, device=mu.device) == M)
        track = source.estimate().unsqueeze(-1).expand(*present.shape, M + 1)
        predicted = where(arrival, _as_component(track, predicted), predicted)
        restart = torch.cat([cbar[..., :M] / cbar[..., :M].sum(-1, keepdim=True) * (1 - self.p_new),
                             torch.full_like(cbar[..., M:], self.p_new)], -1)
        cbar = torch.where(present.unsqueeze(-1), restart, cbar)
        log_cbar = torch.where(cbar > 0, cbar.clamp_min(torch.finfo(mu.dtype).tiny).log(), -torch.inf)
        prior = ModeBelief(log_cbar, predicted)
        out = self.extended.update(predicted, y.unsqueeze(-2), generator=generator)
        joint = out.log_likelihood + log_cbar
        norm = torch.logsumexp(joint, dim=-1, keepdim=True)
        log_mu = safe_log_normalize(joint, norm)
        is_extra = torch.arange(M + 1, device=mu.device) == M
        drop = is_extra & (log_mu < torch.log(torch.tensor(self.drop_below, dtype=mu.dtype)))
        log_mu = torch.where(drop, -torch.inf, log_mu)
        log_mu = safe_log_normalize(log_mu, torch.logsumexp(log_mu, dim=-1, keepdim=True))
        new_target = ModeBelief(log_mu, out.belief)
        extras = {"mode_log_likelihood": out.log_likelihood, "source_present": present,
                  "extra_mode_active": log_mu[..., M] > -torch.inf}
        if out.extras:
            extras["modes"] = dict(out.extras)
        log_likelihood = torch.where(any_observed(y), norm.squeeze(-1), 0.0)  # exactly 0 without a datum
        return StepOutput(SourceTrackBelief(new_target, source), prior, log_likelihood,
                          out.innovation, out.innovation_cov, extras)


def _check_track(belief, who: str) -> None:
    if not isinstance(belief, SourceTrackBelief):
        raise TypeError(f"belief: {who} needs a SourceTrackBelief (from {who}.initial_belief), got "
                        f"{type(belief).__name__}")


def _as_component(track: GaussianBelief, like: Belief) -> Belief:
    """The source track's estimate as a mode filter's belief of ``like``'s type (a Gaussian is
    itself; a particle set is drawn from nothing new: its particles are moved to the track's
    moments by an affine map, keeping their weights)."""
    if type(like) is GaussianBelief:
        return track
    particles = getattr(like, "particles", None)
    if particles is None:
        raise TypeError(f"SourceModeVSIMM: cannot restart a mode filter belief of type {type(like).__name__} from "
                        "the source track's estimate")
    moments = like.estimate()
    # x -> m_s + L_s L^{-1} (x - m): the weighted particle set gets mean m_s and covariance P_s exactly
    L = cholesky(moments.cov)
    L_s = cholesky(track.cov)
    white = torch.linalg.solve_triangular(L.unsqueeze(-3), (particles - moments.mean.unsqueeze(-2)).unsqueeze(-1),
                                          upper=False).squeeze(-1)
    moved = track.mean.unsqueeze(-2) + (L_s.unsqueeze(-3) @ white.unsqueeze(-1)).squeeze(-1)
    return type(like)(moved, like.log_weights.expand(moved.shape[:-1]))
