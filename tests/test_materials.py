"""Materials that mean the same on every mesh (docs/physics.md section M): spring constants fitted to the
continuum energy on grid cells of any aspect ratio and warp angle and on triangle meshes, warp/weft/bias."""

import math

import numpy as np
import pytest

import cloth_warp as cw
from analytic import elastic_catenary_sag, elastica_deflection
from cloth_warp import topology as topo
from cloth_warp.builder import spring_constants
from cloth_warp.elasticity import Orthotropic, membrane_tensor, nnls
from conftest import run_steps
from meshes import KINDS, strip_mesh

WOVEN = cw.FabricMaterial(areal_density=0.2, stretch_stiffness=1000.0, stretch_stiffness_weft=600.0, shear_stiffness=20.0,
                          bend_stiffness=2e-5, bend_stiffness_weft=1e-5)
ASPECTS = [(6, 18), (8, 16), (12, 12), (16, 8), (18, 6)]  # cells 1:3 to 3:1 on a unit square


def membrane_energy(t, k, strain):
    """Energy [J] of t's stretch/shear springs under the uniform small strain `strain` (2x2, local xy)."""
    x0 = t.positions[:, :2]
    x = x0 + x0 @ strain.T
    i, j = t.springs[t.spring_kind != topo.SpringKind.BEND].T
    kk = k[t.spring_kind != topo.SpringKind.BEND]
    rest = np.linalg.norm(x0[i] - x0[j], axis=1)
    return 0.5 * float(np.sum(kk * (np.linalg.norm(x[i] - x[j], axis=1) - rest) ** 2))


def continuum_energy(area, strain, tensor, warp_angle):
    """A (1/2) e : C : e with e the strain in the warp/weft frame."""
    c, s = math.cos(warp_angle), math.sin(warp_angle)
    r = np.array([[c, s], [-s, c]])
    e = r @ strain @ r.T
    v = np.array([e[0, 0], e[1, 1], 2.0 * e[0, 1]])
    return 0.5 * area * v @ tensor.voigt() @ v


def material_strains(warp_angle, eps=1e-6):
    """Warp stretch, weft stretch and shear in the material frame, as local strains."""
    c, s = math.cos(warp_angle), math.sin(warp_angle)
    w, f = np.array([c, s]), np.array([-s, c])
    return {"warp": eps * np.outer(w, w), "weft": eps * np.outer(f, f), "shear": eps * (np.outer(w, f) + np.outer(f, w))}


@pytest.mark.parametrize("resolution", ASPECTS)
@pytest.mark.parametrize("warp_deg", [0.0, 90.0])
def test_grid_membrane_is_exact_for_any_cell_shape(resolution, warp_deg):
    """Check warp, weft and shear energy of a uniformly strained grid equals the continuum's (1e-5) for cells 1:3-3:1."""
    t = topo.grid_topology(resolution, (1.0, 1.0), warp_angle=warp_deg)
    k, _ = spring_constants(t, WOVEN)
    angle = math.radians(warp_deg)
    for mode, strain in material_strains(angle).items():
        expected = continuum_energy(1.0, strain, membrane_tensor(WOVEN), angle)
        assert membrane_energy(t, k, strain) == pytest.approx(expected, rel=1e-5), mode


def test_bias_cut_grid_is_exact():
    """Check a square grid with the warp at 45 deg (a bias cut) stores the fabric's energy exactly (1e-5)."""
    t = topo.grid_topology((12, 12), (1.0, 1.0), warp_angle=45.0)
    k, _ = spring_constants(t, WOVEN)
    for mode, strain in material_strains(math.radians(45.0)).items():
        expected = continuum_energy(1.0, strain, membrane_tensor(WOVEN), math.radians(45.0))
        assert membrane_energy(t, k, strain) == pytest.approx(expected, rel=1e-5), mode


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("warp_deg", [0.0, 90.0])
def test_mesh_membrane_stretch_within_3_percent(kind, warp_deg):
    """Check warp and weft stretch energy of triangle meshes (warp along their rows or across) within 3 %."""
    v, tri = strip_mesh(kind, 1.0, 0.5, 0.05)
    angle = math.radians(warp_deg)
    t = topo.mesh_topology(v, tri, warp_direction=(math.cos(angle), math.sin(angle), 0.0))
    k, _ = spring_constants(t, WOVEN)
    area = t.particle_area.sum()
    for mode in ("warp", "weft"):
        strain = material_strains(angle)[mode]
        expected = continuum_energy(area, strain, membrane_tensor(WOVEN), angle)
        assert membrane_energy(t, k, strain) == pytest.approx(expected, rel=3e-2), mode


