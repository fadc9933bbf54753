"""Cloth topology in pure numpy: grids, triangle meshes, spring sets, welding, adjacency.

Nothing here touches Warp, so every rule can be unit-tested on its own. A :class:`ClothTopology` holds
the springs and, for each region of the cloth (a grid cell or a triangle for the membrane, a vertex's
neighbourhood for bending), which springs carry its energy and in which direction from the warp; the
spring constants come from fitting those springs to the material's continuum energy
(:mod:`cloth_warp.elasticity`, docs/physics.md section M):

================  ==============================  =================================================
category          force law                       spring constant
================  ==============================  =================================================
STRUCTURAL        linear spring                   k = m / L^2 [N/m] (m: membrane modulus x area)
SHEAR             linear spring                   k = m / L^2 [N/m]
BEND (Choi-Ko)    immediate buckling, push only   k_b = m 4 L / (c0 a1 a2) [N m^2] (m: plate modulus x area)
BEND (Provot)     linear span-2 "flexion" spring  k matched to k_b at 10 % chord compression [N/m]
================  ==============================  =================================================

So the material means the same at every resolution, cell shape and mesh (membrane stiffness in N/m,
flexural rigidity per unit width in N m).
"""

from __future__ import annotations

import enum
import logging
import warnings
from dataclasses import dataclass, field

import numpy as np

from .elasticity import SpringRegions
from .validation import LIMITS, MESH_SECONDS_PER_PARTICLE, check_build_size, check_number, check_vector

log = logging.getLogger(__name__)


class SpringKind(enum.IntEnum):
    """What a spring models; selects the material value that scales it."""

    STRUCTURAL = 0
    SHEAR = 1
    BEND = 2
    SEAM = 3
    """A sewing seam: a zero-length spring pulling two stitched points together (not strain-limited)."""


class SpringLaw(enum.IntEnum):
    """The force law a spring uses inside the kernels."""

    LINEAR = 0
    """f = -k (l - L) n in tension and compression."""
    BUCKLING = 1
    """Choi-Ko immediate buckling on a span-2 triple (end, middle, end); see kernels.forces.bending_force."""


class SpringModel(enum.Enum):
    """Which spring set a cloth is built with."""

    PROVOT = "provot"
    """Structural + shear + linear span-2 flexion springs (Provot 1995)."""
    CHOI_KO = "choi_ko"
    """Stiff structural + shear springs; span-2 buckling springs incl. span-2 diagonals (Choi & Ko 2002)."""


class MembraneModel(enum.Enum):
    """What carries a cloth's stretch and shear (the membrane); bending: :class:`BendingModel`."""

    SPRINGS = "springs"
    """The structural and shear springs, their constants fitted to the continuum energy per region (exact on
    grids at any warp angle and cell shape; on triangle meshes a spring net obeys Cauchy's relation and
    cannot store a shear stiffness far below the stretch stiffness off the material axes)."""
    ELEMENT = "element"
    """One orthotropic constant-strain (StVK) element per triangle: the continuum energy on any mesh. The
    structural and shear springs stay, with zero stiffness, for the strain limiter and diagnostics."""


class BendingModel(enum.Enum):
    """What carries a cloth's bending."""

    SPRINGS = "springs"
    """Span-2 bend springs (Choi-Ko buckling or Provot flexion, per `spring_model`) fitted to the plate tensor per
    vertex; exact on grids of any cell shape and on meshes whose triples are straight at rest (right-angled,
    equilateral). On irregular meshes no neighbour pair is straight: the triples push at rest and bend 5-30 %
    off the plate (docs/physics.md section M)."""
    STENCIL = "stencil"
    """One plate-bending stencil per vertex (:mod:`cloth_warp.plate`): the plate energy of the vertex's dual area,
    exact for uniform curvature on any triangle mesh; quadratic (no immediate buckling)."""


def default_bending_model(grid: bool) -> BendingModel:
    """Bend springs on grids (exact at any cell shape, with Choi-Ko's immediate buckling), stencils on triangle
    meshes (whose bend triples are kinked at rest when the mesh is irregular)."""
    return BendingModel.SPRINGS if grid else BendingModel.STENCIL


# Grid cells more elongated than this get membrane elements by default: a spring lattice stores the right energy
# for uniform strain at any cell shape, but on cells 2:1 and beyond its non-uniform modes go 10-30x too soft once
# the shear is >= 0.2 of the stretch stiffness (knits); on cells up to 1.5:1 springs and elements agree.
GRID_SPRING_ASPECT = 1.5


def default_membrane_model(grid: bool, cell_aspect: float = 1.0) -> MembraneModel:
    """Elements on triangle meshes (a spring net there shears 3.6x too stiffly at G/C = 0.02) and on grids whose
    cells are more elongated than GRID_SPRING_ASPECT; springs on other grids, where they are exact, cheaper, and
    where every shipped grid scene was tuned (an element cloth draped on the sphere scene stalls at ~1 mm/s with two
    corners up, where springs come to rest: left open). Either is a choice per cloth (``membrane=``)."""
    if grid and max(cell_aspect, 1.0 / cell_aspect) <= GRID_SPRING_ASPECT:
        return MembraneModel.SPRINGS
    return MembraneModel.ELEMENT


# Choi-Ko's quartic fit of the buckling curve (physics.md 7.2, as in Blender's implicit.c):
# f_b = (4 k_b / L^2) |P(l/L)|, P(s) = -11.541 s^4 + 34.193 s^3 - 39.083 s^2 + 23.116 s - 9.713.
BUCKLING_POLY = (-11.541, 34.193, -39.083, 23.116, -9.713)
# Onset force factor c0 = 4 |P(1)| (the exact curve gives 12): f_b(L^-) = c0 k_b / L^2.
BUCKLING_ONSET = 4.0 * abs(sum(BUCKLING_POLY))

