"""What a trajectory knows (docs/robustness.md): :func:`~torchmm.smooth`'s arguments checked against the run
that made the trajectory (its provenance: the same filter object and state, the same data by version or
fingerprint, the same per-step models), and the padding steps of runs of unequal length or of runs whose
last steps hold no measurement."""

from __future__ import annotations

from typing import Any

import torch
import torch.utils._pytree as pytree
from torch import Tensor

from torchmm.multimodel.bank import ListBank, VectorizedBank
from torchmm.provenance import fingerprints, module_state, tensor_versions
from torchmm.run import Trajectory, per_step_models

__all__ = ["SMOOTHERS", "after_last_datum", "checked_against_run", "padding_steps", "per_step_list",
           "same_data", "same_models", "singular_process_noise", "unobserved_tail", "why_not_smoothable"]


def per_step_list(value: Any, steps: int, name: str) -> list | None:
    """Per-step models as a list of ``steps`` (from a sequence, a callable ``k -> model`` or one model)."""
    if value is None:
        return None
    at = per_step_models(value, steps, name)
    return [at(k) for k in range(steps)]


# -- what the trajectory knows: the arguments checked against the run that made it --------------------

#: the filters smooth dispatches on (a check against the run follows a check of the filter's type)
#: the backward passes smooth runs, by the filter's ``smoother`` name (Filter.smoother)
SMOOTHERS = ("modes", "particles", "unscented", "rts")

#: the smoothers :func:`~torchmm.smooth` has, for the message that names them
SUPPORTED = ("KalmanFilter (RTS), ExtendedKalmanFilter (extended RTS), UnscentedKalmanFilter (unscented RTS), "
             "ParticleFilter (FFBSm), IMM / GPB1 / GPB2 over Gaussian mode filters (the two-filter and Kim's "
             "smoother)")


def why_not_smoothable(filter: Any) -> str | None:
    """Why :func:`~torchmm.smooth` has no backward pass for ``filter``'s runs, or None where it has one: by
    the filter's declared ``smoother`` and, for a multiple-model filter, its mode filters' (the multiple-model
    smoothers run Kalman, extended or unscented modes) and its bank's kind (a vectorised or a list bank).
    Reads no data: a study asks it before it filters (experiments/estimators.py), ``smooth`` at its entry."""
    kind = getattr(filter, "smoother", None)
    if kind not in SMOOTHERS:
        return f"no smoother for {type(filter).__name__} yet; supported: {SUPPORTED}"
    if kind != "modes":
        return None
    bank = getattr(filter, "bank", None)
    odd = [m for m in bank.members() if getattr(m, "smoother", None) not in ("rts", "unscented")]
    if odd:
        return (f"the multiple-model smoothers need Gaussian mode filters (Kalman, extended or unscented); "
                f"{type(filter).__name__}'s are {type(odd[0]).__name__}")
    if not isinstance(bank, (VectorizedBank, ListBank)):
        return f"the multiple-model smoothers run a vectorised or a list bank, not {type(bank).__name__}"
    return None


def singular_process_noise(motion: Any) -> bool:
    """Whether ``motion``'s process noise ``Q`` is singular (rank-deficient, e.g. ``q G G^T``): FFBSm needs
    the transition density, which such a ``Q`` has not (one host read)."""
    eig = torch.linalg.eigvalsh(motion.noise_cov())
    return bool((eig[..., 0] <= 1e-10 * eig[..., -1].abs()).any())


