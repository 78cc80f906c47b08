"""The filter interface shared by every single- and multiple-model filter."""

from __future__ import annotations

import copy
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from torchmm.beliefs import Belief
from torchmm.contract import BeliefArg, entry_point
from torchmm.linalg import any_observed
from torchmm.typing import StepOutput
from torchmm.validation import broadcast_shape, check_filter_dtype, check_parameter_batch

__all__ = ["Filter", "StepOutput", "check_model_batches"]


class Filter(nn.Module):
    """Stateless recursive filter: belief in, belief out.

    The module holds models and options only; nothing changes between calls, so one filter can
    serve any number of independent batches. Subclasses implement :meth:`predict` and
    :meth:`update`; :meth:`step` is predict-then-update.

    The contract (docs/architecture.md):

    * ``initial_belief(belief, ...)`` turns a Gaussian (or any) prior into this filter's belief
      type; the default returns ``belief`` validated. Multiple-model filters add ``mode_probs``.
    * ``predict(belief, *, u=None)`` and ``update(belief, z)``; per step, the models can be
      replaced without building a filter: ``update(..., sensor=s)`` uses the sensor ``s`` for this
      update (multi-sensor and multi-rate updates), ``predict(..., motion=f)`` the motion model
      ``f`` (a time-varying or per-step ``dt`` model); both go through :meth:`with_sensor` /
      :meth:`with_motion`, which every filter inherits.
    * Filters that draw random numbers set ``uses_generator = True`` and take
      ``generator=`` in ``initial_belief``, ``predict``, ``update`` and ``step``: the random stream
      is an argument of the call, never state of the module. Combinators and
      :func:`~torchmm.run_filter` pass it only to filters that declare it.
    """

    #: the backward pass :func:`torchmm.smooth` runs for this filter's trajectories, by name (issue 47:
    #: ``smooth`` names no filter class): ``"rts"`` (Kalman, extended: Rauch-Tung-Striebel), ``"unscented"``
    #: (the unscented RTS), ``"particles"`` (FFBSm), ``"modes"`` (Kim's and the two-filter smoother of a
    #: multiple-model filter); None: no smoother
    smoother: ClassVar[str | None] = None

    #: True for filters whose steps draw random numbers (they accept ``generator=``)
    uses_generator: bool = False
    #: the number of trailing axes of one measurement: 1 for ``(*B, m)``; a set of detections
    #: ``(*B, D, m)`` (torchmm.association.PDA) has 2. Combinators insert their mode axes before them.
    measurement_rank: int = 1
    #: True for filters whose data is a pytree of their own that :meth:`check_measurements` checks
    #: (:class:`~torchmm.association.SequentialSensors`' SensorScans); run_filter then calls it
    checks_pytrees: bool = False

    def informative(self, z: Tensor) -> Tensor:
        """``(*B,)`` bool: where the measurement ``z`` carries information (the engine's "observed";
        where False the step's log-likelihood is exactly 0). Default: some component is finite (a
        measurement with every component missing carries none). Set-valued measurements override it
        (an empty scan still tells that nothing was detected)."""
        return any_observed(z)

    @property
    def state_dim(self) -> int | None:
        """The state dimension ``n`` of the filter's motion model (None if it has none)."""
        return getattr(self._modules.get("motion"), "state_dim", None)

    @property
    def meas_dim(self) -> int | None:
        """The measurement dimension ``m`` of the filter's sensor (None if it has none)."""
        return getattr(self._modules.get("measurement"), "meas_dim", None)

    @entry_point(belief=BeliefArg())
    def initial_belief(self, belief: Any, **kwargs) -> Any:
        """This filter's belief at time 0 from a prior ``belief`` (batch ``(*B,)``).

        The default checks the prior's values (:meth:`~torchmm.beliefs.Belief.validate`) and
        returns it; filters whose belief is not the prior's type (particles, mode beliefs, adaptive
        noise) override it, keeping ``belief`` as the first argument.
        """
        if kwargs:
            raise TypeError(f"{type(self).__name__}.initial_belief: unexpected arguments {sorted(kwargs)}")
        if not isinstance(belief, Belief):
            raise TypeError(f"belief: expected a belief (e.g. GaussianBelief), got {type(belief).__name__}")
        check_filter_dtype(self, belief, "belief")
        check_state_dim(self, belief, "belief")
        return belief.validate_once("belief")

    def predict(self, belief: Any, *, u: Tensor | None = None) -> Any:
        """Time update. Returns the prior belief for the next measurement."""
        raise NotImplementedError

    def check_bank_member(self, name: str, num_modes: int) -> None:
        """Raise if this filter, as configured, cannot be a mode filter of a bank of ``num_modes``.

        Called by the banks of IMM / GPB at construction (``name`` is the argument to blame). The
        default accepts; e.g. a :class:`~torchmm.filters.particle.ParticleFilter` needs a fixed
        ``num_particles`` when ``num_modes > 1`` because mixing merges the particle sets.
        """

    def check_parameter_batch(self, batch: torch.Size) -> None:
        """Check, reading shapes only, that this filter's model parameters broadcast with a start belief of
        batch ``batch`` without adding runs (:func:`~torchmm.validation.check_parameter_batch`): a
        ``ValueError`` naming the parameter (``motion.F``, ``measurement.R``, ``transition``).
        :func:`~torchmm.run_filter` calls it once at entry. The default checks nothing (the steps check
        shapes); the Gaussian filters check their models
        (:func:`~torchmm.filters.base.check_model_batches`), the multiple-model filters their transition."""

    def check_measurements(self, measurements: Tensor, batch: torch.Size, name: str = "measurements", *,
                           time: bool = True) -> None:
        """Check the shape and dtype of measurements that are not a sensor's (``meas_dim`` is None: a
        scan of detections, ``(*B, D, m)``) against the belief's batch ``(*B,)``, naming ``name``:
        :func:`~torchmm.run_filter` calls it once at entry with the whole sequence (``time``:
        ``(T, *B, ...)``), a combinator over such filters once per step with its datum (shapes only:
        no value is read). The default checks nothing (a sensor's ``(T, *B, m)`` is checked by
        ``run_filter`` itself; other filters check each step's datum)."""
    def update(self, belief: Any, z: Any) -> StepOutput:
        """Measurement update of a prior ``belief`` with ``z`` (NaN = missing)."""
        raise NotImplementedError

    def update_each(self, belief: Any, zs: Tensor) -> StepOutput:
        """One prior and ``D`` alternative measurements (what data association asks for: an update per
        detection). A measurement with a non-finite component counts as none (the prior kept,
        log-likelihood 0). This default updates the prior repeated ``D`` times (a view); the Kalman
        and extended Kalman filters compute what does not depend on the datum (gain, posterior
        covariance) once.

        Shapes:
            belief: batch ``(*B,)``; zs: ``(D, *B, m)`` -> the updates with batch ``(D, *B)``.
        """
        if self.measurement_rank == 1:
            zs = torch.where(torch.isfinite(zs).all(-1, keepdim=True), zs, torch.nan)
        return self.update(belief.unsqueeze(0).expand(zs.shape[0], *belief.batch_shape), zs)

    def step(self, belief: Any, z: Any, *, u: Tensor | None = None, motion: nn.Module | None = None,
             sensor: nn.Module | None = None, generator: torch.Generator | None = None) -> StepOutput:
        """One predict/update cycle from the posterior at ``k-1`` to the posterior at ``k``.

        ``motion`` / ``sensor`` replace the filter's models for this step (:meth:`with_motion`,
        :meth:`with_sensor`); ``generator`` is the random stream of filters that draw random numbers.
        """
        predictor = self if motion is None else self.with_motion(motion)
        prior = call_with(predictor, "predict", belief, u=u, generator=generator)
        updater = self if sensor is None else self.with_sensor(sensor)
        return call_with(updater, "update", prior, z, generator=generator)

    def forward(self, belief: Any, z: Any, **inputs) -> StepOutput:
        return self.step(belief, z, **inputs)

    # -- per-step models ------------------------------------------------------------------------
    def with_sensor(self, sensor: nn.Module) -> Filter:
        """This filter with ``sensor`` as its measurement model (shares every other module).

        A shallow copy, cached per sensor object, so calling it every step costs a dictionary
        lookup. Raises ``ValueError`` naming ``sensor`` if its state dimension differs from the
        filter's; filters that derive buffers from their sensor at construction override
        :meth:`_sensor_changed`.
        """
        return self._with_module("measurement", sensor, "sensor")

    def with_motion(self, motion: nn.Module) -> Filter:
        """This filter with ``motion`` as its motion model (cached like :meth:`with_sensor`)."""
        return self._with_module("motion", motion, "motion")

    def _sensor_changed(self) -> None:
        """Hook run on the copy made by :meth:`with_sensor` (re-derive sensor-dependent buffers)."""

    def _with_module(self, slot: str, module: nn.Module, name: str) -> Filter:
        current = self._modules.get(slot)
        if module is current:
            return self
        if current is None:
            raise TypeError(f"{name}: {type(self).__name__} has no {slot} model to replace")
        if not isinstance(module, nn.Module):
            raise TypeError(f"{name}: expected a torchmm model (nn.Module), got {type(module).__name__}")
        n_new, n_old = getattr(module, "state_dim", None), self.state_dim
        if n_new is not None and n_old is not None and n_new != n_old:
            raise ValueError(f"{name}: state_dim {n_new} differs from the filter's {n_old}")
        cache = self.__dict__.setdefault("_model_cache", {})
        key = (slot, id(module))
        hit = cache.get(key)
        if hit is not None and hit._modules.get(slot) is module:
            return hit
        _check_replacement(module, current, name, type(self).__name__)  # once per model (cached after)
        clone = copy.copy(self)
        for table in ("_modules", "_buffers", "_parameters"):
            clone.__dict__[table] = dict(self.__dict__[table])
        clone.__dict__["_model_cache"] = {}
        clone._modules[slot] = module
        if slot == "measurement":
            clone._sensor_changed()
        if len(cache) > 64:  # a per-step sequence of fresh models: do not grow without bound
            cache.clear()
        cache[key] = clone
        return clone


