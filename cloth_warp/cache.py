"""Animation caches: USD (.usdc / .usda / .usd) written frame by frame, and .npz for numpy users.

A USD cache is what DCC tools (usdview, Houdini, Blender, Maya, Omniverse) play:

* stage metadata: ``upAxis`` (the simulation's own; points are never rotated), ``metersPerUnit = 1``,
  ``kilogramsPerUnit = 1``, ``timeCodesPerSecond = framesPerSecond = fps``, start/end time codes = the
  frames written (updated as frames land); time codes come from an integer frame counter;
* a root ``Xform`` (``/World``) that is the ``defaultPrim`` with one ``Mesh`` per cloth: static topology
  (authored once, never time-sampled), ``subdivisionScheme = "none"``, ``doubleSided = 1``, indexed
  face-varying ``primvars:st`` (per corner, so UV seams of a welded mesh survive); ``points`` time-sampled
  plus a default value (the rest pose), ``extent``, vertex ``normals`` and ``velocities`` [m/s] per frame, and
  ``primvars:strain`` per vertex and per frame (indexed; each vertex's largest strain l / L - 1 over its mesh edges:
  DCC tools keep vertex primvars they read per frame, where Blender drops per-frame constant attributes); bound to a
  UsdPreviewSurface material of its fabric's colour (``/World/Looks``, :mod:`cloth_warp.looks`), the same colour as
  ``displayColor``;
* per-frame diagnostics as custom attributes on each cloth prim (``clothWarp:maxStrain``,
  ``clothWarp:dt`` [s], ``clothWarp:solverIterations``, ``clothWarp:solverResidual``,
  ``clothWarp:colliderContacts``, ``clothWarp:colliderCcd``, ``clothWarp:colliderSamples``, with contacts in the implicit
  solve ``solveContacts`` and ``solveSelfContacts``, and, with self-collision, ``clothWarp:selfProximity``,
  ``selfCcd``, ``selfSweeps``, ``impactZones``, ``selfUnresolved`` and, with strain limiting,
  ``strainExcessStructural``, ``strainExcessShear``, ``strainLimitSweeps``, ``strainLimitMissed`` and, for a sewn
  garment, ``seamGap`` [m]);
* colliders under ``/World/colliders`` as UsdGeom Cube (scaled) / Plane / Mesh prims -- spheres, capsules and
  cylinders (axis Z) as meshes whose facets stay within 0.5 mm of the surface (:data:`ROUND_SAGITTA`; a DCC's own
  tessellation of an implicit sphere leaves cloth floating above it), their radius and height in customData -- with
  a translate and an orient op (time-sampled per frame when animated), bound to a ground / solid / body material,
  and their shape, thickness and friction in the prim's customData;
* provenance in the layer's ``customLayerData["cloth_warp"]``: versions, scene, resolved settings,
  status (``running`` / ``complete`` / ``interrupted`` / ``diverged`` / ``failed``), frames written.

The first frame written is the initial state at ``start_frame``; frame k of the simulation is time code
``start_frame + k``. A run takes the output's lock (a second live run on the same output is refused),
authors into ``<stem>.partial-<pid><ext>`` next to the final path and saves it every ``save_every`` frames
(crate saves are incremental and release the samples, which bounds memory; a save that fails -- disk full,
I/O error -- is rolled back to the last good save: :class:`~cloth_warp.outputs.CrateRollback`); ``.usda``
and ``.npz`` rewrite the whole file at each save, so they save at save_every x 1, 2, 4, ... frames, each
to a temporary name renamed over the last. :meth:`CacheWriter.close` stamps the status and renames the
partial file (as of its last good save) to the final name -- also after an interruption, a divergence or
a failed save -- so a file under the final name is always a valid cache of the frames it says it holds
(``frames_written``). A hard kill (SIGKILL, power loss) leaves the partial file as of its last save
(status ``partial``), which ``cloth-warp run --resume`` continues (a kill inside a crate save leaves its
rollback journal, and ``--resume`` first rolls the file back: :func:`~cloth_warp.outputs.recover_partial`).
Each save also stores the simulator's checkpoint at the last frame written (:func:`read_checkpoint`), a custom
attribute of ``/World``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import logging
import math
import os
import pathlib
import platform

import numpy as np

from . import looks
from .topology import seam_roots
from .outputs import (USD_SUFFIXES, CacheWriteError, CrateRollback, OutputLock, atomic_path, check_output, partial_path,
                      remove_partial, usd_error_text)

log = logging.getLogger(__name__)

CACHE_SUFFIXES = USD_SUFFIXES + (".npz",)
DIAGNOSTICS = {  # per-frame custom attributes: name -> (USD type name, description)
    "maxStrain": ("float", "max structural/shear strain l/L - 1 at the end of the frame"),
    "dt": ("float", "smallest step used in the frame [s]"),
    "solverIterations": ("int", "linear-solver iterations of the frame's steps (summed; 0 for explicit integrators)"),
    "solverResidual": ("float", "relative residual of the last linear solve in the frame (0 if none)"),
    "colliderContacts": ("int", "particle-collider contacts resolved in the frame's steps (summed)"),
    "colliderCcd": ("int", "of those, contacts only the continuous (swept) test found (summed)"),
    "colliderSamples": ("int", "cloth edge and triangle samples pushed out of mesh colliders in the frame's steps (summed)"),
    "solveContacts": ("int", "particle-collider contacts held inside the implicit solve in the frame's steps (summed)"),
    "solveSelfContacts": ("int", "cloth-cloth contact elements held inside the implicit solve in the frame's steps (summed)"),
    "selfProximity": ("int", "cloth-cloth repulsion impulses (proximity within the thickness) in the frame's steps"),
    "selfCcd": ("int", "cloth-cloth impacts found by continuous collision detection (summed over sweeps)"),
    "selfSweeps": ("int", "CCD sweeps with impulses run in the frame's steps"),
    "impactZones": ("int", "rigid impact zones formed in the frame's steps (Provot's fail-safe)"),
    "selfUnresolved": ("int", "steps that ended with cloth-cloth impacts left (should be 0)"),
    "strainExcessStructural": ("float", "worst strain above the strain limit on structural springs after limiting, in the frame's steps"),
    "strainExcessShear": ("float", "worst strain above the strain limit on shear springs after limiting, in the frame's steps"),
    "strainLimitSweeps": ("int", "strain-limit sweeps run in the frame's steps (summed)"),
    "strainLimitMissed": ("int", "steps whose strain limiting stopped at its cap above its tolerance (should be 0)"),
    "seamGap": ("float", "largest distance between sewn particles at the end of the frame [m] (0 without seams)"),
    "attachmentGap": ("float", "largest distance between an attached particle and its point on the body at the end of the frame [m]"),
}
# per-frame diagnostic attribute <- collision counter (cloth_warp.collision / cloth_warp.selfcollision)
COUNTER_DIAGNOSTICS = {"colliderContacts": "collider_contacts", "colliderCcd": "collider_ccd", "colliderSamples": "collider_samples",
                       "solveContacts": "solve_contacts", "solveSelfContacts": "solve_self_contacts",
                       "selfProximity": "self_proximity", "selfCcd": "self_ccd", "selfSweeps": "self_sweeps",
                       "impactZones": "impact_zones", "selfUnresolved": "unresolved"}
# per-frame diagnostic attribute <- the strain limiter's report (FrameReport.counters)
STRAIN_LIMIT_DIAGNOSTICS = {"strainExcessStructural": "strain_excess_structural", "strainExcessShear": "strain_excess_shear",
                            "strainLimitSweeps": "strain_limit_sweeps", "strainLimitMissed": "strain_limit_missed"}
COLLIDER_SCOPE = "colliders"  # colliders are written under /World/colliders
LOOKS_SCOPE = "Looks"  # materials under /World/Looks
STRAIN_PRIMVAR = "strain"  # per-vertex strain, time-sampled (primvars:strain)


def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (float32, (n, 3)); isolated or degenerate vertices get +z."""
    p = np.asarray(points, np.float64)
    t = np.asarray(triangles)
    fn = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])  # 2 x area x unit normal
    n = np.zeros_like(p)
    for c in range(3):
        for k in range(3):
            n[:, k] += np.bincount(t[:, c], weights=fn[:, k], minlength=len(p))
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, length, out=np.tile([0.0, 0.0, 1.0], (len(p), 1)), where=length > 1e-30)
    return n.astype(np.float32)


