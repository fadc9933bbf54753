"""What the continuum elements cost: one implicit frame of a draping Cusick-size disc with each membrane (springs,
element) and bending (springs, stencil) choice, as a ratio to springs + springs measured in the same run.

    python benchmarks/bench_materials.py [--rings 32] [--frames 8] [--out benchmarks/results/bench_materials]

Writes <out>.md and <out>.json. Each case runs `frames` frames of 1/60 s (2 implicit substeps, tolerance 1e-3, the
solver's defaults) after one warm-up frame, on the device Warp picks ("cuda:0" where there is one).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import time

import numpy as np
import warp as wp

import cloth_warp as cw

CASES = [("springs", "springs"), ("element", "springs"), ("springs", "stencil"), ("element", "stencil")]


def run_case(membrane: str, bending: str, rings: int, frames: int, device) -> dict:
    b = cw.ModelBuilder()
    rot = cw.quat_from_axis_angle((1.0, 0.0, 0.0), -90.0)
    cloth = b.add_cloth_disc(radius=0.15, rings=rings, material="cotton", rotation=rot, position=(0.0, 0.5, 0.0),
                             membrane=membrane, bending=bending)
    b.add_sphere((0.0, 0.4, 0.0), 0.09)
    model = b.finalize(device)
    sim = cw.Simulator(model, cw.SolverImplicitEuler(model), fps=60, substeps=2)
    sim.step_frame()
    wp.synchronize_device(device)
    iterations = 0
    start = time.perf_counter()
    for _ in range(frames):
        sim.step_frame()
        iterations += sim.solver.last_iterations
    wp.synchronize_device(device)
    seconds = (time.perf_counter() - start) / frames
    return {"membrane": membrane, "bending": bending, "particles": cloth.topology.particle_count, "ms_per_frame": 1e3 * seconds,
            "cg_iterations_last_substep": iterations / frames}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rings", type=int, default=32)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default="benchmarks/results/bench_materials")
    args = ap.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    rows = [run_case(m, bnd, args.rings, args.frames, device) for m, bnd in CASES]
    reference = rows[0]["ms_per_frame"]
    for r in rows:
        r["ratio"] = r["ms_per_frame"] / reference
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"device": str(device), "machine": platform.processor() or platform.machine(), "rings": args.rings, "frames": args.frames}
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    lines = [f"# Membrane and bending choices: one implicit frame ({device}, disc of {rows[0]['particles']} particles on a ball)",
             "", f"`python benchmarks/bench_materials.py --rings {args.rings} --frames {args.frames}`", "",
             "| membrane | bending | ms / frame | ratio to springs + springs | CG iterations (last substep) |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['membrane']} | {r['bending']} | {r['ms_per_frame']:.1f} | {r['ratio']:.2f} | {r['cg_iterations_last_substep']:.0f} |")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return np.array([r["ratio"] for r in rows])


if __name__ == "__main__":
    main()
