"""Write scenes/meshes/skirt.obj: a flared skirt (a cone frustum open at both ends) with a UV seam.

The OBJ duplicates the seam column (u = 0 and u = 1 at the same positions), as exported garments do; the
simulator welds it and writes face-varying UVs, so the seam survives in the cache. Units: metres, +Y up.
Run from the repository root: python scenes/meshes/make_skirt.py
"""

import math
import pathlib

WAIST_RADIUS, HEM_RADIUS = 0.16, 0.36  # [m]
WAIST_HEIGHT, HEM_HEIGHT = 1.0, 0.45  # [m]
AROUND, DOWN = 48, 14  # segments around the waist, rows from waist to hem


def skirt_obj() -> str:
    lines = ["# Flared skirt for cloth_warp (scenes/meshes/make_skirt.py); metres, +Y up", "o skirt"]
    for j in range(DOWN + 1):
        s = j / DOWN
        r = WAIST_RADIUS + s * (HEM_RADIUS - WAIST_RADIUS)
        y = WAIST_HEIGHT + s * (HEM_HEIGHT - WAIST_HEIGHT)
        for i in range(AROUND + 1):  # column AROUND repeats column 0 (the seam)
            a = 2.0 * math.pi * (i % AROUND) / AROUND
            lines.append(f"v {r * math.sin(a):.6f} {y:.6f} {r * math.cos(a):.6f}")
    for j in range(DOWN + 1):
        for i in range(AROUND + 1):
            lines.append(f"vt {i / AROUND:.6f} {1.0 - j / DOWN:.6f}")

    def vid(i, j):  # 1-based OBJ index, same for v and vt
        return j * (AROUND + 1) + i + 1

    for j in range(DOWN):
        for i in range(AROUND):
            a, b, c, d = vid(i, j), vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)
            # Counter-clockwise seen from outside (normals point away from the axis).
            lines.append(f"f {a}/{a} {d}/{d} {c}/{c}")
            lines.append(f"f {a}/{a} {c}/{c} {b}/{b}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    out = pathlib.Path(__file__).with_name("skirt.obj")
    out.write_text(skirt_obj())
    print(f"wrote {out}")
