"""Sewing: the particles of a closed seam move as one point.

A garment's panels are sewn by zero-length seam springs (:meth:`~cloth_warp.builder.ModelBuilder.add_cloth_pattern`):
they pull the panels together while it is dressed (:mod:`~cloth_warp.dressing`), but a spring holds a seam only as
well as its stiffness lets it, a few millimetres open under a garment's weight. The sewing pass welds: each sewn point
whose seams are closed in the model's initial state (every seam spring in it within :data:`WELD_DISTANCE`: a dressed
garment's, or panels built touching) has, after every step, its particles moved to their centre of mass with their
mean velocity (momentum kept; a point with pinned particles goes where they are), so a sewn seam stays closed to float
precision however the cloth around it is loaded. Points still open at the start are left to their springs for the
whole run: welding a seam point by point as it closes would lock the closed part rigid and leave the rest stuck open.

The pass runs after the strain limiter and before the contact passes (:mod:`~cloth_warp.passes`), which get the last
word and keep the point whole: the collider pass moves particles that coincide alike, and self-collision gives a
welded point's particles one velocity change (:class:`Weld` on its velocities). Under ``wp.Tape`` the weld is an
average and differentiates.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .kernels import constraints as kc
from .model import Control, Model, ModelFlags
from .passes import StepPass
from .topology import SpringKind, particle_springs, particle_triangles, sewn_point_roots

WELD_DISTANCE = 1.0e-3
"""[m] a sewn point whose seam springs are all this short at the start is welded (a dressing sews until they are)."""


def seam_ends(model: Model) -> np.ndarray:
    """The particle pairs of the model's seam springs, int32 (seams, 2)."""
    return model.spring_indices.numpy().reshape(-1, 2)[model.spring_kind.numpy() == int(SpringKind.SEAM)].astype(np.int32)


def seam_gap(model: Model, positions, ends=None) -> float:
    """The largest distance [m] between sewn particles at `positions` ((n, 3); 0 without seams; `ends`: the model's
    :func:`seam_ends`, when known)."""
    return widest_pair(positions, seam_ends(model) if ends is None else ends)


def widest_pair(positions, pairs) -> float:
    """The largest distance [m] between the two particles of any of `pairs` ((p, 2)) at `positions` (0 without any)."""
    if len(pairs) == 0:
        return 0.0
    x = np.asarray(positions, np.float64)
    return float(np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1).max())


def welded_point_roots(model: Model, weld_distance: float = WELD_DISTANCE) -> np.ndarray:
    """Per particle, the root of its sewn point when that point is closed at the model's initial positions (every
    seam spring in it within `weld_distance` [m]), else -1 (int32, (n,))."""
    roots = sewn_point_roots(model)
    if roots is None:
        return np.full(model.particle_count, -1, np.int32)
    ends = seam_ends(model)
    x = model.particle_q.numpy().astype(np.float64)
    open_seam = np.linalg.norm(x[ends[:, 0]] - x[ends[:, 1]], axis=1) > weld_distance
    open_point = np.zeros(len(roots), bool)
    open_point[roots[ends[open_seam, 0]]] = True
    roots = roots.copy()
    roots[(roots >= 0) & open_point[np.maximum(roots, 0)]] = -1
    return roots


def solve_roots(model: Model, roots: np.ndarray) -> np.ndarray:
    """Of the welded points (`roots`, :func:`welded_point_roots`), those an implicit solve takes as one particle: per
    particle its point's root, -1 for any other and for the points with a pinned or soft-pinned particle (the sewing
    pass puts those where their pins are) (int32, (n,))."""
    roots = np.asarray(roots, np.int32).copy()
    welded = roots >= 0
    if not welded.any():
        return roots
    held = (model.particle_pinned.numpy() != 0) | (model.particle_pin_stiffness.numpy() > 0.0)
    held_point = np.zeros(len(roots), bool)
    held_point[roots[welded & held]] = True
    roots[welded & held_point[np.maximum(roots, 0)]] = -1
    return roots


