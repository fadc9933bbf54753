"""Sewing patterns (cloth_warp/patterns.py): GarmentCode specifications read, curved edges, placement, panels meshed
with matching vertices along stitched edges."""

import math
import re

import numpy as np
import pytest

from cloth_warp.patterns import PatternEdge, PatternError, mesh_pattern, read_garmentcode


def skirt_spec(gap_cm=30.0, hem=(140.0, 0, 1)):
    """A two-panel skirt in centimetres: front and back face each other `gap_cm` apart (the back turned 180 degrees
    about y), sides stitched, a circular hem and a quadratic waist."""
    def panel(z, turned):
        edges = [{"endpoints": [0, 1]},
                 {"endpoints": [1, 2], "curvature": {"type": "circle", "params": list(hem)}},
                 {"endpoints": [2, 3]},
                 {"endpoints": [3, 0], "curvature": {"type": "quadratic", "params": [[0.5, 0.06]]}, "label": "waist"}]
        return {"translation": [-30.0 if not turned else 30.0, 100.0, z], "rotation": [0.0, 180.0 if turned else 0.0, 0.0],
                "vertices": [[0, 0], [-8, -55], [68, -55], [60, 0]], "edges": edges, "label": "leg"}

    return {"pattern": {"panels": {"front": panel(gap_cm / 2, False), "back": panel(-gap_cm / 2, True)},
                        "stitches": [[{"panel": "front", "edge": 0}, {"panel": "back", "edge": 2}],
                                     [{"panel": "front", "edge": 2}, {"panel": "back", "edge": 0}]]},
            "properties": {"units_in_meter": 100, "curvature_coords": "relative"}}


@pytest.mark.parametrize("large_arc,right", [(0, 1), (0, 0), (1, 1), (1, 0)])
def test_circle_edges_are_svg_arcs(large_arc, right):
    """Check a circle edge [radius, large_arc, right] from (-1, 0) to (1, 0): every sampled point at the radius from
    the centre, the ends exact, the arc on the right of start -> end when right = 1 (SVG's sweep flag in a y-up
    frame), the large arc sweeping more than half a turn."""
    e = PatternEdge(np.array([-1.0, 0.0]), np.array([1.0, 0.0]), "circle", radius=2.0, large_arc=bool(large_arc), sweep=bool(right))
    centre, _, sweep = e.arc()
    p = e.sample(40)
    np.testing.assert_allclose(np.linalg.norm(p - centre, axis=1), 2.0, atol=1e-12)
    np.testing.assert_allclose(p[[0, -1]], [[-1, 0], [1, 0]], atol=1e-12)
    middle = e.points(np.array([0.5]))[0]
    assert (middle[1] < 0.0) == bool(right)  # the right of +x is -y
    assert (abs(sweep) > math.pi) == bool(large_arc)
    assert e.length() == pytest.approx(2.0 * abs(sweep), rel=1e-4)


def test_bezier_control_points_are_relative_to_the_edge():
    """Check relative control points map to start + u e + v (-e_y, e_x): a quadratic over (0,0)-(2,0) with (0.5, 0.25)
    has its control at (1, 0.5) and its midpoint at (1, 0.25); a cubic's ends and symmetry."""
    spec = {"pattern": {"panels": {"p": {
        "vertices": [[0, 0], [2, 0], [2, 2], [0, 2]],
        "edges": [{"endpoints": [0, 1], "curvature": {"type": "quadratic", "params": [[0.5, 0.25]]}},
                  {"endpoints": [1, 2], "curvature": {"type": "cubic", "params": [[0.25, -0.2], [0.75, -0.2]]}},
                  {"endpoints": [2, 3]}, {"endpoints": [3, 0]}]}}},
        "properties": {"units_in_meter": 1}}
    p = read_garmentcode(spec).panels["p"]
    np.testing.assert_allclose(p.edges[0].controls[0], [1.0, 0.5])
    np.testing.assert_allclose(p.edges[0].points(np.array([0.5]))[0], [1.0, 0.25])
    cubic = p.edges[1]  # from (2,0) up to (2,2): the edge's left is -x, so v = -0.2 bows it out to +x
    np.testing.assert_allclose(cubic.controls, [[2.4, 0.5], [2.4, 1.5]])
    mid = cubic.points(np.array([0.5]))[0]
    assert mid[0] == pytest.approx(2.3) and mid[1] == pytest.approx(1.0)


