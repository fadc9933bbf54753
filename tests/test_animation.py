"""ControlAnimator: the device-side control update equals the host's (Model.update_control, GustyWind.at),
and a frame of advance_clock + apply recorded into a graph replays the eager sequence.

Tolerance. The kernels repeat the host's float64 arithmetic operation for operation without FMA contraction
and round once to float32, so on the CPU the results are bitwise equal in practice. Two things the kernels
cannot reproduce exactly: numpy's dot / matmul go through BLAS (summation order, FMA) and the transcendental
functions (acos, sin, cos) are the platform's (glibc here, CUDA's libdevice on a GPU, within 1-2 float64 ulp).
Both change the float64 result by a few float64 ulp, which moves the float32 result by at most one float32
ulp. Keyframed values are therefore checked to one float32 ulp of their row's largest magnitude (positions
and quaternions separately). Point caches involve only + - * / and are checked bitwise when the cache is
float32-representable (a USD point cache is float32); a float64 cache is stored as float32 on the device,
which bounds the difference by its rounding (see test_float64_point_cache_is_within_its_float32_rounding).
"""

import pathlib

import numpy as np
import pytest
import trimesh
import warp as wp

import cloth_warp as cw
from cloth_warp.animation import ControlAnimator
from cloth_warp.collision import collider_distance
from cloth_warp.graphs import record
from cloth_warp.kernels import animation as ka
from cloth_warp.scene import build_model, build_wind, load_scene
from cloth_warp.wind import GustyWind

ROOT = pathlib.Path(__file__).resolve().parents[1]
DT = 1.0 / 120.0


def within_float32_ulp(device_rows, host_rows, what: str):
    """Assert |device - host| <= one float32 ulp of the row's largest |host| entry."""
    d = np.asarray(device_rows, np.float64)
    h = np.asarray(host_rows, np.float64)
    if h.size == 0:
        return
    d, h = d.reshape(len(d), -1), h.reshape(len(h), -1)
    assert np.all(np.isfinite(d)), f"{what}: a row was not written"
    tol = np.spacing(np.abs(h).max(axis=1, keepdims=True).astype(np.float32)).astype(np.float64)
    err = np.abs(d - h)
    assert np.all(err <= tol), f"{what}: max |device - host| = {err.max():.3g}, rows {np.unique(np.nonzero(err > tol)[0])[:8]}"


def controls_within_float32_ulp(device_control, host_control, model, what: str):
    """within_float32_ulp for the pin targets and the colliders' start and end poses (positions and quaternions
    apart)."""
    within_float32_ulp(device_control.pin_target.numpy(), host_control.pin_target.numpy(), f"{what}: pin targets")
    for name in ("collider_transform_start", "collider_transform_end"):
        h = getattr(host_control, name).numpy()[: model.collider_count]
        d = getattr(device_control, name).numpy()[: model.collider_count]
        within_float32_ulp(d[:, :3], h[:, :3], f"{what}: {name} positions")
        within_float32_ulp(d[:, 3:], h[:, 3:], f"{what}: {name} rotations")


def keyframe_times(model) -> np.ndarray:
    """Times [s] that probe every branch: before the first keyframe, on each one, just off each one, between,
    after the last, and where time - DT lands on a keyframe."""
    kfs = [kf.time for h in model.handles for kf in h.keyframes] + [kf.time for c in model.colliders for kf in c.keyframes]
    kfs = np.unique(kfs)
    return np.unique(np.concatenate([kfs, kfs + DT, kfs - 1e-9, kfs + 1e-9, np.linspace(kfs[0] - 0.5, kfs[-1] + 0.5, 97)]))


def nan_fill(array):
    """Overwrite a device array with NaN (what the animator does not write stays NaN)."""
    array.assign(np.full(array.numpy().shape, np.nan, np.float32))


