"""The generic study's results (``experiment=compare``, :mod:`experiments.studies.compare`): the reductions
over runs (:func:`reduce`, the paired differences :func:`paired`) and the tables, curves and figures written
from them (:func:`learned_tables`, :func:`series_table`, :func:`curves_and_figures`); split from the study's
module by concern (issue 47)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from experiments import learning
from experiments.harness import join_runs
from experiments.uncertainty import Z95, armse_influence, chi2_interval, rmse_se_per_step


# -- reductions ---------------------------------------------------------------------------------------------
def _t(x) -> Tensor:
    return torch.as_tensor(x, dtype=torch.float64)


def _per_run_mean(x: Tensor) -> Tensor:
    """Each run's time average of ``x (T, N)`` over its finite entries: ``(N,)``; NaN for a run with
    none (a value that cannot be computed is never 0)."""
    ok = torch.isfinite(x)
    count = ok.sum(0)
    return torch.where(count > 0, torch.where(ok, x, 0.0).sum(0) / count.clamp_min(1), torch.nan)


def _mean_se(values: Tensor) -> tuple[float, float]:
    values = values[torch.isfinite(values)]
    n = values.numel()
    if n == 0:
        return math.nan, math.nan
    return float(values.mean()), float(values.std() / math.sqrt(n)) if n > 1 else math.nan


def _t_quantile(dof: int) -> float:
    from scipy.stats import t

    return float(t.ppf(0.975, dof)) if dof > 0 else math.nan


def reduce(parts: list[dict], groups: list[str], metrics: list[str]) -> tuple[dict, dict]:
    """One estimator's per-run values joined over its units -> ``(summary, per_run_influence)``."""
    runs = sum(int(p["runs"]) for p in parts)
    summary: dict[str, Any] = {}
    influence: dict[str, Tensor] = {}
    curves: dict[str, Tensor] = {}
    runs_rmse: dict[str, Tensor] = {}  # each run's own average RMSE (the per-series table)
    notes: list[str] = []  # said in the results' notes
    steps = None
    if "rmse" in metrics and f"sq_{groups[0]}" in parts[0]:
        for g in groups:
            sq = _t(join_runs([p[f"sq_{g}"] for p in parts]))
            steps = sq.shape[0]
            value, h, per_step = armse_influence(sq)
            summary[f"rmse_{g}"], summary[f"rmse_{g}_se"] = value, _mean_se(h)[1]  # (over the runs scored)
            influence[f"rmse_{g}"] = h
            runs_rmse[f"rmse_{g}"] = _per_run_mean(sq.sqrt())  # the study's ARMSE of that run alone
            curves[f"rmse_{g}"] = per_step
            curves[f"rmse_{g}_se"] = rmse_se_per_step(sq)  # over each step's runs scored (NaN for one)
    if "nees" in metrics and "nees" in parts[0]:
        x = _t(join_runs([p["nees"] for p in parts]))
        per = _per_run_mean(x)
        summary["nees"], summary["nees_se"] = _mean_se(per)
        influence["nees"] = per
        n = int(parts[0]["state_dim"])  # the components with truth
        curve = torch.nanmean(x, 1)
        curves["nees"] = curve
        if n and math.isfinite(summary["nees"]):  # over the runs with a NEES (not those without truth)
            lo, hi = chi2_interval(int(torch.isfinite(per).sum()) * n)
            summary["nees_low"], summary["nees_high"] = lo * n, hi * n
            # each step's interval for the runs scored there (padding and missing truth: fewer)
            count = torch.isfinite(x).sum(1)
            bounds = {c: chi2_interval(c * n) for c in set(count.tolist()) if c > 0}
            low = torch.tensor([bounds[c][0] * n if c else math.nan for c in count.tolist()], dtype=torch.float64)
            high = torch.tensor([bounds[c][1] * n if c else math.nan for c in count.tolist()], dtype=torch.float64)
            scored = count > 0
            curves["nees_low"], curves["nees_high"] = low, high  # each step's band (drawn, and in curves.npz)
            summary["nees_steps_inside"] = float(((curve >= low) & (curve <= high))[scored].double().mean())
    if "nis" in metrics and "nis" in parts[0]:
        x = _t(join_runs([p["nis"] for p in parts]))
        dof = _t(join_runs([p["dof"] for p in parts]))
        x = torch.where(dof > 0, x, torch.nan)
        per = _per_run_mean(x)
        summary["nis"], summary["nis_se"] = _mean_se(per)
        influence["nis"] = per
        curves["nis"] = torch.nanmean(x, 1)
        # each step's band: the run-averaged NIS of step t is chi2(D_t) / N_t for a consistent filter, D_t the
        # sum of its N_t runs' degrees of freedom (multi-rate sensors, missing components: they differ by step)
        n_t, d_t = (dof > 0).sum(1), torch.where(dof > 0, dof, 0.0).sum(1)
        bands = {(d, n): chi2_interval(int(d)) for d, n in set(zip(d_t.tolist(), n_t.tolist())) if n > 0}
        curves["nis_low"], curves["nis_high"] = (
            torch.tensor([bands[(d, n)][j] * d / n if n > 0 else math.nan for d, n in zip(d_t.tolist(), n_t.tolist())],
                         dtype=torch.float64) for j in (0, 1))
        dofs = sorted({int(v) for v in dof[dof > 0].tolist()})
        if len(dofs) == 1:  # the summary's band: a step's run-averaged NIS over the N runs with a NIS, chi2(N m) / N
            m = dofs[0]
            lo, hi = chi2_interval(int(torch.isfinite(per).sum()) * m)
            summary["nis_dof"], summary["nis_low"], summary["nis_high"] = m, lo * m, hi * m
        elif dofs:  # no one band: no step of m degrees of freedom for a mean m (before: chi2 of the rounded mean)
            notes.append(f"nis: the steps' degrees of freedom differ ({', '.join(map(str, dofs))}: multi-rate sensors "
                         "or missing components), so the summary has no one chi-square band (nis_dof, nis_low, "
                         "nis_high); each step's band, for its own degrees of freedom, is in the curves "
                         "nis_low/nis_high.")
        white = _t(join_runs([p["white"] for p in parts]))  # (T, N, m)
        if "whiteness" in metrics:
            # each run's and component's sample lag-1 autocorrelation of its normalised innovations (zero-mean
            # under a consistent filter): sum_t x_t x_{t+1} over the pairs of consecutive ones present, over
            # sum_t x_t^2 over all present, so that it lies in [-1, 1] (the pairs' sum is at most the squares')
            a, b = white[:-1], white[1:]
            ok = torch.isfinite(a) & torch.isfinite(b)
            num = torch.where(ok, a * b, 0.0).sum(0)
            den = torch.where(torch.isfinite(white), white * white, 0.0).sum(0)
            r = torch.where(ok.any(0) & (den > 0), num / den.clamp_min(1e-300), torch.nan)  # (N, m)
            pairs = int(ok.sum())
            # no pair of consecutive innovations: NaN, named as dropped by the study
            summary["whiteness_lag1"] = float(r[torch.isfinite(r)].mean()) if pairs else math.nan
            if pairs:
                summary["whiteness_bound"] = Z95 / math.sqrt(pairs)
    if "loglik" in metrics and "loglik" in parts[0]:
        ll = _t(join_runs([p["loglik"] for p in parts]))
        per = ll.sum(0)
        summary["loglik"], summary["loglik_se"] = _mean_se(per)
        influence["loglik"] = per
    if "mode_accuracy" in metrics and parts[0].get("hits") is not None:
        hits = _t(join_runs([p["hits"] for p in parts]))
        per = hits.mean(0)
        summary["mode_accuracy"], summary["mode_accuracy_se"] = _mean_se(per)
        influence["mode_accuracy"] = per
        curves["mode_accuracy"] = hits.mean(1)
        # each step's standard error over the runs: sd / sqrt(N) (NaN for one run)
        curves["mode_accuracy_se"] = (hits.double().std(1) / math.sqrt(runs) if runs > 1
                                      else torch.full((hits.shape[0],), math.nan, dtype=torch.float64))
    steps = steps or int(parts[0]["steps"])
    summary["seconds_per_step"] = sum(float(p["seconds"]) for p in parts) / steps
    per_run_values = {**{k: v for k, v in influence.items() if not k.startswith("rmse_")}, **runs_rmse}
    if "nees" in per_run_values and "series_nees" in parts[0]:  # each series' NEES over its own components
        per_run_values["nees"] = _per_run_mean(_t(join_runs([p["series_nees"] for p in parts])))
    if "measured" in parts[0]:
        per_run_values["measured"] = _t(join_runs([p["measured"] for p in parts], dim=0))
    return summary, {"influence": influence, "curves": curves, "per_run": per_run_values, "notes": notes}


