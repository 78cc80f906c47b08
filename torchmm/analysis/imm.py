r"""Analysis of the IMM input interaction (paper 001: Liang, Cheng, Jia, Pan, 2001).

All functions work on a batched IMM run's internals: posterior mode probabilities ``u(k)``,
mode-conditioned estimates ``x_j(k|k)``, the mixed (interacted) estimates ``x_j^0(k|k)`` that
start the next cycle, and the transition matrix. Deviations are measured from the *matched*
model's estimate ``x_i(k|k)`` (eqs. (4.1)-(4.4)):

.. math::
    \Delta x_j^0 = x_j^0 - x_i,\quad \Delta x = x - x_i,\quad \Delta x_j = x_j - x_i

Readings of the printed equations (see ``docs/reproduction.md``): (2.2) is the transition matrix
(row-stochastic; (2.3) is printed transposed); the numerator of (4.6) is ``||Delta x_j^0||``;
the denominators of (4.20)/(4.21) are ``pi_lj u_l`` / ``pi_jl u_j``; (4.15) is (4.14) with
``pi_ij = alpha_j`` and ``pi_jj = 1 - alpha_i``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchmm.contract import Finite, Labels, Real, Stochastic, entry_point
from torchmm.models.transition import transition_alpha

__all__ = [
    "ConclusionCheck",
    "InteractionDeviations",
    "check_conclusions",
    "check_probability_bounds",
    "delta_ratio",
    "interaction_deviations",
    "matched_model",
    "mixed_probability_bounds",
    "predicted_mode_probs",
    "ratio_bounds",
    "zeta_ratio",
]


# -- shape checks at entry (values are checked by the kinds: finite tensors, integer indices) -------
def _check_alpha(alpha: Tensor, name: str = "alpha") -> None:
    if alpha.dim() < 1 or alpha.shape[-1] < 1:
        raise ValueError(f"{name}: expected shape (M,), got {tuple(alpha.shape)}")
    if bool((alpha.detach() < 0).any()):
        raise ValueError(f"{name}: must be non-negative (the off-diagonal entries of eq. (2.2))")


def _check_modes(probs: Tensor, M: int, name: str = "mode_probs") -> None:
    if probs.dim() < 1 or probs.shape[-1] != M:
        raise ValueError(f"{name}: expected shape (*B, {M}), got {tuple(probs.shape)}")


def _check_matched(matched: Tensor, M: int, batch, name: str = "matched") -> None:
    if tuple(matched.shape) != tuple(batch):
        raise ValueError(f"{name}: expected shape {tuple(batch)} (one index per run), "
                         f"got {tuple(matched.shape)}")
    if matched.numel() and bool((matched >= M).any()):
        raise ValueError(f"{name}: model indices must be < {M}, got {int(matched.max())}")


def _check_means(means: Tensor, M: int, batch, name: str = "means") -> None:
    if means.dim() < 2 or means.shape[-2] != M or tuple(means.shape[:-2]) != tuple(batch):
        raise ValueError(f"{name}: expected shape {(*batch, M, 'n')}, got {tuple(means.shape)}")


@entry_point(alpha=Finite(), mode_probs=Finite())
def predicted_mode_probs(alpha: Tensor, mode_probs: Tensor) -> Tensor:
    r"""Eq. (3.1): ``u_j^0(k) = (1 - sum_l alpha_l) u_j(k) + alpha_j``.

    Shapes:
        alpha ``(M,)``, mode_probs ``(*B, M)`` -> ``(*B, M)``
    """
    _check_alpha(alpha)
    _check_modes(mode_probs, alpha.shape[-1])
    return (1 - alpha.sum(-1, keepdim=True)) * mode_probs + alpha


@entry_point(alpha=Finite())
def mixed_probability_bounds(alpha: Tensor) -> tuple[Tensor, Tensor]:
    r"""Eqs. (3.2)/(3.3): the interval that contains ``u_j^0(k)`` whatever ``u(k)`` is.

    ``sum(alpha) <= 1``: ``(alpha_j, 1 - sum(alpha) + alpha_j)``; otherwise ``(0, alpha_j)``.

    Shapes:
        alpha ``(M,)`` -> lower ``(M,)``, upper ``(M,)``
    """
    _check_alpha(alpha)
    return _mixed_probability_bounds(alpha)


def _mixed_probability_bounds(alpha: Tensor) -> tuple[Tensor, Tensor]:
    total = alpha.sum(-1, keepdim=True)
    dominant = total <= 1
    lower = torch.where(dominant, alpha, torch.zeros_like(alpha))
    upper = torch.where(dominant, 1 - total + alpha, alpha)
    return lower, upper


@entry_point(alpha=Finite(), mode_probs=Finite())
def ratio_bounds(alpha: Tensor, mode_probs: Tensor) -> tuple[Tensor, Tensor]:
    r"""Eq. (3.8): ``u_i^0 / u_j^0`` lies between ``u_i / u_j`` and ``alpha_i / alpha_j``.

    Valid when ``sum(alpha) <= 1`` (then (3.7) is a mediant of the two ratios).

    Shapes:
        alpha ``(M,)``, mode_probs ``(*B, M)`` -> lower, upper ``(*B, M, M)`` (entry ``[i, j]``)
    """
    _check_alpha(alpha)
    _check_modes(mode_probs, alpha.shape[-1])
    return _ratio_bounds(alpha, mode_probs)


def _ratio_bounds(alpha: Tensor, mode_probs: Tensor) -> tuple[Tensor, Tensor]:
    posterior = mode_probs.unsqueeze(-1) / mode_probs.unsqueeze(-2)
    prior = (alpha.unsqueeze(-1) / alpha.unsqueeze(-2)).expand_as(posterior)
    return torch.minimum(posterior, prior), torch.maximum(posterior, prior)


@entry_point(alpha=Finite(), mode_probs=Finite(), matched=Labels())
def delta_ratio(alpha: Tensor, mode_probs: Tensor, matched: Tensor) -> Tensor:
    r"""Eq. (4.10): ``delta(k) = alpha_i / ((1 - sum alpha) u_i(k) + alpha_i)`` for matched ``i``.

    Shapes:
        alpha ``(M,)``, mode_probs ``(*B, M)``, matched ``(*B,)`` -> ``(*B,)``
    """
    _check_alpha(alpha)
    M = alpha.shape[-1]
    _check_modes(mode_probs, M)
    _check_matched(matched, M, mode_probs.shape[:-1])
    a_i = alpha[matched]
    u_i = mode_probs.gather(-1, matched.unsqueeze(-1)).squeeze(-1)
    return a_i / ((1 - alpha.sum()) * u_i + a_i)


@entry_point(transition=Stochastic(), mode_probs=Finite(), matched=Labels())
def zeta_ratio(transition: Tensor, mode_probs: Tensor, matched: Tensor) -> Tensor:
    r"""Eq. (4.14), two-model IMM: ``zeta_j = 1 / (1 + pi_ij u_i / (pi_jj u_j))``, ``j != i``.

    Shapes:
        transition ``(2, 2)``, mode_probs ``(*B, 2)``, matched ``(*B,)`` -> ``(*B,)``
    """
    if transition.shape[-1] != 2:
        raise ValueError(f"transition: eq. (4.14) is for two models, got {transition.shape[-1]}")
    _check_modes(mode_probs, 2)
    _check_matched(matched, 2, mode_probs.shape[:-1])
    other = 1 - matched
    u_i = mode_probs.gather(-1, matched.unsqueeze(-1)).squeeze(-1)
    u_j = mode_probs.gather(-1, other.unsqueeze(-1)).squeeze(-1)
    return 1 / (1 + transition[matched, other] * u_i / (transition[other, other] * u_j))


@entry_point(means=Finite(), truth=Finite())
def matched_model(means: Tensor, truth: Tensor) -> Tensor:
    """The model whose estimate is closest to the truth ("matched model", section 4).

    Shapes:
        means ``(*B, M, n)``, truth ``(*B, n)`` -> ``(*B,)``
    """
    if means.dim() < 2:
        raise ValueError(f"means: expected shape (*B, M, n), got {tuple(means.shape)}")
    if truth.dim() < 1 or truth.shape[-1] != means.shape[-1]:
        raise ValueError(f"truth: expected shape (*B, {means.shape[-1]}), got {tuple(truth.shape)}")
    return (means - truth.unsqueeze(-2)).square().sum(-1).argmin(-1)


class InteractionDeviations(NamedTuple):
    """Norms of the deviations (4.1)-(4.4) from the matched estimate ``x_i``.

    Shapes:
        output: ``||x - x_i||``, ``(*B,)``
        mixed: ``||x_j^0 - x_i||``, ``(*B, M)``
        model: ``||x_j - x_i||``, ``(*B, M)`` (zero at ``j = i``)
    """

    output: Tensor
    mixed: Tensor
    model: Tensor


@entry_point(mode_probs=Finite(), means=Finite(), mixed_means=Finite(), matched=Labels())
def interaction_deviations(
    mode_probs: Tensor, means: Tensor, mixed_means: Tensor, matched: Tensor
) -> InteractionDeviations:
    """Deviation norms from an IMM cycle's internals (the output ``x`` is ``sum u_l x_l``, (2.13)).

    Shapes:
        mode_probs ``(*B, M)``, means ``(*B, M, n)`` (``x_j(k|k)``), mixed_means ``(*B, M, n)``
        (``x_j^0(k|k)``), matched ``(*B,)``
    """
    _check_internals(mode_probs, means, mixed_means, matched)
    return _interaction_deviations(mode_probs, means, mixed_means, matched)


def _check_internals(mode_probs: Tensor, means: Tensor, mixed_means: Tensor, matched: Tensor) -> None:
    if mode_probs.dim() < 1:
        raise ValueError(f"mode_probs: expected shape (*B, M), got {tuple(mode_probs.shape)}")
    M, batch = mode_probs.shape[-1], mode_probs.shape[:-1]
    _check_means(means, M, batch)
    if mixed_means.shape != means.shape:
        raise ValueError(f"mixed_means: expected the shape of means {tuple(means.shape)}, "
                         f"got {tuple(mixed_means.shape)}")
    _check_matched(matched, M, batch)


def _interaction_deviations(
    mode_probs: Tensor, means: Tensor, mixed_means: Tensor, matched: Tensor
) -> InteractionDeviations:
    ref = means.gather(-2, matched[..., None, None].expand(*matched.shape, 1, means.shape[-1]))
    output = torch.einsum("...m,...mn->...n", mode_probs, means)
    return InteractionDeviations(
        output=(output - ref.squeeze(-2)).norm(dim=-1),
        mixed=(mixed_means - ref).norm(dim=-1),
        model=(means - ref).norm(dim=-1),
    )


class ConclusionCheck(NamedTuple):
    """Where a conclusion's premise held, whether its claim held, and where it applies at all.

    ``applicable`` marks the entries the conclusion speaks about (its model count; for
    Conclusion 2 the mismatched models), so ``applicable & ~premise`` is where the premise failed.

    Shapes: all bool, ``(*B,)`` or ``(*B, M)`` (per model, Conclusion 2).
    """

    premise: Tensor
    holds: Tensor
    applicable: Tensor


@entry_point(transition=Stochastic(), mode_probs=Finite(), means=Finite(), mixed_means=Finite(),
             matched=Labels(), tol=Real(minimum=0.0))
def check_conclusions(
    transition: Tensor,
    mode_probs: Tensor,
    means: Tensor,
    mixed_means: Tensor,
    matched: Tensor,
    *,
    tol: float = 1e-9,
) -> dict[int, ConclusionCheck]:
    r"""Check Conclusions 1-5 of paper 001 on one interaction step of a batched IMM run.

    Claims are compared up to rounding: ``a <= b (1 + tol) + tol * scale`` with ``scale`` the
    largest ``|x_j|`` of the run (deviations are differences of estimates of that size, so their
    absolute rounding error scales with it; several claims also hold with equality in a limit,
    e.g. ``u_i -> 0`` gives ``delta -> 1``). Premises require non-degenerate deviations, i.e.
    norms above ``tol * scale``.

    1. ``sum(alpha) < 1`` (diagonally dominant (2.2)): ``||Dx_i^0|| < ||Dx||`` (``delta < 1``).
    2. ``sum(alpha) <= 1`` and ``||Dx|| <= ||Dx_j||`` for mismatched ``j``: ``||Dx_j^0|| <= ||Dx_j||``.
    3. Two models, ``pi_ij > 0``: ``||Dx_j^0|| < ||Dx_j||`` (``zeta_j < 1``), any transition matrix.
    4. Two models, ``pi_jj > pi_ij`` and ``pi_ii > pi_ji``: the matched model's start is better
       than the output, the mismatched one's worse: ``||Dx_i^0|| < ||Dx|| < ||Dx_j^0||``.
    5. Three models, ``pi_ij > 0`` for ``j != i``: some mismatched ``j`` has ``||Dx_j^0|| < ||Dx_j||``.

    Args:
        transition: ``(M, M)`` matrix the IMM used (``alpha`` is read off it when it has the
            form (2.2); Conclusions 1 and 2 need that form).
        mode_probs: ``u(k)``, ``(*B, M)``.
        means: ``x_j(k|k)``, ``(*B, M, n)``.
        mixed_means: ``x_j^0(k|k)`` of the next cycle, ``(*B, M, n)``.
        matched: index of the matched model, ``(*B,)``.

    Returns:
        ``{conclusion: ConclusionCheck}``; masks ``(*B,)`` except Conclusion 2 ``(*B, M)``.
    """
    M = transition.shape[-1]
    _check_modes(mode_probs, M)
    _check_internals(mode_probs, means, mixed_means, matched)
    dev = _interaction_deviations(mode_probs, means, mixed_means, matched)
    scale = 1 + means.abs().amax(dim=(-1, -2))
    floor = tol * scale  # (*B,): rounding level of the deviations; also the non-degeneracy threshold
    batch = matched.shape
    false = torch.zeros(batch, dtype=torch.bool, device=matched.device)
    true = ~false
    one_hot = torch.nn.functional.one_hot(matched, M).bool()
    mixed_i = dev.mixed.gather(-1, matched.unsqueeze(-1)).squeeze(-1)
    def le(a: Tensor, b: Tensor) -> Tensor:  # "a <= b" up to rounding
        f = floor if a.dim() == floor.dim() else floor.unsqueeze(-1)
        return a <= b * (1 + tol) + f

    alpha = transition_alpha(transition)
    total = None if alpha is None else float(alpha.sum())
    out: dict[int, ConclusionCheck] = {}

    # Conclusion 1 (eq. 4.10): the matched model's interacted estimate beats the output.
    premise = (dev.output > floor) & (total is not None and total < 1)
    out[1] = ConclusionCheck(premise, le(mixed_i, dev.output), true)

    # Conclusion 2 (eqs. 4.11-4.13), per mismatched model j.
    premise = (~one_hot) & (dev.model > floor.unsqueeze(-1)) & le(dev.output.unsqueeze(-1), dev.model)
    premise = premise & (total is not None and total <= 1)
    out[2] = ConclusionCheck(premise, le(dev.mixed, dev.model), ~one_hot)

    if M == 2:
        other = 1 - matched
        pi_ij = transition[matched, other]
        pi_ji = transition[other, matched]
        mixed_j = dev.mixed.gather(-1, other.unsqueeze(-1)).squeeze(-1)
        model_j = dev.model.gather(-1, other.unsqueeze(-1)).squeeze(-1)
        # Conclusion 3 (eq. 4.14).
        out[3] = ConclusionCheck((pi_ij > 0) & (model_j > floor), le(mixed_j, model_j), true)
        # Conclusion 4 (eq. 4.17 with Conclusion 1).
        dominant = (transition[other, other] > pi_ij) & (transition[matched, matched] > pi_ji)
        premise = dominant & (dev.output > floor)
        holds = le(mixed_i, dev.output) & le(dev.output, mixed_j)
        out[4] = ConclusionCheck(premise, holds, true)
    else:
        out[3] = ConclusionCheck(false, false, false)
        out[4] = ConclusionCheck(false, false, false)

    if M == 3:
        # Conclusion 5 (eqs. 4.18-4.22): not every mismatched model can get worse.
        row = transition[matched]  # (*B, M): pi_i.
        positive = torch.where(one_hot, True, row > 0).all(-1)
        nondegenerate = torch.where(one_hot, True, dev.model > floor.unsqueeze(-1)).all(-1)
        improved = (~one_hot) & le(dev.mixed, dev.model)
        out[5] = ConclusionCheck(positive & nondegenerate, improved.any(-1), true)
    else:
        out[5] = ConclusionCheck(false, false, false)
    return out


@entry_point(alpha=Finite(), mode_probs=Finite(), predicted=Finite(), tol=Real(minimum=0.0))
def check_probability_bounds(
    alpha: Tensor, mode_probs: Tensor, predicted: Tensor, *, tol: float = 1e-9
) -> dict[str, ConclusionCheck]:
    r"""Check the mode-probability bounds (3.2)/(3.3) and the ratio bound (3.8).

    Args:
        alpha: ``(M,)`` of the transition matrix (form (2.2)).
        mode_probs: ``u(k)``, ``(*B, M)``.
        predicted: the filter's predicted mode probabilities ``u^0(k)`` (``c_j``), ``(*B, M)``.

    Returns:
        ``{"3.2/3.3": ..., "3.8": ...}``; premises ``(*B, M)`` and ``(*B, M, M)``. (3.8) requires
        ``sum(alpha) <= 1``, ``alpha > 0`` and ``u > 0``, and is counted on pairs ``i != j``.
    """
    _check_alpha(alpha)
    _check_modes(mode_probs, alpha.shape[-1])
    if predicted.shape != mode_probs.shape:
        raise ValueError(f"predicted: expected the shape of mode_probs {tuple(mode_probs.shape)}, "
                         f"got {tuple(predicted.shape)}")
    lower, upper = _mixed_probability_bounds(alpha)
    margin = tol * (1 + predicted.abs())
    inside = (predicted >= lower - margin) & (predicted <= upper + margin)
    bounds = ConclusionCheck(torch.ones_like(inside), inside, torch.ones_like(inside))

    lo, hi = _ratio_bounds(alpha, mode_probs)
    ratio = predicted.unsqueeze(-1) / predicted.unsqueeze(-2)
    valid = (mode_probs > 0).unsqueeze(-1) & (mode_probs > 0).unsqueeze(-2)
    off_diagonal = ~torch.eye(alpha.shape[-1], dtype=torch.bool, device=alpha.device)
    valid = valid & off_diagonal & bool(alpha.sum() <= 1) & bool((alpha > 0).all())
    margin = tol * (1 + ratio.abs())
    holds = (ratio >= lo - margin) & (ratio <= hi + margin)
    return {"3.2/3.3": bounds, "3.8": ConclusionCheck(valid, holds, off_diagonal.expand_as(holds))}
