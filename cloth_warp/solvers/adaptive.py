"""Divergence detection and adaptive time stepping.

:class:`StepCheck` holds every threshold (one source), :class:`DivergenceBounds` turns them into bounds for
one scene (checked after every frame on every path by :class:`~cloth_warp.simulator.Simulator`, and on every
trial step by :class:`AdaptiveStepper`), and :class:`AdaptiveStepper` discards a bad step, halves dt and
retries, growing dt back after good steps.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..elasticity import membrane_element_energy, membrane_element_row_bound
from ..diagnostics import Diagnostics, StepStats
from ..model import Control, State
from ..plate import stencil_row_bound
from .base import SolverBase

log = logging.getLogger(__name__)


@dataclass
class StepCheck:
    """When a state or a step counts as bad: every threshold of divergence detection in one place.

    Divergence bounds (relative to the scene; :class:`DivergenceBounds` derives them from the model,
    the solver and the wind, and explains them). A state beyond any of them is diverged: the
    :class:`~cloth_warp.simulator.Simulator` raises :class:`SimulationDiverged` after a frame that ends
    there, and the adaptive stepper rejects a step that ends there.

    Attributes:
        strain_floor: with strain limiting, a structural/shear strain beyond max(strain_floor,
            strain_factor x the limit) (plus any stretch the pins and handles force) is divergence.
        strain_factor: see strain_floor.
        strain_unlimited: without strain limiting, the strain bound (9.0 = ten times the rest length).
        speed_factor: a free particle faster than speed_factor x the scene's speed scale
            sqrt(2 E / M) (E: the energy available to the cloth so far, M: its free mass) is divergence.
        energy_factor: kinetic energy above energy_factor x E is divergence.
        speed_floor: the smallest speed scale [m/s] (the energy of the free mass at this speed is always
            available: a scene at rest is not held to zero).
        max_speed, max_strain: absolute bounds [m/s] / strain replacing the scene-relative ones (None: use
            the scene-relative ones).

    Adaptive stepping only (a step is rejected, never a frame):
        max_strain_jump: max strain rising by more than this within one step, or the integrator's raw
            output (before strain limiting) exceeding the strain limit by more than this.
        energy_growth: kinetic energy above energy_growth * (previous + what one step can add from rest: gravity over
            the step, and the drive speed of handles, moving colliders and wind, :attr:`DivergenceBounds.drive_speed`).
        require_convergence: an iterative linear solve, or the strain limiter, missing its tolerance.
    """

    strain_floor: float = 1.0
    strain_factor: float = 5.0
    strain_unlimited: float = 9.0
    speed_factor: float = 20.0
    energy_factor: float = 4.0
    speed_floor: float = 1.0
    max_speed: float | None = None
    max_strain: float | None = None
    max_strain_jump: float = 0.25
    energy_growth: float = 4.0
    require_convergence: bool = True


class SimulationDiverged(RuntimeError):
    """A simulation diverged; the message holds the diagnosis.

    Attributes:
        frame: the frame that failed (1 = the first simulated frame; None outside a Simulator).
        time: simulated time [s] where it was detected.
        dt: the step [s] that failed.
        reason: what was detected (text); kind: its short name ("non-finite", "non-finite residual",
            "strain", "speed", "energy", or for the adaptive stepper's own checks "strain jump",
            "energy growth", "unconverged", "limiter").
        max_strain, max_speed, kinetic_energy: of the failing state (may be inf/nan).
        suggested_dt: a step [s] strictly smaller than `dt` to try.
    """

    def __init__(self, message: str | None = None, *, time: float, dt: float, max_strain: float, reason: str, suggested_dt: float,
                 frame: int | None = None, kind: str | None = None, max_speed: float = math.nan, kinetic_energy: float = math.nan,
                 detail: str | None = None):
        self.time = float(time)
        self.dt = float(dt)
        self.max_strain = float(max_strain)
        self.reason = reason
        self.kind = kind or reason.split(" ")[0]
        self.suggested_dt = float(suggested_dt)
        self.frame = frame
        self.max_speed = float(max_speed)
        self.kinetic_energy = float(kinetic_energy)
        self.detail = detail if detail is not None else (message or reason)
        super().__init__(message if message is not None else self._compose())

    def _compose(self) -> str:
        where = f"in frame {self.frame} at t = {self.time:.6g} s" if self.frame is not None else f"at t = {self.time:.6g} s"
        return f"simulation diverged {where}: {self.detail}"

    def in_frame(self, frame: int) -> SimulationDiverged:
        """The same diagnosis, naming the frame."""
        return SimulationDiverged(time=self.time, dt=self.dt, max_strain=self.max_strain, reason=self.reason,
                                  suggested_dt=self.suggested_dt, frame=frame, kind=self.kind, max_speed=self.max_speed,
                                  kinetic_energy=self.kinetic_energy, detail=self.detail)

    def diagnosis(self) -> dict:
        """The diagnosis as a JSON-safe dict (non-finite numbers as None)."""

        def num(x):
            return float(x) if x is not None and math.isfinite(x) else None

        return {"frame": self.frame, "time_s": num(self.time), "reason": self.reason, "kind": self.kind,
                "max_strain": num(self.max_strain), "max_speed": num(self.max_speed), "kinetic_energy": num(self.kinetic_energy),
                "last_dt": num(self.dt), "suggested_dt": num(self.suggested_dt)}


# -- scene-relative bounds -------------------------------------------------------------------------------------

def _quat_angle(a, b) -> float:
    """Rotation angle [rad] between two quaternions (the short way, as slerp takes it)."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    return 2.0 * math.acos(min(1.0, abs(float(np.dot(a, b)))))


