"""The generic study: your own scenario x estimators x metrics, from config alone (``experiment=compare``).

* **Scenario** (``scenario``, :func:`experiments.scenarios.system`): any list of modes (linear,
  nonlinear or learned ``nn.Module`` motion models by ``_target_``) or one mode bank, one or more
  sensors with missing and multi-rate reports, a transition matrix, the prior; simulated for
  ``mc_runs`` runs, or recorded data read from CSV / NPZ (``scenario.data``: one series per run,
  optional truth and time stamps; irregular time stamps become per-step motion models).
* **Estimators** (``estimators``): a map of config nodes, each a builder of
  :mod:`experiments.estimators` (``multiple_model`` with any combinator and mode filter,
  ``kalman``, ``custom`` for any torchmm filter node); ``smooth: true`` also scores its smoothed
  trajectory (``torchmm.smooth``) as ``<name> smoothed``.
* **Metrics** (``metrics``, by name): ``rmse`` (per component group, ``scenario.groups``),
  ``nees`` and ``nis`` (with their 95 % chi-square bounds), ``mode_accuracy``, ``loglik`` (the log-
  likelihood of each run's data), ``whiteness`` (lag-1 autocorrelation of the normalised innovations)
  and ``time``. Without truth (recorded data without truth columns) only ``loglik``, ``nis``,
  ``whiteness`` and ``time`` exist.
* **Paired differences** (table ``paired``): every estimator minus the reference
  (``paired.reference``, default the first) on the same runs, with a 95 % interval. The runs share
  their data, so the paired interval is far tighter than two separate ones (``separate_half_width``).
* **Learning** (``learn``, optional): named covariances of the scenario's models made learnable
  (``torchmm.learnable_noise``) and fitted by maximum likelihood on the data through one estimator
  (L-BFGS by default), before every estimator runs with the learned models.

Tables: ``summary``, ``paired``, ``learned`` (with ``learn``). Curves: ``rmse_<group>/<estimator>``
with ``_se`` bands, ``nees/<estimator>`` with ``nees_low``/``nees_high``, ``nis/<estimator>``,
``mode_probability/<estimator>/<mode>``, ``learn/nll`` over the iteration.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

import torch
from hydra.utils import instantiate
from torch import Tensor

from experiments import learning, learning_em, learning_gradient
from experiments.estimators import join_trajectories, mode_model, random_blocks
from experiments.executors import Unit
from experiments.harness import StudyContext, per_run
from experiments.scenarios_system import Concatenated, default_dtype
from experiments.studies.compare_results import (curves_and_figures, learned_tables, not_computed, paired, reduce,
                                                 series_table)
from experiments.studies.compare_truth import marginal_nees, partial_series, series_nees, truth_components
from torchmm import run_filter, smooth
from torchmm.metrics import mode_hits

log = logging.getLogger("torchmm.experiments")

UNIT = "experiments.studies.compare:unit"
TRUTH_METRICS = ("rmse", "nees", "mode_accuracy")
ALL_METRICS = ("rmse", "nees", "nis", "mode_accuracy", "loglik", "whiteness", "time")
#: the parametrisations of a learned covariance (torchmm.learnable_noise)
#: the summary's values (the others are their standard errors, bounds and counts)
_MAIN = ("nees", "nis", "loglik", "mode_accuracy", "whiteness_lag1")


# -- the scenario, its data and its (learned) models ---------------------------------------------------
def _built(ctx: StudyContext):
    """The scenario as configured (before learning), once per process."""
    return ctx.memo(("compare", "built"), lambda: ctx.scenarios(ctx.cfg.scenario)[0])


def _scenario_of(ctx: StudyContext, name: str | None = None):
    """The scenario in the filters' dtype for estimator ``name``: its own models, fitted first when it
    learns by ``method: gradient`` (once per process, on a copy: one estimator's fit never reaches
    another)."""
    if name is None or name not in learning.learners(ctx.cfg):
        return _built(ctx)
    return _learned(ctx, name)[0]


def _learned(ctx: StudyContext, name: str):
    """``(scenario, record, estimator)``: estimator ``name`` on its own copy of the models, fitted
    (memoised)."""
    def fit():
        scenario = learning.own_models(_built(ctx))
        record, est = _learn(ctx, scenario, name)
        return scenario, record, est
    return ctx.memo(("compare", "learned", name), fit)


def _data(ctx: StudyContext, start: int, stop: int):
    """``(truth or None, modes or None, z, present)`` of runs ``start..stop-1``, in the filters' dtype."""
    def load():
        scenario = _built(ctx)
        if scenario.data is not None:
            d = scenario.data
            z = torch.as_tensor(d.measurements[:, start:stop], dtype=ctx.dtype, device=ctx.device)
            truth = None if d.truth is None else torch.as_tensor(d.truth[:, start:stop], dtype=ctx.dtype,
                                                                  device=ctx.device)
            present = torch.as_tensor(d.present[:, start:stop], device=ctx.device)
            return truth, None, z, present
        _, data_scenario = ctx.scenarios(ctx.cfg.scenario)
        sim, z = ctx.simulate_runs(data_scenario.simulate, stop, "data", scenario.name, start=start)
        present = torch.ones(z.shape[:2], dtype=torch.bool, device=z.device)
        return sim.states.to(ctx.dtype), sim.modes, z.to(ctx.dtype), present
    return ctx.memo(("compare", "data", start, stop), load)