@pytest.mark.parametrize("scene", ["twist", "curtain", "sphere_shot"])
def test_handles_and_collider_poses_match_host(scene, device):
    """Check the device's handle pin targets (rotation and translation, slerp) and collider poses at the step's
    start and end equal Model.update_control's to float32 rounding, before, on, between and after keyframes."""
    model = build_model(load_scene(ROOT / "scenes" / f"{scene}.toml"), device)
    animator = ControlAnimator(model)
    assert animator.active and animator.capturable
    host, dev = model.control(), model.control()
    handle_rows = np.unique(np.concatenate([h.particles for h in model.handles])) if model.handles else np.zeros(0, int)
    at_rest = host.pin_target.numpy()[handle_rows].copy()
    moved = False
    for t in keyframe_times(model):
        model.update_control(host, float(t), DT)
        nan_fill(dev.pin_target)
        if animator.colliders_animated:
            nan_fill(dev.collider_transform_start)
            nan_fill(dev.collider_transform_end)
        animator.set_clock(float(t), DT)
        animator.apply(dev)
        h_pin, d_pin = host.pin_target.numpy()[handle_rows], dev.pin_target.numpy()[handle_rows]
        within_float32_ulp(d_pin, h_pin, f"{scene} pin targets at t={t}")
        moved |= bool(np.abs(h_pin - at_rest).max() > 1e-3) if len(handle_rows) else False
        for name in ("collider_transform_start", "collider_transform_end"):
            h, d = getattr(host, name).numpy()[: model.collider_count], getattr(dev, name).numpy()[: model.collider_count]
            within_float32_ulp(d[:, :3], h[:, :3], f"{scene} {name} position at t={t}")
            within_float32_ulp(d[:, 3:], h[:, 3:], f"{scene} {name} rotation at t={t}")
    assert moved or not len(handle_rows)  # the handles did move: the comparison is not of rest poses


@pytest.mark.parametrize("offset", [0.0, 0.5 / 60.0])
def test_gusty_wind_matches_host(offset, device):
    """Check apply_wind writes GustyWind.at(clock time + offset) to float32 rounding for the flag scene's gusts,
    a turning wind about a tilted up axis and a steady wind, at 600 times from -5 s to 500 s."""
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(2, 2), size=(0.1, 0.1))
    model = b.finalize(device)
    control = model.control()
    winds = [build_wind(load_scene(ROOT / "scenes" / "flag.toml")),
             GustyWind((0.0, -1.0, 2.5), strength=0.9, period=2.0, turn=120.0, up=(0.3, 1.0, 0.1), seed=11),
             GustyWind((1.0, 2.0, 3.0))]
    times = np.concatenate([np.linspace(0.0, 20.0, 400), np.random.default_rng(0).uniform(-5.0, 500.0, 200)])
    for wind in winds:
        animator = ControlAnimator(model, wind=wind)
        assert animator.gusty == (not wind.steady)
        got, want = [], []
        for t in times:
            animator.set_clock(float(t), DT)
            animator.apply_wind(control, offset)
            got.append(control.wind.numpy()[0].copy())
            want.append(wind.at(float(t) + offset).astype(np.float32))
        within_float32_ulp(np.array(got), np.array(want), f"wind {wind.mean}")


def write_point_cache(path, mesh, points_at, fps=24.0, seconds=1.0):
    """A USD point cache of trimesh `mesh` whose vertices at time t [s] are points_at(t), one sample per frame
    from time code 1 (as tests/test_colliders.py writes them)."""
    from pxr import Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(fps)
    frames = int(round(seconds * fps))
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(1 + frames)
    prim = UsdGeom.Mesh.Define(stage, "/body")
    prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(mesh.faces), 3, np.int32)))
    prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.faces.reshape(-1).astype(np.int32))))
    for k in range(frames + 1):
        prim.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points_at(k / fps), np.float32)), 1 + k)
    stage.GetRootLayer().Save()


BALL = trimesh.creation.icosphere(subdivisions=2, radius=1.0)


