"""Shared solver machinery: the step interface, scratch buffers and Provot strain limiting."""

from __future__ import annotations

import heapq

import numpy as np
import warp as wp

from ..kernels import constraints as kc
from ..kernels import diagnostics as kd
from ..kernels import forces as kf
from ..model import Control, Model, State


class StrainLimiter:
    """Provot (1995) deformation constraints: no structural/shear spring longer than (1 + max_strain) L.

    Each sweep visits the springs colour by colour (no two springs of a colour share a particle), moving
    the endpoints of over-stretched springs toward each other by `relaxation` times the excess (never
    below the rest length), split by inverse mass (all of it to the free end when the other is pinned). Velocities are then corrected by the position
    change over dt (Provot's "inverse dynamics"), so the limiter adds no momentum: the centre of mass
    of a free sheet moves as without it.

    Each sweep starts with long-range attachments (Kim, Chentanez & Mueller 2012) keep every particle
    within (1 + max_strain) times its shortest rest path along limited springs from the nearest
    `attachments` groups of hard-pinned particles. That bound holds in any state that satisfies the
    spring limits, and it removes the global stretch of a cloth hanging from a few points, which local
    Gauss-Seidel passes alone would need O(n^2) sweeps to remove.

    Gradients flow through the active (clamped) constraints only: the clamp is piecewise.
    """

    def __init__(self, model: Model, max_strain: float = 0.1, iterations: int = 4, attachments: int = 4,
                 tolerance: float | None = 1.0e-3, max_iterations: int = 128, relaxation: float = 1.5):
        from ..validation import LIMITS, check_number

        max_strain = check_number("max_strain", max_strain, LIMITS["strain_limit"])
        if max_strain <= 0.0:
            raise ValueError(f"max_strain: must be > 0 (0.1 = 10 %), got {max_strain!r}")
        iterations = check_number("iterations", iterations, LIMITS["iterations"])
        max_iterations = check_number("max_iterations", max_iterations, LIMITS["iterations"])
        if tolerance is not None:
            tolerance = check_number("tolerance", tolerance, LIMITS["tolerance"])
        self.model = model
        self.max_strain = float(max_strain)
        self.iterations = int(iterations)
        self.tolerance = tolerance
        self.max_iterations = max(int(max_iterations), self.iterations)
        self.excess = wp.zeros(1, dtype=float, device=model.device)
        # Report of the last apply() (measured only on checked, i.e. forward and uncaptured, runs):
        # how far the integrator's output exceeded the limit, and whether the sweeps met the tolerance.
        self.last_initial_excess = 0.0
        self.converged = True
        if not (1.0 <= relaxation < 2.0):
            raise ValueError(f"strain-limit relaxation must be in [1, 2), got {relaxation!r}")
        self.relaxation = float(relaxation)
        self.last_iterations = 0
        ids, dist = attachment_table(model, attachments)
        self.attachment_count = ids.shape[1]

        if self.attachment_count:
            self.attachment_particle = wp.array(ids, dtype=wp.int32, device=model.device)
            self.attachment_rest_distance = wp.array(dist.astype(np.float32), dtype=float, device=model.device)

    @property
    def active(self) -> bool:
        return self.model.strain_limit_color_count > 0

    def apply(self, solver: SolverBase, x_in: wp.array, v_in: wp.array, state_out: State, dt: float):
        """Limit x_in into state_out.particle_q and correct v_in into state_out.particle_qd.

        Runs `iterations` sweeps over all colours; then, when a tolerance is set and the run is neither
        taped nor being captured into a graph, more sweeps (up to `max_iterations`) until no limited
        spring exceeds the limit by more than `tolerance` (strain). Forward runs sweep in place, one thread
        per spring of a colour; taped runs write every pass to a fresh array (one thread per particle).
        """
        m = self.model
        rg = x_in.requires_grad
        checked = self.tolerance is not None and not rg and not m.device.is_capturing
        if checked:
            self.last_initial_excess = self._excess(x_in)
        if not rg:
            self._apply_in_place(x_in, v_in, state_out, dt, checked)
            return
        # Taped: every pass writes a fresh array (one sweep: attachments, then every colour).
        passes = ([self._attach] if self.attachment_count else []) + [
            (lambda src, dst, c=c: self._sweep_color(src, c, dst)) for c in range(m.strain_limit_color_count)
        ]
        prev = x_in
        for k in range(self.iterations * len(passes)):
            last = k == self.iterations * len(passes) - 1
            dst = state_out.particle_q if last else solver.scratch(f"strain_limit{k % 2}", wp.vec3, True)
            passes[k % len(passes)](prev, dst)
            prev = dst
        self.last_iterations = self.iterations
        wp.launch(
            kc.correct_velocity,
            dim=m.particle_count,
            inputs=[x_in, state_out.particle_q, v_in, dt],
            outputs=[state_out.particle_qd],
            device=m.device,
        )

    def _apply_in_place(self, x_in, v_in, state_out: State, dt: float, checked: bool):
        """Forward-only path: sweeps in place on state_out, one thread per spring of a colour."""
        m = self.model
        x = state_out.particle_q
        wp.copy(x, x_in)
        offsets = m.strain_limit_color_offsets
        sweeps = 0
        while True:
            if self.attachment_count:
                self._attach(x, x)  # reads only pinned neighbours, writes its own particle: safe in place
            for c in range(m.strain_limit_color_count):
                wp.launch(
                    kc.apply_strain_limit_springs,
                    dim=int(offsets[c + 1] - offsets[c]),
                    inputs=[m.strain_limit_color_springs, int(offsets[c]), m.spring_indices, m.spring_rest_length,
                            m.particle_mass, m.particle_pinned, self.max_strain, self.relaxation],
                    outputs=[x],
                    device=m.device,
                )
            sweeps += 1
            if sweeps < self.iterations:
                continue
            if not checked:
                break
            excess = self._excess(x)
            if sweeps >= self.max_iterations or excess <= self.tolerance:
                self.converged = excess <= self.tolerance
                break
        self.last_iterations = sweeps
        wp.launch(kc.correct_velocity, dim=m.particle_count, inputs=[x_in, x, v_in, dt], outputs=[state_out.particle_qd], device=m.device)

    def _attach(self, x_src, x_dst):
        m = self.model
        wp.launch(
            kc.apply_attachment_limit,
            dim=m.particle_count,
            inputs=[self.attachment_particle, self.attachment_rest_distance, m.particle_pinned, x_src, self.max_strain],
            outputs=[x_dst],
            device=m.device,
        )

    def _sweep_color(self, x_src, color, x_dst):
        m = self.model
        wp.launch(
            kc.apply_strain_limit_color,
            dim=m.particle_count,
            inputs=[m.strain_limit_colors, m.spring_indices, m.spring_rest_length, m.particle_mass, m.particle_pinned,
                    x_src, color, self.max_strain, self.relaxation],
            outputs=[x_dst],
            device=m.device,
        )

    def _excess(self, x) -> float:
        m = self.model
        self.excess.fill_(-1.0)
        wp.launch(kd.eval_strain_excess, dim=m.spring_count, inputs=[m.spring_indices, m.spring_rest_length, m.spring_limited, x, self.max_strain],
                  outputs=[self.excess], device=m.device)
        return float(self.excess.numpy()[0])




