"""Spring constants from the continuum energy they stand for (docs/physics.md, section M).

A cloth region (a grid cell, a triangle, the neighbourhood of a vertex) of area A stores, for a uniform
membrane strain e or plate curvature k, the energy A W with W(n) = T : n n n n the 4th-order elasticity of
the fabric. A spring of direction n_s stores m_s (n_s . e . n_s)^2 / 2 (membrane, m = k L^2) or
m_s (n_s . k . n_s)^2 / 2 (a span-2 bend spring, m = c0 k_b a1 a2 / (4 L)), so the springs of a region
stand for the tensor sum_s m_s n_s^4 / A. Every region's moduli m_s >= 0 are fitted to the fabric's tensor
in its material frame (warp w, weft f), which makes stretch, shear and bending mean the same on cells of
any aspect ratio and on any triangle mesh:

    membrane  W = C_w w^4 + 6 G w^2 f^2 + C_f f^4       (C: stretch_stiffness per direction, G: shear)
    plate     W = D_w w^4 + 6 H w^2 f^2 + D_f f^4       (D = 9/8 B, H = 3/8 sqrt(B_w B_f): Huber's plate)

Springs obey Cauchy's relation (the coupling C_wwff equals the shear C_wfwf), so a spring lattice has
Poisson ratio G / C and, as a plate, nu = 1/3; B (the strip rigidity a cantilever measures) is D (1 - nu^2).
A region with fewer than three spring directions cannot carry twist: its springs are fitted as strips
(collocation along their own directions with the strip rigidity of that direction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# A plate region whose springs span fewer distinct directions than this (angles mod 180 deg apart by more
# than DISTINCT_DIRECTION) is fitted as strips.
PLATE_DIRECTIONS = 3
DISTINCT_DIRECTION = math.radians(15.0)
# Tikhonov weight of the fit (relative to the normalised energy error): picks the most even split among
# exact solutions (a triangle has six spring directions for five tensor components).
RIDGE = 1.0e-10
# Where no springs lie along the warp and weft (an irregular mesh, a grid cut off-grain), a spring lattice
# cannot store a shear stiffness far below the stretch stiffness (Cauchy: every spring off the axes adds
# both). The fit then keeps stretch right and lets shear come out stiffer: it weighs shear errors against
# SHEAR_FLOOR x sqrt(C_warp C_weft) rather than against G itself. (Exact fits are exact either way.)
SHEAR_FLOOR = 1.0


@dataclass(frozen=True)
class Orthotropic:
    """A fully symmetric 2-D elasticity tensor in the material frame: W(n) = warp w^4 + 6 coupling w^2 f^2
    + weft f^4, with w, f the components of the unit direction n along warp and weft [N/m or N m]."""

    warp: float
    weft: float
    coupling: float

    def voigt(self) -> np.ndarray:
        """The 3x3 Voigt matrix (w, f, engineering shear): [[warp, coupling, 0], [coupling, weft, 0], [0, 0, coupling]]."""
        return np.array([[self.warp, self.coupling, 0.0], [self.coupling, self.weft, 0.0], [0.0, 0.0, self.coupling]])

    def strip(self, angle) -> np.ndarray:
        """Stiffness of a strip cut at `angle` [rad] from the warp, free to contract sideways (uniaxial stress):
        1 / (t S t) with S the compliance and t = (c^2, s^2, c s) [N/m for a membrane, N m for a plate]."""
        a = np.asarray(angle, float)
        c, s = np.cos(a), np.sin(a)
        t = np.stack([c * c, s * s, c * s], axis=-1)
        v = self.voigt()
        if np.linalg.matrix_rank(v) < 3:  # no shear: only the warp and weft directions resist
            return np.where(np.abs(s) < 1e-12, self.warp, np.where(np.abs(c) < 1e-12, self.weft, 0.0))
        compliance = np.einsum("...i,ij,...j->...", t, np.linalg.inv(v), t)
        return 1.0 / compliance


def membrane_tensor(material) -> Orthotropic:
    """The membrane tensor of a material: stretch stiffness per direction and shear stiffness [N/m]."""
    return Orthotropic(material.stretch_stiffness, material.stretch_weft, material.shear_stiffness)


def membrane_element_stiffness(material) -> np.ndarray:
    """The constants of a triangle membrane element (:mod:`cloth_warp.kernels.forces`, `membrane_forces`) for
    a material: (C_11, C_22, C_12, C_66) of the Voigt matrix of :func:`membrane_tensor` in the warp/weft frame
    (1: warp, 2: weft, 6: engineering shear) [N/m], shape (4,). The element stores C_12 and C_66 apart: unlike a
    spring net it is not bound to Cauchy's relation (today the tensor has C_12 = C_66 = G)."""
    v = membrane_tensor(material).voigt()
    return np.array([v[0, 0], v[1, 1], v[0, 1], v[2, 2]])