def _controls(ctx: StudyContext, start: int, stop: int) -> Tensor | None:
    """The data's inputs (``scenario.data.inputs``: regressors) of runs ``start..stop-1`` as the motion
    models' controls ``(T, runs, k)``, or None."""
    scenario = _built(ctx)
    inputs = None if scenario.data is None else scenario.data.inputs
    if inputs is None:
        return None
    return torch.as_tensor(inputs[:, start:stop], dtype=ctx.dtype, device=ctx.device)


def runs_of(ctx: StudyContext) -> int:
    scenario = _built(ctx)
    return scenario.data.runs if scenario.data is not None else int(ctx.cfg.mc_runs)


def _estimator(ctx: StudyContext, scenario, name: str):
    with default_dtype(ctx.dtype):
        est = instantiate(ctx.cfg.estimators[name])(scenario, name=name)
    est.filter.to(device=ctx.device)
    return est


def _module(scenario, where: str):
    """``modes[i]`` / ``modes`` / ``sensors[i]`` / ``sensors``: the scenario's model of that name (a
    ``ValueError`` saying what is wrong)."""
    kind, _, index = where.partition("[")
    if kind not in ("modes", "sensors") or (index and not index.rstrip("]").isdigit()):
        raise ValueError("expected modes[i] or sensors[i]")
    index = int(index.rstrip("]")) if index else 0
    if kind == "modes":
        models = scenario.motion if isinstance(scenario.motion, list) else [scenario.motion]
    else:
        models = list(scenario.measurement.sensors) if isinstance(scenario.measurement, Concatenated) \
            else list(scenario.measurement) if isinstance(scenario.measurement, list) else [scenario.measurement]
    if not 0 <= index < len(models):
        raise ValueError(f"there {'is' if len(models) == 1 else 'are'} {len(models)} {kind} (indices 0.."
                         f"{len(models) - 1})")
    return models[index]


