"""Batched simulators (ground truth and sensors) with explicit generators."""

from torchmm.simulate.detections import Detections, simulate_detections
from torchmm.simulate.markov import (
    JumpSimulation,
    bernoulli_mask,
    periodic_mask,
    sample_categorical,
    simulate_jump_system,
    simulate_measurements,
    simulate_modes,
    simulate_multirate,
)

__all__ = [
    "Detections",
    "JumpSimulation",
    "bernoulli_mask",
    "periodic_mask",
    "sample_categorical",
    "simulate_detections",
    "simulate_jump_system",
    "simulate_measurements",
    "simulate_modes",
    "simulate_multirate",
]
