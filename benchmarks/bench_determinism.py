"""Benchmark: are two runs of a scene bit-identical on a device, and what does Warp's deterministic mode cost?

For each scene, R runs in fresh processes (each compiles or loads its kernels itself) per mode:
- `default`: Warp's default (`wp.config.deterministic = NOT_GUARANTEED`): floating-point atomics (force
  scatters, the CG product, broad-phase counters) land in whatever order the device runs them;
- `run_to_run`: `wp.config.deterministic = RUN_TO_RUN`, set before any kernel module loads, so every module is
  built with Warp's ordered reductions for the atomics that support them.
Each run simulates W warm-up + F frames as `cloth-warp run` builds the scene (benchmarks/bench_step.py's Bench),
recording a SHA-256 of every frame's positions and the median ms/frame of the last F frames. Reported per scene and
mode: whether all R runs gave the same bytes in every frame, the first frame where they differ, the largest
position difference at the end [m], and the ms/frame; the cost is the ratio run_to_run / default in one run of
this script. On the CPU both modes must be bit-identical (Warp's CPU kernels run serially).

Run:  python benchmarks/bench_determinism.py --device cuda:0 --scenes pile drape_sphere hanging_cloth --frames 60
      python benchmarks/bench_determinism.py --device cpu --scenes pile --frames 10 --out /tmp/det.md
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import pathlib
import platform
import statistics
import subprocess
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
TAG = "@@bench_determinism "
MODES = {"default": "NOT_GUARANTEED", "run_to_run": "RUN_TO_RUN"}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["pile", "drape_sphere", "hanging_cloth"], help="shipped scene names")
    p.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    p.add_argument("--frames", type=int, default=60, help="frames per run after warm-up (default 60)")
    p.add_argument("--warmup", type=int, default=3, help="frames before the timed ones (their hashes are compared too)")
    p.add_argument("--runs", type=int, default=2, help="runs per scene and mode (default 2)")
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="scene override, as `cloth-warp run --set`")
    p.add_argument("--out", default=None, help="default benchmarks/results/bench_determinism[_cuda].md (and .json)")
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # internal: JSON of one run
    return p.parse_args(argv)


def worker(spec: dict) -> None:
    """One run: set the mode, build the scene, step, hash every frame, save the last positions."""
    import numpy as np
    import warp as wp

    wp.config.quiet = True
    wp.config.deterministic = getattr(wp.DeterministicMode, MODES[spec["mode"]])
    wp.init()
    sys.path.insert(0, str(HERE))
    from bench_step import Bench

    bench = Bench(spec["scene"], spec["device"], spec["overrides"])
    hashes, times = [], []
    for i in range(spec["warmup"] + spec["frames"]):
        s = bench.frame()
        if i >= spec["warmup"]:
            times.append(s)
        hashes.append(hashlib.sha256(bench.sim.positions().tobytes()).hexdigest()[:16])
    np.save(spec["positions"], bench.sim.positions())
    print(TAG + json.dumps({"hashes": hashes, "ms_frame": 1e3 * statistics.median(times), "particles": bench.model.particle_count,
                            "captured": bool(getattr(bench.sim, "capture", False))}), flush=True)


def run_once(scene: str, mode: str, args, positions: str) -> dict:
    spec = {"scene": scene, "mode": mode, "device": args.device, "overrides": args.overrides, "frames": args.frames,
            "warmup": args.warmup, "positions": positions}
    p = subprocess.run([sys.executable, str(pathlib.Path(__file__).resolve()), "--worker", json.dumps(spec)],
                       capture_output=True, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    for line in p.stdout.splitlines():
        if line.startswith(TAG):
            return json.loads(line[len(TAG):])
    return {"error": (p.stderr.strip().splitlines() or [f"exit {p.returncode}"])[-1]}


def compare(runs: list[dict], finals: list) -> dict:
    """Same bytes in every frame? First differing frame; largest end-position difference [m]."""
    import numpy as np

    first = None
    for i, frame in enumerate(zip(*(r["hashes"] for r in runs))):
        if len(set(frame)) > 1:
            first = i
            break
    diff = max(float(np.abs(f - finals[0]).max()) for f in finals[1:]) if len(finals) > 1 else 0.0
    return {"identical": first is None, "first_diff_frame": first, "max_end_diff_m": diff,
            "ms_frame": statistics.median(r["ms_frame"] for r in runs), "particles": runs[0]["particles"],
            "captured": runs[0]["captured"]}


def main():
    args = parse_args()
    if args.worker:
        return worker(json.loads(args.worker))
    import numpy as np

    sys.path.insert(0, str(HERE.parent))
    from cloth_warp.cli import parse_set

    args.overrides = parse_set(args.set) or None
    rows = []
    with tempfile.TemporaryDirectory(prefix="cw_det_") as tmp:
        for scene in args.scenes:
            row = {"scene": scene}
            for mode in args.modes:
                t = time.perf_counter()
                runs, finals = [], []
                for k in range(args.runs):
                    path = os.path.join(tmp, f"{scene}_{mode}_{k}.npy")
                    r = run_once(scene, mode, args, path)
                    if "error" in r:
                        row[mode] = r
                        break
                    runs.append(r)
                    finals.append(np.load(path))
                else:
                    row[mode] = compare(runs, finals)
                print(f"{scene} {mode}: {row[mode]}  ({time.perf_counter() - t:.0f} s)", flush=True)
            rows.append(row)
    write_report(args, rows)


def write_report(args, rows):
    import warp as wp

    argv = " ".join(sys.argv[1:])
    cuda = args.device.startswith("cuda")
    lines = ["# bench_determinism: two runs of a scene, bit for bit? and what Warp's deterministic mode costs", "",
             f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, Warp {wp.__version__}, "
             f"device {args.device}. Command: `python benchmarks/bench_determinism.py {argv}`", "",
             f"{args.runs} runs per scene and mode, each in a fresh process: {args.warmup} + {args.frames} frames, every frame's "
             "positions hashed; ms/frame is the median of the last frames (median over runs).", "",
             "| scene | particles | captured | mode | runs identical | first differing frame | max end difference [m] | ms/frame | cost |",
             "|---|---:|---|---|---|---:|---:|---:|---:|"]
    for r in rows:
        base = r.get("default", {}).get("ms_frame")
        for mode in args.modes:
            m = r.get(mode, {})
            if "error" in m:
                lines.append(f"| {r['scene']} | | | {mode} | failed: {m['error']} | | | | |")
                continue
            cost = f"{m['ms_frame'] / base:.2f}" if base else ""
            lines.append(f"| {r['scene']} | {m['particles']} | {'yes' if m['captured'] else 'no'} | {mode} | "
                         f"{'yes' if m['identical'] else 'no'} | {'' if m['first_diff_frame'] is None else m['first_diff_frame']} | "
                         f"{m['max_end_diff_m']:.3g} | {m['ms_frame']:.2f} | {cost} |")
    out = pathlib.Path(args.out) if args.out else HERE / "results" / f"bench_determinism{'_cuda' if cuda else ''}.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(json.dumps({"command": f"python benchmarks/bench_determinism.py {argv}", "rows": rows}, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
