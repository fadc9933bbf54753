"""The parametric mannequin (cloth_warp/mannequin.py): proportions, closed segments, rigid ball-jointed posing, the
walk cycle and the arm raise, and its USD point cache read back as a deforming collider."""

import numpy as np
import pytest
import trimesh

import cloth_warp as cw
from cloth_warp.mannequin import MOTIONS, Mannequin


@pytest.fixture(scope="module")
def body():
    return Mannequin(height=1.75, resolution=12)


def test_body_proportions_and_closed_segments(body):
    """Check the body stands on y = 0 at its height (within 2 %), facing +z with its feet forward, and that every
    segment is a closed, outward-facing surface (a collider's inside is well defined)."""
    v = body.rest_vertices
    assert v[:, 1].min() == pytest.approx(0.0, abs=0.01)
    assert v[:, 1].max() == pytest.approx(1.75, rel=0.02)
    assert 0.5 < (v[:, 0].max() - v[:, 0].min()) / 1.75 < 0.7  # arms in an A-pose (hands ~0.6 of the height apart)
    for k, s in enumerate(body.segments):
        sel = np.flatnonzero(body.segment_of_vertex == k)
        tris = body.triangles[np.isin(body.triangles[:, 0], sel)]
        m = trimesh.Trimesh(v, tris, process=False)
        m.remove_unreferenced_vertices()
        assert m.is_watertight and m.volume > 0.0, s.name


@pytest.mark.parametrize("motion", MOTIONS)
def test_segments_move_rigidly_and_stay_jointed(body, motion):
    """Check in every pose each segment is a rigid motion of its rest shape and each joint stays where its parent
    carries it (the child's joint point and the parent's copy of it coincide): the figure never comes apart."""
    rest = body.rest_vertices
    for t in (0.0, 0.37, 0.8, 1.3, 2.0):
        x = body.vertices_at(motion, t)
        transforms = body.segment_transforms(motion, t)
        for k, s in enumerate(body.segments):
            sel = body.segment_of_vertex == k
            a, b = rest[sel][:40], x[sel][:40]
            np.testing.assert_allclose(np.linalg.norm(b[1:] - b[:-1], axis=1), np.linalg.norm(a[1:] - a[:-1], axis=1), atol=1e-12)
            if s.parent is not None:
                joint = np.asarray(s.joint) * body.height
                r, tr = transforms[k]
                pr, pt = transforms[body.index[s.parent]]
                np.testing.assert_allclose(r @ joint + tr, pr @ joint + pt, atol=1e-12)


def test_walk_swings_legs_and_arm_raise_lifts_hands(body):
    """Check the walk cycle swings the feet forward and back (> 10 cm, alternately) and the arms against the legs, and
    the arm raise lifts both hands by more than 40 cm within 2 s; standing still does not move."""
    feet = [body.segment_of_vertex == body.index[f"{side}_foot"] for side in ("left", "right")]
    z = np.array([[body.vertices_at("walk", t)[f][:, 2].mean() for f in feet] for t in np.linspace(0.4, 1.5, 23)])
    assert np.ptp(z[:, 0]) > 0.1 and np.ptp(z[:, 1]) > 0.1
    assert np.corrcoef(z[:, 0], z[:, 1])[0, 1] < -0.85  # alternately
    hands = [body.segment_of_vertex == body.index[f"{side}_hand"] for side in ("left", "right")]
    lift = [body.vertices_at("arm_raise", 2.0)[h][:, 1].mean() - body.rest_vertices[h][:, 1].mean() for h in hands]
    assert min(lift) > 0.4
    np.testing.assert_array_equal(body.vertices_at("still", 1.0), body.rest_vertices)


def test_point_cache_reads_back_as_a_deforming_collider(body, tmp_path):
    """Check the written USD point cache reads back as a deforming mesh collider whose vertices at a frame are the
    mannequin's (float32), at the cache's frame rate."""
    path = tmp_path / "walk.usdc"
    body.write_usd(path, "walk", seconds=0.5, fps=30)
    b = cw.ModelBuilder()
    col = b.add_collider_mesh_file(path, deforming=True)
    assert col.deforming and len(col.point_cache_times) == 16
    np.testing.assert_allclose(col.point_cache_times, np.arange(16) / 30.0)
    got = np.sort(col.vertices_at(10 / 30.0).round(5), axis=0)
    want = np.sort(body.vertices_at("walk", 10 / 30.0).astype(np.float32).round(5), axis=0)
    np.testing.assert_allclose(got, want, atol=2e-5)


def test_bad_arguments():
    with pytest.raises(ValueError, match="height"):
        Mannequin(height=4.0)
    with pytest.raises(ValueError, match="motion"):
        Mannequin(resolution=8).vertices_at("dance", 0.0)
