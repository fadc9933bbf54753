"""Collision handling after the integrator: cloth against colliders and cloth against itself.

Bridson, Fedkiw & Anderson (2002) in the order of physics.md 3(f): the integrator (and the strain
limiter) propose an end-of-step state from the collision-free start state; the collision pass turns
the step's average velocity vbar = (x_end - x_start) / h into one whose straight-line trajectory stays
clear of every collider by its thickness, with inelastic normal response and Coulomb friction, and
hands the same velocity correction to the end velocity. Both are passes (:mod:`~cloth_warp.passes`) run
after the strain limiter (so strain limiting never moves cloth back into a collider): the collider pass,
then, with self-collision on, :class:`~cloth_warp.selfcollision.SelfCollision` on its result, which has
the last word (the cloth is intersection-free at the end of every step).

What differentiates (under ``wp.Tape``): the response is piecewise smooth in positions, velocities,
friction coefficients and collider poses; the choice of contacts (which particles touch what, the
trace's first-hit time) does not, so gradients see the active contact set as fixed.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .diagnostics import ColliderReport, SelfCollisionReport
from .graphs import device_while
from .kernels import collide as kcol
from .kernels import selfcollide as ksc
from .model import Control, Model
from .passes import StepPass
from .records import record_values
from .selfcollision import COUNTERS as SELF_COUNTERS
from .selfcollision import SelfCollision

COUNTERS = ("collider_contacts", "collider_ccd", "collider_samples")
ALL_COUNTERS = COUNTERS + SELF_COUNTERS  # the counter names of both contact passes (frame diagnostics)


class ColliderPass(StepPass):
    """Cloth-collider contact with continuous detection, a pass after the integrator (:mod:`~cloth_warp.passes`).

    Per step and particle, every collider in turn: the particle's path relative to the collider (start
    pose to end pose) is traced for its first point within the collider's thickness; the end point is
    put back on the tangent plane there (offset by the thickness) with inelastic normal response and
    static/kinetic Coulomb friction, then pushed out along the surface normal if curvature still leaves
    it inside. Then the cloth's edges and triangles (:func:`sampled_elements`) are kept out of mesh colliders: each
    element's sample found inside (an edge: the middle of the stretch it runs inside; a triangle: its centroid, or a
    point over a corner of the surface poking through it) is moved out to a quarter of the thickness by its particles
    (kernels/collide.py `collide_element_samples`, SAMPLE_CLEARANCE), in rounds while one pushed (at most
    :attr:`sample_rounds`): the particles alone are held at the thickness, and a coarse cloth's edges between them
    spanned the mannequin's armpit through the body (3.5 cm edges) or cut a shoulder (3.2 cm) while every particle was
    outside. Elements with a pinned or attached particle have none. No host reads: capturable.

    Report (:class:`~cloth_warp.diagnostics.ColliderReport`, summed over the steps since :meth:`reset_report`):
    contacts resolved and, of them, the ones only the continuous trace found (``ccd``: the end point alone was
    clear, so a discrete test would have tunnelled); element samples pushed out (``samples``).
    """

    name = "colliders"

    def __init__(self, model: Model):
        self.model = model
        self.counts = wp.zeros(len(COUNTERS), dtype=wp.int32, device=model.device)
        tris = model.tri_indices.numpy().reshape(-1, 3) if model.tri_count else np.zeros((0, 3), int)
        self.elements = wp.array(sampled_elements(tris), dtype=wp.vec3i, device=model.device)
        """The elements whose samples are kept out of mesh colliders: every edge (its particles and -1), then every
        triangle; (S, 3) int32."""
        self.sample_rounds = 4
        """Most rounds of the element samples per step (more only while the last pushed one): each moves a particle by
        the weighted mean of its samples' pushes, so a sample deeper than its neighbours can take a few."""
        self.samples_on = True
        """Whether the element samples are kept out of the mesh colliders (in a recorded frame: as it was recorded)."""
        self._loop = wp.zeros(3, dtype=wp.int32, device=model.device)  # the rounds' loop state (kernels/collide.py)
        self._push_arrays = None  # (see _pushes)
        self.pinch = False
        """Whether a particle pinched between two facing surfaces is pushed out only to where it is as far from both
        (kernels/collide.py `pinch_height`), where the implicit solve lands it: set by a solver with the collider
        contacts in its solve. Without them the pass resolves each surface as it meets it, as the garments' dressing
        was tuned (dressed with the pinch, the shipped T-shirt started its run with an armpit seam 11 mm open)."""
        self.sample_height: wp.array | None = None
        """Per particle [m], set by a solver with the collider contacts in its solve: forward steps keep the height over a
        mesh collider at which the element samples left each particle they pushed, until it moves away (kernels/collide.py
        `hold_sample_heights`), so that the solve holds it there. None: not kept."""
        self._sample_pushed = None  # per particle, whether a sample pushed it in this pass (int32)

    @property
    def kernel_modules(self) -> tuple:
        return (kcol, ksc)  # (the element samples' pushes are applied as self-collision's velocity changes are)

    def reset_report(self):
        self.counts.zero_()

    def record_arrays(self) -> list:
        return [(self, "counts")]

    def read_report(self) -> ColliderReport:
        c = record_values(self.counts)
        return ColliderReport(contacts=int(c[0]), ccd=int(c[1]), samples=int(c[2]))

    def apply(self, x_start, x_end, v_end, control: Control, dt: float, x_out, v_out):
        m = self.model
        dev = m.device
        samples = self.samples_on and self.elements.shape[0] > 0 and m.collider_count > 0
        taped = x_end.requires_grad
        # the particles' contacts into the outputs, or, before the samples when taped, into arrays of the step's own (the
        # samples read them: a taped kernel's input is never overwritten)
        x_mid, v_mid = (wp.empty_like(x_out), wp.empty_like(v_out)) if samples and taped else (x_out, v_out)
        wp.launch(
            kcol.collide_colliders,
            dim=m.particle_count,
            inputs=[m.particle_pinned, m.collider_count, m.collider_shape, m.collider_size, m.collider_mesh, m.collider_deforming,
                    m.collider_thickness,
                    m.collider_static_friction, m.collider_kinetic_friction, m.collider_mesh_max_distance,
                    control.collider_transform_start, control.collider_transform_end, x_start, x_end, v_end, dt, int(self.pinch)],
            outputs=[x_mid, v_mid, self.counts],
            device=dev,
        )
        if not samples:
            return
        if taped:  # every round, each into arrays of its own
            for k in range(self.sample_rounds):
                last = k == self.sample_rounds - 1
                x_next, v_next = (x_out, v_out) if last else (wp.empty_like(x_out), wp.empty_like(v_out))
                self._sample_round(control, dt, x_mid, v_mid, x_next, v_next, fresh=True)
                x_mid, v_mid = x_next, v_next
            return
        if self.sample_height is not None:  # (the marks are read only to keep the heights)
            self._pushed_marks().zero_()
        self._loop.zero_()  # in place on the outputs: the first round, then more while the last pushed a sample
        self._sample_round(control, dt, x_out, v_out, x_out, v_out)
        device_while(self._loop, self._sample_round, control=control, dt=dt, x=x_out, v=v_out, x_next=x_out, v_next=v_out)
        if self.sample_height is not None:  # the heights the samples left their particles at, for the next step's solve
            wp.launch(kcol.hold_sample_heights, dim=m.particle_count,
                      inputs=[m.collider_count, m.collider_shape, m.collider_mesh, m.collider_thickness, m.collider_mesh_max_distance,
                              control.collider_transform_end, x_out, self._sample_pushed],
                      outputs=[self.sample_height], device=dev)

    def _sample_round(self, control: Control, dt: float, x, v, x_next, v_next, fresh: bool = False):
        """One round of the element samples from (x, v) into (x_next, v_next) (the same arrays but when taped), and the
        rounds' loop state."""
        m = self.model
        dev = m.device
        pushes = self._pushes(fresh)
        for a in pushes:
            a.zero_()
        wp.launch(kcol.collide_element_samples, dim=self.elements.shape[0],
                  inputs=[m.particle_pinned, m.collider_count, m.collider_shape, m.collider_mesh, m.collider_deforming,
                          m.collider_thickness, m.collider_mesh_max_distance, control.collider_transform_start,
                          control.collider_transform_end, self.elements, x, v, dt],
                  outputs=[*pushes, self.counts, self._loop[2:3], self._pushed_marks()], device=dev)
        dx, dv, weights = pushes  # each particle moved by the weighted mean of its samples' pushes
        wp.launch(ksc.apply_velocity_changes, dim=m.particle_count, inputs=[x, dx, weights], outputs=[x_next], device=dev)
        wp.launch(ksc.apply_velocity_changes, dim=m.particle_count, inputs=[v, dv, weights], outputs=[v_next], device=dev)
        if not fresh:
            wp.launch(kcol.next_sample_round, dim=1, inputs=[self.sample_rounds], outputs=[self._loop], device=dev)

    def _pushed_marks(self) -> wp.array:
        """Per particle, whether an element sample pushed it in this pass (int32; kernels/collide.py `hold_sample_heights`)."""
        if self._sample_pushed is None:
            self._sample_pushed = wp.zeros(self.model.particle_count, dtype=wp.int32, device=self.model.device)
        return self._sample_pushed

    def _pushes(self, fresh: bool) -> tuple:
        """Per particle: the weighted sums of its element samples' position [m] and velocity [m/s] changes and of their
        weights (the pass's own arrays; a taped step's fresh)."""
        n, dev = self.model.particle_count, self.model.device
        if fresh or self._push_arrays is None:
            arrays = (wp.zeros(n, dtype=wp.vec3, device=dev, requires_grad=fresh), wp.zeros(n, dtype=wp.vec3, device=dev, requires_grad=fresh),
                      wp.zeros(n, dtype=float, device=dev))
            if fresh:
                return arrays
            self._push_arrays = arrays
        return self._push_arrays


