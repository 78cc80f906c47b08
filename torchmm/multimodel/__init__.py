"""Multiple-model estimation: transition matrices, filter banks, IMM / GPB1 / GPB2, multi-rate IMMs."""

from torchmm.multimodel.bank import FilterBank, ListBank, VectorizedBank, make_bank
from torchmm.multimodel.imm import GPB1, GPB2, IMM, MultipleModelFilter
from torchmm.multimodel.transfer import (
    FusionIMM,
    InfluenceGate,
    MultiRate,
    SourceModeVSIMM,
    SourceTrackBelief,
    SourceUpdateIMM,
    TransferIMM,
    influence_value,
)
from torchmm.multimodel.transition import (
    ModeTransition,
    alpha_transition,
    transition_alpha,
    validate_transition,
)

__all__ = [
    "GPB1",
    "GPB2",
    "IMM",
    "FilterBank",
    "FusionIMM",
    "InfluenceGate",
    "MultiRate",
    "SourceModeVSIMM",
    "SourceTrackBelief",
    "SourceUpdateIMM",
    "TransferIMM",
    "influence_value",
    "ListBank",
    "ModeTransition",
    "MultipleModelFilter",
    "VectorizedBank",
    "alpha_transition",
    "make_bank",
    "transition_alpha",
    "validate_transition",
]
