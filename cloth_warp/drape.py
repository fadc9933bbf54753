"""Drape measures: the Cusick drape coefficient of a circular specimen on a pedestal (BS 5058 / ISO 9073-9).

A disc of fabric (radius R) rests centred on a smaller pedestal (radius r); the drape coefficient is
the share of the annulus outside the pedestal that the fabric's shadow still covers,

    DC = (A_shadow - pi r^2) / (pi R^2 - pi r^2),

1 for a rigid specimen that stays flat, near 0 for a limp one hanging straight down. The shadow is the
fabric's projection along the up axis, rasterised here (the union of the projected triangles).
"""

from __future__ import annotations

import math

import numpy as np

AXES = {"X": 0, "Y": 1, "Z": 2}


def projected_area(points, triangles, *, up_axis: str = "Y", pixel: float) -> float:
    """Area [m^2] of the union of the triangles projected along the up axis (pixel-centre sampling)."""
    up = AXES[up_axis.upper()]
    plane = [a for a in range(3) if a != up]
    p = np.asarray(points, np.float64)[:, plane]
    t = np.asarray(triangles, np.int64)
    lo = p.min(0) - pixel
    shape = np.ceil((p.max(0) + pixel - lo) / pixel).astype(int) + 1
    covered = np.zeros(shape, bool)
    a, b, c = p[t[:, 0]], p[t[:, 1]], p[t[:, 2]]
    for k in range(len(t)):
        tri = np.stack([a[k], b[k], c[k]])
        i0, j0 = np.floor((tri.min(0) - lo) / pixel).astype(int)
        i1, j1 = np.ceil((tri.max(0) - lo) / pixel).astype(int)
        xs = lo[0] + (np.arange(i0, i1 + 1) + 0.5) * pixel
        ys = lo[1] + (np.arange(j0, j1 + 1) + 0.5) * pixel
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        # same-side test against the three edges (either winding)
        d = [(tri[(e + 1) % 3, 0] - tri[e, 0]) * (gy - tri[e, 1]) - (tri[(e + 1) % 3, 1] - tri[e, 1]) * (gx - tri[e, 0]) for e in range(3)]
        inside = ((d[0] >= 0) & (d[1] >= 0) & (d[2] >= 0)) | ((d[0] <= 0) & (d[1] <= 0) & (d[2] <= 0))
        covered[i0:i1 + 1, j0:j1 + 1] |= inside
    return float(covered.sum()) * pixel * pixel


def drape_coefficient(points, triangles, *, pedestal_radius: float, disc_radius: float, up_axis: str = "Y",
                      pixel: float | None = None) -> float:
    """Cusick drape coefficient of a specimen of radius `disc_radius` [m] on a pedestal of `pedestal_radius`."""
    if not (0.0 < pedestal_radius < disc_radius):
        raise ValueError(f"need 0 < pedestal radius < disc radius, got {pedestal_radius!r}, {disc_radius!r}")
    pixel = disc_radius / 400.0 if pixel is None else pixel
    shadow = projected_area(points, triangles, up_axis=up_axis, pixel=pixel)
    a_pedestal = math.pi * pedestal_radius**2
    return (shadow - a_pedestal) / (math.pi * disc_radius**2 - a_pedestal)