def _learn(ctx: StudyContext, scenario, est_name: str) -> tuple[dict, Any]:
    """Estimator ``est_name`` fitted on the study's data, on ``scenario`` (its own copy of the models):
    ``(record, estimator)`` (docs/studies.md, "Learning")."""
    block = learning.spec(ctx.cfg)
    runs = scenario.data.runs if scenario.data is not None else int(ctx.cfg.mc_runs)
    _, _, z, _ = _data(ctx, 0, runs)
    prior = scenario.initial.expand(runs)
    burn, update_first = int(ctx.cfg.get("burn") or 0), bool(ctx.cfg.get("update_first"))
    progress = ctx.progress and f"learn {est_name}"
    if str(block.method) == "mle":
        import torchmm.kernels as kernels

        est = _estimator(ctx, scenario, est_name)
        # the whole data at once, in this one process: no split into units can change the fit, so the
        # kernels that the study otherwise switches off (kernels.by_size) evaluate the likelihood
        with kernels.switched_on(*kernels.by_size()):
            record = learning.fit_mle(est, scenario, block, z, prior=prior, update_first=update_first, burn=burn,
                                      controls=_controls(ctx, 0, runs), progress=progress,
                                      motions=_motions(est, scenario))
        return record, est
    if str(block.method) in ("em", "em_then_mle"):
        import torchmm.kernels as kernels

        est = _estimator(ctx, scenario, est_name)
        _, _, _, present = _data(ctx, 0, runs)
        with kernels.switched_on(*kernels.by_size()):
            record = learning_em.fit_em(est, scenario, block, z, prior=prior, update_first=update_first, burn=burn,
                                     controls=_controls(ctx, 0, runs), present=present, progress=progress)
        return record, est
    record = learning_gradient.fit_gradient(scenario, block, lambda: _estimator(ctx, scenario, est_name), _module, z,
                                            prior, name=est_name, burn=burn, update_first=update_first,
                                            progress=progress, controls=_controls(ctx, 0, runs))
    return record, None


def check_build(cfg, scenario) -> None:
    """The config's dry construction before anything runs (:func:`experiments.config.dry_build`): every
    estimator built on ``scenario``, and each learning estimator's ``learn.parameters`` made learnable
    on its own copy of the models; a failure is one ``ConfigError`` naming the key."""
    from experiments.config import ConfigError, build_error

    if scenario is None:
        return
    for name in cfg.estimators:
        try:
            instantiate(cfg.estimators[name])(scenario, name=name)
        except Exception as err:  # noqa: BLE001 - any constructor's error, named by the estimator's (sub)key
            raise build_error(f"estimators.{name}", cfg.estimators[name], err) from None
    if scenario.data is not None and scenario.data.inputs is not None:
        motions = scenario.motion if isinstance(scenario.motion, list) else [scenario.motion]
        k = scenario.data.inputs.shape[-1]
        for i, m in enumerate(motions):
            B = getattr(m, "input_matrix", None)
            if B is None or B.shape[-1] != k:
                raise ConfigError("scenario.data.inputs", list(cfg.scenario.data.inputs), f"{k} input(s), but "
                                  f"mode {i}'s motion model takes "
                                  f"{'no input' if B is None else str(B.shape[-1]) + ' (its input_matrix)'}")
    names = learning.learners(cfg)
    if names and scenario.motions is not None:  # irregular time stamps: the per-step motion models are fixed
        block = learning.spec(cfg)
        if str(block.method) != "mle":
            raise ConfigError("learn.method", str(block.method), "with irregular time stamps (per-step motion "
                              "models) only method mle learns (the sensors, the transition, the start)")
        entries = [] if isinstance(block.parameters, str) else list(block.parameters)
        moving = [str(e.get("model")) for e in entries if str(e.get("model") or "").startswith("modes")]
        if moving:
            raise ConfigError("learn.parameters", moving[0], "a motion model's tensors with irregular time stamps: "
                              "each step's model is rebuilt for its own dt, so a tensor of one is not the others' "
                              "(learn the sensors, the transition or the start; or give regular time stamps)")
    burn = int(cfg.get("burn") or 0)
    if burn >= scenario.steps:
        raise ConfigError("burn", burn, f"leaves out every step (the data have {scenario.steps}): no log-likelihood "
                          "term is left")
    block = learning.spec(cfg)
    if names and str(block.method) in ("em", "em_then_mle") and scenario.data is not None:
        learning_em.check_whole_vectors(str(block.method), scenario.data)
    for name in names:
        own = learning.own_models(scenario)
        if str(block.method) in ("em", "em_then_mle"):
            est = instantiate(cfg.estimators[name])(own, name=name)
            masks = learning_em.em_fixed(est, block, own.initial, scenario=own)
            if str(block.method) == "em_then_mle" and not est.multiple_model:  # (its MLE stage's kinds)
                learning_em.mle_stage(est, block, learning_em.em_parameters(est, block, scenario=own), masks)
            if burn and str(block.method) == "em":
                raise ConfigError("burn", burn, "method em maximises the likelihood of every step (burn: 0; "
                                  "em_then_mle's maximum likelihood leaves the burn-in out)")
            continue
        if str(block.method) == "mle":
            from torchmm.learn import estimated_entries

            est = instantiate(cfg.estimators[name])(own, name=name)
            params, _ = learning.parameters_of(est, own, block)
            for tensor, param in params.items():
                try:
                    estimated_entries(est.filter, {tensor: param},
                                      est.init(own.initial, None) if tensor.startswith("belief0.") else None)
                except (TypeError, ValueError) as err:
                    raise ConfigError("learn.parameters", param.label, str(err).split(": ", 1)[-1]) from None
            continue
        learning_gradient.gradient_targets(own, block, _module)
        est = instantiate(cfg.estimators[name])(own, name=name)
        if not any(p.requires_grad for p in est.filter.parameters()):
            key = "learn.estimator" if cfg.learn.get("estimator") is not None else "learn.estimators"
            raise ConfigError(key, name, "its filter does not use the scenario's models named in learn.parameters "
                              "(a custom filter builds its own models from its node, even from an interpolation "
                              "such as ${scenario.sensors.0}); name the estimators that do in learn.estimators")