def test_units_and_placement():
    """Check lengths come in metres from units_in_meter and a panel is rotated (XYZ Euler, degrees) then translated."""
    spec = skirt_spec()
    pattern = read_garmentcode(spec)
    back = pattern.panels["back"]
    assert pattern.units_in_meter == 100
    np.testing.assert_allclose(back.edges[1].start, [-0.08, -0.55])
    np.testing.assert_allclose(back.place(np.array([[0.1, 0.0]])), [[0.3 - 0.1, 1.0, -0.15]], atol=1e-12)  # 180 about y: x -> -x
    turned = read_garmentcode({**spec, "pattern": {**spec["pattern"], "panels": {"p": {**spec["pattern"]["panels"]["front"],
                                                                                       "rotation": [90.0, 0.0, 90.0]}}, "stitches": []}})
    # x then z: the panel's x axis goes to +y, its y axis to +z
    np.testing.assert_allclose(turned.panels["p"].placement() @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(turned.panels["p"].placement() @ [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], atol=1e-12)


@pytest.mark.parametrize("edge_length", [0.03, 0.017, 0.012, 0.006])
def test_panels_mesh_with_matching_vertices_along_stitches(edge_length):
    """Check the meshed skirt: each stitched pair of edges has as many vertices on both sides, paired from the ends
    that meet (every pair of the side seams the same 30 cm apart, front to back); the outline keeps its sampled points
    (none added by the mesher) and each panel's triangles cover exactly the area inside it; edges near the target
    length, also under 1.55 cm (where the area bound written with an exponent was read as square metres and the
    panels kept their outline's points alone); texture coordinates are the panel's 2D points."""
    pattern = read_garmentcode(skirt_spec())
    m = mesh_pattern(pattern, edge_length)
    for a, b in pattern.stitches:
        assert len(m.edge_vertices[a]) == len(m.edge_vertices[b]) >= 2
    gaps = np.linalg.norm(m.vertices[m.seams[:, 0]] - m.vertices[m.seams[:, 1]], axis=1)
    np.testing.assert_allclose(gaps, 0.30, atol=1e-9)
    lengths = np.linalg.norm(m.vertices[m.triangles] - m.vertices[m.triangles[:, [1, 2, 0]]], axis=2)
    assert lengths.max() < 2.0 * edge_length and np.median(lengths) == pytest.approx(edge_length, rel=0.35)
    for index, name in enumerate(m.panel_names):
        panel = pattern.panels[name]
        outline = m.uvs[m.outline[index]]
        ring = np.concatenate([e.sample(len(m.edge_vertices[(name, k)]) - 1)[:-1] for k, e in enumerate(panel.edges)])
        np.testing.assert_allclose(outline, ring, atol=1e-12)
        inside = 0.5 * abs(np.sum(outline[:, 0] * np.roll(outline[:, 1], -1) - np.roll(outline[:, 0], -1) * outline[:, 1]))
        t = m.triangles[m.panel[m.triangles[:, 0]] == index]
        uv = m.uvs[t]
        e1, e2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
        area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
        assert area.sum() == pytest.approx(inside, rel=1e-9)
        assert np.all(area > 0.0)
        np.testing.assert_allclose(m.vertices[m.panel == index], panel.place(m.uvs[m.panel == index]), atol=1e-12)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda s: s["pattern"]["panels"]["front"]["edges"][0].update(endpoints=[0, 9]), "pattern.panels.front.edges[0].endpoints"),
        (lambda s: s["pattern"]["panels"]["front"]["edges"][1]["curvature"].update(type="spline"),
         "pattern.panels.front.edges[1].curvature.type: 'spline' is not allowed"),
        (lambda s: s["pattern"]["panels"]["front"]["edges"][1]["curvature"].update(params=[-1.0, 0, 1]),
         "pattern.panels.front.edges[1].curvature.params[0]: the radius must be > 0"),
        (lambda s: s["pattern"]["stitches"][1][0].update(panel="sleeve"), "pattern.stitches[1][0].panel: 'sleeve' is not a panel"),
        (lambda s: s["pattern"]["stitches"][0][1].update(edge=7), "pattern.stitches[0][1].edge: expected an edge index in [0, 4)"),
        (lambda s: s["pattern"]["panels"]["back"]["edges"][2].update(endpoints=[3, 2]), "the edges do not form a loop"),
        (lambda s: s["properties"].update(units_in_meter=0), "properties.units_in_meter: must be > 0"),
        (lambda s: s["pattern"]["stitches"].append([{"panel": "back", "edge": 1}, {"panel": "front", "edge": 2}]),
         "pattern.stitches[2][1]: edge 2 of 'front' is already sewn by stitch 1 (an edge takes one stitch"),
        (lambda s: s["pattern"]["panels"]["back"].update(translation=[0, "up", 0]), "pattern.panels.back.translation[1]"),
    ],
)
def test_bad_specifications_name_the_key(edit, message):
    spec = skirt_spec()
    edit(spec)
    with pytest.raises(PatternError, match=re.escape(message)):
        read_garmentcode(spec)


