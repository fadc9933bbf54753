"""Animation caches: USD (.usdc / .usda / .usd) written frame by frame, and .npz for numpy users.

A USD cache is what DCC tools (usdview, Houdini, Blender, Maya, Omniverse) play:

* stage metadata: ``upAxis`` (the simulation's own; points are never rotated), ``metersPerUnit = 1``,
  ``kilogramsPerUnit = 1``, ``timeCodesPerSecond = framesPerSecond = fps``, start/end time codes = the
  frames written (updated as frames land); time codes come from an integer frame counter;
* a root ``Xform`` (``/World``) that is the ``defaultPrim`` with one ``Mesh`` per cloth: static topology
  (authored once, never time-sampled), ``subdivisionScheme = "none"``, ``doubleSided = 1``, indexed
  face-varying ``primvars:st`` (per corner, so UV seams of a welded mesh survive); ``points`` time-sampled
  plus a default value (the rest pose), ``extent``, vertex ``normals`` and ``velocities`` [m/s] per frame;
* per-frame diagnostics as custom attributes on each cloth prim (``clothWarp:maxStrain``,
  ``clothWarp:dt`` [s], ``clothWarp:solverIterations``, ``clothWarp:solverResidual``,
  ``clothWarp:colliderContacts``, ``clothWarp:colliderCcd`` and, with self-collision, ``clothWarp:selfProximity``,
  ``selfCcd``, ``selfSweeps``, ``impactZones``, ``selfUnresolved``);
* colliders under ``/World/colliders`` as UsdGeom Sphere / Capsule / Cylinder (axis Z) / Cube (scaled) /
  Plane / Mesh prims with a translate and an orient op (time-sampled per frame when animated), grey
  ``displayColor``, and their shape, thickness and friction in the prim's customData;
* provenance in the layer's ``customLayerData["cloth_warp"]``: versions, scene, resolved settings,
  status (``running`` / ``complete`` / ``interrupted`` / ``diverged`` / ``failed``), frames written.

The first frame written is the initial state at ``start_frame``; frame k of the simulation is time code
``start_frame + k``. The cache is authored into ``<name>.partial<ext>`` next to the final path, saved every
``save_every`` frames (crate saves are incremental and release the samples, which bounds memory; ``.usda``
is saved once at the end because each text save rewrites the whole file) and renamed to the final name by
:meth:`close` -- also after an interruption or a divergence, so a file under the final name is always a
complete, valid cache of the frames done. A hard kill (SIGKILL, power loss) leaves only the partial file.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import pathlib
import platform

import numpy as np

log = logging.getLogger(__name__)

USD_SUFFIXES = (".usdc", ".usda", ".usd")
CACHE_SUFFIXES = USD_SUFFIXES + (".npz",)
DIAGNOSTICS = {  # per-frame custom attributes: name -> (USD type name, description)
    "maxStrain": ("float", "max structural/shear strain l/L - 1 at the end of the frame"),
    "dt": ("float", "smallest step used in the frame [s]"),
    "solverIterations": ("int", "linear-solver iterations of the frame's steps (summed; 0 for explicit integrators)"),
    "solverResidual": ("float", "relative residual of the last linear solve in the frame (0 if none)"),
    "colliderContacts": ("int", "particle-collider contacts resolved in the frame's steps (summed)"),
    "colliderCcd": ("int", "of those, contacts only the continuous (swept) test found (summed)"),
    "selfProximity": ("int", "cloth-cloth repulsion impulses (proximity within the thickness) in the frame's steps"),
    "selfCcd": ("int", "cloth-cloth impacts found by continuous collision detection (summed over sweeps)"),
    "selfSweeps": ("int", "CCD sweeps with impulses run in the frame's steps"),
    "impactZones": ("int", "rigid impact zones formed in the frame's steps (Provot's fail-safe)"),
    "selfUnresolved": ("int", "steps that ended with cloth-cloth impacts left (should be 0)"),
}
# per-frame diagnostic attribute <- collision counter (cloth_warp.collision / cloth_warp.selfcollision)
COUNTER_DIAGNOSTICS = {"colliderContacts": "collider_contacts", "colliderCcd": "collider_ccd", "selfProximity": "self_proximity",
                       "selfCcd": "self_ccd", "selfSweeps": "self_sweeps", "impactZones": "impact_zones", "selfUnresolved": "unresolved"}
COLLIDER_SCOPE = "colliders"  # colliders are written under /World/colliders


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


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary name next to `path` to write to; rename it to `path` when the block succeeds
    (and remove it when it fails), so a file under the final name is always complete."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_text(path, text: str):
    """Write a text file atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def partial_path(path: pathlib.Path) -> pathlib.Path:
    """Where a cache is authored before it is renamed to `path`."""
    return path.with_name(f"{path.stem}.partial{path.suffix}")


