"""The ``learn`` block's ``method: em`` (and ``em_then_mle``) of the generic study: EM of a Kalman filter over
linear models (:func:`torchmm.learn.em`) and of a Markov-switching IMM (:func:`torchmm.learn.em_switching`),
each entry of ``learn.parameters`` mapped to EM's names and checked before anything runs; split from
:mod:`experiments.learning` by concern (issue 47)."""

from __future__ import annotations

import math
import time

import numpy as np
import torch
from torch import Tensor

from experiments.config import ConfigError
from experiments.learning import entry_where, fit_mle, parameters_of, rename, start_function


# -- method: em (linear-Gaussian Kalman filters) -----------------------------------------------------------
def check_whole_vectors(method: str, data) -> None:
    """EM's steps take whole measurement vectors (:func:`torchmm.learn.em`, docs/estimation.md): recorded
    ``data`` (:class:`experiments.datafile.DataSeries`) with a step whose measurement cells are missing in
    part (not all) is a ``ConfigError`` naming ``learn.method`` and the file's first such row."""
    z = data.measurements
    seen = np.isfinite(z)
    part = seen.any(-1) & ~seen.all(-1) & data.present
    if not part.any():
        return
    rows = data.rows if data.rows is not None else np.arange(z.shape[0])[:, None] + 0 * part
    k, j = min(zip(*np.nonzero(part)), key=lambda kj: (int(rows[kj]), kj[1]))  # the file's first such row
    raise ConfigError("learn.method", method, f"EM's steps take whole measurement vectors; "
                      f"{data.where(k, j)} (series {data.series[j]!r}, step {k}) has some measurement cells "
                      "missing, not all (method mle learns from such steps; or leave every measurement "
                      "cell of the step empty)")


EM_NAMES = {("modes", "F"): "F", ("modes", "offset"): "offset", ("modes", "Q"): "Q", ("sensors", "H"): "H",
            ("sensors", "R"): "R", (None, "initial_mean"): "initial_mean", (None, "initial_cov"): "initial_cov"}


def em_parameters(est, block, key: str = "learn.parameters", scenario=None) -> list[str]:
    """The names :func:`torchmm.learn.em` takes for ``block.parameters`` of ``est`` (a Kalman filter over
    linear models), or a ``ConfigError`` naming the entry."""
    from torchmm import KalmanFilter
    from torchmm.models.linear import plain_linear

    f = est.filter
    if est.multiple_model:
        return switching_em_parameters(est, block, key, scenario)[0]
    if not isinstance(f, KalmanFilter):
        raise ConfigError("learn.method", str(block.method), f"EM fits a Kalman filter over linear models; "
                          f"{est.name} is a {type(f).__name__} (EM for switching models is not implemented yet: "
                          "method mle)")
    if not (plain_linear(f.motion) and plain_linear(f.measurement)):
        raise ConfigError("learn.method", str(block.method), f"EM fits linear-Gaussian models; {est.name}'s are "
                          f"{type(f.motion).__name__} and {type(f.measurement).__name__} (method mle)")
    names = []
    entries = block.parameters
    if isinstance(entries, str):
        raise ConfigError(key, entries, "method em takes a list of entries")
    for i, entry in enumerate(entries):
        try:
            model, index = entry_where(entry)
        except ValueError as err:
            raise ConfigError(f"{key}[{i}].model", entry.get("model"), str(err)) from None
        if index is not None and model == "modes" and est.mode is not None and index != est.mode:
            raise ConfigError(f"{key}[{i}].model", entry.model, f"{est.name} runs mode {est.mode} only")
        name = EM_NAMES.get((model, str(entry.name)))
        if name is None:
            known = ", ".join(f"{m}.{n}" if m else n for m, n in EM_NAMES)
            raise ConfigError(f"{key}[{i}]", f"{entry.get('model')}.{entry.name}", f"method em estimates {known}")
        for option in ("shared", "lower", "upper"):
            if entry.get(option) not in (None, False):
                raise ConfigError(f"{key}[{i}].{option}", entry.get(option), "method em takes fixed entries, not "
                                  "shared or bounded ones (method mle)")
        names.append(name)
    return names


