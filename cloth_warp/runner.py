"""Running a scene: build, simulate frame by frame, write the cache as frames land, summarise.

:func:`run_scene` is what ``cloth-warp run`` calls; from Python it is one call that returns the summary::

    summary = cloth_warp.run_scene("scenes/flag.toml", {"output.frames": 30}, output="out/flag.usdc")
"""

from __future__ import annotations

import json
import logging
import math
import os
import pathlib
import sys
import time
import warnings

import numpy as np

from . import profiling
from .cache import COUNTER_DIAGNOSTICS, STRAIN_LIMIT_DIAGNOSTICS
from .collision import ALL_COUNTERS as COLLISION_COUNTERS
from .diagnostics import SOLVE_CONTACT_COUNTERS
from .model import attachment_gap
from .profiling import stage
from .sewing import seam_ends, seam_gap
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


def _kernel_modules(solver, animated: bool = False):
    """The solver's kernel modules (:meth:`SolverBase.all_kernel_modules`) and, for a scene with animated handles,
    colliders or a gusty wind, the ControlAnimator's."""
    from .kernels import animation

    return solver.all_kernel_modules() + ([animation] if animated else [])


def _drape_coefficient(scene: Scene, model, positions) -> float:
    """The Cusick drape coefficient of the scene's cloth at `positions` ([measure.cusick])."""
    from .drape import drape_coefficient

    radius = scene.get("measure.cusick.disc_radius") or scene.get("cloth.disc.radius")  # checked by the scene loader
    return drape_coefficient(positions, model.tri_indices.numpy(), pedestal_radius=float(scene.get("measure.cusick.pedestal_radius")),
                             disc_radius=float(radius), up_axis=model.up_axis)


# Kernel modules by their cold compile on the CPU, most expensive first (measured, seconds with backward code:
# collide ~21, implicit ~17 before its solve-only kernels went forward-only): a parallel load starts them first.
_COMPILE_FIRST = ("collide", "implicit", "selfcollide", "forces", "broadphase")


def load_kernels(solver, device, animated: bool = False, workers: int | None = None) -> float:
    """Compile (or load from the kernel cache) the kernel modules a solver uses (and, `animated`, the animator's),
    `workers` modules at a time (default: one per core, at most 4; the CPU compiler releases the GIL, so a cold
    start on two cores takes about as long as its longest module); returns seconds taken."""
    import warp as wp

    t0 = time.perf_counter()
    names = [m.__name__ for m in _kernel_modules(solver, animated)]
    rank = {f"{__package__}.kernels.{n}": i for i, n in enumerate(_COMPILE_FIRST)}
    names.sort(key=lambda n: rank.get(n, len(rank)))
    workers = min(os.cpu_count() or 1, 4) if workers is None else int(workers)
    wp.force_load(device=device, modules=[wp.get_module(n) for n in names], max_workers=workers if workers > 1 else 0)
    return time.perf_counter() - t0


def default_output(scene: Scene) -> pathlib.Path:
    out = scene.data.get("output", {}).get("path")
    return scene.resolve(out) if out is not None else pathlib.Path("out") / f"{scene.name}.usdc"


def _resume_source(out: pathlib.Path, recover: bool = True):
    """The newest cache of `out` (its final file or a dead run's partial file) holding a resume checkpoint:
    (path, frames, checkpoint, metadata), or None. A partial file whose last save was cut off is first rolled
    back to the save before (:func:`~cloth_warp.outputs.recover_partial`): call while holding the output's
    lock, or with ``recover=False`` to look at a rolled-back copy instead."""
    import tempfile

    from .cache import read_checkpoint
    from .outputs import recover_partial, stale_partials

    candidates = ([out] if out.exists() else []) + stale_partials(out)
    with tempfile.TemporaryDirectory() as scratch:
        for path in sorted(candidates, key=lambda p: p.stat().st_mtime, reverse=True):
            source = path
            try:
                copy = pathlib.Path(scratch) / path.name
                if path != out and recover_partial(path, copy_to=None if recover else copy):
                    log.warning("--resume: %s: its last save was cut off; rolled back to the save before", path)
                    source = path if recover else copy
                if not source.exists():
                    continue  # cut off in its first save: nothing was saved
                return (path, *read_checkpoint(source))
            except (ValueError, OSError, KeyError) as exc:
                log.warning("--resume: skipping %s: %s", path, exc)
    return None


def can_resume(out) -> bool:
    """Whether the cache path `out` has something ``--resume`` continues: its final file or a dead run's partial file
    holding a resume checkpoint (read-only; the resumed run takes the output's lock and reads it again)."""
    return _resume_source(pathlib.Path(out), recover=False) is not None


