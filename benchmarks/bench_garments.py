"""Benchmark: garments on the mannequin, as `cloth-warp run` builds the shipped scenes.

For each scene (default: the T-shirt, the dress and the layered outfit) at the scenes' own edge lengths or at
`--edge` [m] (every garment of the scene), reported: particles, the time to build the model (meshing, the dressing
and the settle, on one core), ms per frame of the walk (median over `--frames` frames), CG iterations per frame, the
largest strain at a frame's end, the widest seam gap in any frame, what the passes after the solve still do over the last
20 frames (collider contacts the colliders pass resolved, proximity and CCD impulses of self-collision, per frame), and,
with the body held still (`motion = "still"`,
`--rest` frames after the settle), the largest particle speed over the last 20 frames (at rest means <= 1 mm/s, issue
18's target) and where it is.

Run:  python benchmarks/bench_garments.py                                  (a few minutes on 2 cores)
      python benchmarks/bench_garments.py --scenes tshirt_walk --edge 0.012 --frames 30 --rest 0
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import statistics
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
TAIL = 20


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["tshirt_walk", "dress_walk", "layered_walk"])
    p.add_argument("--edge", type=float, default=None, help="edge length of every garment [m] (default: the scene's)")
    p.add_argument("--frames", type=int, default=60, help="frames of the walk timed (0: skip the walk)")
    p.add_argument("--rest", type=int, default=300, help="frames in the still pose for the rest speed (0: skip)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a scene key for every run, as `cloth-warp run --set` takes it (repeatable)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_garments.md"))
    return p.parse_args(argv)


def overrides_for(scene_name: str, edge: float | None, still: bool, sets: list[str] = ()) -> dict:
    from cloth_warp.cli import parse_set
    from cloth_warp.runner import find_scene
    from cloth_warp.scene import load_scene

    out = parse_set(list(sets))
    scene = load_scene(find_scene(scene_name))
    if edge is not None:
        out["cloth.edge_length"] = edge
        for k in range(len(scene.data.get("garments", []))):
            out[f"garments[{k}].edge_length"] = edge
    if still:
        for k, col in enumerate(scene.data.get("colliders", [])):
            if col.get("type") == "mannequin":
                out[f"colliders[{k}].motion"] = "still"
    return out


def run(scene_name: str, edge: float | None, frames: int, still: bool, device: str, sets: list[str] = ()) -> dict:
    import warp as wp

    from cloth_warp.runner import find_scene, load_kernels
    from cloth_warp.scene import build_model, build_solver, load_scene
    from cloth_warp.sewing import seam_ends, seam_gap
    from cloth_warp.simulator import Simulator

    scene = load_scene(find_scene(scene_name), overrides_for(scene_name, edge, still, sets))
    t = time.perf_counter()
    model = build_model(scene, device)
    build_s = time.perf_counter() - t
    solver = build_solver(scene, model)
    load_kernels(solver, model.device)
    sim = Simulator(model, solver, fps=float(scene.get("output.fps")), substeps=int(scene.get("solver.substeps")))
    ends = seam_ends(model)
    ms, iterations, speeds, strain, gap, pass_work = [], [], [], 0.0, 0.0, []
    for _ in range(frames):
        t = time.perf_counter()
        stats = sim.step_frame()
        wp.synchronize()
        ms.append(1e3 * (time.perf_counter() - t))
        report = sim.frame_report
        iterations.append(report.iterations)
        counters = report.counters()
        colliders = report.passes.get("colliders")
        pass_work.append((colliders.contacts if colliders else 0, counters.get("self_proximity", 0) + counters.get("self_ccd", 0),
                          colliders.samples if colliders else 0))
        speeds.append(stats.max_speed)
        strain = max(strain, stats.max_strain)
        gap = max(gap, seam_gap(model, sim.positions(), ends))
    out = {"scene": scene_name, "motion": "still" if still else "walk", "particles": model.particle_count, "build_s": build_s,
           "frames": frames, "ms_per_frame": statistics.median(ms), "cg_per_frame": statistics.mean(iterations),
           "max_strain": strain, "seam_gap_mm": 1e3 * gap,
           "pass_contacts": statistics.mean(w[0] for w in pass_work[-TAIL:]), "self_impulses": statistics.mean(w[1] for w in pass_work[-TAIL:]),
           "pass_samples": statistics.mean(w[2] for w in pass_work[-TAIL:])}
    if still:
        v = np.linalg.norm(sim.state.particle_qd.numpy(), axis=1)
        out.update(rest_speed_mm_s=1e3 * max(speeds[-TAIL:]), rest_speed_median_mm_s=1e3 * statistics.median(speeds[-TAIL:]),
                   fastest_at=[round(float(c), 3) for c in sim.positions()[int(np.argmax(v))]])
    return out


def main(argv=None):
    args = parse_args(argv)
    sys.path.insert(0, str(ROOT))
    rows = []
    for name in args.scenes:
        if args.frames:
            rows.append(run(name, args.edge, args.frames, False, args.device, args.set))
            print(json.dumps(rows[-1]), flush=True)
        if args.rest:
            rows.append(run(name, args.edge, args.rest, True, args.device, args.set))
            print(json.dumps(rows[-1]), flush=True)
    edge = f"{args.edge:g} m edges" if args.edge else "the scenes' edge lengths"
    lines = [f"# bench_garments ({args.device}, {edge}; Python {platform.python_version()})", "",
             "`python benchmarks/" + pathlib.Path(__file__).name + " " + " ".join(argv if argv is not None else sys.argv[1:]) + "`", "",
             "| scene | motion | particles | build (dress + settle) [s] | frames | ms/frame | CG it/frame | max strain | "
             "widest seam gap [mm] | pass work a frame, last 20 frames: collider contacts / self impulses / element samples | "
             "rest speed, last 20 frames: max / median [mm/s] |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        rest = (f"{r['rest_speed_mm_s']:.2f} / {r['rest_speed_median_mm_s']:.2f} (at {r['fastest_at']})"
                if "rest_speed_mm_s" in r else "")
        lines.append(f"| {r['scene']} | {r['motion']} | {r['particles']} | {r['build_s']:.0f} | {r['frames']} | {r['ms_per_frame']:.0f} | "
                     f"{r['cg_per_frame']:.0f} | {r['max_strain']:.4f} | {r['seam_gap_mm']:.3f} | "
                     f"{r.get('pass_contacts', float('nan')):.1f} / {r.get('self_impulses', float('nan')):.1f} / "
                     f"{r.get('pass_samples', float('nan')):.1f} | {rest} |")
    from reports import write_results

    write_results(args.out, lines + [""], rows)


if __name__ == "__main__":
    main()
