"""Frame loop: a model, a solver and two states advanced frame by frame."""

from __future__ import annotations

import logging
import time as _time

import warp as wp

from .diagnostics import Diagnostics, StepStats
from .model import Model
from .solvers.adaptive import AdaptiveStepper, SimulationDiverged, StepCheck
from .solvers.base import SolverBase
from .solvers.implicit import SolverImplicitEuler

log = logging.getLogger(__name__)


class Simulator:
    """Advances a model frame by frame (forward only; taped rollouts call ``solver.step`` directly).

    With fixed substeps the substep loop of a frame is captured once as a Warp graph (CPU or CUDA) and
    replayed, so per-launch overhead is paid once; with ``adaptive=True`` every step is checked and
    bad steps are retried with half the step (see :class:`AdaptiveStepper`). Capture is skipped for
    animated handles and colliders (their targets and poses are updated on the host each substep), for the implicit solver
    (its iterative solve checks convergence on the host) and for self-collision (its broad phase sizes buffers on the host).

    Args:
        model, solver: what to simulate and how.
        fps: frames per second of the output.
        substeps: steps per frame (dt = 1 / (fps * substeps)).
        adaptive: check steps and back off on divergence (raises SimulationDiverged when dt < dt_min).
        dt_min: the adaptive floor [s].
        capture: force graph capture on/off (default: when possible).
        wind: a :class:`~cloth_warp.wind.GustyWind` (or anything with ``at(time) -> vec3`` [m/s]); set on
            the control once per frame, at the frame's midpoint (a steady wind once).

    After each frame, :attr:`frame_info` holds the smallest and largest step used [s], the solver
    iterations of its steps (summed) (with graph capture: the iterations are not read back, 0) and, with
    collisions, their counters summed over the frame's steps (``collider_contacts``, ``collider_ccd``).
    """

    def __init__(self, model: Model, solver: SolverBase, *, fps: float = 60.0, substeps: int = 1, adaptive: bool = False,
                 dt_min: float = 1.0e-6, check: StepCheck | None = None, capture: bool | None = None, wind=None):
        if not (fps > 0.0):
            raise ValueError(f"fps must be positive, got {fps!r}")
        if int(substeps) < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps!r}")
        self.model = model
        self.solver = solver
        self.fps = float(fps)
        self.substeps = int(substeps)
        self.frame_dt = 1.0 / self.fps
        self.dt = self.frame_dt / self.substeps
        self.state = model.state(requires_grad=False)
        self._other = model.state(requires_grad=False)
        self.control = model.control(requires_grad=False)
        self.frame = 0
        self.time = 0.0
        self.stepper = AdaptiveStepper(solver, self.dt, dt_min=dt_min, check=check) if adaptive else None
        self.diagnostics = self.stepper.diagnostics if adaptive else Diagnostics(model)
        possible = (not adaptive and not model.animated and not isinstance(solver, SolverImplicitEuler)
                    and not model.self_collision)
        self.capture = possible if capture is None else (capture and possible)
        self._graph = None
        self.last_stats: StepStats | None = None
        self.wall_time = 0.0
        self.wind = wind
        if wind is not None and getattr(wind, "steady", False):
            self.control.set_wind(wind.at(0.0))
        self.frame_info = {"dt_min": self.dt, "dt_max": self.dt, "iterations": 0, "residual": 0.0}

    def _substeps(self):
        iterations = 0
        for k in range(self.substeps):
            src, dst = (self.state, self._other) if k % 2 == 0 else (self._other, self.state)
            if self.model.animated:
                self.model.update_control(self.control, self.time + (k + 1) * self.dt, self.dt)
            self.solver.step(src, dst, self.control, self.dt)
            iterations += getattr(self.solver, "last_iterations", 0)
        self.frame_info = {"dt_min": self.dt, "dt_max": self.dt, "iterations": iterations,
                           "residual": float(getattr(self.solver, "last_residual", 0.0))}
        if self.substeps % 2 == 1:
            self.state.assign(self._other)

    def step_frame(self) -> StepStats:
        """Advance one frame; returns the statistics of the new state."""
        t0 = _time.perf_counter()
        collisions = getattr(self.solver, "collisions", None)
        if collisions is not None:
            collisions.reset_counts()
        if self.wind is not None and not getattr(self.wind, "steady", False):
            self.control.set_wind(self.wind.at(self.time + 0.5 * self.frame_dt))
        if self.stepper is not None:
            self.stepper.advance(self.state, self.control, self.time, self.frame_dt)
            r = self.stepper.interval
            self.frame_info = {"dt_min": r.dt_min, "dt_max": r.dt_max, "iterations": r.iterations,
                               "residual": float(getattr(self.solver, "last_residual", 0.0)), "rejected": r.rejected}
        elif self.capture:
            if self._graph is None:
                with wp.ScopedCapture(device=self.model.device) as cap:
                    self._substeps()
                self._graph = cap.graph
            wp.capture_launch(self._graph)
            self.frame_info = {"dt_min": self.dt, "dt_max": self.dt, "iterations": 0, "residual": 0.0}
        else:
            self._substeps()
        if collisions is not None:
            self.frame_info.update(collisions.read_counts())
        self.frame += 1
        self.time = self.frame * self.frame_dt
        stats = self.diagnostics.measure(self.state)
        self.wall_time += _time.perf_counter() - t0
        if not stats.finite:
            raise SimulationDiverged(
                f"simulation diverged in frame {self.frame} (t = {self.time:.6g} s): {stats.nonfinite} particles non-finite; "
                f"try adaptive stepping, more substeps or the implicit_euler integrator",
                time=self.time, dt=self.dt, max_strain=stats.max_strain, reason="non-finite", suggested_dt=self.dt / 2,
            )
        self.last_stats = stats
        return stats

    def positions(self):
        """A copy of the current particle positions [m], shape (particle_count, 3).

        (On the CPU, ``wp.array.numpy()`` is a view that the next frame overwrites.)
        """
        return self.state.particle_q.numpy().copy()
