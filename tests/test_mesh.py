"""Meshes: trimesh formats, seam welding with UVs kept per corner, and clear errors for bad input."""

import warnings

import numpy as np
import pytest

import cloth_warp as cw
from cloth_warp import topology as topo

NU, NV = 32, 16  # sleeve: 32 around, 16 along


def write_sleeve_obj(path):
    """An open cylinder whose OBJ has a UV seam: u = 0 and u = 1 are separate vt at the same v."""
    lines = []
    for j in range(NV + 1):
        for i in range(NU):
            a = 2 * np.pi * i / NU
            lines.append(f"v {0.1 * np.cos(a):.6f} {0.02 * j:.6f} {0.1 * np.sin(a):.6f}")
    for j in range(NV + 1):
        for i in range(NU + 1):
            lines.append(f"vt {i / NU:.6f} {j / NV:.6f}")

    def v(i, j):
        return j * NU + (i % NU) + 1

    def t(i, j):
        return j * (NU + 1) + i + 1

    for j in range(NV):
        for i in range(NU):
            quad = [(i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)]
            for tri in ((0, 1, 2), (0, 2, 3)):
                lines.append("f " + " ".join(f"{v(*quad[k])}/{t(*quad[k])}" for k in tri))
    path.write_text("\n".join(lines) + "\n")
    return path


def boundary_edge_count(triangles):
    edges, tris = topo.edge_triangles(np.asarray(triangles))
    return sum(1 for t in tris if len(t) == 1)


def test_obj_seam_is_welded_and_uvs_survive(tmp_path):
    """Check an OBJ with a UV seam becomes one closed-around cloth with per-corner UVs that do not span the seam."""
    b = cw.ModelBuilder()
    cloth = b.add_cloth_mesh_file(write_sleeve_obj(tmp_path / "sleeve.obj"))
    t = cloth.topology
    assert t.particle_count == NU * (NV + 1)  # 544: the 17 seam duplicates are welded
    assert boundary_edge_count(t.triangles) == 2 * NU  # only the two rims: the seam is closed
    uv = t.corner_uv
    assert uv.shape == (len(t.triangles), 3, 2)
    assert np.ptp(uv[:, :, 0], axis=1).max() <= 1.0 / NU + 1e-6  # no triangle wraps u from 1 to 0
    # Every render vertex (trimesh splits the seam: 561) maps to the particle at the same position.
    verts, _, _ = cw.load_mesh_file(tmp_path / "sleeve.obj")
    assert len(verts) == NU * (NV + 1) + NV + 1
    np.testing.assert_allclose(t.positions[t.render_to_particle], verts, atol=1e-9)


@pytest.mark.parametrize("ext", ["ply", "stl", "off", "glb"])
def test_other_formats_load(tmp_path, ext):
    """Check PLY, STL, OFF and GLB (written by trimesh) load into the same welded cloth."""
    import trimesh

    t = topo.grid_topology((6, 4), (0.6, 0.4))
    path = tmp_path / f"patch.{ext}"
    trimesh.Trimesh(t.positions, t.triangles, process=False).export(path)
    b = cw.ModelBuilder()
    cloth = b.add_cloth_mesh_file(path)
    assert cloth.particle_count == t.particle_count
    assert len(cloth.topology.triangles) == len(t.triangles)


def test_mesh_cloth_stretches_like_a_membrane(device, tmp_path):
    """Check a sleeve hung by its rim stretches by rho g H^2 / (2 E) at the bottom (mesh stretch springs calibrated)."""
    b = cw.ModelBuilder(global_damping=20.0)
    mat = cw.materials.COTTON.replace(damping=0.0, drag_coefficient=0.0)
    cloth = b.add_cloth_mesh_file(write_sleeve_obj(tmp_path / "sleeve.obj"), material=mat)
    top = cloth.select_box((-1, 0.31, -1), (1, 1, 1))  # the upper rim (y = 0.32)
    assert len(top) == NU
    b.pin(top)
    model = b.finalize(device)
    sim = cw.Simulator(model, cw.SolverImplicitEuler(model, tolerance=1e-5), fps=60, substeps=1)
    for _ in range(30):
        stats = sim.step_frame()
    assert stats.finite
    x = sim.positions()
    height = 0.02 * NV
    # Tension per width at height y above the bottom is rho g y, so the bottom moves by rho g H^2 / (2 E).
    expected = mat.areal_density * 9.81 * height**2 / (2.0 * mat.stretch_stiffness)  # 5.0e-5 m
    assert -x[:, 1].min() == pytest.approx(expected, rel=0.05)
    np.testing.assert_allclose(x[top], model.particle_q.numpy()[top])