def keyframe_speed(keyframes, radius: float) -> float:
    """The largest speed [m/s] of a point within `radius` [m] of the pivot of a keyframed rigid motion
    (linear translation, slerp rotation between keyframes: |dt/dt| + omega r per segment)."""
    v = 0.0
    for a, b in zip(keyframes, keyframes[1:]):
        span = float(b.time) - float(a.time)
        if span <= 0.0:
            continue
        move = float(np.linalg.norm(np.subtract(b.translation, a.translation)))
        v = max(v, (move + _quat_angle(a.rotation, b.rotation) * radius) / span)
    return v


def _collider_radius(col, cloth_points: np.ndarray) -> float:
    """How far from its own origin a collider's surface points that can meet the cloth lie [m]."""
    if col.shape == "sphere":
        return float(col.radius)
    if col.shape == "capsule":
        return float(col.radius + 0.5 * col.height)
    if col.shape == "cylinder":
        return float(math.hypot(col.radius, 0.5 * col.height))
    if col.shape == "box":
        return 0.5 * float(np.linalg.norm(col.size))
    if col.shape == "mesh":
        verts = col.point_cache.reshape(-1, 3) if col.point_cache is not None else col.vertices
        return float(np.linalg.norm(verts, axis=1).max())
    # a plane is unbounded: what matters is where the cloth is
    if not len(cloth_points):
        return 0.0
    return float(np.linalg.norm(cloth_points - np.asarray(col.position, float), axis=1).max())


def kinematic_speed(model) -> float:
    """The largest speed [m/s] of anything that moves the cloth kinematically: handle particles (keyframes)
    and collider surfaces (keyframes, deforming point caches)."""
    rest = np.asarray(model.rest_positions, float)
    v = 0.0
    for h in model.handles:
        pts = rest[np.asarray(h.particles, np.int64)]
        radius = float(np.linalg.norm(pts - np.asarray(h.pivot, float), axis=1).max()) if len(pts) else 0.0
        v = max(v, keyframe_speed(h.keyframes, radius))
    for col in model.colliders:
        v = max(v, keyframe_speed(col.keyframes, _collider_radius(col, rest)))
        if col.point_cache is not None and len(col.point_cache) > 1:
            step = np.linalg.norm(np.diff(col.point_cache, axis=0), axis=2).max(axis=1)
            v = max(v, float((step / np.diff(col.point_cache_times)).max()))
    return v


