"""Belief value objects with explicit batch shapes."""

from torchmm.beliefs.adaptive import AdaptiveGaussianBelief
from torchmm.beliefs.base import Belief, cat, register_belief, stack, where
from torchmm.beliefs.existence import ExistenceBelief, ModeExistenceBelief, with_existence
from torchmm.beliefs.gaussian import GaussianBelief
from torchmm.beliefs.mode import ModeBelief, ModelSetBelief
from torchmm.beliefs.ops import mix_gaussians, normalize_log_probs, psd_sqrt, symmetrize
from torchmm.beliefs.particle import ParticleBelief
from torchmm.beliefs.track import SourceTrackBelief

__all__ = [
    "AdaptiveGaussianBelief",
    "Belief",
    "ExistenceBelief",
    "GaussianBelief",
    "ModeBelief",
    "ModeExistenceBelief",
    "ModelSetBelief",
    "ParticleBelief",
    "SourceTrackBelief",
    "cat",
    "mix_gaussians",
    "normalize_log_probs",
    "psd_sqrt",
    "register_belief",
    "stack",
    "symmetrize",
    "where",
    "with_existence",
]
