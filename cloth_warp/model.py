"""Model (immutable description), State (per-step arrays) and Control (time-varying inputs)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .materials import FabricMaterial
from .topology import ClothTopology


@dataclass
class ClothInfo:
    """Where one cloth lives inside the model's flat arrays."""

    name: str
    particle_start: int
    particle_count: int
    tri_start: int
    tri_count: int
    material: FabricMaterial
    topology: ClothTopology

    @property
    def particles(self) -> slice:
        return slice(self.particle_start, self.particle_start + self.particle_count)

    @property
    def triangles(self) -> slice:
        return slice(self.tri_start, self.tri_start + self.tri_count)


@dataclass
class Keyframe:
    """A rigid transform at a time: translation [m] and rotation quaternion (x, y, z, w)."""

    time: float
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)


@dataclass
class Handle:
    """Hard-pinned particles that follow a keyframed rigid transform about `pivot`.

    Between keyframes the translation is interpolated linearly and the rotation by slerp; before the
    first / after the last keyframe the transform is held.
    """

    name: str
    particles: np.ndarray
    keyframes: list[Keyframe]
    pivot: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def transform_at(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """(translation, rotation matrix 3x3) at `time` [s]."""
        t, q = interpolate_keyframes(self.keyframes, time)
        return t, quat_to_matrix(q)

    def targets(self, rest_positions: np.ndarray, time: float) -> np.ndarray:
        """Target positions [m] of the handle's particles at `time`."""
        t, r = self.transform_at(time)
        return (rest_positions - self.pivot) @ r.T + self.pivot + t


def interpolate_keyframes(keyframes: list[Keyframe], time: float) -> tuple[np.ndarray, np.ndarray]:
    """(translation [m], quaternion (x, y, z, w)) at `time` [s]: linear / slerp between keyframes, held
    before the first and after the last."""
    kf = keyframes
    if time <= kf[0].time:
        return np.asarray(kf[0].translation, float), np.asarray(kf[0].rotation, float)
    if time >= kf[-1].time:
        return np.asarray(kf[-1].translation, float), np.asarray(kf[-1].rotation, float)
    k = int(np.searchsorted([f.time for f in kf], time, side="right")) - 1
    a, b = kf[k], kf[k + 1]
    s = (time - a.time) / (b.time - a.time)
    t = (1.0 - s) * np.asarray(a.translation, float) + s * np.asarray(b.translation, float)
    return t, _slerp(np.asarray(a.rotation, float), np.asarray(b.rotation, float), s)


def keyframe_weights(keyframes: list[Keyframe], time: float) -> np.ndarray:
    """Weights w_j with translation(time) = sum_j w_j keyframes[j].translation (linear interpolation, held
    outside the keyframes' range): the derivative of a handle's translation by each keyframe's."""
    w = np.zeros(len(keyframes))
    times = [f.time for f in keyframes]
    if time <= times[0]:
        w[0] = 1.0
    elif time >= times[-1]:
        w[-1] = 1.0
    else:
        k = int(np.searchsorted(times, time, side="right")) - 1
        s = (time - times[k]) / (times[k + 1] - times[k])
        w[k], w[k + 1] = 1.0 - s, s
    return w


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product a * b of quaternions (x, y, z, w): rotate by b, then by a."""
    ax, ay, az, aw = np.asarray(a, float)
    bx, by, bz, bw = np.asarray(b, float)
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def quat_to_matrix(q) -> np.ndarray:
    """3x3 rotation matrix of a quaternion (x, y, z, w) (normalised first)."""
    x, y, z, w = np.asarray(q, float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    q0 = q0 / np.linalg.norm(q0)
    q1 = q1 / np.linalg.norm(q1)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(d)
    return (np.sin((1 - s) * theta) * q0 + np.sin(s * theta) * q1) / np.sin(theta)


class State:
    """Per-step arrays.

    Attributes:
        particle_q: particle positions [m], shape (particle_count,), vec3.
        particle_qd: particle velocities [m/s], shape (particle_count,), vec3.
    """

    def __init__(self, particle_q: wp.array, particle_qd: wp.array):
        self.particle_q = particle_q
        self.particle_qd = particle_qd

    @property
    def requires_grad(self) -> bool:
        return bool(self.particle_q.requires_grad)

    def assign(self, other: State):
        """Copy another state's arrays into this one (forward-only use)."""
        wp.copy(self.particle_q, other.particle_q)
        wp.copy(self.particle_qd, other.particle_qd)


class Control:
    """Time-varying inputs of one step.

    Attributes:
        pin_target: where hard-pinned particles must be at the end of the step and where soft pins
            pull [m], shape (particle_count,), vec3 (ignored for free particles).
        wind: uniform wind velocity [m/s], shape (1,), vec3 (an array so gradients can reach it).
        collider_transform_start, collider_transform_end: each collider's pose (world <- local) at the
            start and at the end of the step, shape (max(collider_count, 1),), wp.transform.
        time: simulated time at the end of the step the control was last updated for [s].
    """

    def __init__(self, pin_target: wp.array, wind: wp.array, collider_transform_start: wp.array | None = None,
                 collider_transform_end: wp.array | None = None):
        self.pin_target = pin_target
        self.wind = wind
        self.collider_transform_start = collider_transform_start
        self.collider_transform_end = collider_transform_end
        self.time = 0.0

    def set_wind(self, wind):
        """Set the uniform wind velocity [m/s] (host-side; not for taped parameters)."""
        self.wind.assign(np.asarray(wind, np.float32).reshape(1, 3))


class Model:
    """Immutable description of the simulated cloth(s); created by :meth:`ModelBuilder.finalize`.

    Attributes (Warp arrays, float32 unless noted):
        particle_q, particle_qd: initial positions [m] / velocities [m/s] (vec3).
        particle_mass: lumped mass [kg] = areal density x dual area.
        particle_pinned: 1 where the particle is hard-pinned (int32).
        particle_pin_stiffness: soft-pin stiffness toward Control.pin_target [N/m] (0 = none).
        spring_indices: endpoints (spring_count, 2) int32; spring_rest_length [m];
        spring_stiffness: k [N/m] (linear law) or k_b [N m^2] (buckling law);
        spring_damping: c [N s/m]; spring_law / spring_kind: int32 enums (topology.SpringLaw / SpringKind);
        spring_middle: middle particle of span-2 bend triples, -1 otherwise. Springs are ordered linear
            first (`linear_spring_count` of them), bend triples after.
        spring_ends (vec2i per spring), bend_triples ((end a, middle, end b) vec3i per bend triple, in
            spring order from `linear_spring_count`), tri_vertices (vec3i): the same indices as vector rows.
        tri_indices: (tri_count, 3) int32; tri_drag: c_A per triangle [N s/m^3];
        tri_corner_weights: share of each triangle's drag per corner (vec3, sums to 1).
        particle_spring_offsets / _ids / _role, particle_tri_offsets / _ids: incidence lists (gather); the
            role is 0 / 1 for a spring's first / second endpoint and 2 for a bend triple's middle.
        strain_limit_colors: (colors, particle_count) int32: per colour, the structural/shear spring at
            each particle or -1 (Gauss-Seidel strain-limit passes).
        gravity: (3,) [m/s^2]; global_damping: mass-proportional damping rate [1/s].
        colliders: the :class:`~cloth_warp.colliders.Collider` descriptions; per collider the arrays
            collider_shape (int32, SHAPES index), collider_size (vec3, kernel convention),
            collider_mesh (uint64 wp.Mesh id, 0 for analytic shapes), collider_deforming (int32, 1 for a
            mesh following a point cache: its wp.Mesh carries vertex velocities), collider_thickness [m],
            collider_static_friction, collider_kinetic_friction (Coulomb coefficients).
        self_collision: cloth-cloth contact on (see :mod:`~cloth_warp.selfcollision`);
            cloth_thickness: the distance [m] kept between non-adjacent cloth elements;
            cloth_friction: Coulomb coefficient between cloth layers; self_collision_stiffness: the
            repulsion stiffness [N/m] of the proximity pass.
    """

    def __init__(self):
        self.device = None
        self.requires_grad = False
        self.particle_count = 0
        self.spring_count = 0
        self.tri_count = 0
        self.gravity = (0.0, -9.81, 0.0)
        self.up_axis = "Y"
        self.global_damping = 0.0
        self.cloths: list[ClothInfo] = []
        self.handles: list[Handle] = []
        self.rest_positions = np.zeros((0, 3))
        self.colliders: list = []
        self.collider_count = 0
        self.self_collision = False
        self.cloth_thickness = 0.0
        self.cloth_friction = 0.0
        self.self_collision_stiffness = 0.0

    @property
    def animated(self) -> bool:
        """True when the control changes during a run (animated handles or colliders)."""
        return bool(self.handles) or any(c.animated for c in self.colliders)

    # -- factories (the only other places requires_grad is decided) ---------------------------
    def state(self, requires_grad: bool | None = None) -> State:
        """A state initialised with the model's initial positions and velocities."""
        rg = self.requires_grad if requires_grad is None else requires_grad
        return State(
            wp.clone(self.particle_q, requires_grad=rg),
            wp.clone(self.particle_qd, requires_grad=rg),
        )

    def control(self, requires_grad: bool | None = None) -> Control:
        """A control with pins at their rest targets and no wind."""
        rg = self.requires_grad if requires_grad is None else requires_grad
        n = max(self.collider_count, 1)
        c = Control(
            wp.clone(self.particle_q, requires_grad=False),
            wp.zeros(1, dtype=wp.vec3, device=self.device, requires_grad=rg),
            wp.zeros(n, dtype=wp.transform, device=self.device),
            wp.zeros(n, dtype=wp.transform, device=self.device),
        )
        self.update_control(c, 0.0, force=True)
        return c

    def collider_transforms(self, time: float) -> np.ndarray:
        """Every collider's pose at `time` [s] as rows (px, py, pz, qx, qy, qz, qw), shape (max(count, 1), 7)."""
        out = np.zeros((max(self.collider_count, 1), 7), np.float32)
        out[:, 6] = 1.0
        for k, col in enumerate(self.colliders):
            p, q = col.pose_at(time)
            out[k, :3], out[k, 3:] = p, q
        return out

    def set_collider_geometry(self, time: float, dt: float = 0.0):
        """Move deforming mesh colliders to their point cache at `time` [s], with vertex velocities
        (x(time) - x(time - dt)) / dt [m/s], and refit their BVHs. (The meshes are shared by every
        Control of the model: the geometry is that of the last step set up; it is not differentiated.)"""
        for k, col in enumerate(self.colliders):
            if not col.deforming:
                continue
            mesh = self.collider_meshes[k]
            end = col.vertices_at(time)
            vel = (end - col.vertices_at(time - dt)) / dt if dt > 0.0 else np.zeros_like(end)
            mesh.points.assign(end.astype(np.float32))
            mesh.velocities.assign(vel.astype(np.float32))
            mesh.refit()

    def update_control(self, control: Control, time: float, dt: float = 0.0, force: bool = False):
        """Set the control for the step that ends at `time` [s] and lasts `dt` [s]: animated handles'
        pin targets at `time`, colliders' poses at `time - dt` and `time` (static ones only when `force`)."""
        control.time = time
        if self.colliders and (force or any(c.animated for c in self.colliders)):
            control.collider_transform_start.assign(self.collider_transforms(time - dt))
            control.collider_transform_end.assign(self.collider_transforms(time))
            self.set_collider_geometry(time, dt)
        if not self.handles:
            return
        targets = control.pin_target.numpy()
        for h in self.handles:
            targets[h.particles] = h.targets(self.rest_positions[h.particles], time)
        control.pin_target.assign(targets.astype(np.float32))

    # -- launch argument bundles ----------------------------------------------------------------
    def cloth(self, name: str) -> ClothInfo:
        for c in self.cloths:
            if c.name == name:
                return c
        raise KeyError(f"no cloth named {name!r}; cloths: {[c.name for c in self.cloths]}")