def test_specification_files_are_read(tmp_path):
    """Check a specification file on disk reads as its dict does, and unreadable files say why."""
    import json

    path = tmp_path / "skirt_specification.json"
    path.write_text(json.dumps(skirt_spec()))
    a, b = read_garmentcode(path), read_garmentcode(skirt_spec())
    assert list(a.panels) == list(b.panels) and a.stitches == b.stitches
    (tmp_path / "broken.json").write_text("{ not json")
    with pytest.raises(PatternError, match="not JSON"):
        read_garmentcode(tmp_path / "broken.json")
    with pytest.raises(PatternError, match="cannot read"):
        read_garmentcode(tmp_path / "missing.json")


def test_a_pattern_sews_into_a_garment():
    """Check a two-panel skirt placed 4 cm apart (front and back), its waist held: the seam springs pull every
    stitched pair of points together to < 1 mm within 0.5 s (measured 0.16 mm after 10 frames) while the fabric stays
    within its strain limit; the seams are SEAM springs (never strain-limited, not in the strain statistics) and the
    cloth's texture coordinates are the panels' own."""
    import cloth_warp as cw
    from cloth_warp.topology import SpringKind

    b = cw.ModelBuilder()
    skirt = b.add_cloth_pattern(skirt_spec(gap_cm=4.0), edge_length=0.03, material="cotton", name="skirt")
    b.pin(skirt.select_box((-1.0, 0.99, -1.0), (1.0, 1.1, 1.0)))  # the waist line
    m = b.finalize("cpu")
    mesh = skirt.pattern_mesh
    assert len(skirt.seams) == sum(len(mesh.edge_vertices[a]) for a, _ in read_garmentcode(skirt_spec()).stitches)
    kinds = np.asarray(b.spring_kind)
    assert np.count_nonzero(kinds == SpringKind.SEAM) == len(skirt.seams)
    sim = cw.Simulator(m, cw.SolverImplicitEuler(m), fps=60, substeps=2)
    pinned = m.particle_pinned.numpy() != 0
    free = ~(pinned[skirt.seams[:, 0]] | pinned[skirt.seams[:, 1]])
    for _ in range(30):
        stats = sim.step_frame()
    x = sim.positions()
    gaps = np.linalg.norm(x[skirt.seams[free, 0]] - x[skirt.seams[free, 1]], axis=1)
    assert gaps.max() < 1e-3, gaps.max()
    assert stats.max_strain < 0.11
    corner_uv = skirt.topology.corner_uv.reshape(-1, 2)
    np.testing.assert_allclose(np.unique(np.round(corner_uv, 9), axis=0), np.unique(np.round(mesh.uvs, 9), axis=0))