def sampled_elements(tri_indices: np.ndarray) -> np.ndarray:
    """The elements of a triangle mesh (T, 3) whose samples the colliders pass keeps out of mesh colliders: every edge
    once (its particles and -1), then every triangle. (S, 3) int32."""
    tris = np.asarray(tri_indices, np.int64).reshape(-1, 3)
    edges = np.unique(np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1), axis=0)
    return np.concatenate([np.column_stack([edges, np.full(len(edges), -1)]), tris]).astype(np.int32).reshape(-1, 3)


class SelfCollisionPass(StepPass):
    """Cloth against itself (:class:`~cloth_warp.selfcollision.SelfCollision`: proximity, CCD, impact zones), a
    pass after the colliders, with the last word: the cloth is intersection-free at the end of every step.

    Report: :class:`~cloth_warp.diagnostics.SelfCollisionReport` (its counters summed since :meth:`reset_report`).
    After ``set_recordable(True)`` (the Simulator's fixed-step frames) forward steps take its capturable path
    (fixed-capacity buffers; sweeps and rigid impact zones looping on the device); a frame in which a buffer
    overflowed is then re-run on the host path (see :mod:`~cloth_warp.passes`), the buffers grown to what it
    needed. Otherwise (a step called directly, taped steps) it takes the host path.

    Args:
        pair_capacity: the capturable path's starting capacity of candidate pairs per kind (default: 4 per
            particle; it grows on overflow).
    """

    name = "self_collision"
    checkpoint_key = "collisions.self"
    device_loops = True

    def __init__(self, model: Model, pair_capacity: int | None = None):
        self.model = model
        capacity = max(1024, 4 * model.particle_count) if pair_capacity is None else int(pair_capacity)
        self.self_collision = SelfCollision(model, capturable=False, pair_capacity=capacity)
        self._recordable = False
        self._status = None

    @property
    def kernel_modules(self) -> tuple:
        from .kernels import broadphase, selfcollide

        return (broadphase, selfcollide)

    @property
    def capturable(self) -> bool:
        """Whether the path it takes now can be recorded (after ``set_recordable(True)``; the host path cannot)."""
        return self.self_collision.capturable

    def set_recordable(self, on: bool) -> None:
        self._recordable = self.self_collision.capturable = bool(on)
        if on:  # its buffers now, not first inside a recorded frame: an allocation there is a memset the graph replays every
            # frame, which cleared the close pairs the next step's self-contacts in the solve start from (in every frame
            # of a frame graph recorded first, and not in one recorded later or run eagerly)
            self.self_collision.prepare_capturable()

    def needs_rerun(self, report: SelfCollisionReport) -> bool:
        return bool(report.overflowed)

    def begin_rerun(self) -> None:
        self.self_collision.restore_frame_start()

    def prepare_rerun(self, report: SelfCollisionReport) -> bool:
        grown = self.self_collision.grow(self._status)
        self.self_collision.capturable = False
        return grown

    def end_rerun(self) -> None:
        self.self_collision.capturable = self._recordable
        if self._recordable:  # grown buffers now, not first inside the next recorded frame (see set_recordable)
            self.self_collision.prepare_capturable()

    def notify_model_changed(self, flags: int) -> None:
        self.self_collision.notify_model_changed(flags)

    def begin_step(self):
        """A new step starts (its rounds share the start state; the last step's broad phase is stale)."""
        self.self_collision.begin_step()

    def reset_report(self):
        """A frame starts: its counters from zero, and what the broad phase carries saved (see :meth:`begin_rerun`)."""
        self.self_collision.reset_counts()
        self.self_collision.save_frame_start()

    def record_arrays(self) -> list:
        return [(self.self_collision, "counts")]

    def read_report(self) -> SelfCollisionReport:
        """The counters since the last reset; the host-side ones (a host-path step's) are cleared as they are read,
        since a replayed frame resets only the device block."""
        sc = self.self_collision
        status, counts = sc.read_report()
        self._status = status  # what prepare_rerun grows
        sc.host_counts = dict.fromkeys(sc.host_counts, 0)
        sc._grown0 = sc.grid.vertex_face.grown + sc.grid.edge_edge.grown
        return SelfCollisionReport.from_counts(counts, tuple(sorted(status.overflow)))

    def checkpoint_state(self) -> dict:
        """The broad phase's buffer capacities and counters (see :meth:`SelfCollision.checkpoint_state
        <cloth_warp.selfcollision.SelfCollision.checkpoint_state>`)."""
        return self.self_collision.checkpoint_state()

    def restore_state(self, state: dict) -> None:
        if not state:
            raise ValueError("the checkpoint holds no self-collision state, this model has self-collision on")
        self.self_collision.restore_state(state)
        self.reset_report()

    def apply(self, x_start, x_end, v_end, control: Control, dt: float, x_out, v_out):
        self.self_collision.apply(x_start, x_end, v_end, dt, x_out, v_out)


