"""The time-loop driver: the only place in torchmm that loops over time steps."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.utils._pytree as pytree
from torch import Tensor

import torchmm.kernels as kernels
from torchmm.beliefs import GaussianBelief
from torchmm.contract import BeliefArg, Data, Finite, Flag, Gen, Of, Unchecked, entry_point
from torchmm.filters.base import Filter, StepOutput, call_with
from torchmm.provenance import Provenance, fingerprints, module_state, note_infinite, tensor_versions
from torchmm.runtime import entries, fast_paths_compiled, one_thread_when_small
from torchmm.validation import check_data_batch, check_filter_dtype, check_measurement, module_tensors

__all__ = ["Keep", "Trajectory", "attach_provenance", "per_step_models", "run_filter", "stack_outputs"]

log = logging.getLogger("torchmm")


@dataclass(frozen=True)
class Trajectory:
    """Time-major record of a filter run: the fields of :class:`StepOutput`, stacked.

    Shapes:
        belief, prior: beliefs with batch ``(T, *B)``; log_likelihood ``(T, *B)``;
        innovation ``(T, *B, [M,] m)``; innovation_cov ``(T, *B, [M,] m, m)``;
        extras: dict of stacked diagnostics (``(T, ...)``). Fields dropped by ``record`` are None.
        provenance: what made it (:class:`~torchmm.provenance.Provenance`: the filter, the per-step
            models, the data's fingerprint), set by :func:`run_filter` and
            :func:`torchmm.parallel.filter`, checked by :func:`~torchmm.smooth`; None for a trajectory
            built by hand (``dataclasses.replace`` keeps it, and ``smooth`` then refuses fields that
            are not the run's own).
    """

    belief: Any
    prior: Any
    log_likelihood: Tensor | None
    innovation: Tensor | None
    innovation_cov: Tensor | None
    extras: dict | None
    provenance: Provenance | None = field(default=None, compare=False, repr=False)

    def estimate(self) -> GaussianBelief:
        """Point estimates and covariances, batch ``(T, *B)`` (IMM/GPB: the combined output)."""
        return self.belief.estimate()

    def total_log_likelihood(self) -> Tensor:
        """``log p(z_{1:T})`` per run, shape ``(*B,)``."""
        return self.log_likelihood.sum(0)

    @property
    def final_belief(self) -> Any:
        """The last posterior, batch ``(*B,)`` (to continue filtering)."""
        return self.belief[-1]


class Keep:
    """``record=Keep("log_likelihood", "belief")``: the :class:`StepOutput` fields a run keeps (the others
    are None), as a record a kernel understands (:mod:`torchmm.kernels`: it computes only those). A
    record written as a function is applied to every step's output: by the eager steps and the
    step-by-step kernels as they go, and to each step of a whole-run kernel's outputs after it ran
    (the Numba kernel; issue 47: before, a record function turned that kernel off).

    Args:
        fields: names of :class:`~torchmm.filters.StepOutput` fields.
        detach: the kept belief is detached from the autograd graph (to continue filtering).

    Examples:
        >>> Keep("log_likelihood")(StepOutput("b", "p", 1.0))
        StepOutput(belief=None, prior=None, log_likelihood=1.0, innovation=None, innovation_cov=None, extras=None)
    """

    def __init__(self, *fields: str, detach: bool = False):
        unknown = [f for f in fields if f not in StepOutput._fields]
        if unknown:
            raise ValueError(f"fields: {unknown} are not StepOutput fields {StepOutput._fields}")
        self.fields = frozenset(fields)
        self.detach = bool(detach)

    def __call__(self, out: StepOutput) -> StepOutput:
        kept = {f: getattr(out, f) for f in self.fields}
        if self.detach and kept.get("belief") is not None:
            kept["belief"] = kept["belief"].detach()
        return StepOutput(**{f: kept.get(f) for f in StepOutput._fields})

    def __repr__(self) -> str:
        return f"Keep({', '.join(repr(f) for f in sorted(self.fields))}{', detach=True' if self.detach else ''})"


def stack_outputs(outputs: list) -> Any:
    """Stack a list of equally structured pytrees (e.g. StepOutputs) along a new leading axis."""
    return kernels.stack_steps(outputs)


@entry_point(filter=Of(Filter), belief0=BeliefArg(), measurements=Data(),
             controls=Finite(optional=True, check=False),
             motions=Of((list, tuple, torch.nn.Module), callable_ok=True, optional=True,
                        what="a sequence of T models, a callable k -> model, or None"),
             sensors=Of((list, tuple, torch.nn.Module), callable_ok=True, optional=True,
                        what="a sequence of T models, a callable k -> model, or None"),
             generator=Gen(), update_first=Flag(),
             record=Of(str, callable_ok=True, optional=True, what="a callable, None or \"estimate\""),
             progress=Unchecked("True, False or the progress bar's description (any string)"),
             fast_path=Flag(optional=True), compile=Flag(optional=True))
@one_thread_when_small(lambda filter, belief0, *args, **kwargs: entries(belief0))
def run_filter(
    filter: Filter,
    belief0: Any,
    measurements: Any,
    *,
    controls: Tensor | None = None,
    motions: Any = None,
    sensors: Any = None,
    generator: torch.Generator | None = None,
    update_first: bool = False,
    record: Callable[[StepOutput], StepOutput] | str | None = None,
    progress: bool | str = False,
    fast_path: bool | None = None,
    compile: bool | None = None,  # noqa: A002
) -> Trajectory:
    """Run ``filter.step`` over a time-major measurement sequence.

    Args:
        filter: any :class:`~torchmm.filters.Filter` (KF, EKF, UKF, IMM, GPB, ...).
        belief0: belief at time 0, batch ``(*B,)`` (for IMM/GPB: ``filter.initial_belief(...)``).
        measurements: ``(T, *B, m)`` with NaN for missing data (any non-finite entry is missing;
            infinite ones are counted in a warning), or any pytree of time-major tensors (each
            filter step receives the pytree indexed at ``k``); ``T >= 1``.
        controls: optional inputs ``(T, *B, k)``; a batch that broadcasts to ``(*B,)`` is shared by the runs
            (``(T, k)``), one that would enlarge it is refused, as the measurements'.
        motions: per-step motion models (time-varying parameters, a per-step ``dt``): a sequence
            of ``T`` models (None entries keep the filter's) or a callable ``k -> model or None``;
            step ``k`` predicts with it (:meth:`~torchmm.filters.Filter.with_motion`). For a
            multiple-model filter a mode-bank model (parameter batch ``(M,)``).
        sensors: per-step sensors, likewise (e.g. a sensor whose noise changes, or which sensor
            reported at step ``k``); step ``k`` updates with it.
        generator: the random stream of filters that draw random numbers (particle filters; passed
            to every step); two calls with equally seeded generators give identical results.
        update_first: the first measurement is at the time of ``belief0``: step 0 is an update
            only (no prediction). The trajectory's ``extras`` then hold the diagnostics every step
            has (not the IMM's ``"mixed"``, which only a prediction makes).
        record: maps each :class:`StepOutput` to what is kept (e.g.
            ``lambda o: o._replace(prior=None)`` to save memory); default keeps everything.
            ``"estimate"``: keep only the point estimate (``belief.estimate()``, the IMM's combined
            output) and the log-likelihood; the fast path then computes the estimate inside its step.
        progress: show a tqdm bar (a string is used as its description).
        fast_path: run a whole-run kernel (the seam :mod:`torchmm.kernels`, docs/architecture.md
            "Kernels": the Numba linear-Gaussian kernel of Kalman filters, IMM, GPB1 and static banks
            over linear-Gaussian modes for small CPU runs; the batch-last kernels of IMM, GPB1, GPB2,
            the variable-structure IMM and IMM-TF for larger ones, and of IMM and GPB1 over extended
            and unscented banks; docs/performance.md has the table), which returns what the steps
            return, to rounding. None (default): where a kernel applies to a run without
            ``motions`` or ``sensors`` and pays (``controls`` only the Numba kernel takes, through
            ``LinearMotion``'s ``input_matrix``; the Numba kernel: every run of at most 128 runs on
            the CPU, its first call in a process loading Numba, ~0.3 s; the extended and unscented banks': at
            least 300 runs x modes; IMM-TF's for 7 to 10 state components: 900; the choice depends
            on the call only); True: always - the kernel None would take, else one where it would not pay
            (a ``ValueError`` naming ``fast_path`` gives every kernel's reason where none can; a kernel that
            gives a run back as it runs, at a regularised or failed update, leaves it to the steps, as under
            None: ``provenance.declined`` says so); False: never (the steps).
        compile: run the fast path's step under ``torch.compile`` (seconds of compiling, cached on
            disk, then fused kernels: docs/performance.md says when it pays); True needs a fast path.
            None (default): the process default of :func:`torchmm.runtime.compile_fast_paths` (off
            unless set), for runs that have a fast path.

    Returns:
        :class:`Trajectory` with every kept field stacked on a leading time axis, batch-first.

    Raises:
        ValueError / TypeError: naming ``belief0``, ``measurements`` or ``controls``, checked once
        here: ``belief0``'s values (:meth:`~torchmm.beliefs.Belief.validate`), its dtype against
        the filter's, the measurement streams' time axis, the controls' batch and width; naming a
        model parameter (``motion.F``, ``transition``) whose batch does not broadcast with ``belief0``'s
        or adds runs to it (:meth:`~torchmm.filters.Filter.check_parameter_batch`); every step then
        checks shapes only.

    Examples:
        >>> from torchmm.filters import KalmanFilter
        >>> from torchmm.models import ConstantVelocity, PositionMeasurement
        >>> kf = KalmanFilter(ConstantVelocity(1), PositionMeasurement(2, [0], 1.0))
        >>> traj = run_filter(kf, GaussianBelief(torch.zeros(4, 2), torch.eye(2)), torch.randn(10, 4, 1))
        >>> traj.estimate().mean.shape
        torch.Size([10, 4, 2])
    """
    belief0.validate_once("belief0")  # (its type, filter's, and the flags' are the contract's, at entry)
    owned = module_tensors(filter) if isinstance(filter, torch.nn.Module) else None  # (walked once a call)
    check_filter_dtype(filter, belief0, "belief0", owned)
    if generator is not None and generator.device.type != belief0.device.type:
        raise ValueError(f"generator: on {generator.device}, the belief on {belief0.device}; create it "
                         f"there: torch.Generator(device={str(belief0.device)!r})")
    leaves = pytree.tree_leaves(measurements)
    if not leaves:
        raise ValueError("measurements: empty")
    if not all(isinstance(t, Tensor) for t in leaves):
        leaf = next(t for t in leaves if not isinstance(t, Tensor))
        # (scans read from a file, experiments.datafile.DetectionScans: their padded array is .z)
        hint = "; scans of detections: pass torch.as_tensor(scans.z)" if hasattr(leaf, "z") else ""
        raise TypeError(f"measurements: expected a tensor (T, *B, m) or a pytree of tensors, got "
                        f"{type(leaf).__name__}{hint}")
    if any(t.dim() < 2 for t in leaves):
        shapes = [tuple(t.shape) for t in leaves]
        raise ValueError(f"measurements: expected time-major (T, *B, m), got shapes {shapes}")
    steps = leaves[0].shape[0]
    if any(t.shape[0] != steps for t in leaves):
        raise ValueError("measurements: all streams must share the leading time axis")
    if steps == 0:
        raise ValueError("measurements: no time steps (T = 0); run_filter needs at least one")
    meas_dim = getattr(filter, "meas_dim", None)
    # the steps check z (*B, m) each; name it once here
    if isinstance(measurements, Tensor) and meas_dim is not None:
        check_measurement(measurements[0], meas_dim, belief0.batch_shape, _first_tensor(belief0, leaves[0]),
                          "measurements")
    elif isinstance(measurements, Tensor) or getattr(filter, "checks_pytrees", False):  # not a sensor's: the filter's own check
        filter.check_measurements(measurements, belief0.batch_shape, "measurements")
    if controls is not None:
        check_controls(filter, controls, steps, belief0.batch_shape)
    # one host read: the data's record
    (data_prints, control_prints), (infinite, _) = fingerprints(measurements, controls)
    note_infinite(infinite, "measurements")
    motion_at = per_step_models(motions, steps, "motions")
    sensor_at = per_step_models(sensors, steps, "sensors")
    for given, keyword, name in ((motions, "motion", "motions"), (sensors, "sensor", "sensors")):
        if given is not None and not _accepts(filter.step, keyword):
            raise TypeError(f"{name}: {type(filter).__name__}.step takes no per-step {keyword} (its models are "
                            "fixed by its construction, e.g. the source sensor of a multi-rate estimator)")
    filter.check_parameter_batch(belief0.batch_shape)  # (shapes only: a parameter adding runs is named)
    estimate_only = isinstance(record, str)
    if estimate_only:
        if record != "estimate":
            raise ValueError(f"record: expected a callable, None or 'estimate', got {record!r}")
        record = keep_estimate
    explicit = compile is True
    if compile is None:
        compile = fast_paths_compiled() and fast_path is not False
    if compile and fast_path is False:
        raise ValueError("compile: compiles the fast path, and fast_path=False turns it off")
    if not isinstance(progress, (bool, str)):
        raise TypeError(f"progress: expected True, False or the progress bar's description, got {progress!r}")
    fields = None
    chosen, declined = kernels.EAGER, "fast_path=False"
    if fast_path is not False:  # the one seam for speed (torchmm.kernels): no filter class is named here
        why, run = "per-step models", None
        if motions is None and sensors is None:
            request = kernels.Request(
                update_first=update_first, forced=fast_path is True, compile=bool(compile),
                compile_required=explicit, progress=progress,
                keep=(frozenset({"belief", "log_likelihood"}) if estimate_only
                      else record.fields if isinstance(record, Keep) else None),
                estimate=estimate_only, detach_belief=isinstance(record, Keep) and record.detach,
                record=None if estimate_only or isinstance(record, Keep) else record, generator=generator,
                controls=controls)
            run, chosen, why = kernels.choose(filter, belief0, measurements, request)
            fields = None if run is None else run()
            if fields is not None and request.record is not None and not getattr(run, "applies_record", True):
                fields = _record_each(fields, request.record, steps)  # (a whole-run kernel's outputs)
            if run is not None and fields is None:  # (declined at run time: the steps run)
                chosen, why = kernels.EAGER, f"{chosen}: declined at run time (a regularised or failed update)"
        declined = why
        if run is None:  # (a plan that declines at run time - a regularised update - leaves it to the steps)
            if fast_path:
                raise ValueError(f"fast_path: no fast path for this run ({why}); use fast_path=None or False")
            if explicit:
                raise ValueError(f"compile: compiles the fast path, which this run has not ({why})")
    iterator = range(steps)
    if progress and fields is None:
        from tqdm.auto import tqdm

        iterator = tqdm(iterator, desc=progress if isinstance(progress, str) else None, leave=False)
    belief = belief0
    kept = []
    if fields is not None:
        iterator = ()
    for k in iterator:
        z = pytree.tree_map(lambda t: t[k], measurements)
        inputs = {}
        motion, sensor = motion_at(k), sensor_at(k)
        if sensor is not None:
            inputs["sensor"] = sensor
        if k == 0 and update_first:
            out = call_with(filter, "update", belief, z, generator=generator, **inputs)
        else:
            if motion is not None:
                inputs["motion"] = motion
            out = call_with(filter, "step", belief, z, u=None if controls is None else controls[k],
                            generator=generator, **inputs)
        belief = out.belief
        kept.append(out if record is None else record(out))
    if update_first:
        kept = _common_extras(kept)
    parts = fields if fields is not None else stack_outputs(kept)
    made = Provenance(  # (attach_provenance's record, made once: the one-shot call's cost)
        "run_filter", filter, steps, measurements, data_prints, tensor_versions(measurements), controls,
        control_prints, None if controls is None else tensor_versions(controls), motions, sensors,
        update_first, belief=parts[0], prior=parts[1], kernel=chosen, declined=declined,
        state=module_state(filter, owned if fields is not None else None))  # (the steps may replace a tensor)
    stacked = Trajectory(*parts, provenance=made)
    kernels.count_run(chosen)
    if not (fields is not None and getattr(run, "flags_clear", False)):  # (a kernel that ran clean flags none)
        _report_flags(stacked.extras)
    return stacked


def _record_each(fields: tuple, record: Callable, steps: int) -> tuple:
    """A record function applied to each step of a whole-run kernel's stacked fields (issue 47: the kernel
    runs instead of the eager steps), the results stacked as the steps' would be."""
    whole = StepOutput(*fields)
    kept = [record(pytree.tree_map(lambda t, k=k: t[k] if isinstance(t, Tensor) else t, whole))
            for k in range(steps)]
    return tuple(stack_outputs(kept))


def _common_extras(kept: list) -> list:
    """``update_first``: step 0 is an update only, so the diagnostics that only a prediction makes (the
    IMM's ``extras["mixed"]``) are missing there; every step keeps the extras all steps have."""
    outs = [o for o in kept if isinstance(o, StepOutput) and isinstance(o.extras, dict)]
    if len(outs) != len(kept) or len(kept) < 2 or all(set(o.extras) == set(outs[0].extras) for o in outs):
        return kept
    common = set.intersection(*(set(o.extras) for o in outs))
    return [o._replace(extras={k: v for k, v in o.extras.items() if k in common}) for o in outs]


def attach_provenance(trajectory: Trajectory, provenance: Provenance) -> Trajectory:
    """``trajectory`` with its record: ``provenance`` completed with the trajectory's own fields and
    the filter's parameter state at the end of the run."""
    provenance = dataclasses.replace(provenance, belief=trajectory.belief, prior=trajectory.prior,
                                     state=module_state(provenance.filter))
    return dataclasses.replace(trajectory, provenance=provenance)


def keep_estimate(out: StepOutput) -> StepOutput:
    """``record="estimate"`` of :func:`run_filter`: the point estimate and the log-likelihood only."""
    return StepOutput(out.belief.estimate(), None, out.log_likelihood)


def check_controls(filter: Filter, controls: Any, steps: int, batch: torch.Size) -> None:
    """``controls (T, *B', k)`` against the run (shapes only): ``T`` steps, a batch that broadcasts *to*
    belief0's ``(*B,)`` (shared by the runs, not enlarging them: the measurements' rule) and ``k`` the columns
    of every input matrix of the filter's motions (``LinearMotion``'s ``input_matrix``)."""
    if not isinstance(controls, Tensor) or controls.dim() < 2:
        raise ValueError("controls: expected a tensor (T, *B, k)")
    if controls.shape[0] != steps:
        raise ValueError(f"controls: expected {steps} time steps, got {controls.shape[0]}")
    k = controls.shape[-1]
    check_data_batch(controls.shape[1:-1], batch, "controls", (steps, *batch, k))
    for name, module in filter.named_modules():
        matrix = getattr(module, "input_matrix", None)
        if isinstance(matrix, Tensor) and matrix.dim() >= 2 and matrix.shape[-1] != k:
            width = matrix.shape[-1]
            raise ValueError(f"controls: {k} inputs a step, but {name or 'the motion'}'s input_matrix "
                             f"{tuple(matrix.shape)} reads {width}: expected (T, *B, {width})")


def _accepts(fn: Callable, keyword: str) -> bool:
    import inspect

    params = inspect.signature(fn).parameters
    return keyword in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


def _first_tensor(belief: Any, default: Tensor) -> Tensor:
    """A tensor of ``belief``'s (its dtype and device), or ``default``."""
    fields = getattr(belief, "_tensors", None)  # (a Belief's own list: cheaper than a pytree walk)
    leaves = [t for t in (pytree.tree_leaves(belief) if fields is None else (t for t, _ in fields()))
              if isinstance(t, Tensor) and t.is_floating_point()]
    return leaves[0] if leaves else default


def per_step_models(models: Any, steps: int, name: str) -> Callable[[int], Any]:
    """``k -> model or None`` from a sequence of ``steps`` models, a callable, or None."""
    if models is None:
        return lambda k: None
    if callable(models) and not isinstance(models, torch.nn.Module):
        return models
    if isinstance(models, torch.nn.Module):
        return lambda k: models
    try:
        count = len(models)
    except TypeError:
        raise TypeError(f"{name}: expected a sequence of models, a callable k -> model, or None, got "
                        f"{type(models).__name__}") from None
    if count != steps:
        raise ValueError(f"{name}: expected one entry per step ({steps}), got {count}")
    return lambda k: models[k]


def _report_flags(extras: dict | None) -> None:
    """One warning per run for updates whose innovation covariance had to be regularised
    (``extras["singular"]``, or the mode filters' ``extras["modes"]["singular"]``), for particle
    updates whose weights all vanished (``extras["degenerate"]``) and for failed updates (a present
    datum, a non-finite prediction: ``extras["failed"]``): the steps only flag them, so that no step
    reads values on the host."""
    extras = extras or {}
    modes = extras.get("modes") if isinstance(extras.get("modes"), dict) else {}
    messages = {
        "singular": "%d of %d updates had an innovation covariance that is not numerically positive definite; "
                    "they used a regularised factor (extras['singular'], docs/robustness.md)",
        "degenerate": "%d of %d particle updates had every weight vanish; their prior weights were kept "
                      "(extras['degenerate'], docs/robustness.md)",
        "failed": "%d of %d updates failed: a datum was present but the prediction (or its covariance) "
                  "was NaN, e.g. a model whose parameters went NaN (for particle filters: a NaN or +inf "
                  "particle likelihood, or a state-dependent R(x) not positive definite); their "
                  "log-likelihood is NaN, not the 0 of missing data (extras['failed'], docs/robustness.md)",
        "empty_set": "%d of %d steps of a variable-structure IMM got an empty model set from its policy; "
                     "their log-likelihood is NaN (extras['empty_set'], docs/robustness.md)",
    }
    for key, message in messages.items():
        flags = extras.get(key)
        if flags is None:
            flags = modes.get(key)
        if isinstance(flags, Tensor) and flags.dtype == torch.bool and flags.numel():
            count = int(flags.numpy().sum()) if flags.device.type == "cpu" else int(flags.sum())
            if count:
                log.warning(message, count, flags.numel())
