"""The ``learn`` block of the generic study (``compare``): each learning estimator estimates its own
parameters on the study's data (docs/studies.md, "Learning").

* ``method: mle`` (default): maximum likelihood of any named tensors of the estimator's filter with
  :func:`torchmm.learn.estimate` - the modes' ``F``, ``Q``, ``offset``, ``input_matrix``, the sensors'
  ``H``, ``R``, the transition matrix - with standard errors, log-likelihood, AIC, BIC and expected
  durations. An entry names a model of the scenario (``modes``, ``modes[i]``, ``sensors``,
  ``sensors[i]``) and a tensor; it is found in the estimator's filter, whatever the filter made of the
  models (a bank stacks the modes' tensors on a mode axis: ``modes[1].Q`` is that axis' entry 1;
  ``modes.Q`` every mode's, ``shared: true`` one value for all modes).
* ``method: em`` (and ``em_then_mle``): EM, in :mod:`experiments.learning_em`.
* ``method: gradient``: the named covariances made learnable (:func:`torchmm.learnable_noise`) and
  fitted with a torch optimiser (L-BFGS or Adam) through :class:`torchmm.learn.Trainer` (no errors).

Every entry is checked before anything runs (:func:`check`, the config's dry construction): a model,
tensor or estimator it does not name is one ``ConfigError`` naming the key.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import re
import time
from typing import Any

import torch
from torch import Tensor

from experiments.config import NO_VALUE, ConfigError

#: old names of the covariance parametrisations (``method: gradient``) and their ``mle`` kinds
KIND_ALIASES = {"log_diagonal": "variance", "cholesky": "covariance"}
GRADIENT_KINDS = ("log_diagonal", "cholesky", "scale")
MLE_KINDS = ("free", "variance", "covariance", "stochastic", "probabilities", "log_diagonal", "cholesky")


def spec(cfg):
    """The ``learn`` block with the schema's defaults for the keys it does not set; None without one."""
    from omegaconf import OmegaConf

    from experiments.schemas import Learn

    if not cfg.get("learn"):
        return None
    block = OmegaConf.merge(OmegaConf.structured(Learn), cfg.learn)
    if str(block.method) == "em_then_lbfgs":  # (the issue's and statsmodels' name: EM, then L-BFGS-B)
        block.method = "em_then_mle"
    return block


def learners(cfg) -> list[str]:
    """The estimators that learn their own parameters (``learn.estimators``; ``learn.estimator``: that one;
    default every estimator): each is fitted on its own copy of the models and runs with its own fit;
    every other estimator runs with the configured values."""
    block = cfg.get("learn")
    if not block:
        return []
    if block.get("estimator") is not None:
        return [str(block.estimator)]
    if block.get("estimators") is not None:
        return [str(n) for n in block.estimators]
    return [str(n) for n in cfg.estimators]


def own_models(scenario):
    """The scenario with copies of its models (the data and everything else shared)."""
    return dataclasses.replace(scenario, motion=copy.deepcopy(scenario.motion),
                               measurement=copy.deepcopy(scenario.measurement))


# -- method: mle -----------------------------------------------------------------------------------------
def _models_in(filter: torch.nn.Module, kind: str, tensor: str) -> list[tuple[str, torch.nn.Module]]:
    """The filter's motion (``kind="modes"``) or measurement models that hold ``tensor`` as their own
    buffer or parameter, in the filter's order (a bank's modes in mode order)."""
    from torchmm.models.base import MeasurementModel, MotionModel

    cls = MotionModel if kind == "modes" else MeasurementModel
    out = []
    for path, module in filter.named_modules():
        if isinstance(module, cls) and (tensor in dict(module.named_buffers(recurse=False))
                                        or tensor in dict(module.named_parameters(recurse=False))):
            out.append((path, module))
    return out


def entry_where(entry) -> tuple[str | None, int | None]:
    model = entry.get("model")
    if model is None:
        return None, None
    match = re.fullmatch(r"(modes|sensors)(?:\[(\d+)\])?", str(model))
    if match is None:
        raise ValueError("expected modes, modes[i], sensors or sensors[i]")
    return match.group(1), None if match.group(2) is None else int(match.group(2))