def em_fixed(est, block, prior, key: str = "learn.parameters", scenario=None) -> dict:
    """The entries' ``fixed`` masks for :func:`torchmm.learn.em` (``{name: mask}``), checked against the
    estimator's models and start (``ConfigError`` naming the entry: a shape, or a covariance pattern
    without a closed-form M-step)."""
    from torchmm.learn.em import fixed_masks

    names = em_parameters(est, block, key, scenario)
    masks = {}
    if est.multiple_model:  # (em_switching's own masks: switching_em_parameters, checked there)
        return masks
    for i, (entry, name) in enumerate(zip(block.parameters, names)):
        given = entry.get("fixed")
        if given is None:
            continue
        mask = given if isinstance(given, bool) else _plain(given)
        try:
            masks.update(fixed_masks(est.filter, est.init(prior, None), names, {name: mask}))
        except (TypeError, ValueError) as err:
            raise ConfigError(f"{key}[{i}].fixed", given, str(err).split(": ", 1)[-1]) from None
    return masks


def _plain(value):
    """A config list (nested ListConfig) as Python lists."""
    if isinstance(value, (list, tuple)) or type(value).__name__ == "ListConfig":
        return [_plain(v) for v in value]
    return value


def switching_em_parameters(est, block, key: str = "learn.parameters", scenario=None) -> tuple[list, dict, dict]:
    """``(parameters, shared, fixed)`` of :func:`torchmm.learn.em_switching` for ``block.parameters`` of a
    multiple-model estimator (an IMM over a vectorised Kalman bank; ``auto``: the scenario's entries), or a
    ``ConfigError`` naming the entry. ``shared``: ``{"H": True or an (m, n) mask, "R": True}``; ``fixed``:
    ``{"H": mask, "transition": mask}`` (entries held at their start values)."""
    from omegaconf import OmegaConf

    from torchmm import KalmanFilter, LinearMeasurement

    inner = getattr(getattr(est.filter, "bank", None), "filter", None)
    if not (isinstance(inner, KalmanFilter) and isinstance(inner.measurement, LinearMeasurement)):
        raise ConfigError("learn.method", str(block.method), f"EM for switching models takes an IMM over Kalman "
                          f"filters with linear sensors; {est.name}'s bank is not one (method mle)")
    entries = block.parameters
    if isinstance(entries, str):
        if entries != "auto" or getattr(scenario, "learn_parameters", None) is None:
            raise ConfigError(key, entries, "method em takes a list of entries, or auto for a scenario that says "
                              "what it estimates (experiments.scenarios.markov_switching)")
        entries = OmegaConf.create(scenario.learn_parameters)
    H = inner.measurement.H
    m, n = H.shape[-2], H.shape[-1]
    names, shared, fixed = [], {}, {}

    def mask(value, at: str, shape: tuple, what: str):
        try:
            out = torch.as_tensor(OmegaConf.to_object(value) if OmegaConf.is_config(value) else value, dtype=torch.bool)
            return out.expand(shape) if out.shape != shape and out.dim() <= len(shape) else out
        except (TypeError, ValueError, RuntimeError):
            raise ConfigError(at, value, f"expected a boolean mask of shape {shape} ({what})") from None

    for i, entry in enumerate(entries):
        at = f"{key}[{i}]"
        name = str(entry.name)
        model = entry.get("model")
        if entry.get("lower") is not None or entry.get("upper") is not None:
            raise ConfigError(at, f"{model}.{name}" if model else name, "method em takes no bounds (method mle)")
        if name == "transition" and model is None:
            names.append("transition")  # (a time-varying one: its logistic coefficients, em_switching's M-step)
            if entry.get("fixed") is not None and getattr(est.filter.transition, "takes_inputs", False):
                raise ConfigError(f"{at}.fixed", entry.fixed, "a time-varying transition's coefficients are "
                                  "estimated whole by method em (method mle holds entries)")
            if entry.get("fixed") is not None:
                M = est.filter.num_modes
                fixed["transition"] = mask(entry.fixed, f"{at}.fixed", (M, M), "entries held at their start")
                if fixed["transition"].shape != (M, M):
                    raise ConfigError(f"{at}.fixed", entry.fixed, f"expected a boolean mask of shape ({M}, {M})")
            continue
        one_sensor = not (getattr(inner.measurement, "H").dim() == 3)  # one sensor for every mode: sensors[0] is it
        if str(model).startswith("sensors") and name in ("H", "R") and ("[" not in str(model)
                                                                       or (one_sensor and str(model) == "sensors[0]")):
            share = entry.get("shared")
            if share not in (None, False, True):
                if name == "R":
                    raise ConfigError(f"{at}.shared", share, "method em shares R whole across the modes or not at all")
                share = mask(share, f"{at}.shared", (m, n), "the entries every mode shares")
                if share.shape != (m, n):
                    raise ConfigError(f"{at}.shared", entry.shared, f"expected a boolean mask of shape ({m}, {n})")
            if entry.get("fixed") is not None:
                if name == "R":
                    raise ConfigError(f"{at}.fixed", entry.fixed, "method em estimates R whole (method mle)")
                fixed["H"] = mask(entry.fixed, f"{at}.fixed", (m, n), "entries held at their start")
            names.append(name)
            if share is not None and share is not False:
                shared[name] = share
            continue
        raise ConfigError(at, f"{model}.{name}", "method em for switching models estimates transition, "
                          "sensors.H and sensors.R (every mode's); others: method mle")
    if scenario is not None:  # each entry as method mle reads it (its names, masks): the learned table's rows
        parameters_of(est, scenario, block, key)
    return names, shared, fixed


