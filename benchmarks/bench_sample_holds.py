"""Benchmark: a coarse cloth over a faceted ball, with and without the element samples' heights held in the solve.

A 1 m cotton square (12^2, 16^2 or 24^2) dropped over a mesh ball (an icosphere of 2, 3 or 4 subdivisions, radius 0.25 m,
turned at random) onto the ground, the contacts and their friction in the implicit solve, self-collision off: its
edges are about as long as the ball's facets, so its edges and triangles cut the ball between particles that are
clear of it, and the colliders pass's element samples push them out (kernels/collide.py `collide_element_samples`).
Each run twice: as shipped (`sample_holds`: a particle the samples pushed keeps, as a contact in the solve, the height
they left it at) and without (`--set`-free: the solver's `sample_holds=False`). Reports the rest speed (the median of
the last 20 frames' largest particle speed; at rest: <= 1 mm/s) and the samples pushed a frame over those frames.

    python benchmarks/bench_sample_holds.py            (36 runs, ~6 min on one core)
"""

from __future__ import annotations

import argparse
import pathlib
import platform
import statistics
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

CASES = [(sub, res, seed) for sub in (2, 3, 4) for res in (12, 16, 24) for seed in (0, 1)]
"""(icosphere subdivisions, grid resolution, seed)"""
TAIL = 20
REST = 1.0e-3


def faceted_ball_drape(subdivisions: int, resolution: int, seed: int, sample_holds: bool = True, device: str = "cpu"):
    """The run's simulator: the cloth 12 cm above a mesh ball (turned at random by `seed`, the cloth moved by up to 5
    cm), 60 fps, 2 substeps. Also tests/test_colliders.py's case."""
    import numpy as np
    import trimesh

    import cloth_warp as cw

    rng = np.random.default_rng(seed)
    ball = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.25)
    turn = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(resolution, resolution), size=(1.0, 1.0), material="cotton",
                     rotation=cw.quat_from_axis_angle((1, 0, 0), -90.0), position=(-0.5 + rng.uniform(-0.05, 0.05), 0.62, 0.5))
    b.add_collider_mesh(np.asarray(ball.vertices) @ turn.T, ball.faces, position=(0.0, 0.3, 0.0), name="ball", thickness=0.004,
                        friction=0.4)
    b.add_ground(friction=0.6)
    m = b.finalize(device)
    solver = cw.SolverImplicitEuler(m, collider_contacts="solve", contact_friction="solve", sample_holds=sample_holds)
    return cw.Simulator(m, solver, fps=60, substeps=2)


def run(case, sample_holds: bool, frames: int) -> dict:
    sim = faceted_ball_drape(*case, sample_holds=sample_holds)
    speeds, samples = [], []
    start = time.perf_counter()
    for _ in range(frames):
        speeds.append(sim.step_frame().max_speed)
        samples.append(sim.frame_report.passes["colliders"].samples)
    return {"case": list(case), "sample_holds": sample_holds, "speed": statistics.median(speeds[-TAIL:]),
            "samples": statistics.mean(samples[-TAIL:]), "samples_total": sum(samples),
            "ms": 1e3 * (time.perf_counter() - start) / frames}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=300, help="frames a run (60 fps)")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_sample_holds.md"))
    args = p.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    from reports import write_results

    rows = [(run(case, True, args.frames), run(case, False, args.frames)) for case in CASES]
    lines = ["# bench_sample_holds: a coarse cloth over a faceted ball, the samples' heights held in the solve or not", "",
             f"Machine: {platform.machine()}, Python {platform.python_version()}, Warp {wp.config.version}. Command: "
             f"`python benchmarks/bench_sample_holds.py" + (f" --frames {args.frames}" if args.frames != 300 else "") + "`. "
             f"{args.frames} frames a run at 60 fps; rest speed: the median of the last {TAIL} frames' largest particle "
             "speed (at rest: <= 1 mm/s); samples: element samples pushed a frame over those frames.", "",
             "| icosphere subdivisions | resolution | seed | held: rest speed [mm/s] | samples a frame | ms/frame "
             "| not held: rest speed [mm/s] | samples a frame | ms/frame |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for on, off in rows:
        s, r, k = on["case"]
        lines.append(f"| {s} | {r} | {k} | {1e3 * on['speed']:.2f} | {on['samples']:.1f} | {on['ms']:.1f} | "
                     f"{1e3 * off['speed']:.2f} | {off['samples']:.1f} | {off['ms']:.1f} |")
    rest_on = sum(on["speed"] <= REST for on, _ in rows)
    rest_off = sum(off["speed"] <= REST for _, off in rows)
    lines += ["", f"At rest: {rest_on} of {len(rows)} with the heights held, {rest_off} without."]
    write_results(args.out, lines, {"rows": [r for pair in rows for r in pair]})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