def _prim_name(name: str) -> str:
    from pxr import Tf

    return Tf.MakeValidIdentifier(name or "cloth")


def _cloth_meshes(model):
    """(name, particle slice, triangles local to the cloth, corner uvs or None) per cloth of the model."""
    tris = model.tri_indices.numpy()
    out, used = [], set()
    for info in model.cloths:
        name = _prim_name(info.name)
        while name in used:
            name += "_"
        used.add(name)
        t = tris[info.triangles] - info.particle_start
        uv = info.topology.corner_uv
        out.append((name, info.particles, t.astype(np.int32), None if uv is None else np.asarray(uv)))
    return out


def _indexed_corner_uvs(corner_uv: np.ndarray):
    """Unique UV values and per-corner indices (faceVarying, indexed) from (t, 3, 2) corner UVs."""
    flat = np.asarray(corner_uv, np.float32).reshape(-1, 2)
    values, indices = np.unique(flat, axis=0, return_inverse=True)
    return values.astype(np.float32), indices.reshape(-1).astype(np.int32)


def _define_colliders(stage, model) -> list:
    """Collider prims under /World/colliders (UsdGeom shapes, meshes for mesh colliders) with a translate and
    an orient op; returns (collider, translate op, orient op, geom) per collider."""
    from pxr import Gf, UsdGeom, Vt

    if not getattr(model, "colliders", None):
        return []
    UsdGeom.Scope.Define(stage, f"/World/{COLLIDER_SCOPE}")
    out = []
    for col in model.colliders:
        path = f"/World/{COLLIDER_SCOPE}/{_prim_name(col.name)}"
        half = col.local_size
        if col.shape == "sphere":
            geom = UsdGeom.Sphere.Define(stage, path)
            geom.CreateRadiusAttr(col.radius)
            extent = [(-half[0],) * 3, (half[0],) * 3]
        elif col.shape in ("capsule", "cylinder"):
            geom = (UsdGeom.Capsule if col.shape == "capsule" else UsdGeom.Cylinder).Define(stage, path)
            geom.CreateRadiusAttr(col.radius)
            geom.CreateHeightAttr(col.height)
            geom.CreateAxisAttr(UsdGeom.Tokens.z)
            top = half[1] + (half[0] if col.shape == "capsule" else 0.0)
            extent = [(-half[0], -half[0], -top), (half[0], half[0], top)]
        elif col.shape == "box":
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
        else:
            geom = UsdGeom.Mesh.Define(stage, path)
            geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            tris = np.asarray(col.triangles, np.int32)
            pts = np.asarray(col.vertices, np.float32)
            geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
            geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(tris), 3, np.int32)))
            geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(tris.reshape(-1))))
            extent = [tuple(pts.min(0)), tuple(pts.max(0))]
        geom.CreateExtentAttr([Gf.Vec3f(*map(float, e)) for e in extent])
        geom.CreateDisplayColorAttr(Vt.Vec3fArray.FromNumpy(np.array([[0.55, 0.57, 0.60]], np.float32)))
        prim = geom.GetPrim()
        prim.SetCustomDataByKey("clothWarp:collider", {"shape": col.shape, "thickness": float(col.thickness),
                                                        "staticFriction": float(col.static_friction),
                                                        "kineticFriction": float(col.kinetic_friction)})
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


