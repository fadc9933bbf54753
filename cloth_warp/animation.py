"""The animated part of a Control, evaluated on the device from a device clock (capturable).

:meth:`Model.update_control` sets handle pin targets, collider poses and deforming colliders on the host,
and the Simulator sets gusty wind once per frame with ``GustyWind.at``. A :class:`ControlAnimator` computes
the same values with kernels that read the time from ``clock``, a device array, so a frame of
``advance_clock`` + ``apply`` per substep can be recorded once with ``wp.ScopedCapture`` and replayed with
no host work. Results equal the host's up to float32 rounding (the same float64 arithmetic, operation for
operation, rounded once to float32; see ``kernels/animation.py``). Point caches are stored as float32 (half
the memory of the host's float64): bit for bit for a float32 cache (as USD stores points); otherwise vertices
differ by up to one float32 ulp of the cache's extent and velocities by about that over the sample interval.

On the CPU the BVH refit of a deforming (point-cache) mesh collider is a host call between graphs. Warp 1.19
records ``wp.Bvh.refit`` into a CPU graph but not ``wp.Mesh.refit`` (``wp_mesh_refit_host`` would run once at
capture time and never be replayed, so the graph would query a stale tree). :meth:`apply` therefore refits through
:func:`cloth_warp.graphs.host_call`, and a frame recorded with :func:`cloth_warp.graphs.record` replays as its graphs
with the refits between them. A plain ``wp.ScopedCapture`` of it raises. On CUDA the refit is a sequence of kernels
and a stream-ordered temporary allocation, recorded into the graph where the device supports memory pools.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from .graphs import host_call
from .kernels import animation as ka
from .model import Control, Model


def refit_mesh_bvh(mesh: wp.Mesh) -> None:
    """Refit a deforming collider mesh's BVH to its points: on the CPU a host call between a frame's graphs. (A function,
    not the bound ``mesh.refit``: ``wp.Mesh.refit`` is looked up at every replay, so a profiler that wraps it, as
    :class:`~cloth_warp.profiling.LaunchCounter` does, sees the replayed refits.)"""
    mesh.refit()


def _keyframe_table(keyframe_lists, device) -> tuple[wp.array, wp.array, wp.array, wp.array]:
    """(first (objects + 1,) int32, times (k,) float64 [s], translations (k,) vec3d [m], rotations (k,) vec4d
    (x, y, z, w)) of the concatenated keyframe lists."""
    first = np.zeros(len(keyframe_lists) + 1, np.int32)
    first[1:] = np.cumsum([len(kfs) for kfs in keyframe_lists])
    frames = [kf for kfs in keyframe_lists for kf in kfs]
    times = np.array([kf.time for kf in frames], np.float64)
    translations = np.array([kf.translation for kf in frames], np.float64).reshape(-1, 3)
    rotations = np.array([kf.rotation for kf in frames], np.float64).reshape(-1, 4)
    return (wp.array(first, dtype=wp.int32, device=device), wp.array(times, dtype=wp.float64, device=device),
            wp.array(translations, dtype=wp.vec3d, device=device), wp.array(rotations, dtype=wp.vec4d, device=device))


class ControlAnimator:
    """Writes a Control's animated inputs from a device clock with kernel launches only.

    Built once per model (every table is uploaded here); :meth:`apply` sets what
    ``Model.update_control(control, time, dt)`` sets for time = clock[0], dt = clock[1], and
    :meth:`apply_wind` what ``control.set_wind(wind.at(clock[0] + offset))`` sets. ``control.time`` (a
    host float) is not touched: whoever replays a graph keeps it.

    Args:
        model: the model whose handles and colliders are animated.
        wind: a :class:`~cloth_warp.wind.GustyWind` for :meth:`apply_wind` (None: no wind updates).
    """

    def __init__(self, model: Model, wind=None):
        device = model.device
        self.model = model
        """The model animated (its handles, colliders and collider meshes are read here, once)."""
        self.device = device
        """Warp device of every array."""
        self.clock = wp.zeros(4, dtype=wp.float64, device=device)  # time [s], dt [s], origin [s], steps since the origin
        """[time at the end of the step [s], the step's length dt [s]], shape (2,), float64."""

        # -- handles: one row per (particle, handle) pair; a particle in several handles follows the last --
        owner: dict[int, int] = {}
        for h_index, h in enumerate(model.handles):
            for p in np.asarray(h.particles).reshape(-1):
                owner[int(p)] = h_index
        particles = np.array(sorted(owner), np.int32)
        self.handle_count = len(model.handles)
        """The number of handles."""
        self.handle_member_count = len(particles)
        """m, the number of handle particles."""
        (self.handle_key_first, self.handle_key_times, self.handle_key_translations,
         self.handle_key_rotations) = _keyframe_table([h.keyframes for h in model.handles], device)
        """Handles' keyframes: handle j's are first[j] .. first[j + 1] - 1; times [s] float64, translations [m]
        vec3d, rotations (x, y, z, w) vec4d, shape (keyframes,); first int32, shape (handles + 1,)."""
        self.handle_pivot = wp.array(np.array([h.pivot for h in model.handles], np.float64).reshape(-1, 3),
                                     dtype=wp.vec3d, device=device)
        """The point each handle turns about [m], shape (handles,), vec3d."""
        self.handle_particle = wp.array(particles, dtype=wp.int32, device=device)
        """Particle index of each handle particle, shape (m,), int32."""
        self.handle_of_particle = wp.array(np.array([owner[int(p)] for p in particles], np.int32), dtype=wp.int32,
                                           device=device)
        """The handle each handle particle follows, shape (m,), int32."""
        rest = np.asarray(model.rest_positions, np.float64).reshape(-1, 3)[particles] if len(particles) else np.zeros((0, 3))
        self.handle_rest = wp.array(rest, dtype=wp.vec3d, device=device)
        """Rest position of each handle particle [m], shape (m,), vec3d."""

        # -- colliders: every pose row is written (static ones with their fixed pose) -----------------
        cols = list(model.colliders)
        self.collider_count = len(cols)
        """The number of colliders (rows written in the control's transforms)."""
        self.colliders_animated = any(c.animated for c in cols)
        """Whether any collider moves or deforms (else :meth:`apply` leaves the poses alone)."""
        (self.collider_key_first, self.collider_key_times, self.collider_key_translations,
         self.collider_key_rotations) = _keyframe_table([c.keyframes for c in cols], device)
        """Colliders' keyframes, as the handles' (a static collider has none)."""
        self.collider_position = wp.array(np.array([c.position for c in cols], np.float64).reshape(-1, 3),
                                          dtype=wp.vec3d, device=device)
        """Initial position of each collider's frame [m], shape (colliders,), vec3d."""
        self.collider_rotation = wp.array(np.array([c.rotation for c in cols], np.float64).reshape(-1, 4),
                                          dtype=wp.vec4d, device=device)
        """Initial orientation (x, y, z, w) of each collider, shape (colliders,), vec4d."""

        # -- deforming (point-cache) mesh colliders ------------------------------------------------
        self.point_caches: list[tuple[wp.Mesh, wp.array, wp.array]] = []
        """Per deforming collider: (its wp.Mesh, sample times [s] (samples,) float64, vertices in its local frame
        [m] (samples, vertices) vec3 float32), uploaded once."""
        for k, c in enumerate(cols):
            if c.deforming:
                self.point_caches.append((
                    model.collider_meshes[k],
                    wp.array(np.asarray(c.point_cache_times, np.float64), dtype=wp.float64, device=device),
                    wp.array(np.asarray(c.point_cache, np.float32), dtype=wp.vec3, device=device),
                ))

        # -- attachments: per attachment its particles, triangles, weights and offsets, uploaded once ----------
        self.attachments: list[tuple[int, wp.array, wp.array, wp.array, wp.array]] = []
        """Per attachment: (collider index, particles int32 (a,), triangles vec3i (a,), weights vec3 (a,), offsets [m] in the
        triangle frame vec3 (a,))."""
        for a in model.attachments:
            self.attachments.append((
                a.collider,
                wp.array(np.asarray(a.particles, np.int32), dtype=wp.int32, device=device),
                wp.array(np.asarray(a.triangles, np.int32), dtype=wp.vec3i, device=device),
                wp.array(np.asarray(a.weights, np.float32), dtype=wp.vec3, device=device),
                wp.array(np.asarray(a.offset, np.float32), dtype=wp.vec3, device=device),
            ))

        # -- gusty wind ------------------------------------------------------------------------------
        self.wind = wind
        """The GustyWind :meth:`apply_wind` evaluates (None: none)."""
        if wind is not None:
            omega = 2.0 * np.pi * wind.frequencies  # the host's first product, kept bit for bit
            gusts = wind.strength, wind.turn
            self._wind_args = [wp.vec3d(*wind.mean), wp.float64(gusts[0]), wp.float64(gusts[1]), wp.vec3d(*wind.up),
                               wp.vec4d(*omega[0]), wp.vec4d(*wind.phases[0]), wp.vec4d(*omega[1]),
                               wp.vec4d(*wind.phases[1]), wp.float64(math.pi / 180.0)]

    # -- what is animated ---------------------------------------------------------------------------
    @property
    def active(self) -> bool:
        """True when anything is animated: handles, attachments, moving or deforming colliders, or a gusty wind."""
        return self.handle_member_count > 0 or bool(self.attachments) or self.colliders_animated or self.gusty

    @property
    def gusty(self) -> bool:
        """True when the wind changes with time (:meth:`apply_wind` has something to do every frame)."""
        return self.wind is not None and not self.wind.steady

    @property
    def capture_blocker(self) -> str | None:
        """Why :meth:`apply` cannot be recorded into a graph on this device, or None when it can."""
        if not self.point_caches or self.device.is_cpu:  # (the CPU's refits: host calls between graphs)
            return None
        if not wp.is_mempool_supported(self.device):
            return f"deforming mesh colliders: wp.Mesh.refit() allocates scan memory; {self.device} has no memory pool"
        return None

    @property
    def capturable(self) -> bool:
        """Whether a frame of :meth:`advance_clock` + :meth:`apply` can be recorded (:func:`cloth_warp.graphs.record`)
        on this device."""
        return self.capture_blocker is None

    @property
    def host_calls(self) -> bool:
        """Whether :meth:`apply` makes host calls (CPU BVH refits) that a recorded frame replays between its graphs."""
        return bool(self.point_caches) and self.device.is_cpu

    # -- the clock ------------------------------------------------------------------------------------
    def set_clock(self, time: float, dt: float = 0.0):
        """Set the clock to a step ending at `time` [s] and lasting `dt` [s], the origin of the steps that follow
        (a host write: eager use)."""
        self.clock.assign(np.array([time, dt, time, 0.0], np.float64))

    def set_steps(self, steps: int, dt: float):
        """Set the clock to the end of step `steps` of `dt` [s] from time 0, as :meth:`advance_clock` counts them
        from a clock set to 0 (time = steps x dt: a run restored there goes on with the clock of the run that went
        through)."""
        self.clock.assign(np.array([steps * dt, dt, 0.0, steps], np.float64))

    def advance_clock(self, dt: float):
        """Move the clock to the next step: time = origin + steps x dt [s], step length dt (one kernel; capturable)."""
        wp.launch(ka.advance_clock, dim=1, inputs=[wp.float64(dt)], outputs=[self.clock], device=self.device)

    # -- the control --------------------------------------------------------------------------------
    def apply(self, control: Control):
        """Write the control for the step the clock describes: handles' and attachments' pin targets at its end,
        colliders' poses at its start and end, deforming colliders' vertices and vertex velocities (and their BVH
        refits). Launches only (no host reads, no allocation), and on the CPU the refits as host calls, so it can be
        recorded with :func:`cloth_warp.graphs.record` where :attr:`capturable`."""
        if self.point_caches and self.device.is_capturing and self.capture_blocker is not None:
            raise RuntimeError(f"ControlAnimator.apply cannot be captured: {self.capture_blocker}")
        if self.handle_member_count:
            wp.launch(ka.handle_pin_targets, dim=self.handle_member_count,
                      inputs=[self.clock, self.handle_key_first, self.handle_key_times, self.handle_key_translations,
                              self.handle_key_rotations, self.handle_pivot, self.handle_particle,
                              self.handle_of_particle, self.handle_rest],
                      outputs=[control.pin_target], device=self.device)
        if self.colliders_animated:
            wp.launch(ka.collider_poses, dim=self.collider_count,
                      inputs=[self.clock, self.collider_key_first, self.collider_key_times, self.collider_key_translations,
                              self.collider_key_rotations, self.collider_position, self.collider_rotation],
                      outputs=[control.collider_transform_start, control.collider_transform_end], device=self.device)
        for mesh, times, cache in self.point_caches:
            wp.launch(ka.point_cache_vertices, dim=cache.shape[1], inputs=[self.clock, times, cache],
                      outputs=[mesh.points, mesh.velocities], device=self.device)
            if self.device.is_cpu:
                host_call(self.device, refit_mesh_bvh, mesh)
            else:
                mesh.refit()
        for collider, particles, triangles, weights, offset in self.attachments:
            wp.launch(ka.attachment_pin_targets, dim=len(particles),
                      inputs=[particles, triangles, weights, offset, self.model.collider_meshes[collider].points, collider,
                              control.collider_transform_end],
                      outputs=[control.pin_target], device=self.device)

    def apply_wind(self, control: Control, time_offset: float = 0.0):
        """Write the wind velocity at clock time + `time_offset` [s] into control.wind (one kernel; the
        Simulator's once-per-frame wind is at the frame's midpoint: the frame's start time in the clock and
        half a frame as the offset). Does nothing without a wind."""
        if self.wind is None:
            return
        wp.launch(ka.gusty_wind, dim=1, inputs=[self.clock, wp.float64(time_offset), *self._wind_args],
                  outputs=[control.wind], device=self.device)
