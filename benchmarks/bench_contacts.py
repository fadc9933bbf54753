"""Benchmark: contacts resolved after the step (the colliders and self-collision passes) or also inside the implicit solve.

For each scene and mode ("pass": both after the step; "solve": `solver.collider_contacts = "solve"`; "solve+self": also
`solver.self_contacts = "solve"`, in scenes with self-collision; "+friction": the collider contacts' friction in the solve,
`solver.contact_friction = "solve"`), the shipped scene is run as `cloth-warp run`
builds it for `--frames` frames (default 300: 5 s at 60 fps). Reported: ms per frame (median over the run), the
largest particle speed over the last 20 frames (median and max: at rest means <= 1 mm/s, issue 17's target), the
largest strain of a strain-limited spring at the end and how many exceed the limit by more than 1 % (a ring
stretched over a collider's rim),
the colliders pass's contacts and the self-collision pass's impulses (proximity + CCD) per frame, the self-contact
elements held in the solve per frame and the CG iterations per frame (means over the last 20 frames), and the
frames re-run because a self-collision buffer overflowed or a step needed impact zones.

Run:  python benchmarks/bench_contacts.py                      (pile and drape_sphere, a few minutes on 2 cores)
      python benchmarks/bench_contacts.py --scenes pile --frames 120 --set cloth.grid.resolution=[48,48]
      python benchmarks/bench_contacts.py --modes solve solve+friction --set collision.self_collision=false
      python benchmarks/bench_contacts.py --scenes pile --resolutions 32 48 64 --seeds 0 1 --set solver.tolerance=1e-4
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import statistics
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
# mode -> (collider contacts, self-contacts, the collider contacts' friction)
MODES = {"pass": ("pass", "pass", "after"), "solve": ("solve", "pass", "after"), "solve+self": ("solve", "solve", "after"),
         "solve+friction": ("solve", "pass", "solve"), "solve+self+friction": ("solve", "solve", "solve")}
TAIL = 20


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["pile", "drape_sphere"])
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    p.add_argument("--seeds", nargs="+", type=int, default=None, help="scene.seed values (the cloth's jitter), one run each")
    p.add_argument("--resolutions", nargs="+", type=int, default=None, help="square grid resolutions (cloth.grid.resolution), one run each")
    p.add_argument("--device", default="cpu", help="Warp device (cpu, cuda:0)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="scene override (TOML value), repeatable")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_contacts.md"))
    return p.parse_args(argv)


def run(scene_name: str, mode: str, frames: int, overrides: dict, device: str = "cpu") -> dict:
    import warp as wp

    from cloth_warp.runner import find_scene, load_kernels
    from cloth_warp.scene import build_model, build_solver, build_wind, load_scene
    from cloth_warp.simulator import Simulator

    collider, self_contacts, friction = MODES[mode]
    scene = load_scene(find_scene(scene_name), {**overrides, "solver.collider_contacts": collider, "solver.self_contacts": self_contacts,
                                                "solver.contact_friction": friction})
    model = build_model(scene, device)
    solver = build_solver(scene, model)
    load_kernels(solver, model.device)
    sim = Simulator(model, solver, fps=float(scene.get("output.fps")), substeps=int(scene.get("solver.substeps")),
                    wind=build_wind(scene))
    ms, speed, contacts, iterations, impulses, elements = [], [], [], [], [], []
    for _ in range(frames):
        t = time.perf_counter()
        stats = sim.step_frame()
        wp.synchronize()
        ms.append(1e3 * (time.perf_counter() - t))
        report = sim.frame_report
        speed.append(stats.max_speed)
        contacts.append(report.passes["colliders"].contacts if "colliders" in report.passes else 0)
        iterations.append(report.iterations)
        counters = report.counters()
        impulses.append(counters.get("self_proximity", 0) + counters.get("self_ccd", 0))
        elements.append(counters.get("solve_self_contacts", 0))
    import numpy as np

    x = sim.positions()
    ends = model.spring_indices.numpy().reshape(-1, 2)
    limited = model.spring_limited.numpy() != 0
    strain = np.linalg.norm(x[ends[:, 0]] - x[ends[:, 1]], axis=1) / model.spring_rest_length.numpy() - 1.0
    limit = solver.strain_limiter.max_strain if solver.strain_limiter is not None else None
    return {"scene": scene_name, "mode": mode, "frames": frames, "ms_per_frame": statistics.median(ms),
            "max_limited_strain": float(strain[limited].max()) if limited.any() else 0.0,
            "springs_over_limit": int((strain[limited] > limit + 0.01).sum()) if limit is not None else None,
            "rest_speed_median": statistics.median(speed[-TAIL:]), "rest_speed_max": max(speed[-TAIL:]),
            "pass_contacts": statistics.mean(contacts[-TAIL:]), "iterations": statistics.mean(iterations[-TAIL:]),
            "self_impulses": statistics.mean(impulses[-TAIL:]), "self_elements": statistics.mean(elements[-TAIL:]),
            "reruns": sim.reruns}


def write_report(rows: list[dict], command: str, device: str, frames: int, overrides: dict, out: pathlib.Path, note: str = ""):
    """The rows as a markdown table at `out` (and the JSON beside it), printed too."""
    import warp as wp

    lines = ["# bench_contacts: contacts after the step (\"pass\") or also inside the implicit solve (\"solve\": collider contacts; "
             "\"solve+self\": and self-contacts; \"+friction\": their friction in the solve too)", "",
             f"Machine: {platform.machine()}, Python {platform.python_version()}, Warp {wp.config.version}, device {device}. "
             f"Command: `{command}`" + (f"; overrides {overrides}" if overrides else "") + note, "",
             f"{frames} frames per run; speeds and counts over the last {TAIL} frames (at rest: <= 1 mm/s).", "",
             "| scene | resolution | seed | contacts | ms/frame | largest speed, median [mm/s] | largest speed, max [mm/s] | colliders-pass contacts/frame "
             "| self-collision pass impulses/frame | self-contact elements in the solve/frame "
             "| CG iterations/frame | frames re-run | max limited strain (end) | springs > limit + 1 % |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['resolution'] or 'scene'} | {'scene' if r['seed'] is None else r['seed']} | {r['mode']} | "
                     f"{r['ms_per_frame']:.1f} | {1e3 * r['rest_speed_median']:.2f} | "
                     f"{1e3 * r['rest_speed_max']:.2f} | {r['pass_contacts']:.0f} | {r['self_impulses']:.0f} | {r['self_elements']:.0f} | "
                     f"{r['iterations']:.0f} | {r['reruns']} | "
                     f"{r['max_limited_strain']:.3f} | {r['springs_over_limit']} |")
    out.write_text("\n".join(lines) + "\n")
    out.with_suffix(".json").write_text(json.dumps({"command": command, "overrides": overrides, "rows": rows}, indent=1) + "\n")
    print("\n".join(lines))


def main(argv=None) -> int:
    import warp as wp

    args = parse_args(argv)
    wp.config.quiet = True
    from cloth_warp.cli import parse_set

    overrides = parse_set(args.set)
    rows = []
    from cloth_warp.runner import find_scene
    from cloth_warp.scene import load_scene

    variants = [{**({"cloth.grid.resolution": [res, res]} if res else {}), **({"scene.seed": seed} if seed is not None else {})}
                for res in (args.resolutions or [None]) for seed in (args.seeds or [None])]
    for name in args.scenes:
        self_collision = bool(load_scene(find_scene(name), overrides).get("collision.self_collision"))
        for variant in variants:
            for mode in args.modes:
                if MODES[mode][1] == "solve" and not self_collision:
                    continue
                r = run(name, mode, args.frames, {**overrides, **variant}, args.device)
                r.update(resolution=variant.get("cloth.grid.resolution", [None])[0], seed=variant.get("scene.seed"))
                rows.append(r)
                print(json.dumps(r), flush=True)
    command = "python benchmarks/bench_contacts.py " + " ".join(sys.argv[1:] if argv is None else argv)
    write_report(rows, command.strip(), args.device, args.frames, overrides, pathlib.Path(args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
