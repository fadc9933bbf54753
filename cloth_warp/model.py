"""Model (immutable description), State (per-step arrays) and Control (time-varying inputs)."""

from __future__ import annotations

import enum
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


def triangle_frames(corners: np.ndarray) -> np.ndarray:
    """Per triangle (corners (t, 3, 3)) its orthonormal frame as rows: the first edge's direction, the in-plane
    direction across it, the unit normal (t, 3, 3)."""
    e1 = corners[:, 1] - corners[:, 0]
    n = np.cross(e1, corners[:, 2] - corners[:, 0])
    e1 = e1 / np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-30)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    return np.stack([e1, np.cross(n, e1), n], axis=1)


@dataclass
class Attachment:
    """Hard-pinned particles bound to a mesh collider's surface (a waistband, a strap, a cuff on a body): each follows
    the point of its triangle at fixed barycentric weights plus a fixed `offset` in the triangle's own frame (along
    its first edge, across it in its plane, along its unit normal), as the collider moves and deforms (its point
    cache), with the surface's velocity.

    Attributes: name; collider: index into the model's colliders; particles (a,); triangles (a, 3) the collider's local
    vertex indices; weights (a, 3) barycentric; offset (a, 3) [m] in the triangle frame (:func:`triangle_frames`).
    """

    name: str
    collider: int
    particles: np.ndarray
    triangles: np.ndarray
    weights: np.ndarray
    offset: np.ndarray

    def targets(self, collider, time: float) -> np.ndarray:
        """World target positions [m] of the attached particles at `time` [s] on `collider` (the model's Collider)."""
        corners = np.asarray(collider.vertices_at(time), np.float64)[self.triangles]
        point = np.einsum("ar,arj->aj", self.weights, corners)
        local = point + np.einsum("aij,ai->aj", triangle_frames(corners), self.offset)
        p, q = collider.pose_at(time)
        return local @ quat_to_matrix(q).T + p


def attachment_gap(model, positions, time: float) -> float:
    """The largest distance [m] between any attached particle at `positions` ((n, 3)) and its target on its collider's
    surface at `time` [s] (0 without attachments): how far attachments drift from the body they are bound to."""
    x = np.asarray(positions, np.float64)
    gaps = [np.linalg.norm(x[a.particles] - a.targets(model.colliders[a.collider], time), axis=1).max()
            for a in model.attachments if len(a.particles)]
    return float(max(gaps, default=0.0))


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


class ModelFlags(enum.IntFlag):
    """Which Model fields were changed after a solver was built (``notify_model_changed(flags)``, Newton's
    ``SolverNotifyFlags`` pattern).

    Whatever derives data from the model when it is built (self-collision's inverse masses, a loss's mass
    weights) refreshes it when told; everything else reads the model at every step. Topology (indices,
    counts, colours, pinned sets) is not a flag: a changed topology needs a new model and solver.
    """

    PARTICLE_PROPERTIES = 1 << 0
    """particle_mass, particle_pin_stiffness (and what derives from them: inverse masses)."""
    PARTICLE_INITIAL_STATE = 1 << 1
    """particle_q, particle_qd: the state :meth:`Model.state` starts from."""
    SPRING_PROPERTIES = 1 << 2
    """spring_rest_length, spring_stiffness, spring_damping."""
    TRIANGLE_PROPERTIES = 1 << 3
    """tri_drag, membrane_stiffness, membrane_damping."""
    COLLIDER_PROPERTIES = 1 << 4
    """collider_thickness, collider_static_friction, collider_kinetic_friction."""
    SELF_COLLISION_PROPERTIES = 1 << 5
    """cloth_thickness, cloth_friction, self_collision_stiffness."""
    MODEL_PROPERTIES = 1 << 6
    """gravity, global_damping."""
    PLATE_PROPERTIES = 1 << 7
    """plate_stiffness."""
    ALL = (PARTICLE_PROPERTIES | PARTICLE_INITIAL_STATE | SPRING_PROPERTIES | TRIANGLE_PROPERTIES | COLLIDER_PROPERTIES
           | SELF_COLLISION_PROPERTIES | MODEL_PROPERTIES | PLATE_PROPERTIES)
    """Every field a flag covers."""


