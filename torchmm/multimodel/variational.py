r"""IMMs over variational-Bayes mode filters: GIMMAF (paper 004) and IMM-VBT (Shen et al. 2015).

Both are :class:`~torchmm.multimodel.IMM` — mixing (6)-(8), mode-probability update (36) with the
mode filters' ``log_likelihood`` and combination (40)-(41) are the IMM's — over one vectorised VB
filter whose motion model is a bank. For GIMMAF the mode likelihood is ``L = exp(ELBO)`` of the
per-model VB posterior after its last fixed-point iteration (eqs. (37)-(39)), read as the per-step
evidence ``p(z_k | z_{1:k-1}, model i)``; IMM-VBT uses the ELBO of its Student-t VB filter.

:class:`VariationalIMM` keeps the mode filters' diagnostics (``elbo`` per iteration, ``P^`` and the
noise-covariance estimates) in ``extras["modes"]``.
"""

from __future__ import annotations

from torchmm.contract import Choice, Finite, Flag, Int, Of, Real, Stochastic, entry_point
from torchmm.models.base import MeasurementModel, MotionModel
from torchmm.filters.variational import SkewTIWVBFilter, StudentTVBFilter
from torchmm.multimodel.imm import IMM

__all__ = ["VariationalIMM", "gimmaf", "imm_vbt"]


class VariationalIMM(IMM):
    """The :class:`IMM` over a VB bank (the return type of :func:`gimmaf` / :func:`imm_vbt`); the
    bank's ``extras`` (per mode) come back as ``extras["modes"]``, as from any IMM.

    Shapes:
        as :class:`IMM`; ``extras["modes"]`` values have batch ``(*B, M)`` (e.g.
        ``elbo (*B, M, iterations)``, ``predicted_cov (*B, M, n, n)``).
    """


@entry_point(motion=Of(MotionModel), measurement=Of(MeasurementModel), transition=Stochastic(),
             skewness=Finite(check=False), df=Finite(check=False), tau=Real(positive=True), iterations=Int(1),
             gamma_shape=Choice("derived", "printed"), elbo_history=Flag(), joseph=Flag(optional=True))
def gimmaf(motion, measurement, transition, *, skewness, df, tau: float = 3.0, iterations: int = 10,
           gamma_shape: str = "derived", elbo_history: bool = False, joseph: bool | None = None) -> VariationalIMM:
    r"""GIMMAF: IMM over skew-t + inverse-Wishart VB filters (:class:`SkewTIWVBFilter`).

    Args:
        motion: a :class:`~torchmm.models.LinearMotion` bank (``F: (M, n, n)``) with the nominal
            process noise ``Q_0``.
        measurement: :class:`~torchmm.models.LinearMeasurement` with the skew-t spread ``R``.
        transition: ``(M, M)``, ``P[i, j] = P(mode_k = j | mode_{k-1} = i)``.
        skewness, df, tau, iterations, gamma_shape, elbo_history, joseph: as :class:`SkewTIWVBFilter`.

    Shapes:
        as :class:`~torchmm.multimodel.IMM`.

    Examples:
        >>> import torch
        >>> from torchmm import GaussianBelief
        >>> from torchmm.models import CoordinatedTurn, PositionMeasurement
        >>> imm = gimmaf(CoordinatedTurn(torch.tensor([0.0, 0.1])), PositionMeasurement(4, [0, 2], 4.0),
        ...              torch.tensor([[0.9, 0.1], [0.1, 0.9]]), skewness=1.0, df=10.0)
        >>> b = imm.initial_belief(GaussianBelief(torch.zeros(3, 4), torch.eye(4)))
        >>> imm.step(b, torch.randn(3, 2)).belief.mode_probs.shape
        torch.Size([3, 2])
    """
    bank = SkewTIWVBFilter(motion, measurement, skewness=skewness, df=df, tau=tau, iterations=iterations,
                           gamma_shape=gamma_shape, elbo_history=elbo_history, joseph=joseph)
    return _build(bank, transition)


@entry_point(motion=Of(MotionModel), measurement=Of(MeasurementModel), transition=Stochastic(),
             df=Real(positive=True), iterations=Int(1), elbo_history=Flag(), joseph=Flag(optional=True))
def imm_vbt(motion, measurement, transition, *, df, iterations: int = 10,
            elbo_history: bool = False, joseph: bool | None = None) -> VariationalIMM:
    """IMM-VBT: IMM over Student-t VB filters (:class:`StudentTVBFilter`), ELBO mode likelihood.

    Args:
        motion: linear motion bank with the nominal ``Q``; measurement: linear, ``R`` the t scale;
        transition: ``(M, M)``; df: ``nu``; iterations: VB iterations per step; elbo_history,
        joseph: as :class:`StudentTVBFilter`.

    Shapes:
        as :class:`~torchmm.multimodel.IMM`.
    """
    bank = StudentTVBFilter(motion, measurement, df=df, iterations=iterations, elbo_history=elbo_history,
                            joseph=joseph)
    return _build(bank, transition)


def _build(bank, transition) -> VariationalIMM:
    """The IMM over ``bank``; errors about the bank name the argument the user passed (``motion``)."""
    try:
        return VariationalIMM(bank, transition)
    except ValueError as err:
        message = str(err)
        if message.startswith("bank: model parameter batch"):
            raise ValueError("motion: parameter batch" + message.removeprefix("bank: model parameter batch")) from None
        raise