def test_a_garments_edges_and_panels_are_named_selections(tmp_path):
    """Check a garment's named selections pick its pattern's particles: "edge:<label>" every edge with that label (the
    waist of both panels), "edge:<panel>:<index>" one edge, "panel:<panel>" a panel; an unknown name lists the allowed
    ones; and a scene's pins take them by name ("edge:waist": the particles on the waist, none else)."""
    import cloth_warp as cw
    from cloth_warp.scene import load_scene, scene_selection

    b = cw.ModelBuilder()
    skirt = b.add_cloth_pattern(skirt_spec(), edge_length=0.04, name="skirt")
    mesh = skirt.pattern_mesh
    front, back = mesh.edge_vertices[("front", 3)], mesh.edge_vertices[("back", 3)]
    np.testing.assert_array_equal(skirt.select("edge:waist"), skirt.indices(np.union1d(front, back)))
    np.testing.assert_array_equal(skirt.select("edge:front:3"), skirt.indices(np.sort(front)))
    np.testing.assert_array_equal(skirt.select("edge:back:1"), skirt.indices(np.sort(mesh.edge_vertices[("back", 1)])))
    np.testing.assert_array_equal(skirt.select("panel:back"), skirt.indices(np.flatnonzero(mesh.panel == 1)))
    assert len(skirt.select("panel:front")) + len(skirt.select("panel:back")) == skirt.particle_count
    y = b.particle_positions[skirt.select("edge:waist"), 1]
    assert np.ptp(y) < 0.05 and y.min() > b.particle_positions[skirt.select("panel:front"), 1].max() - 0.05  # the top
    for bad in ("edge:belt", "edge:front:4", "panel:sleeve", "edge:top", "corners"):
        with pytest.raises(ValueError, match="allowed: edge:waist, panel:front, panel:back, edge:<panel>:<index>"):
            skirt.select(bad)
    import json

    (tmp_path / "skirt_specification.json").write_text(json.dumps(skirt_spec()))
    (tmp_path / "skirt.toml").write_text('[cloth]\npattern = "skirt_specification.json"\nedge_length = 0.04\n'
                                         '[[pins]]\nselect = "edge:waist"\n')
    scene = load_scene(tmp_path / "skirt.toml")
    np.testing.assert_array_equal(scene_selection(scene, scene.data["pins"][0], "pins[0]"), np.union1d(front, back))


def test_a_scene_sews_a_pattern_next_to_a_walking_mannequin(tmp_path):
    """Check a scene file with cloth.pattern (a GarmentCode specification beside it) and a mannequin collider that
    walks runs to completion: the garment is one cloth with its panels' UVs in the cache, the body a deforming mesh
    collider written frame by frame."""
    import json

    from pxr import Usd, UsdGeom

    from cloth_warp.runner import run_scene

    (tmp_path / "skirt_specification.json").write_text(json.dumps(skirt_spec(gap_cm=4.0)))
    (tmp_path / "skirt.toml").write_text(
        '[cloth]\npattern = "skirt_specification.json"\nedge_length = 0.04\nname = "skirt"\n'
        '[[pins]]\nbox = { min = [-1.0, 0.99, -1.0], max = [1.0, 1.1, 1.0] }\n'
        '[[colliders]]\ntype = "mannequin"\nmotion = "walk"\nposition = [0.0, -0.7, -0.6]\n'
        '[solver]\nintegrator = "implicit_euler"\nsubsteps = 2\n[output]\nframes = 6\nfps = 60\n')
    summary = run_scene(tmp_path / "skirt.toml", {}, output=tmp_path / "skirt.usdc", frames=6, progress=None)
    assert summary["status"] == "complete"
    stage = Usd.Stage.Open(str(tmp_path / "skirt.usdc"))
    skirt = UsdGeom.Mesh(stage.GetPrimAtPath("/World/skirt"))
    assert UsdGeom.PrimvarsAPI(skirt).GetPrimvar("st")
    body = UsdGeom.Mesh(stage.GetPrimAtPath("/World/colliders/mannequin0"))
    assert body and len(body.GetPointsAttr().GetTimeSamples()) == 7  # the walking body, frame by frame