def attachment_table(model: Model, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Per particle, the nearest pinned particle of up to `count` pinned groups and the rest path length.

    Groups are connected components of pinned particles (a pinned edge is one group, each pinned corner
    another). Shortest paths run along the limited (structural/shear) springs with their rest lengths
    (Dijkstra from each group). Returns (ids, distances) of shape (particle_count, k), -1 / 0 padded.
    """
    n = model.particle_count
    pinned = model.particle_pinned.numpy() != 0
    if count <= 0 or not pinned.any():
        return np.zeros((n, 0), np.int32), np.zeros((n, 0))
    springs = model.spring_indices.numpy().reshape(-1, 2)
    limited = model.spring_limited.numpy() != 0
    rest = model.spring_rest_length.numpy().astype(np.float64)
    adj: list[list[tuple[int, float]]] = [[] for _ in range(n)]
    for (a, b), r, use in zip(springs.tolist(), rest.tolist(), limited.tolist()):
        if use:
            adj[a].append((b, r))
            adj[b].append((a, r))
    # Pinned groups: connected components of pinned particles through limited springs.
    group = np.full(n, -1)
    groups = []
    for p in np.flatnonzero(pinned):
        if group[p] >= 0:
            continue
        stack, members = [p], []
        group[p] = len(groups)
        while stack:
            q = stack.pop()
            members.append(q)
            for r, _ in adj[q]:
                if pinned[r] and group[r] < 0:
                    group[r] = len(groups)
                    stack.append(r)
        groups.append(members)
    dist = np.full((len(groups), n), np.inf)
    source = np.full((len(groups), n), -1, np.int64)
    for g, members in enumerate(groups):
        heap = [(0.0, int(p), int(p)) for p in members]
        heapq.heapify(heap)
        d_g, s_g = dist[g], source[g]
        while heap:
            d, q, src = heapq.heappop(heap)
            if d >= d_g[q]:
                continue
            d_g[q], s_g[q] = d, src
            for r, w in adj[q]:
                if d + w < d_g[r]:
                    heapq.heappush(heap, (d + w, r, src))
    k = min(count, len(groups))
    order = np.argsort(dist, axis=0)[:k]  # nearest groups per particle
    cols = np.arange(n)
    ids = source[order, cols].T.astype(np.int32)
    dd = dist[order, cols].T
    ids[~np.isfinite(dd)] = -1
    dd[~np.isfinite(dd)] = 0.0
    return ids, dd


class SolverBase:
    """Common interface: ``step(state_in, state_out, control, dt)``.

    A solver never writes `state_in` or the model. Forward runs may swap two states; taped rollouts keep
    one State per step. Scratch arrays are reused only when nothing is taped (``state_in.requires_grad``
    is False); otherwise every intermediate gets a fresh array so no taped kernel's input is overwritten.

    A step runs three stages: the integrator proper (:meth:`integrate`), Provot strain limiting, then
    collision handling (:class:`~cloth_warp.collision.CollisionHandler`, when the model has colliders or
    self-collision), so the state a step returns is always the collision-resolved one.

    Args:
        model: the model to simulate.
        strain_limit: Provot's maximum strain of structural/shear springs (0.1 = 10 %), None to disable.
        strain_limit_iterations: Gauss-Seidel sweeps over all colours per step (the minimum).
        strain_limit_tolerance: keep sweeping (up to 128) until the limit holds to this strain; None for
            a fixed number of sweeps. Not applied inside graph capture or under the tape.
        collisions: handle the model's colliders and self-collision (default True).
        collision_rounds: strain-limit / collision passes per step when both are on (default 2).
    """

    name = "base"
    stability: float | None = None  # explicit integrators: the largest stable h omega_max

    def __init__(self, model: Model, *, strain_limit: float | None = 0.1, strain_limit_iterations: int = 4,
                 strain_limit_tolerance: float | None = 1.0e-3, collisions: bool = True, collision_rounds: int = 2):
        from ..collision import CollisionHandler

        self.model = model
        self.strain_limiter = (
            StrainLimiter(model, strain_limit, strain_limit_iterations, tolerance=strain_limit_tolerance) if strain_limit else None
        )
        handler = CollisionHandler(model) if collisions else None
        self.collisions = handler if handler is not None and handler.active else None
        if int(collision_rounds) < 1:
            raise ValueError(f"collision_rounds must be >= 1, got {collision_rounds!r}")
        self.collision_rounds = int(collision_rounds)
        self._scratch: dict = {}
        # Per-step solver report (iterative solvers fill these). last_failure names a failure that makes the
        # step's result meaningless ("non-finite residual"), None otherwise.
        self.last_iterations = 0
        self.last_residual = 0.0
        self.converged = True
        self.last_failure: str | None = None

    # -- checkpoints ------------------------------------------------------------------------------------------
    def checkpoint_state(self) -> dict:
        """What this solver carries from one step to the next, as numpy arrays and scalars ({} when nothing).

        The strain limiter carries nothing (each step sweeps from the integrator's output; its report is
        per step); the collision handler's state is :meth:`CollisionHandler.checkpoint_state
        <cloth_warp.collision.CollisionHandler.checkpoint_state>`. Scratch buffers are written before they are
        read in every step."""
        out = {"name": self.name}
        if self.collisions is not None:
            out.update({f"collisions.{k}": v for k, v in self.collisions.checkpoint_state().items()})
        return out

    def restore_state(self, state: dict) -> None:
        """Inverse of :meth:`checkpoint_state` (on a solver of the same kind built for the same model)."""
        if str(state.get("name", self.name)) != self.name:
            raise ValueError(f"checkpoint of a {state.get('name')} solver, this one is {self.name}")
        if self.collisions is not None:
            self.collisions.restore_state({k[len("collisions."):]: v for k, v in state.items() if k.startswith("collisions.")})

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

    def element_forces(self, x: wp.array, v: wp.array, control: Control, key: str = "") -> wp.array:
        """Scatter every spring's, bend triple's and triangle's force into a per-particle array [N]."""
        m = self.model
        force = self.scratch("element_force" + key, wp.vec3, x.requires_grad)
        force.zero_()
        dev = m.device
        if m.linear_spring_count:
            wp.launch(kf.eval_spring_forces, dim=m.linear_spring_count,
                      inputs=[m.spring_ends, m.spring_rest_length, m.spring_stiffness, m.spring_damping, x, v],
                      outputs=[force], device=dev)
        if m.spring_count > m.linear_spring_count:
            wp.launch(kf.eval_bending_forces, dim=m.spring_count - m.linear_spring_count,
                      inputs=[m.bend_triples, m.spring_stiffness, m.linear_spring_count, x],
                      outputs=[force], device=dev)
        if m.tri_count:
            wp.launch(kf.eval_drag_forces, dim=m.tri_count,
                      inputs=[m.tri_vertices, m.tri_drag, m.tri_corner_weights, x, v, control.wind], outputs=[force], device=dev)
        return force

    def step(self, state_in: State, state_out: State, control: Control, dt: float):
        """Advance state_in by dt [s] into state_out under control (pins' targets at the step's end)."""
        if not (dt > 0.0):
            raise ValueError(f"time step must be positive, got {dt!r}")
        limiter = self.strain_limiter if self.strain_limiter is not None and self.strain_limiter.active else None
        collide = self.collisions
        if limiter is None and collide is None:
            self.integrate(state_in, state_out.particle_q, state_out.particle_qd, control, dt)
            return
        rg = state_in.requires_grad
        x = self.scratch("x_unlimited", wp.vec3, rg)
        v = self.scratch("v_unlimited", wp.vec3, rg)
        self.integrate(state_in, x, v, control, dt)
        # With both, limiter and collisions alternate: the limiter pulls over-stretched cloth back (possibly
        # into a collider), the collision pass puts it back out; the last word is the collisions'.
        rounds = self.collision_rounds if limiter is not None and collide is not None else 1
        if collide is not None:
            collide.begin_step()
        for r in range(rounds):
            last = r == rounds - 1
            if limiter is not None:
                limited = state_out if collide is None else State(self.scratch(f"x_limited{r}", wp.vec3, rg),
                                                                  self.scratch(f"v_limited{r}", wp.vec3, rg))
                limiter.apply(self, x, v, limited, dt)
                x, v = limited.particle_q, limited.particle_qd
            if collide is not None:
                out = state_out if last else State(self.scratch(f"x_collided{r}", wp.vec3, rg), self.scratch(f"v_collided{r}", wp.vec3, rg))
                collide.apply(state_in.particle_q, x, v, control, dt, out.particle_q, out.particle_qd)
                x, v = out.particle_q, out.particle_qd

    def integrate(self, state_in: State, x_out: wp.array, v_out: wp.array, control: Control, dt: float):
        """The integrator proper (no strain limiting)."""
        raise NotImplementedError
