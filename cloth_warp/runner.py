"""Running a scene: build, simulate frame by frame, write the cache as frames land, summarise.

:func:`run_scene` is what ``cloth-warp run`` calls; from Python it is one call that returns the summary::

    summary = cloth_warp.run_scene("scenes/flag.toml", {"output.frames": 30}, output="out/flag.usdc")
"""

from __future__ import annotations

import json
import logging
import math
import pathlib
import sys
import time

import numpy as np

from .cache import COUNTER_DIAGNOSTICS
from .collision import ALL_COUNTERS as COLLISION_COUNTERS
from .scene import Scene, SceneError, build_model, build_solver, build_wind, load_scene

log = logging.getLogger(__name__)

SHIPPED_SCENES = pathlib.Path(__file__).resolve().parent.parent / "scenes"


def shipped_scenes() -> dict[str, pathlib.Path]:
    """The scenes shipped in the repository's scenes/ folder, by name."""
    if not SHIPPED_SCENES.is_dir():
        return {}
    return {p.stem: p for p in sorted(SHIPPED_SCENES.glob("*.toml"))}


def find_scene(name_or_path) -> pathlib.Path:
    """A scene file path; a bare name (``flag``) that is not a file names a shipped scene."""
    p = pathlib.Path(name_or_path)
    if p.is_file():
        return p
    shipped = shipped_scenes()
    if p.suffix == "" and p.name in shipped:
        return shipped[p.name]
    hint = f"; shipped scenes: {', '.join(shipped)}" if shipped else ""
    raise SceneError(f"scene file not found: {p}{hint}")


def _kernel_modules(solver):
    from .kernels import broadphase, collide, constraints, diagnostics, forces, implicit, selfcollide
    from .solvers import SolverImplicitEuler

    mods = [forces, constraints, diagnostics]
    if isinstance(solver, SolverImplicitEuler):
        mods.append(implicit)
    collisions = getattr(solver, "collisions", None)
    if collisions is not None:
        mods.append(collide)
        if collisions.self_collision is not None:
            mods += [broadphase, selfcollide]
    return mods


def _drape_coefficient(scene: Scene, model, positions) -> float:
    """The Cusick drape coefficient of the scene's cloth at `positions` ([measure.cusick])."""
    from .drape import drape_coefficient

    radius = scene.get("measure.cusick.disc_radius") or scene.get("cloth.disc.radius")  # checked by the scene loader
    return drape_coefficient(positions, model.tri_indices.numpy(), pedestal_radius=float(scene.get("measure.cusick.pedestal_radius")),
                             disc_radius=float(radius), up_axis=model.up_axis)


def load_kernels(solver, device) -> float:
    """Compile (or load from the kernel cache) the kernel modules a solver uses; returns seconds taken."""
    import warp as wp

    t0 = time.perf_counter()
    for m in _kernel_modules(solver):
        wp.load_module(m, device=device)
    return time.perf_counter() - t0


def default_output(scene: Scene) -> pathlib.Path:
    out = scene.data.get("output", {}).get("path")
    return scene.resolve(out) if out is not None else pathlib.Path("out") / f"{scene.name}.usdc"