def paired(reference: str, estimators: dict[str, dict], metrics: list[str]) -> list[list]:
    """Rows ``[metric, estimator, reference, difference, se, low, high, separate_half_width]``: each
    estimator minus ``reference`` on the same runs. RMSEs by the delta method on the per-run influence
    values of both (ARMSE_A - ARMSE_B ~ mean_r (h_A - h_B)); per-run means (NEES, NIS, log-likelihood,
    mode accuracy) by their per-run differences. 95 % Student-t intervals over the ``n`` runs that have a
    value of the metric for both (a series without truth or without measurements is no run of it):
    ``n - 1`` degrees of freedom."""
    rows = []
    ref = estimators[reference]
    for name, est in estimators.items():
        if name == reference:
            continue
        for key, h in est["influence"].items():
            if key not in ref["influence"]:
                continue
            h_ref = ref["influence"][key]
            d = h - h_ref
            ok = torch.isfinite(d)
            n = int(ok.sum())
            if n < 2:
                continue
            if key.startswith("rmse_"):
                diff = est["summary"][key] - ref["summary"][key]
            else:
                diff = float(d[ok].mean())
            se = float(d[ok].std() / math.sqrt(n))
            q = _t_quantile(n - 1)
            separate = q * math.hypot(float(h[torch.isfinite(h)].std()), float(h_ref[torch.isfinite(h_ref)].std())) \
                / math.sqrt(n)
            rows.append([key, name, reference, diff, se, diff - q * se, diff + q * se, separate])
    return rows


