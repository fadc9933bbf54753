"""Divergence without NaN is caught on every path, before the frame is returned, with a diagnosis and a smaller dt;
healthy shipped scenes stay far from the bounds."""

import math
import pathlib

import numpy as np
import pytest

import cloth_warp as cw
from cloth_warp.scene import build_model, build_solver, build_wind, load_scene
from cloth_warp.solvers.adaptive import DivergenceBounds

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"
FEW_SWEEPS = {"solver.strain_limit_iterations": 4}
BOUND_KINDS = ("strain", "speed", "energy")


def make_sim(name: str, overrides: dict, **kwargs) -> cw.Simulator:
    scene = load_scene(SCENES / f"{name}.toml", overrides)
    model = build_model(scene, "cpu")
    solver = build_solver(scene, model)
    return cw.Simulator(model, solver, fps=float(scene.get("output.fps")), substeps=int(scene.get("solver.substeps")),
                        adaptive=bool(scene.get("solver.adaptive")), dt_min=float(scene.get("solver.dt_min")), wind=build_wind(scene),
                        **kwargs)


def diverge(sim, frames: int = 10) -> cw.SimulationDiverged:
    with pytest.raises(cw.SimulationDiverged) as info:
        for _ in range(frames):
            sim.step_frame()
    return info.value


def assert_diagnosis(err: cw.SimulationDiverged, sim: cw.Simulator):
    """The message names frame, time, reason and max strain and suggests a smaller step; the frame was not counted."""
    text = str(err)
    assert f"diverged in frame {err.frame} at t = " in text and err.reason in text and "max strain" in text and "try" in text
    assert 0.0 < err.suggested_dt < err.dt
    assert f"{err.suggested_dt:.3g}" in text
    assert sim.frame == err.frame - 1 and sim.time == pytest.approx((err.frame - 1) / sim.fps)
    d = err.diagnosis()
    assert d["frame"] == err.frame and d["suggested_dt"] == err.suggested_dt
    assert all(v is None or isinstance(v, str | int) or math.isfinite(v) for v in d.values())


@pytest.mark.parametrize("strain_limit, kind", [(0.1, "speed"), (0.0, "strain")])
def test_finite_explicit_divergence_is_caught(strain_limit, kind):
    """Check explicit Euler on stiff cotton, which stays finite (strain held at the limit while particles reach
    1e3 m/s, or strain 50 without a limit), stops within two frames with the bound it crossed."""
    sim = make_sim("hanging_cloth", {"cloth.grid.resolution": [16, 16], "solver.integrator": "explicit_euler", "solver.substeps": 8,
                                     "solver.strain_limit": strain_limit, **FEW_SWEEPS})
    err = diverge(sim)
    assert err.kind == kind and err.frame <= 2
    assert np.isfinite(sim.positions()).all()  # not a NaN: only the bounds can see it
    assert_diagnosis(err, sim)
    assert "symplectic_euler or implicit_euler" in str(err)


@pytest.mark.parametrize("integrator, substeps", [("symplectic_euler", 16), ("midpoint", 8), ("rk4", 4)])
def test_captured_paths_are_checked(integrator, substeps):
    """Check every explicit integrator, graph-captured, stops at the first frame beyond the bounds, and suggests a
    whole number of substeps per frame below the integrator's stability step."""
    sim = make_sim("hanging_cloth", {"cloth.grid.resolution": [12, 12], "solver.integrator": integrator, "solver.substeps": substeps,
                                     **FEW_SWEEPS})
    assert sim.capture
    err = diverge(sim)
    assert sim._graph is not None and err.frame <= 2
    assert err.kind in BOUND_KINDS + ("non-finite",)
    assert_diagnosis(err, sim)
    n = round(sim.frame_dt / err.suggested_dt)
    assert n > substeps and math.isclose(sim.frame_dt / n, err.suggested_dt)
    assert err.suggested_dt <= 0.9 * sim.bounds.stable_dt


@pytest.mark.slow
def test_slow_implicit_drift_is_caught():
    """Check implicit Euler with a loose solve (residual 3e-2) and no strain limit on the 64^2 hanging cloth, which
    drifts into strain 60 and 140 m/s after 2-3 s while staying finite (it used to run to the end), is stopped by the
    energy bound once it has drifted (strain well above the healthy ~0.15; measured: frame 103 with the convergence
    tested every iteration, frame 143 when tested every 4th, whose overshoot made the solve tighter), before it runs
    away, with a suggestion of two steps per frame."""
    sim = make_sim("hanging_cloth", {"solver.strain_limit": 0.0, "solver.tolerance": 3e-2})
    err = diverge(sim, 200)
    assert err.frame < 160 and err.kind in BOUND_KINDS
    assert 0.3 < err.max_strain < 5.0
    assert np.isfinite(sim.positions()).all()
    assert_diagnosis(err, sim)
    assert "solver.substeps >= 2" in str(err)


