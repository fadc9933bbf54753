"""Garments dressed onto a body (cloth_warp/dressing.py): panels wrapped round the body without stretching
(patterns.Wrap), seams closed in a dressing phase, a sewn garment one vertex per seam point to self-collision and in
the cache, nothing inside the body or crossing it."""

import copy
import json
import math
import pathlib

import numpy as np
import pytest

import cloth_warp as cw
from cloth_warp.cache import _cloth_meshes
from cloth_warp.dressing import (SEAM_FINISH, DressingReport, crossing_pairs as dressing_crossings, dress, finish_seams,
                                 finish_seams_clear, seam_gap, self_crossings, settle)
from cloth_warp.mannequin import Mannequin
from cloth_warp.model import quat_to_matrix
from cloth_warp.patterns import Wrap, mesh_pattern, read_garmentcode, wrap_points
from cloth_warp.scene import SceneError, build_model, parse_scene
from cloth_warp.topology import seam_roots
from intersections import crossing_pairs, intersecting_pairs, segment_crosses_triangle

ROOT = pathlib.Path(__file__).resolve().parents[1]
SKIRT = ROOT / "scenes" / "patterns" / "skirt_specification.json"
OVERSKIRT = ROOT / "scenes" / "patterns" / "overskirt_specification.json"


def test_a_circle_edge_radius_is_in_the_pattern_units():
    """Check a circle edge of radius 50 in a centimetre pattern is an arc of radius 0.5 m through its endpoints."""
    spec = {"pattern": {"panels": {"p": {"vertices": [[0, 0], [60, 0], [60, 40], [0, 40]],
                                         "edges": [{"endpoints": [0, 1], "curvature": {"type": "circle", "params": [50, 0, 1]}},
                                                   {"endpoints": [1, 2]}, {"endpoints": [2, 3]}, {"endpoints": [3, 0]}]}}},
            "properties": {"units_in_meter": 100, "curvature_coords": "relative"}}
    edge = read_garmentcode(spec).panels["p"].edges[0]
    centre, _, _ = edge.arc()
    pts = edge.sample(32)
    np.testing.assert_allclose(np.linalg.norm(pts - centre, axis=1), 0.5, atol=1e-9)
    assert np.ptp(pts[:, 1]) == pytest.approx(0.5 - math.sqrt(0.5**2 - 0.3**2), rel=1e-6)  # the sagitta of a 60 cm chord


@pytest.mark.parametrize("tilt", [0.0, 8.0, 20.0])
@pytest.mark.parametrize("seed", [0, 1])
def test_wrapping_keeps_every_length_and_lands_on_the_cylinder_or_cone(tilt, seed):
    """Check panels wrapped about a random axis: lengths are kept (the map's Jacobian is orthonormal on the plane at
    every point), the panels' points lie on the cylinder at the plane's distance (tilt 0) or on the cone of half-angle = tilt about the axis; ."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=3)
    a /= np.linalg.norm(a)
    n = np.cross(a, rng.normal(size=3))
    n /= np.linalg.norm(n)
    # tilt the plane's normal towards the axis: the plane then meets the axis at `tilt` degrees
    n = math.cos(math.radians(tilt)) * n - math.sin(math.radians(tilt)) * a
    c = rng.normal(size=3)
    d = 0.15 + 0.1 * rng.random()
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    origin = c + d * n / math.cos(math.radians(tilt)) if tilt else c + d * n
    uv = rng.uniform(-0.25, 0.25, size=(400, 2))
    x = origin + uv[:, :1] * u + uv[:, 1:] * w
    y = wrap_points(x, n, c, a)
    rel = y - c
    along = rel @ a
    radial = np.linalg.norm(rel - np.outer(along, a), axis=1)
    if tilt == 0.0:
        np.testing.assert_allclose(radial, d, rtol=1e-9)
    else:
        apex = c + a * float((x[0] - c) @ n) / float(n @ a)
        r = y - apex
        cosines = np.abs(r @ a) / np.linalg.norm(r, axis=1)
        np.testing.assert_allclose(cosines, math.cos(math.radians(tilt)), atol=1e-9)
    # lengths are kept: the map's Jacobian is orthonormal on the plane at every point
    h = 1e-6
    p = x
    du = (wrap_points(p + h * u, n, c, a) - wrap_points(p - h * u, n, c, a)) / (2 * h)
    dw = (wrap_points(p + h * w, n, c, a) - wrap_points(p - h * w, n, c, a)) / (2 * h)
    np.testing.assert_allclose(np.linalg.norm(du, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(dw, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.einsum("ij,ij->i", du, dw), 0.0, atol=1e-6)


def test_the_shipped_skirt_wraps_round_the_hips_without_stretching():
    """Check the shipped skirt pattern wrapped round the vertical axis: its mesh edges keep their panel lengths, its
    waist ring is a circle at the placed radius and height, its side seams start open (the dressing closes them)."""
    pattern = read_garmentcode(SKIRT)
    m = mesh_pattern(pattern, 0.03, wraps=[Wrap(("front", "back"), (0.0, 0.0, 0.0))])
    t = m.triangles
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    flat = np.linalg.norm(m.uvs[e[:, 0]] - m.uvs[e[:, 1]], axis=1)
    placed = np.linalg.norm(m.vertices[e[:, 0]] - m.vertices[e[:, 1]], axis=1)
    assert np.abs(placed / flat - 1.0).max() < 2e-3  # chords of a curved surface: second order in the edge length
    waist = np.concatenate([m.vertices[m.edge_vertices[(p, 3)]] for p in ("front", "back")])
    np.testing.assert_allclose(np.linalg.norm(waist[:, [0, 2]], axis=1), 0.19, atol=1e-6)
    np.testing.assert_allclose(waist[:, 1], 1.0, atol=1e-6)
    gaps = np.linalg.norm(m.vertices[m.seams[:, 0]] - m.vertices[m.seams[:, 1]], axis=1)
    assert 0.1 < gaps.min() and gaps.max() < 0.3


def test_wrapping_a_panel_that_is_not_in_the_pattern_names_it():
    with pytest.raises(cw.InvalidValue, match=r"wraps\[0\]\.panels: 'sleeve' is not a panel"):
        mesh_pattern(read_garmentcode(SKIRT), 0.05, wraps=[Wrap(("front", "sleeve"), (0.0, 0.0, 0.0))])


def _penetration(body: Mannequin, x: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Per point, how deep [m] it lies inside the posed body (> 0: inside), each segment a convex hull."""
    import trimesh

    depth = np.full(len(x), -np.inf)
    for k in range(len(body.segments)):
        hull = trimesh.convex.convex_hull(vertices[body.segment_of_vertex == k])
        n = hull.face_normals
        offset = np.einsum("ij,ij->i", hull.vertices[hull.faces[:, 0]], n)
        depth = np.maximum(depth, -(x @ n.T - offset).max(1))
    return depth


