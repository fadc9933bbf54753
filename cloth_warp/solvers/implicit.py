"""Implicit Euler after Baraff & Witkin (1998), solved matrix-free by filtered PCG or block Jacobi."""

from __future__ import annotations

import enum
import math

import numpy as np
import warp as wp

from ..autodiff import paused_tape
from ..kernels import forces as kf
from ..kernels import implicit as ki
from ..model import Control, Model, State
from .base import SolverBase
from .strain_limit import DEFAULT_SWEEPS

WARM_START_FLOOR = 1.0e-6  # the smallest relative residual a warm-started float32 solve is asked for


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
        check_every: iterations between convergence checks (each check reads one number on the host).
        warm_start: start each solve from the previous step's dv (forward runs). The tolerance stays
            relative to the zero-guess residual |S (b - A z)|, so a good start saves iterations.
        warm_start_reduction: a warm-started solve also cuts its starting residual by this factor (down to
            a relative 1e-6, float32's floor) before it stops. Stopping as soon as the previous dv is within
            `tolerance` carries that solve's error from step to step, and the delay sustains a ~6 Hz limit
            cycle of cloth resting on colliders (~30 mm/s at the free edges of a drape, measured; 0.1 mm/s
            with 0.01).
        strain_limit, strain_limit_iterations, collisions: see :class:`~cloth_warp.solvers.base.SolverBase`.

    Differentiation (taped steps, ``state_in.requires_grad``): with ``differentiation="adjoint"`` the solve
    runs outside the tape; the tape holds dv and the residual r = S (b - A dv), evaluated element by element
    from x0, v0 and every model parameter, and a backward hook solves the transposed system
    S A S lam = S dL/d(dv) (A is symmetric: the same CG or Jacobi solve, to the same tolerance) and seeds
    dL/dr = lam. Gradients are then exact up to the solve tolerance; set a tight `tolerance` (1e-6) for
    gradient checks. ``differentiation="unrolled"`` instead tapes `max_iterations` block-Jacobi
    iterations dv <- dv + P r (the reference the adjoint is tested against; memory grows with the
    iterations). Taped steps never warm-start, so a re-run (checkpointing) reproduces the forward run.
    """

    name = "implicit_euler"

    def __init__(
        self,
        model: Model,
        *,
        linear_solver: LinearSolver | str = LinearSolver.CG,
        max_iterations: int = 1000,
        tolerance: float = 1.0e-3,
        check_every: int = 4,
        warm_start: bool = True,
        warm_start_reduction: float = 0.01,
        strain_limit: float | None = 0.1,
        strain_limit_iterations: int = DEFAULT_SWEEPS,
        strain_limit_tolerance: float | None = 1.0e-3,
        collisions: bool = True,
        collision_rounds: int = 2,
        differentiation: str = "adjoint",
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
        # Backward-pass report: adjoint solves run and their iterations (summed).
        self.adjoint_solves = 0
        self.adjoint_iterations = 0
        from ..validation import LIMITS, check_number

        max_iterations = check_number("max_iterations", max_iterations, LIMITS["iterations"])
        tolerance = check_number("tolerance", tolerance, LIMITS["tolerance"])
        self.max_iterations = int(max_iterations)
        self.tolerance = float(tolerance)
        self.check_every = max(1, int(check_every))
        self.warm_start = bool(warm_start)
        if not (0.0 < warm_start_reduction <= 1.0):
            raise ValueError(f"warm_start_reduction must be in (0, 1], got {warm_start_reduction!r}")
        self.warm_start_reduction = float(warm_start_reduction)
        self._has_previous = False
        self._reference_rr = 0.0
        n, s, t = model.particle_count, max(model.spring_count, 1), max(model.tri_count, 1)
        dev = model.device
        self.stiffness_block = wp.zeros(s, dtype=wp.mat33, device=dev)
        self.system_block = wp.zeros(s, dtype=wp.mat33, device=dev)
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
        self.dv_previous = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.residual = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.preconditioned = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.search = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.product = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.cg_scalars = wp.zeros((self.max_iterations + 2, 3), dtype=wp.float64, device=dev)

    def notify_model_changed(self, flags: int) -> None:
        """Model fields changed: besides the passes (:meth:`SolverBase.notify_model_changed`), the previous step's
        velocity change no longer predicts this one, so the next solve starts cold."""
        super().notify_model_changed(flags)
        self._has_previous = False

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
                outputs=[self.stiffness_block, self.system_block, self.bend_vector],
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
        if m.membrane_count or m.plate_count:
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
        wp.launch(
            ki.eval_implicit_system,
            dim=m.particle_count,
            inputs=[*self._product_args()[:9], m.particle_mass, m.particle_pin_stiffness, m.particle_pinned, force, self.stiffness_block,
                    self.system_block, self.bend_vector, self.drag_vector, self.membrane_kv, self.membrane_diag, self.membrane_az,
                    state_in.particle_q, state_in.particle_qd,
                    control.pin_target, wp.vec3(*m.gravity), m.global_damping, dt],
            outputs=[self.rhs, self.precond, self.dv, self.residual, self.preconditioned, self.search, self.cg_scalars],
            device=dev,
        )

    def _product_args(self):
        m = self.model
        return [m.particle_spring_offsets, m.particle_spring_ids, m.particle_spring_role, m.spring_indices, m.spring_middle,
                m.particle_tri_offsets, m.particle_tri_ids, m.tri_indices, m.tri_corner_weights, m.particle_membrane_offsets,
                m.particle_membrane_ids, m.membrane_vertices]

    def _plate_product(self, p: wp.array, dt: float, out: wp.array | None = None):
        """Add the plate stencils' part of A p to `out` (default: set `plate_product` to it, zero without stencils)."""
        m = self.model
        if out is None:
            out = self.plate_product
            if not m.plate_count:
                return  # stays zero
            out.zero_()
        if m.plate_count:
            wp.launch(kf.scatter_plate_product, dim=m.plate_count,
                      inputs=[m.plate_offsets, m.plate_points, m.plate_weights, m.plate_stiffness, p, dt * dt], outputs=[out],
                      device=m.device)

    def solve_cg(self, dt: float, warm: bool = False) -> wp.array:
        """Filtered PCG on the assembled system (`warm`: started from the previous step's dv); returns the
        array holding dv."""
        m = self.model
        dev = m.device
        scal = self.cg_scalars.numpy() if dev.is_cpu else None
        rr0 = self._reference_rr  # |S (b - A z)|^2: the zero-guess residual, also after a warm start
        iterations = 0
        rel = self._start_residual(scal)
        stop = self._stop_residual(rel, warm)
        if rr0 > 1e-300 and rel > stop:
            bends = m.spring_count - m.linear_spring_count
            elements = m.linear_spring_count + bends + m.membrane_count + m.tri_count
            for k in range(self.max_iterations):
                self.product.zero_()
                wp.launch(
                    ki.scatter_system_product,
                    dim=elements,
                    inputs=[m.spring_ends, m.linear_spring_count, m.bend_triples, bends, m.membrane_vertices, m.membrane_count,
                            m.tri_vertices, m.tri_corner_weights, self.system_block, self.bend_vector, self.membrane_block,
                            self.drag_vector, self.search, dt],
                    outputs=[self.product],
                    device=dev,
                )
                self._plate_product(self.search, dt, self.product)
                wp.launch(
                    ki.cg_product,
                    dim=m.particle_count,
                    inputs=[m.particle_mass, m.particle_pin_stiffness, m.particle_pinned, self.search, m.global_damping, dt, k],
                    outputs=[self.product, self.cg_scalars],
                    device=dev,
                )
                wp.launch(
                    ki.cg_update,
                    dim=m.particle_count,
                    inputs=[self.precond, self.search, self.product, k],
                    outputs=[self.dv, self.residual, self.preconditioned, self.cg_scalars],
                    device=dev,
                )
                iterations = k + 1
                if iterations % self.check_every == 0 or iterations == self.max_iterations:
                    rel = math.sqrt(max(self._read(scal, iterations), 0.0) / rr0)
                    if rel <= stop or not math.isfinite(rel):
                        break
                wp.launch(ki.cg_direction, dim=m.particle_count, inputs=[self.preconditioned, self.cg_scalars, k], outputs=[self.search], device=dev)
        self._report(iterations, rel)
        return self.dv

    def solve_jacobi(self, dt: float, warm: bool = False) -> wp.array:
        """Block Jacobi on the assembled system (`warm` as in :meth:`solve_cg`); returns the array holding dv."""
        m = self.model
        dev = m.device
        scal = self.cg_scalars.numpy() if dev.is_cpu else None
        rr0 = self._reference_rr
        src, dst = self.dv, self.dv_alt
        iterations = 0
        rel = self._start_residual(scal)
        stop = self._stop_residual(rel, warm)
        if rr0 > 1e-300 and rel > stop:
            common = self._product_args()
            product_of_src = False  # plate_product holds A_plate src (the residual check leaves it so)
            for k in range(self.max_iterations):
                if not product_of_src:
                    self._plate_product(src, dt)
                wp.launch(
                    ki.jacobi_iterate,
                    dim=m.particle_count,
                    inputs=[*common, m.particle_pinned, self.system_block, self.bend_vector, self.drag_vector, self.membrane_block,
                            self.plate_product, self.plate_diagonal, self.precond, self.rhs, src, dt],
                    outputs=[dst],
                    device=dev,
                )
                src, dst = dst, src
                product_of_src = False
                iterations = k + 1
                if iterations % self.check_every == 0 or iterations == self.max_iterations:
                    slot = 1  # row 0 keeps |r_0|^2
                    self.cg_scalars[slot : slot + 1].zero_()
                    self._plate_product(src, dt)
                    product_of_src = True
                    wp.launch(
                        ki.eval_system_residual,
                        dim=m.particle_count,
                        inputs=[*common, m.particle_mass, m.particle_pin_stiffness, m.particle_pinned, self.system_block,
                                self.bend_vector, self.drag_vector, self.membrane_block, self.plate_product, self.rhs, src,
                                m.global_damping, dt, slot],
                        outputs=[self.cg_scalars],
                        device=dev,
                    )
                    rel = math.sqrt(max(self._read(scal, slot), 0.0) / rr0)
                    if rel <= stop or not math.isfinite(rel):
                        break
        self._report(iterations, rel)
        return src

    def _start_residual(self, scal) -> float:
        """The relative residual of the starting guess; NaN when the system is not finite (a NaN or inf
        right-hand side, matrix or guess): the solve then does not iterate and reports a non-finite residual
        (``last_failure``)."""
        rr0 = self._reference_rr
        start = self._read(scal, 0)
        if not (math.isfinite(rr0) and math.isfinite(start)):
            return math.nan
        return math.sqrt(max(start, 0.0) / rr0) if rr0 > 1e-300 else 0.0

    def _stop_residual(self, rel_start: float, warm: bool) -> float:
        """The relative residual at which this solve stops (see `warm_start_reduction`)."""
        if not warm:
            return self.tolerance
        return min(self.tolerance, max(self.warm_start_reduction * rel_start, WARM_START_FLOOR))

    def _read(self, scal, row: int) -> float:
        if scal is not None:  # CPU: a zero-copy view, no transfer
            return float(scal[row, 2])
        return float(self.cg_scalars[row : row + 1].numpy()[0, 2])

    def _report(self, iterations: int, rel: float):
        self.last_iterations = iterations
        self.last_residual = rel
        self.converged = bool(math.isfinite(rel) and rel <= self.tolerance)
        self.last_failure = None if math.isfinite(rel) else "non-finite residual"

    # -- checkpoints --------------------------------------------------------------------------
    def checkpoint_state(self) -> dict:
        """The warm start (the previous step's dv and whether there is one) on top of the base's state; every
        other array is rebuilt by each step's assembly before it is read."""
        out = super().checkpoint_state()
        out["has_previous"] = bool(self._has_previous)
        out["dv_previous"] = self.dv_previous.numpy().copy()
        return out

    def restore_state(self, state: dict) -> None:
        super().restore_state(state)
        dv = np.asarray(state["dv_previous"], np.float32).reshape(self.model.particle_count, 3)
        self.dv_previous.assign(dv)
        self._has_previous = bool(state["has_previous"])

    # -- the step ----------------------------------------------------------------------------
    def solve(self, state_in: State, control: Control, dt: float) -> wp.array:
        """Assemble and solve the step's linear system; returns the array holding dv [m/s]."""
        self.assemble(state_in, control, dt)
        self._reference_rr = self._read(self.cg_scalars.numpy() if self.model.device.is_cpu else None, 0)
        warm = self.warm_start and self._has_previous and not state_in.requires_grad
        if warm:
            self._restart_from_previous(dt)
        dv = self._iterate(dt, warm)
        if self.warm_start:  # a non-finite solve is no start for the next (nor for a retry of this step)
            if self.last_failure is None:
                wp.copy(self.dv_previous, dv)
            self._has_previous = self.last_failure is None
        return dv

    def _iterate(self, dt: float, warm: bool = False) -> wp.array:
        return self.solve_cg(dt, warm) if self.linear_solver == LinearSolver.CG else self.solve_jacobi(dt, warm)

    def _restart_from_previous(self, dt: float):
        m = self.model
        wp.launch(ki.compose_warm_start, dim=m.particle_count, inputs=[m.particle_pinned, self.dv_previous, self.dv],
                  outputs=[self.dv_alt], device=m.device)
        self._start_from_guess(dt)

    def _start_from_guess(self, dt: float):
        """Restart the iteration from the guess in dv_alt: r0 = S (rhs - A guess), search direction, |r0|^2."""
        m = self.model
        self.cg_scalars.zero_()
        self._plate_product(self.dv_alt, dt)
        wp.launch(
            ki.cg_warm_start,
            dim=m.particle_count,
            inputs=[*self._product_args(), m.particle_mass, m.particle_pin_stiffness, m.particle_pinned, self.system_block,
                    self.bend_vector, self.drag_vector, self.membrane_block, self.plate_product, self.precond, self.rhs, self.dv_alt,
                    m.global_damping, dt],
            outputs=[self.dv, self.residual, self.preconditioned, self.search, self.cg_scalars],
            device=m.device,
        )

    def integrate(self, state_in: State, x_out, v_out, control: Control, dt: float):
        m = self.model
        if state_in.requires_grad:
            dv = self._taped_velocity_change(state_in, control, dt)
        else:
            dv = self.solve(state_in, control, dt)
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
        dv = self._compose(state_in, control, dt, start)
        if self.differentiation == "unrolled":
            for _ in range(self.max_iterations):
                r = self.system_residual(state_in, control, dt, dv)
                nxt = wp.zeros_like(dv, requires_grad=True)
                wp.launch(ki.jacobi_correct, dim=m.particle_count, inputs=[m.particle_pinned, precond, dv, r], outputs=[nxt], device=m.device)
                dv = nxt
            return dv
        r = self.system_residual(state_in, control, dt, dv)
        if tape is not None:
            tape.record_func(lambda: self._adjoint_solve(state_in, control, dt, dv, r), [dv, r])
        return dv

    def _adjoint_solve(self, state_in: State, control: Control, dt: float, dv: wp.array, residual: wp.array):
        """Backward of one taped step: solve S A S lam = S dL/d(dv) and add lam to dL/dr."""
        m = self.model
        report = (self.last_iterations, self.last_residual, self.converged, self.last_failure)
        self.assemble(state_in, control, dt)  # the step's blocks and preconditioner (overwritten since)
        wp.copy(self.rhs, dv.grad)
        self.dv_alt.zero_()
        self._start_from_guess(dt)
        self._reference_rr = self._read(self.cg_scalars.numpy() if m.device.is_cpu else None, 0)
        lam = self._iterate(dt)
        self.adjoint_solves += 1
        self.adjoint_iterations += self.last_iterations
        self.last_iterations, self.last_residual, self.converged, self.last_failure = report
        wp.launch(ki.add_vectors, dim=m.particle_count, inputs=[lam], outputs=[residual.grad], device=m.device)