def ball_path(t: float) -> np.ndarray:
    """An icosphere growing from 15 to 30 cm radius while its centre moves 1 m along x, over 1 s."""
    return BALL.vertices * (0.15 + 0.15 * t) + np.array([1.0 * t, 0.0, 0.0])


def deforming_model(device, tmp_path, cache_scale=None, deforming=True):
    """A small cloth with a rotating + translating handle (one corner taken over by a later handle), a keyframed
    sphere and a keyframed deforming ball read from a USD point cache (or, with `cache_scale`, given as a float64
    array scaled by it; without `deforming`, the ball keeps its first shape)."""
    b = cw.ModelBuilder()
    cloth = b.add_cloth_grid(resolution=(6, 6), size=(0.4, 0.4), position=(-0.2, 1.0, 0.0))
    b.add_handle(cloth.select("edge:top"), keyframes=[(0.1, (0, 0, 0)), (0.6, (0.1, 0.2, 0.0), (0.0, 0.3826834, 0.0, 0.9238795)),
                                                      (0.9, (0.2, 0.2, 0.1), (0.0, 0.0, 0.7071068, 0.7071068))])
    b.add_handle(cloth.select("corner:top_left"), keyframes=[(0.3, (0, 0, 0)), (0.7, (0.0, 0.0, 0.2))])  # overrides the first
    b.add_sphere((0.0, 0.3, 0.0), 0.1, keyframes=[(0.0, (0, 0, 0)), (0.5, (0.5, 0.0, 0.0), (0.0, 0.0, 0.3826834, 0.9238795))])
    keys = [(0.2, (0, 0, 0)), (0.8, (0.0, 0.1, 0.0), (0.0, 0.0, 0.3826834, 0.9238795))]
    if not deforming:
        b.add_collider_mesh(ball_path(0.0), BALL.faces, position=(0.0, -0.5, 0.0), keyframes=keys)
    elif cache_scale is None:
        path = tmp_path / "ball.usda"
        write_point_cache(path, BALL, ball_path)
        b.add_collider_mesh_file(path, deforming=True, position=(0.0, -0.5, 0.0), keyframes=keys)
    else:
        times = np.arange(25) / 24.0
        cache = np.stack([ball_path(t) for t in times])
        b.add_collider_mesh(cache[0], BALL.faces, scale=cache_scale, point_cache=cache, point_cache_times=times,
                            position=(0.0, -0.5, 0.0), keyframes=keys)
    b.add_ground()
    return b.finalize(device)


def cache_times() -> np.ndarray:
    samples = np.arange(25) / 24.0
    return np.unique(np.concatenate([samples, samples + DT, np.linspace(-0.2, 1.3, 61), [1.0 + DT / 2]]))


def test_point_cache_collider_matches_host(device, tmp_path):
    """Check a keyframed deforming collider's vertices and vertex velocities (a float32 USD point cache) equal
    Model.set_collider_geometry's bit for bit, and its poses update_control's, before, on, between and after
    the samples; the BVH is refitted (distances through it follow the moving ball)."""
    model = deforming_model(device, tmp_path)
    animator = ControlAnimator(model)
    assert animator.active and len(animator.point_caches) == 1
    mesh = model.collider_meshes[1]
    host, dev = model.control(), model.control()
    top_speed = 0.0
    for t in cache_times():
        model.update_control(host, float(t), DT)
        want_x, want_v = mesh.points.numpy().copy(), mesh.velocities.numpy().copy()
        nan_fill(mesh.points)
        nan_fill(mesh.velocities)
        animator.set_clock(float(t), DT)
        animator.apply(dev)
        assert np.array_equal(mesh.points.numpy(), want_x), t
        assert np.array_equal(mesh.velocities.numpy(), want_v), t
        top_speed = max(top_speed, float(np.abs(want_v).max()))
        controls_within_float32_ulp(dev, host, model, f"t={t}")
    assert top_speed > 1.0  # the ball moves at 1 m/s and grows: the velocities compared are not zeros
    # the refit: the ball's far side at t = 1 s (1 m from where it started) is 0.3 m from its centre
    animator.set_clock(1.0, DT)
    animator.apply(dev)
    d, _ = collider_distance(model, 1, [[1.0 - 0.35, 0.0, 0.0], [1.0, 0.0, 0.4]], transform=(0, 0, 0, 0, 0, 0, 1))
    np.testing.assert_allclose(d, [0.05, 0.1], atol=0.01)