@pytest.fixture(scope="module")
def dressed():
    """The shipped skirt pattern (coarse) dressed onto the still mannequin, waist attached and settled."""
    body = Mannequin(1.75)
    b = cw.ModelBuilder()
    col = b.add_collider_mesh(body.rest_vertices, body.triangles, name="body", friction=0.5)
    skirt = b.add_cloth_pattern(SKIRT, edge_length=0.04, wraps=[Wrap(("front", "back"), (0.0, 0.0, 0.0))], material="cotton", name="skirt")
    b.enable_self_collision(0.004, 0.3)
    gap0 = seam_gap(b)
    report = dress(b, 1.0, solver_options=dict(collider_contacts="solve"))
    x = b.particle_positions
    waist = skirt.indices()[x[skirt.indices(), 1] > 0.995]
    b.attach(waist, col)
    settled = settle(b, 0.5, solver_options=dict(collider_contacts="solve"))
    return body, b, skirt, gap0, report, settled


def test_dressing_closes_the_seams_with_nothing_inside_the_body(dressed):
    """Check the dressing closes side seams that start 13-23 cm open to under a millimetre, within the strain limit, and
    that the dressed and the settled skirt have no point inside the body, no edge crossing it and no triangle crossing
    another (the garment as the cache writes it, one vertex per seam point)."""
    body, b, skirt, gap0, report, settled = dressed
    assert gap0 > 0.1
    assert report.seam_gap < 1e-3 and report.max_strain < 0.11
    assert settled.seam_gap < 1e-3 and settled.max_strain < 0.11
    x = b.particle_positions
    assert _penetration(body, x, body.rest_vertices).max() < 0.0
    assert not crossing_pairs(x, b.triangles, body.rest_vertices, body.triangles)
    model = b.finalize()
    (cloth,) = _cloth_meshes(model)
    assert not intersecting_pairs(x, cloth.triangles)
    assert cloth.weld is not None and len(np.unique(cloth.weld)) < len(cloth.weld)


def test_a_sewn_garment_is_one_vertex_per_seam_point(dressed):
    """Check the seams' particles share one root (the smallest of them), the cache's triangles use only roots, and the
    cache's strain rest lengths are the panels' own (the dressed skirt's strain within the limit, not the open gaps)."""
    _, b, skirt, _, _, _ = dressed
    model = b.finalize()
    roots = seam_roots(model)
    pairs = skirt.seams
    assert np.all(roots[pairs[:, 0]] == roots[pairs[:, 1]])
    assert np.all(roots <= np.arange(len(roots)))
    (cloth,) = _cloth_meshes(model)
    assert np.all(roots[cloth.triangles] == cloth.triangles)
    edges, rest = cloth.edges()
    x = b.particle_positions
    assert rest.max() < 2.0 * 0.04  # panel edges (the placed, open seams would give rests of 13-23 cm across them)
    strain = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1) / rest - 1.0
    assert strain.max() < 0.11 and strain.min() > -0.5


def test_sewn_panels_do_not_repel_across_their_seams(dressed):
    """Check the dressed, attached skirt hanging on the still body: self-collision finds no contact at its own seams (a
    seam's particles are one vertex), though dozens of particle-triangle pairs there lie within the thickness and
    share no particle index (seen as distinct, the proximity pass pushes them apart: measured, the step diverges)."""
    _, b, _, _, _, _ = dressed
    model = b.finalize()
    roots = seam_roots(model)
    x = b.particle_positions
    tris = b.triangles
    sewn = np.flatnonzero(roots != np.arange(len(roots)))  # the second particle of each seam point
    t_roots = roots[tris]
    near = 0
    for p in sewn:
        touching = (t_roots == roots[p]).any(1) & ~(tris == p).any(1)  # triangles at p's seam point, not at p itself
        near += int((np.linalg.norm(x[tris[touching]] - x[p], axis=2).min(1) < model.cloth_thickness).sum())
    assert near > 50
    sim = cw.Simulator(model, cw.SolverImplicitEuler(model, collider_contacts="solve"), fps=60, substeps=2)
    for _ in range(3):
        sim.step_frame()
        assert sim.frame_report.passes["self_collision"].self_proximity == 0


def test_scene_wraps_need_a_pattern_and_name_panels(tmp_path):
    base = '[cloth]\ngrid = { resolution = [4, 4] }\n[[cloth.wraps]]\npanels = ["front"]\n'
    with pytest.raises(SceneError, match=r"cloth.wraps\[0\]: wraps place a pattern's panels"):
        parse_scene(base)
    (tmp_path / "skirt.json").write_text(SKIRT.read_text())
    text = '[cloth]\npattern = "skirt.json"\nedge_length = 0.05\n[[cloth.wraps]]\npanels = ["front", "sleeve"]\n'
    (tmp_path / "s.toml").write_text(text)
    from cloth_warp.scene import load_scene

    with pytest.raises(SceneError, match=r"cloth.pattern: wraps\[0\].panels: 'sleeve' is not a panel"):
        build_model(load_scene(tmp_path / "s.toml"), "cpu")


def test_dressing_a_layer_holds_the_other_garments_still():
    """Check dress(garments=...) sews the named garment only: the other one's particles keep their places bit for bit
    (an obstacle for the one being dressed) and the report measures the dressed garment's seams, not the other's open
    ones; an unknown name is refused with the cloths' names."""
    b = cw.ModelBuilder()
    wrap = [Wrap(("front", "back"), (0.0, 0.0, 0.0))]
    b.add_cloth_pattern(SKIRT, edge_length=0.06, wraps=wrap, material="cotton", name="skirt")
    over = b.add_cloth_pattern(OVERSKIRT, edge_length=0.06, wraps=wrap, material="silk", name="overskirt")
    b.enable_self_collision(0.004, 0.3)
    before = b.particle_positions.copy()
    report = dress(b, 0.5, garments=["skirt"])
    held = over.indices()
    np.testing.assert_array_equal(b.particle_positions[held], before[held])
    assert report.seam_gap < 1e-3 < seam_gap(b)  # the overskirt's seams are still open
    moved = np.setdiff1d(np.arange(len(before)), held)
    assert np.abs(b.particle_positions[moved] - before[moved]).max() > 0.05
    with pytest.raises(cw.InvalidValue, match=r"no cloth named 'coat'; cloths: skirt, overskirt"):
        dress(b, 0.5, garments=["coat"])


