"""Benchmark: `cloth-warp sweep` on a local Dask cluster - throughput with 1 and 2 workers, and the sweep's overhead per run.

The same variants (a scene and a swept key, ``--seeds``) are run three ways, in one process's turn on the same machine:

1. direct: one ``cloth-warp run`` subprocess per variant, one after the other (what a shell loop does), before and
   after the sweeps (their mean);
2. the sweep with one worker (``cloth_warp.sweep.run_sweep``: a LocalCluster, a manifest, the results table);
3. the sweep with two workers;
4. with ``--batch K``, also the sweep with two workers and ``--batch K`` (each worker steps K variants as batched worlds
   in one process; a scene without self-collision).

Reported: wall seconds of each, the sweep's overhead per run ((2) - (1)) / (1) (cluster start, scheduling, manifest
and table writes; each run is the same subprocess either way), and the throughput ratio (2) / (3). Targets (issue
"many cloths"): overhead <= 5 %, 2 workers >= 1.8x one on a 2-core machine.

Run:  python benchmarks/bench_sweep.py                     (pile, 12 runs of ~6 s; ~4 min on 2 cores)
      python benchmarks/bench_sweep.py --frames 100 --seeds 1
      python benchmarks/bench_sweep.py --scene hanging_cloth --set 'cloth.grid.resolution=[32,32]' --frames 60 --batch 6 \
          --out benchmarks/results/bench_sweep_batch.md
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import platform
import shutil
import subprocess
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))


def _best_split(times: list[float]) -> float:
    """The makespan of the best split of `times` over two workers (exhaustive: sweeps here are small)."""
    total, best = sum(times), sum(times)
    for mask in range(1 << len(times)):
        one = sum(t for i, t in enumerate(times) if mask >> i & 1)
        best = min(best, max(one, total - one))
    return best


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="pile")
    p.add_argument("--param", default="material.preset=cotton,silk,wool")
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--set", action="append", default=[], metavar="KEY.PATH=VALUE", help="a scene key every run sets")
    p.add_argument("--batch", type=int, default=None, help="also the sweep with two workers and --batch K")
    p.add_argument("--out", default=str(HERE / "results" / "bench_sweep.md"))
    args = p.parse_args()

    from cloth_warp.cli import parse_set
    from cloth_warp.sweep import Sweep, parse_params, run_command, run_sweep

    overrides = parse_set(args.set)
    sweep = Sweep(args.scene, parse_params([args.param]), seeds=args.seeds, overrides=overrides, frames=args.frames)
    runs = sweep.runs()
    scene = str((ROOT / "scenes" / f"{args.scene}.toml").resolve())
    work = pathlib.Path(tempfile.mkdtemp(prefix="cw_bench_sweep_"))
    try:
        def run_direct(tag):
            t = time.perf_counter()
            for run in runs:
                d = work / tag / run.id
                d.mkdir(parents=True)
                subprocess.run(run_command(scene, run.values, overrides, d, args.frames, None, False), check=True, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
            return time.perf_counter() - t

        directs = [run_direct("direct_before")]
        walls = {}
        for workers in (1, 2):
            t = time.perf_counter()
            report = run_sweep(sweep, work / f"sweep{workers}", workers=workers)
            walls[workers] = time.perf_counter() - t
            assert report.complete and report.done == len(runs), report
            if workers == 1:
                per_run = [e["wall_s"] for e in json.loads(report.manifest.read_text())["runs"].values()]
        if args.batch:
            t = time.perf_counter()
            report = run_sweep(dataclasses.replace(sweep, batch=args.batch), work / "sweep_batch", workers=2)
            walls["batch"] = time.perf_counter() - t
            assert report.complete and report.done == len(runs), report
        directs.append(run_direct("direct_after"))  # before and after the sweeps: the machine's drift falls on both
    finally:
        shutil.rmtree(work, ignore_errors=True)
    direct = sum(directs) / 2
    result = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
        "command": "python benchmarks/bench_sweep.py " + " ".join(sys.argv[1:]),
        "scene": args.scene, "param": args.param, "seeds": args.seeds, "frames": args.frames, "runs": len(runs),
        "direct_s": direct, "direct_before_after_s": directs, "sweep_1_worker_s": walls[1], "sweep_2_workers_s": walls[2],
        "overhead_per_run": walls[1] / direct - 1.0, "speedup_2_workers": walls[1] / walls[2],
        "run_s": per_run, "bound_2_workers": sum(per_run) / max(max(per_run), _best_split(per_run)),
        "batch": args.batch, "sweep_2_workers_batch_s": walls.get("batch"),
        "speedup_batch": walls[2] / walls["batch"] if args.batch else None,
    }
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")
    lines = [
        "# bench_sweep: `cloth-warp sweep` on a local Dask cluster",
        "",
        f"Machine: {result['machine']}. Command: `{result['command']}`",
        "",
        f"{len(runs)} runs: `{args.scene}` with `--param {args.param}`" + (f" `--seeds {args.seeds}`" if args.seeds else "")
        + "".join(f" `--set {x}`" for x in args.set)
        + f", {args.frames} frames each; every run is a `cloth-warp run` subprocess (the direct loop's too).",
        "",
        "| way | wall [s] | per run [s] |",
        "|---|---:|---:|",
        f"| direct (`cloth-warp run` one after the other; mean of a loop before the sweeps, {directs[0]:.1f} s, and one after, "
        f"{directs[1]:.1f} s) | {direct:.1f} | {direct / len(runs):.2f} |",
        f"| sweep, 1 worker | {walls[1]:.1f} | {walls[1] / len(runs):.2f} |",
        f"| sweep, 2 workers | {walls[2]:.1f} | {walls[2] / len(runs):.2f} |",
        *([f"| sweep, 2 workers, `--batch {args.batch}` (batched worlds) | {walls['batch']:.1f} | {walls['batch'] / len(runs):.2f} |"]
          if args.batch else []),
        "",
        f"Sweep overhead per run (1 worker against direct): {100 * result['overhead_per_run']:+.1f} % (target <= 5 %). "
        f"2 workers against 1: {result['speedup_2_workers']:.2f}x (target >= 1.8x).",
        "",
        f"The runs took {min(per_run):.1f}-{max(per_run):.1f} s each (1 worker); the best split of them over two workers "
        f"bounds the ratio at {result['bound_2_workers']:.2f}x (the last runs of a sweep leave a worker idle).",
        "",
        *([f"`--batch {args.batch}` against one run per process, both with 2 workers: {result['speedup_batch']:.2f}x (a batch "
           f"starts one process, loads the kernels once and steps its worlds together).", ""] if args.batch else []),
    ]
    out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