def run_scene(scene, overrides: dict | None = None, *, output=None, frames: int | None = None, fps: float | None = None,
              device=None, start_frame: int | None = None, progress=None, argv=None) -> dict:
    """Run a scene (a path, a shipped scene name or a :class:`Scene`) and write its cache.

    Args:
        overrides: dotted key paths to values (as ``--set``); ignored when `scene` is a Scene.
        output, frames, fps, start_frame: override the scene's [output] values.
        device: Warp device ("cpu", "cuda", "cuda:0"; default Warp's).
        progress: called after every frame as ``progress(frame, total, summary_so_far)``.
        argv: the command line, stamped into the cache.

    Returns the summary dict (JSON-able): status ``complete`` / ``diverged`` (with ``message`` and
    ``diagnosis``) / ``interrupted``, frames, wall and compile time, ms/frame, max strain, dt range,
    solver iterations, the cache path. A diverged or interrupted run still leaves a valid cache of the
    frames done; an interruption re-raises KeyboardInterrupt after the cache is closed, with the summary
    in the exception's ``summary`` attribute. Bad input raises :class:`SceneError` before anything runs.
    """

    import warp as wp

    from .cache import open_cache
    from .simulator import Simulator
    from .solvers import SimulationDiverged

    if not isinstance(scene, Scene):
        scene = load_scene(find_scene(scene), overrides)
    fps = float(fps if fps is not None else scene.get("output.fps"))
    if not (math.isfinite(fps) and fps > 0):
        raise SceneError(f"fps: must be > 0, got {fps!r}")
    n_frames = int(frames if frames is not None else scene.get("output.frames"))
    if n_frames < 1:
        raise SceneError(f"frames: must be >= 1, got {n_frames!r}")
    start = int(start_frame if start_frame is not None else scene.get("output.start_frame"))
    out = pathlib.Path(output) if output is not None else default_output(scene)
    from .cache import CACHE_SUFFIXES

    if out.suffix.lower() not in CACHE_SUFFIXES:
        raise SceneError(f"output: {out} has an unknown extension; allowed: {', '.join(CACHE_SUFFIXES)}")

    if device is not None:
        try:
            device = wp.get_device(device)
        except (ValueError, RuntimeError) as exc:
            raise SceneError(f"device: {exc} (available: {', '.join(str(d) for d in wp.get_devices())})") from exc
    t_start = time.perf_counter()
    model = build_model(scene, device)
    solver = build_solver(scene, model)
    substeps = int(scene.get("solver.substeps"))
    compile_s = load_kernels(solver, model.device)
    wind = build_wind(scene)
    sim = Simulator(model, solver, fps=fps, substeps=substeps, adaptive=bool(scene.get("solver.adaptive")),
                    dt_min=float(scene.get("solver.dt_min")), wind=wind)
    lo, hi = model.rest_positions.min(0), model.rest_positions.max(0)
    summary = {
        "scene": str(scene.path) if scene.path else None, "status": "running", "frames": 0, "frames_requested": n_frames,
        "fps": fps, "start_frame": start, "device": str(model.device), "particles": model.particle_count,
        "springs": model.spring_count, "triangles": model.tri_count, "integrator": solver.name,
        "substeps": substeps, "dt_nominal": 1.0 / (fps * substeps), "bounds_m": [lo.tolist(), hi.tolist()],
        "output": str(out),
    }
    metadata = {"scene_path": summary["scene"], "scene_sha256": scene.sha256, "scene_text": scene.text,
                "resolved_scene": json.dumps(scene.resolved(), sort_keys=True), "overrides": json.dumps(scene.overrides),
                "argv": json.dumps(list(argv) if argv is not None else sys.argv), "device": summary["device"],
                "integrator": solver.name, "substeps": substeps, "description": scene.get("scene.description")}
    writer = open_cache(out, model, fps=fps, start_frame=start, save_every=int(scene.get("output.save_every")),
                        normals=bool(scene.get("output.normals")), velocities=bool(scene.get("output.velocities")),
                        metadata=metadata)
    max_strain, dt_min, dt_max, iterations, rejected, contacts = 0.0, math.inf, 0.0, [], 0, {}
    t_loop = time.perf_counter()
    interrupted = None
    try:
        writer.write(sim.state.particle_q.numpy(), sim.state.particle_qd.numpy())
        for f in range(n_frames):
            stats = sim.step_frame()
            info = sim.frame_info
            diag = {"maxStrain": stats.max_strain, "dt": info["dt_min"], "solverIterations": info["iterations"],
                    "solverResidual": info["residual"]}
            diag.update({attr: info.get(key) for attr, key in COUNTER_DIAGNOSTICS.items()})
            writer.write(sim.state.particle_q.numpy(), sim.state.particle_qd.numpy(), diag)
            for key in COLLISION_COUNTERS:
                if key in info:
                    contacts[key] = contacts.get(key, 0) + info[key]
            max_strain = max(max_strain, stats.max_strain)
            dt_min, dt_max = min(dt_min, info["dt_min"]), max(dt_max, info["dt_max"])
            iterations.append(info["iterations"])
            rejected += info.get("rejected", 0)
            summary["frames"] = f + 1
            if progress is not None:
                summary["wall_s"] = time.perf_counter() - t_loop
                progress(f + 1, n_frames, summary)
        summary["status"] = "complete"
        cusick = scene.data.get("measure", {}).get("cusick")
        if cusick is not None:
            summary["drape_coefficient"] = _drape_coefficient(scene, model, sim.positions())
    except SimulationDiverged as exc:
        summary.update(status="diverged", message=str(exc),
                       diagnosis={"frame": start + summary["frames"] + 1, "time_s": exc.time, "reason": exc.reason,
                                  "max_strain": exc.max_strain, "last_dt": exc.dt, "suggested_dt": exc.suggested_dt})
    except KeyboardInterrupt as exc:
        summary["status"] = "interrupted"
        interrupted = exc
    except BaseException:
        summary["status"] = "failed"
        raise
    finally:
        wall = time.perf_counter() - t_loop
        done = summary["frames"]
        summary.update(
            wall_s=wall, total_s=time.perf_counter() - t_start, compile_s=compile_s,
            ms_per_frame=1e3 * wall / done if done else None, max_strain=max_strain,
            dt_min=dt_min if done else None, dt_max=dt_max if done else None, rejected_steps=rejected,
            solver_iterations={"mean": float(np.mean(iterations)), "max": int(np.max(iterations))} if iterations else None,
            frames_written=writer.frames_written, end_frame=start + writer.frames_written - 1,
            colliders=model.collider_count, self_collision=bool(model.self_collision), contacts=contacts,
        )
        writer.close(summary["status"], {k: summary[k] for k in ("frames", "wall_s", "max_strain", "compile_s", "drape_coefficient")
                                         if k in summary})
        summary["output_bytes"] = out.stat().st_size if out.exists() else 0
    if interrupted is not None:
        interrupted.summary = summary
        raise interrupted
    return summary
