"""Hydra entry point of every torchmm study: ``torchmm-run experiment=<name> [key=value ...]``.

Equivalently ``python -m experiments.run ...``. The study named by ``study`` (a dotted path to a
``run(ctx)`` function) gets a :class:`~experiments.context.StudyContext` and writes
``results.json``, ``results.md``, ``figures/*.png`` and TensorBoard events into the Hydra run
directory.

Before Hydra starts, :func:`experiments.config.precheck` validates the whole config (every job of
a sweep): a user error is one line on stderr and exit status 2, and no run folder is created.
Run folders are unique: ``${torchmm.unique_dir:<base>}`` (``conf/config.yaml``) creates
``<base>``, or ``<base>_1``, ``<base>_2``, ... if it exists, atomically (``os.mkdir``), so two
runs started in the same second never share a folder. A run holds its folder's lock
(:func:`experiments.files.lock_folder`) while it runs: a second run aimed at the same folder
(``hydra.run.dir=<dir>``, ``resume=``), or a second sweep into the same ``hydra.sweep.dir``, is
refused with one line and exit status 2 before it writes anything there; a file-level failure
(a corrupt checkpoint, a folder that cannot be written) is one line naming the file, exit status 2.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

# (before Hydra; importing it registers the resolver torchmm.sweep_subdir)
from experiments.claim import claim_folder, fail, resolve_resume
from experiments.config import ConfigError, precheck, validate
from experiments.paths import CONFIG_DIR

if TYPE_CHECKING:
    from experiments.results import Results

# torch, Hydra, the harness and torchmm are imported where they are used (``torchmm-run --help``
# and ``--version`` print in a fraction of a second; a run imports them once it starts). Their names
# stay importable from here (``from experiments.run import unique_dir``): see ``__getattr__`` below.
_LAZY = {
    "torch": ("torch", None),
    "hydra": ("hydra", None),
    "HydraConfig": ("hydra.core.hydra_config", "HydraConfig"),
    "get_method": ("hydra.utils", "get_method"),
    "NonFiniteLossError": ("torchmm.learn", "NonFiniteLossError"),
    "Provenance": ("experiments.provenance", "Provenance"),
    "compile_fast_paths": ("torchmm.runtime", "compile_fast_paths"),
    "retain_freed_memory": ("torchmm.runtime", "retain_freed_memory"),
    "Results": ("experiments.results", "Results"),
    "open_context": ("experiments.context", "open_context"),
    "unique_dir": ("experiments.folders", "unique_dir"),
    "sweep_subdir": ("experiments.claim", "sweep_subdir"),
    "sweep_job_dir": ("experiments.claim", "sweep_job_dir"),
    "_LOCKS": ("experiments.files", "LOCKS"),  # the former name of LOCKS
    **{name: ("experiments.files", name) for name in (
        "LOCKS", "LOCK_FILE", "RunFolderError", "lock_folder", "unlock_folder")},
}


def __getattr__(name: str) -> Any:
    """The lazily imported names of ``_LAZY`` as attributes of this module."""
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    module, attr = _LAZY[name]
    value = importlib.import_module(module)
    return value if attr is None else getattr(value, attr)


log = logging.getLogger("torchmm.experiments")
_fail = fail  # one line, exit status 2


def _unique_locked_dir(base: str) -> str:
    """The ``torchmm.unique_dir`` resolver: :func:`unique_dir`, locked for this process's life (a run's
    or a sweep's folder); a folder that cannot be made is one line and exit status 2, no traceback."""
    try:
        from experiments.files import RunFolderError, lock_folder
        from experiments.folders import unique_dir

        folder = unique_dir(base)
        lock_folder(Path(folder))
    except RunFolderError as err:
        _fail(str(err))
    return folder


if not OmegaConf.has_resolver("torchmm.unique_dir"):
    OmegaConf.register_new_resolver("torchmm.unique_dir", _unique_locked_dir, use_cache=True)


