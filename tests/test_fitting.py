"""cloth-warp fit: parameter recovery from a target cache, the command line and its outputs, bad input."""

import json
import pathlib

import numpy as np
import pytest

import cloth_warp as cw
from cloth_warp.cli import main
from cloth_warp.fitting import SceneFit
from cloth_warp.scene import load_scene

SCENES = pathlib.Path(__file__).resolve().parent.parent / "scenes"
TRUTH = {"material.stretch_stiffness": 150.0, "material.bend_stiffness": 2.0e-4, "material.damping": 0.02}
FRAMES = 15


@pytest.fixture(scope="module")
def target(tmp_path_factory):
    """The fit_hanging scene simulated with the true values (the scene itself starts 2x off each)."""
    out = tmp_path_factory.mktemp("fit") / "target.npz"
    cw.run_scene(SCENES / "fit_hanging.toml", dict(TRUTH), output=out, frames=FRAMES)
    return out


@pytest.mark.slow
def test_fit_recovers_hanging_cloth_material(target):
    """Stretch, bend and damping, each started 2x off, come back within 3 % in 40 iterations (<= 100)."""
    scene = load_scene(SCENES / "fit_hanging.toml")
    start = {k: v for k, v in zip(TRUTH, (300.0, 4.0e-4, 0.04))}
    for key, value in start.items():
        assert scene.get(key) == pytest.approx(value)
    fit = SceneFit(scene, target, list(TRUTH))
    result = fit.run(iterations=40, learning_rate=0.1)
    assert result.final_loss < 1e-3 * result.initial_loss
    for key, truth in TRUTH.items():
        assert result.final_values[key] == pytest.approx(truth, rel=0.03), (key, result.final_values)


def test_scene_parameter_gradients_match_finite_differences(target):
    """The chain rule from model arrays to scene keys (material values via model builds, wind, initial velocity)."""
    scene = load_scene(SCENES / "fit_hanging.toml", {"forces.wind": [0.5, 0.0, 1.0], "cloth.velocity": [0.1, 0.0, 0.0]})
    keys = ["material.stretch_stiffness", "material.areal_density", "material.drag_coefficient", "forces.wind", "cloth.velocity"]
    fit = SceneFit(scene, target, keys, frames=6)
    values = [p.value.copy() for p in fit.parameters]
    loss, grads = fit.loss_and_gradient(values)
    for i, (p, g) in enumerate(zip(fit.parameters, grads)):
        assert np.isfinite(g).all()
        # Derivative along the gradient, relative steps for positive values; Richardson-extrapolated
        # central differences (see test_gradients.py for the choice of eps in float32).
        scale = p.value if p.log else np.ones_like(p.value)
        d = g * scale / np.linalg.norm(g * scale) * scale
        eps = min(0.1, 1e-2 * loss / np.linalg.norm(g * scale))

        def at(e):
            moved = [v.copy() for v in values]
            moved[i] = values[i] + e * d
            return fit.loss_and_gradient(moved)[0]

        coarse = (at(eps) - at(-eps)) / (2 * eps)
        fine = (at(eps / 2) - at(-eps / 2)) / eps
        fd = (4 * fine - coarse) / 3
        ad = float(np.dot(g, d))
        assert fd > 0 and abs(ad - fd) <= 1e-2 * fd, (p.key, ad, fd)


def test_fit_command_writes_scene_report_and_curve(target, tmp_path, capsys):
    out = tmp_path / "fitted.toml"
    rc = main(["fit", str(SCENES / "fit_hanging.toml"), "--target", str(target), "--param", "material.bend_stiffness=1e-5:1e-3",
               "--param", "material.damping", "--iters", "3", "--frames", "4", "-o", str(out)])
    assert rc == 0
    printed = capsys.readouterr()
    assert "3/3" in printed.err and "loss" in printed.err
    assert "material.bend_stiffness" in printed.out and "fitted scene" in printed.out
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["iterations"] == 3 and report["status"] == "complete" and len(report["losses"]) == 3
    assert report["final_loss"] <= report["initial_loss"]
    fitted = load_scene(out)  # a valid scene with the fitted values
    for key in ("material.bend_stiffness", "material.damping"):
        assert fitted.get(key) == pytest.approx(report["final_values"][key])
    assert 1e-5 <= fitted.get("material.bend_stiffness") <= 1e-3
    from PIL import Image

    with Image.open(tmp_path / "fitted_loss.png") as img:
        assert img.size == (640, 400)


