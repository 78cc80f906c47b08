"""Estimation against its references, side by side in one run (issue 45): EM against pykalman, maximum
likelihood against statsmodels.

* ``em_robot``: one EM iteration of Q and R on pykalman's robot data (501 steps, 5 states, time-varying
  offsets), torchmm (:func:`torchmm.learn.em`) against pykalman's ``em``; their parameters compared.
* ``em_batch``: EM of every parameter of a 2-state model over ``--series`` simulated series of
  ``--steps`` steps, each series its own fit: one batched ``em(per_series=True)`` against a loop of
  pykalman fits (timed on ``--pykalman-series`` of them and scaled to all: the loop is linear in them);
  the first series' parameters compared.
* ``fedfunds``: statsmodels' ``MarkovRegression(k_regimes=2, trend="c", switching_variance=True).fit()`` on
  the Fed funds rate against :func:`torchmm.learn.estimate` of the same model from statsmodels' start
  values, standard errors included in both (``fit()`` then ``bse``); each one's log-likelihood printed
  (they reach different maxima: docs/studies.md).
* ``fedfunds_exog``: the same with regressors (statsmodels' ``TestFedFundsConstL1Exog``: the lag, the output
  gap and inflation, switching coefficients, one variance), the regressors the motion's controls.
* ``fedfunds_tvtp``: time-varying transition probabilities (``exog_tvtp``: a constant and the output gap,
  switching mean and variance), torchmm's ``LogisticTransition`` over the same columns.

The last line: ``em_robot_speedup=... em_batch_speedup=... fedfunds_speedup=... fedfunds_exog_speedup=...
fedfunds_tvtp_speedup=...`` (reference time / torchmm time; above 1 torchmm is faster).

    .venv/bin/python benchmarks/estimation.py
    .venv/bin/python benchmarks/estimation.py --series 1000 --steps 100 --pykalman-series 20
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (tests' statsmodels data reader)


def best(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        tic = time.perf_counter()
        fn()
        times.append(time.perf_counter() - tic)
    return min(times)


def em_robot(repeats: int) -> float:
    from pykalman import KalmanFilter as PyKalman
    from pykalman.datasets import load_robot

    from torchmm import GaussianBelief, KalmanFilter
    from torchmm.learn import em
    from torchmm.models import LinearMeasurement, LinearMotion

    d = load_robot()
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=float), dtype=torch.float64)  # noqa: E731
    y = t(np.ma.filled(d.observations.astype(float), np.nan) - d.observation_offset)
    u = torch.cat([torch.zeros(1, 5, dtype=torch.float64), t(d.transition_offsets)])

    its = 10  # an iteration's time: 10 iterations' / 10 (torchmm's em also evaluates the final likelihood)

    def ours():
        kf = KalmanFilter(LinearMotion(t(d.transition_matrix), t(d.initial_transition_covariance),
                                       input_matrix=torch.eye(5, dtype=torch.float64)),
                          LinearMeasurement(t(d.observation_matrix), t(d.initial_observation_covariance)))
        em(kf, GaussianBelief(t(d.initial_state_mean), t(d.initial_state_covariance)), y, ["Q", "R"], iterations=its,
           controls=u, progress=False)
        return kf

    def theirs():
        kf = PyKalman(d.transition_matrix, d.observation_matrix, d.initial_transition_covariance,
                      d.initial_observation_covariance, d.transition_offsets, d.observation_offset,
                      d.initial_state_mean, d.initial_state_covariance,
                      em_vars=["transition_covariance", "observation_covariance"])
        kf.em(d.observations, n_iter=its)
        return kf

    a, b = ours(), theirs()
    diff = max(float(np.abs(a.motion.Q.numpy() - b.transition_covariance).max()),
               float(np.abs(a.measurement.R.numpy() - b.observation_covariance).max()))
    mine, ref = best(ours, repeats) / its, best(theirs, repeats) / its
    print(f"em_robot: one iteration, torchmm {mine * 1e3:.1f} ms, pykalman {ref * 1e3:.1f} ms ({ref / mine:.1f}x); "
          f"largest parameter difference after {its} {diff:.1e}")
    return ref / mine


def em_batch(series: int, steps: int, sample: int, iterations: int, threads: int) -> float:
    from pykalman import KalmanFilter as PyKalman

    from torchmm import GaussianBelief, KalmanFilter
    from torchmm.learn import em
    from torchmm.models import LinearMeasurement, LinearMotion

    g = torch.Generator().manual_seed(0)
    F = torch.tensor([[0.9, 0.2], [-0.1, 0.8]], dtype=torch.float64)
    H = torch.tensor([[1.0, 0.5]], dtype=torch.float64)
    x = torch.zeros(series, 2, dtype=torch.float64)
    ys = []
    for _ in range(steps):
        x = x @ F.mT + 0.3 * torch.randn(series, 2, dtype=torch.float64, generator=g)
        ys.append(x @ H.mT + 0.5 * torch.randn(series, 1, dtype=torch.float64, generator=g))
    y = torch.stack(ys)
    names = ["transition_matrices", "transition_covariance", "observation_matrices", "observation_covariance",
             "initial_state_mean", "initial_state_covariance"]

    def ours():
        kf = KalmanFilter(LinearMotion(torch.eye(2, dtype=torch.float64) * 0.5, torch.eye(2, dtype=torch.float64)),
                          LinearMeasurement(torch.tensor([[1.0, 1.0]], dtype=torch.float64),
                                            torch.eye(1, dtype=torch.float64)))
        b0 = GaussianBelief(torch.zeros(series, 2, dtype=torch.float64),
                            torch.eye(2, dtype=torch.float64).expand(series, 2, 2))
        em(kf, b0, y, ["F", "Q", "H", "R", "initial_mean", "initial_cov"], iterations=iterations, per_series=True,
           progress=False)
        return kf

    def theirs(count):
        fits = []
        for r in range(count):
            kf = PyKalman(np.eye(2) * 0.5, np.array([[1.0, 1.0]]), np.eye(2), np.eye(1), np.zeros(2), np.zeros(1),
                          np.zeros(2), np.eye(2), em_vars=names)
            kf.em(y[:, r].numpy(), n_iter=iterations)
            fits.append(kf)
        return fits

    a, b = ours(), theirs(1)[0]
    diff = float(np.abs(a.motion.Q[0].numpy() - b.transition_covariance).max())
    torch.set_num_threads(threads)  # (the batched tensors are large: every core)
    mine = best(ours, 1)
    torch.set_num_threads(1)
    tic = time.perf_counter()
    theirs(sample)
    ref = (time.perf_counter() - tic) * series / sample
    print(f"em_batch: {series} series x {steps} steps, {iterations} iterations: torchmm {mine:.2f} s batched "
          f"({threads} threads), "
          f"pykalman {ref:.1f} s ({sample} fits timed, scaled) ({ref / mine:.0f}x); series 0's Q difference {diff:.1e}")
    return ref / mine


def fedfunds(repeats: int) -> float:
    import statsmodels.api as sm

    from experiments.realdata import fedfunds_imm, load_fedfunds
    from torchmm import GaussianBelief
    from torchmm.learn import estimate, stationary

    y = load_fedfunds()[:, 0].numpy()
    model = sm.tsa.MarkovRegression(y, k_regimes=2, trend="c", switching_variance=True)
    p00, p10, c0, c1, s0, s1 = model.start_params
    z = torch.as_tensor(y).reshape(-1, 1)
    start = GaussianBelief(torch.ones(1, dtype=torch.float64), torch.zeros(1, 1, dtype=torch.float64))
    out = {}

    def ours():
        imm, _ = fedfunds_imm([c0, c1], [s0, s1], [[p00, 1 - p00], [p10, 1 - p10]])
        out["ours"] = estimate(imm, lambda f: f.initial_belief(start, stationary(f.transition.matrix())), z,
                               {"transition.value": "stochastic", "bank.filter.measurement.H": "free",
                                "bank.filter.measurement.R": "variance"}, progress=False)

    return _against_statsmodels("fedfunds", ours, model, out, repeats)


def _against_statsmodels(name: str, ours, model, out: dict, repeats: int, extra=lambda: "") -> float:
    """Time ``ours()`` (which leaves its estimate in ``out["ours"]``) against statsmodels' ``model.fit()``
    with its standard errors; print both log-likelihoods and the ratio."""
    def theirs():
        res = model.fit(disp=False)
        _ = res.bse
        out["theirs"] = res

    ours()  # (Numba's first load in this process: not timed)
    mine, ref = best(ours, repeats), best(theirs, repeats)
    print(f"{name}: fit with standard errors, torchmm {mine * 1e3:.0f} ms (llf {out['ours'].loglik:.4f}{extra()}), "
          f"statsmodels {ref * 1e3:.0f} ms (llf {out['theirs'].llf:.4f}) ({ref / mine:.2f}x)")
    return ref / mine


def fedfunds_exog(repeats: int) -> float:
    """statsmodels' ``TestFedFundsConstL1Exog`` model (Fed funds on its lag, the output gap and inflation,
    switching coefficients, one variance): ``fit()`` with ``bse`` against :func:`torchmm.learn.estimate`
    from its start values - the regressors the motion's controls, through the Numba kernel."""
    import ast
    import importlib.util
    from pathlib import Path

    import statsmodels.api as sm

    from torchmm import IMM, GaussianBelief, KalmanFilter
    from torchmm.learn import Param, estimate, stationary
    from torchmm.models import LinearMeasurement, LinearMotion

    spec = importlib.util.find_spec("statsmodels.tsa.regime_switching.tests.test_markov_regression")
    found = {}
    for node in ast.parse(Path(spec.origin).read_text()).body:  # (its data, not its pytest module)
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and getattr(node.targets[0], "id", "") in (
                "fedfunds", "ogap", "inf"):
            found[node.targets[0].id] = np.array([float("nan") if isinstance(e, ast.Attribute) else
                                                  ast.literal_eval(e) for e in node.value.elts])  # (np.nan)
    ff, ogap, inf = found["fedfunds"], found["ogap"], found["inf"]
    y, X = ff[4:], np.c_[ff[3:-1], ogap[4:], inf[4:]]
    model = sm.tsa.MarkovRegression(y, k_regimes=2, exog=X)
    p = model.start_params  # p00, p10, const0, const1, (lag, ogap, inf) x (regime 0, 1), sigma2
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=float), dtype=torch.float64)  # noqa: E731
    z, u = t(y).reshape(-1, 1), t(X)
    out = {}

    def ours():
        F = torch.diag(t([1.0, 0.0, 0.0, 0.0]))  # the state (1, x_t): a constant and the inputs
        G = torch.cat([torch.zeros(1, 3, dtype=torch.float64), torch.eye(3, dtype=torch.float64)])
        motion = LinearMotion(F.expand(2, 4, 4), torch.zeros(2, 4, 4, dtype=torch.float64), input_matrix=G.expand(2, 4, 3))
        H = t([[[p[2], p[4], p[6], p[8]]], [[p[3], p[5], p[7], p[9]]]])
        sensor = LinearMeasurement(H, t([p[10], p[10]]).reshape(2, 1, 1))
        imm = IMM(KalmanFilter(motion, sensor), t([[p[0], 1 - p[0]], [p[1], 1 - p[1]]]))
        start = GaussianBelief(t([1.0, 0.0, 0.0, 0.0]), torch.zeros(4, 4, dtype=torch.float64))
        shared = torch.full((2, 1, 1), 0, dtype=torch.long)
        out["ours"] = estimate(imm, lambda f: f.initial_belief(start, stationary(f.transition.matrix())), z,
                               {"transition.value": "stochastic",
                                "bank.filter.measurement.H": "free",
                                "bank.filter.measurement.R": Param("variance", groups=shared)},
                               controls=u.reshape(-1, 3), progress=False)

    return _against_statsmodels("fedfunds_exog", ours, model, out, repeats,
                                lambda: f", kernel {estimate.objective.kernel}")


