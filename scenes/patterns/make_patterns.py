"""Write the shipped sewing patterns (GarmentCode JSON specifications, centimetres) sized to the parametric mannequin
at 1.75 m (cloth_warp/mannequin.py). Run from anywhere: ``python scenes/patterns/make_patterns.py``.

Each panel is a flat piece in its own 2D frame (x across, y up) placed by translation and XYZ Euler rotation as
GarmentCode places them; the scenes wrap them round the body (``[[cloth.wraps]]``) and sew them in a dressing phase.
"""

import json
import math
import pathlib

HERE = pathlib.Path(__file__).resolve().parent


def _spec(panels: dict, stitches: list) -> dict:
    return {"pattern": {"panels": panels, "stitches": stitches},
            "properties": {"curvature_coords": "relative", "units_in_meter": 100}}


def _line(i, j, label=""):
    e = {"endpoints": [i, j]}
    if label:
        e["label"] = label
    return e


def _arc(i, j, radius, large, right, label=""):
    e = {"endpoints": [i, j], "curvature": {"type": "circle", "params": [radius, large, right]}}
    if label:
        e["label"] = label
    return e


def cone_panel(waist: float, hem: float, length: float, waist_height: float, wrap_radius: float, back: bool) -> dict:
    """A flared panel that is half of a cone's development: waist and hem arcs of half the circumferences `waist` and
    `hem` [cm] about an apex above it, `length` [cm] down its sides. Placed leaning out so that, wrapped round the vertical axis through
    the body, its waist sits at `wrap_radius` [cm] at height `waist_height` [cm] (wider than the body: dressing closes
    the gap)."""
    r_w = length * waist / (hem - waist)  # apex to waist along the panel
    r_h = r_w + length
    beta = 0.5 * waist / r_w  # the panel's angle at the apex [rad]
    apex_y = r_w  # the apex at (0, r_w) in the panel's frame; the waist's middle at the origin
    pts = []
    for r in (r_w, r_h):
        for s in (-1, 1):
            a = -math.pi / 2 + s * beta / 2
            pts.append([r * math.cos(a), apex_y + r * math.sin(a)])
    # vertices: 0 waist left, 1 waist right, 2 hem left, 3 hem right -> loop 0 -> 2 -> 3 -> 1 -> 0 (counter-clockwise)
    verts = [pts[0], pts[2], pts[3], pts[1]]
    edges = [_line(0, 1, "left_side"), _arc(1, 2, r_h, 0, 1, "hem"), _line(2, 3, "right_side"), _arc(3, 0, r_w, 0, 0, "waist")]
    sin_tilt = wrap_radius / r_w
    tilt = math.degrees(math.asin(sin_tilt))
    apex_world = waist_height + r_w * math.cos(math.radians(tilt))
    if not back:  # facing +z, the hem leaning out (+z)
        rotation = [-tilt, 0.0, 0.0]
        translation = [0.0, apex_world - apex_y * math.cos(math.radians(tilt)), apex_y * sin_tilt]
    else:  # turned to face -z
        rotation = [-tilt, 180.0, 0.0]
        translation = [0.0, apex_world - apex_y * math.cos(math.radians(tilt)), -apex_y * sin_tilt]
    return {"vertices": [[round(x, 6), round(y, 6)] for x, y in verts], "edges": edges, "translation": translation,
            "rotation": rotation, "label": "back" if back else "front"}


def skirt() -> dict:
    """An A-line skirt: two flared panels (waist 96 cm: the body's 91 cm at y = 1 m, its 4 mm contact thickness and a
    little ease; hem 160 cm; 46 cm long) sewn at the sides."""
    front = cone_panel(96.0, 160.0, 46.0, 100.0, 19.0, back=False)
    back = cone_panel(96.0, 160.0, 46.0, 100.0, 19.0, back=True)
    stitches = [[{"panel": "front", "edge": 0}, {"panel": "back", "edge": 2}],
                [{"panel": "front", "edge": 2}, {"panel": "back", "edge": 0}]]
    return _spec({"front": front, "back": back}, stitches)


def overskirt() -> dict:
    """A shorter, fuller skirt worn over the A-line one (a layered outfit): waist 104 cm (over the inner skirt's
    waistband), hem 190 cm, 34 cm long, placed on a wider cone than the inner skirt (its layer outside)."""
    front = cone_panel(104.0, 190.0, 34.0, 100.5, 21.5, back=False)
    back = cone_panel(104.0, 190.0, 34.0, 100.5, 21.5, back=True)
    stitches = [[{"panel": "front", "edge": 0}, {"panel": "back", "edge": 2}],
                [{"panel": "front", "edge": 2}, {"panel": "back", "edge": 0}]]
    return _spec({"front": front, "back": back}, stitches)


def main():
    for name, make in (("skirt", skirt), ("overskirt", overskirt)):
        (HERE / f"{name}_specification.json").write_text(json.dumps(make(), indent=1) + "\n")


if __name__ == "__main__":
    main()
