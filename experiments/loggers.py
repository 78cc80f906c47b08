"""What studies log: the :class:`Logger` interface, TensorBoard (:class:`TensorBoardLogger`) or
nothing (:class:`NullLogger`), and :class:`CurveRecorder`, which keeps every logged curve as data
(``curves.npz``, ``curves.csv``). (Named ``loggers``, not ``logging``: the standard library's stays
importable inside the package.)"""

from __future__ import annotations

import logging
import struct
from collections.abc import Iterable, Sequence
from pathlib import Path

import torch

from experiments.files import write_atomic

log = logging.getLogger("torchmm.experiments")

#: where a run folder's earlier event files go when the run is continued (:func:`set_aside_event_files`)
SUPERSEDED = "superseded"


class Logger:
    """Logging interface of studies (TensorBoard or nothing)."""

    def scalar(self, tag: str, value: float, step: int = 0) -> None: ...

    def series(self, tag: str, values: Iterable[float], start: int = 1) -> None:
        """One scalar per time step (TensorBoard x-axis = time step)."""
        for k, v in enumerate(values, start=start):
            self.scalar(tag, float(v), k)

    def sweep(self, tag: str, x: Sequence[float], values: Iterable[float], axis: str) -> None:
        """One value per point of an in-study parameter sweep (``axis``, e.g. ``alpha``): a curve
        over that parameter, not over time steps (TensorBoard: drawn as a figure, ``sweeps/``)."""

    def histogram(self, tag: str, values: torch.Tensor, step: int = 0) -> None: ...

    def figure(self, tag: str, figure, png: bytes | None = None) -> None:
        """A matplotlib figure; ``png``: the figure already rendered as PNG (logged as it is)."""

    def text(self, tag: str, text: str) -> None: ...

    def hparams(self, hparams: dict, metrics: dict) -> None:
        """The run's settings and headline numbers (TensorBoard's HPARAMS tab: a row per run)."""

    def close(self) -> None: ...


class NullLogger(Logger):
    """``logger=none``: discard everything."""


class TensorBoardLogger(Logger):
    """TensorBoard events under ``<run dir>/tb``: one event file, this execution's. A run continued in its
    folder (``resume=``, a sweep re-run into its ``hydra.sweep.dir``) logs everything again (its curves,
    figures and hparams are made from all its units, the kept ones included), so the earlier event files are
    moved aside first (:func:`set_aside_event_files`): each point is in ``tb/`` once."""

    def __init__(self, log_dir: Path, flush_secs: int = 10):
        from torch.utils.tensorboard import SummaryWriter

        set_aside_event_files(Path(log_dir))
        self.writer = SummaryWriter(log_dir=str(log_dir), flush_secs=flush_secs)

    def scalar(self, tag, value, step=0):
        self.writer.add_scalar(tag, value, step)

    def histogram(self, tag, values, step=0):
        self.writer.add_histogram(tag, values.detach().cpu(), step)

    def figure(self, tag, figure, png=None):
        if png is None:
            self.writer.add_figure(tag, figure, close=False)
            return
        # the PNG the study saved, as TensorBoard's encoded image: no second rendering
        from tensorboard.compat.proto.summary_pb2 import Summary

        width, height = struct.unpack(">II", png[16:24])  # the IHDR chunk
        channels = {0: 1, 2: 3, 4: 2, 6: 4}.get(png[25], 4)  # by the PNG colour type
        image = Summary.Image(height=height, width=width, colorspace=channels, encoded_image_string=png)
        self.writer._get_file_writer().add_summary(Summary(value=[Summary.Value(tag=tag, image=image)]))

    def text(self, tag, text):
        self.writer.add_text(tag, text)

    def hparams(self, hparams, metrics):
        # into this run's own event file (SummaryWriter.add_hparams would open a second writer)
        from torch.utils.tensorboard.summary import hparams as hparams_summary

        writer = self.writer._get_file_writer()
        for summary in hparams_summary(hparams, metrics):
            writer.add_summary(summary)
        for key, value in metrics.items():
            self.writer.add_scalar(key, value)

    def close(self):
        self.writer.flush()
        self.writer.close()