# Provot flexion springs are linear and store energy ~ theta^4; their stiffness is matched to the
# buckling spring of the same bending rigidity at 10 % chord compression: (1/2) k (0.1 L)^2 = c0 k_b/L^2 * 0.1 L.
PROVOT_MATCH_COMPRESSION = 0.1


@dataclass
class ClothTopology:
    """The simulation mesh of one cloth and its springs (all arrays numpy).

    Attributes:
        positions: rest positions [m], shape (n, 3).
        triangles: welded triangles, shape (t, 3), indices into positions.
        springs: spring endpoints, shape (s, 2).
        spring_kind: :class:`SpringKind` per spring, shape (s,).
        spring_law: :class:`SpringLaw` per spring, shape (s,).
        membrane: the cells/triangles and the stretch/shear springs that carry their membrane energy.
        bending: the vertex neighbourhoods and the bend springs that carry their bending energy.
        spring_middle: for span-2 bend springs the particle between the two ends, else -1, shape (s,).
        particle_area: lumped (dual) area per particle [m^2], shape (n,).
        render_to_particle: for meshes loaded with seams, original vertex -> particle, shape (n_render,).
        corner_uv: per-triangle-corner texture coordinates, shape (t, 3, 2), or None.
        grid_shape: (nx, ny) cell counts for grids, None for meshes.
        corner_weights: per triangle corner, the share of the triangle's air drag that goes to that
            corner, shape (t, 3); chosen so that sum over triangles of weight x area = particle_area
            (drag per unit mass uniform on a flat sheet). None means 1/3 each.
        triangle_warp: per triangle, the unit warp direction in its plane at rest, shape (t, 3) (the weft is
            normal x warp, the normal that of the triangle's winding); None: :func:`triangle_frames` defaults.
    """

    positions: np.ndarray
    triangles: np.ndarray
    springs: np.ndarray
    spring_kind: np.ndarray
    spring_law: np.ndarray
    membrane: SpringRegions
    bending: SpringRegions
    spring_middle: np.ndarray
    particle_area: np.ndarray
    render_to_particle: np.ndarray | None = None
    corner_uv: np.ndarray | None = None
    grid_shape: tuple[int, int] | None = None
    corner_weights: np.ndarray | None = None
    warnings: list[str] = field(default_factory=list)
    triangle_warp: np.ndarray | None = None

    @property
    def particle_count(self) -> int:
        return len(self.positions)

    @property
    def spring_count(self) -> int:
        return len(self.springs)


class _SpringList:
    """Springs and, per region entry, (region, spring, angle from the warp [rad], factor k / m)."""

    def __init__(self):
        self.i, self.j, self.kind, self.law, self.middle = [], [], [], [], []
        self.entries = {"membrane": [], "bending": []}

    def add(self, i, j, kind, law, middle=-1) -> int:
        """Append a spring; `middle` is kept for buckling triples only (linear springs have none)."""
        self.i.append(i)
        self.j.append(j)
        self.middle.append(int(middle) if law == SpringLaw.BUCKLING else -1)
        self.kind.append(int(kind))
        self.law.append(int(law))
        return len(self.i) - 1

    def carry(self, which: str, region: int, spring: int, angle: float, factor: float):
        """Spring `spring` carries part of `region`'s energy along `angle` from the warp."""
        self.entries[which].append((region, spring, angle, factor))

    def regions(self, which: str, area, fit_all: bool) -> SpringRegions:
        e = self.entries[which]
        cols = list(zip(*e)) if e else [[], [], [], []]
        return SpringRegions.build(area, *cols, fit_all=fit_all)

    def arrays(self):
        springs = np.stack([np.asarray(self.i, np.int32), np.asarray(self.j, np.int32)], axis=1).reshape(-1, 2)
        return (
            springs,
            np.asarray(self.kind, np.int32),
            np.asarray(self.law, np.int32),
            np.asarray(self.middle, np.int32),
        )


def bend_factor(span: float, a1: float, a2: float, law: SpringLaw) -> float:
    """Spring constant per plate modulus m [N m^3] of a span-2 bend spring over segments a1, a2 (span L).

    Kinked by a small angle theta = kappa L / 2 (uniform normal curvature kappa along it), the spring
    shortens by delta = a1 a2 theta^2 / (2 L) and a buckling spring stores c0 k_b delta / L^2 (constant
    onset force) = (1/2) (c0 k_b a1 a2 / (4 L)) kappa^2: so m = c0 k_b a1 a2 / (4 L), k_b = 4 L m / (c0 a1 a2).
    A linear Provot spring is matched to that buckling spring at PROVOT_MATCH_COMPRESSION of its chord:
    (1/2) k (c L)^2 = c0 k_b c L / L^2, so k = 2 c0 k_b / (c L^3).
    """
    kb = 4.0 * span / (BUCKLING_ONSET * a1 * a2)
    return kb if law == SpringLaw.BUCKLING else 2.0 * BUCKLING_ONSET * kb / (PROVOT_MATCH_COMPRESSION * span**3)


