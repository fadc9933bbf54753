"""Batched worlds (cloth_warp.worlds): each world of a batch steps exactly as it does alone."""

import numpy as np
import pytest
import warp as wp

from cloth_warp.runner import find_scene, load_kernels
from cloth_warp.scene import PASSES_ONLY, build_model, build_solver, build_wind, load_scene
from cloth_warp.simulator import Simulator
from cloth_warp.solvers.implicit import SolverImplicitEuler
from cloth_warp.worlds import build_worlds, split_worlds

FRAMES = 12


@pytest.fixture(params=[True, False], ids=["world threads", "item threads"])
def world_threads(request, monkeypatch):
    """Both forms of a batch's CG on the CPU: one thread per world (the CPU's) and one per particle and element
    (CUDA's)."""
    monkeypatch.setattr(SolverImplicitEuler, "world_threads", request.param)
    return request.param


def _run(model, scene, frames=FRAMES, solves=None):
    """Step `frames` frames; each frame's solve reports appended to `solves` (a batch's per world)."""
    solver = build_solver(scene, model)
    load_kernels(solver, model.device)
    sim = Simulator(model, solver, fps=float(scene.get("output.fps")), substeps=int(scene.get("solver.substeps")), wind=build_wind(scene))
    sweeps = []
    for _ in range(frames):
        sim.step_frame()
        sweeps.append(sim.frame_report.passes["strain_limit"].sweeps if "strain_limit" in sim.frame_report.passes else 0)
        if solves is not None:
            solves.append(sim.world_solves if model.world_count > 1 else sim.frame_report.solves)
    return sim, sum(sweeps)


def _check_batch(name, variants):
    """Each world of the batch equal to its single run bit for bit: its positions, and its solves' records in every
    frame (iterations, and the residuals, summed in float64: a last-bit difference in r.r shows there first)."""
    scenes = [load_scene(find_scene(name), v) for v in variants]
    records = [[] for _ in scenes]
    singles = [_run(build_model(s, "cpu"), s, solves=r) for s, r in zip(scenes, records)]
    batched = []
    batch, _ = _run(build_worlds(scenes, "cpu"), scenes[0], solves=batched)
    assert batch.model.world_count == len(scenes)
    for k, (x, (single, _)) in enumerate(zip(split_worlds(batch.model, batch.positions()), singles)):
        assert np.array_equal(x, single.positions()), f"world {k} differs from its single run by {np.abs(x - single.positions()).max():.3g} m"
        assert [f[k] for f in batched] == records[k], f"world {k}: its solves' records differ from its single run's"
    return singles


@pytest.mark.parametrize("seed", [0, 1])
def test_batched_worlds_equal_their_single_runs_bit_for_bit(seed, world_threads):
    """Worlds of different sizes and materials (so their CG iteration counts and strain-limit sweeps differ per step),
    batched in one model, each equal to its own run on the CPU bit for bit."""
    rng = np.random.default_rng(seed)
    presets = ["cotton", "silk", "denim", "wool"]
    variants = [{"material.preset": presets[int(rng.integers(len(presets)))], "cloth.grid.resolution": [int(rng.integers(6, 14)), int(rng.integers(6, 14))],
                 "solver.strain_limit": 0.03, "scene.seed": int(rng.integers(100)), "cloth.jitter": 0.002} for _ in range(3)]
    singles = _check_batch("hanging_cloth", variants)
    sweeps = [s for _, s in singles]
    its = [single.frame_report.iterations for single, _ in singles]
    # the test's point: worlds that differ in their work per step (limiter sweeps and CG iterations)
    assert max(sweeps) > 0 and len(set(sweeps)) > 1 and len(set(its)) > 1, (sweeps, its)


