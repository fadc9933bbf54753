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


def tshirt() -> dict:
    """A T-shirt: front and back panels (55 cm wide: 110 cm round against the chest's 97; hip to shoulder, a 22 cm
    wide crew neckline, 9 cm deep in front and 3 cm at the back, armholes from the shoulder point down to the side
    seams' tops) and two short sleeves (40 cm round at the cuff, a bell-shaped cap whose halves match the armholes, an
    underarm seam). The body panels are placed round the torso leaning in by 15 degrees about the armpit line (wrapped
    on cylinders about axes leaning alike: in the scene, `[[cloth.wraps]]`), each sleeve round its upper arm's axis in
    the mannequin's A-pose (arms 25 degrees out, shoulder joints at 0.8 of the height, 0.125 of it out); the shoulders,
    sides, underarms and armholes are sewn in the dressing. (Upright panels left the shoulder seams 43 cm to close: the
    pull slid the shirt up the chest until the neckline gripped the neck and the seams at the neck stayed 1 cm open; a
    34 cm cuff, 1 cm looser than the arm, caught the underarm seam between arm and torso.)"""
    hem_y, half, armpit, shoulder_x, shoulder, neck_x, neck, scoop = 90.0, 27.5, 34.0, 20.0, 58.0, 11.0, 63.0, 0.3
    reach, tilt = 21.5, 15.0  # [cm] the panels' distance from the body's axis at the armpits; [deg] their lean

    def body(dip: float, back: bool) -> dict:
        radius = (neck_x ** 2 + dip ** 2) / (2.0 * dip)  # the neckline: an arc from neck point to neck point
        verts = [[-half, 0.0], [half, 0.0], [half, armpit], [shoulder_x, shoulder], [neck_x, neck], [-neck_x, neck],
                 [-shoulder_x, shoulder], [-half, armpit]]
        armhole = {"type": "quadratic", "params": [[0.5, scoop]]}  # curving in towards the neck, as armholes do
        edges = [_line(0, 1, "hem"), _line(1, 2, "right_side"), {**_line(2, 3, "right_armhole"), "curvature": armhole},
                 _line(3, 4, "right_shoulder"), _arc(4, 5, radius, 0, 0, "neckline"), _line(5, 6, "left_shoulder"),
                 {**_line(6, 7, "left_armhole"), "curvature": armhole}, _line(7, 0, "left_side")]
        # leaning in above the armpits by `tilt` (the tops nearer the shoulders: a shorter way to sew them, and less
        # cloth pushed up the chest while it closes); the hem centre is where the panel leaves the armpit line
        side = -1.0 if back else 1.0
        lean = math.radians(tilt)
        hem = [0.0, hem_y + armpit - armpit * math.cos(lean), side * (reach / math.cos(lean) + armpit * math.sin(lean))]
        return {"vertices": verts, "edges": edges, "translation": [round(v, 6) for v in hem],
                "rotation": [-tilt, 180.0 if back else 0.0, 0.0], "label": "back" if back else "front"}

    chord = math.hypot(half - shoulder_x, shoulder - armpit)
    # each armhole edge's length: a quadratic Bezier whose control point is `scoop` chords off the chord's middle
    t = [k / 200.0 for k in range(201)]
    bulge = [2.0 * u * (1.0 - u) * scoop * chord for u in t]  # the curve's offset from the chord
    armhole = sum(math.hypot(chord / 200.0, bulge[k + 1] - bulge[k]) for k in range(200))
    cuff, width, underarm = 40.0, 42.0, 12.0
    cap = math.sqrt(armhole ** 2 - (0.5 * width) ** 2)  # the cap's height: each half as long as its armhole

    def sleeve(side: float) -> dict:
        tilt = math.radians(25.0)
        down = [side * math.sin(tilt), -math.cos(tilt), 0.0]  # along the arm, away from the shoulder
        out = [side * math.cos(tilt), math.sin(tilt), 0.0]  # from the arm's axis up and out: the sleeve's top
        joint = [side * 0.125 * 175.0, 0.80 * 175.0, 0.0]
        reach = 7.5  # [cm] the sleeve's radius where it is placed (the arm's is 5.25)
        peak = underarm + cap  # the cap's top, placed over the shoulder joint
        origin = [joint[k] + reach * out[k] + peak * down[k] for k in range(3)]
        verts = [[-0.5 * cuff, 0.0], [0.5 * cuff, 0.0], [0.5 * width, underarm], [0.0, peak], [-0.5 * width, underarm]]
        edges = [_line(0, 1, "cuff"), _line(1, 2, "right_underarm"), _line(2, 3, "right_cap"), _line(3, 4, "left_cap"),
                 _line(4, 0, "left_underarm")]
        name = "left_sleeve" if side > 0 else "right_sleeve"
        return {"vertices": [[round(x, 6), round(y, 6)] for x, y in verts], "edges": edges,
                "translation": [round(v, 6) for v in origin], "rotation": [0.0, side * 90.0, side * 25.0], "label": name}

    panels = {"front": body(9.0, False), "back": body(3.0, True), "left_sleeve": sleeve(1.0), "right_sleeve": sleeve(-1.0)}
    # the back is turned about y: its left edges are on the body's left (+x), where the front's right edges are; a
    # sleeve's panel x runs round the arm towards the back on the left arm, towards the front on the right one
    stitches = [[{"panel": "front", "edge": 1}, {"panel": "back", "edge": 7}],
                [{"panel": "front", "edge": 7}, {"panel": "back", "edge": 1}],
                [{"panel": "front", "edge": 3}, {"panel": "back", "edge": 5}],
                [{"panel": "front", "edge": 5}, {"panel": "back", "edge": 3}],
                [{"panel": "front", "edge": 2}, {"panel": "left_sleeve", "edge": 3}],
                [{"panel": "back", "edge": 6}, {"panel": "left_sleeve", "edge": 2}],
                [{"panel": "front", "edge": 6}, {"panel": "right_sleeve", "edge": 2}],
                [{"panel": "back", "edge": 2}, {"panel": "right_sleeve", "edge": 3}],
                [{"panel": "left_sleeve", "edge": 1}, {"panel": "left_sleeve", "edge": 4}],
                [{"panel": "right_sleeve", "edge": 1}, {"panel": "right_sleeve", "edge": 4}]]
    return _spec(panels, stitches)


def main():
    for name, make in (("skirt", skirt), ("overskirt", overskirt), ("dress", dress), ("tshirt", tshirt)):
        (HERE / f"{name}_specification.json").write_text(json.dumps(make(), indent=1) + "\n")


if __name__ == "__main__":
    main()
