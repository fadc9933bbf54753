"""Provot (1995) strain limiting with its convergence check on the device and a per-step record.

The limiter sweeps until no structural or shear spring is longer than (1 + max_strain) L by more than its
tolerance, or until its cap of sweeps; the check runs on the device after every sweep
(``wp.capture_while``), so eager, graph-captured and taped steps stop at the same sweep. What each step
left is recorded on the device (:meth:`StrainLimiter.record_step`) and read once per frame
(:meth:`StrainLimiter.read_report`, a :class:`~cloth_warp.diagnostics.StrainLimitReport`).
"""

from __future__ import annotations

import heapq
import math

import numpy as np
import warp as wp

from ..autodiff import paused_tape
from ..diagnostics import StrainLimitReport
from ..graphs import device_while
from ..kernels import collide as kcol
from ..kernels import constraints as kc
from ..kernels.worlds import world_slots_length
from ..model import Control, Model, ModelFlags, State
from ..passes import StepPass
from ..records import record_values
from ..reductions import launch_reduction

DEFAULT_SWEEPS = 128
"""Cap of Gauss-Seidel sweeps per step (API and scene default)."""
REPORT_TOLERANCE = 1.0e-3
"""Excess strain counted as a miss when the limiter runs a fixed number of sweeps (tolerance None)."""


class StrainLimitWarning(UserWarning):
    """The strain limit was not reached within the cap of sweeps in some steps of a run."""


