"""Multiple-model estimation: transition matrices, filter banks, IMM / GPB1 / GPB2, multi-rate IMMs."""

from torchmm.models.transition import (
    LogisticTransition,
    ModeTransition,
    alpha_transition,
    transition_alpha,
    validate_transition,
)
from torchmm.multimodel.bank import FilterBank, IndexedBank, ListBank, VectorizedBank, make_bank
from torchmm.multimodel.embedding import Embedded, kinematic_index
from torchmm.multimodel.gpb2 import GPB2
from torchmm.multimodel.imm import (
    GPB1,
    IMM,
    Collapse,
    Interaction,
    MomentMixing,
    MultipleModelFilter,
    NoInteraction,
    StaticMM,
)
from torchmm.multimodel.particle import MultipleModelParticleFilter
from torchmm.multimodel.particle_mixing import ParticleMixing, mixing_indices
from torchmm.multimodel.structure import (
    ActiveSetMixing,
    AllModels,
    DropBelow,
    FixedSet,
    ModelSetPolicy,
    VariableStructureIMM,
)
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

__all__ = [
    "ActiveSetMixing",
    "DropBelow",
    "Collapse",
    "Interaction",
    "MomentMixing",
    "NoInteraction",
    "ParticleMixing",
    "AllModels",
    "FixedSet",
    "ModelSetPolicy",
    "VariableStructureIMM",
    "GPB1",
    "GPB2",
    "IMM",
    "Embedded",
    "FilterBank",
    "IndexedBank",
    "FusionIMM",
    "InfluenceGate",
    "MultiRate",
    "SourceModeVSIMM",
    "SourceTrackBelief",
    "SourceUpdateIMM",
    "TransferIMM",
    "influence_value",
    "ListBank",
    "LogisticTransition",
    "ModeTransition",
    "MultipleModelFilter",
    "MultipleModelParticleFilter",
    "StaticMM",
    "VectorizedBank",
    "alpha_transition",
    "kinematic_index",
    "make_bank",
    "mixing_indices",
    "transition_alpha",
    "validate_transition",
]
