"""Frame loop: a model, a solver and two states advanced frame by frame."""

from __future__ import annotations

import json
import logging
import math
import time as _time

import numpy as np
import warp as wp

from .diagnostics import Diagnostics, FrameReport, StepStats, StrainLimitReport, combined_stats
from .graphs import record
from .animation import ControlAnimator
from .model import Model
from .profiling import stage
from .records import FrameRecord
from .wind import GustyWind
from .solvers.adaptive import AdaptiveStepper, DivergenceBounds, SimulationDiverged, StepCheck
from .solvers.base import SolverBase

log = logging.getLogger(__name__)

CHECKPOINT_VERSION = 1


def _failure_fields(e: SimulationDiverged) -> dict:
    """A diagnosis's fields (the constructor's keywords), for a checkpoint."""
    return {"time": e.time, "dt": e.dt, "max_strain": e.max_strain, "reason": e.reason, "suggested_dt": e.suggested_dt,
            "frame": e.frame, "kind": e.kind, "max_speed": e.max_speed, "kinetic_energy": e.kinetic_energy, "detail": e.detail}


def _scalar(value):
    """A checkpoint value as a Python scalar (a 0-d array from an .npz comes back as one)."""
    return value.item() if isinstance(value, np.ndarray) and value.ndim == 0 else value


