"""One long series, one thread: torchmm against statsmodels on the shipped real data (issue 31's workload).

    python benchmarks/single_series.py [--repeats 20] [--imm-steps 2000]

Side by side in one process, the same data and parameters, results checked equal:

* **Nile, local level** (``UnobservedComponents(y, "llevel", use_exact_diffuse=True)``): one
  log-likelihood evaluation at the MLE (statsmodels' ``loglike`` of the model built once; torchmm's
  :class:`~torchmm.learn.Objective` built once, from the exact diffuse start, experiments/realdata.py;
  and the per-call ``negative_log_likelihood``, which checks its arguments every call), the same with
  its gradient (torchmm: backward through ``log_diagonal`` parametrised Q and R; its cost is given
  against the same learnable objective's value without gradient), and the whole MLE fit
  (statsmodels' ``fit()``, L-BFGS with a numerical score; torchmm: building the ``Objective`` and
  ``Objective.minimize()``, scipy's L-BFGS-B with the autograd gradient) from the same start;
* **Fed funds, 2-regime Markov switching** (``MarkovRegression(..., switching_variance=True)``):
  filter + Kim smoother at the MLE (``smooth(params)``; torchmm: the IMM over a constant state,
  ``run_filter`` + ``smooth(method="kim")``);
* **a 3-mode IMM** (paper 000's modes, linear Kalman), one run of ``--imm-steps`` steps: microseconds
  per step, and its gradient's cost relative to the likelihood.

Prints best and median times and the ratios ``statsmodels time / torchmm time`` (above 1: torchmm is
faster); the last line is ``nile_ratio=... fedfunds_ratio=... imm_us_per_step=...``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np
import torch

torch.set_num_threads(1)


def _times(fn, repeats: int) -> tuple[float, float]:
    fn()  # warm-up (first-call costs are not what a fit pays per evaluation)
    out = []
    for _ in range(repeats):
        tic = time.perf_counter()
        fn()
        out.append(time.perf_counter() - tic)
    return min(out), statistics.median(out)


def _show(name: str, best: float, median: float) -> None:
    print(f"  {name:<44} best {best * 1e3:9.3f} ms   median {median * 1e3:9.3f} ms")


def nile(repeats: int) -> float:
    import statsmodels.api as sm

    from experiments.realdata import load_nile, local_level, local_level_start
    from torchmm import run_filter
    from torchmm.learn import Objective, negative_log_likelihood

    y = load_nile()
    model = sm.tsa.UnobservedComponents(y[:, 0].numpy(), "llevel", use_exact_diffuse=True)
    params = model.fit(method="bfgs", gtol=1e-8, maxiter=1000, disp=False).params  # (r, q)
    r, q = (float(v) for v in params)
    kf, belief0 = local_level(q, r, first=y[0])
    objective = Objective(kf, belief0, y[1:])  # checked once; every call reads the parameters and runs

    def torch_ll():
        with torch.no_grad():
            return -objective()

    constant = -0.5 * math.log(2 * math.pi)  # statsmodels keeps the diffuse observation's constant
    diff = abs(float(torch_ll()) + constant - model.loglike(params))
    print(f"Nile (T = {len(y)}): |torchmm - statsmodels| log-likelihood at the MLE = {diff:.1e} "
          f"(torchmm's kernel: {objective.kernel})")
    sm_best, sm_med = _times(lambda: model.loglike(params), repeats)
    tm_best, tm_med = _times(torch_ll, repeats)
    call_best, call_med = _times(lambda: negative_log_likelihood(kf, belief0, y[1:], reduction="sum"), repeats)
    # the one-shot call (issue 47): a plain run_filter, every field of the trajectory kept, checks included
    one_best, one_med = _times(lambda: run_filter(kf, belief0, y[1:]), repeats)
    fixed_best, _ = _times(lambda: run_filter(kf, belief0, y[1:2]), repeats)
    # the same call on data and a start it has not seen (copies made beforehand): every value check and
    # fingerprint computed again (a repeated call on the same unchanged tensors keeps them: Unchanged)
    fresh = iter([(y[1:].clone(), belief0.map_tensors(lambda t, e: t.clone())) for _ in range(repeats + 1)])
    fresh_best, fresh_med = _times(lambda: run_filter(kf, *reversed(next(fresh))), repeats)
    _show("statsmodels loglike", sm_best, sm_med)
    _show("torchmm Objective() (no grad)", tm_best, tm_med)
    _show("torchmm negative_log_likelihood (checks every call)", call_best, call_med)
    _show("torchmm run_filter, one-shot (the whole trajectory)", one_best, one_med)
    _show("torchmm run_filter, one-shot on new data and start", fresh_best, fresh_med)
    print(f"  one-shot run_filter: {sm_best / one_best:.3f}x statsmodels' loglike ({sm_best / fresh_best:.3f}x on "
          f"new tensors); its fixed cost (T = 1) {fixed_best * 1e3:.3f} ms, "
          f"{(one_best - fixed_best) / (len(y) - 2) * 1e6:.2f} us a step")
    ratio = sm_best / tm_best

    kf_learn, _ = local_level(q, r, learnable=True)
    learn_objective = Objective(kf_learn, lambda f: local_level_start(f, y[0]), y[1:])

    def with_grad():
        loss = learn_objective()
        kf_learn.zero_grad()
        loss.backward()

    def learnable_ll():
        with torch.no_grad():
            return -learn_objective()

    lv_best, lv_med = _times(learnable_ll, repeats)
    g_best, g_med = _times(with_grad, repeats)
    _show("torchmm the same, learnable (log q, log r), no grad", lv_best, lv_med)
    _show("torchmm the same + gradient (log q, log r)", g_best, g_med)
    # the gradient's cost against the same function's value (the parametrisation and the start function
    # included in both); against the fixed-parameter model's value for comparison
    print(f"  ratio loglike (statsmodels / torchmm) = {ratio:.3f}; gradient / likelihood = {g_best / lv_best:.2f} "
          f"(against the fixed-parameter Objective: {g_best / tm_best:.2f})")

    # the whole fit from the same start (q, r) = (1000, 10000): statsmodels' fit() (L-BFGS, numerical
    # score) against building torchmm's Objective and Objective.minimize() (scipy's L-BFGS-B, autograd)
    from torch.nn.utils import parametrize

    sm_times, tm_times = [], []
    for _ in range(max(3, repeats // 4)):
        fresh = sm.tsa.UnobservedComponents(y[:, 0].numpy(), "llevel", use_exact_diffuse=True)
        tic = time.perf_counter()
        sm_fit = fresh.fit(start_params=[10000.0, 1000.0], disp=False)
        sm_times.append(time.perf_counter() - tic)
        kf2, _ = local_level(1000.0, 10000.0, learnable=True)
        tic = time.perf_counter()
        result = Objective(kf2, lambda f: local_level_start(f, y[0]), y[1:]).minimize()
        tm_times.append(time.perf_counter() - tic)
    with parametrize.cached():
        learned_q, learned_r = float(kf2.motion.Q.detach().reshape(())), float(kf2.measurement.R.detach().reshape(()))
    sm_fit_s, tm_fit_s = min(sm_times), min(tm_times)
    print(f"  MLE fit: statsmodels fit() {sm_fit_s * 1e3:.2f} ms -> r = {sm_fit.params[0]:.2f}, q = {sm_fit.params[1]:.3f};"
          f" torchmm Objective + minimize {tm_fit_s * 1e3:.2f} ms ({result.nfev} evaluations) -> r = {learned_r:.2f},"
          f" q = {learned_q:.3f} (ratio {sm_fit_s / tm_fit_s:.2f}; optimum r = {r:.2f}, q = {q:.3f})")
    return ratio


def fedfunds(repeats: int) -> float:
    import statsmodels.api as sm

    from experiments.realdata import fedfunds_imm, load_fedfunds
    from torchmm import run_filter, smooth
    from torchmm.learn import Objective

    y = load_fedfunds()
    model = sm.tsa.MarkovRegression(y[:, 0].numpy(), k_regimes=2, trend="c", switching_variance=True)
    params = model.fit().params
    transition = model.regime_transition_matrix(params)[:, :, 0].T
    imm, belief0 = fedfunds_imm(params[2:4], params[4:6], transition, mode_probs=model.initial_probabilities(params))

    def torch_smooth():
        with torch.no_grad():
            traj = run_filter(imm, belief0, y)
            return traj, smooth(traj, method="kim")

    traj, smoothed = torch_smooth()
    result = model.smooth(params)
    diff = max(abs(float(traj.log_likelihood.sum()) - result.llf),
               float(np.abs(smoothed.belief.mode_probs.numpy() - result.smoothed_marginal_probabilities).max()))
    print(f"Fed funds (T = {len(y)}): largest |torchmm - statsmodels| (llf, smoothed probabilities) = {diff:.1e}")
    sm_best, sm_med = _times(lambda: model.smooth(params), repeats)
    raw_best, raw_med = _times(lambda: model.smooth(params, return_raw=True), repeats)
    tm_best, tm_med = _times(torch_smooth, repeats)
    objective = Objective(imm, belief0, y)  # the prepared filter + Kim smoother (checked once)
    prepared = objective.smoothed()
    diff = float((prepared.mode_probs - smoothed.belief.mode_probs).abs().max())
    pr_best, pr_med = _times(objective.smoothed, repeats)
    _show("statsmodels MarkovRegression.smooth", sm_best, sm_med)
    _show("statsmodels smooth(return_raw=True) (its compute)", raw_best, raw_med)
    _show("torchmm run_filter + smooth(kim)", tm_best, tm_med)
    _show("torchmm Objective.smoothed() (prepared)", pr_best, pr_med)
    fixed_best, _ = _times(lambda: run_filter(imm, belief0, y[:1]), repeats)
    fresh = iter([(y[:1].clone(), belief0.map_tensors(lambda t, e: t.clone())) for _ in range(repeats + 1)])
    fresh_best, _ = _times(lambda: run_filter(imm, *reversed(next(fresh))), repeats)
    print(f"  the IMM's one-shot run_filter fixed cost (T = 1): {fixed_best * 1e3:.3f} ms repeated, "
          f"{fresh_best * 1e3:.3f} ms on new data and start")
    ratio = sm_best / tm_best
    print(f"  ratio (statsmodels / torchmm) = {ratio:.4f}; against return_raw {raw_best / tm_best:.4f}; the prepared "
          f"call against return_raw {raw_best / pr_best:.4f} (its smoothed probabilities within {diff:.1e})")
    return ratio


def imm(steps: int, repeats: int) -> float:
    from torchmm import IMM, ConstantVelocity, GaussianBelief, KalmanFilter, PositionMeasurement, run_filter
    from torchmm.learn import negative_log_likelihood
    from torchmm.models import learnable_noise

    motion = ConstantVelocity(1, q=1.0, acceleration=[[0.25], [0.0], [-0.25]], dtype=torch.float64)
    sensor = PositionMeasurement(2, [0], 100.0, dtype=torch.float64)
    transition = torch.tensor([[0.5, 0.25, 0.25], [0.25, 0.5, 0.25], [0.25, 0.25, 0.5]], dtype=torch.float64)
    filt = IMM(KalmanFilter(motion, sensor), transition)
    prior = filt.initial_belief(GaussianBelief.create([10.0, 10.0], [[100.0, 1.0], [1.0, 100.0]],
                                                      dtype=torch.float64).expand(1))
    z = torch.randn(steps, 1, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 10

    def run():
        with torch.no_grad():
            run_filter(filt, prior, z, record="estimate")

    best, med = _times(run, max(2, repeats // 5))
    us = best / steps * 1e6
    print(f"3-mode IMM, 1 run x {steps} steps: best {us:.1f} us a step (median {med / steps * 1e6:.1f})")
    learnable_noise(sensor, "R", "log_diagonal")

    def grad():
        loss = negative_log_likelihood(filt, prior, z, reduction="sum")
        filt.zero_grad()
        loss.backward()

    def like():
        with torch.no_grad():
            negative_log_likelihood(filt, prior, z, reduction="sum")

    l_best, _ = _times(like, max(2, repeats // 5))
    g_best, _ = _times(grad, max(2, repeats // 5))
    print(f"  likelihood {l_best / steps * 1e6:.1f} us a step; with its gradient {g_best / steps * 1e6:.1f} "
          f"(x{g_best / l_best:.2f})")
    return us


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--imm-steps", type=int, default=2000)
    args = parser.parse_args(argv)
    nile_ratio = nile(args.repeats)
    fed_ratio = fedfunds(args.repeats)
    us = imm(args.imm_steps, args.repeats)
    print(f"nile_ratio={nile_ratio:.4f} fedfunds_ratio={fed_ratio:.4f} imm_us_per_step={us:.1f}")


if __name__ == "__main__":
    main()
