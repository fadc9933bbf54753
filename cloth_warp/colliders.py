"""Collider descriptions: rigid shapes the cloth rests on, slides over and is pushed by.

A :class:`Collider` is a plane, sphere, capsule, box, cylinder or triangle mesh with a pose, a
thickness (the contact offset: no cloth vertex comes closer to the surface than this) and Coulomb
friction coefficients. An optional list of keyframes animates it as a rigid body: at time t its pose
is the keyframe transform (translation [m] from the initial position, rotation about its own origin)
applied after the initial pose, interpolated linearly / by slerp and held outside the keyframes.

Shapes in their own frame (as the kernels in ``cloth_warp.kernels.collide`` see them): a plane is
z = 0 with +z out of the solid; capsules and cylinders lie along local z (as USD's default axis);
boxes are centred. The builder's ``add_*`` methods place them from friendlier arguments (a normal, an
axis, a centre).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from .model import Keyframe, interpolate_keyframes, quat_multiply
from .validation import (
    LIMITS,
    InvalidValue,
    check_direction,
    check_keyframes,
    check_number,
    check_points,
    check_quaternion,
    check_vector,
)

SHAPES = ("plane", "sphere", "capsule", "box", "cylinder", "mesh")
SHAPE_IDS = {name: i for i, name in enumerate(SHAPES)}  # the kernels' SHAPE_* constants


@dataclass
class Collider:
    """One rigid collider.

    Attributes:
        name: prim name in caches.
        shape: one of :data:`SHAPES`.
        radius: sphere / capsule / cylinder radius [m].
        height: capsule: length of the cylindrical part (caps excluded, as UsdGeom.Capsule);
            cylinder: full height [m].
        size: box edge lengths along its local x, y, z [m].
        vertices, triangles: mesh collider geometry in its local frame [m] (already scaled).
        position: initial position of the local origin [m]; rotation: initial orientation (x, y, z, w).
        thickness: contact offset [m]: cloth vertices are kept at least this far from the surface.
        static_friction, kinetic_friction: Coulomb coefficients mu_s >= mu_k >= 0.
        keyframes: rigid animation (:class:`~cloth_warp.model.Keyframe`), empty for a static collider.
        point_cache: a deforming mesh collider's vertices (local frame [m]) at `point_cache_times`, shape
            (samples, vertices, 3) (a body read from a USD point cache); between samples the vertices move
            linearly, outside them they hold. The triangles stay the same.
        point_cache_times: the samples' times [s], increasing.
    """

    name: str
    shape: str
    radius: float = 0.0
    height: float = 0.0
    size: tuple = (0.0, 0.0, 0.0)
    vertices: np.ndarray | None = None
    triangles: np.ndarray | None = None
    position: tuple = (0.0, 0.0, 0.0)
    rotation: tuple = (0.0, 0.0, 0.0, 1.0)
    thickness: float = 0.004
    static_friction: float = 0.3
    kinetic_friction: float = 0.3
    keyframes: list[Keyframe] = field(default_factory=list)
    point_cache: np.ndarray | None = None
    point_cache_times: np.ndarray | None = None

    def __post_init__(self):
        if self.shape not in SHAPES:
            raise ValueError(f"collider {self.name!r}: unknown shape {self.shape!r}; allowed: {', '.join(SHAPES)}")
        where = f"collider {self.name!r}"

        def arg(key):
            return f"{where} {key}"

        self.thickness = check_number(arg("thickness"), self.thickness, LIMITS["thickness"])
        self.static_friction = check_number(arg("static_friction"), self.static_friction, LIMITS["friction"])
        self.kinetic_friction = check_number(arg("kinetic_friction"), self.kinetic_friction, LIMITS["friction"])
        try:
            if self.shape in ("sphere", "capsule", "cylinder"):
                need = "radius > 0"
                self.radius = check_number(arg("radius"), self.radius, LIMITS["length"])
            if self.shape == "capsule":
                need = "height >= 0 (the straight part)"
                self.height = check_number(arg("height"), self.height, LIMITS["height"])
            if self.shape == "cylinder":
                need = "height > 0"
                self.height = check_number(arg("height"), self.height, LIMITS["length"])
            if self.shape == "box":
                need = "three positive edge lengths"
                self.size = check_vector(arg("size"), self.size, LIMITS["length"])
        except InvalidValue as exc:
            raise InvalidValue(f"{exc}; a {self.shape} needs {need}") from None
        if self.shape == "mesh":
            self._check_mesh(where)
        if self.point_cache is not None:
            self._check_point_cache(where)
        if self.kinetic_friction > self.static_friction:
            raise ValueError(f"{where}: kinetic_friction {self.kinetic_friction} exceeds static_friction {self.static_friction}")
        self.rotation = check_quaternion(arg("rotation"), self.rotation)
        self.position = check_vector(arg("position"), self.position, LIMITS["position"])
        self.keyframes = [Keyframe(t, tr, q) for t, tr, q in check_keyframes(arg("keyframes"), self.keyframes)]

    def _check_mesh(self, where: str):
        if self.vertices is None or self.triangles is None:
            raise ValueError(f"{where}: a mesh collider needs vertices and triangles")
        from .topology import orient_triangles

        v = check_points(f"{where} vertices", self.vertices)
        t = np.asarray(self.triangles)
        if len(v) < 3:
            raise ValueError(f"{where} vertices: a mesh needs at least 3 vertices, got {len(v)}")
        if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0 or not np.issubdtype(t.dtype, np.integer):
            raise ValueError(f"{where} triangles: must be a non-empty (m, 3) integer array, got shape {t.shape}")
        if t.min() < 0 or t.max() >= len(v):
            raise ValueError(f"{where} triangles: index out of range [0, {len(v)}): {t.min()}..{t.max()}")
        issues = []
        flip = orient_triangles(v, t, issues=issues)
        if flip.any():
            t = t.copy()
            t[flip] = t[flip][:, [0, 2, 1]]
        for msg in issues:
            warnings.warn(f"{where}: {msg}", stacklevel=4)
        self.vertices = v
        self.triangles = t.astype(np.int32)

    def _check_point_cache(self, where: str):
        if self.shape != "mesh":
            raise ValueError(f"{where}: only a mesh collider can deform (point_cache)")
        pc = np.asarray(self.point_cache, np.float64)
        times = np.asarray(self.point_cache_times if self.point_cache_times is not None else [], np.float64).reshape(-1)
        if pc.ndim != 3 or pc.shape[1:] != self.vertices.shape:
            raise ValueError(f"{where}: point_cache must have shape (samples, {len(self.vertices)}, 3), got {pc.shape}")
        if len(times) != len(pc) or len(pc) == 0:
            raise ValueError(f"{where}: point_cache_times needs one time per sample ({len(pc)}), got {len(times)}")
        if not np.all(np.isfinite(times)):
            raise ValueError(f"{where} point_cache_times: must be finite, got {times.tolist()}")
        check_points(f"{where} point_cache", pc.reshape(-1, 3))
        if np.any(np.diff(times) <= 0.0):
            raise ValueError(f"{where}: point_cache_times must increase strictly")
        self.point_cache, self.point_cache_times = pc, times

    @property
    def deforming(self) -> bool:
        return self.point_cache is not None

    @property
    def animated(self) -> bool:
        return len(self.keyframes) > 0 or self.deforming

    def vertices_at(self, time: float) -> np.ndarray:
        """A mesh collider's local vertices [m] at `time` [s] (the point cache, linear between samples)."""
        if not self.deforming:
            return self.vertices
        times = self.point_cache_times
        k = int(np.clip(np.searchsorted(times, time, side="right") - 1, 0, len(times) - 1))
        if k == len(times) - 1 or time <= times[0]:
            return self.point_cache[k]
        w = (time - times[k]) / (times[k + 1] - times[k])
        return (1.0 - w) * self.point_cache[k] + w * self.point_cache[k + 1]

    @property
    def local_size(self) -> tuple[float, float, float]:
        """The kernels' size vector: radius / half height / half extents (see the kernels' docstring)."""
        if self.shape == "sphere":
            return (self.radius, 0.0, 0.0)
        if self.shape in ("capsule", "cylinder"):
            return (self.radius, 0.5 * self.height, 0.0)
        if self.shape == "box":
            return tuple(0.5 * float(s) for s in self.size)
        return (0.0, 0.0, 0.0)

    def pose_at(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """(position [m], quaternion (x, y, z, w)) of the collider's frame at `time` [s]."""
        p0 = np.asarray(self.position, float)
        q0 = np.asarray(self.rotation, float)
        if not self.keyframes:
            return p0, q0
        t, q = interpolate_keyframes(self.keyframes, time)
        return p0 + t, quat_multiply(q, q0)

    def distance(self, points) -> np.ndarray:
        """Signed distance [m] of world points to the surface at the initial pose (numpy; for tests and
        tools: meshes are measured by trimesh)."""
        from .model import quat_to_matrix

        x = np.atleast_2d(np.asarray(points, float))
        r = quat_to_matrix(self.rotation)
        p = (x - np.asarray(self.position)) @ r  # world -> local (row vectors)
        s = self.local_size
        if self.shape == "plane":
            return p[:, 2]
        if self.shape == "sphere":
            return np.linalg.norm(p, axis=1) - s[0]
        if self.shape == "capsule":
            q = p.copy()
            q[:, 2] -= np.clip(p[:, 2], -s[1], s[1])
            return np.linalg.norm(q, axis=1) - s[0]
        if self.shape == "box":
            q = np.abs(p) - np.asarray(s)
            return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(1), 0.0)
        if self.shape == "cylinder":
            d = np.stack([np.linalg.norm(p[:, :2], axis=1) - s[0], np.abs(p[:, 2]) - s[1]], 1)
            return np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(1), 0.0)
        return mesh_signed_distance(self.vertices, self.triangles, p)


