"""Step statistics (max strain, kinetic energy, max speed, non-finite values, work done by gravity) and the
strain limiter's report."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .kernels import diagnostics as kd
from .model import Model, State


@dataclass(frozen=True)
class StepStats:
    """Statistics of one state.

    Attributes:
        max_strain: max over structural/shear springs of l / L - 1 (0 if none is stretched).
        kinetic_energy: of the free (unpinned) particles [J].
        max_speed: of the free particles [m/s].
        nonfinite: number of particles with a NaN/Inf position or velocity.
        gravity_work: the work gravity has done on the free particles since the model's initial
            positions, sum m g . (x - x_initial) [J] (positive when the cloth has come down; the divergence
            bounds use it, see :class:`~cloth_warp.solvers.adaptive.DivergenceBounds`).
    """

    max_strain: float
    kinetic_energy: float
    max_speed: float
    nonfinite: int
    gravity_work: float = 0.0

    @property
    def finite(self) -> bool:
        return self.nonfinite == 0


class Diagnostics:
    """Measures :class:`StepStats` with one kernel launch and one 20-byte read."""

    def __init__(self, model: Model):
        self.model = model
        self.stats = wp.zeros(5, dtype=float, device=model.device)
        mass = model.particle_mass.numpy().astype(np.float64)
        free = model.particle_pinned.numpy() == 0
        self.total_mass_free = float(mass[free].sum())
        # gravity's potential is measured from the free particles' initial centre of mass (small float32 sums),
        # and its initial value in float64 is subtracted on the host
        x0 = model.particle_q.numpy().astype(np.float64)
        g = np.asarray(model.gravity, np.float64)
        origin = (mass[free, None] * x0[free]).sum(0) / self.total_mass_free if self.total_mass_free > 0.0 else np.zeros(3)
        self._origin = wp.vec3(*origin.astype(np.float32))
        self._gravity = wp.vec3(*g.astype(np.float32))
        origin32 = origin.astype(np.float32).astype(np.float64)
        self._potential0 = float((mass[free] * ((x0[free] - origin32) @ g)).sum()) if self.total_mass_free > 0.0 else 0.0

    def measure(self, state: State) -> StepStats:
        m = self.model
        self.stats.zero_()
        wp.launch(
            kd.eval_step_statistics,
            dim=m.particle_count,
            inputs=[m.particle_spring_offsets, m.particle_spring_ids, m.particle_spring_role, m.spring_indices, m.spring_rest_length,
                    m.spring_limited, m.particle_mass, m.particle_pinned, state.particle_q, state.particle_qd, self._gravity,
                    self._origin],
            outputs=[self.stats],
            device=m.device,
        )
        s = self.stats.numpy()
        return StepStats(float(s[0]), float(s[1]), float(s[2]), int(s[3]), float(s[4]) - self._potential0)


@dataclass(frozen=True)
class StrainLimitReport:
    """What the strain limiter left over some steps (a frame, or a whole run when reports are added up).

    Excesses are strains above the limit, l / L - 1 - max_strain, after the limiter's last pass of a step
    (before any collision pass that follows it), the worst over the steps, floored at 0.

    Attributes:
        max_strain: the limit (0.1 = 10 %); tolerance: the excess above which a step counts as missed.
        max_sweeps: the cap of sweeps per step (``strain_limit_iterations``).
        structural_excess, shear_excess: worst excess left on structural / shear springs.
        initial_excess: worst excess of the integrator's output, before limiting.
        steps: steps limited; missed_steps: of those, steps that ended above the tolerance.
        sweeps: sweeps run, summed over the steps; most_sweeps: the most in one step.
        frames, missed_frames: frames covered, and frames with a missed step.
    """

    max_strain: float
    tolerance: float
    max_sweeps: int
    structural_excess: float
    shear_excess: float
    initial_excess: float
    steps: int
    missed_steps: int
    sweeps: int
    most_sweeps: int
    frames: int = 1
    missed_frames: int = 0

    @property
    def held(self) -> bool:
        """Every step met the tolerance."""
        return self.missed_steps == 0

    @property
    def excess(self) -> float:
        return max(self.structural_excess, self.shear_excess)

    @property
    def mean_sweeps(self) -> float:
        return self.sweeps / self.steps if self.steps else 0.0

    def __add__(self, other: StrainLimitReport) -> StrainLimitReport:
        """The report of both stretches of steps."""
        return StrainLimitReport(
            self.max_strain, self.tolerance, self.max_sweeps, max(self.structural_excess, other.structural_excess),
            max(self.shear_excess, other.shear_excess), max(self.initial_excess, other.initial_excess), self.steps + other.steps,
            self.missed_steps + other.missed_steps, self.sweeps + other.sweeps, max(self.most_sweeps, other.most_sweeps),
            self.frames + other.frames, self.missed_frames + other.missed_frames)