def membrane_element_energy(x, vertices, rest_inverse, area, stiffness) -> np.ndarray:
    """Energy [J] per triangle element, A (1/2) e . C e with e = (E_ww, E_ff, 2 E_wf) the Green strain
    E = (F^T F - I) / 2 in the material frame, F = [x_1 - x_0, x_2 - x_0] Dm^-1 (numpy, float64), shape (t,).

    Args:
        x: positions [m], (n, 3); vertices: corners, (t, 3); rest_inverse: Dm^-1 [1/m], (t, 2, 2);
        area: rest areas [m^2], (t,); stiffness: (C_11, C_22, C_12, C_66) per element [N/m], (t, 4) or (4,).
    """
    x = np.asarray(x, np.float64)
    p = x[np.asarray(vertices)]
    ds = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], axis=2)  # (t, 3, 2)
    f = ds @ np.asarray(rest_inverse, np.float64)
    fw, ff = f[..., 0], f[..., 1]
    e = np.stack([0.5 * (np.sum(fw * fw, 1) - 1.0), 0.5 * (np.sum(ff * ff, 1) - 1.0), np.sum(fw * ff, 1)], axis=1)
    c = np.broadcast_to(np.asarray(stiffness, np.float64), (len(e), 4))
    w = c[:, 0] * e[:, 0] ** 2 + c[:, 1] * e[:, 1] ** 2 + 2.0 * c[:, 2] * e[:, 0] * e[:, 1] + c[:, 3] * e[:, 2] ** 2
    return 0.5 * np.asarray(area, np.float64) * w


def membrane_element_row_bound(vertices, rest_inverse, area, stiffness, particle_count: int) -> np.ndarray:
    """Per particle, the block-Gershgorin bound sum over its elements and their corners l of |K_kl| [N/m]
    (spectral norms of the 3x3 blocks of the rest stiffness K = A B^T C B, which rotations leave unchanged),
    so omega_max^2 <= max_i (bound_i + springs' 2 sum_j k_ij) / m_i, shape (particle_count,)."""
    vertices = np.asarray(vertices)
    out = np.zeros(particle_count)
    if not len(vertices):
        return out
    inv = np.asarray(rest_inverse, np.float64)
    g = np.stack([-(inv[:, 0] + inv[:, 1]), inv[:, 0], inv[:, 1]], axis=1)  # (t, 3 corners, 2): row k of [-1 -1; I] Dm^-1
    # strain Jacobian of corner k at rest in the material plane: rows (g_w, 0), (0, g_f), (g_f, g_w)
    b = np.zeros(g.shape[:2] + (3, 2))
    b[..., 0, 0] = g[..., 0]
    b[..., 1, 1] = g[..., 1]
    b[..., 2, 0] = g[..., 1]
    b[..., 2, 1] = g[..., 0]
    c4 = np.broadcast_to(np.asarray(stiffness, np.float64), (len(vertices), 4))
    c = np.zeros((len(vertices), 3, 3))
    c[:, 0, 0], c[:, 1, 1], c[:, 0, 1], c[:, 1, 0], c[:, 2, 2] = c4[:, 0], c4[:, 1], c4[:, 2], c4[:, 2], c4[:, 3]
    blocks = np.einsum("t,tkia,tij,tljb->tklab", np.asarray(area, np.float64), b, c, b)  # (t, 3, 3, 2, 2)
    norms = np.linalg.norm(blocks, ord=2, axis=(-2, -1)).sum(axis=2)  # (t, 3)
    np.add.at(out, vertices.reshape(-1), norms.reshape(-1))
    return out