def test_bias_stiffness_follows_warp_weft_and_shear():
    """Check the strip stiffness at 0/90/45 deg: C_w - G^2/C_f, C_f - G^2/C_w and the compliance formula."""
    m = WOVEN
    cw_, cf, g = m.stretch_stiffness, m.stretch_weft, m.shear_stiffness
    assert m.stretch_stiffness_at(0.0) == pytest.approx(cw_ - g * g / cf)
    assert m.stretch_stiffness_at(90.0) == pytest.approx(cf - g * g / cw_)
    det = cw_ * cf - g * g
    bias = 4.0 / ((cf + cw_ - 2 * g) / det + 1.0 / g)
    assert m.stretch_stiffness_at(45.0) == pytest.approx(bias)
    # Plates: strips along the warp and the weft have the rigidity they are given (Huber, nu = 1/3).
    assert m.bend_stiffness_at(0.0) == pytest.approx(m.bend_stiffness)
    assert m.bend_stiffness_at(90.0) == pytest.approx(m.bend_weft)
    iso = cw.FabricMaterial(bend_stiffness=3e-5)
    assert iso.bend_stiffness_at(30.0) == pytest.approx(3e-5)  # Huber's plate of equal rigidities is isotropic


def test_nnls_matches_the_kkt_conditions():
    """Check the small non-negative least-squares solver: x >= 0, gradient zero on the support, >= 0 off it."""
    rng = np.random.default_rng(3)
    for _ in range(50):
        a, b = rng.normal(size=(6, 5)), rng.normal(size=6)
        x = nnls(a, b)
        grad = a.T @ (a @ x - b)
        assert (x >= 0).all()
        np.testing.assert_allclose(grad[x > 0], 0.0, atol=1e-9)
        assert (grad[x == 0] >= -1e-9).all()


def test_orthotropic_strip_of_a_shear_free_lattice():
    """Check a lattice without shear resists only along warp and weft."""
    t = Orthotropic(2.0, 3.0, 0.0)
    assert t.strip(0.0) == pytest.approx(2.0) and t.strip(math.pi / 2) == pytest.approx(3.0) and t.strip(0.3) == 0.0


# -- simulated: cantilever tip against the heavy elastica (physics.md 1(a)) ------------------------------

RHO, G_ACC, LENGTH = 0.15, 9.81, 1.0


def cantilever_deflection(mesh, material, h=0.025, width=0.05, aspect=1.0, warp_angle=0.0):
    """Tip deflection / length of a strip clamped at x <= 0 (two cells), overhang LENGTH along +x, settled."""
    b = cw.ModelBuilder(global_damping=2.0)
    rot = cw.quat_from_axis_angle((1, 0, 0), 90.0)
    if mesh == "grid":
        ax, ay = h, h / aspect
        seg, rows = int(round(LENGTH / ax)), max(2, int(round(width / ay)))
        c = b.add_cloth_grid(resolution=(seg + 2, rows), size=(LENGTH + 2 * ax, rows * ay), position=(-2 * ax, 0.0, 0.0),
                             material=material, rotation=rot, warp_angle=warp_angle)
        x0 = c.topology.positions - np.array([2 * ax, 0.0, 0.0])
    else:
        v, tri = strip_mesh(mesh, LENGTH, width, h, root=2 * h)
        c = b.add_cloth_mesh(v, tri, material=material, rotation=rot,
                             warp_direction=(math.cos(math.radians(warp_angle)), math.sin(math.radians(warp_angle)), 0.0))
        x0 = c.topology.positions
    b.pin(c.particle_start + np.flatnonzero(x0[:, 0] <= 1e-9))
    tip = c.particle_start + np.flatnonzero(x0[:, 0] >= LENGTH - 1e-9)
    model = b.finalize("cpu")
    solver = cw.SolverImplicitEuler(model, strain_limit=None, tolerance=1e-5, max_iterations=3000)
    s = run_steps(solver, model, 150, 0.05)
    return -float(s.particle_q.numpy()[tip, 1].mean()) / LENGTH