@pytest.mark.parametrize("membrane, bending", [("element", "springs"), ("springs", "stencil"), ("element", "stencil")])
def test_batched_element_worlds_equal_their_single_runs_bit_for_bit(membrane, bending, world_threads):
    """Membrane elements and plate stencils batched (every kind of element the CG's product scatters), with worlds
    whose cells differ in shape and whose CG iteration counts differ, each equal to its own run bit for bit."""
    variants = [{"material.preset": p, "cloth.grid.resolution": r, "cloth.grid.size": z, "cloth.membrane": membrane,
                 "cloth.bending": bending, "cloth.jitter": 0.002, "scene.seed": k}
                for k, (p, r, z) in enumerate([("silk", [6, 9], [1.0, 0.8]), ("denim", [8, 5], [0.7, 1.0]), ("cotton", [7, 7], [1.0, 1.0])])]
    singles = _check_batch("hanging_cloth", variants)
    model = singles[0][0].model
    assert (model.membrane_count > 0) == (membrane == "element") and (model.plate_count > 0) == (bending == "stencil")
    its = [single.frame_report.iterations for single, _ in singles]
    assert len(set(its)) > 1, its


def test_batched_block_jacobi_worlds_equal_their_single_runs_bit_for_bit():
    """Block Jacobi batched: each world checks its residual, stops and counts its iterations on its own (the batch
    iterates while any world does), so worlds whose solves take different iteration counts each equal their own run."""
    variants = [{"material.preset": p, "cloth.grid.resolution": r, "solver.linear_solver": "jacobi", "solver.substeps": 8,
                 "solver.strain_limit": 0.03, "cloth.jitter": 0.002, "scene.seed": k}
                for k, (p, r) in enumerate([("silk", [6, 5]), ("denim", [7, 7]), ("cotton", [5, 8])])]
    singles = _check_batch("hanging_cloth", variants)
    its = [single.frame_report.iterations for single, _ in singles]
    assert len(set(its)) > 1, its


def _contact_records(sim, frames, world=None):
    """Step `frames` frames; each frame's (iterations, contacts, re-solves) of the solves (of batch world `world`)."""
    out = []
    for _ in range(frames):
        sim.step_frame()
        r = sim.frame_report.solves if world is None else None
        out.append(r if r is None else (r.iterations, r.contacts, r.contact_resolves))
        if world is not None:
            out[-1] = [(w.iterations, w.contacts, w.contact_resolves) for w in sim.world_solves]
    return out


@pytest.mark.parametrize("scene, friction", [("tablecloth", "after"), ("tablecloth", "solve"), ("sphere_shot", "solve")])
def test_batched_worlds_with_contacts_in_the_solve_equal_their_single_runs_bit_for_bit(scene, friction, world_threads):
    """Collider contacts in the solve, batched: each world finds its contacts, releases those that pull and re-solves
    on its own (a world with nothing released sits a re-solve out, its solve as it was), with its own rounds, counts
    and record, so worlds that release and re-solve differently each equal their own run bit for bit, frame by frame."""
    presets = ["silk", "denim", "cotton"]
    variants = [{"material.preset": p, "cloth.grid.resolution": [7 + 2 * k, 9 - k], "cloth.jitter": 0.002, "scene.seed": k,
                 "solver.collider_contacts": "solve", "solver.contact_friction": friction} for k, p in enumerate(presets)]
    scenes = [load_scene(find_scene(scene), v) for v in variants]
    frames = 24
    singles, records = [], []
    for s in scenes:
        sim = _run(build_model(s, "cpu"), s, frames=0)[0]
        records.append(_contact_records(sim, frames))
        singles.append(sim)
    batch = _run(build_worlds(scenes, "cpu"), scenes[0], frames=0)[0]
    batched = _contact_records(batch, frames, world=True)
    for k, (x, single) in enumerate(zip(split_worlds(batch.model, batch.positions()), singles)):
        assert np.array_equal(x, single.positions()), f"world {k} differs from its single run by {np.abs(x - single.positions()).max():.3g} m"
        assert [f[k] for f in batched] == records[k], f"world {k}: its solves' records differ"
    contacts = [sum(f[1] for f in r) for r in records]
    resolves = [[f[2] for f in r] for r in records]
    assert min(contacts) > 0, contacts
    if scene == "tablecloth":  # (the ball of sphere_shot, a moving collider, passes without a release)
        assert sum(map(sum, resolves)) > 0 and len({tuple(r) for r in resolves}) > 1, resolves  # the worlds re-solve differently