# -- one unit: an estimator on a range of runs ------------------------------------------------------------
def _innovation_stats(traj, z: Tensor, multiple: bool):
    """``(nis (T, N), dof (T, N), white (T, N, m))``: the NIS over the present components, their number,
    and the normalised innovations (NaN where a component is missing); None if the filter records no
    innovation. For a multiple-model filter the innovation is the mixture's: the predicted-mode-weighted
    mean of the mode innovations and its covariance (spread included)."""
    nu, S = traj.innovation, traj.innovation_cov
    if nu is None or S is None:
        return None
    if multiple:
        c = traj.prior.mode_probs if traj.prior is not None else traj.belief.mode_probs
        if c.shape[-1] != nu.shape[-2]:  # innovations per hypothesis (GPB2's mode pairs): not scored
            return None
        mean = (c.unsqueeze(-1) * nu).sum(-2)
        d = nu - mean.unsqueeze(-2)
        S = (c[..., None, None] * (S + d.unsqueeze(-1) * d.unsqueeze(-2))).sum(-3)
        nu = mean
    present = torch.isfinite(z) & torch.isfinite(nu)
    nu0 = torch.where(present, nu, torch.zeros_like(nu))
    keep = present.unsqueeze(-1) & present.unsqueeze(-2)
    eye = torch.eye(nu.shape[-1], dtype=nu.dtype, device=nu.device)
    S0 = torch.where(keep, torch.nan_to_num(S), eye)  # missing rows/cols -> identity, zero coupling
    L = torch.linalg.cholesky(S0)
    white = torch.linalg.solve_triangular(L, nu0.unsqueeze(-1), upper=False).squeeze(-1)
    nis = white.square().sum(-1)
    white = torch.where(present, white, torch.nan)
    return nis, present.sum(-1), white


def _motions(est, scenario):
    """The per-step motion models of irregular time stamps for ``est``: the scenario's (one per mode) for a
    multiple-model estimator, its own mode's for ``kalman``; None for other single filters (``custom``:
    they keep their own ``dt``, noted in the results)."""
    if scenario.motions is None:
        return None
    if est.multiple_model:
        return scenario.motions
    if est.mode is None:
        return None

    # (est.mode was checked against the scenario's modes when the estimator was built: estimators.kalman)
    return [None if m is None else mode_model(m, est.mode) for m in scenario.motions]