def package_versions() -> dict:
    """Versions stamped into caches and run summaries."""
    import warp as wp
    from pxr import Usd

    from . import __version__

    versions = {"cloth_warp": __version__, "warp": wp.config.version, "usd": ".".join(map(str, Usd.GetVersion())),
                "numpy": np.__version__, "python": platform.python_version()}
    try:
        import trimesh

        versions["trimesh"] = trimesh.__version__
    except ImportError:  # pragma: no cover - a core dependency
        pass
    return versions


def _prim_name(name: str) -> str:
    from pxr import Tf

    return Tf.MakeValidIdentifier(name or "cloth")


@dataclasses.dataclass(frozen=True)
class ClothMesh:
    """A cloth as the cache writes it: its prim name, particle slice, triangles (local particle indices; a garment's
    as its panels have them, each panel its own particles), corner UVs
    (t, 3, 2) or None, fabric name, its own rest positions [m] (as built: lengths are the rest lengths), and for a
    sewn garment `weld`: per local particle the seam point it is one with."""

    name: str
    particles: slice
    panel_triangles: np.ndarray
    corner_uv: np.ndarray | None
    fabric: str
    rest_positions: np.ndarray
    weld: np.ndarray | None = None

    @property
    def triangles(self) -> np.ndarray:
        """The triangles written: a sewn garment is one surface, its seams' triangles share each seam point's first
        particle (the others stay as points)."""
        return self.panel_triangles if self.weld is None else self.weld[self.panel_triangles].astype(np.int32)

    def edges(self) -> tuple[np.ndarray, np.ndarray]:
        """(the written mesh's unique edges (e, 2), their rest lengths [m])."""
        edges = triangle_edges(self.panel_triangles)
        rest = self.rest_positions
        length = np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)
        if self.weld is None:
            return edges, length
        edges, first = np.unique(np.sort(self.weld[edges], axis=1), axis=0, return_index=True)
        return edges, length[first]


def _cloth_meshes(model):
    """(name, particle slice, triangles local to the cloth, corner uvs or None, fabric name) per cloth of the model; a
    sewn garment's triangles refer to the first particle of each seam point (its other particles stay as points)."""
    tris = model.tri_indices.numpy()
    roots = seam_roots(model)
    out, used = [], set()
    for info in model.cloths:
        name = _prim_name(info.name)
        while name in used:
            name += "_"
        used.add(name)
        start = info.particle_start
        t = tris[info.triangles] - start
        weld = None
        if roots is not None:
            local = roots[info.particles] - start
            if np.any(local != np.arange(len(local))):
                weld = local
        uv = info.topology.corner_uv
        fabric = getattr(info.material, "name", None) or "custom"
        out.append(ClothMesh(name, info.particles, t.astype(np.int32), None if uv is None else np.asarray(uv), fabric,
                             np.asarray(info.topology.positions, np.float64), weld))
    return out


def triangle_edges(tris: np.ndarray) -> np.ndarray:
    """The unique edges (e, 2) of a triangle mesh."""
    e = np.sort(np.asarray(tris, np.int64)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0)


def vertex_strain(x: np.ndarray, edges: np.ndarray, rest_length: np.ndarray) -> np.ndarray:
    """Per vertex the largest strain l / L - 1 of its mesh edges (0 for a vertex without edges)."""
    strain = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1) / rest_length - 1.0
    out = np.full(len(x), -np.inf)
    np.maximum.at(out, edges[:, 0], strain)
    np.maximum.at(out, edges[:, 1], strain)
    return np.where(np.isfinite(out), out, 0.0).astype(np.float32)


ROUND_SAGITTA = 5.0e-4
"""Round colliders (sphere, capsule, cylinder) are written as meshes whose facets lie at most this far [m] inside
the true surface (a DCC tessellates implicit spheres coarsely: a 10-segment ball shows cloth floating 1-2 cm above it)."""


def round_segments(radius: float, sagitta: float = ROUND_SAGITTA) -> int:
    """Segments around a circle of `radius` [m] whose chords stay within `sagitta` [m] of it (16 to 256: past a
    2.6 m radius the chords sit farther in, by 0.5 mm x (radius / 2.6 m))."""
    if radius <= sagitta:
        return 16
    return int(np.clip(np.ceil(np.pi / np.arccos(1.0 - sagitta / radius)), 16, 256))


def round_collider_mesh(col):
    """(vertices, triangles) in the collider's local frame (axis Z for capsules and cylinders) for a round collider."""
    import trimesh

    n = round_segments(col.radius)
    if col.shape == "sphere":
        m = trimesh.creation.uv_sphere(radius=col.radius, count=[n, n])
    elif col.shape == "capsule":  # (its facets between the caps' rows sit ~1.2 chords' sagitta in: half per chord)
        m = trimesh.creation.capsule(height=col.height, radius=col.radius, count=[round_segments(col.radius, 0.5 * ROUND_SAGITTA)] * 2)
        m.apply_translation(-0.5 * (m.bounds[0] + m.bounds[1]))
    else:
        m = trimesh.creation.cylinder(radius=col.radius, height=col.height, sections=n)
    return np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.int32)


def _indexed_corner_uvs(corner_uv: np.ndarray):
    """Unique UV values and per-corner indices (faceVarying, indexed) from (t, 3, 2) corner UVs."""
    flat = np.asarray(corner_uv, np.float32).reshape(-1, 2)
    values, indices = np.unique(flat, axis=0, return_inverse=True)
    return values.astype(np.float32), indices.reshape(-1).astype(np.int32)


def _define_colliders(stage, model) -> list:
    """Collider prims under /World/colliders (UsdGeom Cube and Plane; meshes for mesh colliders and, tessellated, for
    round ones) with a translate and an orient op, bound to their look's material (defined once per look used);
    returns (collider, translate op, orient op, geom) per collider."""
    from pxr import Gf, UsdGeom, Vt

    if not getattr(model, "colliders", None):
        return []
    UsdGeom.Scope.Define(stage, f"/World/{COLLIDER_SCOPE}")
    out, materials = [], {}
    for col in model.colliders:
        path = f"/World/{COLLIDER_SCOPE}/{_prim_name(col.name)}"
        if col.shape == "box":
            geom = UsdGeom.Cube.Define(stage, path)
            geom.CreateSizeAttr(1.0)
            extent = [(-0.5,) * 3, (0.5,) * 3]
        elif col.shape == "plane":
            geom = UsdGeom.Plane.Define(stage, path)
            geom.CreateAxisAttr(UsdGeom.Tokens.z)
            geom.CreateWidthAttr(20.0)
            geom.CreateLengthAttr(20.0)
            geom.CreateDoubleSidedAttr(False)
            extent = [(-10.0, -10.0, 0.0), (10.0, 10.0, 0.0)]
        else:  # mesh colliders, and round ones tessellated finely (round_collider_mesh)
            geom = UsdGeom.Mesh.Define(stage, path)
            geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            if col.shape == "mesh":
                tris, pts = np.asarray(col.triangles, np.int32), np.asarray(col.vertices, np.float32)
            else:
                pts, tris = round_collider_mesh(col)
            geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
            geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(tris), 3, np.int32)))
            geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(tris.reshape(-1))))
            extent = [tuple(pts.min(0)), tuple(pts.max(0))]
        geom.CreateExtentAttr([Gf.Vec3f(*map(float, e)) for e in extent])
        look = looks.collider_look(col.shape, bool(col.deforming))
        if look not in materials:
            materials[look] = looks.define_material(stage, f"/World/{LOOKS_SCOPE}/{look}", looks.COLLIDER_COLORS[look], looks.ROUGHNESS[look])
        looks.bind_look(geom, materials[look], looks.COLLIDER_COLORS[look])
        prim = geom.GetPrim()
        shape = {"shape": col.shape, "thickness": float(col.thickness), "staticFriction": float(col.static_friction),
                 "kineticFriction": float(col.kinetic_friction)}
        if col.shape in ("sphere", "capsule", "cylinder"):  # the exact shape beside its tessellation
            shape.update(radius=float(col.radius), **({"height": float(col.height), "axis": "Z"} if col.shape != "sphere" else {}))
        prim.SetCustomDataByKey("clothWarp:collider", shape)
        translate = geom.AddTranslateOp()
        orient = geom.AddOrientOp()
        if col.shape == "box":
            geom.AddScaleOp().Set(Gf.Vec3f(*map(float, col.size)))
        out.append((col, translate, orient, geom))
    return out