@pytest.mark.parametrize(
    "vertices, triangles, message",
    [
        (np.zeros((0, 3)), np.zeros((0, 3), int), "empty"),
        ([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], [[0, 1, 2]], "non-finite"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]], "out of range"),
        ([[0, 0, 0], [1, 0, 0]], [[0, 1]], "shape"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 1]], "no usable triangles"),
    ],
)
def test_bad_meshes_are_rejected(vertices, triangles, message):
    """Check empty, NaN, out-of-range, malformed and all-degenerate meshes raise a MeshError naming the problem."""
    with pytest.raises(cw.MeshError, match=message):
        cw.ModelBuilder().add_cloth_mesh(vertices, triangles)


def test_degenerate_and_nonmanifold_are_reported():
    """Check degenerate triangles are dropped and non-manifold edges kept, each with a warning."""
    v = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [2, 0, 0]]
    tris = [[0, 1, 2], [0, 3, 1], [0, 1, 4], [0, 1, 5]]  # edge 0-1 in three triangles; 0-1-5 is degenerate
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cloth = cw.ModelBuilder().add_cloth_mesh(v, tris)
    text = " ".join(str(w.message) for w in caught)
    assert "degenerate" in text and "non-manifold" in text
    assert len(cloth.topology.triangles) == 3


def test_missing_and_unreadable_files(tmp_path):
    """Check a missing file and a file that is not a mesh give clear errors."""
    with pytest.raises(FileNotFoundError, match="not found"):
        cw.ModelBuilder().add_cloth_mesh_file(tmp_path / "nope.obj")
    bad = tmp_path / "bad.ply"
    bad.write_text("this is not a ply file\n")
    with pytest.raises(cw.MeshError):
        cw.ModelBuilder().add_cloth_mesh_file(bad)


@pytest.mark.parametrize(
    "call, error, message",
    [
        (lambda: cw.FabricMaterial(areal_density=-1.0), ValueError, "areal_density"),
        (lambda: cw.FabricMaterial(bend_stiffness=float("nan")), ValueError, "bend_stiffness"),
        (lambda: cw.materials.preset("velvet"), KeyError, "known presets: cotton"),
        (lambda: cw.ModelBuilder().add_cloth_grid(resolution=(0, 4)), ValueError, "resolution"),
        (lambda: cw.ModelBuilder().add_cloth_grid(size=(1.0, -1.0)), ValueError, "size"),
        (lambda: cw.ModelBuilder(up_axis="X"), ValueError, "up_axis"),
        (lambda: cw.ModelBuilder().add_cloth_grid().select("edge:middle"), ValueError, "allowed: corners"),
        (lambda: cw.ModelBuilder().pin([0]), IndexError, "out of range"),
        (lambda: cw.ModelBuilder().add_cloth_grid(resolution=(2, 2)).builder.pin([100]), IndexError, "out of range"),
        (lambda: cw.make_solver("verlet", None), ValueError, "allowed: explicit_euler"),
    ],
)
def test_bad_parameters_raise_clear_errors(call, error, message):
    """Check bad materials, presets, grids, selections, pins and solver names raise errors naming the problem."""
    with pytest.raises(error, match=message):
        call()


def test_bad_step_arguments(device):
    """Check a non-positive dt and bad solver options are rejected."""
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(2, 2))
    model = b.finalize(device)
    with pytest.raises(ValueError, match="time step"):
        cw.SolverSymplecticEuler(model).step(model.state(), model.state(), model.control(), 0.0)
    with pytest.raises(ValueError, match="linear solver"):
        cw.SolverImplicitEuler(model, linear_solver="lu")
    with pytest.raises(ValueError, match="max_strain"):
        cw.SolverSymplecticEuler(model, strain_limit=-0.1)


def test_pins_from_a_mesh_vertex_attribute(tmp_path):
    """Check a per-vertex mask on the original (seam-split) mesh selects the welded particles it covers."""
    b = cw.ModelBuilder()
    cloth = b.add_cloth_mesh_file(write_sleeve_obj(tmp_path / "sleeve.obj"))
    verts, _, _ = cw.load_mesh_file(tmp_path / "sleeve.obj")
    mask = (verts[:, 1] > 0.31).astype(float)  # the upper rim, including its seam duplicate
    selected = cloth.select_mask(mask)
    assert len(selected) == NU  # 33 render vertices on the rim, 32 particles after welding
    np.testing.assert_allclose(cloth.topology.positions[selected - cloth.particle_start, 1], 0.02 * NV)
    with pytest.raises(ValueError, match="vertex mask has 3 entries"):
        cloth.select_mask([1.0, 0.0, 1.0])
