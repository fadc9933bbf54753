"""Shipped scenes run and behave physically; the command line reports bad input with the key path."""

import pathlib
import subprocess
import sys

import numpy as np
import pytest

from cloth_warp.scene import SceneError, load_scene, run_scene

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = sorted((ROOT / "scenes").glob("*.toml"))


@pytest.mark.parametrize("path", SCENES, ids=lambda p: p.stem)
def test_shipped_scenes_validate(path):
    """Check every shipped scene passes validation."""
    load_scene(path)


def test_hanging_cloth_scene_runs(tmp_path):
    """Check the hanging-cloth scene falls from rest with its two corners fixed, within the strain limit."""
    out = tmp_path / "hang.npz"
    summary = run_scene(ROOT / "scenes" / "hanging_cloth.toml", {"cloth.grid.resolution": [16, 16]}, output=out, frames=6)
    assert summary["status"] == "done" and summary["frames"] == 6
    data = np.load(out)
    x = data["positions"]
    assert x.shape == (7, 17 * 17, 3)
    corners = [16 * 17, 16 * 17 + 16]  # grid row 16 = the pinned "top" corners
    np.testing.assert_allclose(x[-1, corners], x[0, corners])
    # The free far edge falls nearly freely at first: at least 80 % of g t^2 / 2 = 4.9 cm after 0.1 s.
    assert x[0, :, 1].min() - x[-1, :, 1].min() > 0.8 * 0.5 * 9.81 * 0.1**2
    assert summary["max_strain"] <= 0.101


def test_cantilever_scene_droops(tmp_path):
    """Check the cantilever scene keeps its clamp and its tip droops."""
    summary = run_scene(ROOT / "scenes" / "cantilever.toml", output=tmp_path / "c.npz", frames=10)
    x = np.load(tmp_path / "c.npz")["positions"]
    assert summary["status"] == "done"
    assert x[-1, :, 1].min() < -0.005  # the tip has dropped by more than 5 mm (rest: y = 0)
    clamped = x[0, :, 0] <= 1e-6
    np.testing.assert_allclose(x[-1, clamped], x[0, clamped])


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"cloth.gird": 1}, "unknown key 'cloth.gird' (did you mean 'grid'?)"),
        ({"solver.integrator": "verlet"}, "solver.integrator: 'verlet' is not allowed"),
        ({"solver.substeps": 0}, "solver.substeps: must be >= 1"),
        ({"material.preset": "velvet"}, "material.preset: unknown preset 'velvet'"),
        ({"material.areal_density": "heavy"}, "material.areal_density: expected a finite number"),
        ({"cloth.grid.resolution": [4]}, "cloth.grid.resolution"),
        ({"cloth.mesh": "missing.obj"}, "either cloth.grid or cloth.mesh"),
        ({"forces.up_axis": "X"}, "forces.up_axis"),
    ],
)
def test_scene_errors_name_the_key(overrides, message):
    """Check each kind of bad scene value raises a SceneError naming the key path and what is allowed."""
    with pytest.raises(SceneError) as info:
        load_scene(ROOT / "scenes" / "hanging_cloth.toml", overrides)
    assert message in str(info.value)


def test_toml_syntax_error_names_line(tmp_path):
    """Check a TOML syntax error reports its line and column."""
    bad = tmp_path / "bad.toml"
    bad.write_text("[cloth]\ngrid = { resolution = [8, 8] \n")
    with pytest.raises(SceneError, match="line 2"):
        load_scene(bad)


def test_command_line_exit_codes(tmp_path):
    """Check `python -m cloth_warp run` exits 0 with output written, and 2 on bad input with the key in the message."""
    scene = ROOT / "scenes" / "hanging_cloth.toml"
    out = tmp_path / "cli.npz"
    ok = subprocess.run([sys.executable, "-m", "cloth_warp", "run", str(scene), "--frames", "2", "-o", str(out),
                         "--set", "cloth.grid.resolution=[8, 8]", "--quiet"], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert "done: 2 frames" in ok.stdout and out.exists()
    bad = subprocess.run([sys.executable, "-m", "cloth_warp", "run", str(scene), "--set", "solver.substeps=0"],
                         capture_output=True, text=True)
    assert bad.returncode == 2
    assert "solver.substeps" in bad.stderr
