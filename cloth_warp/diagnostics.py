"""Step statistics: max strain, kinetic energy, max speed, non-finite values."""

from __future__ import annotations

from dataclasses import dataclass

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
    """

    max_strain: float
    kinetic_energy: float
    max_speed: float
    nonfinite: int

    @property
    def finite(self) -> bool:
        return self.nonfinite == 0


class Diagnostics:
    """Measures :class:`StepStats` with one kernel launch and one 16-byte read."""

    def __init__(self, model: Model):
        self.model = model
        self.stats = wp.zeros(4, dtype=float, device=model.device)
        self.total_mass_free = float(model.particle_mass.numpy()[model.particle_pinned.numpy() == 0].sum())

    def measure(self, state: State) -> StepStats:
        m = self.model
        self.stats.zero_()
        wp.launch(
            kd.eval_step_statistics,
            dim=m.particle_count,
            inputs=[m.particle_spring_offsets, m.particle_spring_ids, m.particle_spring_role, m.spring_indices, m.spring_rest_length,
                    m.spring_limited, m.particle_mass, m.particle_pinned, state.particle_q, state.particle_qd],
            outputs=[self.stats],
            device=m.device,
        )
        s = self.stats.numpy()
        return StepStats(float(s[0]), float(s[1]), float(s[2]), int(s[3]))
