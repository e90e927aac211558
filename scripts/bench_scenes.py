"""Benchmark: PRDP against converged physics on the bundled scenes.

For each scene: one training run with the converged cap K_eps (the baseline)
and one with PRDP, same seed, same epochs, one after the other in this process
(so both see the same machine load). Recorded per run: the final validation
metric, cumulative forward + backward inner iterations, the solvers' time
(KSP solves only) and the whole training wall time, the K schedule; and the
ratios PRDP / baseline for each. For ``hybrid`` scenes also the validation
metric of the coarse solver alone (no correction), so the network's gain is on
record.

Writes ``bench-results/bench_scenes.json`` (``--out``) and prints one line per
scene. Run: ``python scripts/bench_scenes.py --scenes burgers-emulator,ns-hybrid``
(about 6 minutes on 2 cores).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fempdl import experiments, scene

from bench_common import comma_list, machine_info, write_json_atomically


def summary(run) -> dict:
    last = run.rows[-1]
    return {"final_metric": run.final_metric, "total_iterations": run.total_iterations,
            "solve_time": last["solve_time"], "wall_time": run.wall_time, "k_schedule": run.k_schedule,
            "epochs": len(run.rows)}


def bench_scene(name: str) -> dict:
    sc = scene.load(name)
    base = experiments.run(sc, "converged")
    prdp = experiments.run(sc, "prdp", k_eps_value=base.k_eps)
    out = {"k_eps": base.k_eps, "converged": summary(base), "prdp": summary(prdp)}
    out["ratios"] = {key: out["prdp"][key] / out["converged"][key]
                     for key in ("final_metric", "total_iterations", "solve_time", "wall_time")}
    if sc.task == "hybrid":
        task = experiments.build_task(sc, experiments.solver_options(sc, 1))
        out["uncorrected_metric"] = task.uncorrected_metric
        task.close()
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", type=comma_list(str), default=["burgers-emulator", "ns-hybrid"])
    parser.add_argument("--out", type=Path, default=Path("bench-results/bench_scenes.json"))
    args = parser.parse_args(argv)
    results = {"machine": machine_info(), "scenes": {}}
    for name in args.scenes:
        results["scenes"][name] = r = bench_scene(name)
        write_json_atomically(results, args.out)
        ratio = r["ratios"]
        print(f"{name}: K_eps {r['k_eps']}, PRDP K {r['prdp']['k_schedule']}; PRDP / converged: metric "
              f"{ratio['final_metric']:.2f}x, iterations {ratio['total_iterations']:.2f}x, solver time "
              f"{ratio['solve_time']:.2f}x, wall time {ratio['wall_time']:.2f}x", flush=True)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
