"""Benchmark: garments on the mannequin, as `cloth-warp run` builds the shipped scenes.

For each scene (default: the T-shirt, the dress and the layered outfit) at the scenes' own edge lengths or at
`--edge` [m] (every garment of the scene), reported: particles, the time to build the model (meshing, the dressing
and the settle, on one core), ms per frame of the walk (median over `--frames` frames), CG iterations per frame, the
largest strain at a frame's end, the widest seam gap in any frame, what the passes after the solve still do over the last
20 frames (collider contacts the colliders pass resolved, proximity and CCD impulses of self-collision, per frame), and,
with the body held still (`motion = "still"`,
`--rest` frames after the settle), the largest particle speed over the last 20 frames (at rest means <= 1 mm/s, issue
18's target) and where it is.

With `--edges E1 E2 ...` the scenes run at each of those edge lengths, `--jobs` runs at a time, each in its own process,
and the table ends with how many of the runs held still came to rest (issue 18's garments at other edge lengths: their
end states are chaotic, so a count over edge lengths says more than one run).

Run:  python benchmarks/bench_garments.py                                  (a few minutes on 2 cores)
      python benchmarks/bench_garments.py --scenes tshirt_walk --edge 0.012 --frames 30 --rest 0
      python benchmarks/bench_garments.py --scenes tshirt_walk --frames 0 --edges 0.022 0.024 0.026 0.030 0.032 0.034
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
TAG = "BENCH_GARMENTS "  # a worker's (`--one`) result line


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["tshirt_walk", "dress_walk", "layered_walk"])
    p.add_argument("--edge", type=float, default=None, help="edge length of every garment [m] (default: the scene's)")
    p.add_argument("--edges", type=float, nargs="+", default=None, metavar="E",
                   help="run at each of these edge lengths [m] (instead of --edge), --jobs at a time")
    p.add_argument("--jobs", type=int, default=2, help="with --edges: runs at a time (one process each)")
    p.add_argument("--one", nargs=3, default=None, metavar=("SCENE", "EDGE", "MOTION"), help=argparse.SUPPRESS)
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


REST_SPEED = 1.0e-3  # [m/s] issue 18's target for a garment held still (the median of the last 20 frames' largest speed)


def tasks_of(args) -> list[tuple[str, float | None, bool]]:
    """(scene, edge length or None, held still) of every run, in the table's order."""
    edges = args.edges if args.edges else [args.edge]
    out = []
    for edge in edges:
        for name in args.scenes:
            if args.frames:
                out.append((name, edge, False))
            if args.rest:
                out.append((name, edge, True))
    return out


def worker(task: tuple, args) -> tuple:
    """The worker process (argv, env, cwd) for one run (`--one`)."""
    name, edge, still = task
    sets = [a for kv in args.set for a in ("--set", kv)]
    cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--one", name, "none" if edge is None else repr(edge),
           "still" if still else "walk", "--frames", str(args.frames), "--rest", str(args.rest), "--device", args.device, *sets]
    return cmd, None, ROOT


def rest_summary(rows: list[dict]) -> str:
    """How many of the runs held still came to rest, and the largest strain of all the runs."""
    still = [r for r in rows if "rest_speed_median_mm_s" in r]
    line = f"Largest strain at a frame's end over the {len(rows)} runs: {100 * max(r['max_strain'] for r in rows):.2f} %."
    if still:
        at_rest = sum(r["rest_speed_median_mm_s"] <= 1e3 * REST_SPEED for r in still)
        line = (f"Held still: {at_rest} of {len(still)} at rest (the median of the last {TAIL} frames' largest speed at most "
                f"{1e3 * REST_SPEED:g} mm/s). " + line)
    return line


def main(argv=None):
    args = parse_args(argv)
    sys.path.insert(0, str(ROOT))
    if args.one:
        name, edge, motion = args.one
        print(TAG + json.dumps(run(name, None if edge == "none" else float(edge), args.rest if motion == "still" else args.frames,
                                   motion == "still", args.device, args.set)), flush=True)
        return
    tasks = tasks_of(args)
    if args.edges:
        from reports import run_workers

        rows = run_workers([worker(task, args) for task in tasks], args.jobs, TAG)
        for row in rows:
            print(json.dumps(row), flush=True)
    else:
        rows = []
        for name, edge, still in tasks:
            rows.append(run(name, edge, args.rest if still else args.frames, still, args.device, args.set))
            print(json.dumps(rows[-1]), flush=True)
    for row, (_, edge, _) in zip(rows, tasks):
        row["edge"] = edge
    edge = (f"edges {', '.join(f'{e:g}' for e in args.edges)} m" if args.edges else f"{args.edge:g} m edges" if args.edge
            else "the scenes' edge lengths")
    lines = [f"# bench_garments ({args.device}, {edge}; Python {platform.python_version()})", "",
             "`python benchmarks/" + pathlib.Path(__file__).name + " " + " ".join(argv if argv is not None else sys.argv[1:]) + "`", "",
             "| scene | edge [m] | motion | particles | build (dress + settle) [s] | frames | ms/frame | CG it/frame | max strain | "
             "widest seam gap [mm] | pass work a frame, last 20 frames: collider contacts / self impulses / element samples | "
             "rest speed, last 20 frames: max / median [mm/s] |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        rest = (f"{r['rest_speed_mm_s']:.2f} / {r['rest_speed_median_mm_s']:.2f} (at {r['fastest_at']})"
                if "rest_speed_mm_s" in r else "")
        lines.append(f"| {r['scene']} | {'scene' if r['edge'] is None else format(r['edge'], 'g')} | {r['motion']} | {r['particles']} | "
                     f"{r['build_s']:.0f} | {r['frames']} | {r['ms_per_frame']:.0f} | "
                     f"{r['cg_per_frame']:.0f} | {r['max_strain']:.4f} | {r['seam_gap_mm']:.3f} | "
                     f"{r.get('pass_contacts', float('nan')):.1f} / {r.get('self_impulses', float('nan')):.1f} / "
                     f"{r.get('pass_samples', float('nan')):.1f} | {rest} |")
    from reports import write_results

    write_results(args.out, lines + ["", rest_summary(rows), ""], rows)


if __name__ == "__main__":
    main()