def unit(ctx: StudyContext, *, name: str, start: int, stop: int) -> dict:
    """Per-run values of estimator ``name`` (and its smoothed trajectory) on runs ``start..stop-1``.

    Padding (the steps after a recorded series' end, ``present`` False) is invisible: the smoother
    ends each run at its own last step (``smooth(..., present=)``), and no padded step is scored
    (RMSE, NEES) or shown (the run-0 examples are NaN there); the filter's own numbers at padded
    steps are those of missing data (log-likelihood 0, no innovation). A series' rows after its last
    measurement are its steps (``present``: scored against their truth, counted in its length), but
    ``smooth`` ends the run at its last measurement too: the smoothed beliefs there are the filtered
    predictions, and the earlier steps' are those of the series without the empty rows."""
    scenario = _scenario_of(ctx, name)
    truth, modes, z, present = _data(ctx, start, stop)
    fitted = _learned(ctx, name)[2] if name in learning.learners(ctx.cfg) else None
    est = fitted if fitted is not None else _estimator(ctx, scenario, name)
    runs = z.shape[1]
    # a filter that draws: each block of runs alone on its own stream (its draws do not depend on unit_runs)
    blocks = (random_blocks(runs, start, ctx.block_runs) if est.filter.uses_generator
              else [(slice(0, runs), None)])
    controls, motions = _controls(ctx, start, stop), _motions(est, scenario)
    parts, smoothed_parts, seconds, smoothing = [], [], 0.0, 0.0
    for sl, block in blocks:
        generator = None if block is None else ctx.block_generators("filter", scenario.name, name)(block)
        tic = time.perf_counter()
        start_belief = est.init(scenario.initial.expand(sl.stop - sl.start), generator)
        part = run_filter(est.filter, start_belief, z[:, sl],
                          controls=None if controls is None else controls[:, sl], motions=motions,
                          generator=generator, update_first=bool(ctx.cfg.get("update_first")))
        seconds += time.perf_counter() - tic
        parts.append(part)
        if est.smooth:  # (each part with its own record of the run)
            tic = time.perf_counter()
            smoothed_parts.append(smooth(part, present=present[:, sl],
                                         **({"method": est.smooth} if isinstance(est.smooth, str) else {})))
            smoothing += time.perf_counter() - tic
    traj = join_trajectories(parts)
    out = {}
    trajectories = {name: (traj, traj.estimate(), seconds)}
    if est.smooth:
        smoothed = join_trajectories(smoothed_parts)
        trajectories[f"{name} smoothed"] = (smoothed, smoothed.estimate(), seconds + smoothing)
    known = truth_components(scenario)
    for label, (tr, estimate, secs) in trajectories.items():
        v: dict[str, Any] = {"runs": runs, "steps": z.shape[0], "seconds": secs, "multiple_model": est.multiple_model,
                             "state_dim": len(known) if known else 0}
        if label == name:  # (a smoother does not change the data's likelihood); the first `burn` terms left out
            burn = int(ctx.cfg.get("burn") or 0)
            scored = torch.isfinite(z[burn:]).any(-1).any(0)  # a run without any datum after burn: no likelihood
            v["loglik"] = per_run(torch.where(scored, traj.log_likelihood[burn:], torch.nan).detach())
            v["measured"] = per_run(torch.isfinite(z).any(-1).sum(0))  # each run's steps with a datum
        if truth is not None and known:
            scored = present.unsqueeze(-1) & torch.isfinite(truth)
            for group, idx in scenario.groups.items():
                err = (estimate.mean[..., idx] - truth[..., idx]).square()
                ok = scored[..., idx].all(-1)
                v[f"sq_{group}"] = per_run(torch.where(ok, err.sum(-1), torch.nan).detach())
            pooled = marginal_nees(estimate, truth, present, known)  # over the file's components with truth
            v["nees"] = per_run(pooled.detach())
            if scenario.data is not None:  # each series' own, over its components (the table `series`)
                v["series_nees"] = per_run(series_nees(estimate, truth, present, known, pooled).detach())
            if est.multiple_model and modes is not None:
                v["hits"] = per_run(mode_hits(tr.belief.mode_log_probs, modes).to(ctx.dtype).detach())
        if label == name:
            stats = _innovation_stats(traj, z, est.multiple_model)
            if stats is not None:
                nis, dof, white = stats
                burn = int(ctx.cfg.get("burn") or 0)  # the burn-in's innovations (a diffuse start's) left out
                if burn:
                    nis, dof, white = nis[burn:], dof[burn:], white[burn:]
                v["nis"], v["dof"] = per_run(torch.where(dof > 0, nis, torch.nan).detach()), per_run(dof.to(ctx.dtype))
                v["white"] = per_run(white.detach())
        shown = present[:, 0]  # run 0's curves end at its own last step
        if est.multiple_model and start == 0:
            probs = tr.belief.mode_probs[:, 0]
            v["example_probs"] = per_run(torch.where(shown.unsqueeze(-1), probs, torch.nan).detach())
        if start == 0:
            v["example_mean"] = per_run(torch.where(shown.unsqueeze(-1), estimate.mean[:, 0], torch.nan).detach())
            v["example_cov"] = per_run(torch.where(shown[:, None, None], estimate.cov[:, 0], torch.nan).detach())
        out[label] = v
    return out


