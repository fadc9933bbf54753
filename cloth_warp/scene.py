"""Scene files (TOML): validation with the offending key path, model/solver construction, runs.

The schema (every key optional unless marked; units SI):

    [cloth]                 grid = {resolution = [nx, ny], size = [sx, sy] [m]} or mesh = "file.obj" (relative
                            to the scene file), scale, position [m], rotation = {axis = [x, y, z], angle [deg]},
                            velocity [m/s], spring_model = "choi_ko" | "provot", name
    [material]              preset = "cotton" | "denim" | "silk" | "polyester" | "knit" | "wool", and any of
                            areal_density [kg/m^2], stretch_stiffness [N/m], shear_stiffness [N/m],
                            bend_stiffness [N m], damping [s], drag_coefficient [N s/m^3] (override the preset)
    [[pins]]                select = "corners" | "corner:..." | "edge:...", or indices = [...], or
                            box = {min = [...], max = [...]}; stiffness [N/m] for a soft pin
    [[handles]]             like pins, plus keyframes = [{time [s], translation [m], rotation = {axis, angle}}]
    [forces]                up_axis = "Y" | "Z", gravity [m/s^2], wind [m/s], global_damping [1/s]
    [solver]                integrator (see cloth_warp.solvers.SOLVERS), linear_solver = "cg" | "jacobi",
                            substeps, strain_limit (0 disables), strain_limit_iterations, tolerance,
                            max_iterations, adaptive, dt_min [s]
    [output]                frames, fps, path (.npz; relative to the scene file)
    [colliders]             reserved for the collisions issue
"""

from __future__ import annotations

import difflib
import json
import logging
import math
import os
import pathlib
import time
import tomllib
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)


class SceneError(ValueError):
    """A scene that cannot run; the message names the key path and what is allowed."""


SCHEMA = {
    "cloth": {"grid": {"resolution": list, "size": list}, "mesh": str, "scale": float, "position": list,
              "rotation": {"axis": list, "angle": float}, "velocity": list, "spring_model": str, "name": str},
    "material": {"preset": str, "areal_density": float, "stretch_stiffness": float, "shear_stiffness": float,
                 "bend_stiffness": float, "damping": float, "drag_coefficient": float},
    "pins": [{"select": str, "indices": list, "box": {"min": list, "max": list}, "stiffness": float}],
    "handles": [{"select": str, "indices": list, "box": {"min": list, "max": list},
                 "keyframes": [{"time": float, "translation": list, "rotation": {"axis": list, "angle": float}}]}],
    "forces": {"up_axis": str, "gravity": list, "wind": list, "global_damping": float},
    "solver": {"integrator": str, "linear_solver": str, "substeps": int, "strain_limit": float,
               "strain_limit_iterations": int, "tolerance": float, "max_iterations": int, "adaptive": bool, "dt_min": float},
    "output": {"frames": int, "fps": float, "path": str},
    "colliders": list,
}


def _check(value, schema, path: str):
    if isinstance(schema, dict):
        if not isinstance(value, dict):
            raise SceneError(f"{path or 'scene'}: expected a table, got {type(value).__name__}")
        for key, item in value.items():
            kp = f"{path}.{key}" if path else key
            if key not in schema:
                close = difflib.get_close_matches(key, schema.keys(), n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise SceneError(f"unknown key {kp!r}{hint}; allowed: {', '.join(sorted(schema))}")
            _check(item, schema[key], kp)
    elif isinstance(schema, list):
        if not isinstance(value, list):
            raise SceneError(f"{path}: expected an array, got {type(value).__name__}")
        if schema:
            for i, item in enumerate(value):
                _check(item, schema[0], f"{path}[{i}]")
    elif schema is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise SceneError(f"{path}: expected a finite number, got {value!r}")
    elif schema is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SceneError(f"{path}: expected an integer, got {value!r}")
    elif not isinstance(value, schema):
        raise SceneError(f"{path}: expected {schema.__name__}, got {type(value).__name__} {value!r}")


def _set_key(data: dict, dotted: str, value):
    keys = dotted.split(".")
    node = data
    for k in keys[:-1]:
        node = node.setdefault(k, {})
        if not isinstance(node, dict):
            raise SceneError(f"--set {dotted}: {k!r} is not a table")
    node[keys[-1]] = value


@dataclass
class Scene:
    """A validated scene: its data, where it came from and how to resolve relative paths."""

    data: dict
    path: pathlib.Path | None = None
    overrides: dict = field(default_factory=dict)

    @property
    def base(self) -> pathlib.Path:
        return self.path.parent if self.path else pathlib.Path.cwd()

    def get(self, dotted: str, default=None):
        node = self.data
        for k in dotted.split("."):
            if not isinstance(node, dict) or k not in node:
                return default
            node = node[k]
        return node


def load_scene(path, overrides: dict | None = None) -> Scene:
    """Read and validate a TOML scene; `overrides` maps dotted key paths to values (like --set)."""
    path = pathlib.Path(path)
    if not path.exists():
        raise SceneError(f"scene file not found: {path}")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{path}: TOML syntax error: {exc}") from exc
    for key, value in (overrides or {}).items():
        _set_key(data, key, value)
    _check(data, SCHEMA, "")
    scene = Scene(data, path, dict(overrides or {}))
    _check_values(scene)
    return scene


def _vec(scene: Scene, key: str, n: int = 3, default=None):
    v = scene.get(key, default)
    if v is None:
        return None
    if len(v) != n or not all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in v):
        raise SceneError(f"{key}: expected {n} finite numbers, got {v!r}")
    return tuple(float(c) for c in v)