FIELD_FLAGS: dict[str, ModelFlags] = {
    "particle_mass": ModelFlags.PARTICLE_PROPERTIES,
    "particle_pin_stiffness": ModelFlags.PARTICLE_PROPERTIES,
    "particle_q": ModelFlags.PARTICLE_INITIAL_STATE,
    "particle_qd": ModelFlags.PARTICLE_INITIAL_STATE,
    "spring_rest_length": ModelFlags.SPRING_PROPERTIES,
    "spring_stiffness": ModelFlags.SPRING_PROPERTIES,
    "spring_damping": ModelFlags.SPRING_PROPERTIES,
    "tri_drag": ModelFlags.TRIANGLE_PROPERTIES,
    "membrane_stiffness": ModelFlags.TRIANGLE_PROPERTIES,
    "membrane_damping": ModelFlags.TRIANGLE_PROPERTIES,
    "plate_stiffness": ModelFlags.PLATE_PROPERTIES,
    "collider_thickness": ModelFlags.COLLIDER_PROPERTIES,
    "collider_static_friction": ModelFlags.COLLIDER_PROPERTIES,
    "collider_kinetic_friction": ModelFlags.COLLIDER_PROPERTIES,
    "cloth_thickness": ModelFlags.SELF_COLLISION_PROPERTIES,
    "cloth_friction": ModelFlags.SELF_COLLISION_PROPERTIES,
    "self_collision_stiffness": ModelFlags.SELF_COLLISION_PROPERTIES,
    "gravity": ModelFlags.MODEL_PROPERTIES,
    "global_damping": ModelFlags.MODEL_PROPERTIES,
}
"""The :class:`ModelFlags` member that covers each changeable Model field."""


