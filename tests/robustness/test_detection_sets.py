"""Scans of detections under the contract (issue 44): every public association filter, enumerated.

Every public filter of ``torchmm.association`` that takes a set of detections per scan
(``measurement_rank == 2``) has a case here (a red test otherwise), also over an IMM (``PDA(IMM)``,
``IMM(PDA)``, ``JPDA(IMM)``, ...), over a filter without a shared gain (``PDA(UKF)``, ``JPDA(GPB2)``)
and over particles. For each:

* **an empty scan is an all-missing one**: the padded set kind
  (:class:`torchmm.contract.Sets`) lists its equivalents: a scan of size ``D = 0``, ``(*B, 0, m)``
  (what ``experiments.datafile.read_detections`` returns for a file whose scans are all empty), must
  give exactly the result of the scan whose rows are all missing (NaN), of any size. Compared bit for
  bit: the posterior, the log-likelihood, ``extras["failed"]``, the missed-detection weight (and the
  absent rows' weights 0), through ``update`` and through ``run_filter`` over several scans;
* the kind's invalid scans (a string, complex numbers) and the shapes it cannot take (a wrong
  detection size, a batch that enlarges the belief's) raise naming ``z``;
* a belief of the other float dtype than the filter's raises naming ``belief``; detections of the
  other float dtype are cast (as every filter's measurements are: docs/robustness.md);
* a track whose covariance is not positive semi-definite (``-I``, ``-4 I``) fails its run: ``failed``
  True and a NaN log-likelihood, as a NaN prediction does, without changing the other runs.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import pytest
import torch

from torchmm import GPB2, IMM, GaussianBelief, KalmanFilter, ParticleFilter, UnscentedKalmanFilter, run_filter
from torchmm.association import (
    GNN,
    MHT,
    HypothesisBelief,
    IPDA,
    JIPDA,
    JPDA,
    PDA,
    ManagedMHT,
    ManagedTracks,
    ParticleJPDA,
    ParticlePDA,
    position_initiator,
)
from torchmm.beliefs import ExistenceBelief, ModeBelief, ModeExistenceBelief, ParticleBelief
from torchmm.contract import Sets
from torchmm.filters.base import Filter
from torchmm.models import ConstantVelocity, PositionMeasurement

RUNS, TRACKS, M = 3, 2, 1
P2 = [[0.9, 0.1], [0.2, 0.8]]
SCAN = Sets(axis=-2, missing=math.nan)  # a scan of detections: (*B, D, m), a NaN row is no detection


def _cv(dtype=torch.float64):
    return ConstantVelocity(1, q=0.5, dtype=dtype)


def _cvp(dtype=torch.float64):
    return ConstantVelocity(1, q=0.5, noise="continuous", dtype=dtype)


def _bank():
    return ConstantVelocity(1, q=0.5, acceleration=[[0.0], [1.0]], dtype=torch.float64)


def _pos(dtype=torch.float64):
    return PositionMeasurement(2, [0], 1.0, dtype=dtype)


def _kf():
    return KalmanFilter(_cv(), _pos())


def _imm():
    return IMM(KalmanFilter(_bank(), _pos()), torch.tensor(P2))


def _gpb2():
    return GPB2(KalmanFilter(_bank(), _pos()), torch.tensor(P2))


def _pf(bank=False):
    motion = ConstantVelocity(1, q=0.5, noise="continuous", acceleration=[[0.0], [1.0]], dtype=torch.float64) \
        if bank else _cvp()
    # (an IMM's particle interaction joins the modes' particle sets: num_particles resamples them back)
    return ParticleFilter(motion, _pos(), num_particles=64, generator=torch.Generator().manual_seed(3))


ASSOC = {"detection_probability": 0.9, "clutter_density": 0.05}


def _prior(batch) -> GaussianBelief:
    mean = torch.zeros(*batch, 2, dtype=torch.float64)
    if len(batch) > 1:  # the tracks of a run 4 m apart
        mean[..., 0] = 4.0 * torch.arange(batch[-1], dtype=torch.float64)
    return GaussianBelief(mean, 4.0 * torch.eye(2, dtype=torch.float64).expand(*batch, 2, 2))


@dataclass
class DetectionCase:
    name: str
    make: Callable[[], Filter]
    start: Callable[[Any], Any]  # filter -> belief0, batch (RUNS,) or (RUNS, TRACKS)
    tracks: bool = False  # the belief's batch ends with a run's tracks
    particles: bool = False
    managed: bool = False


def _gauss(f):
    return f.initial_belief(_prior((RUNS,)))


def _joint(f):
    return f.initial_belief(_prior((RUNS, TRACKS)))


def _particles(runs_shape):
    return lambda f: f.filter.initial_belief(_prior(runs_shape), 64, generator=torch.Generator().manual_seed(4))


def _imm_particles(f):
    pf = f.bank.filter
    return f.initial_belief(pf.initial_belief(_prior((RUNS,)), 64, generator=torch.Generator().manual_seed(4)))


def _managed(joint):
    return lambda: ManagedTracks(joint(), capacity=3, initiate=position_initiator(2, [0], 1.0, 4.0),
                                 birth_existence=0.2)


CASES = [
    DetectionCase("pda", lambda: PDA(_kf(), **ASSOC), _gauss),
    DetectionCase("pda_ukf", lambda: PDA(UnscentedKalmanFilter(_cv(), _pos()), **ASSOC), _gauss),
    DetectionCase("pda_imm", lambda: PDA(_imm(), **ASSOC), _gauss),
    DetectionCase("pda_gpb2", lambda: PDA(_gpb2(), **ASSOC), _gauss),
    DetectionCase("imm_pda", lambda: IMM(PDA(KalmanFilter(_bank(), _pos()), **ASSOC), torch.tensor(P2)), _gauss),
    DetectionCase("jpda", lambda: JPDA(_kf(), **ASSOC), _joint, tracks=True),
    DetectionCase("jpda_lbp", lambda: JPDA(_kf(), method="lbp", **ASSOC), _joint, tracks=True),
    DetectionCase("jpda_imm", lambda: JPDA(_imm(), **ASSOC), _joint, tracks=True),
    DetectionCase("jpda_gpb2", lambda: JPDA(_gpb2(), **ASSOC), _joint, tracks=True),
    DetectionCase("gnn", lambda: GNN(_kf(), **ASSOC), _joint, tracks=True),
    DetectionCase("gnn_imm", lambda: GNN(_imm(), **ASSOC), _joint, tracks=True),
    DetectionCase("mht", lambda: MHT(_kf(), hypotheses=3, **ASSOC), _joint),
    DetectionCase("mht_imm", lambda: MHT(_imm(), hypotheses=3, **ASSOC), _joint),
    DetectionCase("ipda", lambda: IPDA(_kf(), **ASSOC), _gauss),
    DetectionCase("ipda_imm", lambda: IPDA(_imm(), **ASSOC), _gauss),
    DetectionCase("jipda", lambda: JIPDA(_kf(), **ASSOC), _joint, tracks=True),
    DetectionCase("jipda_lbp", lambda: JIPDA(_kf(), method="lbp", **ASSOC), _joint, tracks=True),
    DetectionCase("jipda_imm", lambda: JIPDA(_imm(), **ASSOC), _joint, tracks=True),
    DetectionCase("particle_pda", lambda: ParticlePDA(_pf(), **ASSOC), _particles((RUNS,)), particles=True),
    DetectionCase("imm_particle_pda", lambda: IMM(ParticlePDA(_pf(bank=True), **ASSOC), torch.tensor(P2)),
                  _imm_particles, particles=True),
    DetectionCase("particle_jpda", lambda: ParticleJPDA(_pf(), **ASSOC), _particles((RUNS, TRACKS)),
                  tracks=True, particles=True),
    DetectionCase("particle_jpda_lbp", lambda: ParticleJPDA(_pf(), method="lbp", **ASSOC),
                  _particles((RUNS, TRACKS)), tracks=True, particles=True),
    DetectionCase("managed", _managed(lambda: JIPDA(_kf(), **ASSOC)), lambda f: f.initial_belief((RUNS,)),
                  managed=True),
    DetectionCase("managed_lbp", _managed(lambda: JIPDA(_kf(), method="lbp", **ASSOC)),
                  lambda f: f.initial_belief((RUNS,)), managed=True),
    DetectionCase("managed_imm", _managed(lambda: JIPDA(_imm(), method="lbp", **ASSOC)),
                  lambda f: f.initial_belief((RUNS,)), managed=True),
    DetectionCase("managed_mht", lambda: ManagedMHT(_imm(), capacity=3, initiate=position_initiator(2, [0], 1.0, 4.0),
                                                    birth_density=0.01, hypotheses=3, **ASSOC),
                  lambda f: f.initial_belief((RUNS,)), managed=True),
]
# the Gaussian cases whose filter factorises S from the prior's covariance (the UKF's sigma points take a
# square root of it that clamps negative eigenvalues to 0, docs/robustness.md: S = R, positive definite)
GAUSSIAN = [c for c in CASES if not c.particles and not c.managed and c.name != "pda_ukf"]


def _detection_filters() -> dict[str, type]:
    """Every public filter of torchmm.association that takes a set of detections per scan."""
    module = importlib.import_module("torchmm.association")
    out = {}
    for name in module.__all__:
        obj = getattr(module, name)
        if inspect.isclass(obj) and issubclass(obj, Filter) and getattr(obj, "measurement_rank", 1) == 2:
            out[name] = obj
    return out


def _covered(f) -> set[type]:
    """The association classes a case's filter is made of (itself, or what a combinator wraps)."""
    found = {type(f)}
    for attr in ("filter", "association", "bank"):
        inner = getattr(f, attr, None)
        if isinstance(inner, Filter):
            found |= _covered(inner)
    return found


