"""An independent triangle-triangle intersection checker for the self-collision tests (numpy, float64;
shares no code with the solver).

Two triangles that share no vertex intersect iff an edge of one crosses the other (for triangles in
general position); every mesh edge is tested against every triangle it is not incident to, after an
exact bounding-box filter.
"""

import numpy as np


def unique_edges(tris):
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def segment_crosses_triangle(p, q, a, b, c, eps=1e-12):
    """Vectorised Moeller-Trumbore: does segment pq cross triangle abc (closed)? All (k, 3) arrays."""
    d = q - p
    e1 = b - a
    e2 = c - a
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > eps
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = p - a
    u = inv * np.einsum("ij,ij->i", s, h)
    qv = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, qv)
    t = inv * np.einsum("ij,ij->i", e2, qv)
    return ok & (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0) & (t >= 0.0) & (t <= 1.0)


def intersecting_pairs(x, tris, chunk=256):
    """(edge, triangle) index pairs where a mesh edge crosses a triangle not incident to it."""
    x = np.asarray(x, np.float64)
    tris = np.asarray(tris, np.int64)
    edges = unique_edges(tris)
    tlo = x[tris].min(1)
    thi = x[tris].max(1)
    elo = np.minimum(x[edges[:, 0]], x[edges[:, 1]])
    ehi = np.maximum(x[edges[:, 0]], x[edges[:, 1]])
    found = []
    for s in range(0, len(edges), chunk):
        lo, hi, ed = elo[s:s + chunk], ehi[s:s + chunk], edges[s:s + chunk]
        overlap = np.all((lo[:, None] <= thi[None]) & (tlo[None] <= hi[:, None]), axis=2)
        incident = (tris[None, :, :] == ed[:, None, 0:1]).any(2) | (tris[None, :, :] == ed[:, None, 1:2]).any(2)
        ei, ti = np.nonzero(overlap & ~incident)
        if len(ei) == 0:
            continue
        e = ed[ei]
        hit = segment_crosses_triangle(x[e[:, 0]], x[e[:, 1]], x[tris[ti, 0]], x[tris[ti, 1]], x[tris[ti, 2]])
        found.extend(zip((ei[hit] + s).tolist(), ti[hit].tolist()))
    return found


def crossing_pairs(xa, tris_a, xb, tris_b, chunk=256):
    """(mesh, edge, triangle) triples where an edge of one mesh crosses a triangle of the other (mesh 0: an edge of
    a crossing b's triangle; 1: the other way): two surfaces intersect iff some edge of one crosses the other."""
    out = []
    for side, (x, t, y, u) in enumerate(((xa, tris_a, xb, tris_b), (xb, tris_b, xa, tris_a))):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        edges = unique_edges(np.asarray(t, np.int64))
        u = np.asarray(u, np.int64)
        tlo, thi = y[u].min(1), y[u].max(1)
        elo = np.minimum(x[edges[:, 0]], x[edges[:, 1]])
        ehi = np.maximum(x[edges[:, 0]], x[edges[:, 1]])
        # only what overlaps the other mesh's bounding box can cross it (exact: a cheap cull for a large body)
        keep_t = np.all((tlo <= ehi.max(0)) & (elo.min(0) <= thi), axis=1)
        keep_e = np.all((elo <= thi.max(0)) & (tlo.min(0) <= ehi), axis=1)
        kept_t = np.flatnonzero(keep_t)
        u, tlo, thi = u[kept_t], tlo[kept_t], thi[kept_t]
        edge_ids = np.flatnonzero(keep_e)
        edges, elo, ehi = edges[keep_e], elo[keep_e], ehi[keep_e]
        for s in range(0, len(edges), chunk):
            lo, hi, ed = elo[s:s + chunk], ehi[s:s + chunk], edges[s:s + chunk]
            ei, ti = np.nonzero(np.all((lo[:, None] <= thi[None]) & (tlo[None] <= hi[:, None]), axis=2))
            if len(ei) == 0:
                continue
            e = ed[ei]
            hit = segment_crosses_triangle(x[e[:, 0]], x[e[:, 1]], y[u[ti, 0]], y[u[ti, 1]], y[u[ti, 2]])
            out.extend((side, int(edge_ids[a + s]), int(kept_t[b])) for a, b in zip(ei[hit], ti[hit]))
    return out


def closest_points(points, x, tris, chunk=64):
    """For each point, the closest point of the triangle mesh (x, tris), its distance and triangle (brute force, the
    region tests of Ericson's Real-Time Collision Detection 5.1.5, vectorised)."""
    p_all = np.asarray(points, np.float64)
    a, b, c = (np.asarray(x, np.float64)[np.asarray(tris, np.int64)[:, k]] for k in range(3))
    best_q = np.zeros_like(p_all)
    best_d = np.full(len(p_all), np.inf)
    best_t = np.zeros(len(p_all), np.int64)
    for s in range(0, len(p_all), chunk):
        p = p_all[s:s + chunk, None, :]
        ab, ac, ap = b - a, c - a, p - a
        d1, d2 = np.einsum("tk,ptk->pt", ab, ap), np.einsum("tk,ptk->pt", ac, ap)
        bp = p - b
        d3, d4 = np.einsum("tk,ptk->pt", ab, bp), np.einsum("tk,ptk->pt", ac, bp)
        cp = p - c
        d5, d6 = np.einsum("tk,ptk->pt", ab, cp), np.einsum("tk,ptk->pt", ac, cp)
        va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
        with np.errstate(divide="ignore", invalid="ignore"):
            denom = va + vb + vc
            v = np.where(denom != 0, vb / denom, 0.0)
            w = np.where(denom != 0, vc / denom, 0.0)  # inside the face
            # edges: ab, ac, bc
            t_ab = np.clip(np.where(d1 - d3 != 0, d1 / (d1 - d3), 0.0), 0, 1)
            t_ac = np.clip(np.where(d2 - d6 != 0, d2 / (d2 - d6), 0.0), 0, 1)
            t_bc = np.clip(np.where((d4 - d3) + (d5 - d6) != 0, (d4 - d3) / ((d4 - d3) + (d5 - d6)), 0.0), 0, 1)
        v = np.where(vc <= 0, t_ab, v)
        w = np.where(vc <= 0, 0.0, w)
        edge_ac = (vb <= 0) & (vc > 0)
        v, w = np.where(edge_ac, 0.0, v), np.where(edge_ac, t_ac, w)
        edge_bc = (va <= 0) & (vb > 0) & (vc > 0)
        v, w = np.where(edge_bc, 1.0 - t_bc, v), np.where(edge_bc, t_bc, w)
        q = a[None] + v[..., None] * ab[None] + w[..., None] * ac[None]
        d = np.linalg.norm(q - p, axis=2)
        t = d.argmin(1)
        rows = np.arange(len(t))
        best_q[s:s + chunk], best_d[s:s + chunk], best_t[s:s + chunk] = q[rows, t], d[rows, t], t
    return best_q, best_d, best_t