def run_study(cfg: DictConfig, output_dir: Path, overrides: list[str] | None = None) -> Results:
    """Run the configured study into ``output_dir`` (usable without Hydra's main, e.g. in tests).

    The config is validated first (:func:`experiments.config.validate`): a bad key raises
    :class:`~experiments.config.ConfigError` before anything is written. ``overrides`` (the
    command line's ``key=value``; Hydra's task overrides) name the run in TensorBoard's hparams.
    """
    from hydra.utils import get_method

    import torchmm.kernels as kernels
    from experiments.changes import config_changes
    from experiments.context import open_context
    from experiments.files import LOCKS, lock_folder, unlock_folder

    from experiments.folders import with_data_files

    validate(cfg, overrides=overrides)
    config = with_data_files(OmegaConf.to_container(cfg, resolve=True))  # (the data files: result keys)
    study = get_method(cfg.study)
    held = set(LOCKS)  # the locks taken here are released at the end (the command line's: at exit)
    try:
        lock_folder(Path(output_dir))  # another process running there: FolderInUse, nothing written
        ctx = open_context(cfg, Path(output_dir), config, experiment=str(cfg.experiment_name))
        lock_folder(ctx.output_dir)  # a fresh sibling (another config was in output_dir)
        ctx.results.changes = config_changes(config)  # results.md: what differs from the study's defaults
        # the kernels whose choice depends on the number of runs are off: a study's numbers must not
        # depend on how its runs are split into units (experiments.executors.execute does the same for each unit)
        with kernels.switched_off(*kernels.by_size()):
            return _run(cfg, ctx, study, config, overrides)
    finally:
        for key in set(LOCKS) - held:
            unlock_folder(Path(key))


def _run(cfg: DictConfig, ctx, study, config: dict, overrides: list[str] | None) -> Results:
    import torch

    from experiments.provenance import Provenance
    from torchmm import kernels
    from torchmm.runtime import compile_fast_paths, retain_freed_memory

    ctx.bar_label, ctx.bar_position = _sweep_bars()
    if ctx._checkpoint:
        print(f"torchmm-run: resuming: {len(ctx._checkpoint)} finished units in the checkpoint of "
              f"{ctx.output_dir} (those the study asks for again are kept)",
              file=sys.stderr, flush=True)
    previous_threads = torch.get_num_threads()
    threads = cfg.get("threads")
    if threads:
        torch.set_num_threads(int(threads))
    if cfg.get("retain_freed_memory"):
        retain_freed_memory()
    previous_compile = compile_fast_paths(bool(cfg.get("compile", False)))
    kernels_off = cfg.get("cpu_kernels", True) is False  # the eager particle path (the same numbers)
    previous_kernels = kernels.enabled("particle_stages")
    if kernels_off:
        kernels.set_enabled("particle_stages", False)
    provenance = Provenance()
    provenance.start(device=ctx.device, dtype=ctx.dtype, threads=torch.get_num_threads())
    # (read before the study rewrites results.json)
    previous = finished_provenance(ctx.output_dir)
    ctx.logger.text("config", "```yaml\n" + OmegaConf.to_yaml(config) + "```")  # the resolved config
    try:
        with kernels.counting() as runs:  # which kernel computed each run_filter call of this process
            study(ctx)
        provenance.finish()
        units_kept = len(ctx.reused)  # (the checkpoint's units the study read back, not all it held)
        provenance.record_kernels(runs, executor=str((cfg.get("executor") or {}).get("kind", "local")),
                                  resumed=units_kept > 0 and not runs)
        provenance.continue_from(previous, units_kept)  # a finished run continued: its provenance kept
        ctx.results.provenance = provenance.data
        ctx.results.save()
        ctx.logger.save(ctx.output_dir, figures=ctx.figures)  # curves.npz / curves.csv: every curve as data
        if ctx.figures and (ctx.output_dir / "curves.npz").exists():  # figures/curves/: from that file alone
            from experiments.plot import plot_curves

            plot_curves(ctx.output_dir, formats=("png",))  # PDF/SVG: torchmm-plot RUN_DIR
        ctx.logger.hparams(*hparams(config, overrides or [], ctx.results))
    finally:
        ctx.close_executor()
        ctx.logger.close()
        torch.set_num_threads(previous_threads)
        compile_fast_paths(previous_compile)
        if kernels_off:
            kernels.set_enabled("particle_stages", previous_kernels)
    log.info("results written to %s", ctx.output_dir)
    return ctx.results


def finished_provenance(folder: Path) -> dict | None:
    """The provenance of the finished run ``folder`` holds (its results.json's, with an ``end``), or None."""
    try:
        provenance = json.loads((Path(folder) / "results.json").read_text()).get("provenance")
    except (OSError, ValueError, AttributeError):
        return None
    return provenance if isinstance(provenance, dict) and provenance.get("end") else None