def test_every_detection_filter_has_a_case():
    covered = set().union(*(_covered(c.make()) for c in CASES))
    missing = sorted(name for name, cls in _detection_filters().items() if cls not in covered)
    assert not missing, f"association filters without a DetectionCase in {__name__}: {missing}"


# -- helpers --------------------------------------------------------------------------------------------------
def _scan(rows: int, seed: int = 0) -> torch.Tensor:
    """``(RUNS, rows, 1)``: detections near the tracks, some far (clutter), the last row missing."""
    gen = torch.Generator().manual_seed(seed)
    z = torch.randn(RUNS, rows, M, generator=gen, dtype=torch.float64) * 3.0 + 2.0
    if rows > 1:
        z[:, -1] = math.nan
    return z


def _update(case: DetectionCase, f, belief, z):
    if case.particles:  # a copy: the same random stream at every call (a particle filter keeps its own)
        return copy.deepcopy(f).update(belief, z, generator=torch.Generator().manual_seed(11))
    return f.update(belief, z)


def _step_prior(case: DetectionCase):
    """A filter and its prior after one scan with detections (a belief that is not the start)."""
    f = case.make()
    belief = case.start(f)
    kwargs = {"generator": torch.Generator().manual_seed(5)} if case.particles else {}
    out = f.step(belief, _scan(4), **kwargs)
    prior = f.predict(out.belief, **kwargs)
    return f, prior