def fit_switching_em(est, scenario, block, z: Tensor, *, prior, update_first: bool, burn: int, controls=None,
                     present=None, progress: bool | str = False) -> dict:
    """EM (Baum-Welch for the chain, weighted least squares for each mode's sensor) of a multiple-model
    estimator, then with ``em_then_mle`` maximum likelihood from there."""
    from torchmm.learn import em_switching
    from torchmm.learn.entries import blocks

    names, shared, fixed = switching_em_parameters(est, block, scenario=scenario)
    params, where = parameters_of(est, scenario, block)  # (the entries as mle names them: the learned table)
    tic = time.perf_counter()
    ergodic = bool(scenario.ergodic)
    try:
        out = em_switching(est.filter, est.init(prior, None), z, names, iterations=int(block.iterations),
                           tol=float(block.get("tolerance") or 0.0) or None, update_first=update_first, shared=shared,
                           fixed=fixed, ergodic=ergodic, controls=controls, present=present, progress=progress)
    except ValueError as err:  # a mask the model cannot take (a shared entry fixed in one regime only, ...)
        raise ConfigError("learn.parameters", block.parameters if isinstance(block.parameters, str) else "entries",
                          str(err)) from None
    # the ergodic start of the estimated transition (a time-varying one's at the first step's controls, as
    # fit_mle's); where the transition is not estimated the start stays as it was, and EM is exact
    approximate = ergodic and "transition" in names
    init = start_function(est, scenario, "transition" in names, controls)
    if init is not None:
        est.init = init
    if str(block.method) == "em_then_mle":
        mle = fit_mle(est, scenario, block, z, prior=prior, update_first=update_first, burn=burn, controls=controls,
                      progress=progress)
        mle.update(em=out.loglik, method="em_then_mle", seconds=time.perf_counter() - tic)
        return mle
    rows, durations, k = [], [], 0
    for b in blocks(est.filter, params):  # (at EM's estimates: each estimated entry, named as under mle)
        values = b.value.to(torch.float64).cpu().reshape(-1)[b.reported].tolist()
        rows += [[est.name, rename(n, where), v, None, None] for n, v in zip(b.names(), values)]
        k += b.u0.numel()  # (the free values: a fixed entry, a shared one's copies, a row's rest not counted)
        if b.kind == "stochastic":
            M = b.shape[-1]
            P = b.value.to(torch.float64).cpu().reshape(-1, M, M)
            for i, d in enumerate((1 / (1 - P.diagonal(dim1=-2, dim2=-1))).reshape(-1).tolist()):
                at = f"[{i // M},{i % M}]" if P.shape[0] > 1 else f"[{i}]"
                durations.append([est.name, f"duration of {rename(b.label + at, where)}", d, None, None])
    rows += durations  # (after the estimates, as under mle)
    nobs = int(torch.isfinite(z).all(-1).sum())
    return {"rows": rows, "loglik": out.loglik[-1], "k": k, "nobs": nobs, "aic": -2 * out.loglik[-1] + 2 * k,
            "bic": -2 * out.loglik[-1] + k * math.log(max(1, nobs)), "iterations": out.iterations,
            "evaluations": len(out.loglik), "converged": out.converged,
            "message": "" if out.monotone else f"the likelihood decreased at iteration(s) {out.decreases}",
            "seconds": time.perf_counter() - tic,
            "note": "the ergodic start's dependence on the transition matrix is left out of EM's M-step "
                    "(statsmodels does the same): its fixed point is near, not at, the maximum; em_then_mle "
                    "finishes it" if approximate else "", "method": "em", "nll": [-v for v in out.loglik],
            "through": est.name, "em": out.loglik}


