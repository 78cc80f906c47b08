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
  (29)-(36) marks the source datum as harmful (that step is then the IMM step).
* the baselines IMM-SU, IMM-FU and VSIMM are in :mod:`.source_baselines` (re-exported here).

The target-only baseline is the plain :class:`~torchmm.multimodel.IMM` on the ``target`` stream.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.contract import Choice, Int, Of, Real, Stochastic, entry_point
from torchmm.beliefs import Belief, GaussianBelief, ModeBelief, where
from torchmm.filters.base import Filter, StepOutput
from torchmm.linalg import any_observed, cholesky, cholesky_solve, condition
from torchmm.models.base import MeasurementModel
from torchmm.models.linear import LinearMeasurement, LinearMotion, matvec, plain_linear
from torchmm.models.streams import MultiRate
from torchmm.multimodel.bank import FilterBank, VectorizedBank
from torchmm.multimodel.imm import IMM, mode_posterior
from torchmm.validation import broadcast_shape
from torchmm.multimodel.multirate import (
    bank_members,
    check_source_sensor,
    gaussian_moments,
    member_models,
    mode_param,
    multirate_streams,
    per_mode,
)
from torchmm.multimodel.source_baselines import FusionIMM, SourceModeVSIMM, SourceTrackBelief, SourceUpdateIMM

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


def _linearised_predict(bank: FilterBank, belief: GaussianBelief, u: Tensor | None, who: str):
    """``f_j(x)``, ``F_j P F_j^T + Q_j`` and ``F_j`` per mode (the extended Kalman prediction; the
    Kalman prediction for linear models), batch ``(*B, M)``."""
    members = bank_members(bank, who)

    def predict(motion, sensor, mean, cov, uj):
        # a linear model's own F (unexpanded: one broadcast matmul), else the Jacobian at the mean
        F = motion.F if isinstance(motion, LinearMotion) else motion.jacobian(mean, u=uj)
        return motion(mean, u=uj), F @ cov @ F.mT + motion.noise_cov(mean), F

    if isinstance(bank, VectorizedBank):
        return predict(*member_models(bank.filter, who), belief.mean, belief.cov, u)
    outs = [predict(*member_models(f, who), belief.mean[..., j, :], belief.cov[..., j, :, :],
                    None if u is None else u.select(-2, 0 if u.shape[-2] == 1 else j))
            for j, (f, _) in enumerate(members)]
    stacked = []
    for i, event in enumerate((1, 2, 2)):
        parts = [o[i] for o in outs]
        shape = broadcast_shape(*(p.shape for p in parts))
        stacked.append(torch.stack([p.expand(shape) for p in parts], dim=-1 - event))
    return tuple(stacked)


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
    shift = torch.where(observed, matvec(H, estimate - x_star), 0.0).unsqueeze(-1)
    # R_oo^{-1} shift_o: R restricted to the observed components (the identity elsewhere, as condition does; a
    # correlated R's full inverse would mix a missing row's shift into the observed ones)
    pair = observed.unsqueeze(-1) & observed.unsqueeze(-2)
    R_o = torch.where(pair, R, torch.eye(R.shape[-1], dtype=R.dtype, device=R.device))
    value = -cholesky_solve(cholesky(R_o), shift).squeeze(-1)  # (regularised if R is singular)
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


InfluenceGate.__init__ = entry_point(threshold=Real(), mode=Int(0), weight=Choice("prior", "process"))(
    InfluenceGate.__init__)


# --------------------------------------------------------------------------------------------
# IMM-TF / IF-TF
# --------------------------------------------------------------------------------------------
class TransferGaussian(NamedTuple):
    """A :class:`TransferIMM`'s description of itself for the batch-last kernel
    (``filter.transfer_gaussian()``, :mod:`torchmm.kernels.batch_last.transfer`).

    Shapes (``*P``: ``()`` or the modes ``(M,)``): model: the IMM's
    :class:`~torchmm.kernels.linear.LinearGaussian` (rule ``"mix"``); H_S ``(*P, m_S, n)`` and R_S
    ``(*P, m_S, m_S)``: the source sensor; the options as the filter's.
    """

    model: Any
    H_S: Tensor
    R_S: Tensor
    smoothing_reference: str
    mode_likelihood: str
    gate: Any


