"""The cloth-warp command line: subcommands, --set, --stats, exit codes 0/2/3/130, previews."""

import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from cloth_warp import __version__
from cloth_warp.cache import CacheReader
from cloth_warp.cli import main

ROOT = pathlib.Path(__file__).resolve().parents[1]
HANG = str(ROOT / "scenes" / "hanging_cloth.toml")
SMALL = ["--set", "cloth.grid.resolution=[8, 8]"]


def test_version_and_scenes(capsys):
    """Check --version and the list of shipped scenes (one line each, with the description)."""
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out.strip() == f"cloth-warp {__version__}"
    assert main(["scenes"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    names = {line.split()[0] for line in lines}
    assert {"flag", "curtain", "garment", "catenary", "cantilever", "hanging_cloth"} <= names
    assert all(len(line.split(maxsplit=1)) == 2 for line in lines)


def test_validate(capsys):
    """Check validate reports a good scene (by shipped name) and exits 2 naming the key of a bad one."""
    assert main(["validate", "flag"]) == 0
    out = capsys.readouterr().out
    assert "valid" in out and "925 particles" in out
    assert main(["validate", "flag", "--set", "solver.integrator=verlet"]) == 2
    assert "solver.integrator: 'verlet' is not allowed" in capsys.readouterr().err


def test_run_with_set_and_stats(tmp_path, capsys):
    """Check run exits 0, applies --set, writes the cache and a JSON summary, and prints the summary."""
    out, stats = tmp_path / "run.usdc", tmp_path / "stats.json"
    code = main(["run", HANG, "-o", str(out), "--frames", "3", "--fps", "30", "--stats", str(stats), *SMALL,
                 "--set", "material.preset=silk"])
    assert code == 0
    summary = json.loads(stats.read_text())
    assert summary["status"] == "complete" and summary["frames"] == 3 and summary["particles"] == 81
    assert summary["fps"] == 30.0 and summary["dt_min"] == pytest.approx(1 / 30)
    assert summary["compile_s"] >= 0.0 and summary["ms_per_frame"] > 0.0 and summary["solver_iterations"]["max"] > 0
    reader = CacheReader(out)
    assert reader.frame_count == 4 and reader.fps == 30.0
    assert "silk" in reader.metadata["resolved_scene"]
    printed = capsys.readouterr().out
    assert "complete: 3/3 frames of 81 particles" in printed and "max strain" in printed and str(out) in printed


def test_bad_input_exits_2(tmp_path, capsys):
    """Check a bad --set value, a malformed --set, a missing scene and a bad output extension all exit 2."""
    for args, message in (
        (["--set", "solver.substeps=0"], "solver.substeps: must be >= 1"),
        (["--set", "nonsense"], "--set expects key.path=value"),
        (["-o", str(tmp_path / "x.abc")], "unknown extension"),
        (["--device", "tpu"], "device: Invalid device identifier"),
    ):
        assert main(["run", HANG, "--frames", "1", *args]) == 2
        assert message in capsys.readouterr().err
    assert main(["run", str(tmp_path / "nope.toml")]) == 2
    assert "scene file not found" in capsys.readouterr().err


def test_diverged_run_exits_3(tmp_path, capsys):
    """Check a diverging run exits 3, says where and why, and keeps the good frames."""
    out = tmp_path / "boom.usdc"
    code = main(["run", HANG, "-o", str(out), "--frames", "40", "--quiet", *SMALL, "--set", "solver.integrator=explicit_euler",
                 "--set", "solver.strain_limit=0", "--set", "material.preset=denim"])
    assert code == 3
    err = capsys.readouterr().err
    assert "diverged in frame" in err and "try" in err
    assert CacheReader(out).metadata["status"] == "diverged"


def test_info(tmp_path, capsys):
    """Check info names frames, fps, status, the mesh, diagnostics and the scene; --json is parseable."""
    out = tmp_path / "i.usdc"
    assert main(["run", HANG, "-o", str(out), "--frames", "2", "--quiet", *SMALL]) == 0
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    for expected in ("frames      3 (1..3) at 60 fps, up axis Y", "status      complete", "/World/cloth: 81 points, 128 triangles",
                     "maxStrain", "hanging_cloth.toml", "cloth_warp 0.1.0"):
        assert expected in text
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 3 and info["meshes"][0]["uv"] is True
    assert main(["info", str(tmp_path / "missing.usdc")]) == 2


def test_preview_png_and_gif(tmp_path):
    """Check preview renders a shaded still (cloth colour present, not a flat image) and an animated GIF."""
    from PIL import Image

    out = tmp_path / "p.usdc"
    assert main(["run", HANG, "-o", str(out), "--frames", "4", "--quiet", *SMALL, "--set", 'material.preset="silk"']) == 0
    png, gif = tmp_path / "p.png", tmp_path / "p.gif"
    assert main(["preview", str(out), "-o", str(png), "--size", "96", "64"]) == 0
    img = np.asarray(Image.open(png).convert("RGB")).astype(int)
    assert img.shape == (64, 96, 3)
    cloth = (img[:, :, 0] > img[:, :, 2] + 15)  # the front side, in silk's dusty rose (the ground is grey, the sky blue)
    assert 0.02 < cloth.mean() < 0.9
    assert len(np.unique(img[cloth].sum(axis=1))) > 5  # shaded, not one flat colour
    assert main(["preview", str(out), "-o", str(gif), "--size", "64", "64", "--every", "2"]) == 0
    with Image.open(gif) as anim:
        assert anim.n_frames == 3  # frames 1, 3, 5 of 5
    assert main(["preview", str(out), "-o", str(tmp_path / "p.jpg")]) == 2


def test_preview_draws_each_cloth_in_its_fabric_colour(tmp_path):
    """Check the preview shades a cloth in the colour its cache binds to its fabric (displayColor): in linear RGB a lit
    pixel is albedo x light + a grey rim, so (R - G) / (R - B) is the albedo's own ratio; silk's and cotton's differ."""
    from PIL import Image

    from cloth_warp.looks import fabric_color

    for preset in ("silk", "cotton"):
        out, png = tmp_path / f"{preset}.usdc", tmp_path / f"{preset}.png"
        assert main(["run", HANG, "-o", str(out), "--frames", "2", "--quiet", *SMALL, "--set", f'material.preset="{preset}"']) == 0
        assert main(["preview", str(out), "-o", str(png), "--size", "192", "128"]) == 0
        linear = (np.asarray(Image.open(png).convert("RGB")) / 255.0) ** 2.2
        r, g, b = linear[..., 0], linear[..., 1], linear[..., 2]
        albedo = fabric_color(preset)
        want = (albedo[0] - albedo[1]) / (albedo[0] - albedo[2])
        cloth = r - b > 0.03  # warm: not the grey ground or the blue sky
        assert cloth.mean() > 0.02, preset
        assert np.median((r - g)[cloth] / (r - b)[cloth]) == pytest.approx(want, abs=0.15), preset


def test_python_m_and_console_script_agree():
    """Check `python -m cloth_warp` and the installed `cloth-warp` script are the same command."""
    a = subprocess.run([sys.executable, "-m", "cloth_warp", "--version"], capture_output=True, text=True)
    assert a.returncode == 0 and a.stdout.strip() == f"cloth-warp {__version__}"
    exe = shutil.which("cloth-warp")
    if exe is None:
        pytest.skip("cloth-warp is not on PATH (pip install -e .)")
    b = subprocess.run([exe, "--version"], capture_output=True, text=True)
    assert b.stdout == a.stdout


@pytest.mark.slow
def test_ctrl_c_leaves_a_valid_cache(tmp_path):
    """Check SIGINT to a running `cloth-warp run` exits 130 and leaves a cache that opens and holds the frames done."""
    out = tmp_path / "sigint.usdc"
    proc = subprocess.Popen([sys.executable, "-m", "cloth_warp", "run", HANG, "-o", str(out), "--frames", "100000",
                             "--set", "cloth.grid.resolution=[16, 16]", "--set", "output.save_every=5"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        deadline = time.monotonic() + 120
        while not list(tmp_path.glob('sigint.partial-*')) and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(2.0)  # let it simulate some frames
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 130, stderr
    assert "interrupted" in stderr
    reader = CacheReader(out)
    assert reader.metadata["status"] == "interrupted" and reader.frame_count >= 2
    assert reader.metadata["frames_written"] == reader.frame_count
    assert np.isfinite(reader.points(reader.end_frame)).all()
    assert not list(tmp_path.glob('sigint.partial-*'))
