"""Hydra entry point of every torchmm study: ``torchmm-run experiment=<name> [key=value ...]``.

Equivalently ``python -m experiments.run ...``. The study named by ``study`` (a dotted path to a
``run(ctx)`` function) gets a :class:`~experiments.harness.StudyContext` and writes
``results.json``, ``results.md``, ``figures/*.png`` and TensorBoard events into the Hydra run
directory.
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import get_method
from omegaconf import DictConfig, OmegaConf

from experiments.harness import Results, open_context
from torchmm.runtime import retain_freed_memory

log = logging.getLogger("torchmm.experiments")

#: conf/ next to this package (absolute, so the console script works from any directory)
CONFIG_DIR = str(Path(__file__).resolve().parent.parent / "conf")


def run_study(cfg: DictConfig, output_dir: Path) -> Results:
    """Run the configured study into ``output_dir`` (usable without Hydra's main, e.g. in tests)."""
    config = OmegaConf.to_container(cfg, resolve=True)
    study = get_method(cfg.study)
    ctx = open_context(cfg, Path(output_dir), config, experiment=str(cfg.experiment_name))
    previous_threads = torch.get_num_threads()
    threads = cfg.get("threads")
    if threads:
        if int(threads) < 1:
            raise ValueError(f"threads: expected a positive integer or null, got {threads}")
        torch.set_num_threads(int(threads))
    if cfg.get("retain_freed_memory"):
        retain_freed_memory()
    try:
        study(ctx)
        ctx.results.save()
    finally:
        ctx.logger.close()
        torch.set_num_threads(previous_threads)
    log.info("results written to %s", ctx.output_dir)
    return ctx.results


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="config")
def main(cfg: DictConfig) -> None:
    run_study(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    main()
