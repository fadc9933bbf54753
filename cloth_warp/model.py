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
        kf = self.keyframes
        if time <= kf[0].time:
            return np.asarray(kf[0].translation, float), _quat_to_matrix(kf[0].rotation)
        if time >= kf[-1].time:
            return np.asarray(kf[-1].translation, float), _quat_to_matrix(kf[-1].rotation)
        k = int(np.searchsorted([f.time for f in kf], time, side="right")) - 1
        a, b = kf[k], kf[k + 1]
        s = (time - a.time) / (b.time - a.time)
        t = (1.0 - s) * np.asarray(a.translation, float) + s * np.asarray(b.translation, float)
        return t, _quat_to_matrix(_slerp(np.asarray(a.rotation, float), np.asarray(b.rotation, float), s))

    def targets(self, rest_positions: np.ndarray, time: float) -> np.ndarray:
        """Target positions [m] of the handle's particles at `time`."""
        t, r = self.transform_at(time)
        return (rest_positions - self.pivot) @ r.T + self.pivot + t


def _quat_to_matrix(q) -> np.ndarray:
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
        time: simulated time at the end of the step the control was last updated for [s].
    """

    def __init__(self, pin_target: wp.array, wind: wp.array):
        self.pin_target = pin_target
        self.wind = wind
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
        tri_indices: (tri_count, 3) int32; tri_drag: c_A per triangle [N s/m^3];
        tri_corner_weights: share of each triangle's drag per corner (vec3, sums to 1).
        particle_spring_offsets / _ids / _role, particle_tri_offsets / _ids: incidence lists (gather); the
            role is 0 / 1 for a spring's first / second endpoint and 2 for a bend triple's middle.
        strain_limit_colors: (colors, particle_count) int32: per colour, the structural/shear spring at
            each particle or -1 (Gauss-Seidel strain-limit passes).
        gravity: (3,) [m/s^2]; global_damping: mass-proportional damping rate [1/s].
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
        c = Control(
            wp.clone(self.particle_q, requires_grad=False),
            wp.zeros(1, dtype=wp.vec3, device=self.device, requires_grad=rg),
        )
        self.update_control(c, 0.0)
        return c

    def update_control(self, control: Control, time: float):
        """Move the animated handles' pin targets to where they are at `time` [s]."""
        control.time = time
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