def checked_against_run(filter: Any, trajectory: Trajectory, measurements: Any, controls: Any, motions: Any,
                         sensors: Any, method: str | None, steps: int) -> tuple:
    """``(filter, measurements, controls, motions, sensors)``: those given, checked against
    ``trajectory.provenance``, or the run's own where not given (motions and sensors as lists).

    Host reads: none when the arguments are the run's own objects, unchanged (tensor version
    counters); one checksum pass where other data are given."""
    run = trajectory.provenance
    if run is None or (filter is not None and getattr(filter, "smoother", None) not in SMOOTHERS):
        # built by hand: nothing to check against, smoothed as given (or a filter that smooth refuses)
        if filter is None:
            raise TypeError("filter: this trajectory carries no record of the filter that made it "
                            "(built by hand, joined, mapped or unpickled); pass it: "
                            "smooth(filter, trajectory)")
        return filter, measurements, controls, per_step_list(motions, steps, "motions"), \
            per_step_list(sensors, steps, "sensors")
    made = run.made_by
    if trajectory.belief is not run.belief or trajectory.prior is not run.prior or steps != run.steps:
        raise ValueError(f"trajectory: its beliefs are not the ones {made} returned ({steps} of its "
                         f"{run.steps} steps, or fields reversed, sliced or replaced); smooth the trajectory "
                         "as the run returned it (a Trajectory built anew carries no record and is smoothed "
                         "as given)")
    if filter is None:
        filter = run.filter
    elif type(filter) is not type(run.filter):
        raise TypeError(f"filter: a {type(filter).__name__}, but a {type(run.filter).__name__} made this "
                        f"trajectory ({made}); pass that filter, or smooth(trajectory) to use it")
    elif filter is not run.filter:
        raise ValueError(f"filter: not the filter that made this trajectory (a {type(run.filter).__name__}, "
                         f"given to {made}); pass that same object, or smooth(trajectory) to use it. "
                         "An equal filter built again is refused too: the trajectory knows its filter by "
                         "identity")
    if module_state(filter) != run.state:
        raise ValueError(f"filter: its parameters or buffers changed (in place, or replaced) since {made} "
                         "made this trajectory; filter again with the changed filter")
    two_filter = getattr(filter, "smoother", None) == "modes" and method in (None, "two_filter", "two_filter_info")
    if measurements is not None or two_filter:
        measurements = same_data(measurements, run.measurements, run.data, run.data_versions,
                                  "measurements", made)
    if controls is not None or run.controls is not None:
        controls = same_data(controls, run.controls, run.control_data, run.control_versions,
                              "controls", made)
    motions = same_models(motions, run.motions, steps, "motions", made)
    sensors = same_models(sensors, run.sensors, steps, "sensors", made)
    return filter, measurements, controls, motions, sensors


def same_data(given: Any, recorded: Any, prints: tuple | None, versions: tuple | None, name: str,
               made: str) -> Any:
    """``given`` (or the run's own ``recorded`` data where None), checked to be the data of the run."""
    if recorded is None:
        raise ValueError(f"{name}: {made} ran without {name}; smooth with what the run was given")
    data = recorded if given is None else given
    if data is recorded and versions is not None and tensor_versions(data) == versions:
        return data  # the run's own tensors, unchanged since: nothing to read
    leaves = pytree.tree_leaves(data)
    if not all(isinstance(t, Tensor) for t in leaves):
        bad = next(type(t).__name__ for t in leaves if not isinstance(t, Tensor))
        raise TypeError(f"{name}: expected a tensor (T, *B, ...) like the one given to {made}, got {bad}")
    if len(leaves) != len(prints):
        raise ValueError(f"{name}: {len(leaves)} data streams, the {name} given to {made} had {len(prints)}")
    for t, p in zip(leaves, prints):  # shapes, dtypes and devices first (no value read)
        if tuple(t.shape) != p.shape:
            raise ValueError(f"{name}: expected shape {p.shape} (the {name} {made} filtered), "
                             f"got {tuple(t.shape)}")
        if t.dtype != p.dtype:
            raise TypeError(f"{name}: dtype {t.dtype} differs from the {name} {made} filtered ({p.dtype})")
        if t.device != p.device:
            raise ValueError(f"{name}: on device {t.device}, the {name} {made} filtered were on {p.device}")
    (again,), _ = fingerprints(data)  # one pass, one host read
    for p, q in zip(prints, again):
        why = p.differs(q)
        if why is not None:
            if given is None:
                raise ValueError(f"{name}: the {name} given to {made} were changed in place since ({why}); "
                                 "pass the data as filtered, or filter again")
            raise ValueError(f"{name}: not the data {made} filtered ({why}: reversed, permuted, other or "
                             "changed data); pass those, or smooth(trajectory) to use the ones the "
                             "trajectory carries")
    return data