def check_model_batches(filter: Filter, batch: torch.Size) -> None:
    """:meth:`Filter.check_parameter_batch` of a filter whose ``motion`` and ``measurement`` models act on
    beliefs of batch ``(*B,)`` (a Kalman, extended or unscented filter): each parameter of the models that
    list their parameters' event axes (``param_events``: :class:`~torchmm.models.LinearMotion`,
    :class:`~torchmm.models.LinearMeasurement`) against ``batch``, named ``motion.F``, ``measurement.R``."""
    for slot in ("motion", "measurement"):
        model = getattr(filter, slot, None)
        events = getattr(model, "param_events", None) if isinstance(model, nn.Module) else None
        for key, event in (events or {}).items():
            tensor = getattr(model, key, None)
            if isinstance(tensor, Tensor):
                check_parameter_batch(tensor.shape[:tensor.dim() - event], batch, f"{slot}.{key}")


def call_with(filter: Filter, method: str, *args, generator: torch.Generator | None = None, **kwargs):
    """``getattr(filter, method)(*args, **kwargs)``, passing ``generator`` only to filters that draw
    random numbers (``filter.uses_generator``)."""
    if generator is not None and filter.uses_generator:
        kwargs["generator"] = generator
    return getattr(filter, method)(*args, **kwargs)