def strip_material(alpha, **kw):
    """Inextensible-enough strip material with q L^3 / B = alpha along the warp."""
    return cw.FabricMaterial(areal_density=RHO, stretch_stiffness=3e3, shear_stiffness=3e2,
                             bend_stiffness=RHO * G_ACC * LENGTH**3 / alpha, **kw)


@pytest.mark.slow
def test_cantilever_on_every_cell_shape_and_mesh():
    """Check the tip of a clamped strip (alpha = 2) on cells 1:3-3:1 (bend springs) and right, equilateral and
    irregular triangles (plate stencils, strips 4 cells wide: two-cell strips bend 4-17 % softly, docs/physics.md
    section P): within 3 % of the heavy elastica and within 2 % of one another (measured: grids within 0.2 %, right
    +0.5 %, equilateral +0.15 %, irregular +1.85 %; more irregular seeds in test_mesh_bending)."""
    mat = strip_material(2.0)
    expected = elastica_deflection(2.0)
    cases = {f"grid {a}": ("grid", a) for a in (1 / 3, 1 / 2, 2.0, 3.0)} | {k: (k, 1.0) for k in KINDS}
    got = {name: cantilever_deflection(mesh, mat, aspect=aspect, width=0.05 if mesh == "grid" else 0.1)
           for name, (mesh, aspect) in cases.items()}
    errors = {name: round(d / expected - 1.0, 4) for name, d in got.items()}
    assert max(abs(e) for e in errors.values()) < 0.03, errors
    assert max(got.values()) / min(got.values()) - 1.0 < 0.02, errors


@pytest.mark.slow
def test_warp_weft_and_bias_strips_droop_as_predicted():
    """Check strips cut along the warp, the weft and the bias (45 deg) droop like the elastica of B(angle)."""
    mat = strip_material(2.0, bend_stiffness_weft=RHO * G_ACC * LENGTH**3 / 4.0)
    for angle in (0.0, 90.0, 45.0):
        alpha = RHO * G_ACC * LENGTH**3 / mat.bend_stiffness_at(angle)
        got = cantilever_deflection("grid", mat, warp_angle=angle)
        assert got == pytest.approx(elastica_deflection(alpha), rel=3e-2), angle


# -- simulated: membrane stretch and catenary sag on every cell shape, mesh, warp angle and orientation ------

SOFT = cw.FabricMaterial(areal_density=RHO, stretch_stiffness=400.0, stretch_stiffness_weft=240.0, shear_stiffness=80.0,
                         bend_stiffness=1e-7)
"""A woven with a knit-like shear (G/C = 0.2-0.33; strains of 0.2-0.7 % under its own weight, where StVK and linear
springs agree within 1 %) whose bending is negligible at these lengths."""
STRIP_CASES = {f"grid {a:.2g}": ("grid", a) for a in (1 / 3, 1 / 2, 1.0, 2.0, 3.0)} | {k: (k, 1.0) for k in KINDS}


def add_strip(b, mesh, material, length, width, h, aspect, warp_deg, rotation, membrane="element"):
    """A strip [0, length] x [0, width] (local xy) of `mesh` kind; returns (cloth, local rest positions)."""
    if mesh == "grid":
        ax, ay = h, h / aspect
        cols, rows = int(round(length / ax)), max(2, int(round(width / ay)))
        c = b.add_cloth_grid(resolution=(cols, rows), size=(length, rows * ay), material=material, rotation=rotation,
                             warp_angle=warp_deg, membrane=membrane)
    else:
        v, tri = strip_mesh(mesh, length, width, h)
        a = math.radians(warp_deg)
        c = b.add_cloth_mesh(v, tri, material=material, rotation=rotation, warp_direction=(math.cos(a), math.sin(a), 0.0),
                             membrane=membrane)
    return c, c.topology.positions


def settle(model, frames, fps=20.0):
    solver = cw.SolverImplicitEuler(model, strain_limit=None, tolerance=1e-6, max_iterations=3000)
    sim = cw.Simulator(model, solver, fps=fps)
    for _ in range(frames):
        sim.step_frame()
    return sim.state.particle_q.numpy()