def parameters_of(est, scenario, block, key: str = "learn.parameters") -> tuple[dict, dict]:
    """``({filter tensor name: Param}, {filter tensor name: (model, tensor, mode axis?)})``: each
    ``learn.parameters`` entry found in the estimator's filter. ``ConfigError`` naming the entry."""
    from torchmm.models.transition import ModeTransition

    filter = est.filter
    out, where = {}, {}
    M = scenario.num_modes
    entries = block.parameters
    if isinstance(entries, str):
        if entries != "auto" or getattr(scenario, "learn_parameters", None) is None:
            raise ConfigError(f"{key}", entries, "expected a list of entries, or auto for a scenario that says what it "
                              "estimates (experiments.scenarios.markov_switching)")
        from omegaconf import OmegaConf

        entries = OmegaConf.create(scenario.learn_parameters)
    for i, entry in enumerate(entries):
        at = f"{key}[{i}]"
        name = str(entry.name)
        kind = KIND_ALIASES.get(str(entry.get("kind") or ""), entry.get("kind"))
        if kind == "scale":
            raise ConfigError(f"{at}.kind", "scale", "method mle estimates a covariance as variance (its diagonal) or "
                              "covariance (full); scale is method gradient's")
        if name in START_NAMES:
            tensor, param, shape = _start_entry(est, scenario, entry, name, kind, at)
            if tensor in out:
                raise ConfigError(at, name, "names a tensor another entry names")
            out[tensor] = param
            where[tensor] = (None, name, False, _entry_names(entry, shape, at), None, shape)
            continue
        if name == "transition":
            if entry.get("model") is not None:
                raise ConfigError(f"{at}.model", entry.model, "the transition matrix belongs to no model (leave "
                                  "model out)")
            from torchmm.models.transition import LogisticTransition

            for option in ("shared", "lower", "upper"):
                if entry.get(option) not in (None, False):
                    what = "shared entries (it belongs to no mode)" if option == "shared" else "bounds"
                    raise ConfigError(f"{at}.{option}", entry.get(option), f"the transition matrix takes no "
                                      f"{what} (its rows are probabilities; fixed holds entries)")
            logistic = [p for p, m in filter.named_modules() if isinstance(m, LogisticTransition)]
            if logistic:  # time-varying: its logistic coefficients, free
                if kind not in (None, "free", "stochastic"):
                    raise ConfigError(f"{at}.kind", kind, "a time-varying transition's logistic coefficients "
                                      "are free")
                tensor = f"{logistic[0]}.coef" if logistic[0] else "coef"
                shape = tuple(dict(filter.named_buffers())[tensor].shape)
                fixed = _with_fixed(None, entry.get("fixed"), torch.Size(shape), stacked=False, at=at)
                out[tensor] = _param("free", at, fixed=fixed, label="transition")
                where[tensor] = (None, "transition", False, _entry_names(entry, shape, at), None, shape)
                continue
            paths = [p for p, m in filter.named_modules() if isinstance(m, ModeTransition)]
            if not paths:
                raise ConfigError(f"{at}.name", name, f"{est.name} has no transition matrix (a single-mode filter)")
            tensor = f"{paths[0]}.value" if paths[0] else "value"
            if tensor not in dict(filter.named_buffers()):
                raise ConfigError(f"{at}.name", name, f"{est.name}'s transition matrix is a learnable module "
                                  "(ModeTransition(learnable=True)): estimate a fixed one")
            if kind not in (None, "stochastic"):
                raise ConfigError(f"{at}.kind", kind, "the transition matrix's kind is stochastic")
            shape = tuple(dict(filter.named_buffers())[tensor].shape)
            fixed = _with_fixed(None, entry.get("fixed"), torch.Size(shape), stacked=False, at=at)
            out[tensor] = _param("stochastic", at, fixed=fixed, label="transition")
            where[tensor] = (None, "transition", False, _entry_names(entry, shape, at), None, shape)
            continue
        try:
            model, index = entry_where(entry)
        except ValueError as err:
            raise ConfigError(f"{at}.model", entry.get("model"), str(err)) from None
        if model is None:
            raise ConfigError(f"{at}.model", None, f"name which model holds {name!r}: modes, modes[i], sensors or "
                              "sensors[i] (only the transition matrix needs none)")
        if model == "modes":
            count = M
        elif isinstance(scenario.measurement, list):  # one sensor per mode (mode_sensors)
            count = len(scenario.measurement)
        else:  # one sensor, or several stacked (Concatenated)
            count = len(getattr(scenario.measurement, "sensors", [None]))
        if index is not None and not 0 <= index < count:
            raise ConfigError(f"{at}.model", entry.model, f"there {'is' if count == 1 else 'are'} {count} {model} "
                              f"(indices 0..{count - 1})")
        found = _models_in(filter, model, name)
        if not found:
            raise ConfigError(f"{at}.name", name, f"no {model[:-1]} model of {est.name}'s filter holds a tensor "
                              f"{name!r} (a custom filter builds its own models; a nonlinear model's parameters "
                              "are its own names)")
        shared = entry.get("shared") not in (None, False)
        fixed_given = entry.get("fixed")
        bounds = {k: entry.get(k) for k in ("lower", "upper") if entry.get(k) is not None}
        if len(found) == 1:
            path, module = found[0]
            tensor = f"{path}.{name}" if path else name
            value = getattr(module, name)
            batch = tuple(getattr(module, "param_batch_shape", ()) or ())
            stacked = len(batch) == 1 and batch[0] == count and count > 1 and value.shape[:1] == (count,)
            if stacked:  # a bank's tensor with a mode axis: entry `index`, or every mode
                fixed = None
                if index is not None:
                    fixed = torch.ones(value.shape, dtype=torch.bool)
                    fixed[index] = False
                groups = None
                share = _shared_mask(entry.get("shared"), value.shape[1:], at)
                if share is not None and bool(share.any()):
                    if index is not None:
                        raise ConfigError(f"{at}.shared", entry.get("shared"), f"shares {model}[i].{name} across "
                                          f"the modes: name {model} without an index")
                    per = value[0].numel()
                    groups = torch.arange(per).reshape(value.shape[1:])
                    groups = torch.where(share, groups, -1).expand(value.shape).clone()
                fixed = _with_fixed(fixed, fixed_given, value.shape, stacked=True, at=at)
            else:  # one model (a single-mode estimator, or a sensor shared by every mode)
                if index is not None and model == "modes" and M > 1 and est.mode is not None and index != est.mode:
                    raise ConfigError(f"{at}.model", entry.model, f"{est.name} runs mode {est.mode} only")
                fixed = _with_fixed(None, fixed_given, value.shape, stacked=False, at=at)
                groups = None  # (shared: one model is shared by every mode already)
            kind = kind or ("variance" if name in ("Q", "R") else "free")
            if kind in ("variance", "covariance") and (value.dim() < 2 or value.shape[-1] != value.shape[-2]):
                raise ConfigError(f"{at}.kind", kind, f"{name} is not a square matrix")
            if tensor in out:
                raise ConfigError(f"{at}", f"{entry.get('model')}.{name}", "names a tensor another entry names")
            label = model if stacked else str(entry.model)
            out[tensor] = _param(kind, at, fixed=fixed, groups=groups, label=f"{label}.{name}", **bounds)
            inner = tuple(value.shape[1:] if stacked else value.shape)
            where[tensor] = (label, name, stacked, _entry_names(entry, inner, at), groups, inner)
        else:  # one model per mode (a list bank): modes[i] is the i-th
            chosen = found if index is None else [found[index]] if index < len(found) else []
            if not chosen:
                raise ConfigError(f"{at}.model", entry.model, f"{est.name} has {len(found)} {model}")
            if shared:
                raise ConfigError(f"{at}.shared", True, f"{est.name}'s {model} are separate models (a list bank): "
                                  "sharing a value across them is not supported")
            for j, (path, module) in enumerate(chosen):
                jj = j if index is None else index
                tensor = f"{path}.{name}"
                value = getattr(module, name)
                fixed = _with_fixed(None, fixed_given, value.shape, stacked=False, at=at)
                out[tensor] = _param(kind or ("variance" if name in ("Q", "R") else "free"), at, fixed=fixed,
                                     label=f"{model}[{jj}].{name}", **bounds)
                where[tensor] = (f"{model}[{jj}]", name, False, _entry_names(entry, value.shape, at), None,
                                 tuple(value.shape))
    starting = [w[1] for w in where.values() if w[1] in START_NAMES]
    if starting and scenario.ergodic and est.multiple_model and any(w[1] == "transition" for w in where.values()):
        raise ConfigError(key, starting[0], "with the transition matrix "
                          "estimated, initial_mode_probs: ergodic makes the start a function of it; give "
                          "initial_mode_probs (a list or null) to estimate the start")
    return out, where


