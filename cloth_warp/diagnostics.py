"""Step statistics (max strain, kinetic energy, max speed, non-finite values, work done by gravity), the reports
of the linear solve and of each pass, and the frame's report that gathers them."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Mapping

import numpy as np
import warp as wp

from .kernels import diagnostics as kd
from .model import Model, State
from .records import record_values


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


def combined_stats(per_world: list[StepStats]) -> StepStats:
    """The statistics of several worlds together: the largest maxima, the summed sums."""
    return StepStats(max(s.max_strain for s in per_world), sum(s.kinetic_energy for s in per_world),
                     max(s.max_speed for s in per_world), sum(s.nonfinite for s in per_world),
                     sum(s.gravity_work for s in per_world))


class Diagnostics:
    """Measures :class:`StepStats` with one kernel launch and one small read (per world in a batch:
    :meth:`read_worlds`)."""

    def __init__(self, model: Model):
        self.model = model
        self.worlds = worlds = int(model.world_count)
        self.stats = wp.zeros(worlds * (kd.STAT_MAXIMA + kd.STAT_SUMS), dtype=float, device=model.device)
        mass = model.particle_mass.numpy().astype(np.float64)
        free = model.particle_pinned.numpy() == 0
        self.total_mass_free = float(mass[free].sum())
        # gravity's potential is measured from the free particles' initial centre of mass (small float32 sums),
        # and its initial value in float64 (per world) is subtracted on the host
        x0 = model.particle_q.numpy().astype(np.float64)
        g = np.asarray(model.gravity, np.float64)
        origin = (mass[free, None] * x0[free]).sum(0) / self.total_mass_free if self.total_mass_free > 0.0 else np.zeros(3)
        self._origin = wp.vec3(*origin.astype(np.float32))
        self._gravity = wp.vec3(*g.astype(np.float32))
        origin32 = origin.astype(np.float32).astype(np.float64)
        potential = np.where(free, mass * ((x0 - origin32) @ g), 0.0)
        world = model.particle_world.numpy() if worlds > 1 else np.zeros(len(mass), np.int32)
        self._potential0 = np.bincount(world, weights=potential, minlength=worlds)

    def measure(self, state: State) -> StepStats:
        """:meth:`launch` then :meth:`read`."""
        self.launch(state)
        return self.read()

    def launch(self, state: State) -> None:
        """Measure `state` on the device (capturable: a fill and one launch)."""
        m = self.model
        self.stats.zero_()
        split = self.worlds * kd.STAT_MAXIMA
        wp.launch(
            kd.eval_step_statistics,
            dim=m.particle_count,
            inputs=[m.particle_spring_offsets, m.particle_spring_ids, m.particle_spring_role, m.spring_indices, m.spring_rest_length,
                    m.spring_limited, m.particle_mass, m.particle_pinned, state.particle_q, state.particle_qd, self._gravity,
                    self._origin, m.particle_world, self.worlds],
            outputs=[self.stats[:split], self.stats[split:]],
            device=m.device,
        )

    def record_arrays(self) -> list:
        """The device record the frame's report reads (:class:`~cloth_warp.records.FrameRecord`)."""
        return [(self, "stats")]

    def read(self) -> StepStats:
        """The statistics the last :meth:`launch` measured (one small read, or the frame record's copy), over
        every world of a batch (the largest maxima, the summed sums)."""
        per = self.read_worlds()
        return per[0] if self.worlds == 1 else combined_stats(per)

    def read_worlds(self) -> list[StepStats]:
        """The statistics of each world (a one-world model: one)."""
        s = record_values(self.stats)
        split = self.worlds * kd.STAT_MAXIMA
        maxima = s[:split].reshape(self.worlds, kd.STAT_MAXIMA)
        sums = s[split:].reshape(self.worlds, kd.STAT_SUMS)
        return [StepStats(float(mx[kd.STAT_MAX_STRAIN]), float(sm[kd.STAT_KINETIC_ENERGY]), float(mx[kd.STAT_MAX_SPEED]),
                          int(sm[kd.STAT_NONFINITE]), float(sm[kd.STAT_GRAVITY_POTENTIAL]) - float(p0))
                for mx, sm, p0 in zip(maxima, sums, self._potential0)]


@dataclass(frozen=True)
class ColliderReport:
    """The collider pass over some steps: contacts resolved, and of them those only the continuous trace found; the
    cloth's element samples (points of its edges and triangles) pushed out of a mesh collider."""

    contacts: int
    ccd: int
    samples: int = 0

    def counters(self) -> dict:
        """As the frame diagnostics name them."""
        return {"collider_contacts": self.contacts, "collider_ccd": self.ccd, "collider_samples": self.samples}