def fit_em(est, scenario, block, z: Tensor, *, prior, update_first: bool, burn: int, controls=None, present=None,
           progress: bool | str = False) -> dict:
    """EM of ``block.parameters`` of ``est``'s Kalman filter on ``z`` (in place; the start belief too), then
    with ``method: em_then_mle`` maximum likelihood from there (statsmodels' ``fit``: EM, then a
    quasi-Newton method), which adds the standard errors. Returns the record."""
    from torchmm.learn import em

    if est.multiple_model:
        return fit_switching_em(est, scenario, block, z, prior=prior, update_first=update_first, burn=burn,
                                controls=controls, present=present, progress=progress)
    names = em_parameters(est, block)
    masks = em_fixed(est, block, prior)
    tic = time.perf_counter()
    out = em(est.filter, _shared_start(est.init(prior, None)), z, names, iterations=int(block.iterations),
             tol=float(block.get("tolerance") or 0.0) or None, update_first=update_first, controls=controls,
             present=present, fixed=masks or None, progress=progress)
    start = out.belief0
    est.init = lambda prior_, generator=None: start
    rows = []
    tensors = {"F": est.filter.motion.F, "offset": est.filter.motion.offset, "Q": est.filter.motion.Q,
               "H": est.filter.measurement.H, "R": est.filter.measurement.R, "initial_mean": start.mean[0] if
               start.mean.dim() > 1 else start.mean, "initial_cov": start.cov[0] if start.cov.dim() > 2 else start.cov}
    k = 0
    for entry, name in zip(block.parameters, names):
        value = tensors[name].detach().cpu()
        label = f"{entry.model}.{name}" if entry.get("model") is not None else name
        symmetric = name in ("Q", "R", "initial_cov")
        held = masks.get(name)
        for flat, v in enumerate(value.reshape(-1).tolist()):
            index = [int(i) for i in np.unravel_index(flat, tuple(value.shape))] if value.dim() else []
            if symmetric and index[-1] > index[-2]:
                continue  # (the upper triangle repeats the lower)
            if held is not None and bool(held.reshape(-1)[flat % held.numel()]):
                continue  # (a fixed entry: not estimated)
            rows.append([est.name, f"{label}[{','.join(map(str, index))}]", v, None, None])
            k += 1
    record = {"rows": rows, "loglik": out.loglik[-1], "k": k, "nobs": int(torch.isfinite(z).all(-1).sum()),
              "aic": -2 * out.loglik[-1] + 2 * k, "bic": -2 * out.loglik[-1] + k * math.log(max(1, int(
                  torch.isfinite(z).all(-1).sum()))), "iterations": out.iterations, "evaluations": len(out.loglik),
              "converged": out.converged, "message": "" if out.monotone else
              f"the likelihood decreased at iteration(s) {out.decreases}", "seconds": time.perf_counter() - tic,
              "note": "", "method": "em", "nll": [-v for v in out.loglik], "through": est.name, "em": out.loglik}
    if str(block.method) == "em_then_mle":
        mle = fit_mle(est, scenario, mle_stage(est, block, names, masks), z, prior=prior,
                      update_first=update_first, burn=burn, controls=controls, progress=progress)
        mle["em"] = out.loglik
        mle["method"] = "em_then_mle"
        mle["seconds"] = time.perf_counter() - tic
        return mle
    return record


