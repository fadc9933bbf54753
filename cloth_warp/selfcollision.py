"""Cloth-cloth collisions: Bridson, Fedkiw & Anderson (2002) with Provot's rigid impact zones.

Per step, from the collision-free start x^n and the candidate end x~ (physics.md 3(f)):

1. average velocity vbar = (x~ - x^n) / h; hash-grid broad phase on the swept boxes (Choi & Ko), grown
   by a margin so later corrections that move no end point farther than it reuse the pairs (also the
   solver's second limiter/collision round of the step); when some end points do move farther, only
   the elements touching them are registered again and their pairs searched (a patch); of the pairs,
   only those whose distance at x^n is within the thickness plus what their vertices can travel are kept;
2. proximity pass at x^n: elements closer than the cloth thickness get repulsion impulses (never
   separating faster than 10 % of the overlap per step) with Coulomb friction;
3. CCD sweeps on the trajectories x^n + t vbar: the first coplanar time at which the elements touch
   gets an inelastic impulse that leaves them separating at 10 % of the thickness per step; while
   impacts remain (up to `sweeps`) the sweep repeats on the pairs with a particle the last one moved;
4. rigid impact zones: the particles of pairs still colliding are merged (connected components) into zones
   that move rigidly with their linear and angular momentum (x = x_cm + h v_cm + R(h omega) r; a zone with
   pinned particles moves with them); detection is repeated with the zones and zones merge until no impact
   remains;
5. x^{n+1} = x^n + h vbar, v^{n+1} = v~ + (vbar - vbar_candidate).

Under ``wp.Tape`` steps 2-3 differentiate with the contact set held fixed; an impact zone's rigid
motion is not differentiated, so the step passes no gradient to its particles' positions.
Pinned particles have infinite mass (impulses never move them) and keep their motion in a zone.

The capturable path (``SelfCollision(model, capturable=True)``, forward only) runs the same physics without
reading the device on the host, so a frame can be recorded once as a graph (``wp.ScopedCapture``) and
replayed: buffers have fixed capacities (what does not fit is dropped and the need recorded), counts stay
on the device, the CCD sweeps are a ``wp.capture_while`` loop, the broad phase is built in full on the
device and registered with the trajectories it was built on, and kept, from step to step, while every particle's
start and end points stay within the margin of its registered ones (a pile at rest keeps it for hundreds of
steps); when some left the margin it is patched on the device (``wp.capture_if``: the elements touching at most
``patch_limit`` escaped particles tested against every element) or, past that, built again; impacts left after the sweeps form rigid impact zones on the device (a
``capture_while`` loop of detection and merge rounds; zones join as trees whose roots hook under the smaller
(atomic minima) with pointer jumping, to each zone's smallest particle; their motion from float64 sums per zone:
the same kernels as the host path's, whose zones come from :func:`connected_labels`). After the frame, :meth:`SelfCollision.status` (one read) says whether a buffer
overflowed; the caller then calls :meth:`SelfCollision.grow` and runs the frame again on the host path.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .broadphase import SelfCollisionGrid
from .graphs import device_if, device_while
from .kernels import broadphase as kbp
from .kernels import contact as kct
from .kernels import selfcollide as ksc
from .model import ModelFlags
from .sewing import Weld
from .topology import seam_roots
from .records import record_values

log = logging.getLogger(__name__)

KINDS = (0, 1)  # vertex-face, edge-edge
COUNTERS = ("self_proximity", "self_ccd", "self_sweeps", "impact_zones", "impact_zone_particles", "unresolved", "oversized",
            "pair_buffer_growths", "broad_phase_builds", "broad_phase_patches")
# the capturable path's fixed-capacity buffers and where their needs are recorded in the counter block
BUFFERS = {"points": ksc.NEED_POINT_ENTRIES, "edges": ksc.NEED_EDGE_ENTRIES, "vertex_face": ksc.NEED_VERTEX_FACE,
           "edge_edge": ksc.NEED_EDGE_EDGE}


def inverse_masses(mass: np.ndarray, pinned: np.ndarray) -> np.ndarray:
    """1 / m [1/kg] per particle, 0 for pinned (`pinned`: booleans) and massless ones (float64, (n,))."""
    mass = np.asarray(mass, np.float64)
    return np.where(pinned | (mass <= 0.0), 0.0, 1.0 / np.maximum(mass, 1e-30))


@dataclass(frozen=True)
class SelfCollisionStatus:
    """What the capturable path reports after a frame (one device read, :meth:`SelfCollision.status`)."""

    overflow: dict = field(default_factory=dict)
    """Buffers that were too small: name ("points" / "edges": hash-grid entries, "vertex_face" / "edge_edge":
    candidate pairs) -> (entries or pairs needed, capacity). Their steps dropped candidates: run again."""

    @property
    def needs_rerun(self) -> bool:
        """The frame's result is not valid: grow the buffers (:meth:`SelfCollision.grow`) and run it again on the
        host path."""
        return bool(self.overflow)


class SelfCollision:
    """Self-collision of a model's cloth(s), run by :class:`~cloth_warp.collision.CollisionHandler`.

    Args:
        model: its ``cloth_thickness`` [m], ``cloth_friction`` and ``self_collision_stiffness`` [N/m] are read at
            every use (in a recorded graph: when recorded), its masses when built and on :meth:`notify_model_changed`.
        sweeps: CCD passes with impulses before rigid impact zones take over.
        zone_iterations: the most detection / merge rounds of impact zones per step.
        capturable: run forward steps on the capturable path (see the module; also settable as
            :attr:`capturable`); taped steps always take the host path.
        pair_capacity: the first capacity of each candidate-pair buffer (both paths grow it when needed).

    Counters (summed since :meth:`reset_counts`): ``self_proximity`` (repulsion impulses),
    ``self_ccd`` (CCD impacts found), ``self_sweeps`` (CCD passes run), ``impact_zones`` (zones formed),
    ``impact_zone_particles``, ``unresolved`` (steps that ended with impacts left: should stay 0),
    ``oversized`` (elements whose box spans more than 64 voxels on an axis: broad phase clamped),
    ``pair_buffer_growths``, ``broad_phase_builds`` (full hash-grid builds) and ``broad_phase_patches``
    (re-registrations of the elements whose end points left the margin). They live in one device block
    (:attr:`counts`, read once by :meth:`read_counts`) with the capturable path's status.
    """

    def __init__(self, model, sweeps: int = 4, zone_iterations: int = 64, capturable: bool = False, pair_capacity: int = 1024):
        self.model = model
        dev = model.device
        tris = model.tri_indices.numpy().reshape(-1, 3)
        self.grid = SelfCollisionGrid(tris, model.particle_count, dev, rest_positions=model.rest_positions, pair_capacity=pair_capacity,
                                      particle_root=seam_roots(model))
        self.edge_indices = self.grid.edges.elements  # (E, 3) rows, -1 padded: columns 0, 1 used
        self.tri_indices = model.tri_indices
        self.mass = np.zeros(0)
        """Particle masses [kg], numpy (n,) float64: a copy of model.particle_mass (impact zones' momentum)."""
        self.inv_mass_np = np.zeros(0)
        """Inverse masses [1/kg], numpy (n,) float64, 0 for pinned particles."""
        self.inv_mass = wp.zeros(model.particle_count, dtype=float, device=dev)
        """The same inverse masses on the device, shape (n,) (the impulse kernels' weights)."""
        self._read_masses()
        self.sweeps = int(sweeps)
        self.zone_iterations = int(zone_iterations)
        self.patch_limit = 32
        """The capturable path patches its broad phase when at most this many particles left the margin (testing the
        elements touching them against every element), else builds it again."""
        self.keep_broad_phase = True
        """The capturable path keeps its broad phase from step to step while the trajectories stay within the margin
        of the registered ones (:meth:`_refresh_fixed`); off, it builds it at every step's first round, its boxes grown
        by half the thickness (the dressing's: see cloth_warp/dressing.py)."""
        self.counts = wp.zeros(ksc.COUNT_SIZE, dtype=wp.int32, device=dev)
        """Counters and status, int32 [ksc.COUNT_SIZE] (indices ksc.COUNT_* / ksc.NEED_*)."""
        self.grid.clamped = self.counts[ksc.COUNT_OVERSIZED:ksc.COUNT_OVERSIZED + 1]  # the broad phase counts into the block
        self.no_zone = wp.full(model.particle_count, -1, dtype=wp.int32, device=dev)
        self.capturable = bool(capturable)
        """Forward steps take the capturable path (no device reads; see the module)."""
        self._cache: dict = {}
        self._last_weight = None
        self._resolved = None  # (x_start, dt, vbar) of the last round that ended without impacts
        self._close: dict = {}
        self.proximity_reach = 1.0
        """How close [fraction of the thickness] two elements come before the proximity pass pushes them apart: the
        thickness alone (1); an implicit solve that holds the self-contacts sets PROXIMITY_REACH_UNDER_SOLVE, so that the
        layers its elements hold under load (up to load / stiffness inside their rest distance) are left to it."""
        self.share_close_pairs = False
        """Whether the host path copies its close pairs into the capturable path's lists after each step, where the
        implicit solve's self-contacts read their candidates (:meth:`contact_candidates`; set by that solver)."""
        self._flip = False
        self._fixed = None  # the capturable path's buffers (see _fixed_buffers)
        self._step_start = None  # without keep_broad_phase: the start positions of the step whose first round built it
        self._sums = None  # impact zones' sums (see _zone_sums)
        weld = Weld(model)
        self.weld = weld if weld.points else None
        """The model's welded sewn points (cloth_warp.sewing), each of whose particles takes the point's mean velocity
        change after every impulse pass, so that the step keeps them one point (None without any)."""
        self.reset_counts()

    # -- the model's values ----------------------------------------------------------------------
    # Thickness, friction and stiffness are read from the model at every use; the inverse masses are derived
    # once and refreshed by notify_model_changed, so a fit that writes new masses simulates them.
    @property
    def thickness(self) -> float:
        """The distance [m] kept between non-adjacent elements (model.cloth_thickness)."""
        return float(self.model.cloth_thickness)

    @property
    def friction(self) -> float:
        """Coulomb coefficient between layers (model.cloth_friction)."""
        return float(self.model.cloth_friction)

    @property
    def stiffness(self) -> float:
        """Repulsion stiffness [N/m] of the proximity pass (model.self_collision_stiffness)."""
        return float(self.model.self_collision_stiffness)

    @property
    def margin(self) -> float:
        """How far [m] a corrected end point may move before its elements are registered again (boxes grow by
        this). Measured on the pile at 64^2 and 128^2 with 1-4 mm thickness: ~4 % of a voxel (8 % of an edge)
        balances close pairs (grow with it) against patches and rebuilds (shrink with it)."""
        return max(0.04 * self.grid.cell_size, 0.125 * self.thickness)

    def notify_model_changed(self, flags: int) -> None:
        """Refresh what is derived from the model after its fields changed (:class:`~cloth_warp.model.ModelFlags`):
        the inverse masses on PARTICLE_PROPERTIES, the welded sewn points on PARTICLE_INITIAL_STATE. (Thickness,
        friction and stiffness are read at every use.)"""
        if flags & ModelFlags.PARTICLE_PROPERTIES:
            self._read_masses()
        if flags & ModelFlags.PARTICLE_INITIAL_STATE:
            weld = Weld(self.model)
            self.weld = weld if weld.points else None

    def _read_masses(self):
        m = self.model
        mass = m.particle_mass.numpy().astype(np.float64)
        pinned = m.particle_pinned.numpy() != 0
        self.mass = mass
        self.inv_mass_np = inverse_masses(mass, pinned)
        self.inv_mass.assign(self.inv_mass_np.astype(np.float32))  # in place: launches keep reading this array

    # -- counters --------------------------------------------------------------------------------
    def reset_counts(self):
        self.counts.zero_()
        self.grid.clamped.zero_()
        self.host_counts = {"self_sweeps": 0, "impact_zones": 0, "impact_zone_particles": 0, "unresolved": 0, "broad_phase_builds": 0,
                            "broad_phase_patches": 0}
        self._grown0 = self.grid.vertex_face.grown + self.grid.edge_edge.grown

    def read_counts(self) -> dict:
        """The counters (:data:`COUNTERS`) since :meth:`reset_counts`: one read of the device block."""
        return self._counts_of(self.counts.numpy())

    def _counts_of(self, c: np.ndarray) -> dict:
        out = {"self_proximity": int(c[ksc.COUNT_PROXIMITY]), "self_ccd": int(c[ksc.COUNT_CCD])}
        out.update(self.host_counts)
        out["self_sweeps"] += int(c[ksc.COUNT_SWEEPS])
        out["impact_zones"] += int(c[ksc.COUNT_ZONES])
        out["impact_zone_particles"] += int(c[ksc.COUNT_ZONE_PARTICLES])
        out["unresolved"] += int(c[ksc.COUNT_UNRESOLVED])
        out["broad_phase_builds"] += int(c[ksc.COUNT_BUILDS])
        out["broad_phase_patches"] += int(c[ksc.COUNT_PATCHES])
        out["oversized"] = int(c[ksc.COUNT_OVERSIZED])
        out["pair_buffer_growths"] = self.grid.vertex_face.grown + self.grid.edge_edge.grown - self._grown0
        return out

    def status(self) -> SelfCollisionStatus:
        """The capturable path's report since :meth:`reset_counts` (one read of the device block)."""
        return self._status_of(self.counts.numpy())

    def read_report(self) -> tuple[SelfCollisionStatus, dict]:
        """(:meth:`status`, :meth:`read_counts`) from one read of the device block (or the frame record's copy)."""
        c = record_values(self.counts)
        return self._status_of(c), self._counts_of(c)

    def capacities(self) -> dict:
        """The capturable path's buffers' capacities (names as in :class:`SelfCollisionStatus`)."""
        g = self.grid
        return {"points": g.points.entry_capacity, "edges": g.edges.entry_capacity, "vertex_face": g.vertex_face.capacity,
                "edge_edge": g.edge_edge.capacity}

    def _status_of(self, c: np.ndarray) -> SelfCollisionStatus:
        caps = self.capacities()
        overflow = {name: (int(c[slot]), caps[name]) for name, slot in BUFFERS.items() if int(c[slot]) > caps[name]}
        return SelfCollisionStatus(overflow=overflow)

    def grow(self, status: SelfCollisionStatus | None = None) -> bool:
        """Grow the buffers that overflowed (`status`: default, read it now) to the next power of two of their need;
        True when any changed (then graphs recorded before must be recorded again: the arrays are new). The
        recorded needs are cleared (the other counters are not: :meth:`reset_counts` before running again)."""
        status = self.status() if status is None else status
        changed = self.grid.grow({name: needed for name, (needed, _) in status.overflow.items()})
        if changed:
            self._fixed = None
        if status.overflow:
            self.counts[ksc.NEED_POINT_ENTRIES:].zero_()
        return changed

    # -- checkpoints -----------------------------------------------------------------------------
    def checkpoint_state(self) -> dict:
        """What carries from one step to the next: the broad phase's buffer capacities and counters, the patch double
        buffer's parity and the last step's close pairs (the implicit solve's self-contact candidates: without them a
        resumed pile at rest took its first step with no repulsion between its layers and jumped to 0.22 m/s). (Each
        step starts afresh otherwise: :meth:`begin_step` drops the last step's grid and resolved velocities; counters
        are per frame.)"""
        out = {f"grid.{k}": v for k, v in self.grid.checkpoint_state().items()}
        out["flip"] = bool(self._flip)
        if self._fixed is not None:  # the last step's close pairs: the next step's self-contact candidates in the solve
            f = self._fixed
            for kind in KINDS:
                count = min(int(f.close_count[kind].numpy()[0]), f.close[kind].shape[0])
                out[f"close{kind}"] = f.close[kind].numpy()[:count].astype(np.int32).reshape(count, 2)
            out["unprimed"] = int(f.unprimed.numpy()[0])
            # and the trajectories they were registered for, with the elements' boxes a patch tests against: the next
            # step keeps them as the run it continues does
            out.update({key: a.numpy().copy() for key, a in f.registered(self.grid).items()})
        return out

    def restore_state(self, state: dict) -> None:
        self.grid.restore_state({k[len("grid."):]: v for k, v in state.items() if k.startswith("grid.")})
        self._flip = bool(state["flip"])
        self._resolved = None
        self._fixed = None  # capacities may have changed
        self.reset_counts()
        if any(f"close{kind}" in state for kind in KINDS):  # (checkpoints from before they were kept: none)
            f = self._fixed_buffers()
            for kind in KINDS:
                pairs = np.asarray(state.get(f"close{kind}", np.zeros((0, 2))), np.int32).reshape(-1, 2)
                count = min(len(pairs), f.close[kind].shape[0])
                if count:
                    wp.copy(f.close[kind], wp.array(pairs[:count], dtype=wp.vec2i, device=self.model.device), count=count)
                f.close_count[kind].fill_(count)
            f.unprimed.fill_(int(state.get("unprimed", 0)))  # (checkpoints from before it was kept: found when saved)
            if "registration" in state:  # (checkpoints from before the broad phase was kept across steps: built again)
                for key, a in f.registered(self.grid).items():
                    a.assign(np.asarray(state[key], np.float32).reshape(a.numpy().shape))

    # -- buffers ---------------------------------------------------------------------------------
    def _buffer(self, key: str, dtype, fresh: bool, shape=None) -> wp.array:
        shape = self.model.particle_count if shape is None else shape
        if fresh:
            return wp.zeros(shape, dtype=dtype, device=self.model.device, requires_grad=dtype is not wp.int32)
        buf = self._cache.get(key)
        if buf is None or buf.shape[0] < (shape if isinstance(shape, int) else shape[0]):
            buf = wp.zeros(shape, dtype=dtype, device=self.model.device)
            self._cache[key] = buf
        return buf

    def _pairs(self, kind: int):
        """The step's candidate pairs of a kind: the broad phase's, less those too far apart to touch."""
        return self._close[kind]

    def _grid_pairs(self, kind: int):
        buf = self.grid.vertex_face if kind == 0 else self.grid.edge_edge
        return buf.pairs, buf.count

    def contact_candidates(self, x_start: wp.array, velocity: wp.array, dt: float) -> list[tuple[wp.array, wp.array]]:
        """Per pair kind, (pairs, device count): the close pairs of the last step either path ran (the capturable
        path's lists; the host path copies its own there when :attr:`share_close_pairs`). What is close at the end of a
        step is close at the start of the next: the candidates of the next step's self-contacts in the implicit solve,
        which checks their distance itself. Before any step ran (a run's first step; a frame run again from such a
        start or with grown buffers), the close pairs of the trajectories x_start [m] + t velocity [m/s], t in [0, dt]
        [s], are found first (:meth:`_prime_fixed`; a device-side branch: a recorded frame replays it only then).
        Without them the T-shirt's first step carried two armhole pairs from 5 mm to 1.6 mm apart and the pass after
        the solve stretched a spring to 14.8 %, and a cloth lying on a cloth left its first frame at 65-107 mm/s."""
        f = self._fixed_buffers()
        device_if(f.unprimed, self._prime_fixed, x_start=x_start, velocity=velocity, dt=dt)
        return [(f.close[kind], f.close_count[kind]) for kind in KINDS]

    def forget_close_pairs(self):
        """Let the next :meth:`contact_candidates` find the close pairs of its own start, not the last step's: a taped
        step's self-contacts, so that its element set is a function of its start alone (a rollout run again from a
        checkpoint, or again from another start, gets the elements its start has)."""
        self._fixed_buffers().unprimed.fill_(1)

    def _prime_fixed(self, x_start, velocity, dt):
        """The close pairs of the trajectories x_start + t velocity, by a broad phase built for them and then forgotten
        (the step's pass builds its own, as it would have)."""
        self._build_fixed(x_start, velocity, dt, self._fixed_pad())
        self._fixed.registration.zero_()
        self._fixed.unprimed.zero_()

    def _fixed_pad(self) -> float:
        """[m] The capturable path's boxes grow by this (and the margin) around their trajectories: half the close reach,
        so that two elements coming within that reach of each other have overlapping boxes."""
        return 0.5 * max(self.thickness, self.close_reach())

    def _keep_close_pairs(self):
        """The host path's close pairs into the capturable path's lists (:meth:`contact_candidates`)."""
        f = self._fixed_buffers()
        for kind in KINDS:
            pairs, count = self._close[kind]
            count = min(count, f.close[kind].shape[0])
            if count:
                wp.copy(f.close[kind], pairs, count=count)
            f.close_count[kind].fill_(count)
        f.unprimed.zero_()

    def close_reach(self) -> float:
        """Distance [m] (beyond what their vertices travel in the step) within which candidate pairs are kept as close:
        the thickness and the clearance the implicit solve's self-contacts hold layers at (kernels/contact.py
        SELF_CLEARANCE: a pair resting there stays a candidate of the next step's solve), plus CCD's tolerance. Pairs
        farther than the thickness get no impulse from the pass, so the pass's results do not depend on it."""
        return self.thickness * (1.0 + float(kct.SELF_CLEARANCE)) + self.contact_tolerance()

    def contact_tolerance(self) -> float:
        """Distance [m] at which CCD counts two elements as touching."""
        return max(1.0e-3 * self.thickness, 1.0e-6)

    def first_contact_times(self, x_start: wp.array, vbar: wp.array, dt: float) -> dict:
        """Diagnostics: for the step x_start + t vbar, t in [0, dt], every candidate pair of each kind
        ("vertex_face": (triangle, particle), "edge_edge": (edge, edge) as rows of :attr:`edges`) and its first
        contact time [s] (-1 when none)."""
        dev = self.model.device
        self._forget_registration()
        self.grid.update(x_start, vbar, dt, 0.5 * self.thickness)
        out = {}
        for kind, name in zip(KINDS, ("vertex_face", "edge_edge")):
            pairs, count = self._grid_pairs(kind)
            times = wp.zeros(max(count, 1), dtype=float, device=dev)
            if count:
                wp.launch(ksc.eval_first_contact, dim=count,
                          inputs=[pairs, kind, self.tri_indices, self.edge_indices, x_start, vbar, dt, self.contact_tolerance()],
                          outputs=[times], device=dev, record_tape=False)
            out[name] = (pairs.numpy()[:count].copy(), times.numpy()[:count].copy())
        return out

    @property
    def edges(self) -> np.ndarray:
        """The cloth's edges (E, 2) as indexed by edge-edge pairs."""
        return self.grid.edges_np

    # -- the pipeline ----------------------------------------------------------------------------
    def apply(self, x_start: wp.array, x_end: wp.array, v_end: wp.array, dt: float, x_out: wp.array, v_out: wp.array):
        """Resolve the step x_start -> (x_end, v_end) into a collision-free (x_out, v_out) (the outputs
        may alias the inputs when nothing is taped). With :attr:`capturable` (and nothing taped) on the
        capturable path, whose result is valid unless :meth:`status` asks for a re-run."""
        rg = x_end.requires_grad
        if self.capturable and not rg:
            self._apply_fixed(x_start, x_end, v_end, dt, x_out, v_out)
            return
        m = self.model
        dev = m.device
        n = m.particle_count
        h_c = self.thickness
        vbar0 = self._buffer("vbar0", wp.vec3, rg)
        wp.launch(ksc.average_velocity, dim=n, inputs=[x_start, x_end, dt], outputs=[vbar0], device=dev)
        pad = 0.5 * h_c
        self._refresh_grid(x_start, vbar0, dt, pad)  # the solver's later rounds of a step reuse the first's pairs
        # 2. proximity pass (repulsion + friction) at the start positions
        vbar = self._impulse_pass(vbar0, "proximity", rg, lambda kind, pairs, count, dv, w: wp.launch(
            ksc.self_proximity, dim=count,
            inputs=[pairs, kind, self.tri_indices, self.edge_indices, self.inv_mass, x_start, vbar0, h_c * self.proximity_reach,
                    self.stiffness, self.friction, dt],
            outputs=[dv, w, self.counts], device=dev))
        # 3. CCD sweeps with impulses; 4. impact zones
        tolerance = self.contact_tolerance()
        separation = 0.1 * h_c / dt
        # A later round of the step starts from the last round's collision-free vbar: only pairs with a
        # particle whose vbar differs from it (moved by the limiter or the proximity pass) can collide.
        resumed = self._resolved is not None and self._resolved[0] is x_start and self._resolved[1] == float(dt)
        if resumed:
            changed = self._buffer("changed", float, False)
            wp.launch(ksc.mark_changed, dim=n, inputs=[vbar, self._resolved[2]], outputs=[changed], device=dev, record_tape=False)
            self._last_weight = changed
        resolved = True
        for sweep in range(self.sweeps + 1):
            respond = sweep < self.sweeps
            if sweep > 0:
                self._refresh_grid(x_start, vbar, dt, pad)
            hits, vbar_next = self._ccd(x_start, vbar, dt, tolerance, separation, respond, rg, self.no_zone, incremental=sweep > 0 or resumed)
            if respond:
                self.host_counts["self_sweeps"] += 1
            if hits == 0:
                break
            if respond:
                vbar = vbar_next
        else:
            vbar, resolved = self._impact_zones(x_start, vbar, dt, tolerance, separation, rg, pad)
        self._resolved = None
        if resolved:
            final = self._buffer("resolved_vbar", wp.vec3, False)
            wp.copy(final, vbar)
            self._resolved = (x_start, float(dt), final)
        wp.launch(ksc.finish_step, dim=n, inputs=[x_start, vbar, vbar0, v_end, dt], outputs=[x_out, v_out], device=dev)
        if not rg and self.share_close_pairs:
            self._keep_close_pairs()

    def save_frame_start(self):
        """Copy what the capturable path carries from step to step (the registered broad phase and its close pairs) as a
        frame starts (recorded in a frame's graph): a frame run again because another pass or world asked starts from
        it (:meth:`restore_frame_start`), so it repeats what the frame did, as a run without the re-run does."""
        if self._fixed is not None:
            for live, saved in self._fixed.carried:
                wp.copy(saved, live)

    def restore_frame_start(self):
        """Back to what :meth:`save_frame_start` copied (before a frame runs again)."""
        if self._fixed is not None:
            for live, saved in self._fixed.carried:
                wp.copy(live, saved)

    def _forget_registration(self):
        """The capturable path's broad phase no longer holds (the host path rebuilt the buffers it shares): its next
        step builds it again."""
        if self._fixed is not None:
            self._fixed.registration.zero_()

    def begin_step(self):
        """A new step starts: the start positions changed, so the host path's broad phase and the last round's result are
        stale (the capturable path's broad phase tests its registered trajectories itself: :meth:`_refresh_fixed`)."""
        self.grid.invalidate()
        self._resolved = None
        self._step_start = None

    # -- the capturable path ----------------------------------------------------------------------
    # The same passes as the host path, launched over fixed capacities with the counts on the device. Its
    # results equal the host path's bit for bit while the host path builds or keeps its broad phase and both
    # have the same grid capacities; where the host path patches, this one patches in its own way (or builds
    # again), so the candidate lists (and the order in which impulses add up) differ: then the results differ
    # by round-off.
    def prepare_capturable(self) -> None:
        """Allocate the capturable path's arrays now (outside any graph capture; see :meth:`_fixed_buffers`)."""
        self._fixed_buffers()

    def _fixed_buffers(self) -> "_FixedBuffers":
        """The capturable path's arrays, allocated on the host (first use, and after :meth:`grow`)."""
        caps = (self.grid.vertex_face.capacity, self.grid.edge_edge.capacity)
        if self._fixed is None or self._fixed.capacities != caps:  # grown (here or by the host path)
            self._fixed = _FixedBuffers(self.model, self.grid)
            self._zone_sums()  # now, not first inside the zones' capture_if body: CUDA refuses allocations there
        return self._fixed

    def _apply_fixed(self, x_start, x_end, v_end, dt, x_out, v_out):
        """:meth:`apply` on the capturable path (no device reads; impacts left after the sweeps form rigid impact
        zones on the device)."""
        m = self.model
        dev = m.device
        n = m.particle_count
        f = self._fixed_buffers()
        h_c = self.thickness
        wp.launch(ksc.average_velocity, dim=n, inputs=[x_start, x_end, dt], outputs=[f.vbar0], device=dev)
        if self.keep_broad_phase:
            # boxes grown by half the close reach (plus the margin): two elements that come within that reach of each other
            # in a step whose trajectories are within the margin of the registered ones have overlapping registered boxes
            pad = self._fixed_pad()
            # kept while every trajectory stays within the margin of its registered one, across the steps too
            self._refresh_fixed(x_start, f.vbar0, dt, pad)
        else:
            pad = 0.5 * h_c
            first = self._step_start is not x_start  # (begin_step forgets it)
            self._step_start = x_start
            if first:
                self._build_fixed(x_start, f.vbar0, dt, pad)
            else:
                self._refresh_fixed(x_start, f.vbar0, dt, pad)
        # 2. proximity pass
        f.dv.zero_()
        f.weight.zero_()
        for kind in KINDS:
            wp.launch(ksc.self_proximity_listed, dim=f.close[kind].shape[0],
                      inputs=[f.close_count[kind], f.close[kind], kind, self.tri_indices, self.edge_indices, self.inv_mass, x_start, f.vbar0,
                              h_c * self.proximity_reach, self.stiffness, self.friction, dt],
                      outputs=[f.dv, f.weight, self.counts], device=dev, record_tape=False)
        wp.launch(ksc.apply_velocity_changes, dim=n, inputs=[f.vbar0, f.dv, f.weight], outputs=[f.vbar], device=dev)
        self._weld_velocity(f.vbar, f.vbar)
        # 3. CCD sweeps on the device: the first on every close pair (a later round of the step: on the pairs
        # with a particle whose vbar changed since the last round's result), then while impacts remain
        resumed = self._resolved is not None and self._resolved[0] is x_start and self._resolved[1] == float(dt)
        if resumed:
            wp.launch(ksc.mark_changed, dim=n, inputs=[f.vbar, self._resolved[2]], outputs=[f.changed], device=dev,
                      record_tape=False)
        sweep = {"x_start": x_start, "dt": dt, "pad": pad, "tolerance": self.contact_tolerance(), "separation": 0.1 * h_c / dt}
        wp.launch(ksc.begin_sweeps, dim=1, inputs=[self.sweeps], outputs=[f.loop], device=dev, record_tape=False)
        self._sweep_fixed(first=True, weight=f.changed if resumed else None, **sweep)
        device_while(f.loop, self._sweep_fixed, first=False, weight=f.weight, **sweep)
        # 4. impacts left: rigid impact zones, detection and merge rounds on the device
        wp.launch(ksc.begin_zones, dim=1, inputs=[f.loop], outputs=[f.zones], device=dev, record_tape=False)
        device_while(f.zones, self._zone_round_fixed, **sweep)
        wp.copy(f.resolved, f.vbar)
        self._resolved = (x_start, float(dt), f.resolved)
        wp.launch(ksc.finish_step, dim=n, inputs=[x_start, f.vbar, f.vbar0, v_end, dt], outputs=[x_out, v_out], device=dev)
        f.unprimed.zero_()  # its close pairs: the next step's candidates

    def _sweep_fixed(self, x_start, dt, pad, tolerance, separation, first: bool, weight):
        """One CCD sweep of the capturable path (the body of its ``capture_while`` loop after the first): the
        broad phase refreshed for the current vbar (not before the first), CCD on the close pairs (`weight`:
        only those with a particle whose weight is > 0), the impulses averaged into vbar, the loop state updated."""
        f = self._fixed
        dev = self.model.device
        if not first:
            self._refresh_fixed(x_start, f.vbar, dt, pad)
        lists = {kind: (f.close[kind], f.close_count[kind]) for kind in KINDS}
        if weight is not None:
            lists = self._changed_pairs_fixed(weight)
        f.dv.zero_()  # after the selection: it reads the last sweep's weights
        f.weight.zero_()
        for kind, (pairs, count) in lists.items():
            wp.launch(ksc.self_ccd_listed, dim=pairs.shape[0],
                      inputs=[count, pairs, kind, self.tri_indices, self.edge_indices, self.inv_mass, self.no_zone, x_start, f.vbar, dt,
                              tolerance, separation],
                      outputs=[f.dv, f.weight, self.counts, f.loop], device=dev, record_tape=False)
        wp.launch(ksc.apply_velocity_changes, dim=self.model.particle_count, inputs=[f.vbar, f.dv, f.weight], outputs=[f.vbar], device=dev)
        self._weld_velocity(f.vbar, f.vbar)
        wp.launch(ksc.end_sweep, dim=1, inputs=[self.sweeps], outputs=[f.loop, self.counts], device=dev, record_tape=False)

    def _zone_round_fixed(self, x_start, dt, pad, tolerance, separation):
        """One round of the capturable path's impact zones (the body of its ``capture_while`` loop): CCD on every close
        pair with the zones so far (their own pairs skipped); where impacts remain, merge their particles into the
        zones, move each zone rigidly and refresh the broad phase (``capture_if``); when none remain (or after
        ``zone_iterations`` merges: counted unresolved), count the zones and clear them."""
        f = self._fixed
        dev = self.model.device
        for kind in KINDS:
            wp.launch(ksc.detect_impacts_listed, dim=f.close[kind].shape[0],
                      inputs=[f.close_count[kind], f.close[kind], kind, self.tri_indices, self.edge_indices, self.inv_mass, f.zone, x_start,
                              f.vbar, dt, tolerance, separation, f.dv, f.weight, f.scratch_counts],
                      outputs=[f.hits[kind], self.counts, f.zones], device=dev, record_tape=False)
        wp.launch(ksc.end_zone_detection, dim=1, inputs=[self.zone_iterations], outputs=[f.zones, self.counts], device=dev, record_tape=False)
        device_if(f.zones[ksc.ZONE_MERGE:ksc.ZONE_MERGE + 1], self._merge_zones_fixed, x_start=x_start, dt=dt, pad=pad)
        device_if(f.zones[ksc.ZONE_FINISH:ksc.ZONE_FINISH + 1], self._finish_zones_fixed)

    def _merge_zones_fixed(self, x_start, dt, pad):
        """The particles of the pairs the last detection flagged join zones (passes on the device to a fixed point),
        every zone takes its rigid motion, and the broad phase follows the new velocities."""
        f = self._fixed
        dev = self.model.device
        wp.launch(ksc.set_flag, dim=1, inputs=[1], outputs=[f.link_changed], device=dev, record_tape=False)
        device_while(f.link_changed, self._link_zones_fixed)
        self._zone_motion(f.zone, x_start, f.vbar, dt, f.vbar)
        self._weld_velocity(f.vbar, f.vbar)
        self._refresh_fixed(x_start, f.vbar, dt, pad)

    def _link_zones_fixed(self):
        """One pass of joining (flagged pairs, welded sewn points) and pointer jumping; the flag says whether another
        pass is needed."""
        f = self._fixed
        dev = self.model.device
        n = self.model.particle_count
        f.link_changed.zero_()
        for kind in KINDS:
            wp.launch(ksc.merge_colliding_pairs, dim=f.close[kind].shape[0],
                      inputs=[f.close_count[kind], f.close[kind], f.hits[kind], kind, self.tri_indices, self.edge_indices],
                      outputs=[f.zone, f.link_changed], device=dev, record_tape=False)
        if self.weld is not None:
            wp.launch(ksc.merge_sewn_points, dim=n, inputs=[self.weld.particle_seam_root], outputs=[f.zone, f.link_changed], device=dev,
                      record_tape=False)
        wp.launch(ksc.follow_zone_names, dim=n, inputs=[], outputs=[f.zone, f.link_changed], device=dev, record_tape=False)

    def _finish_zones_fixed(self):
        f = self._fixed
        wp.launch(ksc.finish_zones, dim=self.model.particle_count, inputs=[], outputs=[f.zone, self.counts], device=self.model.device,
                  record_tape=False)

    def _zone_motion(self, zone, x_start, vbar, dt, v_out):
        """v_out: the free members of each zone of `zone` (labels, see :func:`~cloth_warp.kernels.selfcollide.in_zone`)
        at their zone's rigid motion over the step from x_start with velocities vbar (linear and angular momentum
        kept; with pinned members, the rigid motion that fits theirs); other particles' entries are left as they are
        (v_out may be vbar). Not taped."""
        m = self.model
        dev, n = m.device, m.particle_count
        z = self._zone_sums()
        for a in z.accumulated:
            a.zero_()
        per_particle = [zone, m.particle_mass, self.inv_mass, x_start, vbar]
        wp.launch(ksc.gather_zone_mass, dim=n, inputs=per_particle, outputs=[z.mass, z.moment, z.momentum, z.pinned, z.heaviest], device=dev,
                  record_tape=False)
        wp.launch(ksc.gather_zone_moments, dim=n, inputs=[*per_particle, dt, z.mass, z.moment, z.momentum, z.pinned, z.heaviest],
                  outputs=[z.angular, z.inertia, z.weight, z.start, z.end], device=dev, record_tape=False)
        wp.launch(ksc.gather_zone_covariance, dim=n, inputs=[*per_particle, dt, z.mass, z.pinned, z.heaviest, z.weight, z.start, z.end],
                  outputs=[z.covariance], device=dev, record_tape=False)
        wp.launch(ksc.solve_zone_motion, dim=n,
                  inputs=[zone, dt, z.mass, z.moment, z.momentum, z.pinned, z.angular, z.inertia, z.weight, z.start, z.end, z.covariance],
                  outputs=[z.rotation, z.origin, z.target], device=dev, record_tape=False)
        wp.launch(ksc.set_zone_motion, dim=n, inputs=[zone, self.inv_mass, x_start, dt, z.mass, z.rotation, z.origin, z.target],
                  outputs=[v_out], device=dev, record_tape=False)

    def _zone_sums(self) -> "_ZoneSums":
        if self._sums is None:
            self._sums = _ZoneSums(self.model.particle_count, self.model.device)
        return self._sums

    def _changed_pairs_fixed(self, weight) -> dict:
        """The close pairs with an element whose particle has weight > 0 (see :meth:`_active_lists`)."""
        f = self._fixed
        dev = self.model.device
        for name, elements in self.grid.element_sets():
            wp.launch(kbp.mark_changed_elements, dim=elements.count, inputs=[elements.elements, weight, self.no_zone], outputs=[f.flags[name]],
                      device=dev, record_tape=False)
        out = {}
        for kind in KINDS:
            first, second = (f.flags["triangles"], f.flags["points"]) if kind == 0 else (f.flags["edges"], f.flags["edges"])
            f.active_count[kind].zero_()
            wp.launch(kbp.select_flagged_pairs_listed, dim=f.active[kind].shape[0], inputs=[f.close_count[kind], f.close[kind], first, second, 1],
                      outputs=[f.active[kind], f.active_count[kind]], device=dev, record_tape=False)
            out[kind] = (f.active[kind], f.active_count[kind])
        return out

    def _refresh_fixed(self, x_start, vbar, dt, pad):
        """Keep the broad phase and its close pairs while no particle's start or end point left the margin around its
        registered trajectory's, from step to step (at rest a pile keeps them for hundreds of steps); when at most
        :attr:`patch_limit` particles did, patch it (:meth:`_patch_fixed`), else build it again (device-side branches;
        also when nothing is registered, or with another step or thickness)."""
        f = self._fixed
        dev = self.model.device
        f.escaped.zero_()
        wp.launch(kbp.take_moved, dim=self.model.particle_count, inputs=[x_start, vbar, dt, self.margin],
                  outputs=[f.start_reference, self.grid.fixed_reference, f.escaped_particles, f.escaped], device=dev, record_tape=False)
        wp.launch(kbp.patch_or_build, dim=1, inputs=[f.escaped, int(self.patch_limit), f.registration, dt, pad, self.margin,
                                                     self.close_reach()],
                  outputs=[f.rebuild, f.patch], device=dev, record_tape=False)
        device_if(f.rebuild, self._build_fixed, x_start=x_start, velocity=vbar, dt=dt, pad=pad)
        device_if(f.patch, self._patch_fixed, x_start=x_start, dt=dt, pad=pad)

    def _patch_fixed(self, x_start, dt, pad):
        """The capturable path's patch (the host path's :meth:`SelfCollisionGrid.refresh` "patched", on the device):
        the escaped particles took their current trajectory as reference (:func:`take_moved`); the elements touching
        them get their new boxes, the close pairs with such an element are dropped and those pairs found again by
        testing the few fresh elements against every element (no hash grid: the grid keeps its entries, unused until
        the next build). The close lists stay within their capacity; a larger need is recorded as an overflow."""
        f = self._fixed
        g = self.grid
        dev = self.model.device
        grow = pad + self.margin
        for name, s in g.element_sets():
            f.fresh_count[name].zero_()
            wp.launch(kbp.mark_fresh, dim=s.count, inputs=[s.elements, f.escaped_particles],
                      outputs=[f.flags[name], f.fresh[name], f.fresh_count[name]], device=dev, record_tape=False)
            wp.launch(kbp.fresh_bounds, dim=s.count, inputs=[f.flags[name], s.elements, f.start_reference, g.fixed_reference, dt, grow],
                      outputs=[s.lo, s.hi], device=dev, record_tape=False)
        for kind in KINDS:  # the close pairs without a fresh element
            first, second = (f.flags["triangles"], f.flags["points"]) if kind == 0 else (f.flags["edges"], f.flags["edges"])
            f.active_count[kind].zero_()
            wp.launch(kbp.select_flagged_pairs_listed, dim=f.close[kind].shape[0], inputs=[f.close_count[kind], f.close[kind], first, second, 0],
                      outputs=[f.active[kind], f.active_count[kind]], device=dev, record_tape=False)
            wp.launch(kbp.copy_pairs_listed, dim=f.close[kind].shape[0], inputs=[f.active_count[kind], f.active[kind]],
                      outputs=[f.close[kind], f.close_count[kind]], device=dev, record_tape=False)
        close = [f.start_reference, g.fixed_reference, dt, self.margin, self.close_reach()]  # on the registered trajectories
        pts, tri, edg = g.points, g.triangles, g.edges
        wp.launch(ksc.patch_vertex_face_points, dim=pts.count,
                  inputs=[f.fresh_count["triangles"], f.fresh["triangles"], tri.lo, tri.hi, pts.lo, pts.hi, self.tri_indices, self.edge_indices,
                          tri.adjacency, pts.adjacency, *close, f.capacities[0]],
                  outputs=[f.close[0], f.close_count[0]], device=dev, record_tape=False)
        wp.launch(ksc.patch_vertex_face_triangles, dim=tri.count,
                  inputs=[f.flags["triangles"], f.fresh_count["points"], f.fresh["points"], tri.lo, tri.hi, pts.lo, pts.hi, self.tri_indices,
                          self.edge_indices, tri.adjacency, pts.adjacency, *close, f.capacities[0]],
                  outputs=[f.close[0], f.close_count[0]], device=dev, record_tape=False)
        wp.launch(ksc.patch_edge_edge, dim=edg.count,
                  inputs=[f.flags["edges"], f.fresh_count["edges"], f.fresh["edges"], edg.lo, edg.hi, self.tri_indices, self.edge_indices,
                          edg.adjacency, *close, f.capacities[1]],
                  outputs=[f.close[1], f.close_count[1]], device=dev, record_tape=False)
        for kind, slot in zip(KINDS, (ksc.NEED_VERTEX_FACE, ksc.NEED_EDGE_EDGE)):
            wp.launch(kbp.clamp_count, dim=1, inputs=[f.capacities[kind], slot], outputs=[f.close_count[kind], self.counts], device=dev,
                      record_tape=False)
        wp.launch(ksc.increment_count, dim=1, inputs=[ksc.COUNT_PATCHES], outputs=[self.counts], device=dev, record_tape=False)

    def _build_fixed(self, x_start, velocity, dt, pad):
        """A full broad phase on the device (boxes grown by the margin) and its close pairs, registered for the
        trajectories x_start + t velocity (:meth:`_refresh_fixed` keeps them while the particles stay near those)."""
        f = self._fixed
        dev = self.model.device
        g = self.grid
        wp.copy(f.start_reference, x_start)
        g.build_fixed(x_start, velocity, dt, pad, self.margin, self.counts, BUFFERS)
        wp.launch(ksc.increment_count, dim=1, inputs=[ksc.COUNT_BUILDS], outputs=[self.counts], device=dev, record_tape=False)
        reach = self.close_reach()
        wp.launch(kbp.register_broad_phase, dim=1, inputs=[dt, pad, self.margin, reach], outputs=[f.registration], device=dev,
                  record_tape=False)
        for kind in KINDS:
            buf = g.vertex_face if kind == 0 else g.edge_edge
            f.close_count[kind].zero_()
            wp.launch(ksc.select_close_pairs_listed, dim=buf.capacity,
                      inputs=[buf.count_array, buf.pairs, kind, self.tri_indices, self.edge_indices, x_start, g.fixed_reference, dt, self.margin,
                              reach],
                      outputs=[f.close[kind], f.close_count[kind]], device=dev, record_tape=False)

    # -- the host path's broad phase -------------------------------------------------------------
    def _refresh_grid(self, x_start, vbar, dt, pad):
        """Keep the candidate pairs valid for the trajectories x_start + t vbar (the handler invalidates the
        broad phase at the start of each step: same array, new start positions): a full broad phase on new
        start positions, then only a patch for the particles whose end points left the margin (see
        :meth:`SelfCollisionGrid.refresh`); of the pairs, those close enough to touch are kept (within the
        thickness, given how far their vertices can move)."""
        self._forget_registration()  # the host path rebuilds the grid's buffers the capturable path also uses
        done = self.grid.refresh(x_start, vbar, dt, pad, self.margin)
        self.host_counts[f"broad_phase_{'patches' if done == 'patched' else 'builds'}"] += done != "kept"
        if done == "kept":
            return
        close_inputs = [x_start, self.grid.reference_velocity, dt, self.margin, self.close_reach()]
        if done == "built":
            self._close = self._select("close", ksc.select_close_pairs, {kind: self._grid_pairs(kind) for kind in KINDS}, close_inputs)
            return
        # patched: the current close pairs without a freshly registered element, then the patch's close pairs
        dev = self.model.device
        self._flip = not self._flip  # double buffer: the new list is compacted from the current one
        close = {}
        for kind in KINDS:
            pairs, count = self._close[kind]
            patch = self.grid.patch_vertex_face if kind == 0 else self.grid.patch_edge_edge
            selected = self._buffer(f"patched{kind}{int(self._flip)}", wp.vec2i, False, shape=max(count + patch.count, 1))
            counter = self._buffer(f"patched_count{kind}", wp.int32, False, shape=1)
            counter.zero_()
            if count:
                wp.launch(kbp.select_flagged_pairs, dim=count, inputs=[pairs, *self.grid.fresh_flags(kind), 0], outputs=[selected, counter],
                          device=dev, record_tape=False)
            if patch.count:
                wp.launch(ksc.select_close_pairs, dim=patch.count, inputs=[patch.pairs, kind, self.tri_indices, self.edge_indices, *close_inputs],
                          outputs=[selected, counter], device=dev, record_tape=False)
            close[kind] = (selected, int(counter.numpy()[0]))
        self._close = close

    def _select(self, key: str, kernel, lists: dict, inputs: list) -> dict:
        """Compact each kind's pairs with `kernel(pairs, kind, triangles, edges, *inputs)` -> kind: (pairs, count)."""
        out = {}
        for kind, (pairs, count) in lists.items():
            selected = self._buffer(f"{key}{kind}", wp.vec2i, False, shape=max(count, 1))
            counter = self._buffer(f"{key}_count{kind}", wp.int32, False, shape=1)
            counter.zero_()
            if count:
                wp.launch(kernel, dim=count, inputs=[pairs, kind, self.tri_indices, self.edge_indices, *inputs],
                          outputs=[selected, counter], device=self.model.device, record_tape=False)
            out[kind] = (selected, int(counter.numpy()[0]))
        return out

    def _weld_velocity(self, vbar, out):
        """out: `vbar` with each welded sewn point's particles at their mean velocity (the same array when no weld)."""
        if self.weld is not None:
            self.weld.apply_velocity(vbar, out)

    def _impulse_pass(self, vbar, key, rg, launch, lists=None):
        """Run `launch(kind, pairs, count, dv, weight)` for each pair kind, then average the accumulated
        velocity changes into a new vbar. `lists` maps kind -> (pairs, count) (default: the grid's)."""
        m = self.model
        lists = lists or {kind: self._pairs(kind) for kind in KINDS}
        if sum(count for _, count in lists.values()) == 0:
            self._last_weight = None
            return vbar
        dv = self._buffer(f"dv_{key}", wp.vec3, rg)
        weight = self._buffer(f"w_{key}", float, rg)
        if not rg:
            dv.zero_()
            weight.zero_()
        for kind, (pairs, count) in lists.items():
            if count:
                launch(kind, pairs, count, dv, weight)
        self._last_weight = weight
        out = self._buffer(f"vbar_{key}", wp.vec3, rg)
        wp.launch(ksc.apply_velocity_changes, dim=m.particle_count, inputs=[vbar, dv, weight], outputs=[out], device=m.device)
        if self.weld is None:
            return out
        welded = self._buffer(f"vbar_{key}_welded", wp.vec3, rg)
        self._weld_velocity(out, welded)
        return welded

    def _active_lists(self, zone, incremental: bool) -> dict:
        """The pairs a CCD pass must test: all candidates on a new vbar; otherwise only the pairs with a
        particle whose vbar changed since the last pass (it received an impulse there, or belongs to an
        impact zone): every other pair would give the last pass's answer, a miss. That holds across broad-phase
        updates too: a pair the last pass did not test had trajectories outside each other's reach, and
        unchanged particles keep their trajectories."""
        lists = {kind: self._pairs(kind) for kind in KINDS}
        if not incremental or self._last_weight is None:
            return lists
        dev = self.model.device
        flags = {}
        for name, elements in self.grid.element_sets():
            flags[name] = self._buffer(f"changed_{name}", wp.int32, False, shape=max(elements.count, 1))
            wp.launch(kbp.mark_changed_elements, dim=elements.count, inputs=[elements.elements, self._last_weight, zone], outputs=[flags[name]],
                      device=dev, record_tape=False)
        out = {}
        for kind, (pairs, count) in lists.items():
            first, second = (flags["triangles"], flags["points"]) if kind == 0 else (flags["edges"], flags["edges"])
            selected = self._buffer(f"active{kind}", wp.vec2i, False, shape=max(count, 1))
            counter = self._buffer(f"active_count{kind}", wp.int32, False, shape=1)
            counter.zero_()
            if count:
                wp.launch(kbp.select_flagged_pairs, dim=count, inputs=[pairs, first, second, 1], outputs=[selected, counter], device=dev,
                          record_tape=False)
            out[kind] = (selected, int(counter.numpy()[0]))
        return out

    def _ccd(self, x_start, vbar, dt, tolerance, separation, respond, rg, zone, incremental=True):
        """One CCD pass: the number of impacts found, and vbar after their impulses (when `respond`)."""
        dev = self.model.device
        before = int(self.counts.numpy()[ksc.COUNT_CCD])
        hit = {}
        lists = self._active_lists(zone, incremental)

        def launch(kind, pairs, count, dv, w):
            hit[kind] = self._buffer(f"hit{kind}", wp.int32, False, shape=max(count, 1))
            wp.launch(ksc.self_ccd, dim=count,
                      inputs=[pairs, kind, self.tri_indices, self.edge_indices, self.inv_mass, zone, x_start, vbar, dt, tolerance,
                              separation, int(respond)],
                      outputs=[dv, w, hit[kind], self.counts], device=dev)

        out = self._impulse_pass(vbar, f"ccd{int(respond)}", rg, launch, lists)
        self._last_hits = {kind: (lists[kind][0], lists[kind][1], flags) for kind, flags in hit.items()}
        return int(self.counts.numpy()[ksc.COUNT_CCD]) - before, out

    def _colliding_pairs(self) -> np.ndarray:
        """The particle quadruples of the pairs the last CCD pass found colliding, (k, 4)."""
        tris = self.tri_indices.numpy().reshape(-1, 3)
        edges = self.grid.edges_np
        quads = []
        for kind, (pairs, count, flags) in self._last_hits.items():
            sel = pairs.numpy()[:count][flags.numpy()[:count] != 0]
            if kind == 0:
                quads.append(np.column_stack([tris[sel[:, 0]], sel[:, 1]]))
            else:
                quads.append(np.column_stack([edges[sel[:, 0]], edges[sel[:, 1]]]))
        return np.concatenate(quads) if quads else np.zeros((0, 4), np.int64)

    def _impact_zones(self, x_start, vbar, dt, tolerance, separation, rg, pad):
        """Provot's rigid impact zones until no impact remains (or `zone_iterations` rounds); returns vbar
        and whether no impact remains."""
        m = self.model
        dev = m.device
        n = m.particle_count
        resolved = True
        links = np.zeros((0, 2), np.int64)  # particle pairs that must move together (all rounds of this step)
        for _ in range(self.zone_iterations):
            quads = self._colliding_pairs()
            links = np.concatenate([links, np.column_stack([np.repeat(quads[:, 0], 3), quads[:, 1:].ravel()])])
            if self.weld is not None:  # a sewn point in a zone joins it whole
                sewn = self.weld.links()
                touched = np.isin(sewn, links).any(axis=1)
                links = np.concatenate([links, sewn[np.isin(sewn[:, 1], sewn[touched, 1])]])
            zone = connected_labels(links, n)
            zone_arr = wp.array(zone.astype(np.int32), dtype=wp.int32, device=dev)
            zone_v = self._buffer("zone_vbar", wp.vec3, False)
            wp.copy(zone_v, vbar)
            self._zone_motion(zone_arr, x_start, vbar, dt, zone_v)
            out = self._buffer("vbar_zone", wp.vec3, rg)
            wp.launch(ksc.set_zone_velocity, dim=n, inputs=[zone_arr, zone_v, vbar], outputs=[out], device=dev)
            vbar = out
            if self.weld is not None:  # (a zone holds whole sewn points: its rigid motion gives them one velocity)
                welded = self._buffer("vbar_zone_welded", wp.vec3, rg)
                self._weld_velocity(vbar, welded)
                vbar = welded
            self._refresh_grid(x_start, vbar, dt, pad)
            hits, _ = self._ccd(x_start, vbar, dt, tolerance, separation, False, rg, zone_arr)
            if hits == 0:
                break
        else:
            self.host_counts["unresolved"] += 1
            log.warning("self-collision: impacts remain after %d impact-zone rounds", self.zone_iterations)
            resolved = False
        self.host_counts["impact_zones"] += int((zone == np.arange(n)).sum())
        self.host_counts["impact_zone_particles"] += int((zone >= 0).sum())
        return vbar, resolved


class _FixedBuffers:
    """The capturable path's arrays: per particle vbar (candidate and current), impulse sums, change flags,
    the last resolved vbar and escape flags; per pair kind the close and active lists (the grid's pair
    capacity) with device counts and the close pairs' impact flags; per element set change flags; the CCD and
    impact-zone loop states, the zone labels (ZONE_NONE between steps) and the label propagation's change flag."""

    def __init__(self, model, grid: SelfCollisionGrid):
        dev = model.device
        n = model.particle_count
        self.vbar0 = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.vbar = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.dv = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.weight = wp.zeros(n, dtype=float, device=dev)
        self.changed = wp.zeros(n, dtype=float, device=dev)
        self.resolved = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.escaped_particles = wp.zeros(n, dtype=wp.int32, device=dev)
        self.escaped = wp.zeros(1, dtype=wp.int32, device=dev)
        self.loop = wp.zeros(4, dtype=wp.int32, device=dev)
        self.zones = wp.zeros(ksc.ZONE_STATE_SIZE, dtype=wp.int32, device=dev)
        self.zone = wp.full(n, int(ksc.ZONE_NONE), dtype=wp.int32, device=dev)
        self.link_changed = wp.zeros(1, dtype=wp.int32, device=dev)
        self.scratch_counts = wp.zeros(ksc.COUNT_SIZE, dtype=wp.int32, device=dev)
        caps = (grid.vertex_face.capacity, grid.edge_edge.capacity)
        self.capacities = caps
        self.close = [wp.zeros(c, dtype=wp.vec2i, device=dev) for c in caps]
        self.close_count = [wp.zeros(1, dtype=wp.int32, device=dev) for _ in caps]
        self.active = [wp.zeros(c, dtype=wp.vec2i, device=dev) for c in caps]
        self.active_count = [wp.zeros(1, dtype=wp.int32, device=dev) for _ in caps]
        self.hits = [wp.zeros(c, dtype=wp.int32, device=dev) for c in caps]
        self.flags = {name: wp.zeros(max(s.count, 1), dtype=wp.int32, device=dev) for name, s in grid.element_sets()}
        self.fresh = {name: wp.zeros(max(s.count, 1), dtype=wp.int32, device=dev) for name, s in grid.element_sets()}
        self.fresh_count = {name: wp.zeros(1, dtype=wp.int32, device=dev) for name, _ in grid.element_sets()}
        self.rebuild = wp.zeros(1, dtype=wp.int32, device=dev)
        self.patch = wp.zeros(1, dtype=wp.int32, device=dev)
        self.start_reference = wp.zeros(n, dtype=wp.vec3, device=dev)  # [m] registered trajectories' starts (velocities: the grid's)
        self.registration = wp.zeros(kbp.REGISTRATION_SIZE, dtype=float, device=dev)  # none yet (kernels/broadphase.py REGISTRATION_*)
        if grid.fixed_reference is None:
            grid.fixed_reference = wp.zeros(n, dtype=wp.vec3, device=dev)
        # what a step carries to the next (the registered broad phase: its trajectories, the elements' boxes a patch tests
        # against, its close pairs), each with its copy as the frame started (SelfCollision.save_frame_start)
        self.unprimed = wp.ones(1, dtype=wp.int32, device=dev)  # 1 until close pairs were found (SelfCollision.contact_candidates)
        carried = [*self.registered(grid).values(), *self.close, *self.close_count, self.unprimed]
        self.carried = [(a, wp.empty_like(a)) for a in carried]

    def registered(self, grid: SelfCollisionGrid) -> dict:
        """The registered broad phase, by checkpoint key: the registration, the trajectories (starts [m], velocities
        [m/s]: the grid's) and the elements' boxes [m] a patch tests against."""
        out = {"registration": self.registration, "start_reference": self.start_reference, "velocity_reference": grid.fixed_reference}
        for name, elements in grid.element_sets():
            out[f"{name}_lo"], out[f"{name}_hi"] = elements.lo, elements.hi
        return out


class _ZoneSums:
    """Rigid impact zones' per-zone arrays, indexed by the zone's name (its smallest particle index), shape (n,): the
    float64 sums over its members (:attr:`accumulated`, zeroed before each use) and its rigid step
    x -> target + rotation (x - origin)."""

    def __init__(self, n: int, dev):
        def zeros(dtype):
            return wp.zeros(n, dtype=dtype, device=dev)

        self.mass = zeros(wp.float64)  # [kg] of the free members
        self.moment = zeros(wp.vec3d)  # sum m x of the free members [kg m]
        self.momentum = zeros(wp.vec3d)  # sum m v of the free members [kg m/s]
        self.pinned = zeros(wp.int32)  # pinned members
        self.heaviest = zeros(wp.float64)  # the heaviest member's mass [kg]
        self.angular = zeros(wp.vec3d)  # angular momentum about the centre of mass [kg m^2/s] (free zones)
        self.inertia = zeros(wp.mat33d)  # inertia tensor about the centre of mass [kg m^2] (free zones)
        self.weight = zeros(wp.float64)  # fit weights (zones with pinned members)
        self.start = zeros(wp.vec3d)  # weighted sum of start points
        self.end = zeros(wp.vec3d)  # weighted sum of end points
        self.covariance = zeros(wp.mat33d)  # weighted covariance of start and end points about their centres
        self.accumulated = (self.mass, self.moment, self.momentum, self.pinned, self.heaviest, self.angular, self.inertia, self.weight,
                            self.start, self.end, self.covariance)
        self.rotation = zeros(wp.mat33d)
        self.origin = zeros(wp.vec3d)  # [m]
        self.target = zeros(wp.vec3d)  # [m]


def connected_labels(links: np.ndarray, count: int) -> np.ndarray:
    """Per particle, the smallest particle index of its connected component under `links` (k, 2), or -1
    for particles in no link (min-label propagation with pointer jumping, vectorised)."""
    label = np.arange(count)
    if len(links) == 0:
        return np.full(count, -1)
    a, b = links[:, 0], links[:, 1]
    while True:
        low = np.minimum(label[a], label[b])
        new = label.copy()
        np.minimum.at(new, a, low)
        np.minimum.at(new, b, low)
        new = new[new]  # pointer jumping: follow labels to their labels
        if np.array_equal(new, label):
            break
        label = new
    member = np.zeros(count, bool)
    member[links.ravel()] = True
    return np.where(member, label, -1)