def test_fit_bad_input_exits_2(target, tmp_path, capsys):
    scene = str(SCENES / "fit_hanging.toml")
    assert main(["fit", scene, "--target", str(target), "--param", "material.colour", "-o", str(tmp_path / "x.toml")]) == 2
    assert "allowed" in capsys.readouterr().err
    assert main(["fit", scene, "--target", str(target), "--param", "material.damping=2:1"]) == 2
    assert "lower bound" in capsys.readouterr().err
    assert main(["fit", scene, "--target", str(target), "--param", "material.damping", "--set", "cloth.grid.resolution=[4, 4]"]) == 2
    assert "chamfer" in capsys.readouterr().err
    assert not (tmp_path / "x.toml").exists()


def test_collider_friction_gradient_matches_finite_differences():
    """colliders[0].friction of the incline (a sliding cloth, no air drag: the drag term's gradient used to be
    NaN at c_A = 0): the centre of mass after 10 frames against central differences."""
    scene = load_scene(SCENES / "incline.toml", {"cloth.grid.resolution": [6, 6]})
    substeps = int(scene.get("solver.substeps"))
    fit = SceneFit(scene, lambda model: cw.CentroidLoss((-0.3, 0.0, 0.0), 10 * substeps, model), ["colliders[0].friction"], frames=10)
    value = [fit.parameters[0].value.copy()]
    loss, grad = fit.loss_and_gradient(value)
    eps = 0.01  # the cloth slides throughout (tan 30 deg > 0.3 +- eps): the loss is smooth in mu_k
    fd = (fit.loss_and_gradient([value[0] + eps])[0] - fit.loss_and_gradient([value[0] - eps])[0]) / (2 * eps)
    assert np.isfinite(grad[0]).all() and grad[0][0] > 0.0
    assert grad[0][0] == pytest.approx(fd, rel=1e-2)


@pytest.mark.slow
def test_thrown_cloth_lands_on_target(tmp_path, capsys):
    """scenes/fit_throw.toml as shipped: the fitted initial velocity lands the cloth within 2 cm of its target
    (started 82 cm off), and the fitted scene run forward lands there too, at rest."""
    scene = load_scene(SCENES / "fit_throw.toml")
    target = np.array(scene.get("fit.target.centroid"))
    out = tmp_path / "throw.toml"
    assert main(["fit", str(SCENES / "fit_throw.toml"), "-o", str(out), "-q"]) == 0
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["loss_kind"] == "centroid" and report["initial_loss"] ** 0.5 > 0.5
    assert report["measured"]["distance_m"] < 0.02, report["measured"]
    # The forward run of the fitted scene (no tape, the cache's own frames) lands there too, at rest.
    cache = tmp_path / "throw.npz"
    cw.run_scene(out, output=cache)
    from cloth_warp.cache import CacheReader

    reader = CacheReader(cache)
    model = cw.scene.build_model(load_scene(out), "cpu")
    w = model.particle_mass.numpy() / model.particle_mass.numpy().sum()
    last, before = (reader.points(reader.start_frame + f) for f in (60, 55))
    assert np.linalg.norm(w @ last - target) < 0.02
    assert np.abs(last - before).max() < 1e-3  # still: landed, not sliding through the target