def welded_view(model: Model, roots: np.ndarray) -> Model:
    """The model as an implicit solve sees it when each welded point (`roots`, :func:`solve_roots`) is one particle,
    its root: every spring, bend triple, triangle, membrane element and plate stencil reads and loads the root in place
    of the point's other particles (they coincide, with one velocity, at every step's start: the sewing pass and the
    contact passes keep them so), the root carries the point's mass, and the other particles are pinned, out of the
    system (the solver gives them the root's velocity change after the solve). A spring between two particles of one
    point is moved onto one of its non-root particles, where it loads nothing. The solve is then the seam's reduced
    system, E^T A E with E copying a point's velocity change to its particles: the seam closed by construction, not by
    a weld after the solve that moves what the solve balanced (a T-shirt held still: 91 particles moved by up to 17 mm/s
    every step). A shallow copy: fields not listed share the model's arrays; the masses are a copy (not differentiated
    through: taped steps take them from :func:`point_masses` on the tape)."""
    import copy

    n = model.particle_count
    roots = np.asarray(roots)
    follower = (roots >= 0) & (roots != np.arange(n))
    to_root = np.where(roots >= 0, roots, np.arange(n)).astype(np.int32)
    view = copy.copy(model)
    dev = model.device

    def remapped(a: wp.array, dtype) -> wp.array:
        return wp.array(to_root[a.numpy()], dtype=dtype, device=dev)

    springs = model.spring_indices.numpy().reshape(-1, 2)
    middle = model.spring_middle.numpy()
    ends = to_root[springs]
    internal = (ends[:, 0] == ends[:, 1]) & (middle < 0) & (springs[:, 0] != springs[:, 1])
    # a spring within one point: onto its end that is not the root (pinned in the view: it loads nothing)
    other = np.where(follower[springs[internal, 0]], springs[internal, 0], springs[internal, 1])
    ends[internal] = other[:, None]
    mid = np.where(middle >= 0, to_root[np.maximum(middle, 0)], middle).astype(np.int32)
    ends = ends.astype(np.int32)
    view.spring_indices = wp.array(ends, dtype=wp.int32, device=dev)
    view.spring_ends = wp.array(ends, dtype=wp.vec2i, device=dev)
    view.spring_middle = wp.array(mid, dtype=wp.int32, device=dev)
    first = model.linear_spring_count
    view.bend_triples = wp.array(np.column_stack([ends[first:, 0], mid[first:], ends[first:, 1]]).reshape(-1, 3), dtype=wp.vec3i,
                                 device=dev)
    tris = to_root[model.tri_indices.numpy().reshape(-1, 3)]
    view.tri_indices = wp.array(tris, dtype=wp.int32, device=dev)
    view.tri_vertices = wp.array(tris, dtype=wp.vec3i, device=dev)
    membranes = to_root[model.membrane_vertices.numpy().reshape(-1, 3)] if model.membrane_count else np.zeros((0, 3), np.int32)
    if model.membrane_count:
        view.membrane_vertices = wp.array(membranes, dtype=wp.vec3i, device=dev)
    if model.plate_count:
        view.plate_points = remapped(model.plate_points, wp.int32)
    so, sid, srole = particle_springs(ends, mid, n)
    view.particle_spring_offsets = wp.array(so, dtype=wp.int32, device=dev)
    view.particle_spring_ids = wp.array(sid, dtype=wp.int32, device=dev)
    view.particle_spring_role = wp.array(srole, dtype=wp.int32, device=dev)
    to, tid = particle_triangles(tris, n)
    view.particle_tri_offsets = wp.array(to, dtype=wp.int32, device=dev)
    view.particle_tri_ids = wp.array(tid, dtype=wp.int32, device=dev)
    mo, mid_ids = particle_triangles(membranes, n)
    view.particle_membrane_offsets = wp.array(mo, dtype=wp.int32, device=dev)
    view.particle_membrane_ids = wp.array(mid_ids, dtype=wp.int32, device=dev)
    view.particle_mass = point_masses(model, wp.array(roots.astype(np.int32), dtype=wp.int32, device=dev))
    pinned = model.particle_pinned.numpy().copy()
    pinned[follower] = 1
    view.particle_pinned = wp.array(pinned, dtype=wp.int32, device=dev)
    return view


