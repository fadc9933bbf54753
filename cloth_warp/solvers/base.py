"""Shared solver machinery: the step interface, scratch buffers and Provot strain limiting."""

from __future__ import annotations

import warp as wp

from ..kernels import constraints as kc
from ..model import Control, Model, State


class StrainLimiter:
    """Provot (1995) deformation constraints: no structural/shear spring longer than (1 + max_strain) L.

    Each pass visits the springs colour by colour (no two springs of a colour share a particle), moving
    the endpoints of over-stretched springs toward each other by the excess, split by inverse mass
    (all of it to the free end when the other is pinned). Velocities are then corrected by the position
    change over dt (Provot's "inverse dynamics"), so the limiter adds no momentum: the centre of mass
    of a free sheet moves as without it.

    Gradients flow through the active (clamped) constraints only: the clamp is piecewise.
    """

    def __init__(self, model: Model, max_strain: float = 0.1, iterations: int = 4):
        if not (max_strain > 0.0):
            raise ValueError(f"max_strain must be positive (0.1 = 10 %), got {max_strain!r}")
        if iterations < 1:
            raise ValueError(f"strain-limit iterations must be >= 1, got {iterations!r}")
        self.model = model
        self.max_strain = float(max_strain)
        self.iterations = int(iterations)

    @property
    def active(self) -> bool:
        return self.model.strain_limit_color_count > 0

    def apply(self, solver: SolverBase, x_in: wp.array, v_in: wp.array, state_out: State, dt: float):
        """Limit x_in into state_out.particle_q and correct v_in into state_out.particle_qd."""
        m = self.model
        colors = m.strain_limit_color_count
        passes = self.iterations * colors
        rg = x_in.requires_grad
        prev = x_in
        for k in range(passes):
            dst = state_out.particle_q if k == passes - 1 else solver.scratch(f"strain_limit{k % 2}", wp.vec3, rg)
            wp.launch(
                kc.apply_strain_limit_color,
                dim=m.particle_count,
                inputs=[m.strain_limit_colors, m.spring_indices, m.spring_rest_length, m.particle_mass, m.particle_pinned, prev, k % colors, self.max_strain],
                outputs=[dst],
                device=m.device,
            )
            prev = dst
        wp.launch(
            kc.correct_velocity,
            dim=m.particle_count,
            inputs=[x_in, state_out.particle_q, v_in, dt],
            outputs=[state_out.particle_qd],
            device=m.device,
        )


class SolverBase:
    """Common interface: ``step(state_in, state_out, control, dt)``.

    A solver never writes `state_in` or the model. Forward runs may swap two states; taped rollouts keep
    one State per step. Scratch arrays are reused only when nothing is taped (``state_in.requires_grad``
    is False); otherwise every intermediate gets a fresh array so no taped kernel's input is overwritten.

    Args:
        model: the model to simulate.
        strain_limit: Provot's maximum strain of structural/shear springs (0.1 = 10 %), None to disable.
        strain_limit_iterations: Gauss-Seidel passes over all colours per step.
    """

    name = "base"

    def __init__(self, model: Model, *, strain_limit: float | None = 0.1, strain_limit_iterations: int = 4):
        self.model = model
        self.strain_limiter = StrainLimiter(model, strain_limit, strain_limit_iterations) if strain_limit else None
        self._scratch: dict = {}
        # Per-step solver report (iterative solvers fill these).
        self.last_iterations = 0
        self.last_residual = 0.0
        self.converged = True

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

    def step(self, state_in: State, state_out: State, control: Control, dt: float):
        """Advance state_in by dt [s] into state_out under control (pins' targets at the step's end)."""
        if not (dt > 0.0):
            raise ValueError(f"time step must be positive, got {dt!r}")
        limiter = self.strain_limiter
        if limiter is None or not limiter.active:
            self.integrate(state_in, state_out.particle_q, state_out.particle_qd, control, dt)
            return
        rg = state_in.requires_grad
        x_free = self.scratch("x_unlimited", wp.vec3, rg)
        v_free = self.scratch("v_unlimited", wp.vec3, rg)
        self.integrate(state_in, x_free, v_free, control, dt)
        limiter.apply(self, x_free, v_free, state_out, dt)

    def integrate(self, state_in: State, x_out: wp.array, v_out: wp.array, control: Control, dt: float):
        """The integrator proper (no strain limiting)."""
        raise NotImplementedError