def test_batched_worlds_share_colliders():
    """Drapes over the same ball (a collider shared by the worlds) in three materials."""
    _check_batch("drape_sphere", [{**PASSES_ONLY, "cloth.grid.resolution": [8, 8], "collision.self_collision": False, "material.preset": p}
                                  for p in ("cotton", "silk", "denim")])


def test_batched_worlds_refuse_what_they_do_not_share():
    base = load_scene(find_scene("hanging_cloth"), {"cloth.grid.resolution": [4, 4]})
    with pytest.raises(ValueError, match="solver"):
        build_worlds([base, load_scene(find_scene("hanging_cloth"), {"cloth.grid.resolution": [4, 4], "solver.tolerance": 1e-5})], "cpu")
    model = build_worlds([base, base], "cpu")
    with pytest.raises(ValueError, match="batched worlds"):
        Simulator(model, build_solver(base, model), adaptive=True)


def test_one_world_model_is_unbatched():
    scene = load_scene(find_scene("hanging_cloth"), {"cloth.grid.resolution": [4, 4]})
    m = build_model(scene, "cpu")
    assert m.world_count == 1 and not m.particle_world.numpy().any()
    assert list(m.world_particle_start) == [0, m.particle_count]


def test_a_diverged_world_is_held_and_the_others_go_on():
    """A world whose forces turn non-finite in the middle of a run (a spring's rest length set to NaN, a fault
    injected into one world) is diagnosed on its own and held at its last good state, finite; the other worlds
    still equal their single runs bit for bit, and each world's statistics are its own."""
    variants = [{"material.preset": p, "cloth.grid.resolution": [8, 8]} for p in ("cotton", "silk", "denim")]
    scenes = [load_scene(find_scene("hanging_cloth"), v) for v in variants]
    singles = [_run(build_model(s, "cpu"), s)[0] for s in scenes]
    model = build_worlds(scenes, "cpu")
    batch, _ = _run(model, scenes[0], frames=4)
    held = split_worlds(model, batch.positions())[1].copy()
    spring = int(np.flatnonzero(model.particle_world.numpy()[model.spring_indices.numpy().reshape(-1, 2)[:, 0]] == 1)[0])
    model.spring_rest_length.numpy()[spring] = np.nan  # (a CPU array's numpy() is a view)
    for _ in range(FRAMES - 4):
        stats = batch.step_frame()
    assert list(batch.world_failures) == [1], batch.world_failures
    assert "world 1" in str(batch.world_failures[1]) and batch.world_failures[1].frame == 5
    worlds = split_worlds(model, batch.positions())
    assert np.array_equal(worlds[1], held) and np.isfinite(stats.max_speed)
    for k in (0, 2):
        assert np.array_equal(worlds[k], singles[k].positions()), k
        assert batch.world_stats[k] == singles[k].last_stats, k  # its own statistics, not the batch's


def test_run_worlds_writes_one_cache_per_world(tmp_path):
    """run_worlds: one cache per world with that world's frames (equal to the batch's), and the worlds' own
    diagnostics; two worlds on one output are refused."""
    from cloth_warp.cache import CacheReader
    from cloth_warp.worlds import run_worlds

    scenes = [load_scene(find_scene("hanging_cloth"), {"material.preset": p, "cloth.grid.resolution": [6, 6 + k]})
              for k, p in enumerate(("cotton", "silk"))]
    outs = [tmp_path / f"w{k}.usdc" for k in range(2)]
    results = run_worlds(scenes, outs, frames=5, device="cpu")
    assert [r.status for r in results] == ["complete"] * 2 and [r.frames_written for r in results] == [6, 6]
    single = _run(build_model(scenes[1], "cpu"), scenes[1], frames=5)[0]
    reader = CacheReader(outs[1])
    assert reader.frame_count == 6 and reader.metadata["status"] == "complete"
    np.testing.assert_array_equal(reader.points(reader.start_frame + 5), single.positions())
    with pytest.raises(ValueError, match="same output"):
        run_worlds(scenes, [outs[0], outs[0]], frames=1, device="cpu")