def test_a_scene_with_everything_in_the_solve_dresses():
    """The dressing resolves collider contacts after each step: a scene whose contacts, self-contacts and their friction
    are in the solve still dresses (its contacts' friction in the solve without the contacts there was refused)."""
    b = cw.ModelBuilder()
    b.add_collider_mesh(Mannequin(1.75).rest_vertices, Mannequin(1.75).triangles, name="body", friction=0.5)
    b.add_cloth_pattern(SKIRT, edge_length=0.08, wraps=[Wrap(("front", "back"), (0.0, 0.0, 0.0))], material="cotton", name="skirt")
    b.enable_self_collision(0.004, 0.3)
    options = dict(collider_contacts="solve", self_contacts="solve", contact_friction="solve")
    gap0 = seam_gap(b)
    assert dress(b, 0.1, solver_options=options).seam_gap < gap0  # (closing: 0.1 s of the usual 1)
    settle(b, 0.05, solver_options=options)


def test_scene_garments_are_checked_at_the_gate(tmp_path):
    """Check [[garments]] entries need a unique name and an existing pattern, selections name a cloth of the scene,
    and the layers default to the list's order outside the [cloth]."""
    from cloth_warp.scene import layer_order, load_scene

    for name in ("skirt.json", "over.json"):
        (tmp_path / name).write_text(SKIRT.read_text())
    head = '[cloth]\npattern = "skirt.json"\nname = "skirt"\n'
    cases = [('[[garments]]\npattern = "over.json"\n', r"garments\[0\].name: required"),
             ('[[garments]]\nname = "skirt"\npattern = "over.json"\n', r"garments\[0\].name: 'skirt' is the name of another cloth"),
             ('[[garments]]\nname = "over"\npattern = "none.json"\n', r"garments\[0\].pattern: file not found"),
             ('[[garments]]\nname = "over"\npattern = "over.json"\nlayer = 100\n', r"garments\[0\].layer"),
             ('[[garments]]\nname = "over"\npattern = "over.json"\n[[pins]]\ncloth = "coat"\nindices = [0]\n',
              r"pins\[0\].cloth: 'coat' is not a cloth of the scene; those: over, skirt")]
    for i, (extra, message) in enumerate(cases):
        (tmp_path / f"s{i}.toml").write_text(head + extra)
        with pytest.raises(SceneError, match=message):
            load_scene(tmp_path / f"s{i}.toml")
    (tmp_path / "ok.toml").write_text(head + '[[garments]]\nname = "a"\npattern = "over.json"\n'
                                      '[[garments]]\nname = "b"\npattern = "over.json"\nlayer = 1\n')
    assert layer_order(load_scene(tmp_path / "ok.toml")) == [["skirt"], ["a", "b"]]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_finishing_joins_every_sewn_point_within_a_stitch_and_leaves_wider_ones(seed):
    """Check the dressing's finish on random sewn points: every group of particles joined by seam pairs closer than a
    stitch (SEAM_FINISH) ends at one point, the group's middle (a three-panel corner included), while a pair the
    dressing left wider keeps its particles where they were, also when another seam of the garment is finished (a
    T-shirt's one armpit seam left open must not keep its other seams from being welded); the largest gap finished
    is reported."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.5, 0.5, size=(40, 3))
    # narrow pairs (0.2-2.9 mm), a corner of three particles within a stitch, and two wide pairs (5 and 9 mm)
    narrow = [(0, 1), (2, 3), (4, 5)]
    corner = [(6, 7), (7, 8)]
    wide = [(10, 11), (12, 13)]
    for (a, b), gap in zip(narrow + corner, [0.2e-3, 1.5e-3, 2.9e-3, 1.0e-3, 1.2e-3]):
        d = rng.normal(size=3)
        x[b] = x[a] + gap * d / np.linalg.norm(d)
    for (a, b), gap in zip(wide, [5e-3, 9e-3]):
        d = rng.normal(size=3)
        x[b] = x[a] + gap * d / np.linalg.norm(d)
    pairs = np.array(narrow + corner + wide)
    y, finished = finish_seams(x, pairs[rng.permutation(len(pairs))])
    for a, b in narrow:
        np.testing.assert_array_equal(y[a], y[b])
        np.testing.assert_allclose(y[a], 0.5 * (x[a] + x[b]), atol=1e-15)
    np.testing.assert_allclose(y[[6, 7, 8]], np.repeat(x[[6, 7, 8]].mean(0, keepdims=True), 3, axis=0), atol=1e-15)
    for a, b in wide:
        np.testing.assert_array_equal(y[[a, b]], x[[a, b]])
    untouched = np.setdiff1d(np.arange(40), pairs)
    np.testing.assert_array_equal(y[untouched], x[untouched])
    assert finished == pytest.approx(2.9e-3, rel=1e-9) and finished < SEAM_FINISH
    assert finish_seams(x, np.array(wide))[1] == 0.0


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_finishing_leaves_a_point_whose_finish_would_turn_cloth_through_a_fold(seed):
    """Check the finish leaves a sewn point open where moving its particles to their middle would carry cloth through
    cloth, and finishes the others: a panel B sewn along a hinge to a panel A lies folded flat over it, a fraction of a
    millimetre above a particle p of A (a sleeve under an armpit, as the T-shirt at 2.6 and 3.0 cm edges had it); the
    hinge's two sewn points, 0.6-2.5 mm open, moved to their middles turn B about the hinge by more than that and
    through A's edge from p (plain finish_seams: found by the dressing's count and by the independent checker of
    tests/intersections.py), so finish_seams_clear leaves them, while a sewn pair elsewhere is finished. Random
    rotations, places, edge lengths, gaps and heights."""
    rng = np.random.default_rng(seed)
    L = rng.uniform(0.015, 0.035)  # [m] edge length
    h = rng.uniform(0.6e-3, 2.5e-3)  # [m] the hinge's gap (within a stitch)
    above = rng.uniform(0.05, 0.3) * h  # [m] B over p: turned about the finished hinge, B drops 3 h / 8 at p
    a0, a1, p, r, s_ = (0, 0, 0), (L, 0, 0), (L / 2, L, 0), (L / 2, 2 * L, -3e-3), (L, 2 * L, -3e-3)
    b0, b1, q = (0, 0, h), (L, 0, h), (L / 2, 4 * L, h + 4 * (above - h))
    u, w = (3 * L, 0, 0), (3 * L, 0, 0.5 * h)  # a sewn pair far from the fold
    local = np.array([a0, a1, p, r, s_, b0, b1, q, u, w], float)
    axis = rng.normal(size=3)
    rotation = quat_to_matrix(cw.quat_from_axis_angle(axis / np.linalg.norm(axis), rng.uniform(0.0, 360.0)))
    x = local @ np.asarray(rotation).T + rng.uniform(-1.0, 1.0, size=3)
    tris = np.array([[0, 1, 2], [2, 4, 3], [5, 6, 7]])
    pairs = np.array([[0, 5], [1, 6], [8, 9]])
    roots = np.array([0, 1, 2, 3, 4, 0, 1, 7, 8, 8])

    plain, _ = finish_seams(x, pairs)
    assert dressing_crossings(plain, tris, roots)  # the plain finish turns B through the edge from p
    joined = roots[tris]  # the garment as a cache draws it: each finished point one vertex
    assert len(intersecting_pairs(plain, joined)) > 0
    assert not dressing_crossings(x, tris, roots) and not len(intersecting_pairs(x, tris))

    y, finished, unfinished = finish_seams_clear(x, pairs, tris)
    assert unfinished == 2
    np.testing.assert_array_equal(y[:8], x[:8])  # the hinge left as it was
    np.testing.assert_array_equal(y[8], y[9])
    np.testing.assert_allclose(y[8], 0.5 * (x[8] + x[9]), atol=1e-15)
    assert finished == pytest.approx(0.5 * h, rel=1e-9)
    assert not dressing_crossings(y, tris, roots) and not len(intersecting_pairs(y, tris))


@pytest.mark.slow
def test_the_t_shirt_at_coarse_edges_is_handed_over_untangled_with_its_seams_welded():
    """Check the shipped T-shirt dressed and settled at 3.0 cm edges (1633 particles) is handed to the run with no edge
    through a triangle (the independent checker of tests/intersections.py, every sewn point one vertex as the cache
    draws it), no edge crossing the body, nothing inside it, and every seam within the weld distance. The dressing's
    finish had turned a sleeve through the body panel folded flat against it at an armpit (4 edges through triangles,
    which self-collision kept for the whole run)."""
    from cloth_warp.dressing import body_distance
    from cloth_warp.runner import find_scene
    from cloth_warp.scene import load_scene, scene_builder
    from cloth_warp.sewing import WELD_DISTANCE
    from cloth_warp.topology import SpringKind, joined_roots

    b = scene_builder(load_scene(find_scene("tshirt_walk"), {"cloth.edge_length": 0.03}))
    x = b.particle_positions
    tris = np.asarray(b.triangles, np.int64).reshape(-1, 3)
    seams = b.springs[b.spring_kind == int(SpringKind.SEAM)]
    assert seam_gap(b) < WELD_DISTANCE
    assert not intersecting_pairs(x, joined_roots(seams, len(x))[tris])
    (body,) = b.colliders
    assert not crossing_pairs(x, tris, body.vertices_at(0.0), body.triangles)
    assert body_distance(b.colliders, x).min() > 0.0


def sewn_row(gaps: list, stiffnesses: list):
    """A row of 0.1 m cotton squares (2^2, no gravity), each sewn to the next across gaps[k] [m] by seam springs of
    stiffnesses[k] [N/m] between their facing edges; returns the builder and, per gap, its sewn particle pairs."""
    from cloth_warp.topology import SpringKind

    b = cw.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    panels, left = [], 0.0
    for k in range(len(gaps) + 1):
        panels.append(b.add_cloth_grid(resolution=(2, 2), size=(0.1, 0.1), position=(left, 0.5, 0.0)))
        left += 0.1 + (gaps[k] if k < len(gaps) else 0.0)
    x = b.particle_positions

    def edge(ref, right: bool) -> list[int]:
        ids = ref.indices()
        side = x[ids, 0].max() if right else x[ids, 0].min()
        return [i for i in ids if abs(x[i, 0] - side) < 1e-9]

    seams = []
    for k, stiffness in enumerate(stiffnesses):
        pairs = list(zip(edge(panels[k], True), edge(panels[k + 1], False)))
        for i, j in pairs:
            b.add_spring(i, j, stiffness=stiffness, rest_length=1e-6, kind=SpringKind.SEAM)
        seams.append(pairs)
    return b, seams


def test_settling_ends_with_the_points_the_run_welds_joined():
    """Check a settling ends with every sewn point closed within the run's weld distance (WELD_DISTANCE) joined at its
    middle, so the run starts with it one point (its first frame's seam gap 0: a settling left the shipped T-shirt's
    0.34 mm open); one its springs leave open within ZIP_REACH zipped shut by hand and joined (a seam too weak to close
    5 mm), and a wider one left to its springs."""
    from cloth_warp.dressing import ZIP_REACH
    from cloth_warp.sewing import WELD_DISTANCE

    # the near seam open beyond the weld at the start (not welded while settling), pulled to within it
    b, (near_pairs, weak_pairs, wide_pairs) = sewn_row([1.5 * WELD_DISTANCE, 5.0 * WELD_DISTANCE, 1.5 * ZIP_REACH],
                                                       [0.05, 1e-4, 1e-4])
    report = settle(b, 0.1, solver_options={"strain_limit": None})
    y = b.particle_positions
    for i, j in near_pairs + weak_pairs:
        np.testing.assert_array_equal(y[i], y[j])
    assert report.zipped == len(weak_pairs)
    assert min(np.linalg.norm(y[i] - y[j]) for i, j in wide_pairs) > ZIP_REACH
    assert report.open_seams == len(wide_pairs)
    assert 0.0 < report.finished_from < WELD_DISTANCE


def test_a_settling_goes_on_until_a_seam_open_at_its_end_closes():
    """Check a settling whose seam is still open beyond the weld distance at its end (3 mm, a spring that closes it in
    about 8 frames) goes on, up to half as long again, until it is within it, then joins its points (the run welds
    them); one that stopped at its time left a 2.4 cm T-shirt's seam 2.7 mm open, a spring that opened to 3.3 mm as it
    walked)."""
    from cloth_warp.sewing import WELD_DISTANCE, Weld

    b, (pairs,) = sewn_row([3.0 * WELD_DISTANCE], [0.03])
    report = settle(b, 0.1, solver_options={"strain_limit": None})
    assert 0.1 < report.seconds < 0.15
    y = b.particle_positions
    for i, j in pairs:
        np.testing.assert_array_equal(y[i], y[j])
    assert 0.0 < report.finished_from < WELD_DISTANCE
    assert Weld(b.finalize("cpu")).points == len(pairs)


def test_self_crossings_counts_cloth_through_cloth_with_a_seam_one_vertex():
    """Check the dressing's intersection count (kernels/collide.py find_edge_crossings): a square through another
    crosses it (as the independent checker of tests/intersections.py finds: placed off the other's grid lines, as many
    edges through triangles within one, float32 against float64 near a triangle's edge), lifted clear of it does not,
    and a square sewn at right angles to another along a seam (the seam's particles coincide) is one surface, not a
    crossing."""
    from cloth_warp.topology import SpringKind

    def squares(lift: float, sewn: bool = False, shift=(0.0, 0.0)):
        b = cw.ModelBuilder()
        b.add_cloth_grid(resolution=(4, 4), size=(0.2, 0.2), position=(-0.1, 0.5, 0.1),
                         rotation=cw.quat_from_axis_angle((1, 0, 0), -90.0))  # flat, 0.2 m square centred on (0, 0.5, 0)
        upright = b.add_cloth_grid(resolution=(4, 4), size=(0.2, 0.2), position=(-0.1 + shift[0], 0.4 + lift, shift[1]))
        if sewn:  # its bottom edge on the flat square's middle row, sewn there
            x = b.particle_positions
            for i in upright.indices():
                if abs(x[i, 1] - 0.5) < 1e-6:
                    j = int(np.argmin(np.linalg.norm(x[:25] - x[i], axis=1)))
                    b.add_spring(j, int(i), stiffness=1.0, rest_length=1e-6, kind=SpringKind.SEAM)
        return b

    through = squares(0.0)
    assert self_crossings(through) > 0
    assert len(intersecting_pairs(through.particle_positions, through.triangles)) > 0
    for lift, shift in ((0.013, (0.013, 0.013)), (-0.03, (0.013, 0.031)), (0.04, (0.013, -0.022))):
        generic = squares(lift, shift=shift)
        found = self_crossings(generic)
        assert found >= 10
        assert abs(found - len(intersecting_pairs(generic.particle_positions, generic.triangles))) <= 1
    assert self_crossings(squares(0.15)) == 0
    sewn = squares(0.1, sewn=True)
    assert np.count_nonzero(sewn.spring_kind == int(SpringKind.SEAM)) == 5
    assert self_crossings(sewn) == 0


@pytest.mark.parametrize("turned", [False, True])
def test_body_crossings_counts_garment_edges_spanning_the_body(turned):
    """Check the dressing's count of garment/body crossings (kernels/collide.py find_edge_crossings, both ways):
    a coarse cloth whose particles all lie outside a thin upright body, its edges spanning the body as a 3.5 cm T-shirt's
    span an armpit, crosses it as often as the independent checker of tests/intersections.py finds (the body placed
    by its pose, or turned into it about its own vertical axis); the body moved clear of it does not."""
    import trimesh

    from cloth_warp.dressing import body_crossings

    def garment(centre, rotation=None):
        b = cw.ModelBuilder()
        grid = np.array([(x, 0.5, z) for z in (-0.2, 0.0, 0.2) for x in (-0.2, 0.0, 0.2)])
        tris = [[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [3, 4, 7], [3, 7, 6], [4, 5, 8], [4, 8, 7]]
        b.add_cloth_mesh(grid, tris, material="cotton")
        box = trimesh.creation.box(extents=(0.02, 0.3, 0.3))
        b.add_collider_mesh(box.vertices, box.faces, position=centre, rotation=rotation, name="body")
        return b

    quarter = cw.quat_from_axis_angle((0.0, 1.0, 0.0), 90.0)
    # thin along x between the particles at x = 0 and 0.2 (or, turned a quarter, thin along z between z = 0 and 0.2)
    centre, rotation = ((0.013, 0.51, 0.1), quarter) if turned else ((0.1, 0.51, 0.013), None)
    b = garment(centre, rotation)
    body = b.colliders[0]
    position, q = body.pose_at(0.0)
    world = np.asarray(body.vertices_at(0.0)) @ quat_to_matrix(q).T + np.asarray(position)
    x = b.particle_positions
    tris = np.asarray(b.triangles).reshape(-1, 3)
    assert _penetration_free(b)
    found = body_crossings(b)
    assert found >= 4
    assert found == len(crossing_pairs(x, tris, world, np.asarray(body.triangles)))
    assert body_crossings(garment((0.5, 0.51, 0.5), rotation)) == 0


def _penetration_free(b) -> bool:
    """Whether no particle of the builder lies inside its closed mesh colliders."""
    from cloth_warp.dressing import body_distance

    return bool(body_distance(b.colliders, b.particle_positions).min() > 0.0)


def test_a_garment_handed_to_the_run_tangled_or_open_is_warned_of(caplog):
    """Check what a dressing hands the run that the run cannot undo is warned of, naming the key: cloth crossing itself
    (a T-shirt at 2.6 cm edges had 3 edges through triangles after its settle, before the finish checked for crossings),
    seams left open (springs, not welded) and garment edges spanning the body through it."""
    from cloth_warp.scene import _warn_handed_over

    with caplog.at_level("WARNING", logger="cloth_warp"):
        _warn_handed_over(DressingReport(0.5, 60, 0.0, 0.0, 0.1), "dressing.settle")
        assert not caplog.records
        _warn_handed_over(DressingReport(0.5, 60, 0.0046, 0.0, 0.1, self_crossings=3, open_seams=1, body_crossings=6),
                          "dressing.settle")
    text = caplog.text
    assert "dressing.settle: the garments cross themselves (3 edges" in text
    assert "dressing.settle: 1 seam springs are still open (4.6 mm at most)" in text
    assert "dressing.settle: the garments and the body cross (6 edges through triangles)" in text


def test_a_dressing_that_diverges_stops_with_the_key_and_no_cache(tmp_path, monkeypatch, capsys):
    """A garment that diverges while it settles (the shipped T-shirt did, caught in an armpit crease) stops the command
    before the run with an error naming dressing.settle and the diagnosis (exit 2), not a traceback, and writes nothing."""
    from cloth_warp import dressing
    from cloth_warp.cli import main
    from cloth_warp.solvers import SimulationDiverged

    def diverging(*args, **kwargs):
        raise SimulationDiverged(time=0.6, dt=1.0 / 120.0, max_strain=1.15, reason="strain 1.15 above the bound 1.14",
                                 suggested_dt=1.0 / 240.0, frame=36)

    monkeypatch.setattr(dressing, "settle", diverging)
    out = tmp_path / "skirt.usdc"
    code = main(["run", str(ROOT / "scenes" / "skirt_walk.toml"), "--frames", "2", "--set", "dressing.seconds=0", "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "dressing.settle: the garment diverged while settling" in err and "strain 1.15" in err and "Traceback" not in err
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.parametrize("second_diverges", [False, True])
def test_a_dressing_that_diverges_with_element_samples_is_run_again_without_them(monkeypatch, second_diverges):
    """A dressing or settle that diverges with the colliders pass's element samples (the T-shirt at 2.6 cm edges tore
    at an armpit, strain 1.5) is run again with the particles' contacts alone, and says so in its report; where that
    diverges too, the first divergence is what the caller sees."""
    from cloth_warp import dressing
    from cloth_warp.solvers import SimulationDiverged

    calls = []

    def one_pass(*args, samples):
        calls.append(samples)
        if samples or second_diverges:
            raise SimulationDiverged(time=1.4, dt=1.0 / 120.0, max_strain=1.5, reason=f"strain 1.5 (samples {samples})",
                                     suggested_dt=1.0 / 240.0, frame=84)
        return dressing.DressingReport(1.0, 120, 0.0, 0.0, 0.1, element_samples=samples)

    monkeypatch.setattr(dressing, "_still_pass", one_pass)
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(2, 2), size=(0.1, 0.1))
    for run in (lambda: dressing.dress(b, 0.5), lambda: dressing.settle(b, 0.5)):
        calls.clear()
        if second_diverges:
            with pytest.raises(SimulationDiverged, match="samples True"):
                run()
        else:
            assert run().element_samples is False
        assert calls == [True, False]


def test_a_dressing_without_element_samples_turns_the_colliders_pass_samples_off():
    """The retry's simulator (`samples` False) keeps the particles alone out of the body: its colliders pass has its
    element samples off; the first try's has them on, as the run's."""
    from cloth_warp import dressing

    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(2, 2), size=(0.1, 0.1), position=(0.0, 0.5, 0.0))
    b.add_sphere((0.0, 0.3, 0.0), 0.1, name="ball")
    for samples in (True, False):
        _, sim = dressing._still_simulator(copy.deepcopy(b), 60.0, 2, "cpu", None, samples)
        assert sim.solver.pass_named("colliders").samples_on is samples


def _tube_into_the_hips(shift: float):
    """A 1.19 m round cotton tube (two panels, sides open 4-6 cm) round the hips, moved `shift` [m] along x: its side
    cuts into the pelvis."""
    from cloth_warp.patterns import pattern_from_tables

    half = math.pi * 0.19 / 2.0
    square = [[-half, 0.0], [half, 0.0], [half, 0.4], [-half, 0.4]]
    panels = [{"name": "front", "vertices": square, "translation": [0.0, 0.72, 0.19]},
              {"name": "back", "vertices": square, "translation": [0.0, 0.72, -0.19], "rotation": [0.0, 180.0, 0.0]}]
    stitches = [{"panels": ["front", "back"], "edges": [1, 3]}, {"panels": ["front", "back"], "edges": [3, 1]}]
    body = Mannequin(1.75)
    b = cw.ModelBuilder()
    b.add_collider_mesh(body.rest_vertices, body.triangles, name="body", friction=0.5)
    b.add_cloth_pattern(pattern_from_tables(panels, stitches), edge_length=0.04, wraps=[Wrap(("front", "back"), (0.0, 0.0, 0.0))],
                        material="cotton", name="tube", position=(shift, 0.0, 0.0))
    b.enable_self_collision(0.004, 0.3)
    return body, b


def test_a_garment_placed_into_the_body_is_dressed_out_of_it(monkeypatch):
    """Check panels placed 4.7 cm into the hips are dressed out: the body starts shrunk under them and grows back,
    pushing them out (the report says how deep they started); at the end nothing is inside the body or crossing it and
    the seams are closed. Pushed out in one step instead (no growth), the tube tore in its first frames."""
    from cloth_warp import dressing
    from cloth_warp.solvers import SimulationDiverged

    body, b = _tube_into_the_hips(0.08)
    assert dressing._closed(b.colliders[0])  # (the mannequin: a union of closed parts; an open sheet has no inside)
    sheet = cw.ModelBuilder().add_collider_mesh([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], [[0, 2, 1], [0, 3, 2]])
    assert not dressing._closed(sheet)
    depth = -dressing.mesh_depths(b.colliders[0], b.particle_positions).min()
    assert 0.04 < depth < 0.05
    report = dress(b, 1.0)
    assert report.grown_from == pytest.approx(depth) and report.inside == 0
    assert report.seam_gap < 1e-3 and report.max_strain < 0.11
    x = b.particle_positions
    assert _penetration(body, x, body.rest_vertices).max() < 0.0
    assert not crossing_pairs(x, b.triangles, body.rest_vertices, body.triangles)
    _, b = _tube_into_the_hips(0.08)
    monkeypatch.setattr(dressing, "growing_collider", lambda c, depth, seconds, device=None, start=0.0: c)
    with pytest.raises(SimulationDiverged):
        dress(b, 1.0)


def test_a_grown_body_waits_shrunk_until_its_start():
    """Check growing_collider: a closed ball shrunk 1 cm (plus twice its thickness) holds that shape until `start` and
    is back to its own at start + the growth's time (at GROWTH_SPEED, within `seconds`); a layered dressing starts the
    growth once the seams are closed."""
    import trimesh

    from cloth_warp import dressing

    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    c = cw.ModelBuilder().add_collider_mesh(ball.vertices, ball.faces, thickness=0.002)
    for start in (0.0, 0.6):
        grown = dressing.growing_collider(dressing.frozen_collider(c), 0.01, 0.3, start=start)
        grow = (0.01 + 2 * 0.002) / dressing.GROWTH_SPEED
        np.testing.assert_allclose(grown.point_cache_times, [start, start + grow])
        np.testing.assert_allclose(np.linalg.norm(grown.point_cache[0], axis=1), 0.2 - 0.014, rtol=1e-4)  # (vertex normals: radial to 1e-5)
        np.testing.assert_allclose(grown.point_cache[1], ball.vertices)


def test_a_garment_placed_too_deep_into_the_body_says_how_deep(tmp_path):
    """Check a tube placed 6.7 cm into the hips, deeper than the body can shrink under it, stops its dressing with a
    SceneError that says how deep the garment starts inside which body (nothing written)."""
    half = math.pi * 0.19 / 2.0
    square = f"[[{-half}, 0.0], [{half}, 0.0], [{half}, 0.4], [{-half}, 0.4]]"
    text = (f'[cloth]\nname = "tube"\nposition = [0.11, 0.0, 0.0]\nedge_length = 0.04\n'
            f'[[cloth.panels]]\nname = "front"\nvertices = {square}\ntranslation = [0.0, 0.72, 0.19]\n'
            f'[[cloth.panels]]\nname = "back"\nvertices = {square}\ntranslation = [0.0, 0.72, -0.19]\nrotation = [0.0, 180.0, 0.0]\n'
            '[[cloth.stitches]]\npanels = ["front", "back"]\nedges = [1, 3]\n'
            '[[cloth.stitches]]\npanels = ["front", "back"]\nedges = [3, 1]\n'
            '[[cloth.wraps]]\npanels = ["front", "back"]\n'
            '[dressing]\nseconds = 1.0\nsettle = 0.0\n'
            '[[colliders]]\ntype = "mannequin"\nname = "body"\nmotion = "still"\n'
            '[collision]\nself_collision = true\n[solver]\nintegrator = "implicit_euler"\nsubsteps = 2\n')
    with pytest.raises(SceneError, match=r"dressing\.seconds: the garment diverged .* starts 6\.\d cm inside the body 'body'"):
        build_model(parse_scene(text, tmp_path / "tube.toml"), "cpu")


def _overskirt_at(tmp_path, z: float) -> pathlib.Path:
    """The shipped overskirt pattern with its panels placed `z` [m x 100] from the body's axis (21.5 shipped; the
    skirt's are 19): nearer than the skirt's at the waist, it starts crossing the skirt."""
    spec = json.loads(OVERSKIRT.read_text())
    for name, sign in (("front", 1.0), ("back", -1.0)):
        spec["pattern"]["panels"][name]["translation"][2] = sign * z
    path = tmp_path / f"overskirt_{z:g}.json"
    path.write_text(json.dumps(spec))
    return path


def _crossed_layers(tmp_path, z: float):
    body = Mannequin(1.75)
    b = cw.ModelBuilder()
    b.add_collider_mesh(body.rest_vertices, body.triangles, name="body", friction=0.5)
    wrap = [Wrap(("front", "back"), (0.0, 0.0, 0.0))]
    skirt = b.add_cloth_pattern(SKIRT, edge_length=0.06, wraps=wrap, material="cotton", name="skirt")
    over = b.add_cloth_pattern(_overskirt_at(tmp_path, z), edge_length=0.06, wraps=wrap, material="silk", name="overskirt")
    b.enable_self_collision(0.004, 0.3)
    return body, b, skirt, over


def _layer_crossings(b, skirt, over) -> list:
    x = b.particle_positions
    return crossing_pairs(x, skirt.topology.triangles + skirt.particle_start, x, over.topology.triangles + over.particle_start)


@pytest.mark.parametrize("z", [17.0, 15.0])
def test_layers_placed_into_each_other_are_dressed_apart_in_their_order(tmp_path, monkeypatch, z):
    """Check an overskirt placed crossing the skirt under it (at the waist 2 or 4 cm nearer the body than the skirt, its
    flare outside it lower down) is dressed over it: while the skirt is sewn, the held overskirt is moved out of its
    way (and kept where it was placed); while the overskirt is sewn, the dressed skirt starts pulled in under it (the
    body shrunk too where the skirt lies on it) and grows back once the overskirt's seams are closed, pushing it out
    (growing back while they closed, at 15 cm the skirt's waist corner came out between the overskirt's open corners
    and held them 5.1 mm apart on an AMD EPYC, 6 edges through the overskirt; not on another machine). At the end the two cross nowhere,
    neither crosses the body, both seams are closed, the held garment of each stage keeps its place bit for bit, and
    every overskirt particle lies outside the skirt (on a horizontal ray from the body's axis). Without the layers moved aside the same
    dressing diverges or ends crossing."""
    from cloth_warp import dressing
    from cloth_warp.solvers import SimulationDiverged

    body, b, skirt, over = _crossed_layers(tmp_path, z)
    assert len(_layer_crossings(b, skirt, over)) > 50
    placed = b.particle_positions[over.indices()].copy()
    move_layers, starts = dressing._move_layers, []
    monkeypatch.setattr(dressing, "_move_layers", lambda *args: starts.append(args[-1]) or move_layers(*args))
    first = dress(b, 1.0, garments=["skirt"])
    assert first.layered_from > 0.01 and first.seam_gap < 1e-3 and first.max_strain < 0.11
    np.testing.assert_array_equal(b.particle_positions[over.indices()], placed)
    dressed = b.particle_positions[skirt.indices()].copy()
    second = dress(b, 1.0, garments=["overskirt"], under=["skirt"])
    assert second.layered_from > 0.005 and second.crossing == 0 and second.inside == 0
    assert second.seam_gap < 1e-3 and second.max_strain < 0.11
    np.testing.assert_array_equal(b.particle_positions[skirt.indices()], dressed)
    # the overskirt held over the skirt is pushed out and left; the skirt under the overskirt waits for its seams
    assert starts[0] == 0.0 and starts[-1] == pytest.approx(0.6)
    assert not _layer_crossings(b, skirt, over)
    x = b.particle_positions
    assert not crossing_pairs(x, b.triangles, body.rest_vertices, body.triangles)
    # the order, independently: on the horizontal ray from the body's axis through each overskirt particle, the skirt
    # is met before it, never after it
    p = x[over.indices()]
    axis = p * [0.0, 1.0, 0.0]
    out = p + 0.5 * (p - axis) / np.linalg.norm(p - axis, axis=1, keepdims=True)
    corners = x[skirt.topology.triangles + skirt.particle_start]
    r, t = np.repeat(np.arange(len(p)), len(corners)), np.tile(np.arange(len(corners)), len(p))
    before = segment_crosses_triangle(axis[r], p[r], *(corners[t, k] for k in range(3)))
    after = segment_crosses_triangle(p[r], out[r], *(corners[t, k] for k in range(3)))
    assert not after.any()
    assert len(np.unique(r[before])) > 0.5 * len(p)  # (all but the rows above the skirt's waistband)

    _, b, skirt, over = _crossed_layers(tmp_path, z)
    monkeypatch.setattr(dressing, "_misplaced_layers", lambda *args: [])
    try:
        dress(b, 1.0, garments=["skirt"])
        dress(b, 1.0, garments=["overskirt"], under=["skirt"])
    except SimulationDiverged:
        return
    assert _layer_crossings(b, skirt, over)


def test_a_layer_that_cannot_be_moved_aside_far_enough_is_named(tmp_path, monkeypatch):
    """Check a layer under the garment being dressed that has no room to be pulled in under it (here: none) stops the
    dressing with an InvalidValue naming both garments, how deep and which way to place the panels."""
    from cloth_warp import dressing

    _, b, _, _ = _crossed_layers(tmp_path, 17.0)
    dress(b, 1.0, garments=["skirt"])
    monkeypatch.setattr(dressing, "_layer_room", lambda trial, layer, device: np.zeros(len(layer.x)))
    monkeypatch.setattr(dressing, "growing_collider", lambda c, depth, seconds, device=None, start=0.0: c)
    with pytest.raises(cw.InvalidValue, match=r"'overskirt' starts 0\.\d cm on the wrong side of 'skirt', which goes under it, "
                                              r"and 'skirt' cannot be moved that far out of its way: place the panels further out"):
        dress(b, 1.0, garments=["overskirt"], under=["skirt"])


def test_a_layered_scene_placed_crossing_dresses_in_its_layer_order(tmp_path):
    """Check a scene whose outer garment (layer 1) is placed crossing the inner one builds (the dressing passes the
    layers under each garment) and ends with the two crossing nowhere."""
    text = (f'[cloth]\npattern = "{SKIRT.as_posix()}"\nedge_length = 0.06\nname = "skirt"\nlayer = 0\n'
            '[[cloth.wraps]]\npanels = ["front", "back"]\n'
            f'[[garments]]\nname = "overskirt"\npattern = "{_overskirt_at(tmp_path, 17.0).as_posix()}"\nedge_length = 0.06\n'
            'layer = 1\n[[garments.wraps]]\npanels = ["front", "back"]\n'
            '[dressing]\nseconds = 1.0\nsettle = 0.0\n'
            '[[colliders]]\ntype = "mannequin"\nname = "body"\nmotion = "still"\n'
            '[collision]\nself_collision = true\n[solver]\nintegrator = "implicit_euler"\nsubsteps = 2\n')
    from cloth_warp.scene import scene_builder

    b = scene_builder(parse_scene(text, tmp_path / "layers.toml"), "cpu")
    refs = {ref.name: ref for ref, _, _ in b.cloths}
    assert not _layer_crossings(b, refs["skirt"], refs["overskirt"])


def test_layer_offsets_are_signed_along_the_cloths_outward_normal_and_none_beside_it():
    """Check dressing.layer_offsets on a 1 m square sheet at z = 0 facing +z: a point over it is as far above as it is,
    one under it negative, one beside its border (mostly along the sheet) or beyond LAYER_REACH has none (NaN); and
    outward_normals turns a panel's normals away from a body (a ball under the sheet) whatever its winding."""
    from cloth_warp import dressing

    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    up = np.tile([0.0, 0.0, 1.0], (4, 1))
    points = [[0.5, 0.5, 0.1], [0.3, 0.6, -0.05], [1.2, 0.5, 0.01], [0.5, 0.5, dressing.LAYER_REACH + 0.01]]
    s = dressing.layer_offsets(points, x, tris, up)
    np.testing.assert_allclose(s[:2], [0.1, -0.05], atol=1e-6)
    assert np.isnan(s[2:]).all()
    np.testing.assert_allclose(dressing.layer_offsets(points[:2], x, tris, -up), [-0.1, 0.05], atol=1e-6)
    ball = cw.ModelBuilder()
    body = ball.add_collider_mesh(*_ball(0.3, (0.5, 0.5, -0.5)), name="ball")
    for winding in (tris, tris[:, ::-1]):
        np.testing.assert_allclose(dressing.outward_normals(x, winding, [body]), up, atol=1e-6)
        np.testing.assert_allclose(dressing.outward_normals(x - [0.0, 0.0, 1.0], winding, [body]), -up, atol=1e-6)


def _ball(radius: float, centre) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return np.asarray(sphere.vertices) + centre, np.asarray(sphere.faces)


def test_depths_in_a_body_of_overlapping_parts_are_signed_by_their_union():
    """Check `mesh_depths` (the dressing's inside test) signs points in the mannequin's box as the union of its
    overlapping closed parts does (numpy's generalised winding number, `cloth_warp.colliders.mesh_signed_distance`),
    the overlaps at the joints and the armpits included, with the distance to the nearest face. Built without Warp's
    winding-number support, the query signed 49 of these 2000 points wrongly (up to 2.8 cm deep)."""
    from cloth_warp import dressing
    from cloth_warp.colliders import mesh_signed_distance

    body = Mannequin(1.75)
    b = cw.ModelBuilder()
    b.add_collider_mesh(body.rest_vertices, body.triangles, name="body")
    v = np.asarray(body.rest_vertices, np.float64)
    points = np.random.default_rng(0).uniform(v.min(0), v.max(0), size=(2000, 3))
    reference = mesh_signed_distance(v, np.asarray(body.triangles), points)
    assert (reference < 0.0).sum() > 200
    depths = dressing.mesh_depths(b.colliders[0], points)
    np.testing.assert_array_equal(np.sign(depths), np.sign(reference))
    np.testing.assert_allclose(np.abs(depths), np.abs(reference), atol=1e-5)
