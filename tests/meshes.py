"""Strip and sheet meshes of several kinds for property tests (pure numpy): grid cells of any aspect ratio,
right-angled, equilateral and irregular triangles. Every mesh has straight edges at x = 0 and x = length, so
a clamp at x <= 0 is the same on all of them."""

import numpy as np

from cloth_warp import topology as topo

KINDS = ("right", "equilateral", "irregular")


def strip_mesh(kind: str, length: float, width: float, h: float, root: float = 0.0, seed: int = 0):
    """(vertices (n, 3), triangles) of the strip [-root, length] x [0, width] in the xy-plane, edge length ~h."""
    if kind == "right":
        nx, ny = int(round((length + root) / h)), max(2, int(round(width / h)))
        t = topo.grid_topology((nx, ny), (length + root, width))
        v = t.positions.copy()
        v[:, 0] -= root
        return v, t.triangles.astype(np.int64)
    rows = max(2, int(round(width / (h * np.sqrt(3) / 2))))
    nx = int(round((length + root) / h))
    xs_even = np.linspace(-root, length, nx + 1)
    xs_odd = np.unique(np.concatenate([[-root, 0.0, length], 0.5 * (xs_even[1:] + xs_even[:-1])]))
    verts, row_ids = [], []
    for j in range(rows + 1):
        xs = xs_odd if j % 2 else xs_even
        row_ids.append(list(range(len(verts), len(verts) + len(xs))))
        verts.extend((x, j * width / rows, 0.0) for x in xs)
    v = np.asarray(verts)
    tris = []
    for j in range(rows):
        a, b = row_ids[j], row_ids[j + 1]
        ia = ib = 0
        while ia < len(a) - 1 or ib < len(b) - 1:  # zip the two rows by x
            if ib >= len(b) - 1 or (ia < len(a) - 1 and v[a[ia + 1], 0] <= v[b[ib + 1], 0]):
                tris.append((a[ia], a[ia + 1], b[ib]))
                ia += 1
            else:
                tris.append((a[ia], b[ib + 1], b[ib]))
                ib += 1
    if kind == "irregular":
        rng = np.random.default_rng(seed)
        eps = 1e-9 * max(length, width)
        inner = (v[:, 1] > eps) & (v[:, 1] < width - eps) & (np.abs(v[:, 0]) > eps) & (v[:, 0] > -root + eps) & (v[:, 0] < length - eps)
        v[inner, :2] += rng.uniform(-0.25, 0.25, (int(inner.sum()), 2)) * h
    return v, np.asarray(tris, np.int64)