def _two_squares(stitch):
    """Two 40 cm squares in metres; "b" turned 90 degrees about z and moved so that the ends of a's right edge lie
    nearer the matching ends of b's left edge than the crossed ones (as in GarmentCode's hoody, whose hood seam's ends lie
    39 cm from the torso edge's ends one way round and 41 cm the other, summed)."""
    square = {"vertices": [[0, 0], [0.4, 0], [0.4, 0.4], [0, 0.4]], "edges": [{"endpoints": [k, (k + 1) % 4]} for k in range(4)]}
    return {"pattern": {"panels": {"a": {**square}, "b": {**square, "translation": [0.5, 0.45, 0.0], "rotation": [0.0, 0.0, 90.0]}},
                        "stitches": [stitch]}, "properties": {"units_in_meter": 1}}


@pytest.mark.parametrize("right_wrong", [False, True])
def test_stitches_are_sewn_as_garmentcode_sews_them_wherever_the_panels_lie(right_wrong):
    """Check a stitch sews the start of its first edge to the end of its second (two panels' counter-clockwise outlines
    run opposite ways along a seam), and start to start with GarmentCode's third entry "right_wrong", whatever the
    placement: here pairing the ends that lie nearest would sew the seam the other way (it twisted the hood of
    GarmentCode's own hoody pattern into a spike, and the waist seams of its pencil dress and jumpsuit)."""
    stitch = [{"panel": "a", "edge": 1}, {"panel": "b", "edge": 3}] + (["right_wrong"] if right_wrong else [])
    pattern = read_garmentcode(_two_squares(stitch))
    assert pattern.aligned == (frozenset({0}) if right_wrong else frozenset())
    m = mesh_pattern(pattern, 0.1)
    va, vb = m.edge_vertices[("a", 1)], m.edge_vertices[("b", 3)]
    x = m.vertices
    nearest = np.linalg.norm(x[va] - x[vb], axis=1).sum() < np.linalg.norm(x[va] - x[vb[::-1]], axis=1).sum()
    assert nearest  # (the placement would mislead a rule by distance)
    np.testing.assert_array_equal(m.seams, np.c_[va, vb if right_wrong else vb[::-1]])


def test_a_stitchs_third_entry_must_be_right_wrong():
    """Check a stitch with a third entry other than GarmentCode's "right_wrong" names it."""
    with pytest.raises(PatternError, match=re.escape("pattern.stitches[0][2]: 'inside_out' is not allowed; allowed: right_wrong")):
        read_garmentcode(_two_squares([{"panel": "a", "edge": 1}, {"panel": "b", "edge": 3}, "inside_out"]))


def test_absolute_control_points_are_read_in_the_panel_frame():
    """Check curvature_coords = "absolute" (GarmentCode's older templates): control points are the panel frame's
    points, in the pattern's unit, and give the curve their relative form gives; the old bare-list quadratic too."""
    def spec(coords, quadratic, cubic):
        return {"pattern": {"panels": {"p": {
            "vertices": [[0, 0], [200, 0], [200, 200], [0, 200]],
            "edges": [{"endpoints": [0, 1], "curvature": quadratic},
                      {"endpoints": [1, 2], "curvature": {"type": "cubic", "params": cubic}},
                      {"endpoints": [2, 3]}, {"endpoints": [3, 0]}]}}},
            "properties": {"units_in_meter": 100, "curvature_coords": coords}}

    relative = read_garmentcode(spec("relative", {"type": "quadratic", "params": [[0.5, 0.25]]}, [[0.25, -0.2], [0.75, -0.2]]))
    absolute = read_garmentcode(spec("absolute", {"type": "quadratic", "params": [[100, 50]]}, [[240, 50], [240, 150]]))
    bare = read_garmentcode(spec("absolute", [100, 50], [[240, 50], [240, 150]]))
    t = np.linspace(0.0, 1.0, 9)
    for k in range(2):
        np.testing.assert_allclose(absolute.panels["p"].edges[k].points(t), relative.panels["p"].edges[k].points(t), atol=1e-12)
    np.testing.assert_allclose(bare.panels["p"].edges[0].controls, [[1.0, 0.5]])
    with pytest.raises(PatternError, match="properties.curvature_coords: 'polar' is not allowed; allowed: relative, absolute"):
        read_garmentcode(spec("polar", [100, 50], [[240, 50], [240, 150]]))