@dataclass(frozen=True)
class SelfCollisionReport:
    """The self-collision pass over some steps (:class:`~cloth_warp.selfcollision.SelfCollision` documents each)."""

    self_proximity: int
    self_ccd: int
    self_sweeps: int
    impact_zones: int
    impact_zone_particles: int
    unresolved: int
    oversized: int
    pair_buffer_growths: int
    broad_phase_builds: int
    broad_phase_patches: int

    overflowed: tuple = ()
    """The capturable path's buffers that were too small (the frame is re-run after they grow)."""

    @classmethod
    def from_counts(cls, counts: dict, overflowed: tuple = ()) -> SelfCollisionReport:
        named = {f.name: int(counts.get(f.name, 0)) for f in fields(cls) if f.name != "overflowed"}
        return cls(**named, overflowed=tuple(overflowed))

    def counters(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "overflowed"}


@dataclass(frozen=True)
class LinearSolveReport:
    """The implicit solver's linear solves over some steps (read from the device once per frame).

    Attributes:
        solves: solves run; iterations: summed over them; most_iterations: the most in one solve.
        failed: solves whose residual was not finite (their steps' results are meaningless); first_failed: the
            1-based solve that failed first (0: none).
        unconverged: finite solves that ended above the tolerance (at the cap of iterations).
        worst_residual, last_residual: the largest finite and the last relative residual |r_k| / |r_0|.
        tolerance: the solver's relative tolerance.
        contacts: collider contacts constrained inside the solves (``collider_contacts="solve"``), summed over them;
            contact_resolves: solves run again because contacts that pulled were released; self_contacts: self-contact
            elements in the systems (``self_contacts="solve"``), summed over the solves.
    """

    solves: int
    iterations: int
    most_iterations: int
    failed: int
    first_failed: int
    unconverged: int
    worst_residual: float
    last_residual: float
    tolerance: float
    contacts: int = 0
    contact_resolves: int = 0
    self_contacts: int = 0

    @property
    def converged(self) -> bool:
        return self.failed == 0 and self.unconverged == 0


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

    def counters(self) -> dict:
        """As the frame diagnostics name them."""
        return {"strain_excess_structural": self.structural_excess, "strain_excess_shear": self.shear_excess,
                "strain_limit_sweeps": self.sweeps, "strain_limit_missed": self.missed_steps}

    def __add__(self, other: StrainLimitReport) -> StrainLimitReport:
        """The report of both stretches of steps."""
        return StrainLimitReport(
            self.max_strain, self.tolerance, self.max_sweeps, max(self.structural_excess, other.structural_excess),
            max(self.shear_excess, other.shear_excess), max(self.initial_excess, other.initial_excess), self.steps + other.steps,
            self.missed_steps + other.missed_steps, self.sweeps + other.sweeps, max(self.most_sweeps, other.most_sweeps),
            self.frames + other.frames, self.missed_frames + other.missed_frames)


SOLVE_CONTACT_COUNTERS = ("solve_contacts", "contact_resolves", "solve_self_contacts")
"""The frame counters of collider contacts inside the implicit solve (:attr:`LinearSolveReport.contacts`, ``contact_resolves``)."""


@dataclass(frozen=True)
class FrameReport:
    """What one frame did (:attr:`Simulator.frame_report <cloth_warp.simulator.Simulator.frame_report>`), read
    from the device once after it (:class:`~cloth_warp.records.FrameRecord`).

    Attributes:
        stats: the statistics of the frame's last state.
        dt_min, dt_max: the smallest and largest step taken [s].
        iterations: linear-solve iterations, summed over the frame's steps (0 without a linear solve).
        residual: the last solve's relative residual.
        solves: the frame's :class:`LinearSolveReport` (fixed steps with a linear solve; None otherwise).
        passes: each pass's report by pass name (:class:`ColliderReport`, :class:`SelfCollisionReport`,
            :class:`StrainLimitReport`).
        rejected: adaptive steps rejected and retried with a smaller step.
        reruns: times a fixed-step frame was run again because a pass asked (None with adaptive steps).
    """

    stats: StepStats
    dt_min: float
    dt_max: float
    iterations: int = 0
    residual: float = 0.0
    solves: LinearSolveReport | None = None
    passes: Mapping[str, object] = field(default_factory=dict)
    rejected: int = 0
    reruns: int | None = 0

    def counters(self) -> dict:
        """Flat, by the names the cache's per-frame diagnostics and the run summary use."""
        out = {"dt_min": self.dt_min, "dt_max": self.dt_max, "iterations": self.iterations, "residual": self.residual}
        if self.reruns is None:
            out["rejected"] = self.rejected
        else:
            out["frame_reruns"] = self.reruns
        if self.solves is not None and (self.solves.contacts or self.solves.self_contacts):
            out.update(zip(SOLVE_CONTACT_COUNTERS, (self.solves.contacts, self.solves.contact_resolves, self.solves.self_contacts)))
        for report in self.passes.values():
            if report is not None:  # (a pass without a report: the sewing)
                out.update(report.counters())
        return out