def collider_reach(model) -> float:
    """How far [m] a moving collider's surface can carry cloth: over its animated colliders, the largest
    distance between two positions of one surface point (keyframe translations apart, plus the rotation
    between keyframes times the surface's radius; a deforming mesh: twice its vertices' largest displacement
    from the first sample). 0 when no collider moves."""
    rest = np.asarray(model.rest_positions, float)
    reach = 0.0
    for col in model.colliders:
        kf = col.keyframes
        if len(kf) > 1:
            kf = [kf[i] for i in np.unique(np.linspace(0, len(kf) - 1, min(len(kf), 1024)).astype(np.int64))]
            t = np.array([k.translation for k in kf], float)
            move = float(np.linalg.norm(t[:, None, :] - t[None, :, :], axis=2).max())
            turn = 2.0 * max(_quat_angle(kf[0].rotation, k.rotation) for k in kf)  # any two poses: at most twice from the first
            reach = max(reach, move + min(turn, 2.0 * math.pi) * _collider_radius(col, rest))
        if col.point_cache is not None and len(col.point_cache) > 1:
            reach = max(reach, 2.0 * float(np.linalg.norm(col.point_cache - col.point_cache[:1], axis=2).max()))
    return reach


def wind_speed(wind) -> float:
    """The largest speed [m/s] a wind reaches: a :class:`~cloth_warp.wind.GustyWind` in closed form (its
    gust signal is at most 4 sqrt(1/2) = 2 sqrt(2) in magnitude; turning keeps the speed), anything else
    with ``at(time)`` sampled every 10 ms over 10 s."""
    if wind is None:
        return 0.0
    mean = getattr(wind, "mean", None)
    strength = getattr(wind, "strength", None)
    if mean is not None and strength is not None:
        return float(np.linalg.norm(mean)) * (1.0 + abs(float(strength)) * 2.0 * math.sqrt(2.0))
    return max(float(np.linalg.norm(wind.at(t))) for t in np.linspace(0.0, 10.0, 1001))


def forced_strain(model, samples: int = 16, max_particles: int = 128, max_times: int = 256) -> float:
    """The stretch [strain] hard pins and handles impose: max over pairs of pinned/handle particles and over
    time of |target_i - target_j| / |rest_i - rest_j| - 1 (Euclidean rest distance: never below the stretch
    along the cloth). 0 without handles (static pins keep their rest distances). Sampled: keyframe times and
    `samples` points between them (at most `max_times`), at most `max_particles` pinned particles."""
    if not model.handles:
        return 0.0
    rest = np.asarray(model.rest_positions, float)
    ids = np.flatnonzero(model.particle_pinned.numpy() != 0)
    if len(ids) < 2:
        return 0.0
    if len(ids) > max_particles:
        ids = ids[np.linspace(0, len(ids) - 1, max_particles).astype(np.int64)]
    times = sorted({float(k.time) for h in model.handles for k in h.keyframes})
    grid = set(times)
    for a, b in zip(times, times[1:]):
        grid.update(np.linspace(a, b, samples + 1)[1:-1].tolist())
    grid = sorted(grid)
    if len(grid) > max_times:
        grid = [grid[i] for i in np.unique(np.linspace(0, len(grid) - 1, max_times).astype(np.int64))]
    r = rest[ids]
    d0 = np.linalg.norm(r[:, None, :] - r[None, :, :], axis=2)
    mask = d0 > 1e-9
    worst = 0.0
    where = {int(p): k for k, p in enumerate(ids)}
    for t in grid:
        x = r.copy()
        for h in model.handles:
            sel = [where[int(p)] for p in h.particles if int(p) in where]
            if sel:
                x[sel] = h.targets(r[sel], t)
        d = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=2)
        worst = max(worst, float((d[mask] / d0[mask]).max()) - 1.0)
    return max(worst, 0.0)