def plate_tensor(material, twist: float = 1.0) -> Orthotropic:
    """The plate tensor of a material with `twist` x Huber's H = sqrt(D_w D_f) / 3 (nu = 1/3 when isotropic),
    and D such that a free strip cut along the warp or the weft (which bends anticlastically) has the
    rigidity B it is measured at: D_w - H^2 / D_f = B_w (D = 9/8 B at twist 1)."""
    bw, bf = material.bend_stiffness, material.bend_weft
    h = twist * 3.0 / 8.0 * math.sqrt(bw * bf)
    grow = 0.5 * (1.0 + math.sqrt(1.0 + 4.0 * h * h / (bw * bf))) if bw * bf > 0.0 else 1.0
    return Orthotropic(grow * bw, grow * bf, h)


# Twist fractions tried for a plate region whose springs cannot store Huber's twist with moduli >= 0 (say
# the diagonals of a 3:1 cell): the first that fits within PLATE_FIT, else the best.
TWISTS = (1.0, 0.5, 0.25, 0.1, 0.0)
PLATE_FIT = 1.0e-4


@dataclass
class SpringRegions:
    """Regions of one cloth and the springs that carry their energy (one row per (region, spring) entry).

    Attributes:
        area: region area [m^2], shape (r,).
        plate: 1 where the region's springs are fitted to the full tensor, 0 where as strips, shape (r,).
        region, spring: the entry's region and spring index, shape (e,) int.
        angle: the spring's direction in the region's tangent plane, from its warp direction [rad], shape (e,).
        factor: spring constant per modulus (k = factor m): 1 / L^2 for a membrane spring [1/m^2], 4 L /
            (c0 a1 a2) for a span-2 buckling spring [1/m], shape (e,).
    """

    area: np.ndarray
    plate: np.ndarray
    region: np.ndarray
    spring: np.ndarray
    angle: np.ndarray
    factor: np.ndarray

    @classmethod
    def build(cls, area, region, spring, angle, factor, fit_all: bool = False) -> SpringRegions:
        """Regions from entries; a region is a plate when its springs span PLATE_DIRECTIONS directions (or all when `fit_all`)."""
        region = np.asarray(region, np.int64)
        angle = np.asarray(angle, float)
        area = np.asarray(area, float)
        plate = np.ones(len(area), np.int8)
        if not fit_all:
            plate[:] = 0
            for r, dirs in _group(region, np.mod(angle, np.pi), len(area)):
                plate[r] = int(_distinct(dirs) >= PLATE_DIRECTIONS)
        return cls(area, plate, region, np.asarray(spring, np.int64), angle, np.asarray(factor, float))

    def spring_constants(self, tensors, spring_count: int) -> np.ndarray:
        """Per-spring constants (k or k_b) that make every region store the tensor (a list: the first each
        region fits, see :func:`fit_moduli`), summed over the regions."""
        m = fit_moduli(self, tensors)
        return np.bincount(self.spring, m * self.factor, minlength=spring_count)


def _group(keys: np.ndarray, values: np.ndarray, count: int):
    order = np.argsort(keys, kind="stable")
    starts = np.searchsorted(keys[order], np.arange(count + 1))
    for r in range(count):
        if starts[r + 1] > starts[r]:
            yield r, values[order[starts[r]:starts[r + 1]]]


def _distinct(angles: np.ndarray) -> int:
    """How many directions (mod pi) differ from one another by more than DISTINCT_DIRECTION."""
    kept: list[float] = []
    for a in np.sort(angles):
        if all(min(abs(a - b), math.pi - abs(a - b)) > DISTINCT_DIRECTION for b in kept):
            kept.append(float(a))
    return len(kept)


