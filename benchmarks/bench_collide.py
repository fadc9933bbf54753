"""Benchmark: the cost of collider contact relative to the rest of the step (drape over a sphere and the ground).

For each resolution the shipped `drape_sphere` scene (cotton over a 25 cm ball onto the ground, implicit
Euler, 2 steps per 1/60 s frame) runs `--warmup` frames to put the cloth in contact, then `--frames`
frames are timed three ways in the same process, from the same state: with collisions, without them
(`collisions=False`, the same solver and strain limiter), and the collision kernel alone (one launch per
step on the same arrays). Reported: ms per frame and per step, the collision pass's share, and contacts
per step. Self-collision is switched off here (benchmarks/bench_selfcollide.py measures it).

Run:  python benchmarks/bench_collide.py                  (32^2, 64^2, 128^2; ~3 min on 2 cores)
      python benchmarks/bench_collide.py --sizes 32 --frames 5 --out benchmarks/results/quick_collide.md
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--frames", type=int, default=10)
    p.add_argument("--warmup", type=int, default=40)
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default=None, help="default benchmarks/results/bench_collide[_cuda].md")
    return p.parse_args()


def device_name(device: str) -> str:
    import warp as wp

    return "CPU backend" if device == "cpu" else f"{device}, {wp.get_device(device).name}"


def measure(size: int, frames: int, warmup: int, device: str = "cpu") -> dict:
    import warp as wp

    import cloth_warp as cw
    from cloth_warp.scene import PASSES_ONLY, build_model, build_solver, load_scene

    # collider contact alone (bench_selfcollide.py measures self-collision), by the colliders pass after the step
    scene = load_scene(ROOT / "scenes" / "drape_sphere.toml", {**PASSES_ONLY, "cloth.grid.resolution": [size, size],
                                                               "collision.self_collision": False})
    model = build_model(scene, device)
    solver = build_solver(scene, model)
    sim = cw.Simulator(model, solver, fps=60, substeps=2)
    for _ in range(warmup):
        sim.step_frame()
    start = model.state(requires_grad=False)
    start.assign(sim.state)

    def timed(s) -> float:
        sim_b = cw.Simulator(model, s, fps=60, substeps=2)
        sim_b.state.assign(start)
        sim_b.time = sim.time
        wp.synchronize()
        t0 = time.perf_counter()
        for _ in range(frames):
            sim_b.step_frame()
        return (time.perf_counter() - t0) / frames

    with_ms = timed(solver) * 1e3
    contacts = solver.read_pass_reports()["colliders"].contacts / 2.0  # last frame, per step
    plain = build_solver(scene, model)
    plain.passes = tuple(p for p in plain.passes if p.name != "colliders")
    without_ms = timed(plain) * 1e3
    # the collision kernel alone, on the contact state (what one pass costs)
    x = model.state(requires_grad=False)
    control = model.control(requires_grad=False)
    reps = 20
    wp.synchronize()
    t0 = time.perf_counter()
    for _ in range(reps):
        solver.pass_named("colliders").apply(start.particle_q, start.particle_q, start.particle_qd, control, 1.0 / 120.0, x.particle_q, x.particle_qd)
    wp.synchronize()
    pass_ms = (time.perf_counter() - t0) / reps * 1e3
    return {"size": size, "particles": model.particle_count, "with_ms_frame": with_ms, "without_ms_frame": without_ms,
            "collision_pass_ms": pass_ms, "passes_per_step": solver.collision_rounds, "contacts_per_step": contacts}


def main():
    args = parse_args()
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    rows = [measure(n, args.frames, args.warmup, args.device) for n in args.sizes]
    lines = [
        "# Collider contact cost (drape_sphere: cotton over a sphere and the ground, implicit Euler, 2 steps/frame)",
        "",
        f"`python benchmarks/bench_collide.py --sizes {' '.join(map(str, args.sizes))} --frames {args.frames} --warmup {args.warmup}"
        f"{'' if args.device == 'cpu' else ' --device ' + args.device}` (device {device_name(args.device)}, one process; "
        "ratios are what to compare across machines).",
        "",
        "| grid | particles | ms/frame with collisions | ms/frame without | one collision pass [ms] | passes/step | "
        "collision share of the step | µs per particle per pass | contacts/step |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        share = 2 * r["passes_per_step"] * r["collision_pass_ms"] / r["with_ms_frame"]
        lines.append(f"| {r['size']}² | {r['particles']} | {r['with_ms_frame']:.1f} | {r['without_ms_frame']:.1f} | "
                     f"{r['collision_pass_ms']:.3f} | {r['passes_per_step']} | {100 * share:.1f} % | "
                     f"{1e3 * r['collision_pass_ms'] / r['particles']:.3f} | {r['contacts_per_step']:.0f} |")
    lines += ["", "The collision pass itself is the cost to read (share = 2 steps x passes x pass time / frame time). "
              "The two ms/frame columns start from the same draped state but do not stay comparable: without "
              "collisions the cloth falls through the ball, and its solver and strain-limiter work change "
              "(more at 64^2 and 128^2); with them the limiter also runs once more per step.", ""]
    text = "\n".join(lines)
    print(text)
    out = pathlib.Path(args.out or HERE / "results" / f"bench_collide{'' if args.device == 'cpu' else '_cuda'}.md")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