def not_computed(results: dict, metrics: list[str], groups: list[str], reference: str, rows: list[list],
                 what: str, already: dict) -> dict[str, str]:
    """The ``dropped`` entries of what was asked for and not computed though the data have it: a filter's
    innovation metrics it records none for (GPB2: per mode pair), a standard error or paired difference
    without two runs (``what``: "runs" or "series") with a value. A smoother has no innovations of its own
    (its filter's row has them): not named; nor what ``already`` (the dropped entries so far) names."""
    out: dict[str, str] = {}
    keys = {"nis": ["nis"], "whiteness": ["whiteness_lag1"], "loglik": ["loglik"], "nees": ["nees"],
            "rmse": [f"rmse_{g}" for g in groups]}
    for label, r in results.items():
        smoothed = label.endswith(" smoothed")
        for metric in metrics:
            if smoothed and metric in ("nis", "whiteness", "loglik"):
                continue
            for key in keys.get(metric, []):
                if key not in r["summary"] and f"{key} ({label})" not in already:
                    out[f"{key} ({label})"] = ("its filter records no innovation of the mixture (per mode pair)"
                                               if metric in ("nis", "whiteness") else "not computed by this filter")
    single = all(int(torch.isfinite(v).sum()) < 2 for r in results.values() for v in r["influence"].values())
    if single and any(r["influence"] for r in results.values()):
        out["standard errors (_se) and paired"] = f"at most one of the {what} has a value: they need two"
        return out
    for label, r in results.items():
        for key, value in r["summary"].items():
            if key.endswith("_se") and key[:-3] in r["summary"] and not (value is not None and math.isfinite(value)):
                out[f"{key} ({label})"] = f"fewer than two {what} with a value"
    done = {(row[0], row[1]) for row in rows}
    ref = results[reference]["influence"]
    for label, r in results.items():
        if label != reference:
            for key in r["influence"]:
                if key in ref and (key, label) not in done:
                    out[f"paired {key} ({label})"] = f"fewer than two {what} with a value for both"
    return out