def stable_dt(model, solver) -> float | None:
    """The explicit integrators' stability step [s]: h omega_max < c (c = 2 for Euler and midpoint, 2.83 for
    RK4) with omega_max^2 <= max_i (2 sum_j k_ij + sum_e sum_l |K_e,il| + k_pin,i) / m_i (Gershgorin over linear
    springs, membrane elements' 3x3 blocks at rest and soft pins; bending triples are left out). None for
    implicit solvers."""
    c = getattr(solver, "stability", None)
    if c is None or model.particle_count == 0:
        return None
    n = model.particle_count
    nl = model.linear_spring_count
    ends = model.spring_indices.numpy().reshape(-1, 2)[:nl]
    k = model.spring_stiffness.numpy()[:nl].astype(np.float64)
    ksum = np.bincount(ends[:, 0], k, minlength=n) + np.bincount(ends[:, 1], k, minlength=n)
    mass = model.particle_mass.numpy().astype(np.float64)
    extra = np.zeros(n)
    if model.membrane_count:
        extra = membrane_element_row_bound(model.membrane_vertices.numpy().reshape(-1, 3), model.membrane_rest_inverse.numpy(),
                                           model.membrane_rest_area.numpy(), model.membrane_stiffness.numpy(), n)
    if model.plate_count:
        extra = extra + stencil_row_bound(model.plate_offsets.numpy(), model.plate_points.numpy(), model.plate_weights.numpy(),
                                          model.plate_stiffness.numpy(), n)
    free = (model.particle_pinned.numpy() == 0) & (mass > 0.0)
    if not free.any():
        return None
    w2 = (2.0 * ksum[free] + extra[free] + model.particle_pin_stiffness.numpy()[free]) / mass[free]
    w = math.sqrt(float(w2.max())) if w2.max() > 0.0 else 0.0
    return c / w if w > 0.0 else None