def _equal(a, b, what: str) -> None:
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.shape == b.shape, f"{what}: {a.shape} vs {getattr(b, 'shape', b)}"
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True, msg=lambda m: f"{what}: {m}")
    elif dataclasses.is_dataclass(a):
        for field in dataclasses.fields(a):
            _equal(getattr(a, field.name), getattr(b, field.name), f"{what}.{field.name}")
    elif isinstance(a, dict):
        for key in a:
            if key in ("association", "validated"):
                continue  # compared below, their detection axis differs
            _equal(a[key], b[key], f"{what}[{key!r}]")
    else:
        assert a == b, f"{what}: {a!r} vs {b!r}"


def _same_result(empty, missing, what: str) -> None:
    """``empty`` (a scan of 0 rows) against ``missing`` (all rows missing): the same result."""
    _equal(empty.belief, missing.belief, f"{what}: belief")
    _equal(empty.log_likelihood, missing.log_likelihood, f"{what}: log_likelihood")
    for field in ("innovation", "innovation_cov"):
        a, b = getattr(empty, field), getattr(missing, field)
        if a is not None or b is not None:
            _equal(a, b, f"{what}: {field}")
    if empty.extras is None:
        return
    _equal(empty.extras, missing.extras, f"{what}: extras")
    for key in ("association", "validated"):
        if key in missing.extras:
            a, b = empty.extras[key], missing.extras[key]
            rows = b.shape[-1] - a.shape[-1]
            assert a.shape[:-1] == b.shape[:-1] and rows >= 0, f"{what}: extras[{key!r}] {a.shape} vs {b.shape}"
            _equal(a, b[..., :a.shape[-1]], f"{what}: extras[{key!r}]")
            rest = b[..., a.shape[-1]:]
            assert not rest.nan_to_num(0.0).bool().any(), f"{what}: extras[{key!r}] of the missing rows"


