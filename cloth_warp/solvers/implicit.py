"""Implicit Euler after Baraff & Witkin (1998), solved matrix-free by filtered PCG or block Jacobi."""

from __future__ import annotations

import dataclasses
import enum
import math

import numpy as np
import warp as wp

from ..autodiff import paused_tape
from ..diagnostics import LinearSolveReport
from ..graphs import LoopGraphs, device_while
from ..profiling import stage
from ..records import record_values
from .. import reductions
from ..reductions import launch_reduction
from ..selfcollision import inverse_masses
from ..sewing import point_masses, solve_roots, welded_view
from ..topology import sewn_point_roots
from ..worlds import world_ranges
from ..kernels import forces as kf
from ..kernels import constraints as kc
from ..kernels import contact as kct
from ..kernels import implicit as ki
from ..kernels import selfcollide as ksc
from ..kernels.worlds import world_slots_length
from ..model import Control, Model, ModelFlags, State
from .base import SolverBase
from .strain_limit import DEFAULT_SWEEPS

WARM_START_FLOOR = float(ki.SOLVE_FLOOR)  # the smallest relative residual a warm-started float32 solve is asked for
# With the contacts' friction in the solve, the solves whose contacts are then checked (released, let slide, stuck again)
# stop at this relative residual where the tolerance is tighter, and one more solve goes on to the tolerance once no
# contact changes. 18 piles and drapes over 300 frames (docs/contacts-in-the-solve.md): at tolerance 1e-4, 32 % fewer CG
# iterations a frame at rest than checking at 1e-4 (14 of them at rest against 15, end states being chaotic); at the
# default 1e-3, checked there with no solve after, 15 of 18 at rest in 62 % of the time tolerance 1e-4 takes.
CONTACT_CHECK_TOLERANCE = 1.0e-3


# Where collider contacts are resolved: after the step by the colliders pass, or also inside the CG solve.
COLLIDER_CONTACTS = ("pass", "solve")
# Where "solve" contacts' Coulomb friction acts: on the solved velocities ("after"), or in the solve ("solve").
CONTACT_FRICTION = ("after", "solve")
# With the self-contacts in the solve, the self-collision pass's proximity impulses act on pairs closer than this
# fraction of the thickness (SelfCollision.proximity_reach): the solve's elements hold loaded layers inside their rest
# distance by load / stiffness (a T-shirt held still: 25-28 particles 0.2-0.4 mm inside the thickness, which the pass
# pushed out by 16 mm/s every step).
PROXIMITY_REACH_UNDER_SOLVE = 0.75
# A self-contact element whose load the solved step leaves deeper than this fraction of the way from its rest distance
# to the pass's reach is stiffened until it is held there (a gain per particle, kernels/contact.py
# eval_self_contact_gain_targets): the pass then has nothing to push.
SELF_CONTACT_GAIN_HOLD = 0.75
# Where a welded sewn point is kept one point: in the solve as one particle, or by the sewing pass after the step only.
SEWN_POINTS = ("solve", "pass")

@dataclasses.dataclass(frozen=True)
class TapedContacts:
    """A taped step's collider contacts (per particle): the collider (-1: none; the set held fixed), the height [m]
    it ends the step at (held fixed; below the collider's thickness: pinched) and a pinched one's crease direction (held
    fixed; zero: none), and on the tape the unit normal, the surface velocity [m/s] and the prescribed velocity change
    z [m/s]."""

    collider: wp.array
    height: wp.array
    crease: wp.array
    normal: wp.array
    velocity: wp.array
    dv: wp.array


class LinearSolver(enum.IntEnum):
    """Linear solver of the implicit step."""

    CG = 0
    """Filtered conjugate gradients with a 3x3 block-diagonal (block Jacobi) preconditioner."""
    JACOBI = 1
    """Block Jacobi iteration (3x3 diagonal blocks inverted exactly)."""