class StrainLimiter(StepPass):
    """Provot (1995) deformation constraints: no structural/shear spring longer than (1 + max_strain) L; the
    first pass of a step (:mod:`~cloth_warp.passes`), a corrector (the contact passes after it get the last word).

    Each sweep starts with long-range attachments (Kim, Chentanez & Mueller 2012): every particle stays
    within (1 + max_strain) times its shortest rest path along limited springs from the nearest
    `attachments` groups of hard-pinned particles (a bound every state within the spring limits meets; it
    removes the global stretch of a cloth hanging from a few points). Then it visits the springs colour by
    colour (no two springs of a colour share a particle), moving the endpoints of over-stretched springs
    toward each other by `relaxation` times the excess (never below the rest length), split by inverse
    mass (all of it to the free end when the other is pinned). Velocities are then corrected by the
    position change over dt (Provot's "inverse dynamics"), so the limiter adds no momentum: the centre of
    mass of a free sheet moves as without it.

    A particle touching a collider at a sweep's start (outside its solid and within one thickness beyond
    it; the nearest, relative to the thickness; the colliders at their end-of-step poses) is not moved into it: a
    spring whose correction would move that end inward moves it in the collider's tangent plane only, with the share
    of the excess its inverse mass has along the spring there, and the other end takes the rest (kernels/constraints.py
    `limit_split`). Without that, the limiter shortened springs wrapping a rim or a body through the solid and the
    colliders pass pushed their ends back out, stretched again. The contacts are found again at every sweep, so cloth
    the sweeps carry over a rim is free to turn round it. With seams (:meth:`weld_sewn_points`, set by
    :func:`~cloth_warp.passes.build_passes`) every sweep ends with the sewing pass's weld, so a welded point's
    particles move as one and the weld after the limiter stretches nothing again.

    Sweeps stop when no limited spring exceeds the limit by more than `tolerance` (strain; checked on the
    device after every sweep, also inside a captured graph and under the tape) or after `iterations`
    sweeps (the cap); a step whose integrator output already meets the tolerance runs none. With
    ``tolerance=None`` every step runs exactly `iterations` sweeps. A step that ends above the tolerance is
    counted in the record (:meth:`read_report`), never silently.

    Forward steps sweep in place, one thread per spring of a colour. Taped steps (``x_in.requires_grad``)
    sweep out of place through reused buffers and keep the positions at the start of every
    :attr:`snapshot_every`-th sweep (no gradient arrays: 10 arrays for 128 sweeps); their backward pass
    recomputes the sweeps in between and each sweep's passes, and runs their adjoints (one extra forward
    pass of the sweeps). Gradients flow through the active (clamped) constraints only: the clamp is
    piecewise. Taped steps cannot be captured.

    Args:
        model: the model (its structural/shear springs and their colouring).
        max_strain: the limit (0.1 = 10 %).
        iterations: the most sweeps per step (default :data:`DEFAULT_SWEEPS`).
        attachments: pinned groups each particle is attached to (0: none; at most 4).
        tolerance: excess strain at which sweeping stops; None for exactly `iterations` sweeps.
        relaxation: over-relaxation of each correction, in [1, 2).
        colliders: keep particles touching a collider from being moved into it (below); False sweeps as if there
            were no colliders.
    """

    name = "strain_limit"
    corrector = True
    device_loops = True

    def __init__(self, model: Model, max_strain: float = 0.1, iterations: int = DEFAULT_SWEEPS, attachments: int = 4,
                 tolerance: float | None = 1.0e-3, relaxation: float = 1.5, colliders: bool = True):
        from ..validation import LIMITS, check_number

        max_strain = check_number("max_strain", max_strain, LIMITS["strain_limit"])
        if max_strain <= 0.0:
            raise ValueError(f"max_strain: must be > 0 (0.1 = 10 %), got {max_strain!r}")
        iterations = check_number("iterations", iterations, LIMITS["iterations"])
        if tolerance is not None:
            tolerance = check_number("tolerance", tolerance, LIMITS["tolerance"])
        if not (1.0 <= relaxation < 2.0):
            raise ValueError(f"strain-limit relaxation must be in [1, 2), got {relaxation!r}")
        self.model = model
        self.max_strain = float(max_strain)
        self.iterations = int(iterations)
        self.tolerance = None if tolerance is None else float(tolerance)
        self.relaxation = float(relaxation)
        dev = model.device
        worlds = self.worlds = int(model.world_count)  # batched worlds: one set of each per world (kernels/constraints.py)
        self._excess = wp.zeros(worlds * kc.EXCESS_SIZE, dtype=float, device=dev)  # per-kind accumulator, empty between uses
        self._status = wp.zeros(worlds * kc.STATUS_SIZE, dtype=float, device=dev)  # [before, structural, shear] excess of the last step
        self._loop = wp.zeros(world_slots_length(kc.LIMIT_LOOP_SIZE, worlds), dtype=wp.int32, device=dev)  # [continue, sweeps]
        self.record = wp.zeros(worlds * kc.RECORD_SIZE, dtype=float, device=dev)
        self._record_backup = wp.zeros(worlds * kc.RECORD_SIZE, dtype=float, device=dev)
        self._buffers: dict = {}  # taped steps' work arrays (see the taped path)
        self.colliders = bool(colliders)
        self.contact_normal = wp.zeros(model.particle_count, dtype=wp.vec3, device=dev)
        """Per particle, the outward normal of the collider it touches at the sweep's start, zero for none (unit, (n,))."""
        self.contact_collider = wp.full(model.particle_count, -1, dtype=wp.int32, device=dev)
        """Per particle, the collider it touches at the sweep's start, -1 for none ((n,))."""
        self._touching = False
        self._collider_poses: wp.array | None = None  # the colliders' poses in the apply running (None: no colliders)
        self.weld_distance: float | None = None
        self.point_members: wp.array | None = None
        """Per particle, the particles of its welded sewn point (itself among them), -1 padded ((n, k) int32; None: none
        welded or not set, :meth:`weld_sewn_points`)."""
        if not (0 <= int(attachments) <= kc.ATTACHMENT_MAX):
            raise ValueError(f"attachments: must be in [0, {kc.ATTACHMENT_MAX}], got {attachments!r}")
        self._attachments = int(attachments)
        ids, dist = attachment_table(model, self._attachments)
        self.attachment_count = ids.shape[1]
        if self.attachment_count:
            self.attachment_particle = wp.array(ids, dtype=wp.int32, device=dev)
            self.attachment_rest_distance = wp.array(dist.astype(np.float32), dtype=float, device=dev)
        wp.launch(kc.reset_strain_excess, dim=worlds, outputs=[self._excess], device=dev, record_tape=False)

    def weld_sewn_points(self, weld_distance: float | None) -> None:
        """Keep each welded sewn point's particles together in every sweep (the sewing pass's weld,
        :func:`~cloth_warp.sewing.welded_point_roots` at `weld_distance` [m]; None: not), so that the weld after the
        limiter does not stretch the springs beside a seam again (see the class)."""
        from ..sewing import welded_point_roots

        self.weld_distance = None if weld_distance is None else float(weld_distance)
        roots = np.full(self.model.particle_count, -1) if weld_distance is None else welded_point_roots(self.model, weld_distance)
        sewn = np.flatnonzero(roots >= 0)
        if not len(sewn):
            self.point_members = None
            return
        order = sewn[np.argsort(roots[sewn], kind="stable")]
        _, first, count = np.unique(roots[order], return_index=True, return_counts=True)
        if count.max() > kc.WELD_MEMBERS_MAX:
            raise ValueError(f"a welded sewn point joins {count.max()} particles; the strain limiter keeps at most "
                             f"{kc.WELD_MEMBERS_MAX} together")
        table = np.full((self.model.particle_count, int(count.max())), -1, np.int32)
        for f, c in zip(first.tolist(), count.tolist()):
            members = order[f:f + c]
            table[members, :c] = members
        if self.point_members is not None and self.point_members.shape == table.shape:
            self.point_members.assign(table)  # in place: captured graphs keep reading the same array
        else:
            self.point_members = wp.array(table, dtype=wp.int32, device=self.model.device)

    def notify_model_changed(self, flags: int) -> None:
        """Model fields changed (:class:`~cloth_warp.model.ModelFlags`): new rest lengths give new attachment
        distances (rewritten in place: captured graphs keep reading the same arrays), new initial positions new
        welded points. Masses and rest lengths are otherwise read at every sweep; which particles are pinned is
        topology."""
        if flags & ModelFlags.PARTICLE_INITIAL_STATE and self.weld_distance is not None:
            self.weld_sewn_points(self.weld_distance)
        if flags & ModelFlags.SPRING_PROPERTIES and self.attachment_count:
            ids, dist = attachment_table(self.model, self._attachments)
            self.attachment_particle.assign(ids)
            self.attachment_rest_distance.assign(dist.astype(np.float32))

    @property
    def active(self) -> bool:
        return self.model.strain_limit_color_count > 0

    @property
    def kernel_modules(self) -> tuple:
        return (kc, kcol)

    @property
    def report_tolerance(self) -> float:
        """The excess [strain] above which a step counts as missed."""
        return self.tolerance if self.tolerance is not None else REPORT_TOLERANCE

    # -- the last step (each reads the device) ------------------------------------------------------------------
    @property
    def last_iterations(self) -> int:
        """Sweeps run by the last apply()."""
        return int(self._loop.numpy()[1])

    @property
    def last_initial_excess(self) -> float:
        """Excess strain of the integrator's output in the last apply(), before limiting."""
        return float(self._status.numpy()[0])

    @property
    def last_excess(self) -> float:
        """Excess strain left after the last apply() (structural and shear)."""
        s = self._status.numpy()
        return float(max(s[1], s[2]))

    @property
    def converged(self) -> bool:
        """Whether the last apply() met the tolerance (:attr:`report_tolerance`)."""
        return self.last_excess <= self.report_tolerance

    # -- the record of steps --------------------------------------------------------------------------------------
    def end_step(self):
        self.record_step()

    def record_step(self):
        """Add the last apply() to the record (once per step, after its last round: :meth:`end_step`)."""
        with paused_tape():
            wp.launch(kc.record_strain_limit, dim=self.worlds, inputs=[self._status, self._loop, self.report_tolerance, self.worlds],
                      outputs=[self.record, self._record_backup], device=self.model.device)

    def discard_step(self):
        """Take the last recorded step back out of the record (a rejected adaptive step)."""
        wp.copy(self.record, self._record_backup)

    def reset_report(self):
        self.record.zero_()

    def record_arrays(self) -> list:
        return [(self, "record")]

    def read_report(self) -> StrainLimitReport:
        """The record since the last :meth:`reset_report` (one read of 7 numbers per world; batched worlds': the sweeps
        summed over them, the excess, misses and most sweeps the worst world's)."""
        r = record_values(self.record).astype(np.float64).reshape(self.worlds, kc.RECORD_SIZE)
        r = np.where(np.arange(kc.RECORD_SIZE) == kc.RECORD_SWEEPS, r.sum(0), r.max(0))
        missed = int(r[kc.RECORD_MISSED])
        return StrainLimitReport(
            max_strain=self.max_strain, tolerance=self.report_tolerance, max_sweeps=self.iterations,
            structural_excess=float(r[kc.RECORD_STRUCTURAL]), shear_excess=float(r[kc.RECORD_SHEAR]),
            initial_excess=float(r[kc.RECORD_INITIAL]), steps=int(r[kc.RECORD_STEPS]), missed_steps=missed,
            sweeps=int(r[kc.RECORD_SWEEPS]), most_sweeps=int(r[kc.RECORD_MOST_SWEEPS]), frames=1, missed_frames=int(missed > 0))

    # -- limiting -----------------------------------------------------------------------------------------------------
    def apply(self, x_start, x_end: wp.array, v_end: wp.array, control: Control, dt: float, x_out: wp.array, v_out: wp.array):
        """Limit x_end into x_out and correct v_end into v_out by the position change over dt (see the class; the
        control gives the colliders' end poses, None: no colliders; the start positions are not used)."""
        self._collider_poses = None
        if self.colliders and self.model.collider_count and control is not None:
            self._collider_poses = control.collider_transform_end
        elif self._touching:
            self.contact_normal.zero_()
            self.contact_collider.fill_(-1)
            self._touching = False
        state_out = State(x_out, v_out)
        if x_end.requires_grad:
            self._apply_taped(x_end, v_end, state_out, dt)
        else:
            self._apply_forward(x_end, v_end, state_out, dt)

    def _touch_colliders(self, x):
        """The collider each particle touches at x (a sweep's start) and its outward normal (:attr:`contact_normal`;
        off a tape: held fixed through the sweep, as the implicit solve holds its contact set)."""
        if self._collider_poses is None:
            return
        m = self.model
        self._touching = True
        wp.launch(kcol.eval_limit_contacts, dim=m.particle_count,
                  inputs=[m.particle_pinned, m.collider_count, m.collider_shape, m.collider_size, m.collider_mesh,
                          m.collider_thickness, m.collider_mesh_max_distance, self._collider_poses, x],
                  outputs=[self.contact_collider, self.contact_normal], device=m.device, record_tape=False)

    @property
    def _check(self) -> int:
        return int(self.tolerance is not None)

    # the tolerance bookkeeping (counters and excess measures: no gradient) stays off a tape
    def _begin(self, x):
        m = self.model
        wp.launch(kc.reset_strain_excess, dim=self.worlds, outputs=[self._excess], device=m.device, record_tape=False)
        self._measure(x)
        self._clear_batch_flag()
        wp.launch(kc.begin_strain_limit, dim=self.worlds, inputs=[self.iterations, self.report_tolerance, self._check, self.worlds],
                  outputs=[self._excess, self._status, self._loop], device=m.device, record_tape=False)

    def _end_sweep(self, x):
        if self._check:
            self._measure(x)
        self._clear_batch_flag()
        wp.launch(kc.end_strain_limit_sweep, dim=self.worlds, inputs=[self.iterations, self.report_tolerance, self._check, self.worlds],
                  outputs=[self._excess, self._status, self._loop], device=self.model.device, record_tape=False)

    def _clear_batch_flag(self):
        """Batched worlds: clear the batch's loop state before the worlds' kernels set it (kernels/worlds.py world_slot)."""
        if self.worlds > 1:
            self._loop[:kc.LIMIT_LOOP_SIZE].zero_()

    def _finish(self, x):
        if not self._check:  # fixed sweeps: measure what they left, once
            self._measure(x)
            wp.launch(kc.finish_strain_limit, dim=self.worlds, outputs=[self._excess, self._status], device=self.model.device, record_tape=False)

    def _measure(self, x):
        m = self.model
        launch_reduction(kc.eval_strain_excess_kinds, kc.eval_strain_excess_kinds_blocks, m.spring_count,
                         inputs=[m.spring_indices, m.spring_rest_length, m.spring_limited, m.spring_kind, x, self.max_strain,
                                 m.particle_world, self.worlds],
                         outputs=[self._excess], device=m.device, per_item=self.worlds > 1)

    def _apply_forward(self, x_in, v_in, state_out: State, dt: float):
        """Forward-only path: sweeps in place on state_out, one thread per spring of a colour."""
        m = self.model
        x = state_out.particle_q
        wp.copy(x, x_in)
        self._begin(x)
        welded = self._buffer("welded") if self.point_members is not None else None  # (not in the loop: CUDA refuses it)
        device_while(self._loop, self._sweep_in_place, x=x, welded=welded)
        self._finish(x)
        wp.launch(kc.correct_velocity, dim=m.particle_count, inputs=[x_in, x, v_in, dt], outputs=[state_out.particle_qd], device=m.device)

    def _sweep_in_place(self, x, welded):
        m = self.model
        self._touch_colliders(x)
        if self.attachment_count:
            self._attach(x, x)  # reads only pinned neighbours, writes its own particle: safe in place
        offsets = m.strain_limit_color_offsets
        for c in range(m.strain_limit_color_count):
            wp.launch(
                kc.apply_strain_limit_springs,
                dim=int(offsets[c + 1] - offsets[c]),
                inputs=[m.strain_limit_color_springs, int(offsets[c]), m.spring_indices, m.spring_rest_length,
                        m.particle_mass, m.particle_pinned, self.contact_normal, self.max_strain, self.relaxation, m.particle_world, self.worlds, self._loop],
                outputs=[x],
                device=m.device,
            )
        if welded is not None:
            wp.launch(kc.weld_limited_points, dim=m.particle_count,
                      inputs=[self.point_members, m.particle_mass, m.particle_pinned, x, m.particle_world, self.worlds, self._loop],
                      outputs=[welded], device=m.device)
            wp.copy(x, welded)
        self._end_sweep(x)

    # -- taped path -----------------------------------------------------------------------------------------------
    # Buffers (particle_count vec3 each, no gradients, allocated once): one per pass of a sweep, the running
    # positions, two adjoints and `snapshot_every` sweep starts of one segment (recomputed in the backward pass).
    @property
    def snapshot_every(self) -> int:
        """Taped steps keep the positions at the start of every this-many-th sweep (ceil(sqrt(iterations)))."""
        return max(1, math.ceil(math.sqrt(self.iterations)))

    def _apply_taped(self, x_in, v_in, state_out: State, dt: float):
        m = self.model
        if m.device.is_capturing:
            raise RuntimeError("taped strain limiting cannot be captured into a graph: its sweeps are counted on the host "
                               "so that the backward pass knows them")
        x_out = state_out.particle_q
        every = self.snapshot_every
        with paused_tape() as tape:
            snapshots = [x_in]  # the positions at the start of sweeps 0, every, 2 every, ...
            gates = []  # batched worlds: which worlds each sweep ran in (the loop state before it)
            run = self._buffer("run")
            x = x_in
            sweeps = 0
            self._begin(x_in)
            while self._loop.numpy()[0]:
                if sweeps and sweeps % every == 0:
                    snapshots.append(wp.clone(x))
                if self.worlds > 1:
                    gates.append(wp.clone(self._loop))
                wp.copy(run, self._sweep(x))
                x = run
                sweeps += 1
                self._end_sweep(x)
            self._finish(x)
            wp.copy(x_out, x)
        if tape is not None:
            grads = [a for a in (x_in, x_out, m.spring_rest_length, m.particle_mass) if a.grad is not None]
            poses = self._collider_poses
            tape.record_func(lambda: self._backward(snapshots, gates, sweeps, x_in, x_out, poses), grads)
        wp.launch(kc.correct_velocity, dim=m.particle_count, inputs=[x_in, x_out, v_in, dt], outputs=[state_out.particle_qd], device=m.device)

    def _passes(self, gate: wp.array | None = None):
        """One sweep as out-of-place passes (thread per particle): (kernel, the inputs before x, the inputs after x).
        Batched worlds: the passes run in the worlds `gate` (a loop state; default the current one) has sweeping."""
        m = self.model
        gate = self._loop if gate is None else gate
        out = []
        if self.attachment_count:
            out.append((kc.apply_attachment_limit, [self.attachment_particle, self.attachment_rest_distance, m.particle_pinned],
                        [self.max_strain, m.particle_world, self.worlds, gate]))
        for c in range(m.strain_limit_color_count):
            out.append((kc.apply_strain_limit_color, [m.strain_limit_colors, m.spring_indices, m.spring_rest_length,
                                                      m.particle_mass, m.particle_pinned, self.contact_normal],
                        [c, self.max_strain, self.relaxation, m.particle_world, self.worlds, gate]))
        if self.point_members is not None:
            out.append((kc.weld_limited_points, [self.point_members, m.particle_mass, m.particle_pinned],
                        [m.particle_world, self.worlds, gate]))
        return out

    def _buffer(self, key):
        buf = self._buffers.get(key)
        if buf is None:
            buf = self._buffers[key] = wp.zeros(self.model.particle_count, dtype=wp.vec3, device=self.model.device)
        return buf

    def _sweep(self, x_src, record: list | None = None, gate: wp.array | None = None) -> wp.array:
        """One sweep out of place through the pass buffers; returns the last pass's (a buffer: copy it to keep it).
        `record` gets the input of every pass; `gate` as in :meth:`_passes`."""
        m = self.model
        self._touch_colliders(x_src)
        for k, (kernel, before, after) in enumerate(self._passes(gate)):
            dst = self._buffer(("pass", k))
            wp.launch(kernel, dim=m.particle_count, inputs=[*before, x_src, *after], outputs=[dst], device=m.device)
            if record is not None:
                record.append(x_src)
            x_src = dst
        return x_src

    def _backward(self, snapshots: list, gates: list, sweeps: int, x_in: wp.array, x_out: wp.array, poses: wp.array | None = None):
        """Adjoint of a taped apply(): d/dx_out -> d/dx_in (and the rest lengths and masses, when they have gradients).

        Segment by segment from the last: the sweep starts of the segment are recomputed from its snapshot, then
        each sweep's passes from its start (bit-identical to the forward run, in the worlds it ran in: `gates`) and
        their adjoints run in reverse; each sweep's contact normals from its start, with the colliders' poses of the
        step taped (`poses`)."""
        m = self.model
        self._collider_poses = poses

        def gate(k):
            return gates[k] if gates else None

        every = self.snapshot_every
        adj, spare = self._buffer("adjoint0"), self._buffer("adjoint1")
        wp.copy(adj, x_out.grad)
        if not x_out.retain_grad:  # consumed, as a kernel's adjoint consumes its outputs' (Warp's final-write-wins)
            x_out.grad.zero_()
        grad_of = {id(a): a.grad for a in (m.spring_rest_length, m.particle_mass) if a.grad is not None}
        normal_adj = None
        if poses is not None:  # the contact normals turn with the points they were found at (a sweep's start)
            normal_adj = grad_of[id(self.contact_normal)] = self._buffer("normal_adjoint")
        for first in range(every * ((sweeps - 1) // every) if sweeps else -1, -1, -every):
            starts = [snapshots[first // every]]
            for k in range(first + 1, min(first + every, sweeps)):
                seg = self._buffer(("segment", k - first))
                wp.copy(seg, self._sweep(starts[-1], gate=gate(k - 1)))
                starts.append(seg)
            for k in range(first + len(starts) - 1, first - 1, -1):
                start = starts[k - first]
                sources: list = []
                self._sweep(start, sources, gate=gate(k))
                passes = self._passes(gate(k))
                if normal_adj is not None:
                    normal_adj.zero_()
                for j in range(len(passes) - 1, -1, -1):
                    kernel, before, after = passes[j]
                    spare.zero_()
                    wp.launch(kernel, dim=m.particle_count, inputs=[*before, sources[j], *after], outputs=[self._buffer(("pass", j))],
                              adj_inputs=[grad_of.get(id(a)) for a in before] + [spare] + [None] * len(after), adj_outputs=[adj],
                              adjoint=True, device=m.device)
                    adj, spare = spare, adj
                if normal_adj is not None:  # (the sweep's recomputation found its contacts: `_touch_colliders`)
                    wp.launch(kcol.eval_limit_contact_normals, dim=m.particle_count,
                              inputs=[self.contact_collider, m.collider_shape, m.collider_size, m.collider_mesh,
                                      m.collider_mesh_max_distance, poses, start],
                              outputs=[self.contact_normal], adj_inputs=[None] * 6 + [adj], adj_outputs=[normal_adj],
                              adjoint=True, device=m.device)
        wp.launch(kc.accumulate_vectors, dim=m.particle_count, inputs=[adj], outputs=[x_in.grad], device=m.device)

    def _attach(self, x_src, x_dst):
        m = self.model
        wp.launch(
            kc.apply_attachment_limit,
            dim=m.particle_count,
            inputs=[self.attachment_particle, self.attachment_rest_distance, m.particle_pinned, x_src, self.max_strain, m.particle_world,
                    self.worlds, self._loop],
            outputs=[x_dst],
            device=m.device,
        )


def attachment_table(model: Model, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Per particle, the nearest pinned particle of up to `count` pinned groups and the rest path length.

    Groups are connected components of pinned particles (a pinned edge is one group, each pinned corner
    another). Shortest paths run along the limited (structural/shear) springs with their rest lengths
    (Dijkstra from each group). Returns (ids, distances) of shape (particle_count, k), -1 / 0 padded.
    """
    n = model.particle_count
    pinned = model.particle_pinned.numpy() != 0
    if count <= 0 or not pinned.any():
        return np.zeros((n, 0), np.int32), np.zeros((n, 0))
    springs = model.spring_indices.numpy().reshape(-1, 2)
    limited = model.spring_limited.numpy() != 0
    rest = model.spring_rest_length.numpy().astype(np.float64)
    adj: list[list[tuple[int, float]]] = [[] for _ in range(n)]
    for (a, b), r, use in zip(springs.tolist(), rest.tolist(), limited.tolist()):
        if use:
            adj[a].append((b, r))
            adj[b].append((a, r))
    # Pinned groups: connected components of pinned particles through limited springs.
    group = np.full(n, -1)
    groups = []
    for p in np.flatnonzero(pinned):
        if group[p] >= 0:
            continue
        stack, members = [p], []
        group[p] = len(groups)
        while stack:
            q = stack.pop()
            members.append(q)
            for r, _ in adj[q]:
                if pinned[r] and group[r] < 0:
                    group[r] = len(groups)
                    stack.append(r)
        groups.append(members)
    dist = np.full((len(groups), n), np.inf)
    source = np.full((len(groups), n), -1, np.int64)
    for g, members in enumerate(groups):
        heap = [(0.0, int(p), int(p)) for p in members]
        heapq.heapify(heap)
        d_g, s_g = dist[g], source[g]
        while heap:
            d, q, src = heapq.heappop(heap)
            if d >= d_g[q]:
                continue
            d_g[q], s_g[q] = d, src
            for r, w in adj[q]:
                if d + w < d_g[r]:
                    heapq.heappush(heap, (d + w, r, src))
    k = min(count, len(groups))
    # nearest groups per particle; ties (a symmetric cloth's two pinned corners) in group order, which a batch of
    # worlds keeps for each world (an unstable sort ordered them differently there, and the projections onto two
    # active attachments do not commute)
    order = np.argsort(dist, axis=0, kind="stable")[:k]
    cols = np.arange(n)
    ids = source[order, cols].T.astype(np.int32)
    dd = dist[order, cols].T
    ids[~np.isfinite(dd)] = -1
    dd[~np.isfinite(dd)] = 0.0
    return ids, dd