class Simulator:
    """Advances a model frame by frame (forward only; taped rollouts call ``solver.step`` directly).

    With fixed substeps the substep loop of a frame is captured once as a Warp graph (CPU or CUDA) and
    replayed, so per-launch overhead is paid once; with ``adaptive=True`` every step is checked and
    bad steps are retried with half the step (see :class:`AdaptiveStepper`), each step replayed from a graph
    recorded once per step size where the step can be recorded. Handles, keyframed colliders
    and the gusty wind are set on the device from a device clock (:class:`~cloth_warp.animation.ControlAnimator`);
    a pass that asks (self-collision: a buffer overflowed) gets its frame run
    again eagerly from the frame's start. A frame is not captured with adaptive stepping (its steps are) and, on CUDA,
    where the driver lacks conditional graph nodes (CUDA < 12.4: the linear solve, the limiter's sweeps and the CCD
    sweeps loop on the device). On the CPU a deforming mesh collider's BVH refit is a host call between the frame's
    graphs (:func:`cloth_warp.graphs.record`: Warp 1.19 does not record it): a step's graph, the refit, the next.

    Divergence: after every frame, on every path (captured or not, adaptive or not, any integrator), the new
    state is checked against the scene's :class:`~cloth_warp.solvers.adaptive.DivergenceBounds` (non-finite
    values, strain, speed and kinetic energy relative to what the scene can give; thresholds in
    :class:`StepCheck`), and an implicit solve with a non-finite residual is caught after its step. Either
    raises :class:`SimulationDiverged` before :meth:`step_frame` returns, naming the frame, time, reason, max
    strain and a step smaller than the one that failed; `frame` and `time` then stay those of the last good
    frame (the state arrays hold the failed step's result, or with adaptive stepping the last good step's:
    :meth:`restore` a checkpoint to go on). The checks read the statistics measured every frame anyway.

    Args:
        model, solver: what to simulate and how.
        fps: frames per second of the output.
        substeps: steps per frame (dt = 1 / (fps * substeps)).
        adaptive: check steps and back off on divergence (raises SimulationDiverged when dt < dt_min).
        dt_min: the adaptive floor [s].
        check: the thresholds (:class:`StepCheck`, defaults) of the divergence bounds and adaptive checks.
        capture: force graph capture on/off (default: when possible).
        wind: a :class:`~cloth_warp.wind.GustyWind` (or anything with ``at(time) -> vec3`` [m/s]); set on
            the control once per frame, at the frame's midpoint (a steady wind once).

    After each frame, :attr:`frame_report` (:class:`~cloth_warp.diagnostics.FrameReport`) holds the statistics of
    the new state, the smallest and largest step used [s], the linear solves (iterations summed over the steps, the
    last relative residual, the :class:`~cloth_warp.diagnostics.LinearSolveReport`), each pass's report (collider
    contacts, self-collision counters, what the strain limiter left: the worst excess strain l / L - 1 - limit,
    sweeps, steps left above the tolerance) and the re-runs. All of it lives on the device in one block
    (:class:`~cloth_warp.records.FrameRecord`) read once per frame, captured or not; :attr:`frame_info` is the
    same, flat.
    :attr:`strain_limit_frame` is that frame's :class:`~cloth_warp.diagnostics.StrainLimitReport` and
    :attr:`strain_limit_total` the sum over the frames this Simulator ran (``missed_frames`` counts the
    frames that missed the limit).
    :meth:`checkpoint` / :meth:`restore` save and restore everything a run carries from frame to frame.
    """

    def __init__(self, model: Model, solver: SolverBase, *, fps: float = 60.0, substeps: int = 1, adaptive: bool = False,
                 dt_min: float = 1.0e-6, check: StepCheck | None = None, capture: bool | None = None, wind=None):
        from .validation import LIMITS, check_number

        fps = check_number("fps", fps, LIMITS["fps"])
        substeps = check_number("substeps", substeps, LIMITS["substeps"])
        dt_min = check_number("dt_min", dt_min, LIMITS["dt_min"])
        if adaptive and model.world_count > 1:
            raise ValueError(f"adaptive steps: batched worlds ({model.world_count}) step together at one fixed step size")
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
        self.check = check or StepCheck()
        self.bounds = DivergenceBounds(model, solver, self.check, wind=wind)
        self.animator = ControlAnimator(model, wind=wind if isinstance(wind, GustyWind) else None)
        self.animator.set_steps(0, self.dt)
        for p in solver.passes:  # fixed-step frames, captured or not, run the recordable paths (re-run when asked)
            p.set_recordable(not adaptive)
        if not solver.capturable:  # a pass that cannot be recorded: every pass takes its host path
            for p in solver.passes:
                p.set_recordable(False)
        loops = solver.device_loops or any(p.device_loops for p in solver.passes)
        # the strain limiter's sweeps and the linear solve loop on the device (wp.capture_while): CUDA graphs need
        # conditional nodes
        recordable = solver.capturable and not (loops and model.device.is_cuda and not wp.is_conditional_graph_supported())
        possible = recordable and not adaptive and self.animator.capturable
        self.capture = possible if capture is None else (capture and possible)
        # adaptive steps: a graph per step size (the control is set on the host before each step)
        self.stepper = (AdaptiveStepper(solver, self.dt, dt_min=dt_min, check=self.check, bounds=self.bounds,
                                        capture=recordable if capture is None else (capture and recordable)) if adaptive else None)
        self.diagnostics = self.stepper.diagnostics if adaptive else Diagnostics(model)
        self._graph = None
        self.last_stats: StepStats | None = None
        self.wall_time = 0.0
        self.wind = wind
        if wind is not None and getattr(wind, "steady", False):
            self.control.set_wind(wind.at(0.0))
        self.bounds.note_wind(self.control.wind.numpy()[0])
        self.frame_report: FrameReport | None = None  # the last frame's report
        self._record: FrameRecord | None = None  # the frame's device records in one block (gathered when None)
        self.strain_limiter = solver.strain_limiter  # the solver's pass, when it limits
        self.pass_reports: dict = {}  # the last frame's report of each pass, by pass name
        self.reruns = 0  # frames run again because a pass asked (buffers grown, a step for the host path)
        # (live, saved) pairs of what a step carries to the next: a frame saves them as it starts, a re-run restores them
        carried = [self.state.particle_q, self.state.particle_qd, self.animator.clock, *solver.carried_arrays()]
        self._carried = [(a, wp.empty_like(a)) for a in carried]
        self._frame_start_q = self._carried[0][1]  # the positions the frame started from (a held world returns to them)
        self.strain_limit_frame: StrainLimitReport | None = None
        self.strain_limit_total: StrainLimitReport | None = None
        # batched worlds (model.world_count > 1): each world checked on its own; one that diverges is held at its
        # last good state while the others go on (see step_frame)
        self.world_stats: list[StepStats] = []
        self.world_solves: list | None = None
        self.world_failures: dict[int, SimulationDiverged] = {}
        self._held: dict[int, wp.array] = {}

    def notify_model_changed(self, flags: int) -> None:
        """Model fields changed (:class:`~cloth_warp.model.ModelFlags`) between frames: the solver and its passes
        refresh what they derived, the divergence bounds and the diagnostics are measured again from the model,
        and a recorded frame is recorded again. The current state is kept (set it with ``state.assign`` to start
        over from the model's new initial state)."""
        self.solver.notify_model_changed(flags)
        self.bounds = DivergenceBounds(self.model, self.solver, self.check, wind=self.wind)
        self.bounds.note_wind(self.control.wind.numpy()[0])
        if self.stepper is not None:
            self.stepper.bounds = self.bounds
            self.stepper.diagnostics = Diagnostics(self.model)
            self.stepper.forget_graphs()
            self.diagnostics = self.stepper.diagnostics
        else:
            self.diagnostics = Diagnostics(self.model)
        self._graph = None
        self._record = None

    @property
    def frame_info(self) -> dict:
        """The last frame's report, flat (:meth:`FrameReport.counters <cloth_warp.diagnostics.FrameReport.counters>`:
        ``dt_min``, ``dt_max``, ``iterations``, ``residual``, ``frame_reruns`` or ``rejected``, each pass's counters);
        before the first frame, the step and zero counts."""
        if self.frame_report is None:
            return {"dt_min": self.dt, "dt_max": self.dt, "iterations": 0, "residual": 0.0}
        return self.frame_report.counters()

    def _frame_record(self) -> FrameRecord:
        """The block the frame's reports are read from (gathered again after anything that may have replaced a
        record array: a re-run, a restore, a model change)."""
        if self._record is None:
            self._record = FrameRecord.of(self.model.device, [self.diagnostics, self.solver, *self.solver.passes])
            self._graph = None  # recorded graphs write the arrays the block has just replaced
            if self.stepper is not None:
                self.stepper.forget_graphs()
        return self._record

    def _substeps(self):
        """A frame's steps: each sets the animated control from the device clock, then steps (all on the device,
        so a frame records as one graph)."""
        animator = self.animator
        if animator.gusty:
            animator.apply_wind(self.control, 0.5 * self.frame_dt)  # the clock holds the frame's start
        for k in range(self.substeps):
            src, dst = (self.state, self._other) if k % 2 == 0 else (self._other, self.state)
            if animator.active:
                animator.advance_clock(self.dt)
            if self.model.animated:
                animator.apply(self.control)
            self.solver.step(src, dst, self.control, self.dt)
        if self.substeps % 2 == 1:
            self.state.assign(self._other)

    def _frame(self):
        """Everything a fixed-step frame does on the device, recorded as one graph when captured: the records
        reset, the carried arrays saved (a re-run starts from them), the steps, the statistics of the new state."""
        self.solver.reset_pass_reports()
        self.solver.reset_report()
        for live, saved in self._carried:
            wp.copy(saved, live)
        self._substeps()
        with stage("statistics"):
            self.diagnostics.launch(self.state)

    def _run_frame(self):
        if not self.capture:
            self._frame()
            return
        self._frame_record()  # the record arrays in their block before a frame is recorded writing into them
        if self._graph is None:
            with record(self.model.device) as frame:
                self._frame()
            self._graph = frame
        self._graph.replay()

    def _rerun(self, asking: list) -> None:
        """Run the frame again from its start, eagerly, with the passes that asked on their host paths (and their
        buffers grown); the frame is recorded again at the next frame (its arrays may have been replaced)."""
        for p in self.solver.passes:
            p.begin_rerun()
        for p in asking:
            p.prepare_rerun(self.pass_reports[p.name])
        for live, saved in self._carried:
            wp.copy(live, saved)
        try:
            self._frame()
        finally:
            for p in asking:
                p.end_rerun()
        self._graph = None  # grown buffers, or the host path's own reallocations: a recorded frame holds the old arrays
        self._record = None
        self.reruns += 1

    def step_frame(self) -> StepStats:
        """Advance one frame; returns the statistics of the new state (raises :class:`SimulationDiverged`
        instead when it is beyond the scene's divergence bounds, see the class)."""
        t0 = _time.perf_counter()
        if self.wind is not None and not getattr(self.wind, "steady", False):
            w = self.wind.at(self.time + 0.5 * self.frame_dt)  # host arithmetic only: the bounds' record of the wind
            if not self.animator.gusty or self.stepper is not None:
                self.control.set_wind(w)  # a wind the animator does not evaluate, or the adaptive (host) path
            self.bounds.note_wind(w)
        reruns = self.reruns
        try:
            if self.stepper is not None:
                self._frame_record()  # before the stepper records its steps
                self.solver.reset_pass_reports()
                self.solver.reset_report()
                self.stepper.advance(self.state, self.control, self.time, self.frame_dt)
                # (the statistics: the stepper's of its last, accepted, trial step, which the state now holds)
                with self._frame_record().fetched():  # one read: every report below comes from it
                    self.pass_reports = self.solver.read_pass_reports()
                    stats = self.diagnostics.read()
                solves = None
            else:
                self._run_frame()
                with self._frame_record().fetched():
                    self.pass_reports = self.solver.read_pass_reports()
                    solves = self.solver.read_report()
                    stats = self.diagnostics.read()
                    self._read_worlds()
                asking = [p for p in self.solver.passes if p.needs_rerun(self.pass_reports[p.name])]
                if asking and not (solves is not None and solves.failed):  # a failed solve is reported, not re-run
                    self._rerun(asking)
                    with self._frame_record().fetched():
                        self.pass_reports = self.solver.read_pass_reports()
                        solves = self.solver.read_report()
                        stats = self.diagnostics.read()
                        self._read_worlds()
        except SimulationDiverged as exc:
            self.wall_time += _time.perf_counter() - t0
            raise exc.in_frame(self.frame + 1) from None
        if self.stepper is not None:
            r = self.stepper.interval
            self.frame_report = FrameReport(stats=stats, dt_min=r.dt_min, dt_max=r.dt_max, iterations=r.iterations,
                                            residual=float(self.solver.last_residual), passes=self.pass_reports, rejected=r.rejected,
                                            reruns=None)
        else:
            if self.model.world_count > 1:
                stats = self._check_worlds(self.time + self.frame_dt)  # the live worlds' (raises when none is left)
            self.frame_report = FrameReport(stats=stats, dt_min=self.dt, dt_max=self.dt, iterations=solves.iterations if solves else 0,
                                            residual=solves.last_residual if solves else 0.0, solves=solves, passes=self.pass_reports,
                                            reruns=self.reruns - reruns)
            if self.model.world_count == 1 and solves is not None and solves.failed:
                self.wall_time += _time.perf_counter() - t0
                raise self._failed_solve(solves, stats).in_frame(self.frame + 1)
        if self.strain_limiter is not None:
            self._note_strain_limit(self.pass_reports[self.strain_limiter.name])
        end = (self.frame + 1) * self.frame_dt
        bad = self.bounds.violation(stats) if self.model.world_count == 1 else None
        self.wall_time += _time.perf_counter() - t0
        if bad is not None:
            raise self._diverged(bad[0], bad[1], stats, end).in_frame(self.frame + 1)
        self.frame += 1
        self.time = end
        if self.model.animated:
            self.control.time = end  # what the last step's control was set for (the device clock's time)
        self.last_stats = stats
        return stats

    def _read_worlds(self):
        """Batched worlds: each world's statistics and solves (from the frame's record)."""
        if self.model.world_count > 1:
            self.world_stats = self.diagnostics.read_worlds()
            self.world_solves = self.solver.read_world_reports() if hasattr(self.solver, "read_world_reports") else None

    def _check_worlds(self, t: float) -> StepStats:
        """Batched worlds: check each live world against the scene's divergence bounds and its own solves; a world
        that fails gets its diagnosis in :attr:`world_failures` and is held at its state before the frame (velocity
        0, warm start forgotten) from then on, so that the others go on. Returns the statistics over the live
        worlds; raises the first failure when none is left."""
        from .worlds import world_slices

        slices = world_slices(self.model)
        for k, stats in enumerate(self.world_stats):
            if k in self.world_failures:
                continue
            solves = self.world_solves[k] if self.world_solves is not None else None
            if solves is not None and solves.failed:
                failure = self._failed_solve(solves, stats, f"world {k}: ")
            else:
                bad = self.bounds.violation(stats)
                failure = self._diverged(bad[0], f"world {k}: {bad[1]}", stats, t) if bad is not None else None
            if failure is not None:
                self.world_failures[k] = failure.in_frame(self.frame + 1)
                self._held[k] = wp.clone(self._frame_start_q[slices[k]])
        for k, held in self._held.items():
            wp.copy(self.state.particle_q[slices[k]], held)
            self.state.particle_qd[slices[k]].zero_()
            self.solver.forget_world(k, slices[k])
        live = [s for k, s in enumerate(self.world_stats) if k not in self.world_failures]
        if not live:
            raise self.world_failures[min(self.world_failures)]
        return combined_stats(live)

    def _note_strain_limit(self, report: StrainLimitReport):
        self.strain_limit_frame = report
        self.strain_limit_total = report if self.strain_limit_total is None else self.strain_limit_total + report

    def _failed_solve(self, solves, stats: StepStats, prefix: str = "") -> SimulationDiverged:
        """The diagnosis of a frame whose linear solve went non-finite (at the step the record names)."""
        reason = f"{prefix}non-finite residual in the linear solve of step {solves.first_failed} of {self.substeps}"
        return self._diverged("non-finite residual", reason, stats, self.time + solves.first_failed * self.dt)

    def _diverged(self, kind: str, reason: str, stats: StepStats, t: float) -> SimulationDiverged:
        """The diagnosis of a fixed-step run that failed at time t: the step to try is a whole number of
        substeps per frame, strictly smaller than the one that failed."""
        suggested = self.bounds.suggest_dt(self.dt)
        substeps = max(self.substeps + 1, math.ceil(self.frame_dt / suggested * (1.0 - 1e-12)))
        suggested = self.frame_dt / substeps
        if self.solver.name == "explicit_euler":
            other = "; explicit Euler gains energy at any step: symplectic_euler or implicit_euler are the stable choices"
        elif self.solver.stability is not None:
            other = ", stronger strain limiting, adaptive stepping or the implicit_euler integrator"
        else:
            other = ", adaptive stepping or a tighter solver tolerance"
        detail = (f"{reason}; max strain {stats.max_strain:.3g}, max speed {stats.max_speed:.3g} m/s, kinetic energy "
                  f"{stats.kinetic_energy:.3g} J; dt {self.dt:.3g} s: try solver.substeps >= {substeps} (dt <= {suggested:.3g} s){other}")
        return SimulationDiverged(time=t, dt=self.dt, max_strain=stats.max_strain, reason=reason, kind=kind, suggested_dt=suggested,
                                  max_speed=stats.max_speed, kinetic_energy=stats.kinetic_energy, detail=detail)

    def positions(self):
        """A copy of the current particle positions [m], shape (particle_count, 3).

        (On the CPU, ``wp.array.numpy()`` is a view that the next frame overwrites.)
        """
        return self.state.particle_q.numpy().copy()

    # -- checkpoints ------------------------------------------------------------------------------------------------
    def checkpoint(self) -> dict:
        """Everything this run carries from one frame to the next, as numpy arrays and Python scalars (an
        ``np.savez`` without pickling stores it exactly).

        A fresh Simulator built the same way (same model, solver options, fps, substeps, adaptive, wind) and
        :meth:`restore`\\ d from the checkpoint taken after frame K gives frames K+1, ... bit-identical to the
        uninterrupted run on the CPU. Keys:

        * ``version``, ``particle_count``, ``fps``, ``substeps``, ``adaptive``: what the checkpoint fits;
        * ``frame``, ``time`` [s], ``wall_time`` [s]; ``particle_q`` [m] and ``particle_qd`` [m/s], (n, 3) float32;
        * ``control.pin_target``, ``control.wind``, ``control.collider_transform_start`` / ``_end``,
          ``control.time``: the control as the last step left it (handle targets and collider poses are set
          again from the keyframes before every step, the gusty wind before every frame; they are kept so that
          a control set by hand survives too);
        * ``last_stats``: the last frame's statistics (5 numbers, when there is one);
        * ``solver.*``: the solver's (:meth:`SolverBase.checkpoint_state`): its name; implicit Euler's warm
          start (``solver.dv_previous``, ``solver.has_previous``) and contacts' last normal impulses; with
          self-collision the broad phase's buffer capacities and counters and the last step's close pairs (the
          next step's self-contact candidates in the solve) (``solver.collisions.self.*``: each pass's state under
          its ``checkpoint_key``);
        * ``stepper.*`` (adaptive only): the current dt, the good steps since the last change, the statistics of
          the last accepted step, the run's report;
        * ``bounds.wind_speed``: the strongest wind the divergence bounds have seen;
        * batched worlds: ``solver.previous_ready`` (each world's warm start); with diverged worlds
          ``worlds.failures`` (their diagnoses, JSON) and ``worlds.held_q`` [m] (the states they are held at, (n, 3)).

        Nothing else persists: the strain limiter sweeps each step from the integrator's output, the collider
        pass keeps no state, the gusty wind is a function of time, deforming colliders are set from their point
        cache before each step, and the solvers' scratch buffers are written before they are read.
        """
        q = self.state.particle_q.numpy().copy()
        qd = self.state.particle_qd.numpy().copy()
        c = self.control
        out = {
            "version": CHECKPOINT_VERSION, "particle_count": int(self.model.particle_count), "fps": self.fps, "substeps": self.substeps,
            "adaptive": self.stepper is not None, "frame": int(self.frame), "time": float(self.time), "wall_time": float(self.wall_time),
            "particle_q": q, "particle_qd": qd,
            "control.pin_target": c.pin_target.numpy().copy(), "control.wind": c.wind.numpy().copy(),
            "control.collider_transform_start": c.collider_transform_start.numpy().copy(),
            "control.collider_transform_end": c.collider_transform_end.numpy().copy(), "control.time": float(c.time),
        }
        if self.last_stats is not None:
            s = self.last_stats
            out["last_stats"] = np.array([s.max_strain, s.kinetic_energy, s.max_speed, s.nonfinite, s.gravity_work], np.float64)
        out.update({f"solver.{k}": v for k, v in self.solver.checkpoint_state().items()})
        if self.stepper is not None:
            out.update({f"stepper.{k}": v for k, v in self.stepper.checkpoint_state().items()})
        out.update({f"bounds.{k}": v for k, v in self.bounds.checkpoint_state().items()})
        if self.world_failures:  # a batch's diverged worlds: their diagnoses and the states they are held at
            from .worlds import world_slices

            slices = world_slices(self.model)
            held = np.zeros_like(q)
            for k, h in self._held.items():
                held[slices[k]] = h.numpy()
            out["worlds.held_q"] = held
            out["worlds.failures"] = json.dumps({str(k): _failure_fields(e) for k, e in self.world_failures.items()})
        return out

    def restore(self, checkpoint: dict) -> None:
        """Continue from a :meth:`checkpoint` (of a run of the same scene: particle count, fps, substeps,
        adaptive stepping and solver kind must match, else ValueError). The arrays are written in place; the frame
        is recorded again at the next step (a pass's restored buffers may be new arrays)."""
        ck = {k: _scalar(v) for k, v in checkpoint.items()}
        missing = [k for k in ("version", "particle_count", "fps", "substeps", "adaptive", "frame", "time", "particle_q", "particle_qd")
                   if k not in ck]
        if missing:
            raise ValueError(f"not a simulator checkpoint: missing {', '.join(missing)}")
        if int(ck["version"]) != CHECKPOINT_VERSION:
            raise ValueError(f"checkpoint version {ck['version']} (this cloth_warp reads version {CHECKPOINT_VERSION})")
        problems = []
        if int(ck["particle_count"]) != self.model.particle_count:
            problems.append(f"{ck['particle_count']} particles, this model has {self.model.particle_count}")
        if float(ck["fps"]) != self.fps or int(ck["substeps"]) != self.substeps:
            problems.append(f"{ck['fps']:g} fps x {ck['substeps']} substeps, this simulator {self.fps:g} x {self.substeps}")
        if bool(ck["adaptive"]) != (self.stepper is not None):
            problems.append(f"adaptive={bool(ck['adaptive'])}, this simulator adaptive={self.stepper is not None}")
        solver_name = ck.get("solver.name", self.solver.name)
        if solver_name != self.solver.name:
            problems.append(f"the {solver_name} solver, this simulator uses {self.solver.name}")
        if problems:
            raise ValueError("checkpoint does not fit this simulator: " + "; ".join(problems))
        n = self.model.particle_count

        def vec3(key):
            a = np.asarray(ck[key], np.float32)
            if a.shape != (n, 3):
                raise ValueError(f"checkpoint {key} has shape {a.shape}, expected {(n, 3)}")
            return a

        self.state.particle_q.assign(vec3("particle_q"))
        self.state.particle_qd.assign(vec3("particle_qd"))
        c = self.control
        if "control.pin_target" in ck:
            c.pin_target.assign(vec3("control.pin_target"))
            c.wind.assign(np.asarray(ck["control.wind"], np.float32).reshape(1, 3))
            for key in ("collider_transform_start", "collider_transform_end"):
                arr = getattr(c, key)
                arr.assign(np.asarray(ck[f"control.{key}"], np.float32).reshape(arr.shape[0], 7))
            c.time = float(ck["control.time"])
        self.solver.restore_state({k[len("solver."):]: v for k, v in ck.items() if k.startswith("solver.")})
        if self.stepper is not None:
            self.stepper.restore_state({k[len("stepper."):]: v for k, v in ck.items() if k.startswith("stepper.")})
            self.stepper.forget_graphs()  # a pass's restored buffers may be new arrays
        if "bounds.wind_speed" in ck:
            self.bounds.restore_state({"wind_speed": ck["bounds.wind_speed"]})
        self.frame = int(ck["frame"])
        self.time = float(ck["time"])
        self.animator.set_steps(self.frame * self.substeps, self.dt)
        self._graph = None  # a pass's restored buffers may be new arrays
        self._record = None
        self.wall_time = float(ck.get("wall_time", 0.0))
        self.world_failures, self._held = {}, {}
        if "worlds.failures" in ck:
            from .worlds import world_slices

            slices = world_slices(self.model)
            held = vec3("worlds.held_q")
            for k, fields in json.loads(str(ck["worlds.failures"])).items():
                k = int(k)
                if not 0 <= k < len(slices):
                    raise ValueError(f"checkpoint names world {k} failed, this model has {len(slices)} worlds")
                self.world_failures[k] = SimulationDiverged(**fields)
                self._held[k] = wp.array(held[slices[k]], dtype=wp.vec3, device=self.model.device)
        s = ck.get("last_stats")
        self.last_stats = None if s is None else StepStats(float(s[0]), float(s[1]), float(s[2]), int(s[3]), float(s[4]))
        self.frame_report = None
