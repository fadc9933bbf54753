"""Benchmark: what the passes after an implicit step still change, step by step (issue 17's "count what they still do").

For each scene (default: the T-shirt, the dress and the layered outfit held still, as `bench_garments.py --rest`
holds them), after `--warmup` frames (recorded, as a run steps them) the next `--frames` frames are stepped eagerly
and every step's velocities are read after the integrator and after each pass in each round (the strain limiter,
sewing, colliders, self-collision; `SolverBase.step`): per pass, the particles whose velocity it changed by more than
1 mm/s, a step on average, and the largest change [mm/s]. A pass that moves what the solve balanced shows here even
where the frame's largest speed hides it (the T-shirt held still, 2026-11-29: the weld moved 91 particles a step by up
to 17.6 mm/s while each welded point was two particles of the solve).

Run:  python benchmarks/bench_pass_work.py                                   (a few minutes on one core)
      python benchmarks/bench_pass_work.py --scenes tshirt_walk --set solver.sewn_points=pass
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
MOVED = 1.0e-3  # [m/s] a pass "moved" a particle whose velocity it changed by more than this


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["tshirt_walk", "dress_walk", "layered_walk"])
    p.add_argument("--warmup", type=int, default=200, help="frames run before the ones traced")
    p.add_argument("--frames", type=int, default=10, help="frames traced, step by step")
    p.add_argument("--walk", action="store_true", help="keep the mannequin walking (default: held still)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a scene key for every run, as `cloth-warp run --set` takes it (repeatable)")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_pass_work.md"))
    return p.parse_args(argv)


def trace(scene_name: str, warmup: int, frames: int, still: bool, sets: list[str]) -> dict:
    import warp as wp

    from bench_garments import overrides_for
    from cloth_warp.runner import find_scene, load_kernels
    from cloth_warp.scene import build_model, build_solver, load_scene
    from cloth_warp.simulator import Simulator

    scene = load_scene(find_scene(scene_name), overrides_for(scene_name, None, still, sets))
    model = build_model(scene, "cpu")
    solver = build_solver(scene, model)
    load_kernels(solver, model.device)
    fps, substeps = float(scene.get("output.fps")), int(scene.get("solver.substeps"))
    sim = Simulator(model, solver, fps=fps, substeps=substeps)
    for _ in range(warmup):
        sim.step_frame()
    eager = Simulator(model, solver, fps=fps, substeps=substeps, capture=False)
    eager.restore(sim.checkpoint())
    passes = [p.name for p in solver.passes]
    repeat = any(p.corrector for p in solver.passes) and not all(p.corrector for p in solver.passes)
    stages = [f"{name}{r}" for r in range(solver.collision_rounds if repeat else 1) for name in passes]
    moved = {s: [] for s in stages}
    largest = {s: 0.0 for s in stages}
    step = solver.step

    def traced(state_in, state_out, control, dt):
        step(state_in, state_out, control, dt)
        v = solver.scratch("v_unlimited", wp.vec3, False).numpy()
        for k, s in enumerate(stages):
            after = state_out.particle_qd.numpy() if k == len(stages) - 1 else solver.scratch(f"v_{s}", wp.vec3, False).numpy()
            change = np.linalg.norm(after - v, axis=1)
            moved[s].append(int((change > MOVED).sum()))
            largest[s] = max(largest[s], float(change.max()))
            v = after

    solver.step = traced
    t = time.perf_counter()
    for _ in range(frames):
        eager.step_frame()
    steps = len(moved[stages[0]])
    return {"scene": scene_name, "motion": "still" if still else "walk", "warmup": warmup, "steps": steps,
            "trace_s": time.perf_counter() - t,
            "moved_per_step": {s: sum(m) / steps for s, m in moved.items()},
            "largest_mm_s": {s: 1e3 * largest[s] for s in stages},
            "total_per_step": sum(sum(m) for m in moved.values()) / steps}


def main(argv=None):
    args = parse_args(argv)
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "benchmarks"))
    rows = []
    for name in args.scenes:
        rows.append(trace(name, args.warmup, args.frames, not args.walk, args.set))
        print(json.dumps(rows[-1]), flush=True)
    lines = [f"# bench_pass_work (cpu; Python {platform.python_version()})", "",
             "`python benchmarks/" + pathlib.Path(__file__).name + " " + " ".join(argv if argv is not None else sys.argv[1:]) + "`", "",
             f"Particles whose velocity each pass changed by more than {1e3 * MOVED:g} mm/s, a step on average over the traced "
             "steps (the largest change [mm/s] in brackets); a pass's name ends with its round.", "",
             "| scene | motion | steps | per pass: particles a step (largest mm/s) | all passes, a step |", "|---|---|---|---|---|"]
    for r in rows:
        per = ", ".join(f"{s} {m:.1f} ({r['largest_mm_s'][s]:.1f})" for s, m in r["moved_per_step"].items())
        lines.append(f"| {r['scene']} | {r['motion']} | {r['steps']} | {per} | {r['total_per_step']:.1f} |")
    from reports import write_results

    write_results(args.out, lines + [""], rows)


if __name__ == "__main__":
    main()