class WorldSelfCollisionPass(StepPass):
    """Self-collision of batched worlds (:mod:`cloth_warp.worlds`): one :class:`SelfCollisionPass` per world, built on
    the world's own model (``Model.world_models``: its broad phase, buffers, welded seams and counters are its single
    run's) and applied to the world's slice of the batch's particle arrays (contiguous views), world after world. On
    the CPU each world is therefore its single run bit for bit; the batch pays a launch per world and stage (a
    recorded frame replays them). The report sums the worlds' counters; a frame re-runs when any world's buffers
    overflowed, those worlds' grown."""

    name = "self_collision"
    checkpoint_key = "collisions.self"
    device_loops = True

    def __init__(self, model: Model):
        from .worlds import world_slices

        self.model = model
        self.slices = world_slices(model)
        self.worlds = [SelfCollisionPass(m) for m in model.world_models]
        self._reports: list[SelfCollisionReport] = []
        self._views: dict = {}  # (array pointer, world) -> the world's view, one object per array (see _view)

    def _view(self, a: wp.array, k: int) -> wp.array:
        """World k's slice of particle array `a`, the same view object each time (a self-collision pass knows a later
        round of its step by its start positions' identity)."""
        key = (a.ptr, k)
        view = self._views.get(key)
        if view is None:
            view = self._views[key] = a[self.slices[k]]
        return view

    @property
    def kernel_modules(self) -> tuple:
        return self.worlds[0].kernel_modules

    @property
    def capturable(self) -> bool:
        return all(p.capturable for p in self.worlds)

    def set_recordable(self, on: bool) -> None:
        for p in self.worlds:
            p.set_recordable(on)

    def needs_rerun(self, report: SelfCollisionReport) -> bool:
        return bool(report.overflowed)

    def begin_rerun(self) -> None:
        for p in self.worlds:  # each world runs the frame again from where it started it (then as alone)
            p.begin_rerun()

    def prepare_rerun(self, report: SelfCollisionReport) -> bool:
        grown = False
        for p, r in zip(self.worlds, self._reports):
            if p.needs_rerun(r):
                grown = p.prepare_rerun(r) or grown
        return grown

    def end_rerun(self) -> None:
        for p in self.worlds:
            p.end_rerun()

    def notify_model_changed(self, flags: int) -> None:
        for m, sl, p in zip(self.model.world_models, self.slices, self.worlds):
            m.particle_mass.assign(self.model.particle_mass[sl])  # (what a self-collision pass reads of the model)
            m.particle_pinned.assign(self.model.particle_pinned[sl])
            p.notify_model_changed(flags)

    def begin_step(self):
        for p in self.worlds:
            p.begin_step()

    def reset_report(self):
        for p in self.worlds:
            p.reset_report()

    def record_arrays(self) -> list:
        return [pair for p in self.worlds for pair in p.record_arrays()]

    def read_report(self) -> SelfCollisionReport:
        """The worlds' counters summed (:attr:`world_reports`: each world's)."""
        self._reports = [p.read_report() for p in self.worlds]
        counts = {name: sum(getattr(r, name) for r in self._reports) for name in self._reports[0].counters()}
        overflowed = sorted({kind for r in self._reports for kind in r.overflowed})
        return SelfCollisionReport.from_counts(counts, tuple(overflowed))

    @property
    def world_reports(self) -> list[SelfCollisionReport]:
        """Each world's report from the last :meth:`read_report`."""
        return list(self._reports)

    def checkpoint_state(self) -> dict:
        return {f"world{k}.{key}": v for k, p in enumerate(self.worlds) for key, v in p.checkpoint_state().items()}

    def restore_state(self, state: dict) -> None:
        for k, p in enumerate(self.worlds):
            prefix = f"world{k}."
            p.restore_state({key[len(prefix):]: v for key, v in state.items() if key.startswith(prefix)})

    def apply(self, x_start, x_end, v_end, control: Control, dt: float, x_out, v_out):
        if x_start.requires_grad:
            raise NotImplementedError("taped steps of batched worlds with self-collision are not supported yet")
        for k, p in enumerate(self.worlds):
            p.apply(*(self._view(a, k) for a in (x_start, x_end, v_end)), control, dt, self._view(x_out, k), self._view(v_out, k))


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