class CurveRecorder(Logger):
    """Records every per-step series a study logs (``series(tag, values)``) as data, whatever the
    logger; forwards everything to ``inner``. :meth:`save` writes ``curves.npz`` and ``curves.csv``."""

    def __init__(self, inner: Logger):
        self.inner = inner
        #: tag -> (axis name, x values, values); axis "step" for per-step curves
        self.curves: dict[str, tuple[str, list, list[float]]] = {}

    def series(self, tag, values, start=1):
        values = _floats(values)
        self.curves[tag] = ("step", list(range(start, start + len(values))), values)
        self.inner.series(tag, values, start)

    def sweep(self, tag, x, values, axis):
        if not axis or "#" in axis or axis == "step":
            raise ValueError(f"axis: a parameter name without '#' other than 'step', got {axis!r}")
        x, values = _floats(x), _floats(values)
        if len(x) != len(values):
            raise ValueError(f"sweep {tag}: {len(x)} x values but {len(values)} values")
        self.curves[tag] = (axis, x, values)  # once per tag: a re-logged sweep replaces the old points
        self.inner.sweep(tag, x, values, axis)

    def hparams(self, hparams, metrics):
        self.inner.hparams(hparams, metrics)

    def scalar(self, tag, value, step=0):
        self.inner.scalar(tag, value, step)

    def histogram(self, tag, values, step=0):
        self.inner.histogram(tag, values, step)

    def figure(self, tag, figure, png=None):
        self.inner.figure(tag, figure, png=png)

    def text(self, tag, text):
        self.inner.text(tag, text)

    def close(self):
        self.inner.close()

    def save(self, output_dir: Path, figures: bool = True) -> None:
        """``curves.npz``: per curve ``<tag>`` the values and ``<tag>#<axis>`` its x values - the time
        steps (``#step``) or a swept parameter (e.g. ``#alpha``); and a tidy ``curves.csv``
        (``quantity, series, axis, x, value``; the tag is ``quantity/series``). ``figures``: also draw
        the sweeps' curves for TensorBoard."""
        if not self.curves:
            return
        import numpy as np

        arrays = {}
        for tag, (axis, x, values) in self.curves.items():
            arrays[tag] = np.asarray(values, dtype=np.float64)
            arrays[f"{tag}#{axis}"] = np.asarray(x, dtype=np.int64 if axis == "step" else np.float64)
        write_atomic(output_dir / "curves.npz", lambda f: np.savez(f, **arrays))
        lines = ["quantity,series,axis,x,value"]
        for tag, (axis, x, values) in self.curves.items():
            quantity, _, series = tag.partition("/")
            for k, v in zip(x, values):
                lines.append(f"{_csv(quantity)},{_csv(series)},{_csv(axis)},{k!r},{v!r}")
        write_atomic(output_dir / "curves.csv", "\n".join(lines) + "\n")
        sweeps = {tag: c for tag, c in self.curves.items() if c[0] != "step"}
        if figures and sweeps and not isinstance(self.inner, NullLogger):  # TensorBoard: sweeps on their own axis
            from experiments.plot import draw_groups

            for quantity, fig in draw_groups(sweeps):
                self.inner.figure(f"sweeps/{quantity}", fig)
                import matplotlib.pyplot as plt

                plt.close(fig)


def set_aside_event_files(log_dir: Path) -> Path | None:
    """Move the event files already in ``log_dir`` (an earlier execution of this run folder's) into
    ``log_dir/superseded/<k>/`` (``k = 1, 2, ...``: one folder per continuation), each renamed
    ``tfevents`` -> ``superseded``: kept, but not read by TensorBoard (it reads files whose name holds
    ``tfevents``, in every folder under ``--logdir``), which would show each point and the hparams row
    twice. Rename one back to look at it. Returns the folder, or None when there was nothing to move."""
    files = sorted(p for p in log_dir.glob("*tfevents*") if p.is_file()) if log_dir.is_dir() else []
    if not files:
        return None
    used = [int(p.name) for p in (log_dir / SUPERSEDED).glob("*") if p.name.isdigit()]
    folder = log_dir / SUPERSEDED / str(max(used, default=0) + 1)
    folder.mkdir(parents=True)
    for path in files:
        path.rename(folder / path.name.replace("tfevents", SUPERSEDED))
    log.info("%s: %d event file(s) of an earlier execution of this run moved to %s (renamed, so TensorBoard "
             "shows this execution's points once)", log_dir, len(files), folder)
    return folder


def _floats(values) -> list[float]:
    return [float(v) for v in (values.tolist() if isinstance(values, torch.Tensor) else values)]


def _csv(text: str) -> str:
    return f'"{text}"' if any(c in text for c in ',"\n') else text


def make_logger(cfg: dict | None, output_dir: Path) -> Logger:
    kind = (cfg or {}).get("kind", "none")
    if kind == "tensorboard":
        return TensorBoardLogger(output_dir / cfg.get("subdir", "tb"), flush_secs=int(cfg.get("flush_secs", 10)))
    if kind == "none":
        return NullLogger()
    raise ValueError(f"logger.kind: expected 'tensorboard' or 'none', got {kind!r}")