def _columns(angle: np.ndarray) -> np.ndarray:
    """Energy coefficients (w^4, w^3 f, w^2 f^2, w f^3, f^4) of a unit-modulus spring at `angle`, shape (..., 5)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c**4, 4 * c**3 * s, 6 * c * c * s * s, 4 * c * s**3, s**4], axis=-1)


def _region_system(angle: np.ndarray, plate: bool, tensor: Orthotropic):
    """Weighted rows (k, n) and target (k,) per unit area of one region with springs at `angle` [rad]."""
    a, b, g = tensor.warp, tensor.weft, tensor.coupling
    scale = max(a, b, 1e-300)
    a_, b_, g_ = max(a, 1e-3 * scale), max(b, 1e-3 * scale), max(g, SHEAR_FLOOR * math.sqrt(max(a * b, 1e-300)))
    if plate:
        # Relative error per component: warp, weft, shear (floored, see SHEAR_FLOOR), couplings against sqrt(C G).
        weights = np.array([1 / a_, 1 / (4 * math.sqrt(a_ * g_)), 1 / (6 * g_), 1 / (4 * math.sqrt(b_ * g_)), 1 / b_])
        return (_columns(angle) * weights).T, np.array([a, 0.0, 6 * g, 0.0, b]) * weights
    # Strips: along each spring's own direction, the energy of a free strip cut that way.
    strip = np.atleast_1d(tensor.strip(angle))
    w = 1.0 / np.maximum(strip, 1e-3 * scale)
    return (np.cos(angle[:, None] - angle[None, :]) ** 4) * w[:, None], strip * w


def fit_moduli(regions: SpringRegions, tensors) -> np.ndarray:
    """Per entry, the modulus m >= 0 [N m or N m^3] of the regions' springs that best store a tensor x area.

    `tensors` is an Orthotropic or a list of them in order of preference: a plate region takes the first one
    it stores within PLATE_FIT (else the one it stores best); a strip region always fits the first.
    """
    tensors = [tensors] if isinstance(tensors, Orthotropic) else list(tensors)
    m = np.zeros(len(regions.region))
    if max(tensors[0].warp, tensors[0].weft) <= 0.0:
        return m
    # Regions of the same shape (same directions, same kind) share a solution per unit area: solve once.
    solved: dict[tuple, np.ndarray] = {}
    for r, idx in _group(regions.region, np.arange(len(regions.region)), len(regions.area)):
        ang = regions.angle[idx]
        plate = bool(regions.plate[r])
        key = (plate, tuple(np.round(np.mod(ang, 2 * np.pi), 9)))
        if key not in solved:
            best = None
            for tensor in tensors if plate else tensors[:1]:
                a, b = _region_system(ang, plate, tensor)
                x = _ridge_nnls(a, b)
                err = float(np.linalg.norm(a @ x - b) / max(np.linalg.norm(b), 1e-300))
                if best is None or err < best[1]:
                    best = (x, err)
                if err <= PLATE_FIT:
                    break
            solved[key] = best[0]
        m[idx] = solved[key] * regions.area[r]
    return m


def _ridge_nnls(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """argmin |a x - b|^2 + RIDGE |b|^2 |y|^2 / n over x >= 0, y = x scaled to unit columns of a
    (Lawson-Hanson on the augmented system)."""
    n = a.shape[1]
    lam = math.sqrt(RIDGE) * max(float(np.linalg.norm(b)), 1e-300) / math.sqrt(n)
    scale = np.maximum(np.linalg.norm(a, axis=0), 1e-300)
    aa = np.vstack([a / scale, lam * np.eye(n)])
    bb = np.concatenate([b, np.zeros(n)])
    return nnls(aa, bb) / scale


def nnls(a: np.ndarray, b: np.ndarray, iterations: int | None = None) -> np.ndarray:
    """Non-negative least squares argmin_{x >= 0} |a x - b| (Lawson & Hanson 1974), for small systems."""
    m, n = a.shape
    x = np.zeros(n)
    passive = np.zeros(n, bool)
    w = a.T @ (b - a @ x)
    tol = 10 * np.finfo(float).eps * max(1.0, float(np.abs(a).max())) * max(m, n)
    for _ in range(iterations or 3 * n + 10):
        if passive.all() or w[~passive].max(initial=-np.inf) <= tol:
            break
        j = int(np.argmax(np.where(passive, -np.inf, w)))
        passive[j] = True
        while True:
            z = np.zeros(n)
            z[passive] = np.linalg.lstsq(a[:, passive], b, rcond=None)[0]
            if z[passive].min() > 0:
                x = z
                break
            neg = passive & (z <= 0)
            alpha = float(np.min(x[neg] / (x[neg] - z[neg])))
            x = x + alpha * (z - x)
            passive &= x > tol
            x[~passive] = 0.0
        w = a.T @ (b - a @ x)
    return x