def test_float64_point_cache_is_within_its_float32_rounding(device, tmp_path):
    """Check a point cache that is not float32-representable (scaled by 1.1), stored as float32 on the device,
    gives vertices within one float32 ulp of the cache's extent of the host's (the samples' rounding plus the
    result's) and velocities within 2 ulp / sample interval more than the result's rounding."""
    model = deforming_model(device, tmp_path, cache_scale=1.1)
    animator = ControlAnimator(model)
    mesh = model.collider_meshes[1]
    control = model.control()
    extent = np.abs(model.colliders[1].point_cache).max()
    v_tol = 2.0 * np.spacing(np.float32(extent)) * 24.0  # 2 ulp over the 1/24 s sample interval
    for t in cache_times():
        model.set_collider_geometry(float(t), DT)
        want_x, want_v = mesh.points.numpy().copy(), mesh.velocities.numpy().copy()
        animator.set_clock(float(t), DT)
        animator.apply(control)
        x_err = np.abs(mesh.points.numpy().astype(np.float64) - want_x)
        assert x_err.max() <= np.spacing(np.float32(extent)), (t, x_err.max())
        v_err = np.abs(mesh.velocities.numpy() - want_v) - np.spacing(np.abs(want_v).astype(np.float32))
        assert v_err.max() <= v_tol, (t, v_err.max(), v_tol)


def snapshot(control, mesh=None) -> list[np.ndarray]:
    arrays = [control.pin_target, control.collider_transform_start, control.collider_transform_end, control.wind]
    if mesh is not None:
        arrays += [mesh.points, mesh.velocities]
    return [a.numpy().copy() for a in arrays]


def test_captured_frames_replay_the_eager_sequence(device, tmp_path):
    """Check a frame (gusty wind at its midpoint, then advance_clock + apply per substep) recorded with
    cloth_warp.graphs.record and replayed frame after frame writes the same control arrays, bit for bit, as the
    eager sequence, and that the last step equals Model.update_control at the clock's time. The frame includes the
    deforming collider and its BVH refit (distances through the BVH equal an eager refit's): on CUDA recorded in
    the graph, on the CPU a host call between graphs, one per substep; a plain wp.ScopedCapture of it raises on the
    CPU (Warp would not replay the refit)."""
    fps, substeps, frames, t0 = 60.0, 3, 8, 0.05
    frame_dt, dt = 1.0 / fps, 1.0 / (fps * substeps)
    wind = GustyWind((2.0, 0.0, 1.0), strength=0.5, period=0.3, turn=40.0, seed=5)
    model = deforming_model(device, tmp_path)
    animator = ControlAnimator(model, wind=wind)
    assert animator.capturable and animator.point_caches
    assert animator.host_calls == wp.get_device(device).is_cpu
    if animator.host_calls:
        with pytest.raises(RuntimeError, match="refit"):
            with wp.ScopedCapture(device=device):
                animator.apply(model.control())
    mesh = model.collider_meshes[1] if animator.point_caches else None

    def frame(control):
        animator.apply_wind(control, 0.5 * frame_dt)
        for _ in range(substeps):
            animator.advance_clock(dt)
            animator.apply(control)

    eager = model.control()
    animator.set_clock(t0, 0.0)
    want = []
    for _ in range(frames):
        frame(eager)
        want.append(snapshot(eager, mesh))
    if mesh is not None:
        probes = [[0.6, -0.5, 0.0], [0.9, -0.5, 0.0], [1.0, -0.1, 0.0], [1.2, -0.5, 0.3]]
        pose = eager.collider_transform_end.numpy()[1]
        want_distance = collider_distance(model, 1, probes, pose)[0]

    captured = model.control()
    with record(device) as capture:
        frame(captured)
    assert capture.host_calls == (substeps if animator.host_calls else 0)
    animator.set_clock(0.0, 0.0)  # an eager update elsewhere: the replays must move the mesh and refit its BVH
    animator.apply(captured)
    animator.set_clock(t0, 0.0)
    for k in range(frames):
        capture.replay()
        got = snapshot(captured, mesh)
        for a, b in zip(got, want[k], strict=True):
            assert np.array_equal(a, b), f"frame {k}"
    time, step, _, _ = animator.clock.numpy()
    assert step == dt and time == pytest.approx(t0 + frames * frame_dt, abs=1e-12)
    host = model.control()
    model.update_control(host, float(time), float(step))
    controls_within_float32_ulp(captured, host, model, f"t={time}")
    if mesh is not None:
        np.testing.assert_array_equal(collider_distance(model, 1, probes, pose)[0], want_distance)