@kernels.joins("transfer_gaussian", ("step", "predict", "update", "mix", "_influence"))
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

    Where ``gamma_k = 0`` (source NaN), and where the gate rejects the transfer, the step *is* the IMM
    step (bit for bit; with ``"corrected"`` its mode probabilities and log-likelihood too:
    docs/reproduction.md).

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

    @entry_point(bank=Of((Filter, FilterBank, list, tuple),
                         what="a Filter, a list of filters or a FilterBank"),
                 transition=Stochastic(), source=Of(MeasurementModel),
                 smoothing_reference=Choice("combined", "mixed"),
                 mode_likelihood=Choice("prior", "corrected"), gate=Of(InfluenceGate, optional=True))
    def __init__(self, bank, transition, source: MeasurementModel, *, smoothing_reference: str = "combined",
                 mode_likelihood: str = "prior", gate: InfluenceGate | None = None):
        super().__init__(bank, transition)
        bank_members(self.bank, type(self).__name__)
        self.source = check_source_sensor(source, self.bank.state_dim)
        if gate is not None and not 0 <= gate.mode < self.num_modes:
            raise ValueError(f"gate: mode {gate.mode} out of range for {self.num_modes} modes")
        self.smoothing_reference = smoothing_reference
        self.mode_likelihood = mode_likelihood
        self.gate = gate
        if gate is not None and gate.weight == "process":
            self._check_process_weight(gate)

    def _check_process_weight(self, gate: InfluenceGate) -> None:
        """``weight='process'`` takes the anchor mode's ``Q`` as ``W`` of (34), which the paper inverts: a
        ``ValueError`` naming ``gate.weight`` here, before any run, where ``Q`` needs no state and is singular.
        A ``Q`` that needs the state is not checked at the steps (no host read there): (33) is computed
        without inverting ``W`` (:func:`influence_value`), so a singular one gives its limit."""
        filter, index = bank_members(self.bank, type(self).__name__)[gate.mode]
        motion, _ = member_models(filter, type(self).__name__)
        try:
            Q = mode_param(motion.noise_cov(), index)
        except (TypeError, ValueError, RuntimeError, AttributeError):
            return  # (a Q that needs the state)
        if bool((torch.linalg.cholesky_ex(Q)[1] != 0).any()):
            raise ValueError(f"gate.weight: process needs a non-singular process noise Q of the anchor mode "
                             f"{gate.mode} (this one is singular, e.g. q G G^T); use weight='prior'")

    def update(self, belief, z, **kwargs):
        raise NotImplementedError("TransferIMM: the transfer needs the posterior at k-1; call step()")

    def transfer_gaussian(self) -> TransferGaussian | str:
        """This filter's description for the batch-last kernel (:class:`TransferGaussian`), or the reason
        it has none (a bank that is not linear-Gaussian, a source sensor that is not a plain
        :class:`~torchmm.models.LinearMeasurement`, a subclass that overrides the steps)."""
        if not kernels.joined(self, "transfer_gaussian"):
            return f"{type(self).__name__} has not joined the transfer kernels (or overrides their steps)"
        describe = getattr(self.bank, "linear_gaussian", None)
        model = describe() if describe is not None else f"the bank {type(self.bank).__name__} is not linear-Gaussian"
        if isinstance(model, str):
            return model
        if not (isinstance(self.source, LinearMeasurement) and plain_linear(self.source)):
            return "the source sensor is not a LinearMeasurement (its own forward and noise)"
        return TransferGaussian(model._replace(transition=self._matrix(model.F), rule="mix"), self.source.H,
                                self.source.R, self.smoothing_reference, self.mode_likelihood, self.gate)

    def step(self, belief: ModeBelief, z, *, u: Tensor | None = None, generator=None) -> StepOutput:
        who = type(self).__name__
        y, ys = multirate_streams(self, belief, z, self.source)
        uj = None if u is None else u.unsqueeze(-2)
        mixed = self.mix(belief)
        prior = self._predict(mixed, u=u, generator=generator)
        plain = self._update_modes(prior, y, generator=generator)  # the IMM update, Lambda_j from (25)
        present = torch.isfinite(ys).all(-1)  # gamma_k, (*B,)

        # source filter posterior N(m_k^j, D_k^j): the mode-j prediction updated with y_S, R_S
        source_post = gaussian_moments(self.bank.update(prior.components, ys.unsqueeze(-2), sensor=self.source,
                                                generator=generator).belief)
        # transfer smoothing (13)-(14) from the target filter's estimate at k-1
        if self.smoothing_reference == "combined":
            reference = belief.estimate().unsqueeze(-1).expand(*belief.batch_shape, self.num_modes)
        else:
            reference = gaussian_moments(mixed.components)
        mean_pred, cov_pred, F = _linearised_predict(self.bank, reference, uj, who)  # f_j(x_{k-1}), F P F^T + Q
        smoothed = _transfer_smoothing(reference, mean_pred, cov_pred, F, source_post)
        # transferred knowledge u_S = h(f_j(m_{k-1}^j)) (H_j F_j m for linear models), absent where gamma_k = 0
        u_s = per_mode(self.bank, lambda motion, sensor, x, uk: sensor(motion(x, u=uk)), smoothed.mean, uj, who)
        u_s = torch.where(present[..., None, None], u_s, torch.nan)
        corrected = self.bank.update(prior.components, u_s, generator=generator)  # (20)-(21), gain from P^-
        transferred = self.bank.update(corrected.belief, y.unsqueeze(-2), generator=generator)  # (22)-(23)

        mode_log_probs = plain.belief.mode_log_probs
        if self.mode_likelihood == "corrected":
            ll = torch.where(present.unsqueeze(-1), transferred.log_likelihood, plain.extras["mode_log_likelihood"])
            mode_log_probs, log_likelihood = mode_posterior(ll, prior.mode_log_probs, any_observed(y))
        else:
            log_likelihood = plain.log_likelihood

        tentative = ModeBelief(mode_log_probs, transferred.belief).estimate()  # (27) with transfer
        influence, harmful = self._influence(tentative.mean, prior.components, y)
        used = present & ~harmful if self.gate is not None else present
        if self.mode_likelihood == "corrected" and self.gate is not None:
            # a rejected transfer is no transfer: the plain IMM step's mode probabilities and likelihood
            mode_log_probs = torch.where(used.unsqueeze(-1), mode_log_probs, plain.belief.mode_log_probs)
            log_likelihood = torch.where(used, log_likelihood, plain.log_likelihood)
        components = where(used.unsqueeze(-1), transferred.belief, plain.belief.components)
        extras = dict(plain.extras)
        extras.update(mixed=mixed, influence=influence, transfer_used=used, source_present=present,
                      smoothed=smoothed, transferred_knowledge=u_s)
        extras["failed"] = torch.isnan(log_likelihood)  # a failed mode: NaN (docs/robustness.md)
        return StepOutput(ModeBelief(mode_log_probs, components), prior, log_likelihood,
                          plain.innovation, plain.innovation_cov, extras)

    def _influence(self, estimate: Tensor, prior: Belief, y: Tensor) -> tuple[Tensor, Tensor]:
        """Influence value (33) at the transferred output and the gate's harm flag."""
        gate = self.gate or InfluenceGate()
        j = gate.mode
        anchor = gaussian_moments(prior.select(-1, j))
        filter, index = bank_members(self.bank, type(self).__name__)[j]
        motion, sensor = member_models(filter, type(self).__name__)
        at = anchor.mean.unsqueeze(-2) if index is not None else anchor.mean
        H = mode_param(sensor.jacobian(at), index)
        R = mode_param(sensor.noise_cov(at), index)
        if gate.weight == "prior":
            W = anchor.cov
        else:
            W = mode_param(motion.noise_cov(at), index)  # (checked when built, where it needs no state)
        H = H.expand(*estimate.shape[:-1], *H.shape[-2:])
        R = R.expand(*estimate.shape[:-1], *R.shape[-2:])
        value = influence_value(estimate, anchor.mean, y, H, R, W.expand(*estimate.shape[:-1], *W.shape[-2:]))
        innovation = torch.where(torch.isnan(y), 0.0, y - matvec(H, anchor.mean))
        harmful = (value * innovation).sum(-1) > gate.threshold
        return value, harmful


