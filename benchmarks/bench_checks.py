"""Benchmark: what guards a frame, relative to the frame. The divergence check after every frame
(Diagnostics.measure, one kernel and a read of 5 numbers, plus DivergenceBounds.violation on the host) on
the hanging-cloth scene at 64^2 (implicit Euler, one step per frame) and a 32^2 semi-implicit grid
(64 substeps, captured as a graph); the cache writer's checks are in bench_cache.py.

Run:  python benchmarks/bench_checks.py            (~1 min on 2 cores)
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
CASES = {  # name: (scene overrides, frames)
    "hanging 64^2 implicit": ({"cloth.grid.resolution": [64, 64]}, 20),
    "hanging 32^2 semi-implicit, 64 substeps, captured": ({"cloth.grid.resolution": [32, 32], "solver.integrator": "symplectic_euler",
                                                           "solver.substeps": 64}, 20),
}


def measure(overrides, frames, reps=50):
    import cloth_warp as cw
    from cloth_warp.runner import load_kernels
    from cloth_warp.scene import build_model, build_solver, load_scene

    scene = load_scene(ROOT / "scenes" / "hanging_cloth.toml", overrides)
    model = build_model(scene, "cpu")
    solver = build_solver(scene, model)
    load_kernels(solver, model.device)
    sim = cw.Simulator(model, solver, fps=60.0, substeps=int(scene.get("solver.substeps")))
    sim.step_frame()  # warm-up (graph capture)
    per_frame = []
    for _ in range(frames):
        t = time.perf_counter()
        sim.step_frame()
        per_frame.append(time.perf_counter() - t)
    t = time.perf_counter()
    for _ in range(reps):
        stats = sim.diagnostics.measure(sim.state)
        sim.bounds.violation(stats)
    check = (time.perf_counter() - t) / reps
    frame = float(np.median(per_frame))
    return {"frame_ms": 1e3 * frame, "check_ms": 1e3 * check, "ratio": check / frame, "captured": bool(sim.capture)}


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(HERE / "results" / "bench_checks.md"))
    args = p.parse_args()
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    rows = {name: measure(*case) for name, case in CASES.items()}
    print(json.dumps(rows))
    lines = ["# Divergence check per frame (Diagnostics.measure + DivergenceBounds.violation) vs the frame", "",
             "`python benchmarks/bench_checks.py`; median frame over 20 frames, check averaged over 50 calls on the same "
             "state, one process, 2-core CPU machine.", "",
             "| case | frame | check | check / frame |", "|---|---|---|---|"]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['frame_ms']:.1f} ms | {r['check_ms']:.3f} ms | {100 * r['ratio']:.2f} % |")
    pathlib.Path(args.out).write_text("\n".join(lines) + "\n")
    pathlib.Path(args.out).with_suffix(".json").write_text(json.dumps(rows, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
