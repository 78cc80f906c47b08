"""Analytic properties of multiple-model estimators (paper 001's IMM analysis)."""

from torchmm.analysis.imm import (
    ConclusionCheck,
    InteractionDeviations,
    check_conclusions,
    check_probability_bounds,
    delta_ratio,
    interaction_deviations,
    matched_model,
    mixed_probability_bounds,
    predicted_mode_probs,
    ratio_bounds,
    zeta_ratio,
)

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