def _skirt_tables():
    """skirt_spec() as a scene's panel table, in metres."""
    spec = skirt_spec()
    panels = []
    for name, p in spec["pattern"]["panels"].items():
        curves = [{"edge": k, **e["curvature"]} for k, e in enumerate(p["edges"]) if "curvature" in e]
        for c in curves:
            if c["type"] == "circle":
                c["params"] = [c["params"][0] * 0.01, *c["params"][1:]]  # (as read_garmentcode scales: the same bits)
        panels.append({"name": name, "vertices": (np.asarray(p["vertices"], float) * 0.01).tolist(),
                       "translation": (np.asarray(p["translation"], float) * 0.01).tolist(), "rotation": p["rotation"], "curves": curves})
    stitches = [{"panels": [a["panel"], b["panel"]], "edges": [a["edge"], b["edge"]]} for a, b in spec["pattern"]["stitches"]]
    return panels, stitches


def test_a_panel_table_reads_as_its_garmentcode_specification():
    """Check a scene's panel table (edge k from corner k to k + 1, curves by edge, metres) gives the pattern the same
    garment's GarmentCode specification gives: outlines, placement, stitches and their meshes."""
    from cloth_warp.patterns import pattern_from_tables

    panels, stitches = _skirt_tables()
    table, spec = pattern_from_tables(panels, stitches), read_garmentcode(skirt_spec())
    assert list(table.panels) == list(spec.panels) and table.stitches == spec.stitches and table.aligned == spec.aligned
    t = np.linspace(0.0, 1.0, 17)
    for name in spec.panels:
        a, b = table.panels[name], spec.panels[name]
        np.testing.assert_allclose(a.placement(), b.placement(), atol=1e-12)
        np.testing.assert_allclose(a.translation, b.translation, atol=1e-12)
        for ea, eb in zip(a.edges, b.edges, strict=True):
            np.testing.assert_allclose(ea.points(t), eb.points(t), atol=1e-12)
    ma, mb = mesh_pattern(table, 0.03), mesh_pattern(spec, 0.03)
    np.testing.assert_allclose(ma.vertices, mb.vertices, atol=1e-12)
    np.testing.assert_array_equal(ma.seams, mb.seams)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda p, s: p[1].update(name="front"), "cloth.panels[1].name: 'front' is the name of another panel"),
        (lambda p, s: p[0]["curves"][0].update(edge=4), "cloth.panels[0].curves[0].edge: expected an edge index in [0, 4), got 4"),
        (lambda p, s: p[0]["curves"][1].update(edge=1), "cloth.panels[0].curves[1].edge: edge 1 is curved twice"),
        (lambda p, s: p[0]["curves"][0].update(params=[-1.0, 0, 1]), "cloth.panels[0].curves[0].params[0]: the radius must be > 0"),
        (lambda p, s: p[1]["curves"][1].update(type="spline"), "cloth.panels[1].curves[1].type: 'spline' is not allowed"),
        (lambda p, s: s[1].update(panels=["front", "sleeve"]), "cloth.stitches[1].panels[1]: 'sleeve' is not a panel of the pattern"),
        (lambda p, s: s[0].update(edges=[0, 9]), "cloth.stitches[0].edges[1]: expected an edge index in [0, 4), got 9"),
        (lambda p, s: s[0].update(edges=[0]), "cloth.stitches[0].edges: expected the two panels' edge indices"),
    ],
)
def test_bad_panel_tables_name_the_scene_key(edit, message):
    from cloth_warp.patterns import pattern_from_tables

    panels, stitches = _skirt_tables()
    edit(panels, stitches)
    with pytest.raises(PatternError, match=re.escape(message)):
        pattern_from_tables(panels, stitches, "cloth")