def collider_surface(prim, time) -> tuple[np.ndarray, np.ndarray]:
    """World-space (vertices [m], triangles) of a collider prim written by the cache at `time` (for previews)."""
    import trimesh
    from pxr import UsdGeom

    if prim.IsA(UsdGeom.Mesh):
        mesh = UsdGeom.Mesh(prim)
        v = np.asarray(mesh.GetPointsAttr().Get(time), np.float64)
        t = fan_triangulate(np.asarray(mesh.GetFaceVertexCountsAttr().Get()), np.asarray(mesh.GetFaceVertexIndicesAttr().Get()))
    else:
        if prim.IsA(UsdGeom.Sphere):
            m = trimesh.creation.uv_sphere(radius=UsdGeom.Sphere(prim).GetRadiusAttr().Get(), count=[24, 24])
        elif prim.IsA(UsdGeom.Capsule):
            g = UsdGeom.Capsule(prim)
            m = trimesh.creation.capsule(height=g.GetHeightAttr().Get(), radius=g.GetRadiusAttr().Get(), count=[24, 24])
            m.apply_translation(-0.5 * (m.bounds[0] + m.bounds[1]))
        elif prim.IsA(UsdGeom.Cylinder):
            g = UsdGeom.Cylinder(prim)
            m = trimesh.creation.cylinder(radius=g.GetRadiusAttr().Get(), height=g.GetHeightAttr().Get(), sections=32)
        elif prim.IsA(UsdGeom.Cube):
            s = UsdGeom.Cube(prim).GetSizeAttr().Get()
            m = trimesh.creation.box(extents=(s, s, s))
        else:  # plane
            g = UsdGeom.Plane(prim)
            w, ln = 0.5 * g.GetWidthAttr().Get(), 0.5 * g.GetLengthAttr().Get()
            m = trimesh.Trimesh([[-w, -ln, 0], [w, -ln, 0], [w, ln, 0], [-w, ln, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
        v, t = np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int32)
    xf = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time), np.float64)  # row vectors
    return v @ xf[:3, :3] + xf[3, :3], t


CHECKPOINT_PRIM = "/World"  # the root Xform carries the resume checkpoint as a custom attribute
CHECKPOINT_ATTR = "clothWarp:checkpoint"


def pack_checkpoint(checkpoint: dict) -> bytes:
    """A simulator checkpoint ({name: array or scalar}) as bytes (an uncompressed .npz: exact, no pickle)."""
    buf = io.BytesIO()
    np.savez(buf, **{k: np.asarray(v) for k, v in checkpoint.items()})
    return buf.getvalue()


def unpack_checkpoint(data) -> dict:
    """Inverse of :func:`pack_checkpoint` (0-d arrays come back as Python scalars)."""
    with np.load(io.BytesIO(bytes(np.asarray(data, np.uint8))), allow_pickle=False) as z:
        return {k: (z[k].item() if z[k].ndim == 0 else z[k]) for k in z.files}


def read_checkpoint(path) -> tuple[int, dict, dict]:
    """(frames in the cache, the simulator checkpoint taken at its last frame, its provenance metadata) of a
    cache written with checkpoints (``cloth-warp run`` stores one at every save); raises ValueError if none."""
    path = pathlib.Path(path)
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as z:
            if "checkpoint" not in z.files:
                raise ValueError(f"{path}: holds no resume checkpoint")
            meta = json.loads(str(z["metadata"]))
            return int(z["checkpoint_frames"]), unpack_checkpoint(z["checkpoint"]), meta
    from pxr import Sdf, Tf

    try:
        layer = Sdf.Layer.OpenAsAnonymous(str(path))
    except Tf.ErrorException as exc:
        raise ValueError(f"{path}: cannot be read as USD: {usd_error_text(exc)}") from None
    if layer is None:
        raise ValueError(f"{path}: cannot be read as USD")
    meta = dict(layer.customLayerData.get("cloth_warp", {}))
    spec = layer.GetAttributeAtPath(f"{CHECKPOINT_PRIM}.{CHECKPOINT_ATTR}")
    times = layer.ListTimeSamplesForPath(spec.path) if spec else []
    if not times:
        raise ValueError(f"{path}: holds no resume checkpoint")
    tc = max(times)
    frames = int(round(tc)) - int(meta.get("start_frame", 1)) + 1
    return frames, unpack_checkpoint(np.asarray(layer.QueryTimeSample(spec.path, tc), np.uint8)), meta


def read_frames(path, model, count: int):
    """Yield (positions, velocities, diagnostics) of the first `count` frames of a cache of `model` written
    by cloth_warp (what ``--resume`` copies into the continued cache); velocities are zero where the cache
    has none. A cache that does not hold them raises :class:`CacheError`."""
    path = pathlib.Path(path)
    n = model.particle_count
    if path.suffix.lower() == ".npz":
        with np.load(path, allow_pickle=False) as z:  # each z[key] decompresses the whole array: read once
            q_all, qd_all = z["positions"], z["velocities"]
            diag = {k: z[k] for k in DIAGNOSTICS if k in z.files}
        if q_all.shape[0] < count or q_all.shape[1:] != (n, 3) or qd_all.shape != q_all.shape:
            raise CacheError(f"{path}: holds {q_all.shape[0]} frames of shape {q_all.shape[1:]}, expected {count} of ({n}, 3)")
        for k in range(count):
            yield q_all[k], qd_all[k], {d: _diag_value(d, v[k]) for d, v in diag.items()}
        return
    from pxr import Usd

    with usd_errors(path):
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
        start = int(stage.GetStartTimeCode())
        prims = [(stage.GetPrimAtPath(f"/World/{c.name}"), c.particles) for c in _cloth_meshes(model)]
        if not all(p.IsValid() for p, _ in prims):
            raise CacheError(f"{path}: its meshes are not this scene's cloths")
        diag_attrs = {d: prims[0][0].GetAttribute(f"clothWarp:{d}") for d in DIAGNOSTICS}
        diag_times = {d: set(a.GetTimeSamples()) for d, a in diag_attrs.items() if a}
    for k in range(count):
        tc = start + k
        q, qd = np.zeros((n, 3), np.float32), np.zeros((n, 3), np.float32)
        with usd_errors(path):
            for prim, particles in prims:
                q[particles] = _sample(path, prim.GetAttribute("points"), tc, len(q[particles]))
                velocities = prim.GetAttribute("velocities")
                if velocities and velocities.HasAuthoredValue():
                    qd[particles] = _sample(path, velocities, tc, len(q[particles]))
            diag = {d: _diag_value(d, diag_attrs[d].Get(tc)) for d, times in diag_times.items() if tc in times}
        yield q, qd, diag


