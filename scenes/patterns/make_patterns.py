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
    return {"vertices": [[round(x, 6), round(y, 6)] for x, y in verts], "edges": edges,
            **_cone_placement(r_w, wrap_radius, waist_height, back)}


def strapped_cone_panel(top: float, hem: float, length: float, top_height: float, wrap_radius: float,
                        strap_offset: float, strap_width: float, strap_length: float, back: bool) -> dict:
    """A dress panel: half of a cone's development as :func:`cone_panel` (top and hem arcs of half the circumferences
    `top` and `hem` [cm], `length` [cm] down its sides), with two shoulder straps `strap_width` [cm] wide rising
    `strap_length` [cm] from the top arc towards the apex, centred `strap_offset` [cm] along the arc either side of
    its middle. Placed as :func:`cone_panel`; the straps' ends (edges 5 and 9) are sewn to the other panel's over the
    shoulders."""
    r_t = length * top / (hem - top)  # apex to top arc along the panel
    r_h = r_t + length
    half = 0.25 * top / r_t  # half the panel's angle at the apex [rad]
    apex = (0.0, r_t)  # in the panel's frame; the top arc's middle at the origin

    def on_arc(r, a):
        return [apex[0] + r * math.cos(a), apex[1] + r * math.sin(a)]

    down = -math.pi / 2
    straps = []
    for side in (1, -1):  # the right strap, then the left one (the outline runs counter-clockwise)
        centre = down + side * strap_offset / r_t
        base_out, base_in = (on_arc(r_t, centre + side * 0.5 * strap_width / r_t),
                             on_arc(r_t, centre - side * 0.5 * strap_width / r_t))
        mid = on_arc(r_t, centre)
        up = [apex[0] - mid[0], apex[1] - mid[1]]
        norm = math.hypot(*up)
        up = [strap_length * u / norm for u in up]  # both strap sides parallel to the generator through its middle
        tip_out = [base_out[0] + up[0], base_out[1] + up[1]]
        tip_in = [base_in[0] + up[0], base_in[1] + up[1]]
        straps.append((base_out, tip_out, tip_in, base_in))
    (r_out, r_tip_out, r_tip_in, r_in), (l_in, l_tip_in, l_tip_out, l_out) = straps[0], straps[1][::-1]
    verts = [on_arc(r_t, down - half), on_arc(r_h, down - half), on_arc(r_h, down + half), on_arc(r_t, down + half),
             r_out, r_tip_out, r_tip_in, r_in, l_in, l_tip_in, l_tip_out, l_out]
    edges = [_line(0, 1, "left_side"), _arc(1, 2, r_h, 0, 1, "hem"), _line(2, 3, "right_side"),
             _arc(3, 4, r_t, 0, 0, "top"), _line(4, 5), _line(5, 6, "right_strap"), _line(6, 7),
             _arc(7, 8, r_t, 0, 0, "neckline"), _line(8, 9), _line(9, 10, "left_strap"), _line(10, 11),
             _arc(11, 0, r_t, 0, 0, "top")]
    return {"vertices": [[round(x, 6), round(y, 6)] for x, y in verts], "edges": edges,
            **_cone_placement(r_t, wrap_radius, top_height, back)}


def _cone_placement(r_top: float, wrap_radius: float, top_height: float, back: bool) -> dict:
    """Translation, rotation and label placing a panel whose top arc (radius `r_top` [cm] about an apex at
    (0, r_top) in the panel's frame, its middle at the origin) leans out so that, wrapped round the vertical axis
    through the body, the arc sits at `wrap_radius` [cm] at height `top_height` [cm]; the front panel faces +z, the
    back one is turned to face -z."""
    tilt = round(math.degrees(math.asin(wrap_radius / r_top)), 6)  # the arc's middle (the origin) lands at wrap_radius
    if not back:  # the hem leaning out (+z)
        return {"translation": [0.0, top_height, wrap_radius], "rotation": [-tilt, 0.0, 0.0], "label": "front"}
    return {"translation": [0.0, top_height, -wrap_radius], "rotation": [-tilt, 180.0, 0.0], "label": "back"}


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


def dress() -> dict:
    """A strapped A-line dress: two panels from above the bust (top 102 cm round at 1.25 m: the chest's 97 cm with
    ease, below the armpits) to above the knee (hem 180 cm, 75 cm long), each with two 4 cm straps 25 cm long, sewn at
    the sides and over the shoulders (front straps to back straps)."""
    panel = dict(top=102.0, hem=180.0, length=75.0, top_height=125.0, wrap_radius=21.0, strap_offset=11.5,
                 strap_width=4.0, strap_length=25.0)
    front, back = strapped_cone_panel(**panel, back=False), strapped_cone_panel(**panel, back=True)
    stitches = [[{"panel": "front", "edge": 0}, {"panel": "back", "edge": 2}],
                [{"panel": "front", "edge": 2}, {"panel": "back", "edge": 0}],
                [{"panel": "front", "edge": 5}, {"panel": "back", "edge": 9}],  # the back is turned: its left strap
                [{"panel": "front", "edge": 9}, {"panel": "back", "edge": 5}]]  # is over the front's right one
    return _spec({"front": front, "back": back}, stitches)


def main():
    for name, make in (("skirt", skirt), ("overskirt", overskirt), ("dress", dress)):
        (HERE / f"{name}_specification.json").write_text(json.dumps(make(), indent=1) + "\n")


if __name__ == "__main__":
    main()