def _param(kind, at: str, **options):
    """``Param(kind, **options)``, its refusal (a bound on a variance, ``upper`` not above ``lower``, ...) a
    ``ConfigError`` naming the entry's key (``learn.parameters[i].lower``)."""
    from torchmm.learn import Param

    try:
        return Param(kind, **options)
    except (TypeError, ValueError) as err:
        option, _, reason = str(err).partition(": ")
        if option not in ("kind", "fixed", "groups", "lower", "upper"):
            raise ConfigError(at, NO_VALUE, str(err)) from None
        value = kind if option == "kind" else options[option] if option in ("lower", "upper") else NO_VALUE
        raise ConfigError(f"{at}.{'shared' if option == 'groups' else option}", value, reason) from None


#: the start's entries (no model): the prior's mean and covariance, the start's mode probabilities
START_NAMES = ("initial_mean", "initial_cov", "initial_mode_probs")


def _gaussian_path(belief, path: str = "belief0") -> str | None:
    """Where the Gaussian start sits in an estimator's start belief (``belief0``, a mode belief's
    ``belief0.components``), or None (a particle start)."""
    from torchmm import GaussianBelief
    from torchmm.beliefs import Belief

    if type(belief) is GaussianBelief:
        return path
    for f in dataclasses.fields(belief) if dataclasses.is_dataclass(belief) else ():
        value = getattr(belief, f.name)
        if isinstance(value, Belief):
            found = _gaussian_path(value, f"{path}.{f.name}")
            if found is not None:
                return found
    return None


