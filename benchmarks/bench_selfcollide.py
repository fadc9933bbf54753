"""Benchmark: the cost of self-collision relative to the rest of the step (pile and drape scenes).

For each scene and resolution the shipped scene runs `--warmup` frames (the cloth is then folded onto
itself), then `--frames` frames are timed with the self-collision pass, the collider pass and the rest
of the step (integrator + strain limiter) clocked separately in the same process (CPU launches are
synchronous, so wall-clock time around each stage is its cost). Reported: ms per frame, the
self-collision share and its ratio to the rest of the step (target <= 3x), µs per particle per step,
candidate pairs and contact counts per step.

Run:  python benchmarks/bench_selfcollide.py                  (32^2, 64^2, 128^2; ~10 min on 2 cores)
      python benchmarks/bench_selfcollide.py --sizes 32 --frames 3 --out benchmarks/results/quick_self.md
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
SCENES = {"pile": {}, "drape_sphere": {}}


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    p.add_argument("--frames", type=int, default=5)
    p.add_argument("--warmup", type=int, default=45)
    p.add_argument("--scale-thickness", action="store_true",
                   help="scale the self-collision thickness with the cell size (the scene's value at 32^2): the same "
                        "thickness-to-edge ratio at every resolution")
    p.add_argument("--device", default="cpu", help="Warp device; on CUDA each timed stage is bracketed by a synchronize")
    p.add_argument("--out", default=None, help="default benchmarks/results/bench_selfcollide[_scaled][_cuda].md")
    return p.parse_args()


class Clock:
    """Wraps bound methods to sum their wall time [s] under a name."""

    def __init__(self, synchronize: bool = False):
        self.total: dict[str, float] = {}
        self.synchronize = synchronize

    def wrap(self, obj, attr: str, name: str):
        fn = getattr(obj, attr)

        def timed(*a, **k):
            if self.synchronize:
                import warp as wp

                wp.synchronize()
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                if self.synchronize:
                    wp.synchronize()
                self.total[name] = self.total.get(name, 0.0) + time.perf_counter() - t0

        setattr(obj, attr, timed)


def measure(scene_name: str, size: int, frames: int, warmup: int, scale_thickness: bool = False, device: str = "cpu") -> dict:
    import warp as wp

    import cloth_warp as cw
    from cloth_warp.scene import PASSES_ONLY, build_model, build_solver, load_scene

    overrides = {**PASSES_ONLY, "cloth.grid.resolution": [size, size], **SCENES[scene_name]}  # (the self-collision pass's work)
    scene = load_scene(ROOT / "scenes" / f"{scene_name}.toml", overrides)
    if scale_thickness:
        overrides["collision.thickness"] = float(scene.get("collision.thickness")) * 32.0 / size
        scene = load_scene(ROOT / "scenes" / f"{scene_name}.toml", overrides)
    model = build_model(scene, device)
    solver = build_solver(scene, model)
    substeps = int(scene.get("solver.substeps"))
    sim = cw.Simulator(model, solver, fps=60, substeps=substeps)
    t0 = time.perf_counter()
    for _ in range(warmup):
        sim.step_frame()
    warm_s = time.perf_counter() - t0
    selfc = solver.pass_named("self_collision").self_collision
    clock = Clock(synchronize=device != "cpu")
    clock.wrap(selfc, "apply", "self")
    clock.wrap(solver.pass_named("colliders"), "apply", "colliders")
    counts: dict[str, int] = {}
    vf = ee = 0
    wp.synchronize()
    t0 = time.perf_counter()
    for _ in range(frames):
        sim.step_frame()
        for k, v in sim.frame_info.items():
            if k.startswith(("self_", "impact", "collider_", "unresolved")):
                counts[k] = counts.get(k, 0) + v
        vf += selfc.grid.vertex_face.count
        ee += selfc.grid.edge_edge.count
    wp.synchronize()
    total = (time.perf_counter() - t0) / frames
    self_s = clock.total.get("self", 0.0) / frames
    coll_s = clock.total.get("colliders", 0.0) / frames
    steps = frames * substeps
    return {"scene": scene_name, "size": size, "particles": model.particle_count, "warmup_s": warm_s,
            "thickness_m": model.cloth_thickness, "close_pairs": sum(selfc._close[k][1] for k in selfc._close),
            "ms_frame": 1e3 * total, "self_ms_frame": 1e3 * self_s, "collider_ms_frame": 1e3 * coll_s,
            "rest_ms_frame": 1e3 * (total - self_s - coll_s), "passes_per_step": solver.collision_rounds,
            "vf_pairs": vf / frames, "ee_pairs": ee / frames, "per_step": {k: v / steps for k, v in counts.items()}}


def main():
    args = parse_args()
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    rows = []
    for name in args.scenes:
        for n in args.sizes:
            rows.append(measure(name, n, args.frames, args.warmup, args.scale_thickness, args.device))
            r = rows[-1]
            print(f"{name} {n}^2: {r['ms_frame']:.1f} ms/frame, self {r['self_ms_frame']:.1f}, rest {r['rest_ms_frame']:.1f}", flush=True)
    lines = [
        "# Self-collision cost (implicit Euler, 2 steps per 1/60 s frame, limiter/collision rounds per step as shipped)",
        "",
        f"`python benchmarks/bench_selfcollide.py --sizes {' '.join(map(str, args.sizes))} --frames {args.frames} "
        f"--warmup {args.warmup}{' --scale-thickness' if args.scale_thickness else ''}"
        f"{'' if args.device == 'cpu' else ' --device ' + args.device}` "
        f"({'CPU backend' if args.device == 'cpu' else args.device + ', ' + wp.get_device(args.device).name}, one process; "
        + ("thickness scaled with the cell size" if args.scale_thickness else "the scenes' own 4 mm thickness at every resolution")
        + ").",
        "",
        "| scene | grid | particles | thickness [mm] | ms/frame | self-collision ms/frame | colliders ms/frame | rest of step ms/frame | "
        "self / rest | self µs per particle per pass | broad-phase pairs VF / EE | close pairs | repulsions / CCD impacts / zones per step |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        ps = r["per_step"]
        passes = 2 * r["passes_per_step"]
        lines.append(
            f"| {r['scene']} | {r['size']}² | {r['particles']} | {1e3 * r['thickness_m']:.2f} | {r['ms_frame']:.1f} | {r['self_ms_frame']:.1f} | "
            f"{r['collider_ms_frame']:.2f} | {r['rest_ms_frame']:.1f} | {r['self_ms_frame'] / r['rest_ms_frame']:.2f} | "
            f"{1e3 * r['self_ms_frame'] / passes / r['particles']:.2f} | {r['vf_pairs']:.0f} / {r['ee_pairs']:.0f} | {r['close_pairs']} | "
            f"{ps.get('self_proximity', 0):.0f} / {ps.get('self_ccd', 0):.1f} / {ps.get('impact_zones', 0):.2f} |")
    lines += ["", "Self-collision runs once per limiter/collision round (twice per step): broad phase (hash grid, built once per "
              "step and patched where end points move beyond its margin), close-pair filter, proximity pass, CCD sweeps (the "
              "second round only on the pairs the limiter or proximity pass changed) and impact zones.", ""]
    text = "\n".join(lines)
    print(text)
    out = pathlib.Path(args.out or HERE / "results" / f"bench_selfcollide{'_scaled' if args.scale_thickness else ''}{'' if args.device == 'cpu' else '_cuda'}.md")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