def rotation_to_axis(axis, name: str = "axis") -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) of the shortest rotation taking local +z onto `axis` (non-zero; `name` is the
    argument named in the error)."""
    a = check_direction(name, axis)
    z = np.array([0.0, 0.0, 1.0])
    c = float(np.dot(z, a))
    if c < -1.0 + 1e-9:
        return (1.0, 0.0, 0.0, 0.0)  # half turn about x
    v = np.cross(z, a)
    q = np.array([v[0], v[1], v[2], 1.0 + c])
    return tuple((q / np.linalg.norm(q)).tolist())


def closest_mesh_points(vertices, triangles, points, chunk: int = 200_000) -> tuple[np.ndarray, np.ndarray]:
    """Brute force: per point, the closest point [m] of a triangle mesh and its triangle's index (trimesh's per-pair
    closest point over all triangles). O(points x triangles): for binding a few hundred points at set-up."""
    from trimesh.triangles import closest_point

    tri = np.asarray(vertices, float)[np.asarray(triangles)]
    p = np.atleast_2d(np.asarray(points, float))
    per = max(1, chunk // len(tri))
    out, which = np.empty_like(p), np.empty(len(p), np.int64)
    for s in range(0, len(p), per):
        q = p[s : s + per]
        pairs = np.repeat(q, len(tri), axis=0)
        cp = closest_point(np.tile(tri, (len(q), 1, 1)), pairs).reshape(len(q), len(tri), 3)
        k = np.argmin(np.linalg.norm(cp - q[:, None, :], axis=2), axis=1)
        out[s : s + per], which[s : s + per] = cp[np.arange(len(q)), k], k
    return out, which


def mesh_signed_distance(vertices, triangles, points, chunk: int = 200_000) -> np.ndarray:
    """Brute-force signed distance [m] of points to a triangle mesh (negative inside): the nearest point
    over all triangles (trimesh's per-pair closest point) and the sign of the generalised winding number
    (van Oosterom-Strackee solid angles). O(points x triangles): for tests and small meshes."""
    from trimesh.triangles import closest_point

    v = np.asarray(vertices, float)
    tri = v[np.asarray(triangles)]
    p = np.atleast_2d(np.asarray(points, float))
    per = max(1, chunk // len(tri))
    dist = np.empty(len(p))
    for s in range(0, len(p), per):
        q = p[s : s + per]
        pairs = np.repeat(q, len(tri), axis=0)
        cp = closest_point(np.tile(tri, (len(q), 1, 1)), pairs)
        dist[s : s + per] = np.linalg.norm(cp - pairs, axis=1).reshape(len(q), len(tri)).min(1)
    a = tri[None, :, 0, :] - p[:, None, :]
    b = tri[None, :, 1, :] - p[:, None, :]
    c = tri[None, :, 2, :] - p[:, None, :]
    la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
    num = np.einsum("ijk,ijk->ij", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("ijk,ijk->ij", a, b) * lc + np.einsum("ijk,ijk->ij", b, c) * la + np.einsum("ijk,ijk->ij", c, a) * lb
    winding = np.arctan2(num, den).sum(1) / (2.0 * np.pi)
    return np.where(winding > 0.5, -dist, dist)