def grid_topology(
    resolution: tuple[int, int],
    size: tuple[float, float],
    spring_model: SpringModel = SpringModel.CHOI_KO,
    warp_angle: float = 0.0,
) -> ClothTopology:
    """A rectangular grid of nx x ny cells in the local xy-plane, corner (0, 0), extent size [m].

    Vertex (i, j) has index j * (nx + 1) + i. The warp runs along x turned by `warp_angle` [deg] about z
    (45: a bias-cut piece). Springs: x and y edges and both diagonals of every cell (stretch/shear), span-2
    x and y bend springs through every node and, with the Choi-Ko set, span-2 diagonals through interior
    nodes. Each cell's membrane energy is carried by its four edges (half of each: a neighbour has the other
    half) and two diagonals; each node's bending energy (over its dual area) by the bend springs centred on
    it; their constants are fitted to the material (module docstring), exact for any cell aspect ratio.
    """
    nx, ny = check_vector("resolution", resolution, LIMITS["resolution"], size=2)
    sx, sy = check_vector("size", size, LIMITS["length"], size=2)
    warp = np.radians(check_number("warp_angle", warp_angle, LIMITS["angle"]))
    check_grid_size("resolution", nx, ny)
    ax, ay = sx / nx, sy / ny
    xs, ys = np.meshgrid(np.linspace(0.0, sx, nx + 1), np.linspace(0.0, sy, ny + 1))
    positions = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)

    def vid(i, j):
        return j * (nx + 1) + i

    sl = _SpringList()
    x_edge = {(i, j): sl.add(vid(i, j), vid(i + 1, j), SpringKind.STRUCTURAL, SpringLaw.LINEAR) for j in range(ny + 1) for i in range(nx)}
    y_edge = {(i, j): sl.add(vid(i, j), vid(i, j + 1), SpringKind.STRUCTURAL, SpringLaw.LINEAR) for i in range(nx + 1) for j in range(ny)}
    d2 = ax * ax + ay * ay
    phi = np.arctan2(ay, ax)  # the rising diagonal's angle from x
    for j in range(ny):
        for i in range(nx):
            cell = j * nx + i
            for e in (x_edge[i, j], x_edge[i, j + 1]):
                sl.carry("membrane", cell, e, -warp, 1.0 / (ax * ax))
            for e in (y_edge[i, j], y_edge[i + 1, j]):
                sl.carry("membrane", cell, e, 0.5 * np.pi - warp, 1.0 / (ay * ay))
            rising = sl.add(vid(i, j), vid(i + 1, j + 1), SpringKind.SHEAR, SpringLaw.LINEAR)
            falling = sl.add(vid(i + 1, j), vid(i, j + 1), SpringKind.SHEAR, SpringLaw.LINEAR)
            sl.carry("membrane", cell, rising, phi - warp, 1.0 / d2)
            sl.carry("membrane", cell, falling, np.pi - phi - warp, 1.0 / d2)

    law = SpringLaw.BUCKLING if spring_model == SpringModel.CHOI_KO else SpringLaw.LINEAR
    d = np.sqrt(d2)
    for j in range(ny + 1):
        for i in range(nx + 1):
            node = vid(i, j)
            if 0 < i < nx:  # x-span-2 centred on (i, j)
                sl.carry("bending", node, sl.add(vid(i - 1, j), vid(i + 1, j), SpringKind.BEND, law, node), -warp,
                         bend_factor(2 * ax, ax, ax, law))
            if 0 < j < ny:  # y-span-2
                sl.carry("bending", node, sl.add(vid(i, j - 1), vid(i, j + 1), SpringKind.BEND, law, node), 0.5 * np.pi - warp,
                         bend_factor(2 * ay, ay, ay, law))
            if law == SpringLaw.BUCKLING and 0 < i < nx and 0 < j < ny:  # span-2 diagonals (Choi-Ko)
                sl.carry("bending", node, sl.add(vid(i - 1, j - 1), vid(i + 1, j + 1), SpringKind.BEND, law, node), phi - warp,
                         bend_factor(2 * d, d, d, law))
                sl.carry("bending", node, sl.add(vid(i + 1, j - 1), vid(i - 1, j + 1), SpringKind.BEND, law, node),
                         np.pi - phi - warp, bend_factor(2 * d, d, d, law))

    tris = []
    for j in range(ny):
        for i in range(nx):
            a, b, c, e = vid(i, j), vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)
            tris.append((a, b, c))
            tris.append((a, c, e))
    triangles = np.asarray(tris, np.int32)
    # Each cell gives a quarter of its area to each corner; the diagonal corners (a, c) share theirs between
    # the cell's two triangles: drag shares (1/4, 1/2, 1/4) for (a, b, c) and (1/4, 1/4, 1/2) for (a, c, e).
    corner_weights = np.tile([[0.25, 0.5, 0.25], [0.25, 0.25, 0.5]], (len(triangles) // 2, 1))
    # Quad-based lumping keeps the masses symmetric (triangle lumping would depend on the diagonal).
    wx = np.full(nx + 1, ax)
    wx[[0, -1]] *= 0.5
    wy = np.full(ny + 1, ay)
    wy[[0, -1]] *= 0.5
    particle_area = np.outer(wy, wx).ravel()
    membrane = sl.regions("membrane", np.full(nx * ny, ax * ay), fit_all=True)
    bending = sl.regions("bending", particle_area, fit_all=False)
    springs, kind, law, middle = sl.arrays()
    # Texture coordinates span [0, 1]^2 over the grid (u along x, v along y), per triangle corner.
    corner_uv = (positions[:, :2] / np.array([sx, sy]))[triangles]
    triangle_warp = np.tile([np.cos(warp), np.sin(warp), 0.0], (len(triangles), 1))
    return ClothTopology(positions, triangles, springs, kind, law, membrane, bending, middle, particle_area,
                         grid_shape=(nx, ny), corner_uv=corner_uv, corner_weights=corner_weights, triangle_warp=triangle_warp)


def check_grid_size(name: str, nx: int, ny: int):
    """Refuse a grid of nx x ny cells that would not fit in memory (estimated before allocating)."""
    check_build_size(name, f"a {nx} x {ny} grid", (nx + 1) * (ny + 1))


def check_disc_size(name: str, rings: int):
    """Refuse a disc of `rings` rings (1 + 3 rings (rings + 1) particles) that would not fit in memory."""
    check_build_size(name, f"a disc of {rings} rings", 1 + 3 * rings * (rings + 1), MESH_SECONDS_PER_PARTICLE)


# ----------------------------------------------------------------------------------------------
# Triangle meshes


def disc_mesh(radius: float, rings: int) -> tuple[np.ndarray, np.ndarray]:
    """A disc of `radius` [m] in the local xy-plane centred at the origin, meshed in `rings` concentric
    rings (ring k has 6k vertices evenly spaced, so every triangle has edges close to radius / rings).
    Returns (vertices (1 + 3 rings (rings + 1), 3), triangles) with counter-clockwise winding (+z normal)."""
    radius = check_number("radius", radius, LIMITS["length"])
    rings = check_number("rings", rings, LIMITS["rings"])
    check_disc_size("rings", rings)
    verts = [np.zeros(3)]
    starts = [0]
    for k in range(1, rings + 1):
        starts.append(len(verts))
        a = 2.0 * np.pi * np.arange(6 * k) / (6 * k)
        r = radius * k / rings
        verts.extend(np.stack([r * np.cos(a), r * np.sin(a), np.zeros_like(a)], 1))
    tris = []
    for k in range(1, rings + 1):
        inner_n, outer_n = max(6 * (k - 1), 1), 6 * k
        i = inner_n if k == 1 else 0  # the centre only fans out
        j = 0
        # walk both rings by angle, emitting the triangle that advances the ring whose next vertex comes first
        while i < inner_n or j < outer_n:
            a_in = (i + 1) / inner_n if k > 1 else 2.0
            a_out = (j + 1) / outer_n
            inner = starts[k - 1] + i % inner_n
            outer = starts[k] + j % outer_n
            if j < outer_n and (a_out <= a_in or i >= inner_n):
                tris.append((inner, outer, starts[k] + (j + 1) % outer_n))
                j += 1
            else:
                tris.append((inner, outer, starts[k - 1] + (i + 1) % inner_n))
                i += 1
    return np.asarray(verts), np.asarray(tris, np.int64)


class MeshError(ValueError):
    """A mesh that cannot be simulated (the message names the problem)."""


def validate_mesh(vertices, triangles) -> tuple[np.ndarray, np.ndarray]:
    """Check shapes, finiteness and index ranges; return float64 vertices and int64 triangles."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"mesh vertices must have shape (n, 3), got {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3:
        raise MeshError(f"mesh triangles must have shape (t, 3), got {t.shape}")
    if len(v) == 0 or len(t) == 0:
        raise MeshError(f"mesh is empty ({len(v)} vertices, {len(t)} triangles)")
    if not np.issubdtype(t.dtype, np.integer):
        if not np.all(np.isfinite(t)) or np.any(t != np.round(t)):
            raise MeshError("mesh triangle indices must be integers")
        t = t.astype(np.int64)
    bad = ~np.all(np.isfinite(v), axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise MeshError(f"mesh has {int(bad.sum())} vertices with non-finite coordinates (first: vertex {first} = {v[first].tolist()})")
    lo, hi = int(t.min()), int(t.max())
    if lo < 0 or hi >= len(v):
        raise MeshError(f"mesh triangle index out of range: indices span [{lo}, {hi}] but there are {len(v)} vertices")
    return v, t.astype(np.int64)


def weld_vertices(vertices: np.ndarray, triangles: np.ndarray, tolerance: float | None = None):
    """Merge vertices closer than `tolerance` (default 1e-6 of the bounding-box diagonal).

    Returns (particles, welded_triangles, render_to_particle). OBJ/PLY/GLB meshes duplicate vertices at
    UV seams; simulated as is, the cloth would tear along every seam.
    """
    diag = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    tol = tolerance if tolerance is not None else 1e-6 * max(diag, 1e-12)
    keys = np.round(vertices / tol).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    # Order particles by first appearance so a mesh without seams keeps its vertex order.
    order = np.argsort(first)
    remap = np.empty_like(order)
    remap[order] = np.arange(len(order))
    render_to_particle = remap[inverse]
    particles = vertices[first[order]]
    return particles, render_to_particle[triangles], render_to_particle


def clean_triangles(vertices: np.ndarray, triangles: np.ndarray, issues: list[str]) -> np.ndarray:
    """Drop degenerate and duplicate triangles (recording a warning for each kind)."""
    tri = triangles
    repeated = (tri[:, 0] == tri[:, 1]) | (tri[:, 1] == tri[:, 2]) | (tri[:, 0] == tri[:, 2])
    e1 = vertices[tri[:, 1]] - vertices[tri[:, 0]]
    e2 = vertices[tri[:, 2]] - vertices[tri[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    scale = float(np.median(np.linalg.norm(e1, axis=1))) if len(tri) else 1.0
    degenerate = repeated | (area <= 1e-10 * max(scale, 1e-12) ** 2)
    if degenerate.any():
        issues.append(f"dropped {int(degenerate.sum())} degenerate triangle(s) (zero area or repeated vertex), first: triangle {int(np.flatnonzero(degenerate)[0])}")
    keep = ~degenerate
    sorted_t = np.sort(tri, axis=1)
    _, first = np.unique(sorted_t, axis=0, return_index=True)
    dup = np.ones(len(tri), bool)
    dup[first] = False
    dup &= keep
    if dup.any():
        issues.append(f"dropped {int(dup.sum())} duplicate triangle(s)")
    keep &= ~dup
    if not keep.any():
        raise MeshError("mesh has no usable triangles (all degenerate)")
    return tri[keep]


def edge_triangles(triangles: np.ndarray):
    """Unique undirected edges (e, 2) and, per edge, the list of triangles that use it."""
    corners = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    tri_of = np.concatenate([np.arange(len(triangles))] * 3)
    sorted_c = np.sort(corners, axis=1)
    edges, inverse = np.unique(sorted_c, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    counts = np.bincount(inverse, minlength=len(edges))
    splits = np.split(tri_of[order], np.cumsum(counts)[:-1])
    return edges, splits


def orient_triangles(vertices: np.ndarray, triangles: np.ndarray, corner_uv: np.ndarray | None = None,
                     issues: list[str] | None = None) -> np.ndarray:
    """Which triangles to flip (a boolean mask) so that every connected piece of the mesh is wound consistently.

    Two triangles sharing a manifold edge must traverse it in opposite directions. Each piece then faces the
    way that best matches the data: a closed piece outward (positive enclosed volume: a collider's solid side,
    the cache's normals); an open piece with UVs the way its UV layout turns (counter-clockwise in uv, as a grid
    is built); otherwise the way most of its area was already wound. Flips and non-orientable pieces (a
    Moebius band: no consistent choice) are recorded in `issues`.
    """
    t = np.asarray(triangles, np.int64)
    n = len(t)
    flip = np.zeros(n, bool)
    if n == 0:
        return flip
    src, dst = t.ravel(), np.roll(t, -1, axis=1).ravel()
    tri_of = np.repeat(np.arange(n), 3)
    key = np.minimum(src, dst) * (int(t.max()) + 1) + np.maximum(src, dst)
    order = np.argsort(key, kind="stable")
    k = key[order]
    starts = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
    counts = np.diff(np.r_[starts, len(k)])
    pairs = starts[counts == 2]
    t1, t2 = tri_of[order[pairs]], tri_of[order[pairs + 1]]
    # Same direction along the shared edge means one of the two must flip (parity 1).
    parity = (src[order[pairs]] < dst[order[pairs]]) == (src[order[pairs + 1]] < dst[order[pairs + 1]])
    open_tri = np.zeros(n, bool)
    open_tri[tri_of[order[np.repeat(counts, counts) != 2]]] = True  # on a boundary or non-manifold edge
    adjacency = [[] for _ in range(n)]
    for a, b, p in zip(t1.tolist(), t2.tolist(), parity.tolist()):
        adjacency[a].append((b, p))
        adjacency[b].append((a, p))
    x = np.asarray(vertices, np.float64)[t]
    cross = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    volume = np.einsum("ij,ij->i", x[:, 0], cross) / 6.0
    uv_turn = None
    if corner_uv is not None:
        e1, e2 = corner_uv[:, 1] - corner_uv[:, 0], corner_uv[:, 2] - corner_uv[:, 0]
        uv_turn = np.sign(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    # Walk each piece, fixing every triangle's flip relative to the piece's first one; count contradictions.
    piece_of, flip_of, conflicts = [-1] * n, [False] * n, []
    for seed in range(n):
        if piece_of[seed] >= 0:
            continue
        c = len(conflicts)
        conflicts.append(0)
        piece_of[seed], stack = c, [seed]
        while stack:
            a = stack.pop()
            for b, p in adjacency[a]:
                if piece_of[b] < 0:
                    piece_of[b], flip_of[b] = c, flip_of[a] ^ p
                    stack.append(b)
                elif flip_of[b] != flip_of[a] ^ p:
                    conflicts[c] += 1  # each contradicting edge is met from both sides
    piece, flip, conflicts = np.asarray(piece_of), np.asarray(flip_of), np.asarray(conflicts) // 2
    count = len(conflicts)
    sign = np.where(flip, -1.0, 1.0)
    closed = (np.bincount(piece, open_tri, count) == 0) & (conflicts == 0)
    uv_area = np.bincount(piece, sign * uv_turn * area, count) if uv_turn is not None else np.zeros(count)
    majority = np.bincount(piece, area * flip, count) > 0.5 * np.bincount(piece, area, count)
    invert = np.where(closed, np.bincount(piece, sign * volume, count) < 0.0, np.where(uv_area != 0.0, uv_area < 0.0, majority))
    flip ^= invert[piece]
    if issues is not None:
        if flip.any():
            basis = np.where(closed, 0, np.where(uv_area != 0.0, 1, 2))[np.unique(piece[flip])]
            reasons = [r for k, r in enumerate(("outward on closed surfaces", "following the UV layout", "following the majority"))
                       if k in basis]
            issues.append(f"reoriented {int(flip.sum())} of {n} triangle(s) so the winding is consistent "
                          f"({', '.join(reasons)}; first: triangle {int(np.flatnonzero(flip)[0])})")
        if conflicts.any():
            issues.append(f"the mesh is not orientable (a Moebius-like band): {int(conflicts.sum())} edge(s) join triangles "
                          "of opposite winding whatever the choice; normals flip across them")
    return flip


# Bend springs on general meshes join two neighbours a, b of a vertex v when the angle a-v-b is at
# least this (degrees): the discrete "straight line through v" of the two-ring.
MESH_BEND_MIN_ANGLE_DEG = 150.0


def mesh_topology(
    vertices,
    triangles,
    spring_model: SpringModel = SpringModel.CHOI_KO,
    uvs=None,
    weld: bool = True,
    warp_direction=None,
) -> ClothTopology:
    """Springs for an arbitrary triangle mesh (after validation, seam welding and clean-up).

    Rules (general meshes have no grid lines, so the two-ring stands in for them):

    * membrane: every edge (stretch) and, across each interior manifold edge, a spring between the two
      opposite vertices (shear); each triangle's membrane energy is carried by its three edges and the
      cross springs over them.
    * bend: for each vertex v and neighbour a, the neighbour b of v that makes the straightest line
      a-v-b (angle >= MESH_BEND_MIN_ANGLE_DEG) gives a span-2 spring a-b (deduplicated); it carries part of
      v's bending energy (over v's dual area).
    Spring constants are fitted per region to the material in the region's warp/weft frame
    (:mod:`cloth_warp.elasticity`). The warp (:func:`triangle_warp`): the direction of increasing texture u
    where `uvs` are given, else `warp_direction` (local coordinates), else the local x axis, projected onto
    each triangle.
    Non-manifold edges (three or more triangles) keep their stretch spring but get no shear spring and
    are reported. Degenerate and duplicate triangles are dropped and reported.
    """
    v, t = validate_mesh(vertices, triangles)
    check_build_size("vertices", f"a mesh of {len(v)} vertices", len(v), MESH_SECONDS_PER_PARTICLE)
    issues: list[str] = []
    corner_uv = None
    if uvs is not None:
        uv = np.asarray(uvs, np.float64)
        if uv.shape != (len(v), 2):
            raise MeshError(f"mesh uvs must have shape ({len(v)}, 2), got {uv.shape}")
        if not np.all(np.isfinite(uv)):
            raise MeshError(f"mesh uvs: {int((~np.isfinite(uv)).any(1).sum())} texture coordinate(s) are not finite")
    render_to_particle = None
    if weld:
        particles, t_welded, render_to_particle = weld_vertices(v, t)
        if len(particles) < len(v):
            log.info("welded %d seam vertices into %d particles", len(v), len(particles))
    else:
        particles, t_welded = v, t
    keep_tri = t_welded
    t_clean = clean_triangles(particles, keep_tri, issues)
    if uvs is not None:
        # Face-varying UVs per corner of the surviving triangles (seams survive in the cache).
        idx = _surviving_triangle_rows(keep_tri, t_clean)
        corner_uv = uv[t[idx]]
    flip = orient_triangles(particles, t_clean, corner_uv, issues)
    if flip.any():
        t_clean = t_clean.copy()
        t_clean[flip] = t_clean[flip][:, [0, 2, 1]]
        if corner_uv is not None:
            corner_uv = corner_uv.copy()
            corner_uv[flip] = corner_uv[flip][:, [0, 2, 1]]
    used = np.zeros(len(particles), bool)
    used[t_clean.ravel()] = True
    if not used.all():
        issues.append(f"{int((~used).sum())} vertex/vertices belong to no triangle and are simulated as free particles")

    area = 0.5 * np.linalg.norm(
        np.cross(particles[t_clean[:, 1]] - particles[t_clean[:, 0]], particles[t_clean[:, 2]] - particles[t_clean[:, 0]]),
        axis=1,
    )
    particle_area = np.zeros(len(particles))
    for c in range(3):
        np.add.at(particle_area, t_clean[:, c], area / 3.0)

    law = SpringLaw.BUCKLING if spring_model == SpringModel.CHOI_KO else SpringLaw.LINEAR
    normal, warp = triangle_frames(particles, t_clean, corner_uv, warp_direction)
    weft = np.cross(normal, warp)

    def angle_in(frame_w, frame_f, vec):
        return float(np.arctan2(vec @ frame_f, vec @ frame_w))

    sl = _SpringList()
    edges, edge_tris = edge_triangles(t_clean)
    nonmanifold = 0
    for (a, b), tris in zip(edges, edge_tris):
        e = particles[b] - particles[a]
        spring = sl.add(a, b, SpringKind.STRUCTURAL, SpringLaw.LINEAR)
        for k in tris:
            sl.carry("membrane", int(k), spring, angle_in(warp[k], weft[k], e), 1.0 / float(e @ e))
        if len(tris) > 2:
            nonmanifold += 1
        elif len(tris) == 2:
            o = [int(np.setdiff1d(t_clean[k], (a, b))[0]) for k in tris]
            if o[0] != o[1]:
                c = particles[o[1]] - particles[o[0]]
                spring = sl.add(o[0], o[1], SpringKind.SHEAR, SpringLaw.LINEAR)
                for k in tris:
                    sl.carry("membrane", int(k), spring, angle_in(warp[k], weft[k], c), 1.0 / float(c @ c))
    if nonmanifold:
        issues.append(f"{nonmanifold} non-manifold edge(s) (shared by 3+ triangles): kept as stretch springs, no shear/bend across them")

    # Bend springs through each vertex along its straightest neighbour pairs, in the vertex's frame.
    v_normal = np.zeros_like(particles)
    v_warp = np.zeros_like(particles)
    for c in range(3):
        np.add.at(v_normal, t_clean[:, c], normal * area[:, None])
        np.add.at(v_warp, t_clean[:, c], warp * area[:, None])
    v_normal /= np.maximum(np.linalg.norm(v_normal, axis=1, keepdims=True), 1e-300)
    v_warp -= np.sum(v_warp * v_normal, axis=1, keepdims=True) * v_normal
    v_warp /= np.maximum(np.linalg.norm(v_warp, axis=1, keepdims=True), 1e-300)
    v_weft = np.cross(v_normal, v_warp)
    neighbours = [set() for _ in range(len(particles))]
    for a, b in edges:
        neighbours[a].add(int(b))
        neighbours[b].add(int(a))
    cos_min = np.cos(np.radians(MESH_BEND_MIN_ANGLE_DEG))
    pairs: dict[tuple[int, int], int] = {}
    for vtx, nbrs in enumerate(neighbours):
        nb = sorted(nbrs)
        if len(nb) < 2:
            continue
        dirs = particles[nb] - particles[vtx]
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        cosines = dirs @ dirs.T
        for ia in range(len(nb)):
            ib = int(np.argmin(cosines[ia]))
            if cosines[ia, ib] <= cos_min:
                key = (min(nb[ia], nb[ib]), max(nb[ia], nb[ib]))
                pairs.setdefault(key, vtx)
    for (a, b), vtx in pairs.items():
        a1 = float(np.linalg.norm(particles[a] - particles[vtx]))
        a2 = float(np.linalg.norm(particles[b] - particles[vtx]))
        spring = sl.add(a, b, SpringKind.BEND, law, vtx)
        sl.carry("bending", vtx, spring, angle_in(v_warp[vtx], v_weft[vtx], particles[b] - particles[a]),
                 bend_factor(a1 + a2, a1, a2, law))

    membrane = sl.regions("membrane", area, fit_all=True)
    bending = sl.regions("bending", particle_area, fit_all=False)
    springs, kind, law, middle = sl.arrays()
    for msg in issues:
        warnings.warn(f"cloth mesh: {msg}", stacklevel=3)
    return ClothTopology(
        particles,
        t_clean.astype(np.int32),
        springs,
        kind,
        law,
        membrane,
        bending,
        middle,
        particle_area,
        render_to_particle=render_to_particle,
        corner_uv=corner_uv,
        warnings=issues,
        triangle_warp=warp,
    )


def triangle_frames(positions: np.ndarray, triangles: np.ndarray, corner_uv: np.ndarray | None = None,
                    warp_direction=None) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle, the unit normal and the unit warp direction in its plane, shapes (t, 3).

    The warp is `warp_direction` (local coordinates) projected onto the triangle when given; else the
    direction in which the texture coordinate u increases (dx/du, from the triangle's UV Jacobian) where
    `corner_uv` (t, 3, 2) is given and not degenerate; else the local x axis projected, or the local y axis
    where the triangle's plane is within 30 deg of facing along x.
    """
    x = positions[triangles]
    e1, e2 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
    normal = np.cross(e1, e2)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)

    def project(v):
        v = np.broadcast_to(np.asarray(v, float), normal.shape)
        p = v - np.sum(v * normal, axis=1, keepdims=True) * normal
        return p, np.linalg.norm(p, axis=1)

    if warp_direction is not None:
        d = check_vector("warp_direction", warp_direction, LIMITS["position"])
        if np.linalg.norm(d) == 0.0:
            raise ValueError("warp_direction must not be zero")
        warp, length = project(d / np.linalg.norm(d))
        fallback, _ = project(np.cross(d, [0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 * np.linalg.norm(d) else [1.0, 0.0, 0.0])
    else:
        warp, length = project([1.0, 0.0, 0.0])
        fallback, _ = project([0.0, 1.0, 0.0])
    warp = np.where((length < 0.5)[:, None], fallback, warp)
    if corner_uv is not None and warp_direction is None:
        du1, dv1 = corner_uv[:, 1, 0] - corner_uv[:, 0, 0], corner_uv[:, 1, 1] - corner_uv[:, 0, 1]
        du2, dv2 = corner_uv[:, 2, 0] - corner_uv[:, 0, 0], corner_uv[:, 2, 1] - corner_uv[:, 0, 1]
        det = du1 * dv2 - du2 * dv1
        ok = np.abs(det) > 1e-12 * np.maximum(du1 * du1 + dv1 * dv1 + du2 * du2 + dv2 * dv2, 1e-300)
        tangent = (e1 * dv2[:, None] - e2 * dv1[:, None]) / np.where(ok, det, 1.0)[:, None]
        warp = np.where(ok[:, None], tangent, warp)
    warp -= np.sum(warp * normal, axis=1, keepdims=True) * normal
    return normal, warp / np.maximum(np.linalg.norm(warp, axis=1, keepdims=True), 1e-300)


def triangle_rest_shapes(positions: np.ndarray, triangles: np.ndarray, warp: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle, the inverse rest edge matrix in its material frame and its rest area.

    With X_k = ((x_k - x_0) . w, (x_k - x_0) . f) the corners in the triangle's warp/weft frame (w = `warp`,
    default :func:`triangle_frames`; f = n x w with n the normal of the triangle's winding, so det Dm > 0),
    Dm = [X_1 - X_0, X_2 - X_0] and the deformation gradient of current corners x_k is
    F = [x_1 - x_0, x_2 - x_0] Dm^-1 (3x2; its columns map the warp and the weft).

    Returns:
        (Dm^-1 [1/m], shape (t, 2, 2); area [m^2], shape (t,)).
    """
    x = np.asarray(positions, np.float64)[np.asarray(triangles)]
    e1, e2 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
    normal = np.cross(e1, e2)
    twice_area = np.linalg.norm(normal, axis=1)
    normal /= np.maximum(twice_area, 1e-300)[:, None]
    if warp is None:
        _, warp = triangle_frames(positions, triangles)
    w = np.asarray(warp, np.float64)
    w = w - np.sum(w * normal, axis=1, keepdims=True) * normal
    w /= np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-300)
    f = np.cross(normal, w)
    dm = np.stack([np.stack([np.sum(e1 * w, 1), np.sum(e2 * w, 1)], 1), np.stack([np.sum(e1 * f, 1), np.sum(e2 * f, 1)], 1)], 1)
    det = dm[:, 0, 0] * dm[:, 1, 1] - dm[:, 0, 1] * dm[:, 1, 0]
    safe = np.where(np.abs(det) > 1e-300, det, 1.0)
    inverse = np.stack([np.stack([dm[:, 1, 1], -dm[:, 0, 1]], 1), np.stack([-dm[:, 1, 0], dm[:, 0, 0]], 1)], 1) / safe[:, None, None]
    inverse[np.abs(det) <= 1e-300] = 0.0  # a degenerate triangle carries no membrane energy
    return inverse, 0.5 * twice_area


def _surviving_triangle_rows(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Row indices of `after` within `before` (clean_triangles keeps order and rows)."""
    idx = np.empty(len(after), np.int64)
    k = 0
    for r in range(len(before)):
        if k < len(after) and np.array_equal(before[r], after[k]):
            idx[k] = r
            k += 1
    return idx


# ----------------------------------------------------------------------------------------------
# Adjacency for gather kernels and colouring for Gauss-Seidel passes


def csr(owner: np.ndarray, count: int, payload: np.ndarray):
    """Compressed rows: offsets (count+1,) and payload sorted by owner."""
    order = np.argsort(owner, kind="stable")
    offsets = np.zeros(count + 1, np.int32)
    np.cumsum(np.bincount(owner, minlength=count), out=offsets[1:])
    return offsets, payload[order]


def particle_springs(springs: np.ndarray, middle: np.ndarray, particle_count: int):
    """Per particle: offsets, incident spring ids and the particle's role in each (gather formulation).

    Role 0 / 1: first / second endpoint; role 2: middle particle of a span-2 bend triple.
    """
    s = len(springs)
    ids = np.arange(s)
    has_mid = middle >= 0
    owner = np.concatenate([springs[:, 0], springs[:, 1], middle[has_mid]])
    payload = np.stack(
        [
            np.concatenate([ids, ids, ids[has_mid]]),
            np.concatenate([np.zeros(s, np.int64), np.ones(s, np.int64), np.full(int(has_mid.sum()), 2)]),
        ],
        axis=1,
    )
    offsets, rows = csr(owner, particle_count, payload)
    return offsets, rows[:, 0].astype(np.int32), rows[:, 1].astype(np.int32)


def particle_triangles(triangles: np.ndarray, particle_count: int):
    """Per particle: offsets and incident triangle ids."""
    owner = triangles.ravel()
    payload = np.repeat(np.arange(len(triangles)), 3)
    offsets, rows = csr(owner, particle_count, payload)
    return offsets, rows.astype(np.int32)


def color_springs(springs: np.ndarray, particle_count: int, mask: np.ndarray | None = None) -> np.ndarray:
    """Greedy edge colouring: no two springs of one colour share a particle.

    Returns a table (colors, particle_count) holding, for each colour and particle, the spring id of that
    colour incident to the particle, or -1. Used by the strain limiter's Gauss-Seidel passes, which
    process one colour per launch without write conflicts.
    """
    ids = np.flatnonzero(mask) if mask is not None else np.arange(len(springs))
    used: list[set] = [set() for _ in range(particle_count)]
    color = np.full(len(springs), -1, np.int64)
    for s in ids:
        a, b = springs[s]
        c = 0
        while c in used[a] or c in used[b]:
            c += 1
        color[s] = c
        used[a].add(c)
        used[b].add(c)
    n_colors = int(color.max()) + 1 if len(ids) else 0
    table = np.full((n_colors, particle_count), -1, np.int32)
    for s in ids:
        a, b = springs[s]
        table[color[s], a] = s
        table[color[s], b] = s
    return table


def seam_roots(model) -> np.ndarray | None:
    """Per particle, the smallest particle it is sewn to through a chain of seam springs (itself when none), or None
    without seams: a seam's particles are one vertex of the garment (to self-collision's adjacency, and in caches)."""
    kind = model.spring_kind.numpy()
    seams = model.spring_indices.numpy().reshape(-1, 2)[kind == int(SpringKind.SEAM)]
    if len(seams) == 0:
        return None
    return joined_roots(seams, model.particle_count)


def joined_roots(pairs: np.ndarray, count: int) -> np.ndarray:
    """Per item of `count`, the smallest item it is joined to through a chain of `pairs` (itself when none)."""
    root = np.arange(count)

    def find(i):
        while root[i] != i:
            root[i] = root[root[i]]
            i = root[i]
        return i

    for a, b in pairs:
        ra, rb = find(a), find(b)
        if ra != rb:
            root[max(ra, rb)] = min(ra, rb)
    return np.array([find(i) for i in range(len(root))])


def sewn_point_roots(model) -> np.ndarray | None:
    """Per particle, the root (:func:`seam_roots`) of the sewn point it belongs to, -1 for a particle no seam joins
    (int32, (n,)), or None without seams."""
    roots = seam_roots(model)
    if roots is None:
        return None
    sewn = np.full(len(roots), -1, np.int32)
    shared = np.bincount(roots, minlength=len(roots))[roots] > 1
    sewn[shared] = roots[shared]
    return sewn
