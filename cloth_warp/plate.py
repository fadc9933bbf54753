"""Plate-bending stencils: a quadratic bending energy per vertex that means the same on any triangle mesh
(docs/physics.md, section P).

At each vertex v, rest positions of a few nearby vertices in v's warp/weft tangent frame, xi_j, give weights
c_j = (c_j0, c_j1, c_j2) [1/m^2] with

    sum_j c_j = 0,   sum_j c_j xi_j = 0,   sum_j c_j (xi_j1^2 / 2, xi_j2^2 / 2, xi_j1 xi_j2) = diag(1, 1, 2),

so for a flat rest mesh bent into the height field z = xi^T K xi / 2 the vectors u_k = sum_j c_jk x_j [1/m]
are (K_ww, K_ff, 2 K_wf) n: the curvature in Voigt form along the normal n, exactly for uniform curvature
and zero for any rigid or in-plane affine motion. The vertex stores E_v = (1/2) sum_kl S_kl u_k . u_l with
S = A_v D (dual area A_v, D the Voigt matrix of :func:`~cloth_warp.elasticity.plate_tensor` in v's frame)
[N m^3], which is the plate energy of its dual area, whatever the triangles' shapes. E is quadratic in the
positions (constant Hessian, Bergou et al. 2006's quadratic bending generalised to orthotropic plates): the
forces are f_j = -U S c_j with U = sum_l x_l c_l^T (a 3x3 matrix), the stiffness blocks (c_i . S c_j) I.

The rest state is flat: a mesh curved at rest is bent flat by these forces as by bend springs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# A stencil has at least this many points (the vertex and its neighbours): six quadratic constraints and one
# to spare. The one-ring of an interior vertex of valence >= 6 is enough; other vertices (boundaries, corners,
# valence <= 5) add the nearest points of the next ring one at a time until the fit is well posed. Small
# stencils keep short waves stiff: at a wavelength of 8 edges a one-ring stencil stores 90 % of the continuum's
# energy, a whole two-ring only 64-70 % (docs/physics.md section P).
STENCIL_MIN_POINTS = 7
# The quadratic fit must be well posed: the smallest singular value of the scaled constraint matrix above
# this, else a point is added (points nearly on one line cannot measure curvature across it).
STENCIL_CONDITION = 1.0e-3
# ... and its weights small: |c| h^2 at most this (h the one-ring's rms edge length; a regular one-ring has
# 4.1-4.7), else a point is added. Near-degenerate one-rings of irregular meshes give weights 20-90x h^-2
# (stiff, badly conditioned local modes) that one or two more points bring down.
STENCIL_MAX_WEIGHT = 8.0
# The most points a stencil may have (the kernels sum over a fixed count, kernels.forces.PLATE_MAX_POINTS).
STENCIL_MAX_POINTS = 16
# The rings searched for points (a vertex with no well-posed stencil among them, say in a strip one triangle
# wide, is left without one and reported).
STENCIL_MAX_RINGS = 3
# Voigt targets of the three rows: u_0 = K_ww, u_1 = K_ff, u_2 = 2 K_wf.
_TARGETS = np.array([[0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 1, 0], [0, 0, 0, 0, 0, 2]], float).T


@dataclass(frozen=True)
class PlateStencils:
    """The stencils of one cloth (numpy).

    Attributes:
        vertex: the vertex each stencil measures, shape (p,).
        offsets: start of each stencil's points in `points`, shape (p + 1,).
        points: particle indices (local to the cloth), each stencil's vertex first, shape (nnz,).
        weights: c_j [1/m^2], shape (nnz, 3).
        area: the dual area A_v [m^2], shape (p,).
        frames: (warp, weft) unit tangents at each stencil's vertex, shape (p, 2, 3).
    """

    vertex: np.ndarray
    offsets: np.ndarray
    points: np.ndarray
    weights: np.ndarray
    area: np.ndarray
    frames: np.ndarray

    @property
    def count(self) -> int:
        return len(self.vertex)


def vertex_frames(positions: np.ndarray, triangles: np.ndarray, triangle_warp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex the area-weighted unit normal and the warp projected into its tangent plane, shapes (n, 3)."""
    e1 = positions[triangles[:, 1]] - positions[triangles[:, 0]]
    e2 = positions[triangles[:, 2]] - positions[triangles[:, 0]]
    cross = np.cross(e1, e2)  # |cross| = 2 A: the area weight
    normal = np.zeros_like(positions)
    warp = np.zeros_like(positions)
    twice_area = np.linalg.norm(cross, axis=1)[:, None]
    for c in range(3):
        np.add.at(normal, triangles[:, c], cross)
        np.add.at(warp, triangles[:, c], triangle_warp * twice_area)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    warp -= np.sum(warp * normal, axis=1, keepdims=True) * normal
    warp /= np.maximum(np.linalg.norm(warp, axis=1, keepdims=True), 1e-300)
    return normal, warp


def _rings(triangles: np.ndarray, n: int) -> list[set[int]]:
    neighbours = [set() for _ in range(n)]
    for a, b, c in triangles:
        neighbours[a].update((b, c))
        neighbours[b].update((a, c))
        neighbours[c].update((a, b))
    return neighbours


def _constraints(xi: np.ndarray) -> np.ndarray:
    """The 6 x m matrix of the monomials (1, xi_1, xi_2, xi_1^2 / 2, xi_2^2 / 2, xi_1 xi_2) at the points."""
    x, y = xi[:, 0], xi[:, 1]
    return np.stack([np.ones_like(x), x, y, 0.5 * x * x, 0.5 * y * y, x * y])


