"""Collision handling after the integrator: cloth against colliders and cloth against itself.

Bridson, Fedkiw & Anderson (2002) in the order of physics.md 3(f): the integrator (and the strain
limiter) propose an end-of-step state from the collision-free start state; the collision pass turns
the step's average velocity vbar = (x_end - x_start) / h into one whose straight-line trajectory stays
clear of every collider by its thickness, with inelastic normal response and Coulomb friction, and
hands the same velocity correction to the end velocity. Every solver runs it as the last stage of
``step`` (so strain limiting never moves cloth back into a collider). With self-collision on, the
collider pass is followed by :class:`~cloth_warp.selfcollision.SelfCollision` on its result, which has
the last word (the cloth is intersection-free at the end of every step).

What differentiates (under ``wp.Tape``): the response is piecewise smooth in positions, velocities,
friction coefficients and collider poses; the choice of contacts (which particles touch what, the
trace's first-hit time) does not, so gradients see the active contact set as fixed.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .kernels import collide as kcol
from .model import Control, Model
from .selfcollision import COUNTERS as SELF_COUNTERS
from .selfcollision import SelfCollision

COUNTERS = ("collider_contacts", "collider_ccd")
ALL_COUNTERS = COUNTERS + SELF_COUNTERS  # with self-collision, read_counts() also has these


class CollisionHandler:
    """Cloth-collider contact with continuous detection (then self-collision, when the model has it on),
    run by the solvers after each step.

    Per step and particle, every collider in turn: the particle's path relative to the collider (start
    pose to end pose) is traced for its first point within the collider's thickness; the end point is
    put back on the tangent plane there (offset by the thickness) with inelastic normal response and
    static/kinetic Coulomb friction, then pushed out along the surface normal if curvature still leaves
    it inside. Only cloth vertices are tested (a collider's sharp edge can poke between vertices of a
    coarse cloth).

    Counters (summed over the steps since :meth:`reset_counts`): ``collider_contacts`` (particle-collider
    contacts resolved) and ``collider_ccd`` (of them, the ones only the continuous trace found: the end
    point alone was clear, so a discrete test would have tunnelled); with self-collision, also the
    counters of :class:`~cloth_warp.selfcollision.SelfCollision`.
    """

    def __init__(self, model: Model):
        self.model = model
        self.counts = wp.zeros(len(COUNTERS), dtype=wp.int32, device=model.device)
        self.self_collision = SelfCollision(model) if model.self_collision and model.tri_count else None

    @property
    def active(self) -> bool:
        return self.model.collider_count > 0 or self.self_collision is not None

    def notify_model_changed(self, flags: int) -> None:
        """Model fields changed (:class:`~cloth_warp.model.ModelFlags`): the collider pass reads the model at every
        step; self-collision refreshes its inverse masses."""
        if self.self_collision is not None:
            self.self_collision.notify_model_changed(flags)

    def begin_step(self):
        """A new step starts (its passes share the start state; caches of the previous step are stale)."""
        if self.self_collision is not None:
            self.self_collision.begin_step()

    def reset_counts(self):
        self.counts.zero_()
        if self.self_collision is not None:
            self.self_collision.reset_counts()

    def checkpoint_state(self) -> dict:
        """What carries from one frame to the next: with self-collision, its state (see
        :meth:`SelfCollision.checkpoint_state <cloth_warp.selfcollision.SelfCollision.checkpoint_state>`); the
        collider pass keeps nothing (poses come from the control, counters are per frame)."""
        if self.self_collision is None:
            return {}
        return {f"self.{k}": v for k, v in self.self_collision.checkpoint_state().items()}

    def restore_state(self, state: dict) -> None:
        if self.self_collision is not None:
            sub = {k[len("self."):]: v for k, v in state.items() if k.startswith("self.")}
            if not sub:
                raise ValueError("the checkpoint holds no self-collision state, this model has self-collision on")
            self.self_collision.restore_state(sub)
        self.reset_counts()

    def read_counts(self) -> dict:
        """The counters as ints (small device-to-host copies); with self-collision also its counters
        (see :class:`~cloth_warp.selfcollision.SelfCollision`)."""
        c = self.counts.numpy()
        out = {name: int(c[k]) for k, name in enumerate(COUNTERS)}
        if self.self_collision is not None:
            out.update(self.self_collision.read_counts())
        return out

    def apply(self, x_start: wp.array, x_end: wp.array, v_end: wp.array, control: Control, dt: float,
              x_out: wp.array, v_out: wp.array):
        """Resolve the step x_start -> (x_end, v_end) into (x_out, v_out) (may alias x_end / v_end when not taped):
        colliders first, then cloth against itself."""
        m = self.model
        if m.collider_count == 0:
            self.self_collision.apply(x_start, x_end, v_end, dt, x_out, v_out)
            return
        if self.self_collision is not None:
            rg = x_end.requires_grad
            x_c = wp.empty_like(x_end, requires_grad=rg) if rg else x_out
            v_c = wp.empty_like(v_end, requires_grad=rg) if rg else v_out
            self._colliders(x_start, x_end, v_end, control, dt, x_c, v_c)
            self.self_collision.apply(x_start, x_c, v_c, dt, x_out, v_out)
            return
        self._colliders(x_start, x_end, v_end, control, dt, x_out, v_out)

    def _colliders(self, x_start, x_end, v_end, control: Control, dt: float, x_out, v_out):
        m = self.model
        wp.launch(
            kcol.collide_colliders,
            dim=m.particle_count,
            inputs=[m.particle_pinned, m.collider_count, m.collider_shape, m.collider_size, m.collider_mesh, m.collider_deforming,
                    m.collider_thickness,
                    m.collider_static_friction, m.collider_kinetic_friction, m.collider_mesh_max_distance,
                    control.collider_transform_start, control.collider_transform_end, x_start, x_end, v_end, dt],
            outputs=[x_out, v_out, self.counts],
            device=m.device,
        )


def penetration_depths(model: Model, positions: np.ndarray, time: float = 0.0) -> np.ndarray:
    """Per collider, the largest depth [m] by which any free particle lies inside its thickness band
    (0 when none does), measured independently of the kernels with numpy (for tests and reports)."""
    import dataclasses

    free = model.particle_pinned.numpy() == 0
    x = np.asarray(positions, float)[free]
    out = np.zeros(model.collider_count)
    for k, col in enumerate(model.colliders):
        p, q = col.pose_at(time)
        moved = dataclasses.replace(col, position=tuple(p), rotation=tuple(q), keyframes=[], point_cache=None, point_cache_times=None,
                                    vertices=col.vertices_at(time) if col.shape == "mesh" else None)
        d = moved.distance(x) if len(x) else np.zeros(0)
        out[k] = max(0.0, float(np.max(col.thickness - d))) if len(d) else 0.0
    return out


def collider_distance(model: Model, collider: int, points, transform=None) -> tuple[np.ndarray, np.ndarray]:
    """Signed distances [m] and outward unit normals of world `points` to collider number `collider`, as
    the kernels compute them (at the initial pose, or at `transform` = (px, py, pz, qx, qy, qz, qw))."""
    pts = np.atleast_2d(np.asarray(points, np.float32))
    pose = model.collider_transforms(0.0) if transform is None else np.tile(np.asarray(transform, np.float32), (max(model.collider_count, 1), 1))
    x = wp.array(pts, dtype=wp.vec3, device=model.device)
    dist = wp.zeros(len(pts), dtype=float, device=model.device)
    normal = wp.zeros(len(pts), dtype=wp.vec3, device=model.device)
    wp.launch(kcol.eval_collider_distance, dim=len(pts),
              inputs=[collider, model.collider_shape, model.collider_size, model.collider_mesh, model.collider_mesh_max_distance,
                      wp.array(pose, dtype=wp.transform, device=model.device), x],
              outputs=[dist, normal], device=model.device)
    return dist.numpy().copy(), normal.numpy().copy()