def _start_entry(est, scenario, entry, name: str, kind, at: str) -> tuple[str, Any, tuple]:
    """``(belief0 field, Param, one value's shape)`` of a start entry (``initial_mean``, ``initial_cov``,
    ``initial_mode_probs``): estimated once for every series and mode (the prior is shared)."""
    if entry.get("model") is not None:
        raise ConfigError(f"{at}.model", entry.model, f"{name} belongs to no model (leave model out)")
    if entry.get("shared") not in (None, False, True):
        raise ConfigError(f"{at}.shared", entry.get("shared"), f"{name} is one value for every mode and series "
                          "already")
    start = est.init(scenario.initial, None)
    bounds = {k: entry.get(k) for k in ("lower", "upper") if entry.get(k) is not None}
    n = scenario.initial.mean.shape[-1]
    if name == "initial_mode_probs":
        if not est.multiple_model or not hasattr(start, "mode_log_probs"):
            raise ConfigError(at, name, f"{est.name} is not a mode filter: it has no mode probabilities")
        if kind not in (None, "probabilities"):
            raise ConfigError(f"{at}.kind", kind, "the start's mode probabilities are estimated as probabilities")
        field, param_kind, shape = "belief0.mode_probs", "probabilities", (start.mode_log_probs.shape[-1],)
    else:
        path = _gaussian_path(start)
        if path is None:
            raise ConfigError(at, name, f"{est.name}'s start is a {type(start).__name__} (drawn from the prior): "
                              "method mle estimates a Gaussian start's mean and covariance")
        if name == "initial_mean":
            field, param_kind, shape = f"{path}.mean", kind or "free", (n,)
            if param_kind != "free":
                raise ConfigError(f"{at}.kind", kind, "the start's mean is free (with optional bounds)")
        else:
            field, param_kind, shape = f"{path}.cov", kind or "variance", (n, n)
            if param_kind not in ("variance", "covariance"):
                raise ConfigError(f"{at}.kind", kind, "the start's covariance is a variance (its diagonal) or a "
                                  "covariance (full)")
    fixed = _with_fixed(None, entry.get("fixed"), torch.Size(shape), stacked=False, at=at)
    if fixed is not None and param_kind == "covariance":
        raise ConfigError(f"{at}.fixed", entry.get("fixed"), "a full covariance has no fixed entries (kind "
                          "variance: its diagonal)")
    return field, _param(param_kind, at, fixed=fixed, label=name, **bounds), shape