PANEL_SCENE = """
[cloth]
name = "bag"
edge_length = 0.05
[[cloth.panels]]
name = "front"
vertices = [[0.0, 0.0], [0.4, 0.0], [0.4, 0.5], [0.0, 0.5]]
translation = [-0.2, 0.5, 0.05]
[[cloth.panels.curves]]
edge = 2
type = "quadratic"
params = [[0.5, 0.2]]
[[cloth.panels]]
name = "back"
vertices = [[0.0, 0.0], [0.4, 0.0], [0.4, 0.5], [0.0, 0.5]]
translation = [0.2, 0.5, -0.05]
rotation = [0.0, 180.0, 0.0]
[[cloth.stitches]]
panels = ["front", "back"]
edges = [1, 3]
[[cloth.stitches]]
panels = ["front", "back"]
edges = [3, 1]
aligned = false
"""


def test_a_scene_sews_its_panel_table(tmp_path):
    """Check a scene whose cloth is a panel table ([[cloth.panels]], [[cloth.stitches]]) loads, validates the table at
    the gate with the scene's key paths, and builds the garment its GarmentCode specification builds."""
    import cloth_warp as cw
    from cloth_warp.scene import SceneError, build_model, parse_scene

    model = build_model(parse_scene(PANEL_SCENE, tmp_path / "bag.toml"), "cpu")
    square = [[0.0, 0.0], [0.4, 0.0], [0.4, 0.5], [0.0, 0.5]]
    edges = [{"endpoints": [k, (k + 1) % 4]} for k in range(4)]
    spec = {"pattern": {"panels": {
        "front": {"vertices": square, "translation": [-0.2, 0.5, 0.05],
                  "edges": [*edges[:2], {**edges[2], "curvature": {"type": "quadratic", "params": [[0.5, 0.2]]}}, edges[3]]},
        "back": {"vertices": square, "translation": [0.2, 0.5, -0.05], "rotation": [0.0, 180.0, 0.0], "edges": edges}},
        "stitches": [[{"panel": "front", "edge": 1}, {"panel": "back", "edge": 3}],
                     [{"panel": "front", "edge": 3}, {"panel": "back", "edge": 1}]]},
        "properties": {"units_in_meter": 1}}
    b = cw.ModelBuilder()
    ref = b.add_cloth_pattern(spec, edge_length=0.05, name="bag")
    assert len(ref.seams) > 0
    np.testing.assert_array_equal(model.particle_q.numpy(), b.finalize("cpu").particle_q.numpy())
    with pytest.raises(SceneError, match=re.escape("cloth.stitches[1].edges[1]: expected an edge index in [0, 4), got 5")):
        parse_scene(PANEL_SCENE.replace("edges = [3, 1]", "edges = [3, 5]"), tmp_path / "bad.toml")
    with pytest.raises(SceneError, match=re.escape("cloth.panels[0].vertices[1]: expected 2 finite numbers")):
        parse_scene(PANEL_SCENE.replace("[0.4, 0.0], [0.4, 0.5]", "[0.4], [0.4, 0.5]", 1), tmp_path / "bad.toml")
    with pytest.raises(SceneError, match=re.escape("cloth.stitches: stitches sew the panels of cloth.panels; give them")):
        parse_scene('[[cloth.stitches]]\npanels = ["a", "b"]\nedges = [0, 1]\n', tmp_path / "c.toml")
    with pytest.raises(SceneError, match=re.escape("garments[0]: give one of pattern (a GarmentCode specification file) or panels")):
        parse_scene('[[garments]]\nname = "coat"\n', tmp_path / "d.toml")