def same_models(given: Any, recorded: Any, steps: int, name: str, made: str) -> list | None:
    """The per-step models of the run as a list (``given``, checked to be the run's, or the run's own)."""
    if given is None:
        return per_step_list(recorded, steps, name)
    listed = per_step_list(given, steps, name)
    if recorded is None:
        raise ValueError(f"{name}: {made} ran without per-step {name} (every step used the filter's own); "
                         f"smooth with what the run was given")
    if given is recorded:
        return listed
    for k, (a, b) in enumerate(zip(listed, per_step_list(recorded, steps, name))):
        if a is not b:
            raise ValueError(f"{name}: entry {k} is not the model given to {made} for step {k} (a "
                             f"{type(b).__name__}); pass the same models, or leave {name} out to use "
                             "the run's")
    return listed


def padding_steps(present: Tensor | None, trajectory: Trajectory) -> Tensor | None:
    """``(T, *B)`` bool, True at the padding steps that follow each run's last step; None when every step
    is present. Checked at the entry point (one host read): the shape, and padding only at a run's end."""
    if present is None:
        return None
    batch = tuple(trajectory.belief.batch_shape)  # (not the log-likelihood: a record may drop it)
    if tuple(present.shape) != batch:
        raise ValueError(f"present: expected shape {batch} (the trajectory's steps and runs), got "
                         f"{tuple(present.shape)}")
    padding = ~present.to(trajectory.belief.device)
    late = present[1:] & padding[:-1]
    if bool(late.any()):
        k, *run = torch.nonzero(late)[0].tolist()
        raise ValueError(f"present: run {tuple(run)} has a present step {k + 1} after a padding step {k}; padding "
                         "goes at the end of a run (a missing datum inside a run is a NaN measurement)")
    return padding if bool(padding.any()) else None


def unobserved_tail(data: Any, trajectory: Trajectory) -> Tensor | None:
    """``(T, *B)`` bool, True at the steps after each run's last step with a finite measurement (every step of
    a run without one): steps that carry no information about the earlier ones, which a smoother treats as
    padding (docs/smoothing.md, "Runs of different lengths"). One batched pass over ``data`` (the
    measurements the run filtered, ``(T, *B, ...)`` or a pytree of such streams), no host read. None where
    the data are unknown (a trajectory built by hand, smoothed without them) or not laid out ``(T, *B, ...)``
    like the trajectory's beliefs."""
    tail = after_last_datum(data, tuple(trajectory.belief.batch_shape))
    return None if tail is None else tail.to(trajectory.belief.device)


def after_last_datum(data: Any, batch: tuple) -> Tensor | None:
    """:func:`unobserved_tail` for ``data`` laid out ``(*batch, ...)``, ``batch = (T, *B)``: ``(T, *B)`` bool,
    True after each run's last step where any stream has a finite component (also :func:`torchmm.learn.em`'s
    default ``present``); None where ``data`` is None or not laid out so."""
    if data is None:
        return None
    leaves = pytree.tree_leaves(data)
    if not leaves or not all(isinstance(t, Tensor) and tuple(t.shape[:len(batch)]) == batch for t in leaves):
        return None
    observed = None
    for t in leaves:  # a step is observed where any stream has any finite component
        seen = torch.isfinite(t).reshape(*batch, -1).any(-1)
        observed = seen if observed is None else observed | seen
    # observed at this step or a later one: a cumulative "any" from the end
    return ~observed.flip(0).cummax(0).values.flip(0)