class SolverImplicitEuler(SolverBase):
    """Linearly implicit (backward) Euler, one Newton step per time step (Baraff & Witkin 1998).

    Solves ``(M + h D + h^2 K) dv = h (f0 - h K v0)``, then ``v1 = v0 + dv``, ``x1 = x0 + h v1``
    (notation in :mod:`cloth_warp.kernels.implicit`). K = -df/dx keeps springs positive semi-definite:
    linear springs drop their transverse term under compression, buckling springs keep only the
    longitudinal term (physics.md 3(b), 3(d)); triangle membrane elements use Gauss-Newton plus the
    geometric stiffness of the positive part of their stress (physics.md E: the exact Hessian wherever the
    element is in tension both ways, PSD always); so A is SPD and CG applies. Hard pins enter as
    constraints through the filter (velocity change prescribed, no Lagrange multipliers).

    Per step the solver reports `last_iterations`, `last_residual` (the relative residual
    |r_k| / |r_0| of the filtered system), `converged` (residual <= tolerance) and `last_failure`
    ("non-finite residual" when the system or an iterate is not finite: the step's result is meaningless;
    the Simulator raises :class:`~cloth_warp.solvers.adaptive.SimulationDiverged`, the adaptive stepper
    rejects the step; None otherwise).

    Args:
        model: the model.
        linear_solver: :class:`LinearSolver` (CG default).
        max_iterations: iteration cap per step (a 128^2 cotton cloth at dt = 1/60 s needs up to ~660).
        tolerance: relative residual at which the solve stops. 1e-3 reproduces the 1e-4 motion of a 64^2
            cotton cloth at dt = 1/60 s to 0.3 % in kinetic energy; 1e-2 visibly over-damps it.
        check_every: iterations between convergence checks, on the device in the loop's 1-thread counting kernel
            (default: every CG iteration, where the residual is a by-product; every 4th block-Jacobi iteration,
            where a check costs a residual evaluation).
        warm_start: start each solve from the previous step's dv (forward runs; not with collider contacts in the
            solve, whose steps start from their contacts' prescribed parts and zero elsewhere). The tolerance stays
            relative to the zero-guess residual |S (b - A z)|, so a good start saves iterations.
        warm_start_reduction: a warm-started solve also cuts its starting residual by this factor (down to
            a relative 1e-6, float32's floor) before it stops. Stopping as soon as the previous dv is within
            `tolerance` carries that solve's error from step to step, and the delay sustains a ~6 Hz limit
            cycle of cloth resting on colliders (~30 mm/s at the free edges of a drape, measured; 0.1 mm/s
            with 0.01).
        velocity_tolerance: contacts in the solve, forward steps near rest (tolerance x the RMS speed at the step's
            start below it): after the solves that decide the contacts, the step's last solve goes on until its RMS
            velocity error is within it [m/s] (kernels/implicit.py begin_linear_solve), changing no contact; 0 (the
            default): none. At rest the tolerance alone left ~5 um/s RMS of error, which fed a 6.7 Hz wave on the
            shipped drape's free edge; 1e-5 rests it, at a cost (docs/contacts-in-the-solve.md).
        sample_holds: "solve" contacts, forward steps: a particle the colliders pass's element samples pushed out of a
            mesh collider (an edge or triangle of the cloth through the body between particles that were clear) is a
            contact up to the height they left it at (and half a thickness) and keeps its height there (kernels/contact.py
            eval_collider_contacts), instead of being carried back to where the samples push it again; False: such
            particles are contacts as any other (within the band, landing at the thickness).
        pulled_friction: "solve" contacts with their friction in the solve: a damped contact let slide without friction
            because it pulled, that presses in the check of the reversal's extra round, sticks again with a damper and
            the step is solved again (kernels/implicit.py eval_contact_release); False (the default): friction after the
            solve stops it, alone. On, the T-shirt held still rests at 2.2-3.4 cm edges (6 of 6, 4 without); the rest
            set's piles and drapes settle later (52 of 60 at rest after 5 s against 56, the shipped drape at 5.4 s).
        self_contact_stiffening: self-contacts in the solve, forward steps: a self-contact element whose load holds it
            deeper than SELF_CONTACT_GAIN_HOLD of the way from its rest distance to the self-collision pass's reach is
            stiffened for the next steps (a gain per particle, at most 32x, followed with hysteresis: kernels/contact.py
            eval_self_contact_gain_targets, update_self_contact_gains), so that the pass has no loaded pair to push
            out and the next solve to pull back. Off by default: it rests layers pressed into soft contacts (a cloth
            on a cloth at 0.25 N/m: 4.6 mm/s and 840 impulses a frame without it), but it changes the shipped
            garments' runs (docs/garments.md, "Self-contacts stiffened where they are loaded").
        strain_limit, strain_limit_iterations, collisions: see :class:`~cloth_warp.solvers.base.SolverBase`.
        collider_contacts: "pass" (collider contacts resolved after the step by the colliders pass only) or "solve"
            (also inside the solve, Baraff & Witkin's filter: a particle touching a collider at the start of the step
            gets its end-of-step normal velocity prescribed, the one that ends the step at the collider's thickness
            (kernels/contact.py), the rest of its motion solved with the cloth; a contact whose solved impulse pulls
            is released and the step solved again (at most `contact_release_rounds` times), and Coulomb friction
            acts (`contact_friction`) on the solved tangential velocity with that impulse (on a garment's sewn points as
            one point: the particles a seam joins share the law, so friction never holds a seam's sides apart; with
            friction in the solve, only the points whose seams are still open: see `contact_friction`); the
            colliders pass still runs after the step as the guarantee). Taped steps differentiated by the adjoint hold them too
            (below; their friction is per particle); CG only.
        contact_margin: "solve" contacts: a particle within the thickness x (1 + margin) at the step's start is in
            contact (as is one inside, or predicted to reach the surface within the step); on a forward step, one in
            that band that its last step's velocity change does not carry through the thickness keeps its height, or
            settles at kernels/contact.py SETTLE_SPEED if its contact bore load (the cloth may hold it up), instead
            of being pulled down onto the surface in one step.
        contact_release_rounds: "solve" contacts: the re-solves a step may run after its contact checks (releases, friction
            going from stick to slide or back; with a `contact_check_tolerance` looser than `tolerance`, the last is the
            solve to the tolerance). A contact at the static bound that one check lets slide and the next finds stuck
            needs two; with 2, a garment held still went from stick to slide and back every step (the shipped dress:
            17 contacts, 13.8 mm/s; with 4: 0.08 mm/s and 10 % fewer CG iterations a frame; `docs/garments.md`). A slide
            its kinetic impulse reversed is stuck again with one re-solve more than these (none with 0).
        contact_release_fraction: "solve" contacts: a contact is released when it pulls with more than this fraction
            of the particle's weight (times the step): below it the pull is the solve's round-off, and a released
            particle has no friction.
        contact_friction: "solve" contacts' Coulomb friction: "after" the solve (above), or in the "solve" (forward
            steps; kernels/implicit.py eval_contact_friction_terms), with the contact's normal impulse of its last step:
            a sticking or creeping contact as a tangential damper that reaches the static bound at
            `contact_stick_speed` from rest (its solved slip then taken out: no creep) and gives Coulomb's force at the
            speed it creeps at; one the solve pushes past the bound slides, solved again; a sliding one as the kinetic
            impulse; a new contact and a sewn point the sewing pass does not weld (its seam still open) take it after the
            solve, as one point (a welded point's particles start every step together with one velocity: each takes
            its own friction in the solve). With ``self_contacts="solve"`` the
            self-contact elements' friction is in the solve alike (kernels/contact.py self_contact_friction_terms: a
            damper on the pair's relative tangential velocity, or the kinetic impulse). The solve then holds the stuck contacts
            instead of moving the cloth around slides that friction undoes (a drape's contacts slid by up to 1.4 m/s
            in the solve), which lets draped cloth come to rest; it costs iterations (see the README).
        contact_stick_speed: "solve" contacts: the slip [m/s] at which a sticking contact's damper reaches the static
            friction bound from rest; slower slips are taken out after the solve (no creep under static friction).
        self_contacts: "pass" (cloth-cloth contacts resolved after the step by the self-collision pass only) or "solve"
            (also inside the solve: each vertex-face or edge-edge pair closer than the cloth thickness (1 + 5 %) at the
            step's start, among the pairs the self-collision pass found close in the last step, is a repulsion element
            with the model's self-collision stiffness in the system, kernels/contact.py; with "solve" collider
            contacts, a candidate the solved step carries inside that distance becomes one within the step at the
            contact checks, `admit_self_contacts`; the pass still runs after the step as the guarantee, its proximity
            impulses then only within PROXIMITY_REACH_UNDER_SOLVE of the thickness). Forward steps only; CG only; needs
            self-collision on.
        contact_check_tolerance: "solve" contacts, forward steps: the solves after which the contacts are checked
            (released, let slide, stuck again) stop at this relative residual where `tolerance` is tighter, and once
            none changes one more solve goes on to `tolerance` (default: CONTACT_CHECK_TOLERANCE with the friction in
            the solve, else `tolerance`: every solve to it).
        sewn_points: "solve" (each sewn point the sewing pass welds is one particle in the system, its root:
            cloth_warp/sewing.py `welded_view`; the point's other particles take the root's velocity change) or "pass"
            (every particle its own, the seam springs in the system, the point welded after the step by the sewing pass
            alone). With "solve" the pass after the step has nothing left to weld; with "pass" it moves what the solve
            balanced, every step (a T-shirt held still: 91 particles by up to 17 mm/s).

    Differentiation (taped steps, ``state_in.requires_grad``): with ``differentiation="adjoint"`` the solve
    runs outside the tape; the tape holds dv and the residual r = S (b - A dv), evaluated element by element
    from x0, v0 and every model parameter, and a backward hook solves the transposed system
    S A S lam = S dL/d(dv) (A is symmetric: the same CG or Jacobi solve, to the same tolerance) and seeds
    dL/dr = lam. Gradients are then exact up to the solve tolerance; set a tight `tolerance` (1e-6) for
    gradient checks. ``differentiation="unrolled"`` instead tapes `max_iterations` block-Jacobi
    iterations dv <- dv + P r (the reference the adjoint is tested against; memory grows with the
    iterations). Taped steps never warm-start, so a re-run (checkpointing) reproduces the forward run.
    With ``collider_contacts="solve"`` (adjoint only), the step's contact set (less the released) is held fixed and
    its normals, surface velocities and prescribed velocity changes are evaluated again on the tape
    (kernels/contact.py eval_contact_constraints): dv = S dv_solved + z, r = S (b - A dv), the transposed system is
    filtered alike, and friction acts on the tape with lambda = -n . (b - A dv) (whether a contact sticks is held
    fixed too). With ``self_contacts="solve"`` (adjoint only) a taped step's self-contact elements are those of its own
    start (none admitted within the step), frictionless in the solve, held fixed: their part of r on the tape with their
    weights, distances and normals from x0 (kernels/contact.py eval_residual_self_contacts), their blocks in the
    transposed system, their Coulomb friction after the solve on the tape (`_taped_self_contact_friction`). The unrolled
    reference has no contact filter and no elements.
    """

    replay_loops: bool = True
    """On the CPU, record each linear solve's loop once as a graph and replay it where the step runs eagerly (bit for bit
    the eager loop; False, per solver or for the class: launch its kernels one by one, the reference
    tests/test_capture.py and benchmarks/bench_taped_solves.py compare with). CUDA keeps its eager loop for now."""

    world_threads: bool = True
    """On the CPU the CG iterates with one thread per world (kernels/implicit.py cg_*_worlds; one world: one thread):
    a batch's world that stopped costs nothing while the batch's slowest goes on, and a single cloth's iteration is
    three kernels instead of seven or more, each a pass over the cloth (0.84-1.00 of the frame on shipped scenes,
    benchmarks/results/bench_step_world_threads.md; self-contacts in the solve scatter with a kernel of their own between
    the elements and the rows). False, per solver or for the class, or the CUDA reductions forced on the CPU
    (cloth_warp.reductions.USE_BLOCKS): one thread per particle and element, as on CUDA. Bit for bit the same."""

    name = "implicit_euler"
    kernel_modules = (ki,)
    device_loops = True

    def __init__(
        self,
        model: Model,
        *,
        linear_solver: LinearSolver | str = LinearSolver.CG,
        max_iterations: int = 1000,
        tolerance: float = 1.0e-3,
        check_every: int | None = None,
        warm_start: bool = True,
        warm_start_reduction: float = 0.01,
        strain_limit: float | None = 0.1,
        strain_limit_iterations: int = DEFAULT_SWEEPS,
        strain_limit_tolerance: float | None = 1.0e-3,
        collisions: bool = True,
        collision_rounds: int = 2,
        differentiation: str = "adjoint",
        collider_contacts: str = "pass",
        contact_margin: float = 0.01,
        contact_release_rounds: int = 4,
        contact_release_fraction: float = 0.05,
        contact_friction: str = "after",
        contact_stick_speed: float = 1.0e-4,
        self_contacts: str = "pass",
        contact_check_tolerance: float | None = None,
        sewn_points: str = "solve",
        velocity_tolerance: float = 0.0,
        self_contact_stiffening: bool = False,
        sample_holds: bool = True,
        pulled_friction: bool = False,
    ):
        super().__init__(model, strain_limit=strain_limit, strain_limit_iterations=strain_limit_iterations,
                         strain_limit_tolerance=strain_limit_tolerance, collisions=collisions, collision_rounds=collision_rounds)
        if isinstance(linear_solver, str):
            try:
                linear_solver = LinearSolver[linear_solver.upper()]
            except KeyError:
                raise ValueError(f"unknown linear solver {linear_solver!r}; allowed: cg, jacobi") from None
        self.linear_solver = LinearSolver(linear_solver)
        if differentiation not in ("adjoint", "unrolled"):
            raise ValueError(f"unknown differentiation {differentiation!r}; allowed: adjoint, unrolled")
        self.differentiation = differentiation
        if collider_contacts not in COLLIDER_CONTACTS:
            raise ValueError(f"unknown collider_contacts {collider_contacts!r}; allowed: {', '.join(COLLIDER_CONTACTS)}")
        if collider_contacts == "solve" and self.linear_solver != LinearSolver.CG:
            raise ValueError("collider_contacts='solve' needs linear_solver='cg' (the contact filter is in the CG)")
        self.collider_contacts = collider_contacts
        if self_contacts not in COLLIDER_CONTACTS:
            raise ValueError(f"unknown self_contacts {self_contacts!r}; allowed: {', '.join(COLLIDER_CONTACTS)}")
        if self_contacts == "solve" and self.linear_solver != LinearSolver.CG:
            raise ValueError("self_contacts='solve' needs linear_solver='cg' (the contact elements are in the CG's product)")
        self.self_contacts = self_contacts
        colliders = self.pass_named("colliders")
        if colliders is not None:  # the colliders pass keeps pinched particles where this solve lands them
            colliders.pinch = collider_contacts == "solve"
        # the self-collision passes' SelfCollisions, whose close pairs the self-contacts read: per world (batched worlds:
        # one each), with its model's triangles and self-collision stiffness [N/m] and its first particle
        self._self_collisions: list[tuple] = []
        collisions = self.pass_named("self_collision") if self_contacts == "solve" else None
        if collisions is not None and model.world_count > 1:
            for k, (p, wm) in enumerate(zip(collisions.worlds, model.world_models)):
                self._self_collisions.append((p.self_collision, wm.tri_indices, float(wm.self_collision_stiffness),
                                              int(model.world_particle_start[k])))
        elif collisions is not None:
            self._self_collisions.append((collisions.self_collision, model.tri_indices, float(model.self_collision_stiffness), 0))
        for sc, *_ in self._self_collisions:
            sc.share_close_pairs = True
            sc.proximity_reach = PROXIMITY_REACH_UNDER_SOLVE
        # per world, each particle's triangles (its model's CSR), so that a contact nearest at an edge or corner is one element
        self._triangle_rings = [(sc.model.particle_tri_offsets, sc.model.particle_tri_ids) for sc, *_ in self._self_collisions]
        if "solve" in (collider_contacts, self_contacts):
            self.kernel_modules = (ki, kct)
        self.contact_margin = float(contact_margin)
        self.contact_release_rounds = int(contact_release_rounds)
        self.contact_release_fraction = float(contact_release_fraction)
        if contact_friction not in CONTACT_FRICTION:
            raise ValueError(f"unknown contact_friction {contact_friction!r}; allowed: {', '.join(CONTACT_FRICTION)}")
        if contact_friction == "solve" and collider_contacts != "solve":
            raise ValueError("contact_friction='solve' needs collider_contacts='solve' (the friction of the contacts in the "
                             "solve)")
        self.contact_friction = contact_friction
        if not contact_stick_speed > 0.0:
            raise ValueError(f"contact_stick_speed must be positive, got {contact_stick_speed!r}")
        self.contact_stick_speed = float(contact_stick_speed)
        # Backward-pass report: adjoint solves run and their iterations (summed).
        self.adjoint_solves = 0
        self.adjoint_iterations = 0
        from ..validation import LIMITS, check_number

        max_iterations = check_number("max_iterations", max_iterations, LIMITS["iterations"])
        tolerance = check_number("tolerance", tolerance, LIMITS["tolerance"])
        self.max_iterations = int(max_iterations)
        self.tolerance = float(tolerance)
        if contact_check_tolerance is None:  # (measured with the friction in the solve, whose slides are re-solved every step)
            contact_check_tolerance = CONTACT_CHECK_TOLERANCE if contact_friction == "solve" else self.tolerance
        contact_check_tolerance = check_number("contact_check_tolerance", contact_check_tolerance, LIMITS["tolerance"])
        self.contact_check_tolerance = float(contact_check_tolerance)
        if check_every is None:
            check_every = 1 if self.linear_solver == LinearSolver.CG else 4
        self.check_every = max(1, int(check_every))
        self.warm_start = bool(warm_start)
        if not (0.0 < warm_start_reduction <= 1.0):
            raise ValueError(f"warm_start_reduction must be in (0, 1], got {warm_start_reduction!r}")
        self.warm_start_reduction = float(warm_start_reduction)
        if not (math.isfinite(velocity_tolerance) and velocity_tolerance >= 0.0):
            raise ValueError(f"velocity_tolerance must be a speed >= 0 [m/s], got {velocity_tolerance!r}")
        self.velocity_tolerance = float(velocity_tolerance)
        self.self_contact_stiffening = bool(self_contact_stiffening)
        n, s, t = model.particle_count, max(model.spring_count, 1), max(model.tri_count, 1)
        dev = model.device
        # per particle, the height [m] over a mesh collider the colliders pass's element samples left it at (0: none;
        # kernels/collide.py SAMPLE_HOLD_SLACK): with `sample_holds`, such a contact keeps its height in the solve
        self.sample_holds = bool(sample_holds)
        self.pulled_friction = bool(pulled_friction)
        self.sample_height = wp.zeros(n, dtype=float, device=dev)
        if colliders is not None:
            colliders.sample_height = self.sample_height if collider_contacts == "solve" and self.sample_holds else None
        self.stiffness_block = wp.zeros(s, dtype=wp.mat33, device=dev)
        self.system_block = wp.zeros(s, dtype=wp.mat33, device=dev)
        self.spring_compact = wp.zeros(s, dtype=wp.vec4, device=dev)  # B_s as a I + u u^T, for the CG's product
        self.bend_vector = wp.zeros(s, dtype=wp.vec3, device=dev)
        self.drag_vector = wp.zeros(t, dtype=wp.vec3, device=dev)
        # membrane elements: per element B_0, B_1, B_2, the Voigt matrix A (h^2 C + h C_d), the corner matrix of the
        # geometric stiffness; per particle K_e v0, the diagonal blocks and (h D_e + h^2 K_e) z (zero without elements)
        self.membrane_block = wp.zeros((max(model.membrane_count, 1), 5), dtype=wp.mat33, device=dev)
        self.membrane_kv = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.membrane_diag = wp.zeros(n, dtype=wp.mat33, device=dev)
        self.membrane_az = wp.zeros(n, dtype=wp.vec3, device=dev)
        # plate stencils (sharing the three per-particle arrays above): their weighted diagonal h^2 K_jj m/2 for block
        # Jacobi, and their part of A p for the per-particle (gather) kernels, scattered before each
        self.plate_diagonal = wp.zeros(n, dtype=float, device=dev)
        self.plate_product = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.rhs = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.precond = wp.zeros(n, dtype=wp.mat33, device=dev)
        self.dv = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.dv_alt = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.dv_best = wp.zeros(n, dtype=wp.vec3, device=dev)  # CG: the iterate with the smallest residual (restore_best_iterate)
        self.dv_previous = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.residual = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.preconditioned = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.search = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.product = wp.zeros(n, dtype=wp.vec3, device=dev)  # A c (c: the CG search direction)
        # Per-solve scalars, one set per world (batched worlds: kernels/implicit.py, world w's at w * <size>)
        worlds = self.worlds = int(model.world_count)
        self.cg_scalars = wp.zeros((self.max_iterations + 2, worlds * ki.CG_COLUMNS), dtype=wp.float64, device=dev)
        self.warm_scalars = wp.zeros((1, worlds * ki.CG_COLUMNS), dtype=wp.float64, device=dev)  # a warm start's row 0
        self.cg_step = wp.zeros(worlds * 2, dtype=float, device=dev)  # the iteration's alpha and beta (kernels/implicit.py CG_ALPHA, CG_BETA)
        self.cg_sums = wp.zeros(worlds * ki.CG_COLUMNS, dtype=wp.float64, device=dev)  # an iteration's reductions, moved into cg_scalars
        self.effective_mass = wp.zeros(n, dtype=float, device=dev)  # M'_i = m_i (1 + h gamma) + h^2 k_pin [kg] of the assembled step
        # the solve's state on the device (kernels/implicit.py LOOP_*, STATUS_*, RECORD_*): no host read inside a step
        self.loop = wp.zeros(world_slots_length(ki.LOOP_SIZE, worlds), dtype=wp.int32, device=dev)
        self.solve_status = wp.zeros(worlds * ki.STATUS_SIZE, dtype=wp.float64, device=dev)
        self.motion = wp.zeros(2 * worlds, dtype=wp.float64, device=dev)  # per world: sum m |v0|^2, sum m (kernels/implicit.py sum_motion)
        self.solve_record = wp.zeros(worlds * ki.RECORD_SIZE, dtype=wp.float64, device=dev)
        # on the CPU: each world's items, walked by the one-thread-per-world CG kernels
        self._world_ranges = wp.array(world_ranges(model), dtype=wp.int32, device=dev) if dev.is_cpu else None
        self.previous_ready = wp.zeros(worlds, dtype=wp.int32, device=dev)  # 1: dv_previous starts the world's next forward solve
        self._enabled = wp.ones(worlds, dtype=wp.int32, device=dev)
        self._disabled = wp.zeros(worlds, dtype=wp.int32, device=dev)
        # collider contacts in the solve (kernels/contact.py; zero normals: none, as in every other solve)
        self.contact_collider = wp.zeros(n, dtype=wp.int32, device=dev)
        self.contact_normal = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.contact_crease = wp.zeros(n, dtype=wp.vec3, device=dev)  # a contact pinched in a crease: its second direction
        self.contact_facing = wp.zeros(n, dtype=wp.vec3, device=dev)  # a pinched contact: the facing side's outward normal
        self.contact_velocity = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.contact_dv = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.contact_impulse = wp.zeros(n, dtype=float, device=dev)
        # the height [m] above its surface each contact ends the step at; below the collider's thickness: pinched
        self.contact_height = wp.zeros(n, dtype=float, device=dev)
        self.precond_free = wp.zeros(n, dtype=wp.mat33, device=dev)  # contacts' unfiltered preconditioner blocks
        # their friction in the solve (kernels/implicit.py eval_contact_friction_terms): a sticking contact's damper
        # mass [kg], and the friction impulse [kg m/s] in the right-hand side (sticking or sliding)
        self.contact_friction_mass = wp.zeros(n, dtype=float, device=dev)
        self.contact_friction_impulse = wp.zeros(n, dtype=wp.vec3, device=dev)
        # the contacts released in this step (collider + 1; -1: taken back; -2: admitted within it), with their normals
        # and prescribed changes
        self.contact_released = wp.zeros(n, dtype=wp.int32, device=dev)
        # 1: the contact's friction left its step's system as it pulled (kernels/implicit.py eval_contact_release)
        self.contact_pulled = wp.zeros(n, dtype=wp.int32, device=dev)
        self._admit_colliders = False  # (set per step by _solve_with_contacts, with the step's start it reads)
        self.contact_released_normal = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.contact_released_dv = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.contact_slipping = wp.zeros(n, dtype=wp.int32, device=dev)  # 1: the contact was left sliding by the last step
        # sewn points as one particle (sewing.welded_view): self.model is then the solve's view of the model
        if sewn_points not in SEWN_POINTS:
            raise ValueError(f"unknown sewn_points {sewn_points!r}; allowed: {', '.join(SEWN_POINTS)}")
        self.sewn_points = sewn_points
        self.full_model = model
        """The model as built (self.model: the solve's view of it, where sewn points are one particle)."""
        self.particle_point_root = wp.full(n, -1, dtype=wp.int32, device=dev)  # per particle its solved point's root (-1: itself)
        self._point_inv_mass = None  # the view's inverse masses [1/kg] for the self-contacts' friction
        self._view_sewn_points()
        # sewn points that take friction as one point after the solve (kernels/implicit.py gather_seam_friction,
        # _seam_friction_roots): per particle its point's root (-1: any other), per root the sums the friction law needs
        self._sewn_roots = sewn_point_roots(model) if collider_contacts == "solve" else None
        self._sewn = self._sewn_roots is not None and bool((self._sewn_roots >= 0).any())
        self.particle_seam_root = wp.array(self._seam_friction_roots(), dtype=wp.int32, device=dev)
        m_sewn = n if self._sewn else 1
        self.seam_momentum = wp.zeros(m_sewn, dtype=wp.vec3, device=dev)
        self.seam_mass = wp.zeros(m_sewn, dtype=float, device=dev)
        self.seam_impulse = wp.zeros(m_sewn, dtype=float, device=dev)
        # self-contact elements in the solve (kernels/contact.py eval_self_contacts; capacity: the candidates')
        self.self_contact_count = wp.zeros(1, dtype=wp.int32, device=dev)
        # per particle its self-contact elements' stiffness gain (1: the model's stiffness; kernels/contact.py
        # eval_self_contact_gain_targets) and the gain its elements asked in the last step
        self.self_contact_gain = wp.ones(n, dtype=float, device=dev)
        self.self_contact_gain_target = wp.zeros(n, dtype=float, device=dev)
        self._gathered_inv_mass = None  # batched worlds: the worlds' self-collision inverse masses in one array
        # (friction overlaps: the part of each overlap that bounds its friction, kernels/contact.py friction_load_overlap)
        self._self_contact_elements = None  # (indices, weights, normals, friction overlaps, friction masses, friction impulses, stiffness, h^2 k), capacity: the candidates'
        self._self_contacts_on = False  # whether the step being solved has self-contact elements
        # the pairs beyond the elements' rest distance the contact checks may admit (kernels/contact.py admit_self_contacts):
        # (indices, weights, start gaps, stiffness, h^2 k, admitted), capacity: the candidates'
        self._self_contact_admissible = None
        self.self_contact_admissible_count = wp.zeros(1, dtype=wp.int32, device=dev)
        self._loop_graphs = LoopGraphs()  # the linear solves' loops, recorded once where they run eagerly (_solve_loop)
        self.friction_dv = wp.zeros(n, dtype=wp.vec3, device=dev)  # self-contact friction: summed changes and their count
        self.friction_weight = wp.zeros(n, dtype=float, device=dev)
        self._contacts_on = False  # whether the solve being recorded filters contacts
        self.contact_counts = wp.zeros(world_slots_length(ki.COUNT_SIZE, worlds), dtype=wp.int32, device=dev)
        self.release = wp.zeros(world_slots_length(ki.RELEASE_SIZE, worlds), dtype=wp.int32, device=dev)

    def notify_model_changed(self, flags: int) -> None:
        """Model fields changed: besides the passes (:meth:`SolverBase.notify_model_changed`), the previous step's
        velocity change no longer predicts this one, so the next solve starts cold."""
        super().notify_model_changed(flags)
        if flags & (ModelFlags.PARTICLE_PROPERTIES | ModelFlags.PARTICLE_INITIAL_STATE):  # the points' masses, the welded points
            self._view_sewn_points()  # (after the sewing pass found its welded points again; the rest the view shares)
        self.previous_ready.zero_()
        if self._sewn and flags & ModelFlags.PARTICLE_INITIAL_STATE:  # (the sewing pass found its welded points again)
            self.particle_seam_root.assign(self._seam_friction_roots())
        self._loop_graphs.clear()  # (they hold the model's arrays as they were)

    def _view_sewn_points(self):
        """With sewn_points="solve", solve the model's view in which each point the sewing pass welds is one particle
        (sewing.welded_view; none welded: the model itself)."""
        m = self.full_model
        sewing = self.pass_named("sewing")
        roots = solve_roots(m, sewing.weld.roots) if sewing is not None and self.sewn_points == "solve" else None
        if roots is None or not (roots >= 0).any():
            self.model = m
            self.particle_point_root.fill_(-1)
            self._point_inv_mass = None
            return
        self.model = welded_view(m, roots)
        self.particle_point_root.assign(roots)
        inv_mass = inverse_masses(self.model.particle_mass.numpy(), self.model.particle_pinned.numpy() != 0)
        self._point_inv_mass = wp.array(inv_mass.astype(np.float32), dtype=float, device=m.device)

    @property
    def solves_sewn_points(self) -> bool:
        """Whether some sewn points are one particle in this solve (sewn_points="solve" and the sewing pass welds some)."""
        return self.model is not self.full_model

    def _seam_friction_roots(self) -> np.ndarray:
        """Per particle, the root of its sewn point when the point's contacts take Coulomb friction as one point after
        the solve, else -1 (int32, (n,)): every sewn point with friction after the solve; with it in the solve, those
        the sewing pass does not weld (their seams still open: each side held where it landed would keep them open).
        A welded point's particles start every step together with one velocity, so each takes its own friction in
        the solve: as one point after it, the dress held still had contacts on its shoulder seams go from sliding to
        stopped every other step, the cloth beside them swinging at 1.2 mm/s."""
        n = self.model.particle_count
        if not self._sewn:
            return np.full(n, -1, np.int32)
        roots = self._sewn_roots.copy()
        sewing = self.pass_named("sewing")
        if self.contact_friction == "solve" and sewing is not None:
            roots[sewing.weld.roots >= 0] = -1
        if self.solves_sewn_points:  # (a point solved as one particle: its root alone has a contact)
            roots[self.particle_point_root.numpy() >= 0] = -1
        return roots

    # -- the linear system -------------------------------------------------------------------
    def assemble(self, state_in: State, control: Control, dt: float):
        """Evaluate blocks, right-hand side, preconditioner and the initial residual for one step."""
        m = self.model
        dev = m.device
        if m.spring_count:
            wp.launch(
                ki.eval_spring_system_blocks,
                dim=m.spring_count,
                inputs=[m.spring_indices, m.spring_rest_length, m.spring_stiffness, m.spring_damping, m.spring_middle,
                        state_in.particle_q, dt],
                outputs=[self.stiffness_block, self.system_block, self.spring_compact, self.bend_vector],
                device=dev,
            )
        if m.tri_count:
            wp.launch(
                ki.eval_triangle_drag_vectors,
                dim=m.tri_count,
                inputs=[m.tri_indices, m.tri_drag, state_in.particle_q],
                outputs=[self.drag_vector],
                device=dev,
            )
        if m.membrane_count or m.plate_count or self._self_contacts_on:
            self.membrane_kv.zero_()
            self.membrane_diag.zero_()
            self.membrane_az.zero_()
        if m.plate_count:
            self.plate_diagonal.zero_()
            wp.launch(
                ki.eval_plate_system,
                dim=m.plate_count,
                inputs=[m.plate_offsets, m.plate_points, m.plate_weights, m.plate_stiffness, m.particle_pinned, state_in.particle_q,
                        state_in.particle_qd, control.pin_target, dt],
                outputs=[self.membrane_kv, self.membrane_diag, self.membrane_az, self.plate_diagonal],
                device=dev,
            )
        if m.membrane_count:
            wp.launch(
                ki.eval_membrane_system_blocks,
                dim=m.membrane_count,
                inputs=[m.membrane_vertices, m.membrane_rest_inverse, m.membrane_rest_area, m.membrane_stiffness, m.membrane_damping,
                        m.particle_pinned, state_in.particle_q, state_in.particle_qd, control.pin_target, dt],
                outputs=[self.membrane_block, self.membrane_kv, self.membrane_diag, self.membrane_az],
                device=dev,
            )
        self.cg_scalars.zero_()
        force = self.element_forces(state_in.particle_q, state_in.particle_qd, control)
        if self._self_contacts_on:
            self._find_self_contacts(state_in, force, dt)
        wp.launch(
            ki.eval_implicit_system,
            dim=m.particle_count,
            inputs=[*self._product_args()[:9], m.particle_mass, m.particle_pin_stiffness, m.particle_pinned, force, self.stiffness_block,
                    self.system_block, self.bend_vector, self.drag_vector, self.membrane_kv, self.membrane_diag, self.membrane_az,
                    state_in.particle_q, state_in.particle_qd,
                    control.pin_target, wp.vec3(*m.gravity), m.global_damping, dt, m.particle_world, self.worlds],
            outputs=[self.rhs, self.precond, self.dv, self.residual, self.preconditioned, self.search, self.cg_scalars, self.effective_mass],
            device=dev,
        )

    def _find_self_contacts(self, state_in: State, force: wp.array, dt: float):
        """This step's self-contact elements from the self-collision pass's candidates (kernels/contact.py
        eval_self_contacts): their forces into `force`, K v0 and diagonal blocks into the per-particle arrays the
        membrane elements and plate stencils also scatter into."""
        m = self.model
        dev = m.device
        candidates = []
        for sc, _, _, first in self._self_collisions:  # (batched worlds: each world's slice of the particles)
            n = sc.model.particle_count
            x, v = state_in.particle_q, state_in.particle_qd
            if n != m.particle_count:
                x, v = x[first:first + n], v[first:first + n]
            if state_in.requires_grad:  # a taped step's elements: those of its own start (forget_close_pairs)
                sc.forget_close_pairs()
            candidates.append(sc.contact_candidates(x, v, dt))
        capacity = sum(pairs.shape[0] for world in candidates for pairs, _ in world)
        if self._self_contact_elements is None or self._self_contact_elements[0].shape[0] != capacity:
            self._self_contact_elements = (wp.zeros(capacity, dtype=wp.vec4i, device=dev), wp.zeros(capacity, dtype=wp.vec4, device=dev),
                                           wp.zeros(capacity, dtype=wp.vec3, device=dev), wp.zeros(capacity, dtype=float, device=dev),
                                           wp.zeros(capacity, dtype=float, device=dev), wp.zeros(capacity, dtype=wp.vec3, device=dev),
                                           wp.zeros(capacity, dtype=float, device=dev), wp.zeros(capacity, dtype=float, device=dev))
            self._self_contact_admissible = (wp.zeros(capacity, dtype=wp.vec4i, device=dev), wp.zeros(capacity, dtype=wp.vec4, device=dev),
                                             wp.zeros(capacity, dtype=wp.vec3, device=dev), wp.zeros(capacity, dtype=float, device=dev),
                                             wp.zeros(capacity, dtype=float, device=dev), wp.zeros(capacity, dtype=wp.int32, device=dev))
        self.self_contact_count.zero_()
        self.self_contact_admissible_count.zero_()
        inv_mass = self._self_contact_inverse_masses()
        el = self._self_contact_elements
        for (sc, tris, stiffness, first), rings, world in zip(self._self_collisions, self._triangle_rings, candidates):  # (batched: per world)
            for kind, (pairs, count) in enumerate(world):
                wp.launch(kct.eval_self_contacts, dim=pairs.shape[0],
                          inputs=[count, pairs, kind, tris, sc.edge_indices, *rings, m.particle_pinned, self.particle_point_root,
                                  state_in.particle_q,
                                  state_in.particle_qd, self._self_contact_distance(), stiffness, dt, self._gravity_norm,
                                  capacity,
                                  inv_mass, float(m.cloth_friction), self.contact_stick_speed,
                                  int(self.contact_friction == "solve" and not state_in.requires_grad),
                                  first, m.particle_world, self.worlds, dt * dt * stiffness, self.self_contact_gain],
                          outputs=[*el[:6], self.self_contact_count, force, self.membrane_kv, self.membrane_diag, self.contact_counts,
                                   el[6], el[7], *self._self_contact_admissible, self.self_contact_admissible_count], device=dev)

    @property
    def _gravity_norm(self) -> float:
        """|g| [m/s^2] of the model's gravity as it is now (a model change may set it)."""
        return float(np.linalg.norm(np.asarray(self.model.gravity, np.float64)))

    def _release_speed(self, dt: float) -> float:
        """The collider contacts' load threshold [m/s]: `contact_release_fraction` g h. An impulse below it times a
        particle's mass is the solve's round-off: a contact pulling harder is released (`eval_contact_release`), one in
        the band pressing harder settles (kernels/contact.py `eval_collider_contacts`)."""
        return self.contact_release_fraction * self._gravity_norm * dt

    def _self_contact_distance(self) -> float:
        """The self-contact elements' rest distance r [m]: the cloth thickness and the solve's clearance."""
        return float(self.model.cloth_thickness) * (1.0 + float(kct.SELF_CLEARANCE))

    def _admit_self_contacts(self, dt: float, v0: wp.array, rounds: int):
        """Admissible pairs the solved step carries inside the rest distance become elements, and the step is solved
        again (kernels/contact.py admit_self_contacts)."""
        el, ad = self._self_contact_elements, self._self_contact_admissible
        wp.launch(kct.admit_self_contacts, dim=el[0].shape[0],
                  inputs=[self.self_contact_admissible_count, *ad[:5], v0, self.dv, self._self_contact_distance(), dt, el[0].shape[0],
                          rounds, self.model.particle_world, self.worlds],
                  outputs=[ad[5], *el[:6], self.self_contact_count, self.rhs, self.contact_counts, el[6], el[7], self.release],
                  device=self.model.device)

    def _update_self_contact_gains(self, state_in: State, dv: wp.array, dt: float):
        """The next step's gains (kernels/contact.py eval_self_contact_gain_targets, update_self_contact_gains): each
        element's load held SELF_CONTACT_GAIN_HOLD of the way from its rest distance to the self-collision pass's reach."""
        el = self._self_contact_elements
        r = self._self_contact_distance()
        headroom = r - PROXIMITY_REACH_UNDER_SOLVE * float(self.model.cloth_thickness)
        wp.launch(kct.eval_self_contact_gain_targets, dim=el[0].shape[0],
                  inputs=[self.self_contact_count, *el[:3], self.self_contact_gain, state_in.particle_q, state_in.particle_qd, dv,
                          r, SELF_CONTACT_GAIN_HOLD * headroom, dt],
                  outputs=[self.self_contact_gain_target], device=self.model.device)
        wp.launch(kct.update_self_contact_gains, dim=self.model.particle_count,
                  outputs=[self.self_contact_gain_target, self.self_contact_gain], device=self.model.device)

    def _self_contact_inverse_masses(self) -> wp.array:
        """The self-collision passes' inverse masses [1/kg] in the model's particle order: one world's own array, or the
        worlds' gathered into one (copied each step: a world's pass refreshes its own on a model change); where sewn
        points are one particle in the solve, the solve's view's (a point's root: the point's mass)."""
        if self._point_inv_mass is not None:
            return self._point_inv_mass
        if len(self._self_collisions) == 1:
            return self._self_collisions[0][0].inv_mass
        if self._gathered_inv_mass is None:
            self._gathered_inv_mass = wp.zeros(self.model.particle_count, dtype=float, device=self.model.device)
        for sc, _, _, first in self._self_collisions:
            wp.copy(self._gathered_inv_mass, sc.inv_mass, dest_offset=first, count=sc.inv_mass.shape[0])
        return self._gathered_inv_mass

    def _self_contact_product(self, p: wp.array, dt: float, out: wp.array, walk: bool = False):
        """Add the self-contact elements' part of A p to `out` (`walk`: by one thread, as the CPU CG's one-thread-per-world
        iterations take it; else a thread per element of the capacity)."""
        m = self.model
        wp.launch(kct.scatter_self_contact_product, dim=1 if walk else self._self_contact_elements[0].shape[0],
                  inputs=[self.self_contact_count, *self._self_contact_elements[:3], self._self_contact_elements[4],
                          self._self_contact_elements[7], p, int(walk)],
                  outputs=[out], device=m.device)

    def _apply_self_contact_friction(self, state_in: State, dt: float):
        """Coulomb friction between the layers the self-contact elements hold (kernels/contact.py
        eval_self_contact_friction), averaged per particle, on the solved dv (after the warm start kept it)."""
        m = self.model
        dev = m.device
        self.friction_dv.zero_()
        self.friction_weight.zero_()
        wp.launch(kct.eval_self_contact_friction, dim=self._self_contact_elements[0].shape[0],
                  inputs=[self.self_contact_count, *self._self_contact_elements[:7], self._self_contact_inverse_masses(),
                          state_in.particle_qd, self.dv, float(m.cloth_friction), dt,
                          self.contact_stick_speed],
                  outputs=[self.friction_dv, self.friction_weight], device=dev)
        wp.launch(ksc.apply_velocity_changes, dim=m.particle_count, inputs=[self.dv, self.friction_dv, self.friction_weight],
                  outputs=[self.dv], device=dev)  # in place: each thread reads and writes its own particle

    def _product_args(self):
        m = self.model
        return [m.particle_spring_offsets, m.particle_spring_ids, m.particle_spring_role, m.spring_indices, m.spring_middle,
                m.particle_tri_offsets, m.particle_tri_ids, m.tri_indices, m.tri_corner_weights, m.particle_membrane_offsets,
                m.particle_membrane_ids, m.membrane_vertices]

    def _plate_product(self, p: wp.array, dt: float, out: wp.array | None = None):
        """Add the scattered elements' part of A p (plate stencils, self-contact elements) to `out` (default: set
        `plate_product` to it, zero without either); the per-particle (gather) kernels add it to theirs."""
        m = self.model
        if out is None:
            out = self.plate_product
            if not m.plate_count and self.self_contacts != "solve":
                return  # stays zero
            out.zero_()
        if m.plate_count:
            wp.launch(kf.scatter_plate_product, dim=m.plate_count,
                      inputs=[m.plate_offsets, m.plate_points, m.plate_weights, m.plate_stiffness, p, dt * dt], outputs=[out],
                      device=m.device)
        if self._self_contacts_on:
            self._self_contact_product(p, dt, out)

    def _solve_loop(self, solver: str, body, dt: float):
        """A linear solve's iterations on the device while `loop` says so: outside a capture (a taped step's solves, an
        uncaptured run) recorded once as a graph per configuration and replayed (:class:`~cloth_warp.graphs.LoopGraphs`;
        a calibration's taped cantilever steps spent 98 % of their time launching the CG's kernels one by one), on the
        CPU, unless :attr:`replay_loops` is off. The key is what the loop bakes into its launches beyond the solver's
        fixed buffers: the step, which filters and elements are on (the self-contact elements' arrays, reallocated as
        their capacity changes), the iteration cap and check interval. (A model array replaced
        rather than assigned needs :meth:`notify_model_changed`, which drops the graphs.)"""
        if not self.replay_loops or not self.model.device.is_cpu:  # (CUDA: not measured yet; eagerly, capture_while)
            device_while(self.loop, body, dt=dt)
            return
        elements = None
        if self._self_contacts_on:
            elements = tuple((a.ptr, a.shape[0]) for a in self._self_contact_elements)  # (their stiffness: in the arrays)
        key = (solver, float(dt), self._contacts_on, elements, self.max_iterations, self.check_every)
        self._loop_graphs.run(key, self.loop, body, dt=dt)

    def solve_cg(self, dt: float, warm: bool = False, restarted: bool = False, resolve: bool = False, tolerance: float | None = None,
                 velocity_tolerance: float = 0.0) -> wp.array:
        """Filtered PCG on the assembled system (`warm`: a warm start may have replaced the cold one, see
        :meth:`solve`; `restarted`: the start is a composed guess; `resolve`: the step's solve again), iterating on
        the device until the stop residual (and, near rest, within `velocity_tolerance` [m/s]: `begin_linear_solve`);
        returns the array holding dv."""
        self._begin_iterations(warm, restarted, resolve, tolerance, velocity_tolerance)
        self.product.zero_()  # then each iteration's cg_update clears it for the next
        self._solve_loop("cg", self._cg_iteration, dt)
        m = self.model
        wp.launch(ki.best_iterate_status, dim=self.worlds, inputs=[self.worlds], outputs=[self.solve_status, self.loop], device=m.device)
        wp.launch(ki.restore_best_iterate, dim=m.particle_count, inputs=[self.loop, self.dv_best, m.particle_world, self.worlds],
                  outputs=[self.dv], device=m.device)
        return self.dv

    def _cg_iteration(self, dt: float):
        """q = S A c (the element part scattered by one kernel per kind of element, kernels/implicit.py
        scatter_*_product, then the mass term), the update, the count and stop test, the next direction."""
        m = self.model
        dev = m.device
        c, q = self.search, self.product
        if self._world_ranges is not None and self.world_threads and not reductions.USE_BLOCKS:
            self._cg_iteration_worlds(dt)
            return
        self.scatter_element_product(c, dt, q)
        worlds, batched = self.worlds, self.worlds > 1
        gate = [m.particle_world, worlds, self.loop]  # batched worlds: a world that stopped keeps its dv and residual
        launch_reduction(ki.cg_product, ki.cg_product_blocks, m.particle_count,
                         inputs=[self.effective_mass, m.particle_pinned, c, self.contact_normal, self.contact_crease,
                                 int(self._contacts_on), *gate],
                         outputs=[q, self.cg_sums], device=dev, per_item=batched)
        wp.launch(ki.cg_step_size, dim=worlds, inputs=[worlds, self.loop], outputs=[self.cg_sums, self.cg_scalars, self.cg_step], device=dev)
        wp.launch(ki.cg_update, dim=m.particle_count, inputs=[self.precond, c, self.cg_step, *gate],
                  outputs=[q, self.dv, self.residual, self.preconditioned], device=dev)
        launch_reduction(ki.cg_residual_dots, ki.cg_residual_dots_blocks, m.particle_count,
                         inputs=[self.residual, self.preconditioned, *gate],
                         outputs=[self.cg_sums], device=dev, per_item=batched)
        wp.launch(ki.end_cg_iteration, dim=worlds, inputs=[self.check_every, self.max_iterations, worlds],
                  outputs=[self.cg_sums, self.cg_scalars, self.cg_step, self.solve_status, self.loop], device=dev)
        wp.launch(ki.cg_direction, dim=m.particle_count, inputs=[self.preconditioned, self.cg_step, self.loop, m.particle_world, worlds,
                                                                 self.dv],
                  outputs=[c, self.dv_best], device=dev)

    def scatter_element_product(self, p: wp.array, dt: float, out: wp.array):
        """Add the elements' part of A p (springs, bends, membranes, drag triangles, plate stencils, self-contact
        elements: one kernel per kind, kernels/implicit.py scatter_*_product) to `out`; `cg_product` adds the mass
        term and filters the rows."""
        m = self.model
        dev = m.device
        bends = m.spring_count - m.linear_spring_count
        if m.linear_spring_count:
            wp.launch(ki.scatter_spring_product, dim=m.linear_spring_count, inputs=[m.spring_ends, self.spring_compact, p],
                      outputs=[out], device=dev)
        if bends:
            wp.launch(ki.scatter_bend_product, dim=bends, inputs=[m.bend_triples, m.linear_spring_count, self.bend_vector, p, dt],
                      outputs=[out], device=dev)
        if m.membrane_count:
            wp.launch(ki.scatter_membrane_product, dim=m.membrane_count, inputs=[m.membrane_vertices, self.membrane_block, p],
                      outputs=[out], device=dev)
        if m.tri_count:
            wp.launch(ki.scatter_drag_product, dim=m.tri_count,
                      inputs=[m.tri_vertices, m.tri_corner_weights, self.drag_vector, p, dt], outputs=[out], device=dev)
        self._plate_product(p, dt, out)

    def _cg_iteration_worlds(self, dt: float):
        """:meth:`_cg_iteration` on the CPU, one thread per world (kernels/implicit.py cg_*_worlds; one world: one thread)."""
        m = self.model
        dev = m.device
        c, q = self.search, self.product
        worlds, ranges = self.worlds, self._world_ranges
        product = [ranges, worlds, self.loop, m.spring_ends, self.spring_compact, m.bend_triples, m.linear_spring_count,
                   self.bend_vector, dt, m.membrane_vertices, self.membrane_block, m.tri_vertices, m.tri_corner_weights,
                   self.drag_vector, m.plate_offsets, m.plate_points, m.plate_weights, m.plate_stiffness, dt * dt,
                   self.effective_mass, m.particle_pinned, c, self.contact_normal, self.contact_crease, int(self._contacts_on)]
        if self._self_contacts_on:  # their part between the elements' and the rows (the one-item kernels' order)
            wp.launch(ki.cg_product_worlds, dim=worlds, inputs=[*product, 1, 0], outputs=[q, self.cg_sums], device=dev)
            self._self_contact_product(c, dt, q, walk=True)
            wp.launch(ki.cg_product_worlds, dim=worlds, inputs=[*product, 0, 1], outputs=[q, self.cg_sums], device=dev)
        else:
            wp.launch(ki.cg_product_worlds, dim=worlds, inputs=[*product, 1, 1], outputs=[q, self.cg_sums], device=dev)
        wp.launch(ki.cg_step_size, dim=worlds, inputs=[worlds, self.loop], outputs=[self.cg_sums, self.cg_scalars, self.cg_step], device=dev)
        wp.launch(ki.cg_update_worlds, dim=worlds, inputs=[ranges, worlds, self.loop, self.precond, c, self.cg_step],
                  outputs=[q, self.dv, self.residual, self.preconditioned, self.cg_sums], device=dev)
        wp.launch(ki.end_cg_iteration, dim=worlds, inputs=[self.check_every, self.max_iterations, worlds],
                  outputs=[self.cg_sums, self.cg_scalars, self.cg_step, self.solve_status, self.loop], device=dev)
        wp.launch(ki.cg_direction_worlds, dim=worlds, inputs=[ranges, worlds, self.loop, self.preconditioned, self.cg_step, self.dv],
                  outputs=[c, self.dv_best], device=dev)

    def solve_jacobi(self, dt: float, warm: bool = False) -> wp.array:
        """Block Jacobi on the assembled system (`warm` as in :meth:`solve_cg`), iterating on the device; returns
        the array holding dv."""
        self._begin_iterations(warm)
        self._solve_loop("jacobi", self._jacobi_iteration, dt)
        return self.dv

    def _jacobi_iteration(self, dt: float):
        """A due residual check of dv (and the stop), then one iteration dv -> dv_alt -> dv (skipped once stopped:
        dv_alt then already equals dv)."""
        m = self.model
        dev = m.device
        common = self._product_args()
        self._plate_product(self.dv, dt)  # the check's and the iteration's plate part of A dv
        wp.launch(
            ki.eval_system_residual,
            dim=m.particle_count,
            inputs=[*common, m.particle_mass, m.particle_pin_stiffness, m.particle_pinned, self.system_block, self.bend_vector,
                    self.drag_vector, self.membrane_block, self.plate_product, self.rhs, self.dv, m.global_damping, dt, self.loop,
                    m.particle_world, self.worlds],
            outputs=[self.cg_scalars],
            device=dev,
        )
        wp.launch(ki.check_jacobi_residual, dim=self.worlds, inputs=[self.cg_scalars, self.max_iterations, self.worlds],
                  outputs=[self.solve_status, self.loop], device=dev)
        wp.launch(
            ki.jacobi_iterate,
            dim=m.particle_count,
            inputs=[*common, m.particle_pinned, self.system_block, self.bend_vector, self.drag_vector, self.membrane_block,
                    self.plate_product, self.plate_diagonal, self.precond, self.rhs, self.dv, dt, self.loop, m.particle_world, self.worlds],
            outputs=[self.dv_alt],
            device=dev,
        )
        wp.copy(self.dv, self.dv_alt)
        wp.launch(ki.end_jacobi_iteration, dim=self.worlds, inputs=[self.check_every, self.max_iterations, self.worlds],
                  outputs=[self.cg_scalars, self.loop], device=dev)

    def _begin_iterations(self, warm: bool, restarted: bool = False, resolve: bool = False, tolerance: float | None = None,
                          velocity_tolerance: float = 0.0):
        """The reference residual, the stop and whether to iterate, on the device (:func:`~cloth_warp.kernels.implicit.begin_linear_solve`)."""
        if self.worlds > 1:  # the batch's loop state, set by the worlds that iterate
            self.loop[:ki.LOOP_SIZE].zero_()
        wp.launch(ki.begin_linear_solve, dim=self.worlds,
                  inputs=[self.warm_scalars, self.previous_ready, int(warm), int(restarted), int(resolve),
                          wp.float64(self.tolerance if tolerance is None else tolerance),
                          wp.float64(self.warm_start_reduction),
                          wp.float64(WARM_START_FLOOR), self.max_iterations, self.worlds, self.release, self.motion,
                          wp.float64(velocity_tolerance)],
                  outputs=[self.cg_scalars, self.solve_status, self.loop], device=self.model.device)

    # -- the solve's report (each property reads the device; the Simulator reads the record once per frame) ----------
    @property
    def last_iterations(self) -> int:
        """Iterations of the last solve."""
        return int(self.loop.numpy()[ki.LOOP_ITERATION])

    @property
    def last_residual(self) -> float:
        """The last solve's relative residual |r_k| / |r_0| (NaN: not finite)."""
        return float(self.solve_status.numpy()[ki.STATUS_RELATIVE])

    @property
    def converged(self) -> bool:
        rel = self.last_residual
        return bool(math.isfinite(rel) and rel <= self.tolerance)

    @property
    def last_failure(self) -> str | None:
        return None if math.isfinite(self.last_residual) else "non-finite residual"

    @property
    def has_previous(self) -> bool:
        """Whether the next forward solve starts from the last one's dv."""
        return bool(self.previous_ready.numpy()[0])

    def reset_report(self):
        self.solve_record.zero_()

    def record_arrays(self) -> list:
        return [(self, "solve_record")]

    def read_report(self) -> LinearSolveReport:
        """The solves since :meth:`reset_report` (one read of a few numbers, or the frame record's copy); batched
        worlds' summed (most and worst: the largest, last residual: the last world's)."""
        rows = record_values(self.solve_record).astype(np.float64).reshape(self.worlds, ki.RECORD_SIZE)
        r = rows.sum(0)
        for k in (ki.RECORD_MOST_ITERATIONS, ki.RECORD_WORST_RESIDUAL):
            r[k] = rows[:, k].max()
        r[ki.RECORD_LAST_RESIDUAL] = rows[-1, ki.RECORD_LAST_RESIDUAL]
        first = rows[rows[:, ki.RECORD_FIRST_FAILED] > 0, ki.RECORD_FIRST_FAILED]
        r[ki.RECORD_FIRST_FAILED] = first.min() if len(first) else 0.0
        return self._report_of(r)

    def read_world_reports(self) -> list[LinearSolveReport]:
        """The solves since :meth:`reset_report`, one report per world."""
        rows = record_values(self.solve_record).astype(np.float64).reshape(self.worlds, ki.RECORD_SIZE)
        return [self._report_of(r) for r in rows]

    def _report_of(self, r: np.ndarray) -> LinearSolveReport:
        return LinearSolveReport(
            solves=int(r[ki.RECORD_SOLVES]), iterations=int(r[ki.RECORD_ITERATIONS]), most_iterations=int(r[ki.RECORD_MOST_ITERATIONS]),
            failed=int(r[ki.RECORD_FAILED]), first_failed=int(r[ki.RECORD_FIRST_FAILED]), unconverged=int(r[ki.RECORD_UNCONVERGED]),
            worst_residual=float(r[ki.RECORD_WORST_RESIDUAL]), last_residual=float(r[ki.RECORD_LAST_RESIDUAL]), tolerance=self.tolerance,
            contacts=int(r[ki.RECORD_CONTACTS]), contact_resolves=int(r[ki.RECORD_RESOLVES]),
            self_contacts=int(r[ki.RECORD_SELF_CONTACTS]))

    def carried_arrays(self) -> list:
        """The warm start, the contacts' last normal impulses (their next friction), the self-contacts' gains and the
        particles the element samples pushed."""
        return [self.dv_previous, self.previous_ready, self.contact_impulse, self.self_contact_gain, self.sample_height]

    def forget_world(self, world: int, particles: slice) -> None:
        self.dv_previous[particles].zero_()
        self.contact_impulse[particles].zero_()
        self.self_contact_gain[particles].fill_(1.0)
        self.sample_height[particles].zero_()
        self.previous_ready[world : world + 1].zero_()

    # -- checkpoints --------------------------------------------------------------------------
    def checkpoint_state(self) -> dict:
        """The warm start (the previous step's dv and whether there is one) on top of the base's state; every
        other array is rebuilt by each step's assembly before it is read."""
        out = super().checkpoint_state()
        out["has_previous"] = self.has_previous
        out["previous_ready"] = self.previous_ready.numpy().copy()  # per world (a batch's held worlds have none)
        out["dv_previous"] = self.dv_previous.numpy().copy()
        out["contact_impulse"] = self.contact_impulse.numpy().copy()
        out["self_contact_gain"] = self.self_contact_gain.numpy().copy()
        out["sample_height"] = self.sample_height.numpy().copy()
        return out

    def restore_state(self, state: dict) -> None:
        super().restore_state(state)
        dv = np.asarray(state["dv_previous"], np.float32).reshape(self.model.particle_count, 3)
        self.dv_previous.assign(dv)
        ready = np.asarray(state.get("previous_ready", []), np.int32).reshape(-1)
        if ready.shape == (self.worlds,):
            self.previous_ready.assign(ready)
        else:  # (checkpoints written before batched worlds: one flag)
            self.previous_ready.fill_(int(bool(state["has_previous"])))
        if "contact_impulse" in state:  # (checkpoints written before friction was in the solve: none)
            self.contact_impulse.assign(np.asarray(state["contact_impulse"], np.float32).reshape(self.model.particle_count))
        gain = state.get("self_contact_gain")  # (checkpoints written before the gains: none)
        self.self_contact_gain.assign(np.ones(self.model.particle_count, np.float32) if gain is None
                                      else np.asarray(gain, np.float32).reshape(self.model.particle_count))
        held = state.get("sample_height")  # (checkpoints written before the samples' holds: none)
        self.sample_height.assign(np.zeros(self.model.particle_count, np.float32) if held is None
                                  else np.asarray(held, np.float32).reshape(self.model.particle_count))

    # -- the step ----------------------------------------------------------------------------
    def solve(self, state_in: State, control: Control, dt: float) -> wp.array:
        """Assemble and solve the step's linear system; returns the array holding dv [m/s]. No host reads: a
        forward solve (warm-started from the last one's dv when there is one, decided on the device) can be
        recorded in a graph."""
        self._self_contacts_on = self._self_contacts_in_solve(state_in)
        if "solve" in (self.collider_contacts, self.self_contacts):
            self.contact_counts.zero_()
        with stage("assemble"):
            self.assemble(state_in, control, dt)
        warm = self.warm_start and not state_in.requires_grad
        in_solve = "solve" in (self.collider_contacts, self.self_contacts)
        velocity_tolerance = self.velocity_tolerance if in_solve and not state_in.requires_grad else 0.0  # (forward steps)
        if velocity_tolerance > 0.0:
            self.motion.zero_()
            wp.launch(ki.sum_motion, dim=self.model.particle_count,
                      inputs=[self.model.particle_mass, state_in.particle_qd, self.model.particle_world, self.worlds],
                      outputs=[self.motion], device=self.model.device)
        contacts = self._contacts_in_solve(state_in)
        with stage("linear_solve"):
            self._contacts_on = contacts
            if contacts:
                dv = self._solve_with_contacts(state_in, control, dt, velocity_tolerance)
            else:
                if self.collider_contacts == "solve":  # none this step (no collider, an unrolled taped step): no filter
                    self.contact_normal.zero_()
                    self.contact_crease.zero_()
                    self.contact_friction_mass.zero_()
                    self.release.zero_()
                if warm:
                    self._restart_from_previous(dt)
                dv = self._iterate(dt, warm, velocity_tolerance)
        m = self.model
        wp.launch(ki.end_linear_solve, dim=self.worlds, inputs=[self.solve_status, self.loop, wp.float64(self.tolerance), int(self.warm_start),
                                                                self.contact_counts, self.release, self.worlds],
                  outputs=[self.solve_record, self.previous_ready], device=m.device)
        if self.warm_start:  # a non-finite solve is no start for the next (nor for a retry of this step)
            wp.launch(ki.keep_velocity_change, dim=m.particle_count, inputs=[self.previous_ready, dv, m.particle_world, self.worlds],
                      outputs=[self.dv_previous],
                      device=m.device)
        if contacts and not state_in.requires_grad:  # a taped step's friction is on the tape (_taped_velocity_change)
            self._apply_contact_friction(state_in)
        if self._self_contacts_on and not state_in.requires_grad:  # (a taped step's elements: frictionless, their gains kept)
            self._apply_self_contact_friction(state_in, dt)
            if self.self_contact_stiffening:
                self._update_self_contact_gains(state_in, dv, dt)
        return dv

    def _self_contacts_in_solve(self, state_in: State) -> bool:
        """Whether this step has self-contact elements in its system: forward steps with self-collision on, and taped steps
        differentiated by the adjoint (their element set held fixed, frictionless: `_taped_self_contacts`)."""
        return bool(self._self_collisions) and (not state_in.requires_grad or self.differentiation == "adjoint")

    def _contacts_in_solve(self, state_in: State) -> bool:
        """Whether this step constrains collider contacts in its solve: forward steps, and taped steps differentiated
        by the adjoint (the unrolled reference has no filter)."""
        return (self.collider_contacts == "solve" and self.model.collider_count > 0
                and (not state_in.requires_grad or self.differentiation == "adjoint"))

    def _filtered_inverse(self) -> int:
        """Whether a contact's preconditioner block starts as the filtered block's inverse: not where the contacts'
        friction is in the solve, whose damper or slide gives it that (kernels/implicit.py filter_contact_preconditioner)."""
        return int(self.contact_friction != "solve")

    def _iterate(self, dt: float, warm: bool = False, velocity_tolerance: float = 0.0) -> wp.array:
        if self.linear_solver == LinearSolver.CG:
            return self.solve_cg(dt, warm, velocity_tolerance=velocity_tolerance)
        return self.solve_jacobi(dt, warm)

    def _restart_from_previous(self, dt: float):
        """When the last solve left a start (``previous_ready``, on the device): the guess = its dv on free
        particles and this step's z on pinned ones, and its residual in `warm_scalars`."""
        m = self.model
        wp.launch(ki.compose_warm_start, dim=m.particle_count,
                  inputs=[m.particle_pinned, self.dv_previous, self.dv, self.contact_normal, self.contact_crease, self.contact_dv,
                          self._enabled, m.particle_world, self.worlds],
                  outputs=[self.dv_alt], device=m.device)
        self._start_from_guess(dt, self.previous_ready, self.warm_scalars)

    # -- collider contacts in the solve ----------------------------------------------------------
    def _solve_with_contacts(self, state_in: State, control: Control, dt: float, velocity_tolerance: float = 0.0) -> wp.array:
        """Find the step's collider contacts, solve from the guess that meets them (zero elsewhere), release contacts that
        pull and solve again (all on the device; friction follows in :meth:`solve`); near rest, the last solve goes on
        to `velocity_tolerance` [m/s]."""
        m = self.model
        dev = m.device
        # (the contact checks read the step's start and colliders: particles the solve carries into one are admitted)
        self._contact_x0, self._contact_control = state_in.particle_q, control
        self._admit_colliders = not state_in.requires_grad
        wp.launch(kct.eval_collider_contacts, dim=m.particle_count,
                  inputs=[m.particle_pinned, m.collider_count, m.collider_shape, m.collider_size, m.collider_mesh, m.collider_deforming,
                          m.collider_thickness, m.collider_static_friction, m.collider_kinetic_friction, m.collider_mesh_max_distance,
                          control.collider_transform_start, control.collider_transform_end, state_in.particle_q, state_in.particle_qd,
                          wp.vec3(*m.gravity), dt, self.contact_margin, int(not state_in.requires_grad), self.dv_previous,
                          self.previous_ready if self.warm_start else self._disabled, m.particle_world, self.worlds, self.contact_impulse,
                          m.particle_mass, self._release_speed(dt), self.sample_height],
                  outputs=[self.contact_collider, self.contact_normal, self.contact_velocity, self.contact_dv,
                           self.contact_height, self.contact_crease, self.contact_facing, self.contact_counts], device=dev)
        wp.launch(ki.filter_contact_preconditioner, dim=m.particle_count,
                  inputs=[self.contact_normal, self.contact_crease, self._filtered_inverse()],
                  outputs=[self.precond, self.precond_free], device=dev)
        if self.contact_friction == "solve" and state_in.requires_grad:  # a taped step's friction is on the tape
            self.contact_friction_mass.zero_()
            self.contact_friction_impulse.zero_()
        elif self.contact_friction == "solve":  # (after the solve: the terms stay zero)
            wp.launch(ki.eval_contact_friction_terms, dim=m.particle_count,
                      inputs=[m.particle_mass, self.particle_seam_root, self.contact_collider, self.contact_normal,
                              self.contact_velocity, self.contact_impulse, m.collider_static_friction, m.collider_kinetic_friction,
                              state_in.particle_qd, self.precond_free, self.contact_stick_speed, self.contact_height,
                              m.collider_thickness],
                      outputs=[self.rhs, self.effective_mass, self.precond, self.contact_friction_mass,
                               self.contact_friction_impulse],
                      device=dev)
        # the start: the pinned particles' and the contacts' prescribed parts, zero elsewhere. Not the last step's dv: with
        # contacts changing every step it is no better a guess than zero (its residual above 0.1 of the zero guess's), and
        # a solve stopped at the tolerance from it keeps part of it in the slow modes, taking away implicit Euler's damping
        # there: a fold's flap on a resting pile swung at 5 Hz, 2.6 mm/s (32^2, seed 18; 0.47 mm/s from zero). The rest
        # set: 52 of 60 at rest against 41, in 25 % fewer CG iterations (docs/contacts-in-the-solve.md, "The step's start")
        wp.launch(ki.compose_warm_start, dim=m.particle_count,
                  inputs=[m.particle_pinned, self.dv_previous, self.dv, self.contact_normal, self.contact_crease, self.contact_dv,
                          self._disabled, m.particle_world, self.worlds],
                  outputs=[self.dv_alt], device=dev)
        self._start_from_guess(dt, self._enabled, self.warm_scalars)
        # the solves that decide which contacts are released or slide stop short of the tolerance; the step's last solve,
        # from where they left it, goes on to it (forward steps: a taped step's contacts are held fixed)
        loose = self.tolerance if state_in.requires_grad else max(self.tolerance, self.contact_check_tolerance)
        # (and short of the velocity tolerance: the step's last solve goes on to it, a solve more that changes no contact;
        # letting that solve's check change them too, piles of the rest set slid on for seconds: 41 of 60 at rest,
        # geometric mean 1.23 mm/s, against 43 and 0.70 changing none; docs/contacts-in-the-solve.md)
        polish = loose > self.tolerance or velocity_tolerance > 0.0
        rounds = self.contact_release_rounds
        if loose > self.tolerance:  # the last round is the last solve's, to the tolerance
            rounds = max(rounds - 1, 0)
        self.solve_cg(dt, restarted=True, tolerance=loose)
        self.release.zero_()
        self.contact_released.zero_()
        self.contact_pulled.zero_()
        self._check_release(dt, state_in.particle_qd, rounds)
        device_while(self.release, self._resolve, dt=dt, v0=state_in.particle_qd, tolerance=loose, rounds=rounds)
        if polish:  # (to the velocity tolerance only: the worlds near rest)
            self._begin_resolve(1 if loose > self.tolerance else 2, velocity_tolerance)
            self._restart(dt, velocity_tolerance=velocity_tolerance)
            if loose > self.tolerance:
                self._check_release(dt, state_in.particle_qd)
                device_while(self.release, self._resolve, dt=dt, v0=state_in.particle_qd)
            else:  # to the velocity tolerance only: the contacts' impulses, for the next step's friction; no changes
                self._check_release(dt, state_in.particle_qd, 0)
        return self.dv

    def _apply_contact_friction(self, state_in: State):
        """Coulomb friction on the solved dv of the contacts (after the warm start kept the solve's own dv: the next
        solve, which has no friction term, starts from what it would find itself)."""
        m = self.model
        if self._sewn:
            self.seam_momentum.zero_()
            self.seam_mass.zero_()
            self.seam_impulse.zero_()
            wp.launch(ki.gather_seam_friction, dim=m.particle_count,
                      inputs=[m.particle_mass, self.particle_seam_root, self.contact_collider, self.contact_normal,
                              self.contact_velocity, self.contact_impulse, state_in.particle_qd, self.dv],
                      outputs=[self.seam_momentum, self.seam_mass, self.seam_impulse], device=m.device)
        wp.launch(ki.apply_contact_friction, dim=m.particle_count,
                  inputs=[m.particle_mass, self.contact_collider, self.contact_normal, self.contact_velocity, self.contact_impulse,
                          m.collider_static_friction, m.collider_kinetic_friction, state_in.particle_qd, self.particle_seam_root,
                          self.seam_momentum, self.seam_mass, self.seam_impulse, self.contact_friction_mass,
                          self.contact_friction_impulse, self.contact_stick_speed],
                  outputs=[self.dv, self.contact_slipping], device=m.device)

    def _check_release(self, dt: float, v0: wp.array, rounds: int | None = None):
        """Each contact's solved impulse; release those that pull (:func:`~cloth_warp.kernels.implicit.eval_contact_release`);
        friction dampers the solve pushed past the static bound slide (the slip from the step's start velocities `v0`)."""
        m = self.model
        rounds = self.contact_release_rounds if rounds is None else rounds
        self._plate_product(self.dv, dt)
        wp.launch(ki.eval_contact_release, dim=m.particle_count,
                  inputs=[*self._product_args(), m.particle_mass, m.particle_pin_stiffness, m.particle_pinned, self.system_block,
                          self.bend_vector, self.drag_vector, self.membrane_block, self.plate_product, self.dv,
                          self.precond_free, m.global_damping, dt, self._release_speed(dt),
                          rounds, v0, self.contact_velocity, self.contact_height, m.collider_thickness,
                          m.collider_static_friction,
                          m.collider_kinetic_friction, self.contact_stick_speed, m.particle_world, self.worlds],
                  outputs=[self.rhs, self.effective_mass, self.contact_friction_mass, self.contact_friction_impulse, self.precond,
                           self.contact_collider, self.contact_normal, self.contact_crease, self.contact_dv, self.contact_impulse,
                           self.release, self.contact_released, self.contact_released_normal, self.contact_released_dv,
                           self.contact_pulled, int(self.pulled_friction)],
                  device=m.device)
        if self._admit_colliders and rounds > 0:  # (forward steps; the same rounds and flag)
            c = self._contact_control
            wp.launch(kct.admit_collider_contacts, dim=m.particle_count,
                      inputs=[m.particle_pinned, m.collider_count, m.collider_shape, m.collider_size, m.collider_mesh,
                              m.collider_deforming, m.collider_thickness, m.collider_mesh_max_distance,
                              c.collider_transform_start, c.collider_transform_end, self._contact_x0, v0, self.dv, dt, rounds,
                              m.particle_world, self.worlds, self.contact_released_normal, self.contact_released_dv,
                              self.contact_friction_mass],
                      outputs=[self.contact_collider, self.contact_normal, self.contact_velocity, self.contact_dv,
                               self.contact_height, self.contact_crease, self.precond, self.precond_free, self.release,
                               self.contact_released, self.contact_counts],
                      device=m.device)
        elements_change = self._self_contacts_on and rounds > 0 and self._admit_colliders  # (forward steps: a taped step's are fixed)
        if elements_change:  # (same rounds and flag as the collider contacts'; none left: no change)
            self._admit_self_contacts(dt, v0, rounds)
        if elements_change and self.contact_friction == "solve":
            el = self._self_contact_elements
            wp.launch(kct.slide_self_contacts, dim=el[0].shape[0],
                      inputs=[self.self_contact_count, *el[:4], v0, self.dv, el[6],
                              float(m.cloth_friction), dt, self.contact_stick_speed,
                              rounds,
                              m.particle_world, self.worlds],
                      outputs=[el[4], el[5], self.rhs, self.release], device=m.device)

    def _resolve(self, dt: float, v0: wp.array, tolerance: float | None = None, rounds: int | None = None):
        """Solve the step again from its last dv with the released contacts free (to `tolerance`, default the solver's),
        then check again (allowing `rounds` re-solves in the step, default `contact_release_rounds`)."""
        self._begin_resolve(0)
        self._restart(dt, tolerance)
        self._check_release(dt, v0, rounds)

    def _begin_resolve(self, polish: int, velocity_tolerance: float = 0.0):
        """Mark the worlds that solve again (:func:`~cloth_warp.kernels.implicit.begin_contact_resolve`; `polish` 2: those
        near rest for `velocity_tolerance`)."""
        wp.launch(ki.begin_contact_resolve, dim=self.worlds,
                  inputs=[self.worlds, polish, self.motion, wp.float64(self.tolerance), wp.float64(velocity_tolerance)],
                  outputs=[self.release, self.loop], device=self.model.device)

    def _restart(self, dt: float, tolerance: float | None = None, velocity_tolerance: float = 0.0):
        """Solve the step again from its last dv (the worlds begin_contact_resolve marked), a contact taken back or
        admitted in the step from its prescribed z (:func:`~cloth_warp.kernels.implicit.compose_restart`), not the free
        solve's velocity into the collider."""
        m = self.model
        wp.launch(ki.compose_restart, dim=m.particle_count,
                  inputs=[self.contact_released, self.contact_normal, self.contact_crease, self.contact_dv, self.dv, self.release,
                          m.particle_world, self.worlds],
                  outputs=[self.dv_alt], device=m.device)
        self._start_from_guess(dt, self._enabled, self.warm_scalars)
        self.cg_scalars.zero_()  # the first solve's rows (the iterations accumulate into them)
        self.solve_cg(dt, restarted=True, resolve=True, tolerance=tolerance, velocity_tolerance=velocity_tolerance)

    def _start_from_guess(self, dt: float, enabled: wp.array, scalars: wp.array):
        """Restart the iteration from the guess in dv_alt when enabled[0]: r0 = S (rhs - A guess), search direction,
        |r0|^2 into row 0 of `scalars`."""
        m = self.model
        scalars.zero_()
        self._plate_product(self.dv_alt, dt)
        wp.launch(
            ki.cg_warm_start,
            dim=m.particle_count,
            inputs=[*self._product_args(), m.particle_mass, m.particle_pin_stiffness, m.particle_pinned, self.system_block,
                    self.bend_vector, self.drag_vector, self.membrane_block, self.plate_product, self.precond, self.rhs, self.dv_alt,
                    self.contact_normal, self.contact_crease, self.contact_friction_mass, m.global_damping, dt, enabled,
                    m.particle_world, self.worlds],
            outputs=[self.dv, self.residual, self.preconditioned, self.search, scalars],
            device=m.device,
        )

    def integrate(self, state_in: State, x_out, v_out, control: Control, dt: float):
        m = self.full_model
        if state_in.requires_grad:
            if self.solves_sewn_points:  # the points' masses from the model's, on the tape
                self.model.particle_mass = point_masses(m, self.particle_point_root, requires_grad=True)
            dv = self._taped_velocity_change(state_in, control, dt)
        else:
            dv = self.solve(state_in, control, dt)
        if self.solves_sewn_points:  # each sewn point's particles take its root's dv
            out = self.scratch("dv_points", wp.vec3, state_in.requires_grad)
            wp.launch(kc.follow_point_roots, dim=m.particle_count, inputs=[self.particle_point_root, dv], outputs=[out], device=m.device)
            dv = out
        wp.launch(
            ki.integrate_implicit,
            dim=m.particle_count,
            inputs=[m.particle_pinned, state_in.particle_q, state_in.particle_qd, dv, control.pin_target, dt],
            outputs=[x_out, v_out],
            device=m.device,
        )

    # -- differentiation -----------------------------------------------------------------------
    def system_residual(self, state_in: State, control: Control, dt: float, dv: wp.array) -> wp.array:
        """r = S (b - A dv) [kg m/s] in a fresh array, element by element (differentiable)."""
        m = self.model
        dev = m.device
        x0, v0 = state_in.particle_q, state_in.particle_qd
        force = self.element_forces(x0, v0, control, key="_residual")
        r = wp.zeros(m.particle_count, dtype=wp.vec3, device=dev, requires_grad=True)
        wp.launch(ki.eval_residual_particles, dim=m.particle_count,
                  inputs=[m.particle_mass, m.particle_pin_stiffness, m.particle_pinned, force, x0, v0, dv, control.pin_target,
                          wp.vec3(*m.gravity), m.global_damping, dt], outputs=[r], device=dev)
        if m.spring_count:
            wp.launch(ki.eval_residual_springs, dim=m.spring_count,
                      inputs=[m.spring_indices, m.spring_rest_length, m.spring_stiffness, m.spring_damping, m.spring_middle,
                              m.particle_pinned, x0, v0, dv, dt], outputs=[r], device=dev)
        if m.membrane_count:
            wp.launch(ki.eval_residual_membrane, dim=m.membrane_count,
                      inputs=[m.membrane_vertices, m.membrane_rest_inverse, m.membrane_rest_area, m.membrane_stiffness, m.membrane_damping,
                              m.particle_pinned, x0, v0, dv, dt], outputs=[r], device=dev)
        if m.plate_count:
            wp.launch(ki.eval_residual_plate, dim=m.plate_count,
                      inputs=[m.plate_offsets, m.plate_points, m.plate_weights, m.plate_stiffness, m.particle_pinned, v0, dv, dt],
                      outputs=[r], device=dev)
        if m.tri_count:
            wp.launch(ki.eval_residual_drag, dim=m.tri_count,
                      inputs=[m.tri_indices, m.tri_drag, m.tri_corner_weights, m.particle_pinned, x0, dv, dt], outputs=[r], device=dev)
        return r

    def _compose(self, state_in: State, control: Control, dt: float, dv_solved: wp.array) -> wp.array:
        m = self.model
        dv = wp.zeros(m.particle_count, dtype=wp.vec3, device=m.device, requires_grad=True)
        wp.launch(ki.compose_velocity_change, dim=m.particle_count,
                  inputs=[m.particle_pinned, control.pin_target, state_in.particle_q, state_in.particle_qd, dv_solved, dt],
                  outputs=[dv], device=m.device)
        return dv

    def _taped_velocity_change(self, state_in: State, control: Control, dt: float) -> wp.array:
        m = self.model
        with paused_tape() as tape:
            if self.differentiation == "unrolled":
                self.assemble(state_in, control, dt)
                precond = wp.clone(self.precond, requires_grad=False)
                start = wp.zeros(m.particle_count, dtype=wp.vec3, device=m.device)
            else:
                start = wp.clone(self.solve(state_in, control, dt), requires_grad=False)
        elements = self._taped_self_contacts() if self.differentiation == "adjoint" and self._self_contacts_on else None
        dv = self._compose(state_in, control, dt, start)
        if self.differentiation == "unrolled":
            for _ in range(self.max_iterations):
                r = self.system_residual(state_in, control, dt, dv)
                nxt = wp.zeros_like(dv, requires_grad=True)
                wp.launch(ki.jacobi_correct, dim=m.particle_count, inputs=[m.particle_pinned, precond, dv, r], outputs=[nxt], device=m.device)
                dv = nxt
            return dv
        contacts = self._taped_contacts(state_in, control, dt) if self._contacts_in_solve(state_in) else None
        if contacts is not None:
            dv = self._taped_launch(ki.constrain_contact_velocity_change, [contacts.normal, contacts.crease, contacts.dv, dv])
        r = self._taped_residual(state_in, control, dt, dv, elements)
        if contacts is not None:
            r = self._taped_launch(ki.filter_contact_residual, [contacts.normal, contacts.crease, r])
        if tape is not None:
            normal = None if contacts is None else wp.clone(contacts.normal, requires_grad=False)
            crease = None if contacts is None else contacts.crease
            tape.record_func(lambda dv=dv, r=r: self._adjoint_solve(state_in, control, dt, dv, r, normal, crease, elements), [dv, r])
        if contacts is not None:  # friction from the contacts' impulses n . (A dv - b), evaluated after the adjoint's input
            unfiltered = self._taped_residual(state_in, control, dt, dv, elements)
            dv = self._taped_launch(ki.eval_contact_friction, [m.particle_mass, contacts.collider, contacts.height, m.collider_thickness,
                                                               contacts.normal, contacts.velocity,
                                                               m.collider_static_friction, m.collider_kinetic_friction, state_in.particle_qd,
                                                               dv, unfiltered])
        if elements is not None and float(m.cloth_friction) > 0.0:  # (after the collider contacts', as a forward step's)
            dv = self._taped_self_contact_friction(state_in, dt, dv, elements)
        return dv

    def _taped_self_contacts(self) -> tuple:
        """A taped step's self-contact elements, as its (untaped) solve held them: copies of their arrays (particles,
        weights, normals, overlaps, friction masses and impulses, zero: a taped step's elements are frictionless in the
        solve, stiffness, h^2 k) and of their count, for the residual and the friction on the tape and the adjoint's
        system (the element set held fixed)."""
        return tuple(wp.clone(a, requires_grad=False) for a in self._self_contact_elements) + (wp.clone(self.self_contact_count),)

    def _taped_self_contact_friction(self, state_in: State, dt: float, dv: wp.array, elements: tuple) -> wp.array:
        """Coulomb friction between the layers a taped step's elements hold, on the tape: as a forward step's friction
        after the solve (kernels/contact.py eval_self_contact_friction, each element's impulse from its overlap and
        solved normal velocity; averaged per particle), the elements' weights, normals and overlaps from x0
        (eval_self_contact_geometry)."""
        m = self.model
        capacity = elements[0].shape[0]
        weights, normal, overlap = (wp.zeros(capacity, dtype=t, device=m.device, requires_grad=True) for t in (wp.vec4, wp.vec3, float))
        wp.launch(kct.eval_self_contact_geometry, dim=capacity,
                  inputs=[elements[8], elements[0], elements[1], self._self_contact_distance(), state_in.particle_q],
                  outputs=[weights, normal, overlap], device=m.device)
        total = wp.zeros(m.particle_count, dtype=wp.vec3, device=m.device, requires_grad=True)
        weight = wp.zeros(m.particle_count, dtype=float, device=m.device)
        wp.launch(kct.eval_self_contact_friction, dim=capacity,
                  inputs=[elements[8], elements[0], weights, normal, overlap, *elements[4:7], self._self_contact_inverse_masses(),
                          state_in.particle_qd, dv, float(m.cloth_friction), dt, self.contact_stick_speed],
                  outputs=[total, weight], device=m.device)
        return self._taped_launch(ksc.apply_velocity_changes, [dv, total, weight])

    def _taped_residual(self, state_in: State, control: Control, dt: float, dv: wp.array, elements: tuple | None) -> wp.array:
        """r = b - A dv on the tape (`system_residual`), with a taped step's self-contact elements' part
        (kernels/contact.py eval_residual_self_contacts: their weights, distances and normals from x0)."""
        r = self.system_residual(state_in, control, dt, dv)
        if elements is not None:
            indices, weights, stiffness, count = elements[0], elements[1], elements[6], elements[8]
            wp.launch(kct.eval_residual_self_contacts, dim=indices.shape[0],
                      inputs=[count, indices, weights, stiffness, self._self_contact_distance(), state_in.particle_q,
                              state_in.particle_qd, dv, dt], outputs=[r], device=self.model.device)
        return r

    def _taped_launch(self, kernel, inputs: list) -> wp.array:
        """Launch a per-particle kernel with one vec3 output into a fresh taped array; returns it."""
        m = self.model
        out = wp.zeros(m.particle_count, dtype=wp.vec3, device=m.device, requires_grad=True)
        wp.launch(kernel, dim=m.particle_count, inputs=inputs, outputs=[out], device=m.device)
        return out

    def _taped_contacts(self, state_in: State, control: Control, dt: float) -> "TapedContacts":
        """The contact set the (untaped) solve held, less the released, and its normals, surface velocities and
        prescribed velocity changes evaluated again on the tape (kernels/contact.py eval_contact_constraints)."""
        m = self.model
        dev = m.device
        collider = wp.clone(self.contact_collider, requires_grad=False)
        height = wp.clone(self.contact_height, requires_grad=False)
        crease = wp.clone(self.contact_crease, requires_grad=False)
        facing = wp.clone(self.contact_facing, requires_grad=False)
        normal, velocity, dv = (wp.zeros(m.particle_count, dtype=wp.vec3, device=dev, requires_grad=True) for _ in range(3))
        wp.launch(kct.eval_contact_constraints, dim=m.particle_count,
                  inputs=[m.collider_shape, m.collider_size, m.collider_mesh, m.collider_deforming,
                          m.collider_mesh_max_distance, control.collider_transform_start, control.collider_transform_end, collider,
                          height, crease, facing, state_in.particle_q, state_in.particle_qd, dt],
                  outputs=[normal, velocity, dv], device=dev)
        return TapedContacts(collider, height, crease, normal, velocity, dv)

    def _adjoint_solve(self, state_in: State, control: Control, dt: float, dv: wp.array, residual: wp.array,
                       contact_normal: wp.array | None = None, contact_crease: wp.array | None = None, elements: tuple | None = None):
        """Backward of one taped step: solve S A S lam = S dL/d(dv) and add lam to dL/dr (S: the pins' and, given
        `contact_normal` and `contact_crease`, the step's collider contacts' filter; A with the step's self-contact
        `elements`, `_taped_self_contacts`, where it had them)."""
        m = self.model
        report = (wp.clone(self.loop), wp.clone(self.solve_status))  # the forward step's, kept as its report
        self._self_contacts_on = False
        self.assemble(state_in, control, dt)  # the step's blocks and preconditioner (overwritten since)
        if elements is not None:  # the step's elements into the product's arrays (a loop graph reads them there)
            el = self._self_contact_elements
            if el is None or el[0].shape[0] != elements[0].shape[0]:
                el = self._self_contact_elements = tuple(wp.empty_like(a) for a in elements[:8])
            for a, saved in zip(el, elements[:8]):
                wp.copy(a, saved)
            wp.copy(self.self_contact_count, elements[8])
            self._self_contacts_on = True
        if contact_normal is None:
            self.contact_normal.zero_()
            self.contact_crease.zero_()
        else:
            wp.copy(self.contact_normal, contact_normal)
            wp.copy(self.contact_crease, contact_crease)
            wp.launch(ki.filter_contact_preconditioner, dim=m.particle_count,
                      inputs=[self.contact_normal, self.contact_crease, self._filtered_inverse()],
                      outputs=[self.precond, self.precond_free], device=m.device)
        self._contacts_on = contact_normal is not None
        wp.copy(self.rhs, dv.grad)
        self.dv_alt.zero_()
        self._start_from_guess(dt, self._enabled, self.cg_scalars)
        lam = self._iterate(dt)
        self.adjoint_solves += 1
        self.adjoint_iterations += self.last_iterations
        wp.copy(self.loop, report[0])
        wp.copy(self.solve_status, report[1])
        wp.launch(ki.add_vectors, dim=m.particle_count, inputs=[lam], outputs=[residual.grad], device=m.device)