def _check_values(scene: Scene):
    from .materials import PRESETS
    from .solvers import SOLVERS

    grid, mesh = scene.get("cloth.grid"), scene.get("cloth.mesh")
    if grid is not None and mesh is not None:
        raise SceneError("cloth: give either cloth.grid or cloth.mesh, not both")
    if grid is not None:
        res = scene.get("cloth.grid.resolution", [32, 32])
        if len(res) != 2 or not all(isinstance(r, int) and not isinstance(r, bool) and r >= 1 for r in res):
            raise SceneError(f"cloth.grid.resolution: expected two integers >= 1, got {res!r}")
        size = _vec(scene, "cloth.grid.size", 2, [1.0, 1.0])
        if min(size) <= 0:
            raise SceneError(f"cloth.grid.size: expected two positive lengths [m], got {list(size)}")
    if mesh is not None and not (scene.base / mesh).exists():
        raise SceneError(f"cloth.mesh: file not found: {scene.base / mesh}")
    for key in ("cloth.position", "cloth.velocity", "cloth.rotation.axis", "forces.gravity", "forces.wind"):
        _vec(scene, key)
    sm = scene.get("cloth.spring_model", "choi_ko")
    if sm not in ("choi_ko", "provot"):
        raise SceneError(f"cloth.spring_model: {sm!r} is not allowed; allowed: choi_ko, provot")
    preset = scene.get("material.preset")
    if preset is not None and preset.lower() not in PRESETS:
        raise SceneError(f"material.preset: unknown preset {preset!r}; allowed: {', '.join(sorted(PRESETS))}")
    for key in ("areal_density", "stretch_stiffness"):
        v = scene.get(f"material.{key}")
        if v is not None and v <= 0:
            raise SceneError(f"material.{key}: must be > 0, got {v!r}")
    for key in ("shear_stiffness", "bend_stiffness", "damping", "drag_coefficient"):
        v = scene.get(f"material.{key}")
        if v is not None and v < 0:
            raise SceneError(f"material.{key}: must be >= 0, got {v!r}")
    integ = scene.get("solver.integrator", "implicit_euler")
    if integ not in SOLVERS:
        raise SceneError(f"solver.integrator: {integ!r} is not allowed; allowed: {', '.join(SOLVERS)}")
    ls = scene.get("solver.linear_solver", "cg")
    if ls not in ("cg", "jacobi"):
        raise SceneError(f"solver.linear_solver: {ls!r} is not allowed; allowed: cg, jacobi")
    for key, lo in (("solver.substeps", 1), ("output.frames", 1), ("solver.max_iterations", 1), ("solver.strain_limit_iterations", 1)):
        v = scene.get(key)
        if v is not None and v < lo:
            raise SceneError(f"{key}: must be >= {lo}, got {v!r}")
    for key in ("output.fps", "solver.tolerance", "solver.dt_min"):
        v = scene.get(key)
        if v is not None and v <= 0:
            raise SceneError(f"{key}: must be > 0, got {v!r}")
    sl = scene.get("solver.strain_limit")
    if sl is not None and sl < 0:
        raise SceneError(f"solver.strain_limit: must be >= 0 (0 disables), got {sl!r}")
    ua = scene.get("forces.up_axis", "Y")
    if ua not in ("Y", "Z"):
        raise SceneError(f"forces.up_axis: {ua!r} is not allowed; allowed: Y, Z")
    for i, pin in enumerate(scene.get("pins", [])):
        if sum(k in pin for k in ("select", "indices", "box")) != 1:
            raise SceneError(f"pins[{i}]: give exactly one of select, indices, box")


def _rotation(scene: Scene, key: str):
    rot = scene.get(key)
    return None if rot is None else _rotation_q(rot)


def _selection(cloth, spec: dict, where: str):
    try:
        if "select" in spec:
            return cloth.select(spec["select"])
        if "indices" in spec:
            return cloth.indices(spec["indices"])
        box = spec["box"]
        return cloth.select_box(box["min"], box["max"])
    except (ValueError, IndexError, KeyError) as exc:
        raise SceneError(f"{where}: {exc}") from exc