def _changed_keys(a, b, prefix="") -> list[str]:
    """Dotted key paths whose values differ between two nested dicts."""
    if not (isinstance(a, dict) and isinstance(b, dict)):
        return [] if a == b else [prefix or "(scene)"]
    out = []
    for key in sorted(set(a) | set(b)):
        out += _changed_keys(a.get(key), b.get(key), f"{prefix}.{key}" if prefix else str(key))
    return out


def _check_resumable(meta: dict, source, scene: Scene, fps: float, start: int):
    """Refuse to continue a cache written from another scene (other than its [output] table), frame rate or
    start frame (the simulator's restore checks particles, substeps and solver too)."""
    problems = []
    try:
        earlier = json.loads(meta["resolved_scene"])
    except (KeyError, TypeError, ValueError):
        earlier = None
    if earlier is not None:
        changed = [k for k in _changed_keys(earlier, json.loads(json.dumps(scene.resolved()))) if not k.startswith("output")]
        if changed:
            problems.append(f"its scene differs in {', '.join(changed[:8])}{' ...' if len(changed) > 8 else ''} "
                            f"(only [output] keys may change)")
    if not math.isclose(float(meta.get("fps", fps)), fps):
        problems.append(f"it was written at {meta.get('fps')} fps, this run asks {fps:g}")
    if int(meta.get("start_frame", start)) != start:
        problems.append(f"it starts at frame {meta.get('start_frame')}, this run at {start}")
    if problems:
        raise SceneError(f"--resume: cannot continue {source}: " + "; ".join(problems))