def start_after(est, result) -> None:
    """The estimator starts from the estimated start from now on (``est.init``): the prior's mean and
    covariance and the start's mode probabilities of ``result.belief0`` (one value for every series)."""
    from torchmm import GaussianBelief

    belief = result.belief0
    path = _gaussian_path(belief)
    gauss = belief
    for part in path.split(".")[1:]:
        gauss = getattr(gauss, part)
    n = gauss.mean.shape[-1]
    mean, cov = gauss.mean.reshape(-1, n)[0].clone(), gauss.cov.reshape(-1, n, n)[0].clone()
    probs = belief.mode_log_probs.reshape(-1, belief.mode_log_probs.shape[-1])[0].exp().clone() \
        if hasattr(belief, "mode_log_probs") else None
    before = est.init

    def init(prior, generator=None):
        options = {"generator": generator} if generator is not None else {}
        start = GaussianBelief(mean, cov).expand(prior.batch_shape)
        if probs is not None:
            return est.filter.initial_belief(start, probs, **options)
        return before(start, generator)
    est.init = init


def _shared_mask(given, shape: torch.Size, at: str) -> Tensor | None:
    """``shared``: true (every entry one value across the modes), false, or a boolean mask of one mode's
    tensor (those entries shared, the others per mode)."""
    if given is None or given is False:
        return None
    if given is True:
        return torch.ones(shape, dtype=torch.bool)
    try:
        return torch.as_tensor(given, dtype=torch.bool).expand(shape).clone()
    except (RuntimeError, TypeError, ValueError):
        raise ConfigError(f"{at}.shared", given, f"expected true, false or a boolean mask of shape {tuple(shape)}"
                          ) from None


def _with_fixed(fixed: Tensor | None, given, shape: torch.Size, *, stacked: bool, at: str) -> Tensor | None:
    """The config's ``fixed`` mask (of one mode's tensor) or'ed into ``fixed``."""
    if given is None:
        return fixed
    try:
        mask = torch.as_tensor(list(given) if not isinstance(given, bool) else given, dtype=torch.bool)
        mask = mask.expand(shape[1:] if stacked else shape)
    except (RuntimeError, TypeError, ValueError):
        raise ConfigError(f"{at}.fixed", given, f"expected a boolean mask of shape "
                          f"{tuple(shape[1:] if stacked else shape)}") from None
    mask = mask.expand(shape) if stacked else mask
    return mask.clone() if fixed is None else fixed | mask


def _entry_names(entry, shape: torch.Size, at: str) -> list | None:
    """``names``: one model's tensor entries named (e.g. ``[[const, ogap, inf]]`` for an ``H`` of 1 x 3),
    reported as ``const[regime]`` (``const`` where shared by every regime)."""
    given = entry.get("names")
    if given is None:
        return None
    flat = []

    def walk(x):
        if isinstance(x, (list, tuple)) or type(x).__name__ == "ListConfig":
            for v in x:
                walk(v)
        else:
            flat.append(str(x))
    walk(given)
    if len(flat) != math.prod(shape):
        raise ConfigError(f"{at}.names", given, f"expected {math.prod(shape)} names, one per entry of shape "
                          f"{tuple(shape)}")
    return flat