def test_cpu_capture_does_not_replay_mesh_refit(tmp_path):
    """Record why a deforming collider's refit is a host call between graphs on the CPU: in Warp 1.19 a CPU graph
    replays the kernel that moves a mesh's points but not wp.Mesh.refit(), so queries after replay use the
    capture-time tree. When this fails, Warp records the refit: ControlAnimator.apply can refit inside the graph
    on the CPU too."""
    model = deforming_model("cpu", tmp_path)
    animator = ControlAnimator(model)
    mesh, times, cache = animator.point_caches[0]
    probes = [[0.6, 0.0, 0.0], [0.75, 0.2, 0.0], [1.0, 0.0, -0.32]]
    identity = (0, 0, 0, 0, 0, 0, 1)
    animator.set_clock(0.0, DT)
    animator.apply(model.control())
    with wp.ScopedCapture(device="cpu") as capture:
        wp.launch(ka.point_cache_vertices, dim=cache.shape[1], inputs=[animator.clock, times, cache],
                  outputs=[mesh.points, mesh.velocities], device="cpu")
        mesh.refit()
    animator.set_clock(1.0, DT)  # the ball has moved 1 m
    wp.capture_launch(capture.graph)
    assert np.array_equal(mesh.points.numpy(), np.asarray(model.colliders[1].vertices_at(1.0), np.float32))
    stale = collider_distance(model, 1, probes, identity)[0]
    mesh.refit()
    fresh = collider_distance(model, 1, probes, identity)[0]
    np.testing.assert_allclose(fresh, [0.1, 0.02, 0.02], atol=0.01)
    assert np.abs(stale - fresh).max() > 0.05, (stale, fresh)


def test_clock_counts_steps_so_a_restored_run_keeps_its_time():
    """Check the device clock is origin + steps x dt (not a running sum of dt), so a clock restored at step n
    (:meth:`ControlAnimator.set_steps`, as a resumed run sets it) equals, bit for bit, one advanced n times."""
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(2, 2), size=(1.0, 1.0))
    model = b.finalize(device="cpu")
    dt = 1.0 / 60.0 / 7.0
    went = ControlAnimator(model)
    went.set_steps(0, dt)
    for _ in range(1000):
        went.advance_clock(dt)
    summed = 0.0
    for _ in range(1000):
        summed += dt
    restored = ControlAnimator(model)
    restored.set_steps(990, dt)
    for _ in range(10):
        restored.advance_clock(dt)
    assert np.array_equal(went.clock.numpy(), restored.clock.numpy())
    assert went.clock.numpy()[0] == 1000 * dt and summed != 1000 * dt  # a running sum would drift off n x dt