def test_adaptive_suggests_a_smaller_step_than_the_one_that_failed():
    """Check the adaptive stepper stopping at its floor names the frame and suggests a dt below the step that failed
    (it used to suggest half the smallest accepted step, which could be larger)."""
    sim = make_sim("hanging_cloth", {"cloth.grid.resolution": [12, 12], "solver.integrator": "symplectic_euler", "solver.substeps": 1,
                                     "solver.adaptive": True, "solver.dt_min": 2e-3, **FEW_SWEEPS})
    err = diverge(sim, 5)
    assert err.frame <= 2 and err.dt < 2 * 2e-3
    assert_diagnosis(err, sim)
    assert "lower solver.dt_min" in str(err)
    assert np.isfinite(sim.positions()).all()


def test_adaptive_steps_take_the_energy_a_moving_collider_hands_on():
    """Check a fast collider hitting a resting cloth is not taken for a blow-up by the adaptive stepper's energy-growth
    test (sphere_shot's 20 m/s ball: the cloth's kinetic energy jumps by orders of magnitude in one step whatever the
    step; it used to be rejected down to dt_min and end as a divergence), while the bounds still hold."""
    sim = make_sim("sphere_shot", {"cloth.grid.resolution": [12, 12], "solver.adaptive": True})
    energy = []
    for _ in range(30):
        energy.append(sim.step_frame().kinetic_energy)
    assert max(energy) > 1e3 * max(energy[0], 1e-9)  # the ball did hit the cloth
    assert "energy growth" not in sim.stepper.report.reasons, sim.stepper.report  # (the impact's strain jumps may be)


def _poisoned_implicit(adaptive: bool):
    sim = make_sim("hanging_cloth", {"cloth.grid.resolution": [8, 8], "solver.adaptive": adaptive, "solver.dt_min": 1e-3})
    k = sim.model.spring_stiffness.numpy().copy()
    k[0] = np.inf  # finite positions, a non-finite linear system
    sim.model.spring_stiffness.assign(k)
    return sim


def test_nonfinite_residual_is_a_divergence():
    """Check an implicit solve on a non-finite system reports it (0 iterations, not converged) and the Simulator
    stops with reason 'non-finite residual' instead of returning the frame."""
    sim = _poisoned_implicit(adaptive=False)
    err = diverge(sim, 2)
    assert err.kind == "non-finite residual" and "non-finite residual" in err.reason and err.frame == 1
    solver = sim.solver
    assert solver.last_failure == "non-finite residual" and not solver.converged and solver.last_iterations == 0
    assert_diagnosis(err, sim)


def test_nonfinite_residual_is_rejected_by_the_adaptive_stepper():
    """Check the adaptive stepper rejects a step whose solve is not finite (and does not warm-start its retry from
    it), ending at its floor with that reason."""
    sim = _poisoned_implicit(adaptive=True)
    err = diverge(sim, 2)
    assert err.kind == "non-finite residual"
    assert sim.stepper.report.reasons.get("non-finite residual", 0) >= 2
    assert not sim.solver.has_previous
    assert_diagnosis(err, sim)


def test_bounds_follow_the_scene():
    """Check the bounds' inputs: the strain limit, an unlimited cloth, a fast collider's reach, the gusty wind's
    strongest speed, handles' speed; and that a suggestion is always below the step that failed."""
    def bounds(name, overrides=None):
        return make_sim(name, {**(overrides or {}), **({"cloth.grid.resolution": [8, 8]} if name != "curtain" else {})}).bounds

    assert bounds("hanging_cloth").max_strain == pytest.approx(1.0, abs=1e-5)
    assert bounds("hanging_cloth", {"solver.strain_limit": 0.3}).max_strain == pytest.approx(1.5, abs=1e-5)
    assert bounds("hanging_cloth", {"solver.strain_limit": 0.0}).max_strain == pytest.approx(9.0, abs=1e-5)
    shot = bounds("sphere_shot")
    assert shot.kinematic_speed == pytest.approx(20.0) and shot.drive_speed == pytest.approx(40.0)
    assert shot.collider_strain == pytest.approx(1.0 / (0.6 / 8), rel=1e-4)  # 1 m of travel over 7.5 cm cells
    flag = bounds("flag")
    assert flag.wind_speed == pytest.approx(math.hypot(7.0, 1.5) * (1 + 0.4 * 2 * math.sqrt(2)))
    wind = build_wind(load_scene(SCENES / "flag.toml"))
    assert max(np.linalg.norm(wind.at(t)) for t in np.linspace(0, 20, 2001)) <= flag.wind_speed
    curtain = bounds("curtain")
    assert curtain.kinematic_speed == pytest.approx(1.2 / 2.0, rel=1e-6) and curtain.forced_strain == 0.0
    for b in (shot, flag, curtain, bounds("hanging_cloth", {"solver.integrator": "symplectic_euler"})):
        for dt in (1e-1, 1e-3, 1e-6):
            assert 0.0 < b.suggest_dt(dt) < dt


