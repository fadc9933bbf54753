"""Explicit integrators: forward Euler, symplectic Euler, explicit midpoint and classical RK4.

All evaluate the same forces (`SolverBase.element_forces`): springs (linear and Choi-Ko buckling),
triangle membrane elements, gravity, air drag with wind, soft pins and global damping. Hard-pinned particles
move in a straight line onto Control.pin_target during the step.

Stability (physics.md 1(h)): explicit and symplectic Euler and midpoint need h omega_max < 2, RK4
h omega_max < 2.83, with omega_max^2 <= max_i (2 sum_j k_ij + sum of the membrane elements' block norms) / m_i
(`cloth_warp.solvers.adaptive.stable_dt`). Differentiable under wp.Tape
(taped rollouts keep one State per step).
"""

from __future__ import annotations

import warp as wp

from ..kernels import forces as kf
from ..model import Control, State
from .base import SolverBase


class _EulerBase(SolverBase):
    symplectic = 0
    stability = 2.0  # h omega_max below this (physics.md 1(h))

    def integrate(self, state_in: State, x_out, v_out, control: Control, dt: float):
        m = self.model
        force = self.element_forces(state_in.particle_q, state_in.particle_qd, control)
        wp.launch(
            kf.integrate_euler,
            dim=m.particle_count,
            inputs=[m.particle_mass, m.particle_pin_stiffness, m.particle_pinned, force, state_in.particle_q, state_in.particle_qd,
                    control.pin_target, wp.vec3(*m.gravity), m.global_damping, dt, self.symplectic],
            outputs=[x_out, v_out],
            device=m.device,
        )


class SolverExplicitEuler(_EulerBase):
    """Forward Euler (Provot 1995): x1 = x0 + h v0, v1 = v0 + h a(x0, v0). Energy grows by (1 + z^2) per step."""

    name = "explicit_euler"
    symplectic = 0


class SolverSymplecticEuler(_EulerBase):
    """Semi-implicit (symplectic) Euler: v1 = v0 + h a(x0, v0), x1 = x0 + h v1. Bounded energy for h omega < 2."""

    name = "symplectic_euler"
    symplectic = 1


class _RungeKutta(SolverBase):
    # (next-point coefficient of each stage as a fraction of h), final weights
    stage_coeffs: tuple = ()
    weights: tuple = ()

    def integrate(self, state_in: State, x_out, v_out, control: Control, dt: float):
        m = self.model
        rg = state_in.requires_grad
        x0, v0 = state_in.particle_q, state_in.particle_qd
        xe, ve = x0, v0
        ks = []
        common = [control.pin_target, wp.vec3(*m.gravity), m.global_damping, dt]
        for s, c in enumerate(self.stage_coeffs):
            force = self.element_forces(xe, ve, control, key=str(s))
            kx = self.scratch(f"rk_kx{s}", wp.vec3, rg)
            kv = self.scratch(f"rk_kv{s}", wp.vec3, rg)
            xn = self.scratch(f"rk_x{s}", wp.vec3, rg)
            vn = self.scratch(f"rk_v{s}", wp.vec3, rg)
            wp.launch(
                kf.eval_rk_stage,
                dim=m.particle_count,
                inputs=[m.particle_mass, m.particle_pin_stiffness, m.particle_pinned, force, x0, v0, xe, ve, *common, c * dt],
                outputs=[kx, kv, xn, vn],
                device=m.device,
            )
            ks.append((kx, kv))
            xe, ve = xn, vn
        while len(ks) < 4:
            ks.append(ks[-1])
        w = list(self.weights) + [0.0] * (4 - len(self.weights))
        wp.launch(
            kf.combine_rk_stages,
            dim=m.particle_count,
            inputs=[m.particle_pinned, x0, v0, ks[0][0], ks[0][1], ks[1][0], ks[1][1], ks[2][0], ks[2][1],
                    ks[3][0], ks[3][1], control.pin_target, *w, dt],
            outputs=[x_out, v_out],
            device=m.device,
        )


class SolverMidpoint(_RungeKutta):
    """Explicit midpoint (RK2): y1 = y0 + h F(y0 + h/2 F(y0)). Energy factor 1 + z^4/4 per step."""

    name = "midpoint"
    stability = 2.0
    stage_coeffs = (0.5, 0.0)
    weights = (0.0, 1.0)


class SolverRK4(_RungeKutta):
    """Classical fourth-order Runge-Kutta. Stable on the imaginary axis for h omega <= 2.83, slightly dissipative."""

    name = "rk4"
    stability = 2.83
    stage_coeffs = (0.5, 0.5, 1.0, 0.0)
    weights = (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)
