"""The truth of the generic study's recorded data (``experiment=compare``,
:mod:`experiments.studies.compare`): which state components have truth, in the file and in each series,
and each series' NEES over its own components (docs/studies.md, "Recorded data": a series' numbers are
those of a file holding it alone); split from the study's module by concern."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from torchmm import GaussianBelief
from torchmm.metrics import nees

__all__ = ["marginal_nees", "partial_series", "series_components", "series_nees", "truth_components"]


def truth_components(scenario) -> list[int] | None:
    """The state components with truth: every one for simulated data; for recorded data those with a
    finite cell (``truth: [px, null, py, null]`` or an empty column gives none for that component);
    None without truth."""
    if scenario.data is None:
        return list(range(scenario.initial.state_dim))
    if scenario.data.truth is None:
        return None
    known = np.isfinite(scenario.data.truth).any(axis=(0, 1))
    return [int(i) for i in np.flatnonzero(known)] or None


def series_components(truth: np.ndarray | Tensor) -> list[list[int]]:
    """Each series' components with truth (a finite cell in that series): ``truth (T, runs, n)`` -> one
    list per run, what :func:`truth_components` gives for a file holding that series alone (``[]``: none)."""
    finite = torch.isfinite(torch.as_tensor(truth)).any(0)  # (runs, n)
    return [[int(i) for i in torch.nonzero(row).flatten()] for row in finite]


def marginal_nees(estimate, truth: Tensor, present: Tensor, comps: list[int]) -> Tensor:
    """``(T, runs)``: the NEES of the estimate's marginal over the components ``comps`` where every one of
    them has truth at a present step, NaN elsewhere."""
    ok = (present.unsqueeze(-1) & torch.isfinite(truth))[..., comps].all(-1)
    marginal = GaussianBelief(estimate.mean[..., comps], estimate.cov[..., comps, :][..., comps])
    return torch.where(ok, nees(marginal, torch.nan_to_num(truth[..., comps])), torch.nan)


def series_nees(estimate, truth: Tensor, present: Tensor, known: list[int], pooled: Tensor) -> Tensor:
    """``(T, runs)``: each series' NEES over its own components with truth (:func:`series_components`), as
    in a file holding it alone. ``pooled`` is the NEES over the file's components ``known``
    (:func:`marginal_nees`), taken as it is for a series with truth for all of them; NaN for a series
    without truth."""
    out = pooled.clone()
    own = series_components(truth)
    for comps in {tuple(c) for c in own if c != known}:
        runs = [j for j, c in enumerate(own) if tuple(c) == comps]
        out[:, runs] = (marginal_nees(estimate, truth, present, list(comps))[:, runs] if comps
                        else torch.nan)
    return out


def partial_series(scenario, known: list[int] | None) -> dict[str, list[int]]:
    """The series of recorded data with truth for some but not all of the file's components ``known``:
    ``{series: its components}`` (their NEES is over fewer components: not pooled with the others')."""
    if scenario.data is None or scenario.data.truth is None or not known:
        return {}
    own = series_components(scenario.data.truth)
    return {name: c for name, c in zip(scenario.data.series, own) if c and c != known}