def test_handles_pulling_apart_raise_the_strain_bound():
    """Check handles that stretch the cloth (pinned corners pulled 50 % apart) raise the strain bound by that much."""
    b = cw.ModelBuilder()
    c = b.add_cloth_grid(resolution=(4, 4), size=(1.0, 1.0), material="cotton")
    b.add_handle(c.select("corner:top_left"), keyframes=[cw.Keyframe(0.0), cw.Keyframe(1.0, (-0.25, 0.0, 0.0))])
    b.add_handle(c.select("corner:top_right"), keyframes=[cw.Keyframe(0.0), cw.Keyframe(1.0, (0.25, 0.0, 0.0))])
    model = b.finalize("cpu")
    bounds = DivergenceBounds(model, cw.SolverImplicitEuler(model))
    assert bounds.forced_strain == pytest.approx(0.5, rel=1e-6)
    assert bounds.max_strain == pytest.approx(1.5, rel=1e-5)


# (scene, overrides, frames): small versions of shipped scenes with what could trip a careless bound: a ball at
# 20 m/s, gusts, handles, self-collision piles, a cloth without strain limiting, a sharp rim
HEALTHY = [
    ("sphere_shot", {"cloth.grid.resolution": [16, 16]}, 20),
    ("flag", {"cloth.grid.resolution": [12, 8]}, 60),
    ("pile", {"cloth.grid.resolution": [10, 10]}, 40),
    ("hanging_cloth", {"cloth.grid.resolution": [16, 16], "solver.strain_limit": 0.0, "solver.tolerance": 3e-2}, 40),
    ("catenary", {"cloth.grid.resolution": [32, 1]}, 60),
]


@pytest.mark.parametrize("name, overrides, frames", HEALTHY, ids=[h[0] for h in HEALTHY])
def test_healthy_scenes_stay_far_from_the_bounds(name, overrides, frames):
    """Check reduced shipped scenes never come within 2x of a strain bound or 4x of a speed or energy bound (every
    full shipped scene, measured: strain <= 0.41 of its bound (sphere_shot), speed <= 0.11, energy <= 0.15)."""
    sim = make_sim(name, overrides)
    worst = dict.fromkeys(BOUND_KINDS, 0.0)
    for _ in range(frames):
        s = sim.step_frame()
        b = sim.bounds
        for kind, ratio in (("strain", s.max_strain / b.max_strain), ("speed", s.max_speed / b.speed_bound(s)),
                            ("energy", s.kinetic_energy / b.energy_bound(s))):
            worst[kind] = max(worst[kind], ratio)
    assert worst["strain"] < 0.5 and worst["speed"] < 0.25 and worst["energy"] < 0.25, worst


def test_run_never_writes_the_failing_frame(tmp_path):
    """Check a run that diverges without NaN stops with status diverged, a diagnosis with a smaller dt, and a cache
    holding only the good frames: the exploded frame (hundreds of m/s) is not written."""
    from cloth_warp.runner import run_scene

    out = tmp_path / "boom.npz"
    summary = run_scene(SCENES / "hanging_cloth.toml", {"cloth.grid.resolution": [8, 8], "solver.integrator": "explicit_euler",
                                                         "solver.substeps": 4, **FEW_SWEEPS}, output=out, frames=10)
    assert summary["status"] == "diverged" and summary["frames"] < 10
    assert "max strain" in summary["message"] and summary["diagnosis"]["suggested_dt"] < summary["diagnosis"]["last_dt"]
    data = np.load(out)
    assert data["positions"].shape[0] == summary["frames"] + 1
    assert np.linalg.norm(data["velocities"], axis=2).max() < 2.0  # good frames: at most a few frames of free fall