def _first_float(module: nn.Module) -> torch.dtype | None:
    for tensor in (*module.parameters(), *module.buffers()):
        if tensor.is_floating_point():
            return tensor.dtype
    return None


def _check_replacement(module: nn.Module, current: nn.Module, name: str, owner: str) -> None:
    """A per-step model against the filter's own: the same floating dtype and a parameter batch
    (the mode axis of a bank) that broadcasts to the filter's. Reads attributes only."""
    new, old = _first_float(module), _first_float(current)
    if new is not None and old is not None and new != old:
        raise TypeError(f"{name}: dtype {new} differs from the {owner}'s {old}; build the per-step models in "
                        f"{old} (or convert: model.to({old}))")
    new_batch = getattr(module, "param_batch_shape", None)
    old_batch = getattr(current, "param_batch_shape", None)
    if new_batch is not None and old_batch is not None and tuple(new_batch) != tuple(old_batch):
        try:  # per-run parameters (*B, M) are fine; a different mode count is not
            broadcast_shape(new_batch, old_batch)
        except RuntimeError:
            raise ValueError(f"{name}: parameter batch {tuple(new_batch)} does not broadcast with the "
                             f"{owner}'s {tuple(old_batch)} (a mode bank needs one model per mode: "
                             "batch (M,) or (*B, M), or one shared by every mode)") from None


def check_state_dim(filter: Filter, belief: Any, name: str) -> None:
    """``ValueError`` naming ``name`` if the belief's state dimension differs from the filter's
    (reads shapes only)."""
    have, want = getattr(belief, "state_dim", None), getattr(filter, "state_dim", None)
    if isinstance(have, int) and isinstance(want, int) and have != want:
        raise ValueError(f"{name}: state dimension {have} differs from the filter's state_dim {want}")