class DivergenceBounds:
    """The bounds beyond which a state of one scene counts as diverged (thresholds from :class:`StepCheck`).

    Healthy cloth never comes near them; a diverging integrator passes them within a few steps, also when
    it stays finite (explicit Euler on stiff cloth under strain limiting keeps the strain at the limit while
    particles reach 1e5 m/s; without limiting it reaches strains of 1e4; implicit Euler with a loose solve
    (residual 3e-2) and no strain limit drifts into strain 60 and 140 m/s after 2 s on the hanging cloth).
    The factors below are :class:`StepCheck`'s defaults. Measured on every shipped scene at full resolution
    (and on 32^2 explicit variants at their stable substeps): the largest strain is 0.41 of its bound
    (sphere_shot; 0.33 on the Cusick rim, 0.31 in the twist), the largest speed 0.11 of its bound, the largest
    kinetic energy 0.15.

    * **strain**: structural/shear strain above max(1.0, 5 x the strain limit) with a strain limiter (a
      spring twice its rest length is a failed limiter: healthy limited cloth stays at the limit, 20-40 %
      where it wraps a sharp rim), 9.0 without one (ten times the rest length: cloth without strain limiting
      legitimately stretches tens of percent), plus the largest strain the scene imposes: the stretch that
      pins and handles force (:func:`forced_strain`), the cloth's initial strain, and for moving colliders
      their reach over the shortest structural spring (:func:`collider_reach`: a collider has the last word
      over the strain limiter, and the shipped sphere_shot leaves springs at 27x their rest length).
    * **energy**: the energy available to the cloth up to the state checked is
      E = KE_0 + U_0 + max(0, W_g) + M (v_drive^2 + v_floor^2) / 2, with KE_0 and U_0 the initial kinetic and
      spring energy, W_g the work gravity has done on the free particles so far (measured by the same
      statistics launch: it grows as the cloth comes down, not with time, so a cloth lying on the ground
      keeps a tight bound), M the free mass, v_drive = 2 x the fastest handle or collider surface (a moving
      wall hands on up to twice its speed) + the strongest wind (drag pulls the cloth towards it), and
      v_floor = 1 m/s. Without dissipation, and with springs' energy never negative, KE <= E; kinetic energy
      above 4 E (an RMS speed above twice the scene's speed scale) is divergence.
    * **speed**: a free particle faster than 20 x sqrt(2 E / M) (twenty times the speed the whole cloth would
      have with all the available energy): the margin covers energy gathering in a few particles (a whipping
      edge, a fold snapping through) and sphere_shot's 20 m/s ball (v_drive = 40 m/s).

    The checks read the four numbers :class:`~cloth_warp.diagnostics.Diagnostics` measures every frame
    anyway (plus gravity's work, added to the same launch), so they cost a few float operations per frame.
    """

    def __init__(self, model, solver: SolverBase, check: StepCheck | None = None, wind=None):
        self.model = model
        self.solver = solver
        self.check = c = check or StepCheck()
        mass = model.particle_mass.numpy().astype(np.float64)
        free = model.particle_pinned.numpy() == 0
        self.mass_free = float(mass[free].sum())
        x0 = model.particle_q.numpy().astype(np.float64)
        v0 = model.particle_qd.numpy().astype(np.float64)
        self.kinetic_energy0 = 0.5 * float((mass[free] * (v0[free] ** 2).sum(1)).sum())
        nl = model.linear_spring_count
        ends = model.spring_indices.numpy().reshape(-1, 2)
        rest = model.spring_rest_length.numpy().astype(np.float64)
        length = np.linalg.norm(x0[ends[:, 0]] - x0[ends[:, 1]], axis=1) if len(ends) else np.zeros(0)
        k = model.spring_stiffness.numpy().astype(np.float64)
        self.spring_energy0 = 0.5 * float((k[:nl] * (length[:nl] - rest[:nl]) ** 2).sum())
        if model.membrane_count:  # the elastic energy of membrane elements counts as spring energy here
            self.spring_energy0 += float(membrane_element_energy(x0, model.membrane_vertices.numpy().reshape(-1, 3),
                                                                 model.membrane_rest_inverse.numpy(), model.membrane_rest_area.numpy(),
                                                                 model.membrane_stiffness.numpy()).sum())
        limited = model.spring_limited.numpy() != 0
        self.initial_strain = float((length[limited] / rest[limited] - 1.0).max()) if limited.any() else 0.0
        self.forced_strain = forced_strain(model)
        # a moving collider has the last word over the strain limiter: a particle it carries away from its
        # neighbours stretches their springs by up to its reach (sphere_shot's ball, 1 m at 20 m/s through a
        # 40^2 sheet of 15 mm cells, leaves springs at up to 27x their rest length); the shortest limited
        # springs (floored at a tenth of the median, against slivers) take the most strain
        lengths = rest[limited]
        shortest = max(float(lengths.min()), 0.1 * float(np.median(lengths))) if len(lengths) else 0.0
        reach = collider_reach(model)
        self.collider_strain = reach / shortest if reach > 0.0 and shortest > 0.0 else 0.0
        limiter = solver.strain_limiter
        base = max(c.strain_floor, c.strain_factor * limiter.max_strain) if limiter is not None else c.strain_unlimited
        imposed = max(self.forced_strain, self.initial_strain, self.collider_strain, 0.0)
        self.max_strain = float(c.max_strain) if c.max_strain is not None else base + imposed
        self.kinematic_speed = kinematic_speed(model)
        self.wind_speed = wind_speed(wind)
        self.stable_dt = stable_dt(model, solver)

    # -- the bounds ------------------------------------------------------------------------------------------
    @property
    def drive_speed(self) -> float:
        """v_drive [m/s]: twice the fastest handle or collider surface plus the strongest wind."""
        return 2.0 * self.kinematic_speed + self.wind_speed

    def note_wind(self, velocity) -> None:
        """Count a wind velocity [m/s] set on the control (the bound keeps the strongest seen)."""
        s = float(np.linalg.norm(np.asarray(velocity, np.float64)))
        if math.isfinite(s) and s > self.wind_speed:
            self.wind_speed = s

    def available_energy(self, stats: StepStats) -> float:
        """E [J]: what the cloth can have gathered up to the state `stats` describes (see the class)."""
        gw = stats.gravity_work if math.isfinite(stats.gravity_work) else 0.0
        v2 = self.drive_speed ** 2 + self.check.speed_floor ** 2
        return self.kinetic_energy0 + self.spring_energy0 + max(0.0, gw) + 0.5 * self.mass_free * v2

    def speed_bound(self, stats: StepStats) -> float:
        """The largest healthy free-particle speed [m/s] for the state `stats` describes."""
        if self.check.max_speed is not None:
            return float(self.check.max_speed)
        if self.mass_free <= 0.0:
            return math.inf
        return self.check.speed_factor * math.sqrt(2.0 * self.available_energy(stats) / self.mass_free)

    def energy_bound(self, stats: StepStats) -> float:
        """The largest healthy kinetic energy [J] for the state `stats` describes."""
        if self.mass_free <= 0.0:
            return math.inf
        return self.check.energy_factor * self.available_energy(stats)

    def violation(self, stats: StepStats) -> tuple[str, str] | None:
        """(kind, reason) when the state is beyond a bound, else None (NaN counts as beyond)."""
        if not stats.finite:
            return "non-finite", f"non-finite positions or velocities ({stats.nonfinite} particles)"
        if not stats.max_strain <= self.max_strain:
            return "strain", f"strain {stats.max_strain:.3g} above the bound {self.max_strain:.3g}"
        bound = self.speed_bound(stats)
        if not stats.max_speed <= bound:
            return "speed", f"speed {stats.max_speed:.3g} m/s above the bound {bound:.3g} m/s"
        bound = self.energy_bound(stats)
        if not stats.kinetic_energy <= bound:
            return "energy", f"kinetic energy {stats.kinetic_energy:.3g} J above the bound {bound:.3g} J"
        return None

    def suggest_dt(self, failed_dt: float) -> float:
        """A step [s] strictly smaller than `failed_dt`: half of it, or 0.9 x the explicit integrators'
        stability step (:func:`stable_dt`) when that is smaller."""
        dt = 0.5 * float(failed_dt)
        if self.stable_dt is not None and 0.9 * self.stable_dt < dt:
            dt = 0.9 * self.stable_dt
        return dt

    def checkpoint_state(self) -> dict:
        return {"wind_speed": float(self.wind_speed)}

    def restore_state(self, state: dict) -> None:
        self.wind_speed = float(state["wind_speed"])