def run(ctx: StudyContext) -> None:
    cfg = ctx.cfg
    scenario = _built(ctx)
    runs = runs_of(ctx)
    names = list(cfg.estimators)
    if not names:
        raise ValueError("estimators: the study needs at least one estimator")
    for name in names:  # a bad estimator config: an error before any unit runs
        _estimator(ctx, scenario, name)
    known = truth_components(scenario)
    wanted = list(cfg.get("metrics") or ALL_METRICS)
    metrics = [m for m in wanted if known or m not in TRUTH_METRICS]
    dropped = {m: "no truth in the data" for m in wanted if m not in metrics}
    if "mode_accuracy" in metrics and scenario.data is not None:  # recorded data carry no true modes
        metrics.remove("mode_accuracy")
        dropped["mode_accuracy"] = "recorded data carry no true modes"
    groups = list(scenario.groups)
    if known and "rmse" in metrics:
        for g, idx in scenario.groups.items():
            missing = [i for i in idx if i not in known]
            if missing:
                dropped[f"rmse_{g}"] = f"no truth for state component(s) {missing}"
        groups = [g for g in groups if f"rmse_{g}" not in dropped]
        if not groups:
            metrics.remove("rmse")
    partial = known is not None and len(known) < scenario.initial.state_dim
    source = (f"recorded data `{cfg.scenario.data.path}` ({runs} series of up to {scenario.steps} steps)"
              if scenario.data is not None else f"{runs} simulated Monte Carlo runs of {scenario.steps} steps")
    ctx.results.description = (
        f"Scenario `{scenario.name}`: {scenario.num_modes} mode(s) ({', '.join(scenario.mode_labels)}), "
        f"{len(scenario.sensor_dims)} sensor(s); {source} (seed {cfg.seed}, {cfg.dtype}). RMSE is per step over "
        "runs, then averaged over time; every +- is a standard error over the runs."
        + (f" Truth for state component(s) {known} only: NEES is over those ({len(known)} degrees of freedom)."
           if partial and "nees" in metrics else ""))
    learners = learning.learners(cfg)
    if learners:
        learned_tables(ctx, learners, names, {name: _learned(ctx, name)[1] for name in learners})
    if scenario.motions is not None:
        own = [n for n in names if str(cfg.estimators[n].get("_target_", "")).endswith(".custom")]
        if own:
            ctx.results.notes.append(f"Irregular time stamps: {', '.join(own)} (custom filters) keep their own dt; "
                                     "the scenario's estimators predict over each step's length.")
    ranges = [(0, runs)] if scenario.data is not None else ctx.run_ranges(runs)
    units = [Unit(f"{name}/runs{a}-{b}", UNIT, {"name": name, "start": a, "stop": b})
             for name in names for a, b in ranges]
    parts = ctx.map_units(units, desc="estimators")
    results: dict[str, dict] = {}
    examples = {}
    for i, name in enumerate(names):
        mine = parts[i * len(ranges):(i + 1) * len(ranges)]
        for label in mine[0]:
            pieces = [p[label] for p in mine]
            summary, extra = reduce(pieces, groups, metrics)
            results[label] = {"summary": summary, **extra}
            if "example_mean" in pieces[0]:
                examples[label] = pieces[0]
    partial = partial_series(scenario, known) if "nees" in metrics else {}  # not pooled in the summary's NEES
    if partial:
        own = "; ".join(f"{s}: {c}" for s, c in partial.items())
        ctx.results.notes.append(
            f"nees: series {', '.join(partial)} left out of the summary's NEES (over component(s) {known}): "
            f"the truth of those series covers fewer components ({own}), and a NEES over fewer components is "
            "another figure (chi-square with fewer degrees of freedom). Each series' own NEES, over its "
            "components as in a file holding it alone, is in the table series.")
    for label, r in results.items():  # a value the data cannot give is named, never reported
        for key in [k for k in r["summary"] if k in _MAIN or k.startswith("rmse_") and not k.endswith("_se")]:
            value = r["summary"][key]
            if value is None or not math.isfinite(value):
                dropped[f"{key} ({label})"] = (
                    "no two consecutive innovations to compute it from (after the burn-in)" if key == "whiteness_lag1"
                    else f"no series has truth for every one of the components {known} (each series' own "
                    "NEES is in the table series)" if key == "nees" and partial
                    else "no step of any run to compute it from (no measurement or no truth where the estimate exists)")
                for k in [k for k in r["summary"] if k == key or k.startswith(f"{key}_")]:
                    del r["summary"][k]
                r["influence"].pop(key, None)
    for label, r in results.items():
        ctx.results.notes.extend(f"{label}: {note}" for note in r.get("notes", ()))
    ctx.results.dropped.update(dropped)
    what = "series" if scenario.data is not None else "runs"
    for label, r in results.items():  # a per-run value that cannot be computed is left out of the mean, and said
        for key, values in r["influence"].items():
            bad = int((~torch.isfinite(values)).sum()) - (len(partial) if key == "nees" else 0)  # (noted)
            if 0 < bad < values.numel() and key in r["summary"]:
                ctx.results.notes.append(f"{key} ({label}): {bad} of {values.numel()} {what} left out of the mean "
                                         "(nothing to compute it from: no measurement, or no truth where scored).")
    columns = ["estimator"]
    for key in [k for s in results.values() for k in s["summary"] if k != "seconds_per_step"]:
        if key not in columns:
            columns.append(key)
    table = ctx.results.table(
        "summary", columns,
        note="rmse_<group>: average RMSE of the group's components; _se: standard errors over the runs (delta "
             "method for RMSEs; 95 %: +- 1.96 se). nees/nis_low/high: the 95 % chi-square interval of a step's "
             "run-averaged NEES/NIS; nees_steps_inside: the fraction of steps inside it. loglik: each run's "
             "log-likelihood, averaged over runs. whiteness_lag1: lag-1 autocorrelation of the normalised "
             "innovations (0 for a consistent filter; +- whiteness_bound is its 95 % range).")
    for label, r in results.items():
        s = r["summary"]
        if all(s.get(c) is None for c in columns[1:]):
            continue  # e.g. a smoother without truth: its mode probabilities are in the curves
        table.rows.append([label, *[s.get(c) for c in columns[1:]]])
        for key, value in s.items():
            if key != "seconds_per_step":
                ctx.results.metric(label, key, value)
        if "time" in metrics:
            ctx.results.timing[label] = s["seconds_per_step"]
    reference = str((cfg.get("paired") or {}).get("reference") or names[0])
    if reference not in results:
        raise ValueError(f"paired.reference: {reference!r} is not an estimator ({', '.join(results)})")
    rows = paired(reference, results, metrics)
    ctx.results.dropped.update(not_computed(results, metrics, groups, reference, rows, what, ctx.results.dropped))
    ctx.results.table(
        "paired", ["metric", "estimator", "reference", "difference", "se", "ci_low", "ci_high", "separate_half_width"],
        note=f"Each estimator minus `{reference}` on the same runs (common random numbers): the difference, its "
             "standard error and 95 % Student-t interval; separate_half_width is the half-width two independent "
             "intervals would give (the pairing's gain).").rows.extend(rows)
    if scenario.data is not None:
        series_table(ctx, scenario, results)
    curves_and_figures(ctx, scenario, results, examples, groups, _data(ctx, *ranges[0]))  # (run 0: memoised)
    ctx.results.save()