def _sweep_bars() -> tuple[str, int | None]:
    """In a ``-m`` sweep: ``("[job N]", terminal line)`` for the job's progress bars, else ``("", None)``."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return "", None
    hc = HydraConfig.get()
    num = int(hc.job.num)
    jobs = OmegaConf.select(hc, "launcher.n_jobs", default=1) or 1
    jobs = (os.cpu_count() or 1) if int(jobs) < 0 else int(jobs)
    return f"[job {num}]", num % max(jobs, 1)


def hparams(config: dict, overrides: list[str], results: Results) -> tuple[dict, dict]:
    """TensorBoard hparams of a run: ``(settings, headline metrics)``.

    Settings: ``experiment``, ``seed``, ``mc_runs``, ``dtype``, ``device`` and every command-line
    override (``key=value``) except those that do not change results; metrics: every finite number
    of ``results.metrics`` as ``headline/<estimator>/<metric>`` (no cap; a metric that is not a finite
    number is not logged: results.json names why it was dropped)."""
    from experiments.folders import NON_RESULT_KEYS

    settings: dict[str, Any] = {"experiment": results.experiment}
    for key in ("seed", "mc_runs", "dtype", "device"):
        if config.get(key) is not None:
            settings[key] = config[key]
    for item in overrides:
        key, sep, value = item.lstrip("+~").partition("=")
        if not sep or key.split(".")[0] in NON_RESULT_KEYS or key.startswith("hydra"):
            continue
        try:
            settings[key] = int(value)
        except ValueError:
            try:
                settings[key] = float(value)
            except ValueError:
                settings[key] = value
    settings = {k: v if isinstance(v, (int, float, str, bool)) else str(v) for k, v in settings.items()}
    metrics = {}
    for estimator, values in results.metrics.items():
        for name, value in values.items():
            if isinstance(value, (int, float)) and not isinstance(value, bool) and value == value \
                    and abs(value) != float("inf"):
                metrics[f"headline/{estimator}/{name}"] = float(value)
    return settings, metrics


def _hydra_main() -> None:
    """Hydra's main (``@hydra.main``) around :func:`_study_main`, made when a run starts."""
    import hydra

    hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="config")(_study_main)()