def hanging_elongation(mesh, material, aspect=1.0, warp_deg=0.0, spin_deg=0.0, length=1.0, width=0.05, h=0.025,
                       membrane="element"):
    """How far [m] the free end of a strip hung by its top edge drops below its rest position."""
    b = cw.ModelBuilder(global_damping=2.0)
    # local x points down (-y); spun about the vertical by spin_deg (orientation must not matter)
    rot = quat_mul(cw.quat_from_axis_angle((0, 1, 0), spin_deg), cw.quat_from_axis_angle((0, 0, 1), -90.0))
    c, x0 = add_strip(b, mesh, material, length, width, h, aspect, warp_deg, rot, membrane)
    b.pin(c.particle_start + np.flatnonzero(x0[:, 0] <= 1e-9))
    tip = c.particle_start + np.flatnonzero(x0[:, 0] >= length - 1e-9)
    q0 = np.array(b.particle_positions)[tip]
    q = settle(b.finalize("cpu"), 60)[tip]
    return float((q0[:, 1] - q[:, 1]).mean())


def quat_mul(a, b):
    (x1, y1, z1, w1), (x2, y2, z2, w2) = a, b
    return (w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2)


@pytest.mark.slow
@pytest.mark.parametrize("warp_deg", [0.0, 90.0, 45.0])
def test_hanging_strip_stretches_as_its_strip_stiffness_predicts(warp_deg):
    """Check a strip hung by its top edge stretches by rho g L^2 / (2 E) (exact for lumped masses too), E the
    uniaxial stiffness of the material cut at the warp angle (warp, weft, bias), on cells 1:3-3:1 and right,
    equilateral and irregular triangles, one case also turned about the vertical: within 3 % of it and 2 % of
    one another, with the membrane element (measured: -0.6 to -1.8 %, spread 0.8 %). Springs alone miss this
    at G/C = 0.2-0.33 on cells 2:1 and 3:1 (a spring lattice obeys Cauchy's relation: 10-30x too soft there)."""
    expected = RHO * G_ACC / (2.0 * float(membrane_tensor(SOFT).strip(math.radians(warp_deg))))
    cases = dict(STRIP_CASES, **{"grid spun 30 deg": ("grid", 1.0)})
    got = {name: hanging_elongation(mesh, SOFT, aspect, warp_deg, 30.0 if "spun" in name else 0.0)
           for name, (mesh, aspect) in cases.items()}
    errors = {name: round(d / expected - 1.0, 4) for name, d in got.items()}
    assert max(abs(e) for e in errors.values()) < 0.03, errors
    assert max(got.values()) / min(got.values()) - 1.0 < 0.02, errors


def catenary_sag(mesh, material, aspect=1.0, warp_deg=0.0, length=2.0, span=1.4, width=0.05, h=0.05, membrane="element"):
    """Mid-span sag [m] of a strip whose end edges are carried from `length` apart to `span` apart, settled."""
    b = cw.ModelBuilder(global_damping=2.0)
    c, x0 = add_strip(b, mesh, material, length, width, h, aspect, warp_deg, cw.quat_from_axis_angle((1, 0, 0), 90.0), membrane)
    shift = 0.5 * (length - span)
    b.add_handle(c.particle_start + np.flatnonzero(x0[:, 0] <= 1e-9), [(0.0, (0, 0, 0)), (0.5, (shift, 0, 0))])
    b.add_handle(c.particle_start + np.flatnonzero(x0[:, 0] >= length - 1e-9), [(0.0, (0, 0, 0)), (0.5, (-shift, 0, 0))])
    mid = c.particle_start + np.argsort(np.abs(x0[:, 0] - 0.5 * length))[:4]
    q = settle(b.finalize("cpu"), 100)
    return -float(q[mid, 1].mean())


@pytest.mark.slow
@pytest.mark.parametrize("warp_deg", [0.0, 90.0])
def test_catenary_sag_on_every_cell_shape_and_mesh(warp_deg):
    """Check a 2 m strip hung between edges 1.4 m apart sags as the elastic catenary (Irvine) of its weight and
    strip stiffness along the warp or the weft, on cells 1:3-3:1 and every triangle mesh kind: within 3 % of it
    and 2 % of one another, with the membrane element (measured: within 0.1 %)."""
    strip = float(membrane_tensor(SOFT).strip(math.radians(warp_deg)))
    expected = elastic_catenary_sag(1.4, 2.0, RHO * G_ACC, strip)  # per unit width: q = rho g, EA = E
    got = {name: catenary_sag(mesh, SOFT, aspect, warp_deg) for name, (mesh, aspect) in STRIP_CASES.items()}
    errors = {name: round(d / expected - 1.0, 4) for name, d in got.items()}
    assert max(abs(e) for e in errors.values()) < 0.03, errors
    assert max(got.values()) / min(got.values()) - 1.0 < 0.02, errors