class CacheWriter:
    """Common interface: :meth:`write` a frame, :meth:`close` with a status (also as a context manager)."""

    path: pathlib.Path
    frames_written = 0

    def write(self, q: np.ndarray, qd: np.ndarray, diagnostics: dict | None = None) -> int:
        raise NotImplementedError

    def close(self, status: str = "complete", info: dict | None = None) -> pathlib.Path:
        raise NotImplementedError

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
        save_every: crate saves every so many frames (bounds memory and what a crash can lose).
        normals, velocities: author vertex normals / velocities per frame.
        metadata: JSON-able provenance merged into ``customLayerData["cloth_warp"]``.
    """

    def __init__(self, path, model, *, fps: float, start_frame: int = 1, save_every: int = 25, normals: bool = True,
                 velocities: bool = True, metadata: dict | None = None):
        from pxr import Sdf, Usd, UsdGeom, UsdPhysics, Vt

        self.path = pathlib.Path(path)
        if self.path.suffix.lower() not in USD_SUFFIXES:
            raise ValueError(f"a USD cache must end in {', '.join(USD_SUFFIXES)}, got {self.path.name!r}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.partial = partial_path(self.path)
        if self.partial.exists():
            self.partial.unlink()
        stale = Sdf.Layer.Find(str(self.partial))
        self.layer = stale if stale is not None else Sdf.Layer.CreateNew(str(self.partial))
        if stale is not None:
            stale.Clear()
        if self.layer is None:
            raise OSError(f"cannot create {self.partial}")
        self.ascii = self.path.suffix.lower() == ".usda"
        self.fps = float(fps)
        self.start_frame = int(start_frame)
        self.save_every = max(1, int(save_every))
        self.frames_written = 0
        self.closed = False
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
        self.meta = {"generator": "cloth_warp", "versions": package_versions(), "status": "running", "frames_written": 0,
                     "fps": self.fps, "start_frame": self.start_frame, "up_axis": model.up_axis}
        self.meta.update(metadata or {})
        self._set_metadata()

        rest = model.rest_positions
        self.meshes = []
        for name, particles, tris, corner_uv in _cloth_meshes(model):
            mesh = UsdGeom.Mesh.Define(stage, f"/World/{name}")
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            mesh.CreateDoubleSidedAttr(True)
            mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
            mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(tris), 3, np.int32)))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(tris.reshape(-1))))
            mesh.CreateDisplayColorAttr(Vt.Vec3fArray.FromNumpy(np.array([[0.75, 0.45, 0.30]], np.float32)))
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
            prim = mesh.GetPrim()
            for diag, (type_name, doc) in DIAGNOSTICS.items():
                vtype = Sdf.ValueTypeNames.Float if type_name == "float" else Sdf.ValueTypeNames.Int
                attr = prim.CreateAttribute(f"clothWarp:{diag}", vtype, custom=True)
                attr.SetDocumentation(doc)
                attrs[diag] = attr
            self.meshes.append((particles, tris, attrs))
        self.colliders = _define_colliders(stage, model)
        self._write_collider_poses(0)
        self.layer.Save()

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

    @property
    def next_time_code(self) -> int:
        return self.start_frame + self.frames_written

    def write(self, q: np.ndarray, qd: np.ndarray, diagnostics: dict | None = None) -> int:
        """Author one frame (positions [m], velocities [m/s] of all particles); returns its time code."""
        if self.closed:
            raise RuntimeError("cache already closed")
        Vt = self._Vt
        tc = self.next_time_code
        q = np.asarray(q, np.float32)
        qd = np.asarray(qd, np.float32)
        for particles, tris, attrs in self.meshes:
            x = np.ascontiguousarray(q[particles])
            attrs["points"].Set(Vt.Vec3fArray.FromNumpy(x), tc)
            attrs["extent"].Set(Vt.Vec3fArray.FromNumpy(np.stack([x.min(0), x.max(0)])), tc)
            if "normals" in attrs:
                attrs["normals"].Set(Vt.Vec3fArray.FromNumpy(vertex_normals(x, tris)), tc)
            if "velocities" in attrs:
                attrs["velocities"].Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(qd[particles])), tc)
            for key, value in (diagnostics or {}).items():
                if key in DIAGNOSTICS and value is not None:
                    attrs[key].Set(int(value) if DIAGNOSTICS[key][0] == "int" else float(value), tc)
        self.stage.SetEndTimeCode(tc)
        if self.frames_written > 0:
            self._write_collider_poses(self.frames_written)
        self.frames_written += 1
        if not self.ascii and self.frames_written % self.save_every == 0:
            self.meta["frames_written"] = self.frames_written
            self._set_metadata()
            self.layer.Save()
        return tc

    def close(self, status: str = "complete", info: dict | None = None) -> pathlib.Path:
        """Stamp the status (and `info`), save and rename to the final name; returns the final path."""
        if self.closed:
            return self.path
        from pxr import Sdf

        self.closed = True
        self.meta.update(info or {})
        self.meta.update(status=status, frames_written=self.frames_written)
        self._set_metadata()
        self.layer.Save()
        self.meshes.clear()
        self.stage = None
        self.layer = None
        os.replace(self.partial, self.path)
        # A layer of the same name opened earlier in this process would otherwise keep serving old data.
        old = Sdf.Layer.Find(str(self.path))
        if old is not None:
            old.Reload(force=True)
        log.info("wrote %s (%d frames, %s)", self.path, self.frames_written, status)
        return self.path


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
            out[k] = float(v)
        else:
            out[k] = json.dumps(v)
    return out


class NpzCacheWriter(CacheWriter):
    """Frames in a numpy ``.npz``: ``positions`` / ``velocities`` (frames, particles, 3) [m, m/s],
    ``triangles``, ``fps``, ``start_frame``, ``metadata`` (JSON), one array per diagnostic. Held in memory and
    written once by :meth:`close` (temporary name, then rename)."""

    def __init__(self, path, model, *, fps: float, start_frame: int = 1, metadata: dict | None = None, **_):
        self.path = pathlib.Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.fps, self.start_frame = float(fps), int(start_frame)
        self.triangles = model.tri_indices.numpy().copy()
        self.meta = {"generator": "cloth_warp", "versions": package_versions(), "status": "running", **(metadata or {})}
        self.q, self.qd, self.diag = [], [], {k: [] for k in DIAGNOSTICS}
        self.frames_written = 0
        self.closed = False

    def write(self, q, qd, diagnostics=None) -> int:
        self.q.append(np.array(q, np.float32))
        self.qd.append(np.array(qd, np.float32))
        for k in DIAGNOSTICS:
            v = (diagnostics or {}).get(k)
            self.diag[k].append(np.nan if v is None else v)
        self.frames_written += 1
        return self.start_frame + self.frames_written - 1

    def close(self, status="complete", info=None) -> pathlib.Path:
        if self.closed:
            return self.path
        self.closed = True
        self.meta.update(info or {})
        self.meta.update(status=status, frames_written=self.frames_written)
        n = len(self.triangles)
        with atomic_path(self.path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, positions=np.array(self.q).reshape(-1, *(self.q[0].shape if self.q else (0, 3))),
                                velocities=np.array(self.qd).reshape(-1, *(self.qd[0].shape if self.qd else (0, 3))),
                                triangles=self.triangles.reshape(n, 3), fps=self.fps, start_frame=self.start_frame,
                                metadata=json.dumps(self.meta), **{k: np.array(v, np.float64) for k, v in self.diag.items()})
        return self.path


def open_cache(path, model, **kwargs) -> CacheWriter:
    """A cache writer chosen by the file extension (.usdc / .usda / .usd or .npz)."""
    suffix = pathlib.Path(path).suffix.lower()
    if suffix in USD_SUFFIXES:
        return UsdCacheWriter(path, model, **kwargs)
    if suffix == ".npz":
        return NpzCacheWriter(path, model, **kwargs)
    raise ValueError(f"unknown cache format {suffix or '(none)'!r} for {path}; allowed: {', '.join(CACHE_SUFFIXES)}")


# -- reading --------------------------------------------------------------------------------------------------

class CacheReader:
    """Read a cache written by cloth_warp (or any USD stage with meshes): frames, topology, diagnostics.

    Attributes:
        fps, start_frame, end_frame, up_axis, metadata (the ``cloth_warp`` provenance dict, {} if none),
        meshes: list of dicts (path, points (rest), triangles (fan-triangulated), has_uv, samples).
    """

    def __init__(self, path):
        self.path = pathlib.Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"cache not found: {self.path}")
        suffix = self.path.suffix.lower()
        if suffix == ".npz":
            self._read_npz()
        elif suffix in USD_SUFFIXES:
            self._read_usd()
        else:
            raise ValueError(f"unknown cache format {suffix!r}; allowed: {', '.join(CACHE_SUFFIXES)}")

    def _read_npz(self):
        with np.load(self.path) as data:
            self._npz = {k: data[k] for k in data.files}
        d = self._npz
        self.fps, self.start_frame = float(d["fps"]), int(d["start_frame"])
        self.end_frame = self.start_frame + len(d["positions"]) - 1
        self.metadata = json.loads(str(d["metadata"]))
        self.up_axis = self.metadata.get("up_axis", "Y")
        self.stage = None
        self.colliders = []
        self.meshes = [{"path": "npz", "points": d["positions"][0] if len(d["positions"]) else np.zeros((0, 3)),
                        "triangles": d["triangles"], "has_uv": False, "samples": len(d["positions"])}]

    def _read_usd(self):
        from pxr import Usd, UsdGeom

        self.stage = Usd.Stage.Open(str(self.path))
        if self.stage is None:
            raise ValueError(f"cannot open {self.path} as USD")
        self.fps = float(self.stage.GetTimeCodesPerSecond())
        self.start_frame = int(self.stage.GetStartTimeCode())
        self.end_frame = int(self.stage.GetEndTimeCode())
        self.up_axis = str(UsdGeom.GetStageUpAxis(self.stage))
        meta = self.stage.GetRootLayer().customLayerData.get("cloth_warp", {})
        self.metadata = dict(meta)
        self.meshes = []
        self.colliders = []
        for prim in self.stage.Traverse():
            if str(prim.GetPath()).startswith(f"/World/{COLLIDER_SCOPE}/"):
                if prim.IsA(UsdGeom.Gprim):
                    self.colliders.append({"path": str(prim.GetPath()), "prim": prim,
                                           **dict(prim.GetCustomDataByKey("clothWarp:collider") or {})})
                continue
            if prim.IsA(UsdGeom.Mesh):
                mesh = UsdGeom.Mesh(prim)
                points = mesh.GetPointsAttr()
                counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], np.int64)
                indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], np.int64)
                rest = points.Get(Usd.TimeCode.Default())
                if rest is None:
                    rest = points.Get(Usd.TimeCode.EarliestTime())
                self.meshes.append({"path": str(prim.GetPath()), "points": np.asarray(rest, np.float32),
                                    "triangles": fan_triangulate(counts, indices),
                                    "has_uv": UsdGeom.PrimvarsAPI(prim).HasPrimvar("st"),
                                    "samples": points.GetNumTimeSamples(), "prim": prim})

    @property
    def frame_count(self) -> int:
        return self.end_frame - self.start_frame + 1

    def points(self, frame: int, mesh: int = 0) -> np.ndarray:
        """Positions of a mesh at a frame (time code) [m], float32 (n, 3)."""
        if self.stage is None:
            return self._npz["positions"][frame - self.start_frame]
        from pxr import UsdGeom

        attr = UsdGeom.Mesh(self.meshes[mesh]["prim"]).GetPointsAttr()
        return np.asarray(attr.Get(frame), np.float32)

    def diagnostics(self, mesh: int = 0) -> dict:
        """Per-frame diagnostics as {name: (time codes, values)}."""
        if self.stage is None:
            n = len(self._npz["positions"])
            tc = np.arange(self.start_frame, self.start_frame + n)
            return {k: (tc, self._npz[k]) for k in DIAGNOSTICS if k in self._npz}
        prim = self.meshes[mesh]["prim"]
        out = {}
        for k in DIAGNOSTICS:
            attr = prim.GetAttribute(f"clothWarp:{k}")
            if attr and attr.GetNumTimeSamples():
                tc = np.array(attr.GetTimeSamples())
                out[k] = (tc, np.array([attr.Get(t) for t in tc], np.float64))
        return out

    def summary(self) -> dict:
        """What `cloth-warp info` prints (JSON-able)."""
        diag = {}
        for k, (tc, v) in self.diagnostics().items():
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