def _study_main(cfg: DictConfig) -> None:
    """One run (or one sweep job) under Hydra: the study into Hydra's output folder."""
    # the objects of the imports (torch, Hydra: about a million) never become garbage: kept out of the
    # collector, whose first full pass over them otherwise costs ~70 ms in the study's first steps
    import gc

    from hydra.core.hydra_config import HydraConfig

    from experiments.files import RunFolderError
    from torchmm.learn import NonFiniteLossError

    gc.freeze()
    output_dir = Path(HydraConfig.get().runtime.output_dir)
    print(f"torchmm-run: {cfg.get('experiment_name', 'study')} -> {output_dir}", file=sys.stderr, flush=True)
    try:
        results = run_study(cfg, output_dir, overrides=list(HydraConfig.get().overrides.task))
    except ConfigError as err:  # precheck missed it (e.g. a config dir of the user's): one line, no folder
        _remove_if_unused(output_dir)
        print(f"torchmm-run: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    except RunFolderError as err:  # a corrupt checkpoint, a folder that cannot be written or is in use
        print(f"torchmm-run: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    # training diverged: one line naming the parameter (the units done are kept)
    except NonFiniteLossError as err:
        print(f"torchmm-run: error: {err}", file=sys.stderr)
        raise SystemExit(1) from None
    except KeyboardInterrupt:
        print(interrupted_line(output_dir, _sweep_folder()), file=sys.stderr)
        raise SystemExit(130) from None
    _print_headline(results, results.output_dir)


def _sweep_folder() -> tuple[str, bool] | None:
    """In a ``-m`` sweep: ``(hydra.sweep.dir, whether the command line gave it)``, else None."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return None
    hc = HydraConfig.get()
    given = any(str(o).startswith("hydra.sweep.dir=") for o in hc.overrides.hydra)
    return str(hc.sweep.dir), given


def interrupted_line(output_dir: Path, sweep: tuple[str, bool] | None = None) -> str:
    """What Ctrl-C prints: what the run folder keeps (the finished units in its checkpoint.json, or none)
    and what continues it - a single run: the same command with ``resume=latest`` (or ``resume=<dir>``);
    a ``-m`` sweep's job (``sweep``: ``(hydra.sweep.dir, given on the command line)``; ``resume=`` is
    refused with ``-m``): the same command with that ``hydra.sweep.dir`` (docs/scaling.md, "Resuming a
    sweep"); nothing kept in a single run: the same command, which starts afresh."""
    checkpoint = Path(output_dir) / "checkpoint.json"
    try:
        units = json.loads(checkpoint.read_text()).get("units")
        count = len(units) if isinstance(units, dict) else 0
    except (OSError, ValueError, AttributeError):
        count = 0
    kept = (f"{count} finished unit{'s' if count != 1 else ''} kept in {checkpoint}" if count
            else f"no unit had finished, so {output_dir} keeps none")
    if sweep is not None:
        folder, given = sweep
        again = (f"re-run the same command (it has hydra.sweep.dir={folder})" if given
                 else f"re-run the same command with hydra.sweep.dir={folder}")
        return (f"torchmm-run: interrupted; {kept}. To continue the sweep, {again}: each job continues its "
                "own folder")
    if not count:
        return f"torchmm-run: interrupted; {kept}. Run the same command again to start afresh"
    return (f"torchmm-run: interrupted; {kept}. Resume with the same command and resume=latest "
            f"(or resume={output_dir})")


def _print_headline(results: Results, output_dir: Path) -> None:
    """The study's first table and where everything is, at the end of a run."""
    if results.tables:
        name, table = next(iter(results.tables.items()))
        print(f"\n{results.experiment}: {name}\n\n{table.markdown()}\n")
    print(f"torchmm-run: results in {output_dir / 'results.md'} (tables, figures/, provenance)", file=sys.stderr)


def study_summaries(config_dir: str = CONFIG_DIR) -> list[tuple[str, str]]:
    """``(name, summary)`` of every ``conf/experiment/*.yaml`` (its ``# summary:`` comment line)."""
    out = []
    for path in sorted(Path(config_dir, "experiment").glob("*.yaml")):
        summary = next((m.group(1).strip() for m in map(re.compile(r"^#\s*summary:(.*)$").match,
                                                          path.read_text().splitlines()) if m), "")
        out.append((path.stem, summary))
    return out


def help_text() -> str:
    """``torchmm-run --help``: the studies, the common keys (with their defaults, read from
    conf/config.yaml: the one place they are declared) and the config groups."""
    import yaml

    studies = "\n".join(f"  {name:<16} {line}" for name, line in study_summaries())
    common = yaml.safe_load((Path(CONFIG_DIR) / "config.yaml").read_text())
    keys = [f"  {key}={'null' if value is None else str(value).lower() if isinstance(value, bool) else value}"
            for key, value in common.items() if key not in ("defaults", "hydra") and not isinstance(value, dict)]
    groups = sorted(p.name for p in Path(CONFIG_DIR).iterdir() if p.is_dir())
    return (
        "usage: torchmm-run [experiment=NAME] [key=value ...] [-m key=a,b ...]\n\n"
        "Runs a torchmm study: Monte Carlo runs batched in one call per time step; writes results.json,\n"
        "results.md, figures/ and TensorBoard logs into a fresh run folder (named when it starts).\n\n"
        f"studies (experiment=NAME; default quickstart):\n{studies}\n\n"
        "common keys:\n" + "\n".join(keys) + "\n\n"
        f"config groups: {', '.join(groups)} (e.g. mode_filter=unscented, debug=NAME for tiny sizes)\n"
        "-m sweeps (Hydra's joblib launcher); docs/studies.md lists every study's keys.\n"
        "Hydra's own options: --hydra-help, --cfg job, --info.\n"
    )


def _remove_if_unused(output_dir: Path) -> None:
    """Delete a run folder holding nothing but Hydra's own files (``.hydra/``, ``*.log``)."""
    from experiments.files import LOCK_FILE

    ignored = (".hydra", LOCK_FILE)
    if output_dir.is_dir() and all(p.name in ignored or p.suffix == ".log" for p in output_dir.iterdir()):
        shutil.rmtree(output_dir, ignore_errors=True)


def main() -> None:
    """The ``torchmm-run`` console script: validate the command line's config, then run Hydra."""
    args = sys.argv[1:]
    if "--version" in args:
        import torchmm

        print(f"torchmm-run (torchmm {torchmm.__version__})")
        return
    if "--help" in args or "-h" in args:
        print(help_text(), end="")
        return
    from experiments.files import RunFolderError

    precheck(args, CONFIG_DIR)
    args = resolve_resume(args, CONFIG_DIR)
    try:
        args = claim_folder(args, CONFIG_DIR)
    except RunFolderError as err:
        _fail(str(err))
    sys.argv[1:] = args
    _hydra_main()


if __name__ == "__main__":
    main()