def test_run_worlds_closes_a_diverged_world_and_finishes_the_others(tmp_path):
    """A world too stiff for the batch's explicit step (stretch stiffness 1e5 N/m at 40 symplectic substeps: it
    diverges in its first frame, alone as in the batch) gets a cache closed as diverged with its initial frame and
    the diagnosis; the other world runs to the end and equals its single run."""
    from cloth_warp.cache import CacheReader
    from cloth_warp.simulator import SimulationDiverged
    from cloth_warp.worlds import run_worlds

    base = {"cloth.grid.resolution": [6, 6], "solver.integrator": "symplectic_euler", "solver.substeps": 40}
    scenes = [load_scene(find_scene("hanging_cloth"), v) for v in (base, {**base, "material.stretch_stiffness": 1e5})]
    with pytest.raises(SimulationDiverged):
        _run(build_model(scenes[1], "cpu"), scenes[1], frames=1)
    outs = [tmp_path / "ok.usdc", tmp_path / "bad.usdc"]
    ok, bad = run_worlds(scenes, outs, frames=6, device="cpu")
    assert (ok.status, ok.frames_written) == ("complete", 7)
    assert (bad.status, bad.frames_written) == ("diverged", 1) and "world 1" in bad.message and "frame 1" in bad.message
    assert CacheReader(outs[1]).metadata["status"] == "diverged"
    single = _run(build_model(scenes[0], "cpu"), scenes[0], frames=6)[0]
    reader = CacheReader(outs[0])
    np.testing.assert_array_equal(reader.points(reader.start_frame + 6), single.positions())


def _taped_gradients(model, scene, loss, steps):
    from cloth_warp.gradients import Rollout, model_grad_arrays

    solver = build_solver(scene, model)
    load_kernels(solver, model.device)
    rollout = Rollout(model, solver, dt=1.0 / float(scene.get("output.fps")) / int(scene.get("solver.substeps")), steps=steps)
    value = rollout.gradient(loss)
    return value, {k: a.grad.numpy().copy() for k, a in model_grad_arrays(model).items() if a.grad is not None}


def _by_endpoints(keys: np.ndarray, first: int, count: int) -> dict:
    """{sorted element vertex tuple (world-local ids): element index} for the elements (rows of particle ids) of the
    particles first..first+count (a batch orders its springs and triangles its own way)."""
    out = {}
    for e, ids in enumerate(keys):
        if first <= ids.min() < first + count:
            out[tuple(sorted(int(i) - first for i in ids))] = e
    return out


def test_batched_worlds_give_each_world_the_gradient_of_its_own_run():
    """A taped rollout of a batch with one loss per world (world_losses) gives every world's parameters (masses, spring
    stiffnesses, rest lengths and damping, triangle drag) the gradient its own single-world rollout gives, bit for bit
    on the CPU, with the strain limiter sweeping different worlds a different number of times (each world only while it
    is above the limit, the adjoint replaying the same worlds per sweep)."""
    from cloth_warp.gradients import PositionLoss
    from cloth_warp.worlds import world_losses, world_slices

    steps = 8
    variants = [{"material.preset": p, "cloth.grid.resolution": r, "solver.strain_limit": 0.006, "cloth.jitter": 0.002, "scene.seed": k}
                for k, (p, r) in enumerate([("silk", [7, 5]), ("denim", [6, 6]), ("cotton", [5, 8])])]
    scenes = [load_scene(find_scene("hanging_cloth"), v) for v in variants]
    # the worlds differ in their limiter work (forward frames of the same variants, one step each: 4-426 sweeps)
    sweeps = [_run(build_model(s, "cpu"), s, frames=steps)[1] for s in scenes]
    assert max(sweeps) > 0 and len(set(sweeps)) > 1, sweeps
    rng = np.random.default_rng(0)
    singles, targets = [], []
    for s in scenes:
        m = build_model(s, "cpu", requires_grad=True)
        target = {steps: m.particle_q.numpy() + rng.uniform(-0.02, 0.02, size=(m.particle_count, 3))}
        targets.append(target)
        singles.append((m, _taped_gradients(m, s, PositionLoss(target, device="cpu"), steps)))
    batch = build_worlds(scenes, "cpu", requires_grad=True)
    value, grads = _taped_gradients(batch, scenes[0], world_losses(batch, targets), steps)
    # (the batch's terms add into one float32 in another order than each run's: 1e-5 apart here)
    assert value == pytest.approx(sum(v for _, (v, _) in singles), rel=1e-4)
    for k, ((m, (_, g)), sl) in enumerate(zip(singles, world_slices(batch))):
        assert np.array_equal(grads["particle_mass"][sl], g["particle_mass"]), f"world {k}: mass gradients differ"
        assert np.abs(g["particle_mass"]).max() > 0.0
        for indices, width, arrays in (("spring_indices", 2, ["spring_stiffness", "spring_rest_length", "spring_damping"]),
                                       ("tri_indices", 3, ["tri_drag"])):
            local = _by_endpoints(getattr(m, indices).numpy().reshape(-1, width), 0, m.particle_count)
            batched = _by_endpoints(getattr(batch, indices).numpy().reshape(-1, width), sl.start, sl.stop - sl.start)
            assert len(local) == len(getattr(m, indices).numpy().reshape(-1, width))  # (no two elements on the same particles)
            order = [batched[key] for key in sorted(local, key=local.get)]
            for array in arrays:
                assert np.array_equal(grads[array][order], g[array]), f"world {k}: {array} gradients differ"
                assert np.abs(g[array]).max() > 0.0, array