def _sample(path, attr, tc, rows: int) -> np.ndarray:
    """A (rows, 3) float32 array attribute's value at time code tc, or CacheError naming what is wrong."""
    value = np.asarray(attr.Get(tc), np.float32)
    if value.shape != (rows, 3):
        raise CacheError(f"{path}: {attr.GetPath()} at frame {tc} has shape {value.shape}, expected ({rows}, 3)")
    return value


def _diag_value(name, value):
    if value is None or (isinstance(value, float | np.floating) and not np.isfinite(value)):
        return None
    return int(value) if DIAGNOSTICS[name][0] == "int" else float(value)


class CacheWriter:
    """Frames to a cache file, safely (see the module docstring and :mod:`cloth_warp.outputs`).

    Common to every format: `fps` is checked, the output is checked before anything is written (not a folder,
    a writable folder, room for the first saves), the run takes the output's lock (a second live writer of
    the same output gets :class:`~cloth_warp.outputs.OutputBusy`), frames go to a partial file of this run
    and are saved on a schedule; a save that fails raises :class:`~cloth_warp.outputs.CacheWriteError`
    after putting the partial file back to the last good save, and :meth:`close` then renames that one to
    the final name. Non-finite positions or velocities are refused (ValueError) before anything is authored.
    Subclasses author frames (:meth:`_author`), store a checkpoint (:meth:`_store_checkpoint`) and save
    (:meth:`_save_file`).
    """

    path: pathlib.Path
    frames_written = 0
    text_format = False  # each save rewrites the whole file: saves on a doubling schedule

    def _begin(self, path, model, fps, start_frame, save_every, bytes_per_frame, metadata, lock):
        self.path = pathlib.Path(path)
        from .validation import LIMITS, check_number

        self.fps = float(check_number("fps", fps, LIMITS["fps"]))
        self.start_frame = int(check_number("start_frame", start_frame, LIMITS["start_frame"]))
        self.save_every = max(1, int(save_every))
        self.particle_count = int(model.particle_count)
        self.frames_written, self.saved_frames, self.closed, self.broken = 0, 0, False, None
        first_save = min(self.save_every, 25) if not self.text_format else self.save_every
        check_output(self.path, bytes_needed=int(bytes_per_frame * first_save) + 256 * 1024)
        self._owns_lock = lock is None  # a lock handed in is the caller's to release
        self.lock = lock if lock is not None else OutputLock(self.path).acquire()
        self.partial = partial_path(self.path)
        remove_partial(self.partial)  # a file of a dead process that had our pid
        self.meta = {"generator": "cloth_warp", "versions": package_versions(), "status": "running", "frames_written": 0,
                     "fps": self.fps, "start_frame": self.start_frame, "up_axis": model.up_axis, **(metadata or {})}

    @property
    def next_time_code(self) -> int:
        return self.start_frame + self.frames_written

    @property
    def save_due(self) -> bool:
        """Whether the next :meth:`write` saves the file (pass it a checkpoint then)."""
        n = self.frames_written + 1
        if self.text_format:
            return n >= self.save_every and n % self.save_every == 0 and ((n // self.save_every) & (n // self.save_every - 1)) == 0
        return n % self.save_every == 0

    def write(self, q: np.ndarray, qd: np.ndarray, diagnostics: dict | None = None, checkpoint: dict | None = None) -> int:
        """Author one frame (positions [m], velocities [m/s] of all particles; diagnostics by name; the
        simulator checkpoint of this frame, which replaces the one kept and is written with the next save:
        pass one whenever :attr:`save_due`); returns its time code."""
        if self.closed or self.broken:
            raise RuntimeError(f"cache {self.path} already {'closed' if self.closed else 'failed'}")
        q, qd = np.asarray(q, np.float32), np.asarray(qd, np.float32)
        for name, a in (("positions", q), ("velocities", qd)):
            if a.shape != (self.particle_count, 3):
                raise ValueError(f"{name}: expected shape ({self.particle_count}, 3), got {a.shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"{name}: non-finite values in frame {self.next_time_code}; refusing to write them")
        save = self.save_due
        tc = self.next_time_code
        self._author(q, qd, diagnostics or {}, tc)
        self.frames_written += 1
        if checkpoint is not None:  # kept (the latest only) and written with the next save
            self._store_checkpoint(checkpoint, tc)
        if save:
            self._save("partial")
        return tc

    def _save(self, status: str):
        """Stamp status and frames, save; on failure put the file back to the last good save and raise."""
        self.meta.update(status=status, frames_written=self.frames_written)
        try:
            self._save_file()
        except CacheWriteError as exc:
            self.broken = exc
            kept = f"frames {self.start_frame}..{self.start_frame + self.saved_frames - 1}" if self.saved_frames else "no frames"
            raise CacheWriteError(f"{exc}; the cache keeps {kept} (the last good save)") from None
        self.saved_frames = self.frames_written

    def close(self, status: str = "complete", info: dict | None = None, checkpoint: dict | None = None) -> pathlib.Path:
        """Stamp the status (and `info`), store `checkpoint` (the last frame's), save and rename to the final
        name; returns the final path. After a failed save, the last good save is renamed instead (and the
        error raised again unless it was already). A cache with no frame saved leaves no file."""
        if self.closed:
            return self.path
        self.closed = True
        try:
            if self.broken is None:
                self.meta.update(info or {})
                if checkpoint is not None and self.frames_written:
                    self._store_checkpoint(checkpoint, self.next_time_code - 1)
                try:
                    self._save(status)
                except CacheWriteError:
                    self._finish()
                    raise
            self._finish()
        finally:
            if self._owns_lock:
                self.lock.release()
        log.info("wrote %s (%d frames, %s)", self.path, self.saved_frames, status)
        return self.path

    def _finish(self):
        """Rename the partial file (as of its last good save) to the final name; drop it if nothing was saved."""
        self._release()
        if self.saved_frames and self.partial.exists():
            try:
                os.replace(self.partial, self.path)
            except OSError as exc:
                raise CacheWriteError(f"{self.path}: cannot rename {self.partial.name} to it: {exc.strerror or exc}; "
                                      f"the frames are in {self.partial}") from None
        else:
            remove_partial(self.partial)

    def abort(self):
        """Give up: remove the partial file (whatever it holds) and release the output."""
        if not self.closed:
            self.closed = True
            self._release()
            remove_partial(self.partial)
            if self._owns_lock:
                self.lock.release()

    def _release(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close("complete")
        else:
            self.close("interrupted" if issubclass(exc_type, KeyboardInterrupt) else "failed")
        return False


class UsdCacheWriter(CacheWriter):
    """Writes a model's frames to a USD cache as they are simulated (see the module docstring).

    Args:
        path: final file name (.usdc, .usda or .usd = crate).
        model: the simulated :class:`~cloth_warp.Model` (topology, UVs, up axis are read from it).
        fps: frames per second (time codes per second) of the cache.
        start_frame: time code of the first frame written (the initial state).
        save_every: crate saves every so many frames (bounds memory and what a crash can lose); a text
            ``.usda`` saves at save_every x 1, 2, 4, ... frames (each text save rewrites the whole file).
        normals, velocities: author vertex normals / velocities per frame.
        metadata: JSON-able provenance merged into ``customLayerData["cloth_warp"]``.
        lock: the output's :class:`~cloth_warp.outputs.OutputLock`, if the caller holds it already (and
            releases it after :meth:`close`); otherwise the writer takes it and releases it when it closes.
    """

    def __init__(self, path, model, *, fps: float, start_frame: int = 1, save_every: int = 25, normals: bool = True,
                 velocities: bool = True, metadata: dict | None = None, lock: OutputLock | None = None):
        path = pathlib.Path(path)
        if path.suffix.lower() not in USD_SUFFIXES:
            raise ValueError(f"a USD cache must end in {', '.join(USD_SUFFIXES)}, got {path.name!r}")
        self.text_format = path.suffix.lower() == ".usda"
        per_frame = model.particle_count * 12 * (1 + bool(normals) + bool(velocities)) * (4 if self.text_format else 1)
        self._begin(path, model, fps, start_frame, save_every, per_frame, metadata, lock)
        try:  # whatever stops the writer half made (a failed save, Ctrl-C) leaves no partial file
            self._define_stage(model, normals, velocities)
        except BaseException:
            self.abort()
            raise

    def _define_stage(self, model, normals: bool, velocities: bool):
        """Create the partial layer, define the cloth meshes (topology, UVs, looks, rest pose, diagnostics) and
        the colliders, and save it once."""
        from pxr import Sdf, Usd, UsdGeom, UsdPhysics, Vt

        try:
            stale = Sdf.Layer.Find(str(self.partial))
            self.layer = stale if stale is not None else Sdf.Layer.CreateNew(str(self.partial))
            if stale is not None:
                stale.Clear()
        except Exception as exc:  # Tf.ErrorException: an unwritable folder
            raise CacheWriteError(f"{self.partial}: cannot create: {usd_error_text(exc)}") from None
        if self.layer is None:
            raise CacheWriteError(f"{self.partial}: cannot create")
        self._Vt = Vt
        stage = self.stage = Usd.Stage.Open(self.layer)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if model.up_axis == "Z" else UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
        stage.SetTimeCodesPerSecond(self.fps)
        stage.SetFramesPerSecond(self.fps)
        stage.SetStartTimeCode(self.start_frame)
        stage.SetEndTimeCode(self.start_frame)
        root = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(root.GetPrim())
        self.layer.comment = "Cloth animation cache written by cloth_warp"
        self._set_metadata()
        rest = model.rest_positions
        self.meshes = []
        materials = {}
        UsdGeom.Scope.Define(stage, f"/World/{LOOKS_SCOPE}")
        for cloth in _cloth_meshes(model):
            name, particles, tris, corner_uv, fabric = cloth.name, cloth.particles, cloth.triangles, cloth.corner_uv, cloth.fabric
            mesh = UsdGeom.Mesh.Define(stage, f"/World/{name}")
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            mesh.CreateDoubleSidedAttr(True)
            mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
            mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(tris), 3, np.int32)))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(tris.reshape(-1))))
            color = looks.fabric_color(fabric)
            if fabric not in materials:
                materials[fabric] = looks.define_material(stage, f"/World/{LOOKS_SCOPE}/{_prim_name(fabric)}", color, looks.ROUGHNESS["fabric"])
            looks.bind_look(mesh, materials[fabric], color)
            if corner_uv is not None:
                values, indices = _indexed_corner_uvs(corner_uv)
                st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
                st.Set(Vt.Vec2fArray.FromNumpy(values))
                st.SetIndices(Vt.IntArray.FromNumpy(indices))
            x0 = np.ascontiguousarray(rest[particles], np.float32)
            attrs = {"points": mesh.CreatePointsAttr(), "extent": mesh.CreateExtentAttr()}
            attrs["points"].Set(Vt.Vec3fArray.FromNumpy(x0))
            attrs["extent"].Set(Vt.Vec3fArray.FromNumpy(np.stack([x0.min(0), x0.max(0)])))
            if normals:
                attrs["normals"] = mesh.CreateNormalsAttr()
                mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
                attrs["normals"].Set(Vt.Vec3fArray.FromNumpy(vertex_normals(x0, tris)))
            if velocities:
                attrs["velocities"] = mesh.CreateVelocitiesAttr()
                attrs["velocities"].Set(Vt.Vec3fArray.FromNumpy(np.zeros_like(x0)))
            edges, rest_length = cloth.edges()
            strain = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(STRAIN_PRIMVAR, Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
            strain.GetAttr().SetDocumentation("per vertex, the largest strain l / L - 1 of its mesh edges, per frame")
            strain.Set(Vt.FloatArray.FromNumpy(np.zeros(1, np.float32)))  # the rest pose: 0 everywhere (indexed, as per frame)
            strain.SetIndices(Vt.IntArray.FromNumpy(np.zeros(len(x0), np.int32)))
            attrs["strain"] = (strain, edges, rest_length)
            prim = mesh.GetPrim()
            for diag, (type_name, doc) in DIAGNOSTICS.items():
                vtype = Sdf.ValueTypeNames.Float if type_name == "float" else Sdf.ValueTypeNames.Int
                attr = prim.CreateAttribute(f"clothWarp:{diag}", vtype, custom=True)
                attr.SetDocumentation(doc)
                attrs[diag] = attr
            self.meshes.append((particles, tris, attrs))
        self.colliders = _define_colliders(stage, model)
        self._write_collider_poses(0)
        self._checkpoint_attr = None
        self._save_file()

    def _write_collider_poses(self, k: int):
        """Author the animated colliders' poses at frame k (time k / fps; static ones once, at default time)."""
        from pxr import Gf

        tc = self.start_frame + k
        for col, translate, orient, geom in self.colliders:
            if k > 0 and not col.animated:
                continue
            p, q = col.pose_at(k / self.fps)
            when = tc if col.animated else None
            translate.Set(Gf.Vec3d(*map(float, p)), *([when] if when is not None else []))
            orient.Set(Gf.Quatf(float(q[3]), float(q[0]), float(q[1]), float(q[2])), *([when] if when is not None else []))
            if col.deforming:  # a point-cache body: its points, time-sampled like the cloth's
                pts = np.ascontiguousarray(col.vertices_at(k / self.fps), np.float32)
                geom.GetPointsAttr().Set(self._Vt.Vec3fArray.FromNumpy(pts), tc)
                geom.GetExtentAttr().Set(self._Vt.Vec3fArray.FromNumpy(np.stack([pts.min(0), pts.max(0)])), tc)

    def _set_metadata(self):
        self.layer.customLayerData = {"cloth_warp": _usd_dict(self.meta)}

    def _author(self, q, qd, diagnostics, tc):
        Vt = self._Vt
        for particles, tris, attrs in self.meshes:
            x = np.ascontiguousarray(q[particles])
            attrs["points"].Set(Vt.Vec3fArray.FromNumpy(x), tc)
            attrs["extent"].Set(Vt.Vec3fArray.FromNumpy(np.stack([x.min(0), x.max(0)])), tc)
            if "normals" in attrs:
                attrs["normals"].Set(Vt.Vec3fArray.FromNumpy(vertex_normals(x, tris)), tc)
            if "velocities" in attrs:
                attrs["velocities"].Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(qd[particles])), tc)
            strain, edges, rest_length = attrs["strain"]
            values, indices = np.unique(vertex_strain(x, edges, rest_length), return_inverse=True)  # indexed: at rest, mostly 0
            strain.Set(Vt.FloatArray.FromNumpy(values), tc)
            strain.SetIndices(Vt.IntArray.FromNumpy(indices.astype(np.int32)), tc)
            for key, value in diagnostics.items():
                if key in DIAGNOSTICS and value is not None:
                    attrs[key].Set(int(value) if DIAGNOSTICS[key][0] == "int" else float(value), tc)
        self.stage.SetEndTimeCode(tc)
        if tc > self.start_frame:
            self._write_collider_poses(tc - self.start_frame)

    def _store_checkpoint(self, checkpoint: dict, tc: int):
        """Keep one checkpoint, the latest, as a custom byte-array attribute of the root prim (no DCC tool draws it)."""
        from pxr import Sdf

        if self._checkpoint_attr is None:
            prim = self.stage.GetPrimAtPath(CHECKPOINT_PRIM)
            self._checkpoint_attr = prim.CreateAttribute(CHECKPOINT_ATTR, Sdf.ValueTypeNames.UCharArray, custom=True)
            self._checkpoint_attr.SetDocumentation("cloth_warp simulator state at the last saved frame (cloth-warp run --resume)")
        self._checkpoint_attr.Clear()
        self._checkpoint_attr.Set(self._Vt.UCharArray.FromNumpy(np.frombuffer(pack_checkpoint(checkpoint), np.uint8)), tc)

    def _save_file(self):
        from pxr import Tf

        self._set_metadata()
        if self.text_format:  # a text save rewrites the file in place: export beside it, then rename over it
            try:
                with atomic_path(self.partial) as tmp:
                    if not self.layer.Export(str(tmp)):
                        raise CacheWriteError(f"{self.partial}: cannot write")
            except Tf.ErrorException as exc:
                raise CacheWriteError(f"{self.partial}: cannot write: {usd_error_text(exc)}") from None
            except OSError as exc:
                raise CacheWriteError(f"{self.partial}: cannot write: {exc.strerror or exc}") from None
            return
        rollback = CrateRollback(self.partial)
        try:
            rollback.write_journal()  # a kill during the save leaves it: --resume rolls back (outputs.recover_partial)
        except OSError as exc:
            raise CacheWriteError(f"{self.partial}: cannot write its rollback journal: {exc.strerror or exc}") from None
        try:
            ok, why = self.layer.Save(), "the save failed"
        except Tf.ErrorException as exc:
            ok, why = False, usd_error_text(exc)
        if ok:
            try:
                rollback.discard_journal()
            except OSError as exc:
                raise CacheWriteError(f"{self.partial}: cannot sync: {exc.strerror or exc}") from None
            return
        try:
            rollback.restore()
            rollback.discard_journal()
        except OSError as exc:
            why += f"; restoring the last good save failed too ({exc.strerror or exc})"
        raise CacheWriteError(f"{self.partial}: cannot write: {why}")

    def _release(self):
        # A failed crate save leaves the layer unusable: drop it without saving (saving again crashes USD).
        self.meshes, self.colliders, self.stage, self.layer, self._checkpoint_attr = [], [], None, None, None

    def _finish(self):
        from pxr import Sdf

        super()._finish()
        # A layer of the same name opened earlier in this process would otherwise keep serving old data.
        old = Sdf.Layer.Find(str(self.path))
        if old is not None:
            old.Reload(force=True)