def learned_tables(ctx, learners: list[str], names: list[str], records: dict) -> None:
    """The tables ``learned`` (each estimate with its standard error and z, and the expected durations)
    and ``fit`` (each learning estimator's log-likelihood, k, nobs, AIC, BIC and optimiser), the metrics
    and notes of the learning estimators."""
    block = learning.spec(ctx.cfg)
    method = str(block.method)
    mle = method in ("mle", "em", "em_then_mle")
    how = {"mle": "Maximum likelihood (torchmm.learn.estimate)",
           "em": "EM (torchmm.learn.em, em_switching for a switching model)",
           "em_then_mle": "EM, then maximum likelihood from EM's estimates (torchmm.learn.estimate),"
           }.get(method)
    errors = ("no standard errors (EM gives none: method em_then_mle adds them)" if method == "em" else
              "se: from the observed information (delta method through the parametrisation); "
              "z = estimate / se")
    table = ctx.results.table(
        "learned", ["estimator", "parameter", "estimate", "se", "z"],
        note=(f"{how} of each learning estimator's own parameters: it runs with its estimates, the other "
              f"estimators with the configured values. {errors[0].upper() + errors[1:]}. A duration is "
              "1 / (1 - p_ii), the expected time in regime i." if mle else
              f"Each learning estimator's own covariances fitted with {block.optimizer} (method gradient: no "
              "standard errors); it runs with its fit, the other estimators with the configured values."))
    fits = ctx.results.table("fit", ["estimator", "loglik", "k", "nobs", "aic", "bic", "iterations", "converged",
                                     "seconds"],
                             note="The maximised log-likelihood (the sum over the runs or series), the free "
                                  "parameters k, the measured steps nobs, AIC = -2 loglik + 2 k, BIC = -2 loglik + "
                                  "k log(nobs).") if mle else None
    for name in learners:
        record = records[name]
        table.rows.extend(record["rows"])
        if mle:
            fits.rows.append([name, record["loglik"], record["k"], record["nobs"], record["aic"], record["bic"],
                              record["iterations"], record["converged"], record["seconds"]])
            for key in ("loglik", "aic", "bic"):
                ctx.results.metric(name, f"learn_{key}", record[key])
            how = {"mle": "L-BFGS-B iterations", "em": "EM iterations",
                   "em_then_mle": "L-BFGS-B iterations after EM"}[record["method"]]
            ctx.results.notes.append(
                f"Learned by {name}: {len(record['rows'])} estimates in {record['iterations']} {how} "
                f"({record['seconds']:.2f} s): log-likelihood {record['loglik']:.6f}"
                + ("" if record["converged"] else f" (not converged{': ' + record['message'] if record['message'] else ''})")
                + (f"; {record['note']}" if record["note"] else "") + ".")
            if "em" in record:
                ctx.logger.sweep(f"learn/em_loglik/{name}", list(range(len(record["em"]))), record["em"], "iteration")
        else:
            ctx.results.notes.append(
                f"Learned by {name}: {len(record['rows'])} entries in {record['iterations']} {record['optimizer']} "
                f"iterations ({record['seconds']:.2f} s); final negative log-likelihood {record['nll'][-1]:.6f} "
                "(per run).")
            ctx.logger.sweep(f"learn/nll/{name}", list(range(1, len(record["nll"]) + 1)), record["nll"], "iteration")
            ctx.results.metric(name, "learn_nll", record["nll"][-1])
    for name in learners:  # (torchmm.learn.estimate: NaN errors at a point that is not a maximum, said here)
        if mle and method != "em" and not records[name]["converged"]:
            table.note += f" {name}'s fit did not converge: {records[name]['note'] or 'see the notes'}."
    others = [n for n in names if n not in learners]
    if others:
        ctx.results.notes.append(f"Not learning (configured values): {', '.join(others)}.")


def series_table(ctx, scenario, results: dict) -> None:
    """Recorded data: each series' own numbers (its steps, the steps with a measurement, and each
    estimator's log-likelihood, RMSEs, NEES and NIS over that series alone)."""
    keys = []
    for r in results.values():
        keys += [k for k in r["per_run"] if k != "measured" and k not in keys
                 and (k in r["summary"] or bool(torch.isfinite(r["per_run"][k]).any()))]  # (a series' NEES)
    order = ["loglik", *sorted(k for k in keys if k.startswith("rmse_")), "nees", "nis", "mode_accuracy"]
    keys = [k for k in order if k in keys]
    table = ctx.results.table(
        "series", ["estimator", "series", "steps", "measured", *keys],
        note="Each series alone, as the summary of a file holding only it: steps (its length; shorter series are "
             "padded, and padding changes none of its numbers), measured (steps with a datum), its log-likelihood, "
             "average RMSE over its steps, mean NEES and NIS.")
    steps = scenario.data.present.sum(0)
    for label, r in results.items():
        per = r["per_run"]
        if not any(k in per for k in keys):
            continue
        for j, series in enumerate(scenario.data.series):
            measured = per.get("measured")
            table.rows.append([label, series, int(steps[j]), None if measured is None else int(measured[j]),
                               *[float(per[k][j]) if k in per else None for k in keys]])