def test_batched_worlds_with_attachments_equal_their_single_runs_bit_for_bit(world_threads):
    """Strips of different materials and sizes bound (ModelBuilder.attach) to one breathing, swaying point-cache body,
    batched: each world's attached particles follow the shared body and every world equals its own run bit for bit."""
    import trimesh

    import cloth_warp as cw

    ico = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    times = np.linspace(0.0, 1.0, 11)
    cache = np.stack([ico.vertices * (1.0 + 0.25 * np.sin(np.pi * t)) + np.array([0.15 * np.sin(2 * np.pi * t), 0.0, 0.0]) for t in times])

    def world(k):
        b = cw.ModelBuilder()
        body = b.add_collider_mesh(ico.vertices, ico.faces, position=(0.0, 1.0, 0.0), point_cache=cache, point_cache_times=times,
                                   name="body")
        strip = b.add_cloth_grid(resolution=(5 + k, 9 - k), size=(0.12 + 0.02 * k, 0.3), position=(-0.06, 0.7, 0.202),
                                 material=["cotton", "silk", "denim"][k], name="strip")
        b.attach(strip.select("edge:top"), body, offset=0.0 if k == 1 else None)
        return b

    def run(model):
        sim = cw.Simulator(model, cw.SolverImplicitEuler(model), fps=60, substeps=2)
        for _ in range(30):
            sim.step_frame()
        return sim.positions()

    singles = [run(world(k).finalize("cpu")) for k in range(3)]
    batch = cw.ModelBuilder()
    for k in range(3):
        batch.add_world(world(k))
    model = batch.finalize("cpu")
    assert [a.name for a in model.attachments] == [f"world{k}/attachment0" for k in range(3)]
    for k, (x, single) in enumerate(zip(split_worlds(model, run(model)), singles)):
        assert np.array_equal(x, single), f"world {k} differs from its single run by {np.abs(x - single).max():.3g} m"


def test_a_batch_restored_from_a_checkpoint_goes_on_as_the_uninterrupted_batch():
    """A batch checkpointed after a world diverged (and, separately, before) and restored into a fresh Simulator gives
    the uninterrupted batch's frames bit for bit: the diverged world still held where it was, with its diagnosis, the
    others with their warm starts (each world's own), every world's solves' records the same."""
    variants = [{"material.preset": p, "cloth.grid.resolution": [8, 8]} for p in ("cotton", "silk", "denim")]
    scenes = [load_scene(find_scene("hanging_cloth"), v) for v in variants]

    def batch():
        model = build_worlds(scenes, "cpu")
        spring = int(np.flatnonzero(model.particle_world.numpy()[model.spring_indices.numpy().reshape(-1, 2)[:, 0]] == 1)[0])
        return _run(model, scenes[0], frames=0)[0], spring

    def poison(sim, spring):
        sim.model.spring_rest_length.numpy()[spring] = np.nan  # world 1's forces turn non-finite (a CPU view)

    def frames(sim, count):
        out = []
        for _ in range(count):
            sim.step_frame()
            out.append((sim.positions().copy(), sim.world_solves, sorted(sim.world_failures)))
        return out

    reference, spring = batch()
    frames(reference, 3)
    poison(reference, spring)
    expected = frames(reference, 7)
    for at in (0, 3):  # checkpointed before world 1's failure (in frame 4), and after it
        first, spring = batch()
        frames(first, 3)
        poison(first, spring)
        frames(first, at)
        ck = first.checkpoint()
        assert ("worlds.failures" in ck) == (at > 0)
        resumed, spring = batch()
        poison(resumed, spring)
        resumed.restore(ck)
        assert {k: str(e) for k, e in resumed.world_failures.items()} == {k: str(e) for k, e in first.world_failures.items()}
        got = frames(resumed, 7 - at)
        for (x, solves, failed), (y, solves_ref, failed_ref) in zip(got, expected[at:]):
            assert np.array_equal(x, y) and repr(solves) == repr(solves_ref) and failed == failed_ref, at  # (NaN residuals)