# -- an empty scan is an all-missing scan -----------------------------------------------------------------------
def test_the_scan_kind_lists_the_empty_scan_as_the_all_missing_one():
    z = _scan(4)
    [(cls, empty, missing)] = [(e.cls, e.value, e.reference) for e in SCAN.equivalents(z)]
    assert cls == "empty" and empty.shape == (RUNS, 0, M) and missing.shape == z.shape
    assert torch.isnan(missing).all()


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_an_empty_scan_is_an_all_missing_scan(case):
    f, prior = _step_prior(case)
    for rows in (1, 3):
        [eq] = SCAN.equivalents(_scan(rows))
        empty = _update(case, f, prior, eq.value)
        missing = _update(case, f, prior, eq.reference)
        _same_result(empty, missing, f"{case.name}, {rows} missing rows")
        assert not bool(empty.log_likelihood.isnan().any())


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_empty_scans_through_run_filter(case):
    def run(z):
        f = case.make()
        kwargs = {"generator": torch.Generator().manual_seed(9)} if case.particles else {}
        return run_filter(f, case.start(f), z, **kwargs)

    T = 4
    empty = run(torch.zeros(T, RUNS, 0, M, dtype=torch.float64))
    missing = run(torch.full((T, RUNS, 2, M), math.nan, dtype=torch.float64))
    _equal(empty.belief, missing.belief, f"{case.name}: belief")
    _equal(empty.log_likelihood, missing.log_likelihood, f"{case.name}: log_likelihood")
    assert torch.isfinite(empty.log_likelihood).all()


def test_an_empty_scan_weighs_the_missed_detection_only():
    """The values, not only the agreement: log(1 - P_D P_G) and the prior (PDA), log(1 - P_D) (particles)."""
    pda = PDA(_kf(), detection_probability=0.8, clutter_density=0.1, gate_probability=0.95)
    prior = _prior((RUNS,))
    out = pda.update(prior, torch.zeros(RUNS, 0, M, dtype=torch.float64))
    torch.testing.assert_close(out.log_likelihood, torch.full((RUNS,), math.log1p(-0.8 * 0.95), dtype=torch.float64),
                               rtol=0, atol=0)
    _equal(out.belief, prior.expand(RUNS), "belief")
    ppda = ParticlePDA(_pf(), detection_probability=0.8, clutter_density=0.1)
    particles = ppda.filter.initial_belief(prior, 64, generator=torch.Generator().manual_seed(0))
    out = ppda.update(particles, torch.zeros(RUNS, 0, M, dtype=torch.float64), generator=torch.Generator())
    torch.testing.assert_close(out.log_likelihood, torch.full((RUNS,), math.log1p(-0.8), dtype=torch.float64),
                               rtol=0, atol=1e-15)


