"""Shared solver machinery: the step interface (integrate, then the passes of :mod:`~cloth_warp.passes`) and scratch buffers."""

from __future__ import annotations

import warp as wp

from ..kernels import forces as kf
from ..model import Control, Model, State
from ..passes import StepPass, build_passes
from ..profiling import stage
from .strain_limit import DEFAULT_SWEEPS


class SolverBase:
    """Common interface: ``step(state_in, state_out, control, dt)``.

    A solver never writes `state_in` or the model. Forward runs may swap two states; taped rollouts keep
    one State per step. Scratch arrays are reused only when nothing is taped (``state_in.requires_grad``
    is False); otherwise every intermediate gets a fresh array so no taped kernel's input is overwritten.

    A step is the integrator proper (:meth:`integrate`), then the solver's :attr:`passes`
    (:mod:`~cloth_warp.passes`: Provot strain limiting, the colliders, self-collision, built by
    :func:`~cloth_warp.passes.build_passes`), so the state a step returns is always the collision-resolved one.

    Args:
        model: the model to simulate.
        strain_limit: Provot's maximum strain of structural/shear springs (0.1 = 10 %), None to disable.
        strain_limit_iterations: the most Gauss-Seidel sweeps over all colours per step (default 128).
        strain_limit_tolerance: sweep until no structural/shear spring exceeds the limit by more than this
            strain (checked on the device: eager, captured and taped steps alike); None for exactly
            `strain_limit_iterations` sweeps. Steps left above it are counted in
            ``strain_limiter.read_report()`` (per frame in the Simulator).
        collisions: handle the model's colliders and self-collision (default True).
        collision_rounds: rounds of the passes per step when a corrector (the strain limiter) and a contact pass
            are both on (default 2): the limiter pulls over-stretched cloth back, possibly into a collider, and
            the contact passes put it back out; the last word is theirs.
    """

    name = "base"
    stability: float | None = None  # explicit integrators: the largest stable h omega_max
    kernel_modules: tuple = ()  # the integrator's Warp modules besides kernels.forces (see all_kernel_modules)
    device_loops = False  # the integrator loops on the device (wp.capture_while): CUDA capture needs conditional nodes
    # The last step's linear solve (iterative solvers override these with reads of their device state):
    # last_failure names a failure that makes the step's result meaningless ("non-finite residual"), else None.
    last_iterations = 0
    last_residual = 0.0
    converged = True
    last_failure: str | None = None

    def __init__(self, model: Model, *, strain_limit: float | None = 0.1, strain_limit_iterations: int = DEFAULT_SWEEPS,
                 strain_limit_tolerance: float | None = 1.0e-3, collisions: bool = True, collision_rounds: int = 2):
        self.model = model
        self.passes: tuple[StepPass, ...] = tuple(build_passes(
            model, strain_limit=strain_limit, strain_limit_iterations=strain_limit_iterations,
            strain_limit_tolerance=strain_limit_tolerance, collisions=collisions))
        """The stages after the integrator, in the order a step runs them."""
        if int(collision_rounds) < 1:
            raise ValueError(f"collision_rounds must be >= 1, got {collision_rounds!r}")
        self.collision_rounds = int(collision_rounds)
        self._scratch: dict = {}

    def pass_named(self, name: str) -> StepPass | None:
        """The pass of that name (``"strain_limit"``, ``"sewing"``, ``"colliders"``, ``"self_collision"``), None when off."""
        return next((p for p in self.passes if p.name == name), None)

    @property
    def strain_limiter(self):
        """The :class:`~cloth_warp.solvers.strain_limit.StrainLimiter` pass, None when strain limiting is off."""
        return self.pass_named("strain_limit")

    @property
    def capturable(self) -> bool:
        """Whether a forward step can be recorded in a graph: every pass's apply can."""
        return all(p.capturable for p in self.passes)

    def all_kernel_modules(self) -> list:
        """The Warp modules a step launches (the integrator's, its passes', the per-frame diagnostics')."""
        from ..kernels import diagnostics

        out = [kf, *self.kernel_modules, diagnostics]
        for p in self.passes:
            out += [k for k in p.kernel_modules if k not in out]
        return out

    def carried_arrays(self) -> list:
        """The device arrays a forward step carries to the next besides the state (a re-run of a frame starts from
        copies of them; the implicit solver's warm start)."""
        return []

    def forget_world(self, world: int, particles: slice) -> None:
        """Batched worlds: world `world` (its `particles`) was held after it diverged; forget what a step carries
        for it (the implicit solver's warm start), so its next solve starts afresh."""

    def reset_pass_reports(self):
        """Start new records of every pass."""
        for p in self.passes:
            p.reset_report()

    def read_pass_reports(self) -> dict:
        """Each pass's report since :meth:`reset_pass_reports`, by pass name (one read per pass, or none within a
        fetched :class:`~cloth_warp.records.FrameRecord`)."""
        return {p.name: p.read_report() for p in self.passes}

    def reset_report(self):
        """Start a new record of linear solves (solvers without one: nothing)."""

    def read_report(self):
        """The linear solves since :meth:`reset_report`, a :class:`~cloth_warp.diagnostics.LinearSolveReport`
        (None for solvers without a linear solve)."""
        return None

    def record_arrays(self) -> list:
        """(owner, attribute) of each device array :meth:`read_report` reads (the passes name their own), for the
        frame's one-read record (:class:`~cloth_warp.records.FrameRecord`)."""
        return []

    def notify_model_changed(self, flags: int) -> None:
        """Model fields changed (:class:`~cloth_warp.model.ModelFlags`): refresh what this solver and its passes
        derived from the model when they were built. Everything else is read from the model at every step."""
        for p in self.passes:
            p.notify_model_changed(flags)

    # -- checkpoints ------------------------------------------------------------------------------------------
    def checkpoint_state(self) -> dict:
        """What this solver carries from one step to the next, as numpy arrays and scalars: its name and each
        pass's state under the pass's ``checkpoint_key`` (the strain limiter and the collider pass carry nothing;
        self-collision its broad phase). Scratch buffers are written before they are read in every step."""
        out = {"name": self.name}
        for p in self.passes:
            if p.checkpoint_key:
                out.update({f"{p.checkpoint_key}.{k}": v for k, v in p.checkpoint_state().items()})
        return out

    def restore_state(self, state: dict) -> None:
        """Inverse of :meth:`checkpoint_state` (on a solver of the same kind built for the same model)."""
        if str(state.get("name", self.name)) != self.name:
            raise ValueError(f"checkpoint of a {state.get('name')} solver, this one is {self.name}")
        for p in self.passes:
            if p.checkpoint_key:
                prefix = p.checkpoint_key + "."
                p.restore_state({k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)})

    def scratch(self, key: str, dtype, requires_grad: bool, shape=None) -> wp.array:
        """A work array: reused across steps when not taped, fresh (and differentiable) when taped."""
        shape = self.model.particle_count if shape is None else shape
        if requires_grad:
            return wp.zeros(shape, dtype=dtype, device=self.model.device, requires_grad=True)
        buf = self._scratch.get(key)
        if buf is None:
            buf = wp.zeros(shape, dtype=dtype, device=self.model.device)
            self._scratch[key] = buf
        return buf

    def element_forces(self, x: wp.array, v: wp.array, control: Control, key: str = "") -> wp.array:
        """Scatter every spring's, bend triple's, membrane element's, plate stencil's and triangle's (drag) force into a per-particle
        array [N]. Every integrator reads its forces here."""
        m = self.model
        force = self.scratch("element_force" + key, wp.vec3, x.requires_grad)
        force.zero_()
        dev = m.device
        if m.linear_spring_count:
            wp.launch(kf.eval_spring_forces, dim=m.linear_spring_count,
                      inputs=[m.spring_ends, m.spring_rest_length, m.spring_stiffness, m.spring_damping, x, v],
                      outputs=[force], device=dev)
        if m.spring_count > m.linear_spring_count:
            wp.launch(kf.eval_bending_forces, dim=m.spring_count - m.linear_spring_count,
                      inputs=[m.bend_triples, m.spring_stiffness, m.linear_spring_count, x],
                      outputs=[force], device=dev)
        if m.membrane_count:
            wp.launch(kf.eval_membrane_forces, dim=m.membrane_count,
                      inputs=[m.membrane_vertices, m.membrane_rest_inverse, m.membrane_rest_area, m.membrane_stiffness,
                              m.membrane_damping, x, v], outputs=[force], device=dev)
        if m.plate_count:
            wp.launch(kf.scatter_plate_product, dim=m.plate_count,
                      inputs=[m.plate_offsets, m.plate_points, m.plate_weights, m.plate_stiffness, x, -1.0], outputs=[force], device=dev)
        if m.tri_count:
            wp.launch(kf.eval_drag_forces, dim=m.tri_count,
                      inputs=[m.tri_vertices, m.tri_drag, m.tri_corner_weights, x, v, control.wind], outputs=[force], device=dev)
        return force

    def step(self, state_in: State, state_out: State, control: Control, dt: float):
        """Advance state_in by dt [s] into state_out under control (pins' targets at the step's end)."""
        if not (dt > 0.0):
            raise ValueError(f"time step must be positive, got {dt!r}")
        passes = self.passes
        if not passes:
            with stage("integrate"):
                self.integrate(state_in, state_out.particle_q, state_out.particle_qd, control, dt)
            return
        rg = state_in.requires_grad
        x = self.scratch("x_unlimited", wp.vec3, rg)
        v = self.scratch("v_unlimited", wp.vec3, rg)
        with stage("integrate"):
            self.integrate(state_in, x, v, control, dt)
        repeat = any(p.corrector for p in passes) and not all(p.corrector for p in passes)
        rounds = self.collision_rounds if repeat else 1
        for p in passes:
            p.begin_step()
        for r in range(rounds):
            for k, p in enumerate(passes):
                last = r == rounds - 1 and k == len(passes) - 1
                out = state_out if last else State(self.scratch(f"x_{p.name}{r}", wp.vec3, rg), self.scratch(f"v_{p.name}{r}", wp.vec3, rg))
                with stage(p.name):
                    p.apply(state_in.particle_q, x, v, control, dt, out.particle_q, out.particle_qd)
                x, v = out.particle_q, out.particle_qd
        for p in passes:
            p.end_step()

    def integrate(self, state_in: State, x_out: wp.array, v_out: wp.array, control: Control, dt: float):
        """The integrator proper (no strain limiting)."""
        raise NotImplementedError
