"""Adaptive time stepping: discard a bad step, halve dt, retry; grow back after good steps."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

from ..diagnostics import Diagnostics, StepStats
from ..model import Control, State
from .base import SolverBase

log = logging.getLogger(__name__)


@dataclass
class StepCheck:
    """When a step counts as bad.

    Attributes:
        max_speed: any free particle faster than this [m/s].
        max_strain: any structural/shear spring stretched beyond this (1.0 = twice its rest length).
        max_strain_jump: max strain rising by more than this within one step, or the integrator's raw
            output (before strain limiting) exceeding the strain limit by more than this.
        energy_growth: kinetic energy above energy_growth * (previous + what gravity alone can add).
        require_convergence: an iterative linear solve, or the strain limiter, missing its tolerance.
    """

    max_speed: float = 100.0
    max_strain: float = 1.0
    max_strain_jump: float = 0.25
    energy_growth: float = 4.0
    require_convergence: bool = True


class SimulationDiverged(RuntimeError):
    """The step size fell below the floor; the message holds the diagnosis."""

    def __init__(self, message: str, *, time: float, dt: float, max_strain: float, reason: str, suggested_dt: float):
        super().__init__(message)
        self.time = time
        self.dt = dt
        self.max_strain = max_strain
        self.reason = reason
        self.suggested_dt = suggested_dt


@dataclass
class StepperReport:
    """What the stepper did since the last reset."""

    steps: int = 0
    rejected: int = 0
    dt_min: float = math.inf
    dt_max: float = 0.0
    max_strain: float = 0.0
    iterations: int = 0
    reasons: dict = field(default_factory=dict)


class AdaptiveStepper:
    """Advances a state over an interval with a solver, backing off on divergence.

    A trial step is rejected on NaN/Inf, a speed or strain beyond :class:`StepCheck`'s limits, a strain
    jump, kinetic-energy blow-up or a non-converged linear solve; dt is then halved and the step retried
    from the same state. After `grow_after` good steps dt doubles again (never above the nominal dt, and
    not above half the smallest dt that failed during the current interval). If dt would fall below
    `dt_min`, :class:`SimulationDiverged` is raised with time, reason, max strain, last dt and a
    suggestion; the state passed in is left at the last good step (never NaN).

    Forward-only (it reads statistics on the host every step).
    """

    def __init__(self, solver: SolverBase, dt: float, *, dt_min: float = 1.0e-6, grow_after: int = 8, check: StepCheck | None = None):
        if not (dt > 0.0):
            raise ValueError(f"dt must be positive, got {dt!r}")
        self.solver = solver
        self.model = solver.model
        self.nominal_dt = float(dt)
        self.dt = float(dt)
        self.dt_min = float(dt_min)
        self.grow_after = int(grow_after)
        self.check = check or StepCheck()
        self.diagnostics = Diagnostics(self.model)
        self.trial = self.model.state(requires_grad=False)
        self.report = StepperReport()
        self.interval = StepperReport()
        self._stats: StepStats | None = None
        self._good = 0

    def reset_report(self):
        self.report = StepperReport()

    def _rejection(self, new: StepStats, old: StepStats | None, h: float) -> str | None:
        c = self.check
        if not new.finite:
            return "non-finite positions or velocities"
        if new.max_speed > c.max_speed:
            return f"speed {new.max_speed:.3g} m/s above {c.max_speed:g} m/s"
        if new.max_strain > c.max_strain:
            return f"strain {new.max_strain:.3g} above {c.max_strain:g}"
        if c.require_convergence and not getattr(self.solver, "converged", True):
            return f"linear solver did not converge (residual {self.solver.last_residual:.2e} after {self.solver.last_iterations} iterations)"
        limiter = self.solver.strain_limiter
        if limiter is not None and limiter.active:
            if limiter.last_initial_excess > c.max_strain_jump:
                return f"strain {limiter.last_initial_excess + limiter.max_strain:.3g} before strain limiting (limit {limiter.max_strain:g})"
            if c.require_convergence and not limiter.converged:
                return f"strain limiting did not converge in {limiter.last_iterations} sweeps"
        if old is not None:
            if new.max_strain - old.max_strain > c.max_strain_jump:
                return f"strain jumped from {old.max_strain:.3g} to {new.max_strain:.3g} in one step"
            g = math.sqrt(sum(x * x for x in self.model.gravity))
            floor = 0.5 * self.diagnostics.total_mass_free * (g * h) ** 2
            if new.kinetic_energy > c.energy_growth * (old.kinetic_energy + floor):
                return f"kinetic energy grew from {old.kinetic_energy:.3g} J to {new.kinetic_energy:.3g} J in one step"
        return None

    def advance(self, state: State, control: Control, t0: float, duration: float) -> float:
        """Advance `state` in place from time t0 over `duration` [s]; returns the time reached."""
        if self._stats is None:
            self._stats = self.diagnostics.measure(state)
        t, end = t0, t0 + duration
        dt_cap = self.nominal_dt
        eps = 1e-9 * max(duration, 1e-12)
        r = self.report
        interval = self.interval = StepperReport()  # this call's steps alone
        while t < end - eps:
            h = min(self.dt, end - t)
            self.model.update_control(control, t + h, h)
            self.solver.step(state, self.trial, control, h)
            stats = self.diagnostics.measure(self.trial)
            reason = self._rejection(stats, self._stats, h)
            if reason is not None:
                r.rejected += 1
                interval.rejected += 1
                r.reasons[reason.split(" ")[0]] = r.reasons.get(reason.split(" ")[0], 0) + 1
                dt_cap = min(dt_cap, h / 2.0)
                self.dt = h / 2.0
                self._good = 0
                log.debug("t=%.6f s: rejected step of %.3g s (%s)", t, h, reason)
                if self.dt < self.dt_min:
                    ok = r.dt_min if math.isfinite(r.dt_min) else self.dt_min
                    suggestion = (
                        f"try a smaller dt (<= {ok / 2:.3g} s), more substeps, stiffer strain limiting or the implicit_euler integrator"
                    )
                    raise SimulationDiverged(
                        f"simulation diverged at t = {t:.6g} s: {reason}; last dt {h:.3g} s fell below the floor {self.dt_min:.3g} s; "
                        f"max strain at the last good step {self._stats.max_strain:.3g}; {suggestion}",
                        time=t, dt=h, max_strain=self._stats.max_strain, reason=reason, suggested_dt=ok / 2,
                    )
                continue
            state.assign(self.trial)
            self._stats = stats
            t += h
            for rep in (r, interval):
                rep.steps += 1
                rep.dt_min = min(rep.dt_min, h)
                rep.dt_max = max(rep.dt_max, h)
                rep.max_strain = max(rep.max_strain, stats.max_strain)
                rep.iterations += getattr(self.solver, "last_iterations", 0)
            self._good += 1
            if self._good >= self.grow_after and self.dt < self.nominal_dt:
                self.dt = min(2.0 * self.dt, self.nominal_dt, max(dt_cap, self.dt))
                self._good = 0
        return t
