"""Every figure of a Monte Carlo quantity shows its uncertainty (issue 30).

The drawing helpers are checked on known inputs (error-bar lengths, band bounds, ellipse geometry);
the studies that draw such figures run once at debug sizes with ``StudyContext.save_figure``
replaced by a probe that inspects each figure object (error-bar containers, shaded
PolyCollections, ellipse patches) and closes it without writing files.
"""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from matplotlib.container import ErrorbarContainer  # noqa: E402
from matplotlib.patches import Ellipse  # noqa: E402

from experiments.studies import plots  # noqa: E402
from experiments.uncertainty import Z95  # noqa: E402


def _polys(ax):
    return [c for c in ax.collections if isinstance(c, PolyCollection)]


def _errorbars(ax):
    return [c for c in ax.containers if isinstance(c, ErrorbarContainer)]


def _band_limits(poly):
    """(min y, max y) of a fill_between band."""
    ys = np.concatenate([p.vertices[:, 1] for p in poly.get_paths()])
    return ys.min(), ys.max()


# -- helpers on known inputs ---------------------------------------------------------------------
def test_trajectory_2d_ellipse_is_two_sigma():
    T = 5
    truth = torch.zeros(T, 4)
    truth[:, 0] = torch.arange(T, dtype=torch.float64)
    mean = truth.clone()
    cov = torch.eye(4, dtype=torch.float64).repeat(T, 1, 1)
    cov[:, 0, 0], cov[:, 2, 2] = 4.0, 1.0  # diag(4, 1) in (x, y)
    fig = plots.trajectory(truth, truth[:, [0, 2]], {"KF": (mean, cov)}, components=(0, 2), run=None, every=1)
    ax = fig.axes[0]
    ellipses = [p for p in ax.patches if isinstance(p, Ellipse)]
    assert len(ellipses) == T
    for e in ellipses:
        semi = sorted([e.width / 2, e.height / 2])
        assert semi == pytest.approx([2.0, 4.0])  # 2 sigma: 2 * sqrt(1), 2 * sqrt(4)
        # the long axis along x: angle 0 or 180 degrees
        assert math.cos(math.radians(e.angle)) ** 2 * (e.width > e.height) + \
            math.sin(math.radians(e.angle)) ** 2 * (e.width < e.height) == pytest.approx(1.0)
    plt.close(fig)


def test_ellipse_axes_rotated_covariance():
    c, s = math.cos(0.5), math.sin(0.5)
    rot = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    cov = rot @ torch.diag(torch.tensor([9.0, 1.0], dtype=torch.float64)) @ rot.T
    width, height, angle = plots.ellipse_axes(cov, sigma=2.0)
    assert (width, height) == pytest.approx((12.0, 4.0))
    assert math.tan(math.radians(angle)) == pytest.approx(math.tan(0.5))


def test_trajectory_1d_band_is_two_sigma():
    T = 6
    truth = torch.zeros(T, 3, 2, dtype=torch.float64)  # (T, runs, n)
    mean = torch.full((T, 3, 2), 10.0, dtype=torch.float64)
    cov = torch.eye(2, dtype=torch.float64).repeat(T, 3, 1, 1) * 9.0  # sd 3
    fig = plots.trajectory(truth, truth[..., :1], {"IMM": (mean, cov)}, components=(0,), run=1)
    (band,) = _polys(fig.axes[0])
    assert _band_limits(band) == pytest.approx((10.0 - 6.0, 10.0 + 6.0))
    plt.close(fig)


def test_lines_draws_95_percent_error_bars():
    fig = plots.lines([1, 2, 3], {"a": [1.0, 2.0, 3.0], "b": [2.0, 2.0, 2.0]}, xlabel="x", ylabel="y",
                      errors={"a": [0.1, 0.2, 0.3], "b": [None, 0.1, 0.1]})
    ax = fig.axes[0]
    (bars,) = _errorbars(ax)  # "b" has a missing se: a plain line
    assert bars.get_label() == "a"
    segments = bars.lines[2][0].get_segments()
    half = [abs(seg[1][1] - seg[0][1]) / 2 for seg in segments]
    assert half == pytest.approx([Z95 * 0.1, Z95 * 0.2, Z95 * 0.3])
    plt.close(fig)


def test_mode_probabilities_one_panel_per_estimator():
    probs = torch.tensor([[0.7, 0.3], [0.4, 0.6]], dtype=torch.float64)
    fig = plots.mode_probabilities({"IMM": probs, "GPB2": probs}, torch.tensor([0, 1]), ["a", "b"])
    panels = [ax for ax in fig.axes if ax.collections]
    assert len(panels) == 2  # identical probabilities, still both visible
    assert [ax.get_ylabel().split("\n")[0] for ax in panels] == ["IMM", "GPB2"]
    plt.close(fig)
    fig = plots.mode_probabilities(probs, torch.tensor([0, 1]), ["a", "b"])  # one estimator, as before
    assert len(fig.axes) == 2
    plt.close(fig)


def test_nees_figure_and_curves_shade_the_chi_square_band():
    from experiments.plot import draw_groups

    steps = np.arange(1, 6)
    nees = torch.tensor([1.0, 2.0, 3.0, 2.5, 2.0], dtype=torch.float64)
    fig = plots.nees_over_time({"IMM": nees, "KF": nees * 1.1}, {"IMM": (1.2, 3.1), "KF": (1.2, 3.1)})
    (band,) = _polys(fig.axes[0])  # the same bounds: one band
    assert _band_limits(band) == pytest.approx((1.2, 3.1))
    plt.close(fig)

    curves = {"nees/IMM": ("step", steps, nees.numpy()),
              "nees_low/IMM": ("step", steps, np.full(5, 1.2)), "nees_high/IMM": ("step", steps, np.full(5, 3.1)),
              "nees/KF": ("step", steps, nees.numpy()),
              "nees_low/KF": ("step", steps, np.full(5, 0.9)), "nees_high/KF": ("step", steps, np.full(5, 3.5))}
    figures = dict(draw_groups(curves))
    assert set(figures) == {"nees"}  # the bounds get no figure of their own
    limits = sorted(v for p in _polys(figures["nees"].axes[0]) for v in _band_limits(p))
    assert limits == pytest.approx([0.9, 1.2, 3.1, 3.5])  # different bounds: one band per series
    plt.close(figures["nees"])