def fedfunds_tvtp(repeats: int) -> float:
    """statsmodels' Fed funds with time-varying transition probabilities (``exog_tvtp``: a constant and the
    output gap; switching mean and variance) from its start values: ``fit()`` with ``bse`` against
    :func:`torchmm.learn.estimate` of an IMM with a :class:`~torchmm.LogisticTransition`, the logistic
    coefficients free (the Numba kernel reads each step's matrices)."""
    import statsmodels.api as sm

    from tests.experiments.test_markov_switching import _statsmodels_test_data
    from torchmm import IMM, GaussianBelief, KalmanFilter, LogisticTransition
    from torchmm.learn import estimate, stationary
    from torchmm.models import LinearMeasurement, LinearMotion

    ff, ogap = _statsmodels_test_data("fedfunds", "ogap")
    y, X = ff[4:], np.c_[np.ones(len(ff) - 4), ogap[4:]]
    model = sm.tsa.MarkovRegression(y, k_regimes=2, exog_tvtp=X, switching_variance=True)
    p = dict(zip(model.param_names, model.start_params))
    f64 = torch.float64
    z, u = torch.as_tensor(y, dtype=f64).reshape(-1, 1), torch.as_tensor(X, dtype=f64)
    out = {}

    def ours():
        coef = torch.tensor([[[p["p[0->0].tvtp0"], p["p[0->0].tvtp1"]]], [[p["p[1->0].tvtp0"], p["p[1->0].tvtp1"]]]],
                            dtype=f64)
        one = torch.ones(2, 1, 1, dtype=f64)
        imm = IMM(KalmanFilter(LinearMotion(one, 0 * one, input_matrix=torch.zeros(2, 1, 2, dtype=f64)),
                               LinearMeasurement(torch.tensor([[[p["const[0]"]]], [[p["const[1]"]]]], dtype=f64),
                                                 torch.tensor([[[p["sigma2[0]"]]], [[p["sigma2[1]"]]]], dtype=f64))),
                  LogisticTransition(coef, columns=[0, 1]))
        start = GaussianBelief(torch.ones(1, dtype=f64), torch.zeros(1, 1, dtype=f64))
        out["ours"] = estimate(imm, lambda f: f.initial_belief(start, stationary(f.transition.at(u[0]).matrix())), z,
                               {"transition.coef": "free", "bank.filter.measurement.H": "free",
                                "bank.filter.measurement.R": "variance"}, controls=u, progress=False)

    return _against_statsmodels("fedfunds_tvtp", ours, model, out, repeats,
                                lambda: f", kernel {estimate.objective.kernel}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--series", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--pykalman-series", type=int, default=20)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads(),
                        help="torch threads of the batched EM (the rest runs on one)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    a = em_robot(args.repeats)
    b = em_batch(args.series, args.steps, args.pykalman_series, args.iterations, args.threads)
    c = fedfunds(args.repeats)
    d = fedfunds_exog(args.repeats)
    e = fedfunds_tvtp(args.repeats)
    print(f"em_robot_speedup={a:.2f} em_batch_speedup={b:.1f} fedfunds_speedup={c:.2f} fedfunds_exog_speedup={d:.2f} "
          f"fedfunds_tvtp_speedup={e:.2f}")


if __name__ == "__main__":
    main()