def test_normalized_panel_translation_places_panels_as_garmentcode_does():
    """Check properties.normalize_panel_translation (GarmentCode's templates): each panel's vertices are moved to their
    mean and the translation's x and y shifted by it, unrotated, as GarmentCode's loader does, absolute control points
    moved with the vertices; false leaves the panel as written."""
    def spec(normalize):
        return {"pattern": {"panels": {"p": {
            "vertices": [[0, 0], [60, 0], [60, 40], [0, 40]], "translation": [10.0, 100.0, 5.0], "rotation": [20.0, 30.0, 40.0],
            "edges": [{"endpoints": [0, 1], "curvature": {"type": "quadratic", "params": [[30, -10]]}}, {"endpoints": [1, 2]},
                      {"endpoints": [2, 3]}, {"endpoints": [3, 0]}]}}},
            "properties": {"units_in_meter": 100, "curvature_coords": "absolute", "normalize_panel_translation": normalize}}

    plain, moved = read_garmentcode(spec(False)).panels["p"], read_garmentcode(spec(True)).panels["p"]
    mean = np.array([0.3, 0.2])
    np.testing.assert_allclose(moved.edges[1].start, plain.edges[1].start - mean, atol=1e-12)
    np.testing.assert_allclose(moved.edges[0].controls, [[0.0, -0.3]], atol=1e-12)
    np.testing.assert_allclose(moved.translation, [0.1 + 0.3, 1.0 + 0.2, 0.05], atol=1e-12)
    corner = np.array([0.6, 0.4])  # (60, 40) cm, as GarmentCode places it: R (v - mean) + t + (mean, 0)
    np.testing.assert_allclose(moved.place((corner - mean)[None])[0],
                               plain.placement() @ np.r_[corner - mean, 0.0] + [0.4, 1.2, 0.05], atol=1e-12)
    assert np.linalg.norm(moved.place((corner - mean)[None]) - plain.place(corner[None])) > 0.05  # (rotated: not the same)


@pytest.mark.parametrize("radius, overlap", [(0.20, True), (0.21, True), (0.23, False), (0.25, False)])
def test_panels_placed_into_each_other_are_refused(radius, overlap):
    """Check two skirt panels (70 cm hems) wrapped round one axis `radius` out: below 0.223 m their hems overlap, which
    no sewing or self-collision can undo, and the meshing says so naming both; further out they mesh (the refusal
    looks at the panels' inner points only, so panels side by side, touching at a seam, pass)."""
    from cloth_warp.patterns import Wrap, pattern_from_tables

    trapezoid = [[-0.35, 0.0], [0.35, 0.0], [0.25, 0.5], [-0.25, 0.5]]
    panels = [{"name": "front", "vertices": trapezoid, "translation": [0.0, 0.5, radius]},
              {"name": "back", "vertices": trapezoid, "translation": [0.0, 0.5, -radius], "rotation": [0.0, 180.0, 0.0]}]
    pattern = pattern_from_tables(panels, [{"panels": ["front", "back"], "edges": [1, 3]}])
    wraps = [Wrap(("front", "back"), (0.0, 0.0, 0.0))]
    if overlap:
        with pytest.raises(PatternError, match="'front' and 'back' are placed into each other"):
            mesh_pattern(pattern, 0.025, wraps=wraps)
    else:
        mesh_pattern(pattern, 0.025, wraps=wraps)
    flat = mesh_pattern(pattern_from_tables([{"name": "a", "vertices": trapezoid}, {"name": "b", "vertices": trapezoid,
                                                                                    "translation": [0.7, 0.0, 0.0]}]), 0.025)
    assert len(flat.vertices) > 0  # side by side, their hems touching at one corner


@pytest.mark.parametrize("gap, overlap", [(0.0, True), (0.001, True), (0.005, False), (0.02, False)])
def test_a_panel_laid_over_another_is_refused_only_where_they_coincide(gap, overlap):
    """Check a 20 cm pocket laid `gap` [m] in front of a 60 cm panel (2.5 cm edges): in its plane, or within a tenth
    of an edge of it, it is placed into the panel and refused; a few millimetres in front (a pocket, a collar, a layer
    over a cloth's thickness) it is not."""
    from cloth_warp.patterns import pattern_from_tables

    square = [[0.0, 0.0], [0.6, 0.0], [0.6, 0.6], [0.0, 0.6]]
    pocket = [[0.0, 0.0], [0.2, 0.0], [0.2, 0.2], [0.0, 0.2]]
    pattern = pattern_from_tables([{"name": "front", "vertices": square},
                                   {"name": "pocket", "vertices": pocket, "translation": [0.2, 0.2, gap]}])
    if overlap:
        with pytest.raises(PatternError, match="'front' and 'pocket' are placed into each other|'pocket' and 'front' are placed"):
            mesh_pattern(pattern, 0.025)
    else:
        mesh_pattern(pattern, 0.025)