def test_nees_figure_draws_each_steps_band():
    """Per-step bounds (fewer runs at the padded steps: a wider band; none scored: NaN, no band there)."""
    nees = torch.tensor([1.0, 2.0, 3.0, 2.5, 2.0], dtype=torch.float64)
    lo = torch.tensor([0.4, 0.4, 0.2, 0.05, torch.nan], dtype=torch.float64)
    hi = torch.tensor([4.8, 4.8, 5.6, 7.4, torch.nan], dtype=torch.float64)
    fig = plots.nees_over_time({"IMM": nees, "KF": nees * 1.1}, {"IMM": (lo, hi), "KF": (lo.clone(), hi.clone())})
    (band,) = _polys(fig.axes[0])  # the same per-step bounds: one band
    ys = np.concatenate([p.vertices[:, 1] for p in band.get_paths()])
    assert ys.min() == pytest.approx(0.05) and ys.max() == pytest.approx(7.4) and np.isfinite(ys).all()
    plt.close(fig)


# -- the studies' figures ------------------------------------------------------------------------
def _probe(figure) -> dict:
    axes = figure.axes
    return {"errorbars": [len(_errorbars(ax)) for ax in axes], "bands": [len(_polys(ax)) for ax in axes],
            "ellipses": sum(isinstance(p, Ellipse) for ax in axes for p in ax.patches),
            "lines": [len([ln for ln in ax.get_lines() if not ln.get_label().startswith("_")]) for ax in axes],
            "labels": [ax.get_ylabel() for ax in axes]}


@pytest.fixture(scope="module")
def drawn(tmp_path_factory):
    """``{study: {figure: probe}}`` of imm_baseline, imm_tf and imm_analysis at debug sizes."""
    from experiments.harness import StudyContext
    from experiments.run import run_study
    from tests.experiments.test_studies import _compose

    seen: dict[str, dict] = {}
    original = StudyContext.save_figure

    def probe(self, name, figure):
        seen[name] = _probe(figure)
        plt.close(figure)

    StudyContext.save_figure = probe
    out = {}
    try:
        for study, extra in (("imm_baseline", []), ("imm_analysis", []),
                             ("imm_tf", ["estimator_names=[IMM,IMM-TF,IMM-FU]", "mc_runs=3"])):
            seen = {}
            run_study(_compose(study, f"debug={study}", "logger=none", "progress=false", *extra),
                      tmp_path_factory.mktemp(study))
            out[study] = seen
    finally:
        StudyContext.save_figure = original
    return out


def test_imm_baseline_figures_carry_uncertainty(drawn):
    figs = drawn["imm_baseline"]
    assert {"rmse_over_time", "nees", "mode_probabilities", "trajectory"} <= set(figs)
    rmse = figs["rmse_over_time"]
    assert rmse["bands"] == rmse["lines"] == [4, 4]  # a 95 % band per estimator and panel
    assert figs["nees"]["bands"] == [1]  # the chi-square band (every estimator: 4 runs, n = 2)
    modes = figs["mode_probabilities"]
    assert len(modes["labels"]) == 4 and modes["labels"][-1] == "true mode"  # IMM, GPB1, GPB2 + truth
    assert figs["trajectory"]["bands"] == [4]  # 1-D position: a 2-sigma band per estimator


def test_imm_tf_figures_carry_uncertainty(drawn):
    figs = drawn["imm_tf"]
    for name in ("table1", "rs_sweep"):
        # every estimator's line has its error bars, in both panels (the published line has none)
        assert figs[name]["errorbars"] == [3, 3], name
    influence = figs["influence"]
    assert influence["bands"] == influence["lines"] == [2, 1]  # IMM, IMM-TF RMSE bands; IMM-TF's |L_k| band
    assert figs["nees"]["bands"] == [1]
    assert figs["rmse_over_time"]["bands"] == [3, 3]


def test_imm_analysis_figures_carry_uncertainty(drawn):
    figs = drawn["imm_analysis"]
    assert figs["rmse_vs_alpha"]["errorbars"] == [2, 2]  # IMM and GPB1, two and three models
    assert figs["delta_vs_alpha"]["errorbars"] == [2]


def test_curves_of_several_estimators_mode_probabilities_stay_distinct():
    """``mode_probability/<estimator>/<mode>``: the colour names the mode, the line style the
    estimator, the first estimator drawn thicker - coinciding estimators remain visible."""
    from experiments.plot import draw_groups

    steps = np.arange(1, 4)
    p = np.array([0.2, 0.5, 0.9])
    curves = {f"mode_probability/{e}/{m}": ("step", steps, p if m == "a" else 1 - p)
              for e in ("IMM", "GPB2") for m in ("a", "b")}
    figures = dict(draw_groups(curves))
    lines = {ln.get_label(): ln for ln in figures["mode_probability"].axes[0].get_lines()}
    imm, gpb2 = lines["IMM/a"], lines["GPB2/a"]
    assert imm.get_color() == gpb2.get_color() != lines["IMM/b"].get_color()
    assert imm.get_linestyle() != gpb2.get_linestyle()
    assert imm.get_linewidth() > gpb2.get_linewidth()
    plt.close(figures["mode_probability"])