def rename(name: str, where: dict) -> str:
    """A reported entry's name in the study's terms: ``bank.filter.measurement.H[1,0,0]`` ->
    ``sensors[1].H[0,0]`` (or its ``names`` entry: ``const[1]``, ``ogap`` where shared by every mode),
    ``transition.value[0,1]`` -> ``transition[0,1]``."""
    match = re.fullmatch(r"(.*?)(\[[\d,]*\])?", name)
    label, index = match.group(1), match.group(2) or ""
    for model, tensor, stacked, names, groups, shape in where.values():
        prefix = f"{model}.{tensor}" if model is not None else tensor
        if label != prefix or not index:
            continue
        parts = [int(p) for p in index[1:-1].split(",")]
        inner = parts[1:] if stacked else parts
        if names is not None and len(inner) == len(shape):  # (a duration's [i] keeps the tensor's name)
            flat = 0
            for size, i in zip(shape, inner):
                flat = flat * size + i
            shared = groups is not None and int(groups[tuple(parts)]) >= 0
            return names[flat] if shared or not stacked else f"{names[flat]}[{parts[0]}]"
        if stacked:
            rest = ",".join(str(i) for i in inner)
            return f"{model}[{parts[0]}].{tensor}" + (f"[{rest}]" if rest else "")
        return f"{prefix}{index}"
    return name


def start_function(est, scenario, transition_learned: bool, controls: Tensor | None = None):
    """The estimator's start as a function of its filter: with ``initial_mode_probs: ergodic`` and the
    transition matrix estimated, the stationary probabilities of the matrix being evaluated (a time-varying
    one's at the first step's controls, each series its own)."""
    from torchmm.learn import stationary

    if not (scenario.ergodic and transition_learned and est.multiple_model):
        return None
    first = None if controls is None else controls[0]

    def init(prior, generator=None):
        options = {"generator": generator} if generator is not None else {}
        transition = est.filter.transition
        matrix = transition.at(first).matrix() if getattr(transition, "takes_inputs", False) else transition.matrix()
        return est.filter.initial_belief(prior, stationary(matrix), **options)
    return init


def fit_mle(est, scenario, block, z: Tensor, *, prior, update_first: bool, burn: int, controls=None,
            progress: bool | str = False, motions=None) -> dict:
    """Estimate ``block.parameters`` of ``est``'s filter on ``z`` (in place) and return the record: the
    rows of the ``learned`` table, the fit's figures, and the estimator's new start (if it changed)."""
    from torchmm.learn import estimate

    params, where = parameters_of(est, scenario, block)
    transition = any(w[1] == "transition" for w in where.values())
    init = start_function(est, scenario, transition, controls)
    starting = [w[1] for w in where.values() if w[1] in START_NAMES]
    if init is not None:
        est.init = init
    belief0 = (lambda f: est.init(prior, None)) if init is not None else est.init(prior, None)
    tic = time.perf_counter()
    result = estimate(est.filter, belief0, z, params, controls=controls, motions=motions, update_first=update_first,
                      burn=burn,
                      hessian=str(block.get("hessian") or "differences"), maxiter=block.get("maxiter"),
                      progress=progress)
    if starting:
        start_after(est, result)
    rows = [[est.name, rename(n, where), e, s, zv] for n, e, s, zv in result.rows()]
    rows += [[est.name, f"duration of {rename(n.removeprefix('duration of '), where)}", d, s,
              d / s if s and math.isfinite(s) and s > 0 else math.nan] for n, d, s in result.durations]
    return {"rows": rows, "loglik": result.loglik, "k": result.k, "nobs": result.nobs, "aic": result.aic,
            "bic": result.bic, "iterations": result.iterations, "evaluations": result.evaluations,
            "converged": result.converged, "message": result.message, "seconds": time.perf_counter() - tic,
            "note": result.note, "method": "mle", "nll": [-result.loglik], "through": est.name}
