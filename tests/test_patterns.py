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