def point_masses(model: Model, point_root: wp.array, requires_grad: bool = False) -> wp.array:
    """The masses [kg] of `welded_view` in a fresh array: per particle its own, and a point's root (`point_root`, per
    particle, -1: none) its whole point's (kernels/constraints.py gather_point_masses; recorded on a tape)."""
    out = wp.zeros(model.particle_count, dtype=float, device=model.device, requires_grad=requires_grad)
    wp.launch(kc.gather_point_masses, dim=model.particle_count, inputs=[point_root, model.particle_mass], outputs=[out],
              device=model.device)
    return out


class Weld:
    """The model's welded sewn points (:func:`welded_point_roots`) and the average that moves each as one point:
    :meth:`apply` gives every particle of a point the point's centre of mass and mean velocity (momentum kept; where
    it has pinned particles, theirs). The sewing pass welds positions with it; self-collision (cloth_warp.selfcollision)
    welds each of its velocity updates, so that a sewn point's particles take one velocity change."""

    def __init__(self, model: Model, weld_distance: float = WELD_DISTANCE):
        self.model = model
        self.weld_distance = float(weld_distance)
        n = model.particle_count
        self.particle_seam_root = wp.zeros(n, dtype=wp.int32, device=model.device)
        self._sums = self._new_sums(False)
        self._unused = wp.zeros(n, dtype=wp.vec3, device=model.device)  # the positions a velocity-only weld leaves
        self.refresh()

    def refresh(self) -> None:
        """Find the welded points again (the model's initial positions changed)."""
        roots = welded_point_roots(self.model, self.weld_distance)
        self.roots = roots
        self.points = len(np.unique(roots[roots >= 0]))
        self.particle_seam_root.assign(roots)

    def _new_sums(self, requires_grad: bool) -> tuple:
        """Per slot (a sewn point's root; + n for its pinned particles): mass, m x and m v."""
        n2, dev = 2 * self.model.particle_count, self.model.device
        return tuple(wp.zeros(n2, dtype=t, device=dev, requires_grad=requires_grad) for t in (float, wp.vec3, wp.vec3))

    def apply(self, x, v, x_out, v_out) -> None:
        """(x_out, v_out): (x, v) with each welded point's particles at its centre of mass and mean velocity. Outputs may
        alias the inputs (and each other, for a velocity alone) when nothing is taped."""
        m, dev = self.model, self.model.device
        if x.requires_grad:  # taped: fresh sums (the backward pass reads what each weld read)
            sums = self._new_sums(True)
        else:
            sums = self._sums
            for a in sums:
                a.zero_()
        wp.launch(kc.gather_sewn_points, dim=m.particle_count,
                  inputs=[self.particle_seam_root, m.particle_mass, m.particle_pinned, x, v], outputs=list(sums), device=dev)
        wp.launch(kc.weld_sewn_points, dim=m.particle_count,
                  inputs=[self.particle_seam_root, m.particle_pinned, *sums, x, v], outputs=[x_out, v_out], device=dev)

    def apply_velocity(self, v, v_out) -> None:
        """v_out: `v` with each welded point's particles at its mean velocity (may alias `v` when nothing is taped)."""
        self.apply(v, v, wp.zeros_like(v) if v.requires_grad else self._unused, v_out)

    def links(self) -> np.ndarray:
        """(particle, its point's root) pairs of the welded points' particles: what must move together."""
        sewn = np.flatnonzero(self.roots >= 0)
        return np.column_stack([sewn, self.roots[sewn]])


class SewingPass(StepPass):
    """Weld the sewn points closed at the start after each step (see the module and :class:`Weld`). Capturable: no host
    reads. :attr:`welded_points`: how many there are (the pass is :attr:`active` when any)."""

    name = "sewing"
    corrector = True  # it may move a point into a collider: the contact passes after it resolve that

    def __init__(self, model: Model, weld_distance: float = WELD_DISTANCE):
        self.model = model
        self.weld = Weld(model, weld_distance)

    def notify_model_changed(self, flags: int) -> None:
        if flags & ModelFlags.PARTICLE_INITIAL_STATE:
            self.weld.refresh()

    @property
    def welded_points(self) -> int:
        return self.weld.points

    @property
    def active(self) -> bool:
        return self.weld.points > 0

    @property
    def kernel_modules(self) -> tuple:
        return (kc,)

    def apply(self, x_start, x_end, v_end, control: Control, dt: float, x_out, v_out):
        self.weld.apply(x_end, v_end, x_out, v_out)
