"""Benchmark: the shipped garment walks checked frame by frame for crossings, strain and open seams.

Each scene is run as `cloth-warp run` runs it (`run_scene`, its cache written to a temporary folder), then every frame
of the cache is checked with the test suite's independent intersection checker (`tests/intersections.py`, numpy,
sharing no code with the solver): every garment against the body mesh the cache holds (an edge of either crossing a
triangle of the other), every pair of garments, and every garment against itself. Reported per scene: frames, ms per
frame, the largest strain, the widest seam gap and the farthest an attached particle got from its point on the body
(the run's summary, from every frame), and the frames with a crossing of each kind. Issue 18's targets: no crossing in
any frame, strain within the limit, attachments on the body surface to 1e-4 m.

Run:  python benchmarks/bench_walk_intersections.py                               (the four walks, 180 frames each)
      python benchmarks/bench_walk_intersections.py --scenes tshirt_walk --frames 60 --set cloth.edge_length=0.03
"""

from __future__ import annotations

import argparse
import itertools
import pathlib
import platform
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["tshirt_walk", "dress_walk", "layered_walk", "skirt_walk"])
    p.add_argument("--frames", type=int, default=180)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="scene override (TOML value), repeatable")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_walk_intersections.md"))
    return p.parse_args(argv)


def cache_meshes(path: pathlib.Path):
    """The cache's garments (meshes outside /World/colliders) and its mesh colliders, as {name: UsdGeom.Mesh}, its
    first and last frame, and the stage (kept open while the meshes are read)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    garments, bodies = {}, {}
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        parts = prim.GetPath().pathString.split("/")
        (bodies if "colliders" in parts else garments)[prim.GetName()] = UsdGeom.Mesh(prim)
    return garments, bodies, int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()), stage


def check(path: pathlib.Path) -> dict:
    """Frames with a crossing, per kind, over every frame of the cache at `path`."""
    from intersections import crossing_pairs, intersecting_pairs

    garments, bodies, first, last, _stage = cache_meshes(path)
    tris = {k: np.asarray(m.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3) for k, m in {**garments, **bodies}.items()}
    bad = {"crossing_body": [], "crossing_garments": [], "crossing_self": []}
    for f in range(first, last + 1):
        x = {k: np.asarray(m.GetPointsAttr().Get(f), float) for k, m in {**garments, **bodies}.items()}
        if any(crossing_pairs(x[g], tris[g], x[b], tris[b]) for g in garments for b in bodies):
            bad["crossing_body"].append(f)
        if any(crossing_pairs(x[a], tris[a], x[b], tris[b]) for a, b in itertools.combinations(garments, 2)):
            bad["crossing_garments"].append(f)
        if any(intersecting_pairs(x[g], tris[g]) for g in garments):
            bad["crossing_self"].append(f)
    return {"garments": sorted(garments), "bodies": sorted(bodies), "checked_frames": last - first + 1, **bad}


def main(argv=None) -> int:
    import warp as wp

    args = parse_args(argv)
    wp.config.quiet = True
    from cloth_warp.cli import parse_set
    from cloth_warp.runner import run_scene

    rows = []
    for name in args.scenes:
        with tempfile.TemporaryDirectory() as tmp:
            out = pathlib.Path(tmp) / f"{name}.usdc"
            t = time.perf_counter()
            summary = run_scene(name, parse_set(args.set), output=out, frames=args.frames, device="cpu")
            run_s = time.perf_counter() - t
            row = {"scene": name, "frames": summary["frames"], "status": summary["status"], "run_s": run_s, "ms_per_frame": summary.get("ms_per_frame"),
                   "max_strain": summary["max_strain"], "seam_gap_mm": 1e3 * summary.get("seam_gap", 0.0),
                   "attachment_gap_mm": None if summary.get("attachment_gap") is None else 1e3 * summary["attachment_gap"],
                   "strain_limit": summary.get("strain_limit"), **check(out)}
        rows.append(row)
        print(row, flush=True)
    command = ("python benchmarks/bench_walk_intersections.py " + " ".join(sys.argv[1:] if argv is None else argv)).strip()
    lines = ["# bench_walk_intersections: the garment walks checked in every frame", "",
             f"Machine: {platform.machine()}, Python {platform.python_version()}, Warp {wp.config.version}, device cpu. "
             f"Command: `{command}`", "",
             "Every frame of each run's cache (its first frame, the dressed garments, included) checked with "
             "`tests/intersections.py`: garment against body, garment against garment, garment against itself. Run time "
             "includes the dressing and the settle.", "",
             "| scene | garments | frames checked | run [s] | ms/frame | largest strain | limit missed in frames (sweeps a step, most / cap) | "
             "widest seam gap [mm] | attachments off the body [mm] | frames crossing the body | garments crossing each other | "
             "garments crossing themselves |",
             "|---|---|---:|---:|---:|---:|---|---:|---:|---|---|---|"]
    for r in rows:
        kinds = " | ".join(", ".join(map(str, r[k])) or "none" for k in ("crossing_body", "crossing_garments", "crossing_self"))
        limit = r["strain_limit"] or {}
        sweeps = (limit.get("sweeps_per_step") or {}).get("max")
        missed = f"{limit.get('missed_frames', 0)} ({sweeps} / {limit.get('max_sweeps')})" if limit else "no limiter"
        lines.append(f"| {r['scene']} | {', '.join(r['garments'])} | {r['checked_frames']} | {r['run_s']:.0f} | {r['ms_per_frame'] or 0:.0f} | {r['max_strain']:.4f} | "
                     f"{missed} | "
                     f"{r['seam_gap_mm']:.3f} | {'none attached' if r['attachment_gap_mm'] is None else format(r['attachment_gap_mm'], '.5f')} | {kinds} |")
    from reports import write_results

    write_results(args.out, lines, {"command": command, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