SOLVE = {"solver.collider_contacts": "solve", "solver.self_contacts": "solve", "solver.contact_friction": "solve",
         "solver.tolerance": 1e-4}


@pytest.mark.parametrize("scene, contacts", [("pile", PASSES_ONLY), ("drape_sphere", PASSES_ONLY),
                                             ("pile", {"solver.collider_contacts": "solve", "solver.self_contacts": "pass",
                                                       "solver.contact_friction": "solve"}),
                                             ("pile", SOLVE)],
                         ids=["pile", "drape", "pile-contacts-in-solve", "pile-everything-in-solve"])
def test_batched_worlds_with_self_collision_equal_their_single_runs_bit_for_bit(scene, contacts, world_threads):
    """Cloths that fold onto themselves (the pile and the drape over a ball, each world's self-collision its own:
    proximity, CCD and impact zones on its own model and slice), of other materials, sizes and seeds, batched: every
    world equal to its single run bit for bit, frame by frame, with the same solve records, and the batch's
    self-collision counters the sum of the single runs'; also with the collider contacts and their friction in the
    solve, and with the self-contacts in the solve too (each world's elements from its own pass's close pairs, its own
    stiffness, counted, slid and re-solved in its world). (A world's pair buffers overflowing re-runs the frame for
    the whole batch: the others run it again as they ran it.)"""
    variants = [{"material.preset": p, "cloth.grid.resolution": [r, r], "scene.seed": k, **contacts}
                for k, (p, r) in enumerate([("silk", 10), ("denim", 12), ("cotton", 9 if scene == "pile" else 13)])]
    scenes = [load_scene(find_scene(scene), v) for v in variants]
    frames = 50
    records, counters, impulses = [], [], []
    for s in scenes:
        sim = _run(build_model(s, "cpu"), s, frames=0)[0]
        rec, total, hits = [], 0, 0
        for _ in range(frames):
            sim.step_frame()
            rec.append((sim.positions().copy(), repr(sim.frame_report.solves)))
            c = sim.frame_report.passes["self_collision"].counters()
            total += sum(c.values())
            hits += c["self_proximity"] + c["self_ccd"]
        records.append(rec)
        counters.append(total)
        impulses.append(hits)
    assert min(impulses) > 0, impulses  # every world folds onto itself within the frames
    batch = _run(build_worlds(scenes, "cpu"), scenes[0], frames=0)[0]
    assert type(batch.solver.pass_named("self_collision")).__name__ == "WorldSelfCollisionPass"
    total = 0
    for f in range(frames):
        batch.step_frame()
        total += sum(batch.frame_report.passes["self_collision"].counters().values())
        for k, x in enumerate(split_worlds(batch.model, batch.positions())):
            assert np.array_equal(x, records[k][f][0]), f"world {k} frame {f + 1}: {np.abs(x - records[k][f][0]).max():.3g} m"
            assert repr(batch.world_solves[k]) == records[k][f][1], f"world {k} frame {f + 1}"
    assert total == sum(counters), (total, counters)
    if scene == "pile":  # the piles' frames include re-runs of the whole batch for one world's overflow
        assert batch.reruns >= 1
