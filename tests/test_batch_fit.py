"""Batched fitting (issue 19: N targets fitted at once): each world's fit is its single fit, bit for bit on the CPU;
what a batch cannot fit per target is refused; the command line fits several targets in one batch."""

import json
import pathlib

import numpy as np
import pytest

import cloth_warp as cw
from cloth_warp.batch_fit import BatchFit
from cloth_warp.cli import main
from cloth_warp.fitting import SceneFit
from cloth_warp.scene import SceneError, load_scene

SCENES = pathlib.Path(__file__).resolve().parent.parent / "scenes"
COARSE = {"cloth.grid.resolution": [6, 7], "output.frames": 12}
# three targets: the fit_hanging cloth (which starts at 300 N/m, 0.04 s) simulated with other materials
TRUTHS = [{"material.stretch_stiffness": 150.0, "material.damping": 0.02},
          {"material.stretch_stiffness": 600.0, "material.damping": 0.08},
          {"material.stretch_stiffness": 120.0, "material.damping": 0.01}]
KEYS = ["material.stretch_stiffness", "material.damping"]


@pytest.fixture(scope="module")
def targets(tmp_path_factory):
    folder = tmp_path_factory.mktemp("batch_fit")
    out = []
    for k, truth in enumerate(TRUTHS):
        path = folder / f"target{k}.npz"
        cw.run_scene(SCENES / "fit_hanging.toml", {**COARSE, **truth}, output=path)
        out.append(path)
    return out


@pytest.mark.parametrize("checkpoint_every", [None, 5])
def test_each_world_of_a_batched_fit_is_its_single_fit(targets, checkpoint_every):
    """Three targets fitted at once give each target exactly what its own SceneFit gives: the same loss at every
    iteration, the same values, the same best values, bit for bit (the batch's rollout gives every world its own run's
    gradient and loss, also over checkpointed segments; each world's Adam is its own)."""
    scene = load_scene(SCENES / "fit_hanging.toml", COARSE)
    batch = BatchFit(scene, targets, KEYS, checkpoint_every=checkpoint_every)
    assert batch.model.world_count == 3
    assert batch.rollout.segment == (5 if checkpoint_every else batch.rollout.steps)
    results = batch.run(iterations=3, learning_rate=0.1)
    for k, (path, result) in enumerate(zip(targets, results)):
        single = SceneFit(scene, path, KEYS, checkpoint_every=checkpoint_every).run(iterations=3, learning_rate=0.1)
        assert result.status == single.status == "complete"
        assert result.losses == single.losses, f"world {k}"
        assert result.values == single.values, f"world {k}"
        assert result.final_values == single.final_values and result.final_loss == single.final_loss
        assert result.final_loss < result.initial_loss
    # the worlds moved apart: each towards its own target
    stiffness = [r.final_values["material.stretch_stiffness"] for r in results]
    assert stiffness[1] > 300.0 > stiffness[0] and 300.0 > stiffness[2]


def test_a_batched_fit_refuses_what_the_worlds_share_or_cannot_batch(targets, tmp_path):
    scene = load_scene(SCENES / "fit_hanging.toml", COARSE)
    with pytest.raises(SceneError, match=r"--param forces.wind: the worlds of a batch share it"):
        BatchFit(scene, targets, ["forces.wind"])
    with pytest.raises(SceneError, match="loss: 'chamfer' is not batched"):
        BatchFit(scene, targets, KEYS, loss="chamfer")
    longer = tmp_path / "longer.npz"
    cw.run_scene(SCENES / "fit_hanging.toml", {**COARSE, **TRUTHS[0], "output.frames": 16}, output=longer)
    with pytest.raises(SceneError, match="the targets have 12 to 16 frames; give --frames N"):
        BatchFit(scene, [targets[0], longer], KEYS)
    assert BatchFit(scene, [targets[0], longer], KEYS, frames=12).frames == 12


def test_fit_command_fits_several_targets_in_one_batch(targets, tmp_path, capsys):
    """`cloth-warp fit SCENE --target A --target B -o X.toml` writes X_A.toml, X_B.toml (each with its JSON report and
    loss curve) and summarises every target."""
    scene = tmp_path / "scene.toml"
    scene.write_text((SCENES / "fit_hanging.toml").read_text() + "\n")  # (relative to a copy: the outputs beside it)
    out = tmp_path / "fitted.toml"
    args = ["fit", str(scene), "--param", "material.stretch_stiffness", "--iters", "2", "-o", str(out)]
    for key, value in COARSE.items():
        args += ["--set", f"{key}={json.dumps(value)}"]
    for path in targets[:2]:
        args += ["--target", str(path)]
    assert main(args) == 0
    captured = capsys.readouterr()
    assert "2 targets in one batch" in captured.err
    for path in targets[:2]:
        fitted = tmp_path / f"fitted_{path.stem}.toml"
        report = json.loads(fitted.with_suffix(".json").read_text())
        assert report["status"] == "complete" and report["iterations"] == 2
        assert fitted.with_name(fitted.stem + "_loss.png").is_file()
        assert load_scene(fitted).get("material.stretch_stiffness") == pytest.approx(report["final_values"]["material.stretch_stiffness"])
        assert str(fitted) in captured.out


def test_a_world_whose_gradient_is_not_finite_fails_alone(targets, monkeypatch):
    """A world whose gradient turns non-finite (here world 1's, made NaN at the second evaluation) stops fitting:
    its result is ``failed`` with the message and its best values so far, while the other worlds go on, each still
    equal to its single fit bit for bit."""
    scene = load_scene(SCENES / "fit_hanging.toml", COARSE)
    batch = BatchFit(scene, targets, KEYS)
    original = batch.loss_and_gradient
    evaluations = []

    def corrupted(values):
        losses, grads = original(values)
        evaluations.append(len(evaluations))
        if len(evaluations) == 2:
            grads[1] = [np.full_like(np.asarray(g, np.float64), np.nan) for g in grads[1]]
        return losses, grads

    monkeypatch.setattr(batch, "loss_and_gradient", corrupted)
    results = batch.run(iterations=3, learning_rate=0.1)
    assert [r.status for r in results] == ["complete", "failed", "complete"]
    assert "non-finite gradient" in results[1].measured["failure"]
    best = int(np.argmin(results[1].losses))  # its best of the two losses it saw (the second's values, the loss finite)
    assert len(results[1].losses) == 2 and results[1].final_values == results[1].values[best]
    for k in (0, 2):
        single = SceneFit(scene, targets[k], KEYS).run(iterations=3, learning_rate=0.1)
        assert results[k].losses == single.losses and results[k].final_values == single.final_values, f"world {k}"
