"""Data association: filters that take a *set* of detections per scan (clutter, missed detections).

docs/tracking.md. :class:`PDA` (probabilistic data association) wraps any Gaussian filter of the
contract (Kalman, extended, unscented); :class:`JPDA` associates a run's tracks jointly
(:func:`jpda_marginals`: exact, loopy belief propagation or the k best events); :class:`GNN` takes the
best joint event; :class:`MHT` keeps the best global hypotheses (Murty's k best events, N-scan pruning), and
:class:`ManagedMHT` starts, confirms and deletes its own tracks in them;
:class:`IPDA` and :class:`JIPDA` add the probability that the target exists, and
:class:`ManagedTracks` starts, confirms and deletes tracks by it (or by M-of-N); :class:`SequentialSensors`
updates with several sensors in turn, each with its own detection probability, clutter and period; :class:`ParticlePDA`
and :class:`ParticleJPDA` are PDA and JPDA for particle filters.
"""

from torchmm.association.ipda import IPDA, JIPDA
from torchmm.association.jpda import GNN, JPDA, jpda_marginals
from torchmm.association.mht import MHT, HypothesisBelief
from torchmm.association.mht_tracks import ManagedMHT, TrackHypotheses
from torchmm.association.particle import ParticleJPDA, ParticlePDA
from torchmm.association.pda import PDA, chi2_gate
from torchmm.association.sensors import SensorScans, SequentialSensors
from torchmm.association.tracks import ManagedTracks, ModeTrackTable, TrackTable, position_initiator

__all__ = ["GNN", "IPDA", "JIPDA", "JPDA", "MHT", "HypothesisBelief", "PDA", "ManagedMHT", "ManagedTracks", "ModeTrackTable", "ParticleJPDA", "ParticlePDA", "SensorScans",
           "SequentialSensors", "TrackHypotheses", "TrackTable", "chi2_gate",
           "jpda_marginals", "position_initiator"]