def test_vector_parameters_keep_unobservable_components(tmp_path):
    """A banner on a horizontal pole cannot feel wind along the pole (normal-only drag): its gradient is ~0 and
    the fit leaves it where it started instead of taking Adam's full-size steps from noise."""
    scene = load_scene(SCENES / "fit_flag.toml")
    target = tmp_path / "flag_target.npz"
    cw.run_scene(SCENES / "fit_flag.toml", {"forces.wind": [0.0, 1.0, 3.0]}, output=target, frames=12)
    fit = SceneFit(scene, target, None)
    result = fit.run(iterations=6, learning_rate=0.2)
    along, normal = result.final_values["forces.wind"][0], result.final_values["forces.wind"][1:]
    assert abs(along) < 0.02  # 6 steps of 0.2 x 1.5 m/s would move it up to 1.8 m/s
    assert normal[1] > 1.6 and result.final_loss < 0.5 * result.initial_loss


def test_chord_angle_loss_gradient_and_cantilever_target():
    """ChordAngleLoss against central differences (bend stiffness of the fit_cantilever strip, 8 steps), and the
    scene's [fit] table builds it: a too-soft strip droops below 41.5 deg, so d loss / d B < 0."""
    scene = load_scene(SCENES / "fit_cantilever.toml", {"cloth.grid.resolution": [11, 2], "cloth.grid.size": [0.055, 0.01],
                                                          "cloth.position": [-0.005, 0.0, 0.0]})
    fit = SceneFit(scene, None, None, frames=8)
    assert fit.loss_kind == "chord_angle" and [p.key for p in fit.parameters] == ["material.bend_stiffness"]
    value = [fit.parameters[0].value.copy()]
    _, grad = fit.loss_and_gradient(value)
    assert fit.last_measured["chord_angle_deg"] > 41.5 and grad[0][0] < 0.0
    eps = 0.02 * value[0]
    fd = (fit.loss_and_gradient([value[0] + eps])[0] - fit.loss_and_gradient([value[0] - eps])[0]) / (2 * eps[0])
    assert grad[0][0] == pytest.approx(fd, rel=1e-2)


def test_scene_fit_table_is_validated(tmp_path):
    from cloth_warp.scene import SceneError

    base = (SCENES / "fit_throw.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(base.replace("target = { centroid = [1.4, 0.0, 0.5] }", "target = { centroid = [1.4, 0.0, 0.5], chord_angle = 41.5 }"))
    with pytest.raises(SceneError, match="fit.target: give one of"):
        load_scene(bad)
    bad.write_text(base.replace("target = { centroid = [1.4, 0.0, 0.5] }", "target = { chord_angle = 41.5 }"))
    with pytest.raises(SceneError, match="fit.target.tip"):
        load_scene(bad)
    bad.write_text(base.replace('params = ["cloth.velocity"]', 'params = "cloth.velocity"'))
    with pytest.raises(SceneError, match="fit.params: expected an array of strings"):
        load_scene(bad)
    missing = load_scene(SCENES / "fit_flag.toml", {"fit.target.cache": "nowhere.usdc"})
    with pytest.raises(SceneError, match="simulate the target first"):
        SceneFit(missing)


def test_gradients_finite_through_the_drape_scene():
    """The shipped drape_sphere scene (12^2, ball, ground and self-collision on; as shipped, its collider contacts and
    self-contacts in the solve, which a taped step keeps, its self-contact elements held fixed) under the tape for half a
    second, until the cloth lies on the ball and its corners reach the ground: finite, non-zero scene-key gradients."""
    scene = load_scene(SCENES / "drape_sphere.toml", {"cloth.grid.resolution": [12, 12]})
    frames = 30
    fit = SceneFit(scene, lambda model: cw.CentroidLoss((0.1, 0.2, 0.0), frames * 2, model),
                   ["cloth.velocity", "colliders[0].friction", "colliders[1].friction", "material.bend_stiffness"], frames=frames)
    loss, grads = fit.loss_and_gradient([p.value.copy() for p in fit.parameters])
    counts = {k: v for r in fit.solver.read_pass_reports().values() for k, v in r.counters().items()}
    held = fit.solver.read_report()  # (the contacts the taped solves held; the passes' after them)
    assert counts["collider_contacts"] + held.contacts > 0 and counts["self_proximity"] + held.self_contacts > 0, (counts, held)
    assert np.isfinite(loss)
    for p, g in zip(fit.parameters, grads):
        assert np.isfinite(g).all() and np.abs(g).max() > 0.0, (p.key, g)