class Model:
    """Description of the simulated cloth(s), created by :meth:`ModelBuilder.finalize`; solvers never write it.

    Every field is declared below with its unit and shape (Warp arrays are float32 unless noted; n =
    particle_count, s = spring_count, t = tri_count, e = membrane_count, p = plate_count, c = max(collider_count, 1)). The fields listed in
    :data:`FIELD_FLAGS` may be changed between runs (a fit does); whoever changes them then calls
    ``notify_model_changed(flags)`` on what was built from the model (see :class:`ModelFlags`).
    """

    def __init__(self):
        self.device = None
        """Warp device of the arrays."""
        self.requires_grad = False
        """Whether the differentiable arrays (see :func:`~cloth_warp.gradients.model_grad_arrays`) carry .grad."""
        self.up_axis = "Y"
        """The up axis, "Y" or "Z"."""

        # -- particles ---------------------------------------------------------------------------
        self.particle_count = 0
        """n, the number of particles."""
        self.particle_q: wp.array | None = None
        """Initial positions [m], shape (n,), vec3 (differentiable)."""
        self.particle_qd: wp.array | None = None
        """Initial velocities [m/s], shape (n,), vec3 (differentiable)."""
        self.particle_mass: wp.array | None = None
        """Lumped mass [kg] = areal density x dual area, shape (n,) (differentiable)."""
        self.particle_pinned: wp.array | None = None
        """1 where the particle is hard-pinned, shape (n,), int32."""
        self.particle_pin_stiffness: wp.array | None = None
        """Soft-pin stiffness toward Control.pin_target [N/m], shape (n,) (0 = none)."""
        self.rest_positions = np.zeros((0, 3))
        """Positions at rest [m], numpy (n, 3) float64 (handles' targets and the broad phase's voxel size)."""
        self.world_count = 1
        """W, the independent worlds batched in this model (:mod:`~cloth_warp.worlds`); 1: one world."""
        self.particle_world: wp.array | None = None
        """The world of each particle, shape (n,), int32 (zeros with one world)."""
        self.world_particle_start = np.zeros(2, int)
        """Each world's first particle and the particle count after them, numpy (W + 1,) (worlds are contiguous)."""
        self.world_models: list | None = None
        """Batched worlds with self-collision: each world's own Model, which its self-collision pass is built on
        (cloth_warp.collision.WorldSelfCollisionPass); None otherwise."""

        # -- springs and bend triples -------------------------------------------------------------
        self.spring_count = 0
        """s, the number of springs (linear springs first, then bend triples)."""
        self.linear_spring_count = 0
        """The number of linear springs (the first of the s)."""
        self.spring_indices: wp.array | None = None
        """Endpoints, shape (s, 2), int32."""
        self.spring_ends: wp.array | None = None
        """The same endpoints as rows, shape (s,), vec2i."""
        self.spring_rest_length: wp.array | None = None
        """Rest length [m], shape (s,) (differentiable)."""
        self.spring_stiffness: wp.array | None = None
        """k [N/m] of linear springs, k_b [N m^2] of buckling (bend) springs, shape (s,) (differentiable)."""
        self.spring_damping: wp.array | None = None
        """Kelvin-Voigt damping c [N s/m], shape (s,) (0 for buckling springs; differentiable)."""
        self.spring_law: wp.array | None = None
        """:class:`~cloth_warp.topology.SpringLaw` per spring, shape (s,), int32."""
        self.spring_kind: wp.array | None = None
        """:class:`~cloth_warp.topology.SpringKind` per spring, shape (s,), int32."""
        self.spring_middle: wp.array | None = None
        """Middle particle of a span-2 bend triple, -1 otherwise, shape (s,), int32."""
        self.bend_triples: wp.array | None = None
        """(end a, middle, end b) of each bend triple, shape (s - linear_spring_count,), vec3i."""
        self.spring_limited: wp.array | None = None
        """1 for the structural/shear linear springs the strain limiter keeps, shape (s,), int32."""

        # -- triangles -----------------------------------------------------------------------------
        self.tri_count = 0
        """t, the number of triangles."""
        self.tri_indices: wp.array | None = None
        """Corners, shape (t, 3), int32."""
        self.tri_vertices: wp.array | None = None
        """The same corners as rows, shape (t,), vec3i."""
        self.tri_drag: wp.array | None = None
        """Linear air drag c_A [N s/m^3] (force per area per normal relative speed; the kernel multiplies by
        the triangle's current area), shape (t,) (differentiable)."""
        self.tri_corner_weights: wp.array | None = None
        """Share of a triangle's drag per corner, shape (t,), vec3 (sums to 1)."""

        # -- triangle membrane elements (stretch and shear of cloths built with membrane="element") -----
        self.membrane_count = 0
        """e, the number of membrane elements (one per triangle of such cloths; 0 when every cloth uses springs)."""
        self.membrane_vertices: wp.array | None = None
        """Corners of each element (the triangle's, same winding), shape (e,), vec3i."""
        self.membrane_rest_inverse: wp.array | None = None
        """Dm^-1 [1/m]: the inverse of the rest edge matrix in the triangle's warp/weft frame
        (:func:`~cloth_warp.topology.triangle_rest_shapes`), shape (e,), mat22 (fixed: a new rest shape needs a new model)."""
        self.membrane_rest_area: wp.array | None = None
        """Rest area A [m^2], shape (e,) (fixed)."""
        self.membrane_stiffness: wp.array | None = None
        """(C_11, C_22, C_12, C_66) [N/m]: warp, weft, coupling and shear entries of the Voigt matrix in the
        warp/weft frame (:func:`~cloth_warp.elasticity.membrane_element_stiffness`), shape (e,), vec4 (differentiable)."""
        self.membrane_damping: wp.array | None = None
        """Kelvin-Voigt damping C_d = tau C [N s/m] (tau: the material's relaxation time), shape (e,), vec4
        (differentiable)."""
        self.particle_membrane_offsets: wp.array | None = None
        """Start of each particle's elements in particle_membrane_ids, shape (n + 1,), int32."""
        self.particle_membrane_ids: wp.array | None = None
        """Membrane elements incident to each particle, int32."""

        # -- plate-bending stencils (bending of cloths built with bending="stencil", cloth_warp.plate) --------
        self.plate_count = 0
        """p, the number of stencils (one per vertex of such cloths; 0 when every cloth bends with springs)."""
        self.plate_offsets: wp.array | None = None
        """Start of each stencil's points in plate_points, shape (p + 1,), int32."""
        self.plate_points: wp.array | None = None
        """The particles of each stencil: its vertex first, then its nearest neighbours, int32."""
        self.plate_weights: wp.array | None = None
        """c_j [1/m^2]: u_k = sum_j c_jk x_j is the curvature (K_ww, K_ff, 2 K_wf) along the normal, vec3 per entry
        of plate_points (fixed: the rest shape)."""
        self.plate_stiffness: wp.array | None = None
        """S = A_v D [N m^3]: the vertex's dual area times the plate's Voigt matrix in its warp/weft frame,
        shape (p,), mat33 (differentiable)."""

        # -- incidence lists (gather) and strain-limit colouring ------------------------------------
        self.particle_spring_offsets: wp.array | None = None
        """Start of each particle's springs in particle_spring_ids, shape (n + 1,), int32."""
        self.particle_spring_ids: wp.array | None = None
        """Springs incident to each particle, int32."""
        self.particle_spring_role: wp.array | None = None
        """0 / 1 for a spring's first / second endpoint, 2 for a bend triple's middle, int32."""
        self.particle_tri_offsets: wp.array | None = None
        """Start of each particle's triangles in particle_tri_ids, shape (n + 1,), int32."""
        self.particle_tri_ids: wp.array | None = None
        """Triangles incident to each particle, int32."""
        self.strain_limit_color_count = 0
        """The number of spring colours (no two springs of a colour share a particle)."""
        self.strain_limit_colors: wp.array | None = None
        """Per colour, the limited spring at each particle or -1, shape (colours, n), int32 (taped sweeps)."""
        self.strain_limit_color_offsets = np.zeros(1, int)
        """Start of each colour in strain_limit_color_springs, numpy (colours + 1,) int (forward sweeps)."""
        self.strain_limit_color_springs: wp.array | None = None
        """Limited springs ordered by colour, int32."""

        # -- cloths and handles ---------------------------------------------------------------------
        self.cloths: list[ClothInfo] = []
        """Where each cloth lives in the flat arrays, with its material and topology (host-side, as built)."""
        self.handles: list[Handle] = []
        self.attachments: list[Attachment] = []
        """Keyframed groups of hard-pinned particles (their targets go to Control.pin_target)."""

        # -- forces ----------------------------------------------------------------------------------
        self.gravity = (0.0, -9.81, 0.0)
        """Gravitational acceleration [m/s^2], 3 floats."""
        self.global_damping = 0.0
        """Mass-proportional damping rate [1/s]."""

        # -- colliders ----------------------------------------------------------------------------------
        self.colliders: list = []
        """The :class:`~cloth_warp.colliders.Collider` descriptions (host-side)."""
        self.collider_count = 0
        """The number of colliders (the arrays below have c = max(collider_count, 1) rows)."""
        self.collider_shape: wp.array | None = None
        """Index into colliders.SHAPES, shape (c,), int32."""
        self.collider_size: wp.array | None = None
        """Shape dimensions in the kernels' convention [m], shape (c,), vec3."""
        self.collider_mesh: wp.array | None = None
        """wp.Mesh id (0 for analytic shapes), shape (c,), uint64."""
        self.collider_meshes: dict = {}
        """Collider index -> wp.Mesh (keeps the meshes and their BVHs alive)."""
        self.collider_deforming: wp.array | None = None
        """1 for a mesh following a point cache (its wp.Mesh carries vertex velocities), shape (c,), int32."""
        self.collider_thickness: wp.array | None = None
        """Distance [m] the cloth keeps from each collider, shape (c,)."""
        self.collider_static_friction: wp.array | None = None
        """Static Coulomb coefficient, shape (c,) (differentiable)."""
        self.collider_kinetic_friction: wp.array | None = None
        """Kinetic Coulomb coefficient, shape (c,) (differentiable)."""
        self.collider_mesh_max_distance = 0.0
        """How far [m] mesh distance queries look."""

        # -- self-collision ---------------------------------------------------------------------------
        self.self_collision = False
        """Cloth-cloth contact on (see :mod:`~cloth_warp.selfcollision`)."""
        self.cloth_thickness = 0.0
        """Distance [m] kept between non-adjacent cloth elements."""
        self.cloth_friction = 0.0
        """Coulomb coefficient between cloth layers."""
        self.self_collision_stiffness = 0.0
        """Repulsion stiffness [N/m] of the proximity pass (default: the median structural spring constant)."""

    @property
    def animated(self) -> bool:
        """True when the control changes during a run (animated handles, attachments or colliders)."""
        return bool(self.handles) or bool(self.attachments) or any(c.animated for c in self.colliders)

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
        """Set the control for the step that ends at `time` [s] and lasts `dt` [s]: animated handles' and attachments'
        pin targets at `time`, colliders' poses at `time - dt` and `time` (static ones only when `force`)."""
        control.time = time
        if self.colliders and (force or any(c.animated for c in self.colliders)):
            control.collider_transform_start.assign(self.collider_transforms(time - dt))
            control.collider_transform_end.assign(self.collider_transforms(time))
            self.set_collider_geometry(time, dt)
        if not (self.handles or self.attachments):
            return
        targets = control.pin_target.numpy()
        for h in self.handles:
            targets[h.particles] = h.targets(self.rest_positions[h.particles], time)
        for a in self.attachments:
            targets[a.particles] = a.targets(self.colliders[a.collider], time)
        control.pin_target.assign(targets.astype(np.float32))

    # -- launch argument bundles ----------------------------------------------------------------
    def cloth(self, name: str) -> ClothInfo:
        for c in self.cloths:
            if c.name == name:
                return c
        raise KeyError(f"no cloth named {name!r}; cloths: {[c.name for c in self.cloths]}")