# -- adaptive stepping ----------------------------------------------------------------------------------------

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


_REPORT_SCALARS = ("steps", "rejected", "dt_min", "dt_max", "max_strain", "iterations")
MAX_STEP_GRAPHS = 8  # recorded trial steps kept (one per step size: the nominal dt, its halvings, a frame's remainder)


class AdaptiveStepper:
    """Advances a state over an interval with a solver, backing off on divergence.

    A trial step is rejected when it ends beyond the scene's :class:`DivergenceBounds` (non-finite values,
    strain, speed, kinetic energy), when the linear solve's residual is non-finite, or (see
    :class:`StepCheck`) on a strain jump, kinetic-energy blow-up or a non-converged linear solve or strain
    limiter; dt is then halved and the step retried from the same state. After `grow_after` good steps dt
    doubles again (never above the nominal dt, and not above half the smallest dt that failed during the
    current interval). If dt would fall below `dt_min`, :class:`SimulationDiverged` is raised with time,
    reason, max strain, the step that failed and a smaller one to try; the state passed in is left at the
    last good step (never NaN).

    Forward-only (it reads statistics on the host every step). `bounds` defaults to the solver's scene
    without wind; the wind set on the control is then read once per :meth:`advance` and counted. With `capture`
    (when the solver's step can be recorded: :attr:`SolverBase.capturable`), a trial step and its statistics are
    recorded as a graph the first time a step size is used and replayed for every later step of that size (the
    last :data:`MAX_STEP_GRAPHS` sizes are kept); a rejected step is simply run again at the smaller size. The
    control (handles, collider poses) is set on the host before each replay, as without capture.
    """

    def __init__(self, solver: SolverBase, dt: float, *, dt_min: float = 1.0e-6, grow_after: int = 8, check: StepCheck | None = None,
                 bounds: DivergenceBounds | None = None, capture: bool = False):
        if not (dt > 0.0):
            raise ValueError(f"dt must be positive, got {dt!r}")
        self.solver = solver
        self.model = solver.model
        self.nominal_dt = float(dt)
        self.dt = float(dt)
        self.dt_min = float(dt_min)
        self.grow_after = int(grow_after)
        self.check = check or (bounds.check if bounds is not None else StepCheck())
        self._watch_wind = bounds is None
        self.bounds = bounds or DivergenceBounds(self.model, solver, self.check)
        self.diagnostics = Diagnostics(self.model)
        self.trial = self.model.state(requires_grad=False)
        self.report = StepperReport()
        self.interval = StepperReport()
        self._stats: StepStats | None = None
        self._good = 0
        self.capture = bool(capture) and solver.capturable
        self._graphs: dict = {}  # (dt, state arrays, control) -> the recorded trial step

    def forget_graphs(self) -> None:
        """Drop the recorded trial steps (the solver's or the diagnostics' arrays were replaced)."""
        self._graphs.clear()

    def _trial_step(self, state: State, control: Control, h: float) -> None:
        """Step `state` by h into the trial state and measure it on the device (replayed from a graph per h when
        capturing)."""
        if not self.capture:
            self.solver.step(state, self.trial, control, h)
            self.diagnostics.launch(self.trial)
            return
        key = (h, state.particle_q.ptr, state.particle_qd.ptr, id(control), id(self.diagnostics))
        graph = self._graphs.get(key)
        if graph is None:
            if len(self._graphs) >= MAX_STEP_GRAPHS:
                self._graphs.pop(next(iter(self._graphs)))  # the oldest size
            with wp.ScopedCapture(device=self.model.device) as cap:
                self.solver.step(state, self.trial, control, h)
                self.diagnostics.launch(self.trial)
            graph = self._graphs[key] = cap.graph
        wp.capture_launch(graph)

    def reset_report(self):
        self.report = StepperReport()

    def _rejection(self, new: StepStats, old: StepStats | None, h: float) -> tuple[str, str] | None:
        """(kind, reason) when the trial step is bad, else None."""
        c = self.check
        failure = self.solver.last_failure  # the cause, before what it does to the state
        if failure is not None:
            return failure, f"{failure} in the linear solve (after {self.solver.last_iterations} iterations)"
        bad = self.bounds.violation(new)
        if bad is not None:
            return bad
        if c.require_convergence and not self.solver.converged:
            return "unconverged", (f"linear solver did not converge (residual {self.solver.last_residual:.2e} after "
                                   f"{self.solver.last_iterations} iterations)")
        limiter = self.solver.strain_limiter
        if limiter is not None:
            if limiter.last_initial_excess > c.max_strain_jump:
                return "limiter", f"strain {limiter.last_initial_excess + limiter.max_strain:.3g} before strain limiting (limit {limiter.max_strain:g})"
            if c.require_convergence and not limiter.converged:
                return "limiter", f"strain limiting did not converge in {limiter.last_iterations} sweeps"
        if old is not None:
            if new.max_strain - old.max_strain > c.max_strain_jump:
                return "strain jump", f"strain jumped from {old.max_strain:.3g} to {new.max_strain:.3g} in one step"
            # what one step can add from rest: gravity's g h, and a handle, moving collider or wind handing on its
            # drive speed (a ball hitting a resting cloth is not a blow-up; halving the step would not change it)
            g = math.sqrt(sum(x * x for x in self.model.gravity))
            floor = 0.5 * self.diagnostics.total_mass_free * ((g * h) ** 2 + self.bounds.drive_speed ** 2)
            if new.kinetic_energy > c.energy_growth * (old.kinetic_energy + floor):
                return "energy growth", f"kinetic energy grew from {old.kinetic_energy:.3g} J to {new.kinetic_energy:.3g} J in one step"
        return None

    def advance(self, state: State, control: Control, t0: float, duration: float) -> float:
        """Advance `state` in place from time t0 over `duration` [s]; returns the time reached."""
        if self._stats is None:
            self._stats = self.diagnostics.measure(state)
        if self._watch_wind:
            self.bounds.note_wind(control.wind.numpy()[0])
        t, end = t0, t0 + duration
        dt_cap = self.nominal_dt
        eps = 1e-9 * max(duration, 1e-12)
        r = self.report
        interval = self.interval = StepperReport()  # this call's steps alone
        while t < end - eps:
            h = min(self.dt, end - t)
            self.model.update_control(control, t + h, h)
            self._trial_step(state, control, h)
            stats = self.diagnostics.read()
            bad = self._rejection(stats, self._stats, h)
            if bad is not None:
                kind, reason = bad
                for p in self.solver.passes:
                    p.discard_step()  # the frame's records keep accepted steps only
                r.rejected += 1
                interval.rejected += 1
                r.reasons[kind] = r.reasons.get(kind, 0) + 1
                dt_cap = min(dt_cap, h / 2.0)
                self.dt = h / 2.0
                self._good = 0
                log.debug("t=%.6f s: rejected step of %.3g s (%s)", t, h, reason)
                if self.dt < self.dt_min:
                    raise self._diverged(kind, reason, stats, t, h)
                continue
            state.assign(self.trial)
            self._stats = stats
            t += h
            for rep in (r, interval):
                rep.steps += 1
                rep.dt_min = min(rep.dt_min, h)
                rep.dt_max = max(rep.dt_max, h)
                rep.max_strain = max(rep.max_strain, stats.max_strain)
                rep.iterations += self.solver.last_iterations
            self._good += 1
            if self._good >= self.grow_after and self.dt < self.nominal_dt:
                self.dt = min(2.0 * self.dt, self.nominal_dt, max(dt_cap, self.dt))
                self._good = 0
        return t

    def _diverged(self, kind: str, reason: str, stats: StepStats, t: float, h: float) -> SimulationDiverged:
        suggested = self.bounds.suggest_dt(h)
        good = self._stats.max_strain if self._stats is not None else math.nan
        strain = stats.max_strain if math.isfinite(stats.max_strain) else good
        built_up = ""
        if self._stats is not None and kind in ("strain", "speed", "energy"):
            b, s = self.bounds, self._stats
            ratio = {"strain": s.max_strain / b.max_strain, "speed": s.max_speed / b.speed_bound(s),
                     "energy": s.kinetic_energy / b.energy_bound(s)}[kind]
            if ratio > 0.5:  # no smaller step can help: the accepted steps before it drifted there
                built_up = f" (the last good step was already at {100 * ratio:.0f} % of that bound: it built up over accepted steps)"
        detail = (f"{reason}{built_up}; the step of {h:.3g} s was rejected and half of it is below the floor dt_min = "
                  f"{self.dt_min:.3g} s; max strain {stats.max_strain:.3g} (last good step {good:.3g}); try a smaller dt (<= "
                  f"{suggested:.3g} s: lower solver.dt_min), stronger strain limiting or the implicit_euler integrator")
        return SimulationDiverged(time=t, dt=h, max_strain=strain, reason=reason, kind=kind, suggested_dt=suggested,
                                  max_speed=stats.max_speed, kinetic_energy=stats.kinetic_energy, detail=detail)

    # -- checkpoints --------------------------------------------------------------------------------------------
    def checkpoint_state(self) -> dict:
        """What the stepper carries from one :meth:`advance` to the next, as numpy arrays and scalars."""
        out = {"dt": float(self.dt), "nominal_dt": float(self.nominal_dt), "good": int(self._good),
               "has_stats": self._stats is not None, "report_reasons": json.dumps(self.report.reasons, sort_keys=True)}
        if self._stats is not None:
            s = self._stats
            out["stats"] = np.array([s.max_strain, s.kinetic_energy, s.max_speed, s.nonfinite, s.gravity_work], np.float64)
        for key in _REPORT_SCALARS:
            out[f"report_{key}"] = getattr(self.report, key)
        if self._watch_wind:  # bounds of its own (a Simulator's are in the Simulator's checkpoint)
            out.update({f"bounds.{k}": v for k, v in self.bounds.checkpoint_state().items()})
        return out

    def restore_state(self, state: dict) -> None:
        if not math.isclose(float(state["nominal_dt"]), self.nominal_dt, rel_tol=1e-12):
            raise ValueError(f"checkpoint of an adaptive stepper with nominal dt {state['nominal_dt']} s, this one has {self.nominal_dt} s")
        self.dt = float(state["dt"])
        self._good = int(state["good"])
        if bool(state["has_stats"]):
            s = np.asarray(state["stats"], np.float64)
            self._stats = StepStats(float(s[0]), float(s[1]), float(s[2]), int(s[3]), float(s[4]))
        else:
            self._stats = None
        rep = StepperReport(reasons=json.loads(str(state["report_reasons"])))
        for key in _REPORT_SCALARS:
            setattr(rep, key, type(getattr(rep, key))(state[f"report_{key}"]))
        self.report = rep
        self.interval = StepperReport()
        if self._watch_wind and "bounds.wind_speed" in state:
            self.bounds.restore_state({k[len("bounds."):]: v for k, v in state.items() if k.startswith("bounds.")})
