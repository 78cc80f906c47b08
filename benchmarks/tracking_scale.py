"""Where each association method stops paying (issue 46): the tracking study's crossing targets over a
grid of target counts x clutter rates, every method on the same scans: GOSPA (accuracy) and run-scans per
second (speed).

    .venv/bin/python benchmarks/tracking_scale.py                        # 4, 8, 12, 20 targets x 5, 20, 50
    .venv/bin/python benchmarks/tracking_scale.py --targets 3 --clutter 2 --runs 4 --steps 8

The scenario is conf/experiment/tracking.yaml's (targets on a circle of 300 m crossing at its centre at
mid-run, manoeuvring before; P_D 0.9, R 25 m^2; clutter over a 1 km square), its estimators on the IMM of
the truth's three acceleration modes: the exact JPDA (at most 12 targets), JPDA by loopy belief propagation,
the k-best JPDA (``--k`` events), the MHT (``--hypotheses``, 3-scan pruning), GNN and per-target PDA. Each
cell: GOSPA (c = 30 m, p = 2, averaged over scans and runs) and run-scans per second (float64, the
machine's threads). ``-`` where a method does not apply (the exact JPDA beyond 12 targets).

The last line: ``cells=<number of grid cells> best=<method with the lowest mean GOSPA rank>``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

METHODS = {"exact JPDA": "IMM-JPDAF", "LBP JPDA": "IMM-JPDAF-LBP", "k-best JPDA": "IMM-JPDAF-kbest",
           "MHT": "IMM-MHT", "GNN": "GNN-IMM", "PDA": "IMM-PDAF"}


def section(targets: int, clutter: float, args) -> OmegaConf:
    """conf/experiment/tracking.yaml's tracking section with the grid cell's sizes."""
    conf = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "experiment" / "tracking.yaml").tracking
    conf.targets, conf.clutter_rate, conf.steps = targets, clutter, args.steps
    conf.maneuver_start, conf.maneuver_stop = args.steps // 6, args.steps // 3
    conf.jpda.k, conf.mht.hypotheses, conf.mht.k = args.k, args.hypotheses, args.hypotheses
    conf.estimators = [name for name in METHODS.values() if name != "IMM-JPDAF" or targets <= 12]
    return conf


def main() -> None:
    from experiments.studies import tracking
    from torchmm import GaussianBelief, run_filter
    from torchmm.metrics import gospa

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--targets", type=int, nargs="+", default=[4, 8, 12, 20])
    parser.add_argument("--clutter", type=float, nargs="+", default=[5.0, 20.0, 50.0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--k", type=int, default=100)
    parser.add_argument("--hypotheses", type=int, default=10)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    dt = torch.float64
    header = "| targets | clutter | " + " | ".join(METHODS) + " |"
    print("GOSPA (m) / run-scans per second")
    print(header)
    print("|" + "---|" * (2 + len(METHODS)))
    ranks = {m: [] for m in METHODS}
    for N in args.targets:
        for rate in args.clutter:
            t = section(N, rate, args)
            truth, z, x0, present = tracking.simulate(t, args.runs, torch.Generator().manual_seed(0))
            P0 = torch.diag(torch.tensor(list(t.P0), dtype=dt))
            cells, scores = [], {}
            for label, name in METHODS.items():
                if name == "IMM-JPDAF" and N > 12:
                    cells.append("-")
                    continue
                est = tracking.estimators(t, dt, targets=N)[name]
                belief = est.initial(GaussianBelief(x0, P0))
                scans = z.unsqueeze(-3) if est.per_track else z
                run_filter(est.filter, belief, scans[:2], record="estimate")  # (warm-up)
                tic = time.perf_counter()
                with torch.no_grad():
                    traj = run_filter(est.filter, belief, scans, record="estimate")
                seconds = time.perf_counter() - tic
                position = traj.belief.estimate().mean[..., [0, 2]]
                d = gospa(position, truth[..., [0, 2]], c=30.0, p=2.0, truth_present=present)["distance"]
                scores[label] = float(d.mean())
                cells.append(f"{scores[label]:.1f} / {args.steps * args.runs / seconds:.0f}")
            order = sorted(scores, key=scores.get)
            for i, label in enumerate(order):
                ranks[label].append(i)
            print(f"| {N} | {rate:g} | " + " | ".join(cells) + " |", flush=True)
    mean_rank = {m: sum(r) / len(r) for m, r in ranks.items() if r}
    print(f"cells={len(args.targets) * len(args.clutter)} best={min(mean_rank, key=mean_rank.get).replace(' ', '_')}")


if __name__ == "__main__":
    main()