def _usd_dict(d):
    """A JSON-able dict as USD dictionary values (lists and None become JSON strings)."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out[k] = _usd_dict(v)
        elif isinstance(v, bool | str):
            out[k] = v
        elif isinstance(v, int | np.integer):
            out[k] = int(v)
        elif isinstance(v, float | np.floating):
            out[k] = float(v) if math.isfinite(v) else str(v)
        else:
            out[k] = json.dumps(v)
    return out


class NpzCacheWriter(CacheWriter):
    """Frames in a numpy ``.npz``: ``positions`` / ``velocities`` (frames, particles, 3) [m, m/s],
    ``triangles``, ``fps``, ``start_frame``, ``metadata`` (JSON), one array per diagnostic, and the resume
    ``checkpoint`` (bytes) with ``checkpoint_frames``. Held in memory and written whole (temporary name, then
    rename) at save_every x 1, 2, 4, ... frames and at :meth:`close`."""

    text_format = True

    def __init__(self, path, model, *, fps: float, start_frame: int = 1, save_every: int = 25, metadata: dict | None = None,
                 lock: OutputLock | None = None, **_):
        self._begin(path, model, fps, start_frame, save_every, model.particle_count * 24, metadata, lock)
        self.triangles = model.tri_indices.numpy().copy()
        self.q, self.qd, self.diag = [], [], {k: [] for k in DIAGNOSTICS}
        self.checkpoint, self.checkpoint_frames = None, 0

    def _author(self, q, qd, diagnostics, tc):
        self.q.append(np.array(q, np.float32))
        self.qd.append(np.array(qd, np.float32))
        for k in DIAGNOSTICS:
            v = diagnostics.get(k)
            self.diag[k].append(np.nan if v is None else v)

    def _store_checkpoint(self, checkpoint, tc):
        self.checkpoint = np.frombuffer(pack_checkpoint(checkpoint), np.uint8)
        self.checkpoint_frames = tc - self.start_frame + 1

    def _save_file(self):
        n, shape = len(self.triangles), (self.particle_count, 3)
        extra = {"checkpoint": self.checkpoint, "checkpoint_frames": self.checkpoint_frames} if self.checkpoint is not None else {}
        try:
            with atomic_path(self.partial) as tmp, open(tmp, "wb") as fh:
                np.savez_compressed(fh, positions=np.array(self.q).reshape(-1, *shape), velocities=np.array(self.qd).reshape(-1, *shape),
                                    triangles=self.triangles.reshape(n, 3), fps=self.fps, start_frame=self.start_frame,
                                    metadata=json.dumps(self.meta, default=str),
                                    **{k: np.array(v, np.float64) for k, v in self.diag.items()}, **extra)
        except OSError as exc:
            raise CacheWriteError(f"{self.partial}: cannot write: {exc.strerror or exc}") from None


def open_cache(path, model, **kwargs) -> CacheWriter:
    """A cache writer chosen by the file extension (.usdc / .usda / .usd or .npz)."""
    suffix = pathlib.Path(path).suffix.lower()
    if suffix in USD_SUFFIXES:
        return UsdCacheWriter(path, model, **kwargs)
    if suffix == ".npz":
        return NpzCacheWriter(path, model, **kwargs)
    raise ValueError(f"unknown cache format {suffix or '(none)'!r} for {path}; allowed: {', '.join(CACHE_SUFFIXES)}")


# -- reading --------------------------------------------------------------------------------------------------

class CacheError(ValueError):
    """A cache file that cannot be read: ``"<path>: <what is wrong>"`` (``cloth-warp`` exits 2 on it)."""


NPZ_KEYS = ("positions", "triangles", "fps", "start_frame")  # what every .npz cache must hold (NpzCacheWriter)


def _file_kind(head: bytes) -> str:
    """What the first bytes of a file look like, for messages ("a zip archive", "text", ...)."""
    if head.startswith(b"PXR-USDC") or b"PXR-USDC".startswith(head):  # (a prefix: cut short, USD says how)
        return "a binary USD (crate) file"
    if head.startswith(b"#usda") or b"#usda".startswith(head):
        return "a USD text file"
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")) or b"PK\x03\x04".startswith(head):
        return "a zip archive"
    if head.startswith(b"\x93NUMPY"):
        return "a single numpy .npy array"
    if len(head) >= 2 and head[0] == 0x80 and 2 <= head[1] <= 5:
        return "a Python pickle"
    if sum(32 <= b < 127 or b in (9, 10, 13) for b in head) >= 0.95 * len(head):
        return "text"
    return "unrecognised binary data"


@contextlib.contextmanager
def usd_errors(path, what: str = ""):
    """Turn USD errors raised inside the block into :class:`CacheError` naming `path`; USD warnings posted
    there go to this module's log (one line each) instead of USD's own multi-line stderr output."""
    from pxr import Tf

    trap = getattr(Tf, "DiagnosticTrap", None)  # usd-core >= 25.05
    with trap() if trap is not None else contextlib.nullcontext() as diagnostics:
        try:
            yield
        except Tf.ErrorException as exc:
            raise CacheError(f"{path}: {what}{usd_error_text(exc)}") from exc
        finally:
            if diagnostics is not None:
                for w in diagnostics.GetWarnings():
                    log.warning("%s: USD: %s", path, " ".join(str(w.commentary).split()))
                for e in diagnostics.GetErrors():  # posted but not raised: report them, never lose them silently
                    log.warning("%s: USD error: %s", path, " ".join(str(e.commentary).split()))
                diagnostics.Clear()


class CacheReader:
    """Read a cache written by cloth_warp (or any USD stage with animated meshes): frames, topology, diagnostics.

    Every file it cannot use (missing, a folder, unreadable, empty, truncated, corrupt, not the format its
    extension names, a USD without an animated mesh, an ``.npz`` without its keys) raises
    :class:`CacheError` (a ``ValueError``) ``"<path>: <what is wrong>"``; a missing file raises
    ``FileNotFoundError``.

    Attributes:
        fps, start_frame, end_frame, up_axis, metadata (the ``cloth_warp`` provenance dict, {} if none),
        meshes: list of dicts (path, points (rest), triangles (fan-triangulated), has_uv, samples).
    """

    def __init__(self, path):
        self.path = pathlib.Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"cache not found: {self.path}")
        suffix = self.path.suffix.lower()
        if suffix not in CACHE_SUFFIXES:
            raise CacheError(f"{self.path}: unknown cache format {suffix or '(no extension)'!r}; "
                             f"allowed: {', '.join(CACHE_SUFFIXES)}")
        head = self._head()
        if suffix == ".npz":
            self._read_npz(head)
        else:
            self._read_usd(head)

    def _error(self, what: str) -> CacheError:
        return CacheError(f"{self.path}: {what}")

    def _head(self) -> bytes:
        """The file's first bytes; a folder, an unreadable or an empty file raise CacheError."""
        if self.path.is_dir():
            raise self._error("is a directory, not a cache file")
        try:
            with open(self.path, "rb") as fh:
                head = fh.read(64)
        except PermissionError:
            raise self._error("cannot be read: permission denied") from None
        except OSError as exc:
            raise self._error(f"cannot be read: {exc.strerror or exc}") from None
        if not head:
            raise self._error("is empty (0 bytes)")
        return head

    # -- npz -------------------------------------------------------------------------------------------------
    def _read_npz(self, head: bytes):
        import zipfile
        import zlib

        kind = _file_kind(head)
        if kind != "a zip archive":
            extra = " (pickles are never loaded)" if kind == "a Python pickle" else ""
            raise self._error(f"not an .npz archive: the file is {kind}{extra}")
        try:
            if not zipfile.is_zipfile(self.path):
                raise self._error(f"truncated or corrupt .npz archive: no zip directory at its end "
                                  f"({self.path.stat().st_size} bytes)")
        except OSError as exc:
            raise self._error(f"cannot be read: {exc.strerror or exc}") from None
        try:
            with np.load(self.path, allow_pickle=False) as data:
                names = list(data.files)
                missing = [k for k in NPZ_KEYS if k not in names]
                if missing:
                    shown = [k if k.isascii() and k.isprintable() else ascii(k) for k in names[:6]]
                    held = ", ".join(shown) + (f" and {len(names) - 6} more" if len(names) > 6 else "") or "no arrays"
                    raise self._error(f"not a cloth_warp .npz cache: no {', '.join(repr(k) for k in missing)} "
                                      f"{'array' if len(missing) == 1 else 'arrays'} "
                                      f"(needed: {', '.join(NPZ_KEYS)}; it holds {held})")
                d = {k: data[k] for k in names}
                raw = [k for k in NPZ_KEYS if not isinstance(d[k], np.ndarray)]  # a member that is not .npy data
                if raw:
                    what = "is not a numpy array" if len(raw) == 1 else "are not numpy arrays"
                    raise self._error(f"corrupt .npz archive: {', '.join(repr(k) for k in raw)} {what}")
        except CacheError:
            raise
        except ValueError as exc:  # an object (pickled) array, or a malformed .npy header in the archive
            raise self._error(f"corrupt .npz archive: {exc}") from None
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, KeyError) as exc:
            raise self._error(f"corrupt or truncated .npz archive: {exc}") from None
        except MemoryError:  # a corrupt .npy header claiming a huge array
            raise self._error("corrupt .npz archive: an array's header claims more memory than there is") from None
        self._npz = d
        positions, triangles = d["positions"], d["triangles"]
        if positions.dtype.kind not in "fiu" or positions.ndim != 3 or positions.shape[2] != 3 or not positions.shape[0] \
                or not positions.shape[1]:
            raise self._error(f"'positions' must be a (frames >= 1, points >= 1, 3) number array, "
                              f"got {positions.dtype} {positions.shape}")
        n = positions.shape[1]
        if triangles.dtype.kind not in "iu" or triangles.ndim != 2 or triangles.shape[1] != 3 or not triangles.shape[0]:
            raise self._error(f"'triangles' must be a (triangles >= 1, 3) integer array, got {triangles.dtype} {triangles.shape}")
        if triangles.min() < 0 or triangles.max() >= n:
            raise self._error(f"'triangles' index points {triangles.min()}..{triangles.max()}, the cache has {n} points")
        try:
            self.fps, self.start_frame = float(d["fps"]), int(d["start_frame"])
        except (TypeError, ValueError) as exc:
            raise self._error(f"'fps' and 'start_frame' must be single numbers ({exc})") from None
        if not (np.isfinite(self.fps) and self.fps > 0.0):
            raise self._error(f"'fps' must be a number > 0, got {self.fps}")
        self.end_frame = self.start_frame + len(positions) - 1
        self.metadata = {}
        if "metadata" in d:
            try:
                self.metadata = json.loads(str(d["metadata"]))
            except ValueError:
                raise self._error("'metadata' is not JSON") from None
            if not isinstance(self.metadata, dict):
                raise self._error(f"'metadata' must be a JSON object, got {type(self.metadata).__name__}")
        self.up_axis = str(self.metadata.get("up_axis", "Y"))
        self.stage = None
        self.colliders = []
        self.meshes = [{"path": "npz", "points": positions[0], "triangles": triangles.astype(np.int32),
                        "has_uv": False, "samples": len(positions)}]

    # -- USD -------------------------------------------------------------------------------------------------
    def _read_usd(self, head: bytes):
        from pxr import Usd, UsdGeom

        suffix, kind = self.path.suffix.lower(), _file_kind(head)
        usd_kinds = {".usdc": ("a binary USD (crate) file",), ".usda": ("a USD text file",),
                     ".usd": ("a binary USD (crate) file", "a USD text file")}[suffix]
        if kind not in usd_kinds:
            want = {".usdc": "a binary USD (crate) file", ".usda": "a USD text file (it must start with '#usda')",
                    ".usd": "a USD file"}[suffix]
            hint = {"a USD text file": " (rename it .usda)", "a binary USD (crate) file": " (rename it .usdc)",
                    "a zip archive": " (an .npz or .usdz?)"}.get(kind, "")
            raise self._error(f"not {want}: the file is {kind}{hint}")
        if kind == "a binary USD (crate) file":  # USD names a cut crate file only for .usdc, not for .usd
            size = self.path.stat().st_size
            toc = int.from_bytes(head[16:24], "little") if len(head) >= 24 else 0
            if size < 88:
                raise self._error(f"truncated binary USD file: {size} bytes, smaller than its 88-byte header")
            if not 88 <= toc < size:
                raise self._error(f"truncated or corrupt binary USD file: its table of contents is at byte {toc}, "
                                  f"the file has {size} bytes")
        with usd_errors(self.path, "cannot be opened as USD: "):
            self.stage = Usd.Stage.Open(str(self.path))
        if self.stage is None:
            raise self._error("cannot be opened as USD")
        with usd_errors(self.path, "corrupt USD: "):
            self._read_stage(Usd, UsdGeom)

    def _read_stage(self, Usd, UsdGeom):
        stage = self.stage
        self.fps = float(stage.GetTimeCodesPerSecond())
        if not (np.isfinite(self.fps) and self.fps > 0.0):
            raise self._error(f"timeCodesPerSecond must be > 0, got {self.fps}")
        self.up_axis = str(UsdGeom.GetStageUpAxis(stage))
        meta = stage.GetRootLayer().customLayerData.get("cloth_warp", {})
        self.metadata = dict(meta) if hasattr(meta, "keys") else {}
        self.meshes = []
        self.colliders = []
        for prim in stage.Traverse():
            if str(prim.GetPath()).startswith(f"/World/{COLLIDER_SCOPE}/"):
                if prim.IsA(UsdGeom.Gprim):
                    self.colliders.append({"path": str(prim.GetPath()), "prim": prim,
                                           **dict(prim.GetCustomDataByKey("clothWarp:collider") or {})})
                continue
            if prim.IsA(UsdGeom.Mesh):
                self.meshes.append(self._read_mesh(prim, Usd, UsdGeom))
        if not self.meshes:
            found = ", ".join(f"{p.GetPath()} ({p.GetTypeName() or 'untyped'})" for p in list(stage.Traverse())[:5])
            raise self._error(f"holds no cloth mesh (a UsdGeom Mesh with time-sampled points); prims: {found or 'none'}")
        if stage.HasAuthoredTimeCodeRange():
            self.start_frame, self.end_frame = int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode())
        else:  # a stage without startTimeCode / endTimeCode: the points' own samples
            times = self.meshes[0]["times"]
            self.start_frame, self.end_frame = int(times[0]), int(times[-1])
        if self.end_frame < self.start_frame:
            raise self._error(f"endTimeCode {self.end_frame} is before startTimeCode {self.start_frame}")
        for i in range(len(self.meshes)):  # the first and last frames read back with the rest pose's point count
            for f in (self.start_frame, self.end_frame):
                self.points(f, i)

    def _read_mesh(self, prim, Usd, UsdGeom) -> dict:
        where = f"mesh {prim.GetPath()}"
        mesh = UsdGeom.Mesh(prim)
        points = mesh.GetPointsAttr()
        samples = points.GetNumTimeSamples()
        if not samples:
            if points.Get(Usd.TimeCode.Default()) is None:
                raise self._error(f"{where} has no points")
            raise self._error(f"{where} has only static points, no time samples: not an animation cache")
        rest = points.Get(Usd.TimeCode.Default())
        if rest is None:
            rest = points.Get(Usd.TimeCode.EarliestTime())
        rest = np.asarray(rest if rest is not None else [], np.float32)
        if rest.ndim != 2 or rest.shape[1] != 3 or not len(rest):
            raise self._error(f"{where} has no points")
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], np.int64)
        indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], np.int64)
        if not len(counts) or not len(indices):
            raise self._error(f"{where} has no faces (faceVertexCounts / faceVertexIndices are empty)")
        ok, reason = UsdGeom.Mesh.ValidateTopology(indices.tolist(), counts.tolist(), len(rest))
        if not ok:
            raise self._error(f"{where} has invalid topology: {reason}")
        triangles = fan_triangulate(counts, indices)
        if not len(triangles):
            raise self._error(f"{where} has no faces with 3 or more corners")
        times = points.GetTimeSamples()
        display = np.asarray(mesh.GetDisplayColorAttr().Get() or [], np.float64).reshape(-1)
        color = tuple(display[:3]) if display.size >= 3 and np.isfinite(display[:3]).all() else None
        return {"path": str(prim.GetPath()), "points": rest, "triangles": triangles,
                "has_uv": UsdGeom.PrimvarsAPI(prim).HasPrimvar("st"), "samples": samples, "prim": prim,
                "times": (times[0], times[-1]), "color": color}

    @property
    def frame_count(self) -> int:
        return self.end_frame - self.start_frame + 1

    def points(self, frame: int, mesh: int = 0) -> np.ndarray:
        """Positions of a mesh at a frame (time code) [m], float32 (n, 3)."""
        if self.stage is None:
            return self._npz["positions"][frame - self.start_frame]
        from pxr import UsdGeom

        m = self.meshes[mesh]
        with usd_errors(self.path, f"corrupt USD: {m['path']} points at frame {frame}: "):
            value = UsdGeom.Mesh(m["prim"]).GetPointsAttr().Get(frame)
        x = np.asarray(value if value is not None else [], np.float32)
        if x.shape != m["points"].shape:
            raise self._error(f"mesh {m['path']} has {x.shape[0] if x.ndim else 0} points at frame {frame}, "
                              f"{len(m['points'])} at rest")
        return x

    def diagnostics(self, mesh: int = 0) -> dict:
        """Per-frame diagnostics as {name: (time codes, values)}."""
        if self.stage is None:
            n = len(self._npz["positions"])
            tc = np.arange(self.start_frame, self.start_frame + n)
            return {k: (tc, self._npz[k]) for k in DIAGNOSTICS if k in self._npz}
        prim = self.meshes[mesh]["prim"]
        out = {}
        with usd_errors(self.path, "corrupt USD: "):
            for k in DIAGNOSTICS:
                attr = prim.GetAttribute(f"clothWarp:{k}")
                if attr and attr.GetNumTimeSamples():
                    tc = np.array(attr.GetTimeSamples())
                    try:
                        out[k] = (tc, np.array([attr.Get(t) for t in tc], np.float64))
                    except (TypeError, ValueError):  # not numbers: not ours, skip it
                        log.warning("%s: diagnostic %s is not a number per frame; ignored", self.path, k)
        return out

    def summary(self) -> dict:
        """What `cloth-warp info` prints (JSON-able)."""
        diag = {}
        for k, (tc, v) in self.diagnostics().items():
            v = np.asarray(v, np.float64).reshape(-1) if np.asarray(v).dtype.kind in "fiub" else np.zeros(0)
            finite = v[np.isfinite(v)]
            if len(finite):
                diag[k] = {"min": float(finite.min()), "max": float(finite.max()), "mean": float(finite.mean())}
        return {"path": str(self.path), "fps": self.fps, "start_frame": self.start_frame, "end_frame": self.end_frame,
                "frames": self.frame_count, "up_axis": self.up_axis,
                "meshes": [{"path": m["path"], "points": len(m["points"]), "triangles": len(m["triangles"]),
                            "uv": bool(m["has_uv"]), "time_samples": int(m["samples"])} for m in self.meshes],
                "diagnostics": diag, "metadata": _plain(self.metadata)}


def _plain(v):
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    return v if isinstance(v, bool | int | float | str) or v is None else str(v)


def fan_triangulate(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Triangles (t, 3) from polygon face counts and indices (fan around each face's first corner)."""
    counts = np.asarray(counts, np.int64)
    indices = np.asarray(indices, np.int64)
    if counts.size == 0:
        return np.zeros((0, 3), np.int32)
    if np.all(counts == 3):
        return indices.reshape(-1, 3).astype(np.int32)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris = [(indices[s], indices[s + k], indices[s + k + 1]) for s, c in zip(starts, counts) for k in range(1, c - 1)]
    return np.asarray(tris, np.int32).reshape(-1, 3)
