"""Run-indexed random streams: the data (and particle draws) of Monte Carlo run i depend on the seed
and i's block only, so any split of the runs over chunks or workers gives bit-identical tables."""

from __future__ import annotations

import json

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from experiments.harness import cat_runs, open_context
from experiments.run import CONFIG_DIR, run_study
from tests.experiments.test_chunking import _assert_same


def _compose(name: str, *overrides: str):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return compose("config", overrides=[f"experiment={name}", "progress=false", "logger=none", "figures=false",
                                                    *overrides])


def _ctx(tmp_path, *overrides):
    cfg = _compose("imm_baseline", *overrides)
    return open_context(cfg, tmp_path, OmegaConf.to_container(cfg, resolve=True), "imm_baseline")


def test_a_runs_data_depend_on_its_block_only(tmp_path):
    from hydra.utils import instantiate

    ctx = _ctx(tmp_path, "block_runs=4")
    scenario = instantiate(ctx.cfg.scenario, dtype=torch.float64)
    sim10, z10 = ctx.simulate_runs(scenario.simulate, 10, "data")  # blocks 4, 4, 2
    sim12, z12 = ctx.simulate_runs(scenario.simulate, 12, "data")  # blocks 4, 4, 4
    assert z10.shape[1] == 10 and sim10.states.shape[1] == 10 and sim10.initial_state.shape == (10, 2)
    assert torch.equal(z10[:, :8], z12[:, :8]) and torch.equal(sim10.modes[:, :8], sim12.modes[:, :8])
    assert torch.equal(sim10.initial_mode[:8], sim12.initial_mode[:8])
    assert not torch.equal(z10[:, 8:], z12[:, 8:10])  # the last block of 10 has 2 runs: its own draws
    # blocks are independent streams: block 1 differs from block 0, and a different key differs
    assert not torch.equal(z12[:, :4], z12[:, 4:8])
    other, _ = ctx.simulate_runs(scenario.simulate, 8, "other key")
    assert not torch.equal(other.states, sim12.states[:, :8])


def test_cat_runs_joins_tuples_and_named_tuples():
    from torchmm.multimodel import MultiRate

    a = MultiRate(torch.zeros(3, 2, 1), torch.ones(3, 2, 1))
    b = MultiRate(torch.zeros(3, 1, 1), torch.ones(3, 1, 1))
    joined = cat_runs([(a, torch.zeros(3, 2)), (b, torch.zeros(3, 1))])
    assert isinstance(joined[0], MultiRate) and joined[0].source.shape == (3, 3, 1) and joined[1].shape == (3, 3)
    with pytest.raises(TypeError, match="cat_runs"):
        cat_runs([object(), object()])


FAST = {
    "imm_baseline": [],
    "imm_baseline_particle": ["mode_filter=particle", "mode_filter.num_particles=64"],
    "imm_analysis": ["debug=imm_analysis"],
    "imm_tf": ["debug=imm_tf", "rs_sweep=[1.0]", "scenario.steps=40"],
    "learn_dynamics": ["debug=learn_dynamics"],
    "mevsmm": ["debug=mevsmm"],  # particle filters, one stream per block: chunk_runs changes nothing
}


def _tables(tmp_path, name: str, *overrides: str) -> dict:
    study = name.replace("_particle", "")
    out = tmp_path / f"{name}{'_'.join(overrides)}"
    run_study(_compose(study, "mc_runs=7", "block_runs=2", *FAST[name], *overrides), out)
    tables = json.loads((out / "results.json").read_text())["tables"]
    return {k: v for k, v in tables.items() if "seconds_per_step" not in v["columns"]}


@pytest.mark.parametrize("name", sorted(FAST))
def test_every_chunking_gives_bit_identical_tables(name, tmp_path):
    """7 runs in blocks of 2 (2, 2, 2, 1): whole and chunks of 3 (particle filters: whole blocks) - equal
    bit for bit.

    learn_dynamics' learned IMM holds an MLP: its matrix products (BLAS) round differently with the
    batch size, so there the tables agree to rounding (1e-11), not bit for bit (docs/scaling.md)."""
    whole = _tables(tmp_path, name)
    assert whole
    for chunk in ("chunk_runs=3",):
        if name == "learn_dynamics":
            _assert_same(_tables(tmp_path, name, chunk), whole, chunk)  # to 1e-11
        else:
            assert _tables(tmp_path, name, chunk) == whole, chunk