def build(scene: Scene, device=None):
    """Model, solver and run settings from a scene."""
    from . import materials
    from .builder import ModelBuilder
    from .model import Keyframe
    from .solvers import make_solver

    up = scene.get("forces.up_axis", "Y")
    b = ModelBuilder(up_axis=up, gravity=_vec(scene, "forces.gravity"), global_damping=float(scene.get("forces.global_damping", 0.0)))
    mat = materials.preset(scene.get("material.preset", "cotton"))
    changes = {k: float(v) for k, v in scene.get("material", {}).items() if k != "preset"}
    if changes:
        mat = mat.replace(name=f"{mat.name}*", **changes)
    common = dict(position=_vec(scene, "cloth.position", default=[0, 0, 0]), rotation=_rotation(scene, "cloth.rotation"),
                  velocity=_vec(scene, "cloth.velocity", default=[0, 0, 0]), material=mat,
                  spring_model=scene.get("cloth.spring_model", "choi_ko"), name=scene.get("cloth.name", "cloth"))
    if scene.get("cloth.mesh") is not None:
        cloth = b.add_cloth_mesh_file(scene.base / scene.get("cloth.mesh"), scale=float(scene.get("cloth.scale", 1.0)), **common)
    else:
        cloth = b.add_cloth_grid(resolution=tuple(scene.get("cloth.grid.resolution", [32, 32])),
                                 size=_vec(scene, "cloth.grid.size", 2, [1.0, 1.0]), **common)
    for i, pin in enumerate(scene.get("pins", [])):
        b.pin(_selection(cloth, pin, f"pins[{i}]"), stiffness=pin.get("stiffness"))
    for i, h in enumerate(scene.get("handles", [])):
        kfs = [Keyframe(float(k["time"]), tuple(k.get("translation", [0, 0, 0])), _rotation_q(k.get("rotation")))
               for k in h.get("keyframes", [])]
        b.add_handle(_selection(cloth, h, f"handles[{i}]"), kfs)
    model = b.finalize(device)
    opts = {}
    integ = scene.get("solver.integrator", "implicit_euler")
    sl = scene.get("solver.strain_limit", 0.1)
    opts["strain_limit"] = float(sl) if sl else None
    if scene.get("solver.strain_limit_iterations") is not None:
        opts["strain_limit_iterations"] = int(scene.get("solver.strain_limit_iterations"))
    if integ == "implicit_euler":
        opts["linear_solver"] = scene.get("solver.linear_solver", "cg")
        for key in ("tolerance", "max_iterations"):
            if scene.get(f"solver.{key}") is not None:
                opts[key] = scene.get(f"solver.{key}")
    solver = make_solver(integ, model, **opts)
    return model, solver


def _rotation_q(rot):
    from .builder import quat_from_axis_angle

    if rot is None:
        return (0.0, 0.0, 0.0, 1.0)
    return quat_from_axis_angle(rot.get("axis", [0, 0, 1]), float(rot.get("angle", 0.0)))


def run_scene(path, overrides: dict | None = None, *, output=None, frames=None, fps=None, device=None,
              progress=None) -> dict:
    """Run a scene file and write its frames; returns the run summary (also on failure, in 'status').

    The output (.npz: `positions` (frames + 1, particles, 3) [m] including the rest pose, `triangles`,
    `fps`, `scene`) is written to a temporary name and renamed, so a file under the final name is always
    complete; a diverged or interrupted run still writes the frames done.
    """
    from .simulator import Simulator
    from .solvers import SimulationDiverged

    scene = load_scene(path, overrides)
    model, solver = build(scene, device)
    fps = float(fps or scene.get("output.fps", 60.0))
    n_frames = int(frames or scene.get("output.frames", 60))
    out = pathlib.Path(output) if output else scene.base / scene.get("output.path", f"out/{scene.path.stem}.npz")
    sim = Simulator(model, solver, fps=fps, substeps=int(scene.get("solver.substeps", 1)),
                    adaptive=bool(scene.get("solver.adaptive", False)), dt_min=float(scene.get("solver.dt_min", 1e-6)))
    positions = [sim.positions()]
    summary = {"scene": str(scene.path), "frames": 0, "fps": fps, "particles": model.particle_count,
               "springs": model.spring_count, "integrator": solver.name, "status": "running", "output": str(out)}
    t0 = time.perf_counter()
    max_strain, iterations = 0.0, []
    try:
        for f in range(n_frames):
            stats = sim.step_frame()
            positions.append(sim.positions())
            max_strain = max(max_strain, stats.max_strain)
            iterations.append(getattr(solver, "last_iterations", 0))
            summary["frames"] = f + 1
            if progress:
                progress(f + 1, n_frames, stats, time.perf_counter() - t0)
        summary["status"] = "done"
    except SimulationDiverged as exc:
        summary.update(status="diverged", message=str(exc))
    except KeyboardInterrupt:
        summary.update(status="interrupted")
    finally:
        wall = time.perf_counter() - t0
        summary.update(wall_s=wall, ms_per_frame=1e3 * wall / max(summary["frames"], 1), max_strain=max_strain,
                       mean_solver_iterations=float(np.mean(iterations)) if iterations else 0.0)
        write_frames(out, np.stack(positions), model, fps, scene)
    return summary


def write_frames(path: pathlib.Path, positions: np.ndarray, model, fps: float, scene: Scene):
    """Write frames atomically (temporary name in the same folder, then rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        np.savez_compressed(fh, positions=positions.astype(np.float32), triangles=model.tri_indices.numpy(), fps=fps,
                            scene=json.dumps(scene.data))
    os.replace(tmp, path)