def _shared_start(belief):
    """The study's start (the prior is shared by the series) as one start broadcast over them (an expanded
    view), which :func:`torchmm.learn.em` estimates as one start for all series (pooled), not one each."""
    from torchmm import GaussianBelief

    batch, n = belief.batch_shape, belief.mean.shape[-1]
    mean = belief.mean.expand(*batch, n).reshape(-1, n)
    cov = belief.cov.expand(*batch, n, n).reshape(-1, n, n)
    if batch.numel() > 1 and bool((mean == mean[:1]).all()) and bool((cov == cov[:1]).all()):
        return GaussianBelief(mean[0], cov[0]).expand(batch)
    return belief


def mle_stage(est, block, names: list[str], masks: dict, key: str = "learn.parameters"):
    """The ``learn`` block of ``em_then_mle``'s maximum likelihood (:func:`fit_mle`) after EM: every entry EM
    estimated, the start's (``initial_mean``, ``initial_cov``) included, from EM's values, each with the kind
    that estimates what EM did: ``free`` for ``F``, ``H``, the offset and the start's mean; for ``Q``, ``R``
    and ``initial_cov`` ``variance`` where EM estimated the diagonal (a 1x1 matrix, or ``fixed`` holding
    every off-diagonal entry) and ``covariance`` where it estimated the whole matrix. An entry's own
    ``kind`` is taken where it estimates the same; another (``variance`` of a matrix EM estimated whole,
    ``covariance`` of one with fixed entries) or a mask with free blocks larger than one entry (EM's
    block-diagonal covariance: no kind of ``mle`` estimates it) is a ``ConfigError`` naming the entry."""
    from omegaconf import OmegaConf

    from experiments.learning import KIND_ALIASES

    tensors = {"Q": est.filter.motion.Q, "R": est.filter.measurement.R, "initial_cov": None}
    entries = []
    for i, (e, name) in enumerate(zip(block.parameters, names)):
        entry = dict(OmegaConf.to_container(e))
        given = entry.get("kind")
        given = KIND_ALIASES.get(str(given), given) if given is not None else None
        if name not in ("Q", "R", "initial_cov"):
            entry["kind"] = given or "free"
            entries.append(entry)
            continue
        value = tensors[name]
        d = int(value.shape[-1]) if value is not None else int(est.filter.state_dim)
        mask = masks.get(name)
        off = ~torch.eye(d, dtype=torch.bool)
        diagonal = d == 1 or (mask is not None and bool(mask[off].all()))
        if mask is not None and not diagonal:
            raise ConfigError(f"{key}[{i}].fixed", entry.get("fixed"), "method em_then_mle: EM estimates "
                              f"{name} in diagonal blocks larger than one entry, which no kind of maximum "
                              "likelihood estimates (variance: the diagonal; covariance: the whole matrix, "
                              "no fixed entries); method em, or fix every off-diagonal entry")
        kind = "variance" if diagonal else "covariance"
        if given is not None and given != kind and d > 1:
            raise ConfigError(f"{key}[{i}].kind", e.get("kind"), f"method em_then_mle: EM estimates "
                              f"{'the diagonal' if diagonal else 'the whole matrix'} of {name}, its maximum "
                              f"likelihood stage the same (kind {kind}, or leave kind out)"
                              + ("" if diagonal else "; fixed: every off-diagonal entry for a diagonal one"))
        entry["kind"] = given if given is not None and d == 1 else kind
        entries.append(entry)
    return OmegaConf.merge(block, {"parameters": entries})