def stencil_weights(xi: np.ndarray) -> np.ndarray | None:
    """The weights c (m, 3) [1/m^2] of points xi (m, 2) [m] (the vertex itself at xi = 0 among them): the
    smallest in the norm sum_j (1 + |xi_j|^2 / h^2) |c_j|^2 (h the mean distance, so far points weigh less)
    that meet the constraints exactly; None where the quadratic fit is ill-posed."""
    dist2 = np.sum(xi * xi, axis=1)
    h2 = float(np.mean(dist2[dist2 > 0.0])) if np.any(dist2 > 0.0) else 0.0
    if h2 <= 0.0:
        return None
    h = np.sqrt(h2)
    # scale to unit length so the condition test is independent of the mesh size
    m = _constraints(xi / h)
    inv_w = 1.0 / (1.0 + dist2 / h2)
    gram = (m * inv_w) @ m.T
    if np.linalg.svd(m * np.sqrt(inv_w), compute_uv=False)[-1] < STENCIL_CONDITION:
        return None
    c = (inv_w[:, None] * m.T) @ np.linalg.solve(gram, _TARGETS)
    return c / h2  # back to metres: the quadratic rows scale as h^2


def plate_stencils(positions: np.ndarray, triangles: np.ndarray, triangle_warp: np.ndarray,
                   particle_area: np.ndarray) -> tuple[PlateStencils, list[str]]:
    """A stencil for every vertex of a triangle mesh (rest positions [m]), in its warp/weft frame, and
    messages about vertices left without one."""
    n = len(positions)
    normal, warp = vertex_frames(positions, triangles, triangle_warp)
    weft = np.cross(normal, warp)
    neighbours = _rings(triangles, n)
    vertex, offsets, points, weights, areas, frames = [], [0], [], [], [], []
    skipped = 0
    for v in range(n):
        if not neighbours[v] or particle_area[v] <= 0.0:
            continue
        # candidate points: v, then its rings, each nearest first (ties by index)
        order, seen, ring = [v], {v}, set(neighbours[v])
        h2 = 0.0
        for r in range(STENCIL_MAX_RINGS):
            ids = np.array(sorted(ring))
            dist2 = np.sum((positions[ids] - positions[v]) ** 2, axis=1)
            if r == 0:
                h2 = float(dist2.mean())  # the one-ring's mean squared edge length
            order += ids[np.argsort(dist2, kind="stable")].tolist()
            seen |= ring
            if len(order) >= STENCIL_MAX_POINTS:
                break
            ring = set().union(*(neighbours[q] for q in ring)) - seen
            if not ring:
                break
        c, best = None, None
        for count in range(min(max(STENCIL_MIN_POINTS, len(neighbours[v]) + 1), STENCIL_MAX_POINTS), min(len(order), STENCIL_MAX_POINTS) + 1):
            ids = np.array(order[:count])
            d = positions[ids] - positions[v]
            weights_at = stencil_weights(np.stack([d @ warp[v], d @ weft[v]], axis=1))
            if weights_at is None:
                continue
            size = float(np.linalg.norm(weights_at)) * h2
            if best is None or size < best[0]:
                best = (size, ids, weights_at)
            if size <= STENCIL_MAX_WEIGHT:
                break
        if best is not None:
            _, ids, c = best
        if c is None:
            skipped += 1
            continue
        vertex.append(v)
        points.append(ids)
        weights.append(c)
        offsets.append(offsets[-1] + len(ids))
        areas.append(particle_area[v])
        frames.append((warp[v], weft[v]))
    issues = [f"{skipped} vertex(es) without a bending stencil (too few points around them to measure curvature)"] if skipped else []
    stencils = PlateStencils(
        vertex=np.asarray(vertex, np.int64),
        offsets=np.asarray(offsets, np.int64),
        points=np.concatenate(points).astype(np.int64) if points else np.zeros(0, np.int64),
        weights=np.concatenate(weights) if weights else np.zeros((0, 3)),
        area=np.asarray(areas, float),
        frames=np.asarray(frames, float).reshape(-1, 2, 3),
    )
    return stencils, issues


def stencil_energy(x: np.ndarray, offsets: np.ndarray, points: np.ndarray, weights: np.ndarray, stiffness: np.ndarray) -> np.ndarray:
    """E_v = (1/2) sum_kl S_kl u_k . u_l [J] of each stencil at positions x (float64 reference of the kernels)."""
    out = np.zeros(len(stiffness))
    for s in range(len(stiffness)):
        sl = slice(offsets[s], offsets[s + 1])
        u = x[points[sl]].T @ weights[sl]  # (3 components, 3 curvatures): column k is u_k
        out[s] = 0.5 * float(np.sum((u.T @ u) * stiffness[s]))
    return out


def stencil_row_bound(offsets: np.ndarray, points: np.ndarray, weights: np.ndarray, stiffness: np.ndarray, n: int) -> np.ndarray:
    """sum_j |K_ij| per particle of the stencils' stiffness K_ij = c_i . S c_j [N/m] (the Gershgorin bound of its
    rows, for the explicit integrators' stable step)."""
    out = np.zeros(n)
    for s in range(len(stiffness)):
        sl = slice(offsets[s], offsets[s + 1])
        c = weights[sl]
        np.add.at(out, points[sl], np.abs(c @ stiffness[s] @ c.T).sum(axis=1))
    return out