def _finite(value):
    """`value` with non-finite floats as None (summaries stay valid JSON)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def strain_limit_summary(sim, resumed: list[dict] = ()) -> dict | None:
    """What the strain limiter left over a run (None without one): ``limit``, ``tolerance`` (excess strain
    counted as a miss), ``max_sweeps`` (the cap per step), ``frames``, ``missed_frames`` and ``missed_steps``
    (left above the tolerance), the worst excess after limiting ``excess_structural`` / ``excess_shear``,
    ``sweeps_per_step`` (mean and max over this run's steps). `resumed`: the cache diagnostics of the frames
    copied from an earlier run, counted in frames, misses and excess."""
    limiter = sim.strain_limiter
    if limiter is None:
        return None
    total = sim.strain_limit_total
    out = {"limit": limiter.max_strain, "tolerance": limiter.report_tolerance, "max_sweeps": limiter.iterations,
           "frames": total.frames if total else 0, "missed_frames": total.missed_frames if total else 0,
           "missed_steps": total.missed_steps if total else 0,
           "excess_structural": total.structural_excess if total else 0.0, "excess_shear": total.shear_excess if total else 0.0,
           "sweeps_per_step": {"mean": total.mean_sweeps, "max": total.most_sweeps} if total and total.steps else None}
    for diag in resumed:
        missed = int(diag.get("strainLimitMissed") or 0)
        out["frames"] += 1
        out["missed_frames"] += int(missed > 0)
        out["missed_steps"] += missed
        for key, attr in (("excess_structural", "strainExcessStructural"), ("excess_shear", "strainExcessShear")):
            value = diag.get(attr)
            if value is not None and math.isfinite(value):
                out[key] = max(out[key], float(value))
    return out


def strain_limit_message(limit: dict) -> str:
    """The one-line warning of a run whose strain limiting missed its tolerance (a :func:`strain_limit_summary`)."""
    kind = "shear" if limit["excess_shear"] > limit["excess_structural"] else "structural"
    worst = max(limit["excess_structural"], limit["excess_shear"])
    return (f"strain limit {100 * limit['limit']:g} % missed in {limit['missed_frames']} of {limit['frames']} frames "
            f"({limit['missed_steps']} steps stopped at the cap of {limit['max_sweeps']} sweeps; worst {100 * worst:.3g} % "
            f"strain above the limit, on {kind} springs): raise solver.strain_limit_iterations or solver.substeps")


def run_scene(scene, overrides: dict | None = None, *, output=None, frames: int | None = None, fps: float | None = None,
              device=None, start_frame: int | None = None, progress=None, argv=None, resume: bool = False,
              profile: bool = False) -> dict:
    """Run a scene (a path, a shipped scene name or a :class:`Scene`) and write its cache.

    Args:
        overrides: dotted key paths to values (as ``--set``); ignored when `scene` is a Scene.
        output, frames, fps, start_frame: override the scene's [output] values.
        device: Warp device ("cpu", "cuda", "cuda:0"; default Warp's).
        progress: called after every frame as ``progress(frame, total, summary_so_far)``.
        argv: the command line, stamped into the cache.
        resume: continue the newest cache of this output (its final file, or the partial file of a run that
            was killed) from its last saved checkpoint: its frames are copied into a new cache and the
            simulation goes on from there, giving the frames an uninterrupted run gives (bit-identical on
            the CPU); the scene must be the same but for its [output] keys (more frames may be asked).
            Stopped while copying, the earlier cache is left as it was.
        profile: time the step's stages (:mod:`cloth_warp.profiling`: ``frame`` around each step, the solver's own
            stages inside it, ``cache`` around each cache write) and put the :class:`~cloth_warp.profiling.StageReport`
            in the summary under ``profile`` (its ``to_dict()``). Frames then run without graph capture (a replayed
            graph runs no Python to time) and the device is synchronised at every stage boundary: slower than a plain run.

    Returns the summary dict (JSON-able, non-finite values as None): status ``complete`` / ``diverged``
    (with ``message`` and ``diagnosis``) / ``interrupted``, frames, wall and compile time, ms/frame, max
    strain, dt range, solver iterations, the cache path and, with strain limiting, ``strain_limit`` (see
    :func:`strain_limit_summary`); when the limiter missed its tolerance in some frames, a
    :class:`~cloth_warp.solvers.StrainLimitWarning` says in how many (once per run). A diverged or
    interrupted run still leaves a valid cache of the frames done; an interruption re-raises
    KeyboardInterrupt after the cache is closed, with the summary in the exception's ``summary``
    attribute; a failed write (disk full, I/O error) raises
    :class:`~cloth_warp.outputs.CacheWriteError` likewise, after renaming the last good save to the final
    name. Bad input raises :class:`SceneError` before anything runs, an output that cannot be written or is
    being written by another live run :class:`~cloth_warp.outputs.CacheWriteError`.
    """

    import warp as wp

    from .cache import CACHE_SUFFIXES, open_cache
    from .cache import CacheError
    from .outputs import CacheWriteError, DeferredSignals, OutputLock, check_output, remove_partial, stale_partials
    from .simulator import Simulator
    from .solvers import SimulationDiverged

    if not isinstance(scene, Scene):
        scene = load_scene(find_scene(scene), overrides)
    from .validation import LIMITS, InvalidValue, check_number, check_run_length

    try:  # the arguments that override the scene's (already checked) values go through the same gate
        fps = float(check_number("fps", fps if fps is not None else scene.get("output.fps"), LIMITS["fps"]))
        n_frames = int(check_number("frames", frames if frames is not None else scene.get("output.frames"), LIMITS["frames"]))
        start = int(check_number("start_frame", start_frame if start_frame is not None else scene.get("output.start_frame"),
                                 LIMITS["start_frame"]))
        check_run_length("frames x solver.substeps", n_frames, int(scene.get("solver.substeps")))
    except InvalidValue as exc:
        raise SceneError(str(exc)) from None
    out = pathlib.Path(output) if output is not None else default_output(scene)
    if out.suffix.lower() not in CACHE_SUFFIXES:
        raise SceneError(f"output: {out} has an unknown extension; allowed: {', '.join(CACHE_SUFFIXES)}")
    check_output(out)  # before anything is built (the writer checks the room for its first saves too)

    if device is not None:
        if str(device).startswith("cuda") and not wp.is_cuda_available():
            raise SceneError(f"device: {device!r} asked for, but no CUDA device is available here "
                             f"(available: {', '.join(str(d) for d in wp.get_devices())})")
        try:
            device = wp.get_device(device)
        except (ValueError, RuntimeError) as exc:
            raise SceneError(f"device: {exc} (available: {', '.join(str(d) for d in wp.get_devices())})") from exc
    t_start = time.perf_counter()
    model = build_model(scene, device)
    lock = OutputLock(out).acquire()  # before reading what to resume and until the writer closes
    try:
        source = _resume_source(out) if resume else None
        if resume and source is None:
            raise SceneError(f"--resume: no cache of an earlier run of {out} with a resume checkpoint (its final file "
                             f"or a partial file of a killed run)")
        if source is not None:
            _check_resumable(source[3], source[0], scene, fps, start)
            if source[1] - 1 > n_frames:
                raise SceneError(f"--resume: {source[0]} already holds {source[1] - 1} frames, more than the {n_frames} asked")
        solver = build_solver(scene, model)
        substeps = int(scene.get("solver.substeps"))
        wind = build_wind(scene)
        compile_s = load_kernels(solver, model.device, animated=model.animated or (wind is not None and not wind.steady))
        sim = Simulator(model, solver, fps=fps, substeps=substeps, adaptive=bool(scene.get("solver.adaptive")),
                        dt_min=float(scene.get("solver.dt_min")), wind=wind, capture=False if profile else None)
        if source is not None:
            try:
                sim.restore(source[2])
            except ValueError as exc:
                raise SceneError(f"--resume: cannot continue {source[0]}: {exc}") from None
        metadata = {"scene_path": str(scene.path) if scene.path else None, "scene_sha256": scene.sha256,
                    "scene_text": scene.text, "resolved_scene": json.dumps(scene.resolved(), sort_keys=True),
                    "overrides": json.dumps(scene.overrides), "argv": json.dumps(list(argv) if argv is not None else sys.argv),
                    "device": str(model.device), "integrator": solver.name, "substeps": substeps,
                    "description": scene.get("scene.description"), "frames_requested": n_frames}
        if source is not None:
            metadata["resumed_from"] = {"path": str(source[0]), "frames": source[1]}
        lo, hi = model.rest_positions.min(0), model.rest_positions.max(0)
        summary = {
            "scene": metadata["scene_path"], "status": "running", "frames": 0, "frames_requested": n_frames,
            "fps": fps, "start_frame": start, "device": str(model.device), "particles": model.particle_count,
            "springs": model.spring_count, "triangles": model.tri_count, "integrator": solver.name,
            "substeps": substeps, "dt_nominal": 1.0 / (fps * substeps), "bounds_m": [lo.tolist(), hi.tolist()],
            "output": str(out),
        }
        max_strain, dt_min, dt_max, iterations, rejected, contacts = 0.0, math.inf, 0.0, [], 0, {}
        resumed_limit: list[dict] = []  # the per-frame diagnostics of frames copied from an earlier run
        seams, worst_seam = seam_ends(model), 0.0  # the sewn particle pairs; the widest any opened [m]
        worst_attachment = 0.0  # the farthest any attached particle was from its point on the body [m]
        # From the writer's partial file on, a Ctrl-C is held until the loop's handlers below can close or drop it
        # (one between the writer and the loop once left the partial file behind under a loaded full suite).
        with DeferredSignals() as opening:
            writer = open_cache(out, model, fps=fps, start_frame=start, save_every=int(scene.get("output.save_every")),
                                normals=bool(scene.get("output.normals")), velocities=bool(scene.get("output.velocities")),
                                metadata=metadata, lock=lock)
            t_loop = time.perf_counter()
            interrupted = write_error = None
    except BaseException:
        lock.release()
        raise
    try:
        if opening.pending:
            raise KeyboardInterrupt
        if profile:
            profiling.enable(model.device)
        first = 0
        if source is not None:  # the earlier run's frames, then its state at the last of them
            from .cache import read_frames

            for k, (q, qd, diag) in enumerate(read_frames(source[0], model, source[1])):
                with DeferredSignals(raise_after=True):
                    writer.write(q, qd, diag, checkpoint=source[2] if k == source[1] - 1 else None)
                max_strain = max(max_strain, float(diag.get("maxStrain") or 0.0))
                worst_seam = max(worst_seam, float(diag.get("seamGap") or 0.0))
                worst_attachment = max(worst_attachment, float(diag.get("attachmentGap") or 0.0))
                if k > 0:
                    resumed_limit.append(diag)
            first = summary["frames"] = summary["resumed_frames"] = source[1] - 1
        else:
            with DeferredSignals(raise_after=True):
                writer.write(sim.state.particle_q.numpy(), sim.state.particle_qd.numpy(), checkpoint=sim.checkpoint())
        for f in range(first, n_frames):
            with stage("frame"):
                stats = sim.step_frame()
            report = sim.frame_report
            info = report.counters()
            diag = {"maxStrain": stats.max_strain, "dt": report.dt_min, "solverIterations": report.iterations,
                    "solverResidual": report.residual}
            diag.update({attr: info.get(key) for attr, key in COUNTER_DIAGNOSTICS.items()})
            diag.update({attr: info.get(key) for attr, key in STRAIN_LIMIT_DIAGNOSTICS.items()})
            q = sim.state.particle_q.numpy()
            if len(seams):
                diag["seamGap"] = seam_gap(model, q, seams)
                worst_seam = max(worst_seam, diag["seamGap"])
            if model.attachments:
                diag["attachmentGap"] = attachment_gap(model, q, sim.time)
                worst_attachment = max(worst_attachment, diag["attachmentGap"])
            # a frame is written whole: Ctrl-C waits for it (one inside numpy's zip writer of the checkpoint turned
            # into a ValueError, exit 1 with a traceback instead of 130)
            with stage("cache"), DeferredSignals() as held:
                writer.write(q, sim.state.particle_qd.numpy(), diag,
                             checkpoint=sim.checkpoint() if writer.save_due else None)
            for key in COLLISION_COUNTERS + SOLVE_CONTACT_COUNTERS:
                if key in info:
                    contacts[key] = contacts.get(key, 0) + info[key]
            max_strain = max(max_strain, stats.max_strain)
            dt_min, dt_max = min(dt_min, report.dt_min), max(dt_max, report.dt_max)
            iterations.append(report.iterations)
            rejected += report.rejected
            summary["frames"] = f + 1
            if progress is not None:
                summary["wall_s"] = time.perf_counter() - t_loop
                progress(f + 1, n_frames, summary)
            if held.pending:  # (the frame counted, then the interrupt)
                raise KeyboardInterrupt
        summary["status"] = "complete"
        cusick = scene.data.get("measure", {}).get("cusick")
        if cusick is not None:
            summary["drape_coefficient"] = _drape_coefficient(scene, model, sim.positions())
    except SimulationDiverged as exc:
        # frame: the simulation's frame number (the initial state is 0); time_code: where it would be in the cache
        summary.update(status="diverged", message=str(exc), diagnosis={**exc.diagnosis(), "time_code": start + summary["frames"] + 1})
    except (CacheWriteError, CacheError) as exc:  # a failed save, or an earlier cache that cannot be read back
        summary.update(status="failed", message=str(exc))
        write_error = exc if isinstance(exc, CacheWriteError) else SceneError(f"--resume: {exc}")
    except KeyboardInterrupt as exc:
        summary["status"] = "interrupted"
        interrupted = exc
    except BaseException:
        summary["status"] = "failed"
        raise
    finally:
        with DeferredSignals() as deferred:  # nothing stops the cache from closing (signals come after)
            wall = time.perf_counter() - t_loop
            done = summary["frames"]
            new = done - summary.get("resumed_frames", 0)
            if profile:
                profiling.disable()
                summary["profile"] = profiling.report(frames=new).to_dict()
            summary.update(
                wall_s=wall, total_s=time.perf_counter() - t_start, compile_s=compile_s,
                ms_per_frame=1e3 * wall / new if new else None, max_strain=max_strain,
                dt_min=dt_min if iterations else None, dt_max=dt_max if iterations else None, rejected_steps=rejected,
                solver_iterations={"mean": float(np.mean(iterations)), "max": int(np.max(iterations))} if iterations else None,
                colliders=model.collider_count, self_collision=bool(model.self_collision), contacts=contacts,
                strain_limit=strain_limit_summary(sim, resumed_limit),
            )
            if len(seams):
                summary["seam_gap"] = worst_seam
            if model.attachments:
                summary["attachment_gap"] = worst_attachment
            info = {k: summary[k] for k in ("frames", "wall_s", "max_strain", "compile_s", "drape_coefficient", "message", "diagnosis")
                    if k in summary}
            try:
                if source is not None and writer.frames_written < source[1]:
                    writer.abort()  # stopped while copying the earlier frames: the earlier cache stays as it was
                else:
                    # the last frame's state, when it is whole (an interruption or a divergence may have stopped a
                    # step half way: --resume then continues from the last save's checkpoint)
                    checkpoint = sim.checkpoint() if summary["status"] == "complete" and writer.broken is None else None
                    writer.close(summary["status"], info, checkpoint=checkpoint)
                    if summary["status"] == "complete":  # killed runs' partial files, superseded by this cache
                        for stale in stale_partials(out):
                            remove_partial(stale)
            except CacheWriteError as exc:
                if write_error is None:
                    summary.update(status="failed", message=str(exc))
                    write_error = exc
            finally:
                lock.release()
            if source is not None and source[0] != out and writer.saved_frames >= source[1]:
                remove_partial(source[0])  # the dead run's partial file, now continued in the cache
            summary.update(frames_written=writer.saved_frames, end_frame=start + writer.saved_frames - 1,
                           output_bytes=out.stat().st_size if out.exists() else 0)
        if deferred.pending and interrupted is None:
            summary["status"] = "interrupted"
            interrupted = KeyboardInterrupt()
    summary = _finite(summary)
    limit = summary.get("strain_limit")
    if limit and limit["missed_frames"]:
        from .solvers.strain_limit import StrainLimitWarning

        warnings.warn(strain_limit_message(limit), StrainLimitWarning, stacklevel=2)
    for exc in (write_error, interrupted):
        if exc is not None:
            exc.summary = summary
            raise exc
    return summary