def curves_and_figures(ctx, scenario, results, examples, groups, first: tuple) -> None:
    from experiments.studies import plots  # (matplotlib: not at import, so that the config's precheck is light)

    curves = {f"RMSE {g}": {} for g in groups}
    bands = {f"RMSE {g}": {} for g in groups}
    for label, r in results.items():
        c = r["curves"]
        for g in groups:
            if f"rmse_{g}" in c:
                ctx.logger.series(f"rmse_{g}/{label}", c[f"rmse_{g}"])
                ctx.logger.series(f"rmse_{g}_se/{label}", c[f"rmse_{g}_se"])
                curves[f"RMSE {g}"][label], bands[f"RMSE {g}"][label] = c[f"rmse_{g}"], c[f"rmse_{g}_se"]
        for key in ("nees", "nis", "mode_accuracy", "mode_accuracy_se"):
            if key in c:
                ctx.logger.series(f"{key}/{label}", c[key])
        s = r["summary"]
        if "nees_low" in c:  # each step's band for the runs scored there
            ctx.logger.series(f"nees_low/{label}", c["nees_low"])
            ctx.logger.series(f"nees_high/{label}", c["nees_high"])
        if "nis_low" in c:  # each step's band for its runs' degrees of freedom
            ctx.logger.series(f"nis_low/{label}", c["nis_low"])
            ctx.logger.series(f"nis_high/{label}", c["nis_high"])
        ex = examples.get(label)
        if ex is not None and ex.get("example_probs") is not None:
            probs = _t(ex["example_probs"])
            for j, mode in enumerate(scenario.mode_labels):
                ctx.logger.series(f"mode_probability/{label}/{mode}", probs[:, j])
    if any(curves[k] for k in curves):
        ctx.save_figure("rmse_over_time", plots.rmse_over_time({k: v for k, v in curves.items() if v},
                                                                      f"{scenario.name}", bands=bands))
    nees = {label: r["curves"]["nees"] for label, r in results.items() if "nees" in r["curves"]}
    if nees:
        ctx.save_figure("nees", plots.nees_over_time(nees, {label: (results[label]["curves"]["nees_low"],
                                                                      results[label]["curves"]["nees_high"])
                                                             for label in nees if "nees_low" in results[label]["curves"]},
                                                     f"{scenario.name}, NEES"))
    truth, modes, z, _ = first  # the first unit's data: run 0
    probs = {label: _t(ex["example_probs"]) for label, ex in examples.items() if ex.get("example_probs") is not None}
    if probs:
        ctx.save_figure("mode_probabilities", plots.mode_probabilities(
            probs, None if modes is None else modes[:, 0], scenario.mode_labels, f"{scenario.name}, run 0"))
    estimates = {label: (_t(ex["example_mean"]), _t(ex["example_cov"])) for label, ex in examples.items()}
    comps = next(iter(scenario.groups.values()))
    if truth is not None and len(comps) <= 2:
        ctx.save_figure("trajectory", plots.trajectory(truth[:, 0], None, estimates, components=comps, run=None,
                                                       title=f"{scenario.name}, run 0"))
    elif truth is None:
        ctx.save_figure("estimates", _estimates_figure(z[:, 0], estimates, scenario.name))


def _estimates_figure(z: Tensor, estimates: dict, title: str):
    """Recorded data without truth: the first series' measurements and each estimator's first state
    component with its +- 2 sigma band."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.8))
    steps = np.arange(1, z.shape[0] + 1)
    for j in range(z.shape[-1]):
        ax.plot(steps, z[:, j].cpu().numpy(), ".", color="k", ms=3, label="measurements" if j == 0 else None)
    for label, (mean, cov) in estimates.items():
        m, sd = mean[:, 0].numpy(), cov[:, 0, 0].clamp_min(0).sqrt().numpy()
        (line,) = ax.plot(steps, m, lw=1.3, label=f"{label} (+- 2 sd)")
        ax.fill_between(steps, m - 2 * sd, m + 2 * sd, color=line.get_color(), alpha=0.2, lw=0)
    ax.set_xlabel("time step k")
    ax.set_ylabel("state component 0")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8, frameon=False, borderaxespad=0)
    ax.set_title(title)
    fig.tight_layout()
    return fig