# -- invalid scans, dtypes --------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_invalid_scans_raise_naming_z(case):
    f = case.make()
    belief = case.start(f)
    if not case.managed and not isinstance(f, IMM):
        belief = f.predict(belief, **({"generator": torch.Generator()} if case.particles else {}))
    z = _scan(3)
    trials = [(i.cls, i.value) for i in SCAN.invalid(z)]
    trials += [("shape", torch.cat([z, z], -1)), ("shape", z.unsqueeze(0).expand(2, *z.shape)),
               ("shape", z[..., 0])]
    for cls, bad in trials:
        with pytest.raises((TypeError, ValueError), match=r"^z\b"):
            _update(case, f, belief, bad)


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_a_belief_of_the_other_dtype_names_belief_and_float32_detections_are_cast(case):
    f, prior = _step_prior(case)
    with pytest.raises(TypeError, match=r"^belief\b.*float32"):
        _update(case, f, prior.to(torch.float32), _scan(3))
    z = _scan(3).to(torch.float32)
    _equal(_update(case, f, prior, z).belief, _update(case, f, prior, z.to(torch.float64)).belief, case.name)


# -- a track that is not positive semi-definite fails its run -------------------------------------------------
def _corrupt(belief, scale: float):
    """Run 0's covariances replaced by ``-scale I`` (every track and mode of the run)."""
    if isinstance(belief, (ModeBelief, ModeExistenceBelief)):
        return dataclasses.replace(belief, components=_corrupt(belief.components, scale))
    if isinstance(belief, HypothesisBelief):  # (MHT: every hypothesis's tracks of run 0)
        return dataclasses.replace(belief, tracks=_corrupt(belief.tracks, scale))
    cov = belief.cov.expand(*belief.batch_shape, *belief.cov.shape[-2:]).clone()
    cov[0] = -scale * torch.eye(cov.shape[-1], dtype=cov.dtype)
    return dataclasses.replace(belief, cov=cov)


@pytest.mark.parametrize("scale", [1.0, 4.0])
@pytest.mark.parametrize("case", GAUSSIAN, ids=lambda c: c.name)
def test_a_track_that_is_not_psd_fails_its_run_only(case, scale):
    f, prior = _step_prior(case)
    bad = _corrupt(prior, scale)
    z = _scan(4)
    for scan in (z, z[:, :0]):
        out = f.update(bad, scan)
        failed = out.extras["failed"]
        runs_failed = failed.reshape(RUNS, -1).all(-1)
        assert runs_failed.tolist() == [True, False, False], f"{case.name}: {failed}"
        assert torch.isnan(out.log_likelihood[0]).all() and torch.isfinite(out.log_likelihood[1:]).all()
        alone = f.update(prior[1:], scan[1:])
        _equal(out.belief[1:], alone.belief, f"{case.name}: the other runs")
        _equal(out.log_likelihood[1:], alone.log_likelihood, f"{case.name}: the other runs' log-likelihood")


def test_a_particle_belief_case_exists():
    assert any(isinstance(c.start(c.make()), ParticleBelief) for c in CASES if c.particles and not c.tracks)
    assert any(isinstance(c.start(c.make()), ExistenceBelief) for c in CASES)


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_empty_scans_and_failed_tracks_read_nothing_on_the_host(case):
    """The empty scan's shape branch and the failure flag are shapes and elementwise operations: under
    ``no_host_sync`` (which also makes CPU code take its device form) the steps run as before."""
    from torchmm.runtime import no_host_sync

    f, prior = _step_prior(case)
    beliefs = [prior] + ([_corrupt(prior, 4.0)] if case in GAUSSIAN else [])
    scans = (_scan(3)[:, :0], _scan(3))
    gens = [torch.Generator().manual_seed(11) for _ in range(len(beliefs) * len(scans))]
    copies = [copy.deepcopy(f) for _ in gens]
    kwargs = [{"generator": g} if case.particles else {} for g in gens]
    with no_host_sync(f"{case.name}: an empty scan"):
        outs = [c.update(b, scan, **k) for (c, k), (b, scan) in
                zip(zip(copies, kwargs), [(b, s) for b in beliefs for s in scans])]
    assert all(o.log_likelihood.shape[:1] == (RUNS,) for o in outs)
