"""Nothing lost: failed saves roll back to the last good one, outputs are checked before simulating, one live
run per output, SIGKILL then --resume gives the uninterrupted frames, and runs repeat bit for bit."""

import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import cloth_warp as cw
from cloth_warp.cache import CacheReader, UsdCacheWriter, open_cache, read_checkpoint
from cloth_warp.outputs import OutputBusy, OutputLock

ROOT = pathlib.Path(__file__).resolve().parents[1]
HANG = ROOT / "scenes" / "hanging_cloth.toml"
CLI = [sys.executable, "-m", "cloth_warp"]


def _model(n=6):
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(n, n), size=(1.0, 1.0), position=(0.0, 1.0, 0.0), name="sheet")
    return b.finalize("cpu")


def _frame(model, k):
    """A frame whose every value tells its index (so a test can see which frames a file holds)."""
    q = model.rest_positions.astype(np.float32) + np.float32(0.001 * k)
    return q, np.full_like(q, np.float32(k))


def _frames_in(path, model):
    """Frame count of a cache and a check that frame k holds what _frame(model, k) wrote."""
    reader = CacheReader(path)
    for k in range(reader.frame_count):
        np.testing.assert_array_equal(reader.points(reader.start_frame + k), _frame(model, k)[0])
    return reader.frame_count


# -- a save that fails at a random byte ------------------------------------------------------------------------

FAULT_CHILD = textwrap.dedent("""
    import resource, signal, sys
    sys.path.insert(0, {tests!r})
    from test_faults import _model, _frame
    from cloth_warp.cache import open_cache
    from cloth_warp.outputs import CacheWriteError
    model = _model(12)
    writer = open_cache({path!r}, model, fps=24, save_every=2)
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)            # writes past the limit fail with EFBIG instead
    resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
    try:
        for k in range(4096):  # until a save fails
            writer.write(*_frame(model, k))
    except CacheWriteError as exc:
        print("FAILED", writer.saved_frames, exc, flush=True)
    writer.close("failed")
""")


@pytest.mark.parametrize("suffix", [".usdc", ".usda", ".npz"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_failed_save_keeps_the_last_good_save(tmp_path, suffix, seed):
    """Check that a save failing at a random byte (the file-size limit stands in for a full disk: the write
    fails part way, as ENOSPC does) leaves under the final name a cache that opens and holds exactly the
    frames up to the last good save, and that the error names the file and the cause."""
    path = tmp_path / f"fault{suffix}"
    model = _model(12)
    limit = int(np.random.default_rng(seed).uniform(3, 300) * model.particle_count * 36)  # 3..300 frames of .usdc
    script = FAULT_CHILD.format(tests=str(ROOT / "tests"), path=str(path), limit=limit)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "FAILED" in out.stdout, out.stdout
    saved, message = out.stdout.split("FAILED", 1)[1].strip().split(" ", 1)
    assert str(tmp_path / "fault.partial-") in message and "File too large" in message, message
    assert path.exists() and not list(tmp_path.glob('fault.partial-*'))
    assert _frames_in(path, model) == int(saved) > 0


KILL_CHILD = textwrap.dedent("""
    import resource, signal, sys
    sys.path.insert(0, {tests!r})
    from test_faults import _model, _frame
    from cloth_warp.cache import open_cache
    model = _model(12)
    writer = open_cache({path!r}, model, fps=24, save_every=2)
    print("PARTIAL", writer.partial, flush=True)
    signal.signal(signal.SIGXFSZ, signal.SIG_DFL)  # Python ignores it
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))  # SIGXFSZ kills at the write that crosses it
    for k in range(4096):
        saved = writer.saved_frames
        writer.write(*_frame(model, k))
        if writer.saved_frames != saved:
            print("SAVED", writer.saved_frames, flush=True)
""")


@pytest.mark.parametrize("seed", range(4))
def test_killed_during_a_save_rolls_back_to_the_last_good_save(tmp_path, seed):
    """Check that a process killed at a random byte of a crate save (SIGXFSZ's default action at the file-size
    limit: no handler runs, as with SIGKILL or a power cut) leaves a partial file that --resume's recovery
    rolls back to exactly the frames of the last save that went through, and that a look at a rolled-back
    copy leaves the file as it is."""
    from cloth_warp.outputs import recover_partial

    path = tmp_path / "killed.usdc"
    model = _model(12)
    limit = int(np.random.default_rng(seed).uniform(3, 300) * model.particle_count * 36)
    script = KILL_CHILD.format(tests=str(ROOT / "tests"), path=str(path), limit=limit)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert out.returncode == -signal.SIGXFSZ, (out.returncode, out.stderr[-2000:])
    lines = out.stdout.split()
    partial = pathlib.Path(lines[lines.index("PARTIAL") + 1])
    saved = int(lines[len(lines) - 1 - lines[::-1].index("SAVED") + 1])
    assert partial.exists() and not path.exists()
    before, copy = partial.read_bytes(), tmp_path / "copy.usdc"
    assert recover_partial(partial, copy_to=copy) and partial.read_bytes() == before  # a look leaves it as it is
    assert _frames_in(copy, model) == saved
    assert recover_partial(partial)
    assert _frames_in(partial, model) == saved and saved >= 2
    assert not recover_partial(partial)  # the journal is gone


def test_writer_refuses_bad_values(tmp_path):
    """Check the cache writer refuses fps <= 0 and non-finite positions, naming them, and writes nothing."""
    model = _model()
    for fps in (0.0, -24.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="fps"):
            open_cache(tmp_path / "a.usdc", model, fps=fps)
    with UsdCacheWriter(tmp_path / "b.usdc", model, fps=24) as w:
        q, qd = _frame(model, 0)
        w.write(q, qd)
        q[3, 1] = np.nan
        with pytest.raises(ValueError, match="positions: non-finite"):
            w.write(q, qd)
        with pytest.raises(ValueError, match="velocities"):
            w.write(_frame(model, 1)[0], np.full_like(qd, np.inf))
    assert CacheReader(tmp_path / "b.usdc").frame_count == 1


# -- outputs checked before simulating ---------------------------------------------------------------------

def test_unwritable_outputs_fail_before_simulating(tmp_path, capsys):
    """Check that -o naming a folder, or a path under a file, exits 2 naming the problem before any frame."""
    from cloth_warp.cli import main

    (tmp_path / "folder.usdc").mkdir()
    (tmp_path / "afile").write_text("x")
    for out, why in ((tmp_path / "folder.usdc", "is a folder"), (tmp_path / "afile" / "x.usdc", "is a file")):
        assert main(["run", str(HANG), "--set", "cloth.grid.resolution=[4, 4]", "--frames", "2", "-o", str(out), "-q"]) == 2
        err = capsys.readouterr().err
        assert why in err and str(out) in err
    assert list(tmp_path.iterdir()) == [tmp_path / "afile", tmp_path / "folder.usdc"] or len(list(tmp_path.iterdir())) == 2


def test_cuda_without_a_driver_is_a_clear_error(tmp_path):
    """Check `--device cuda` on a machine without a CUDA driver exits 2 with one line saying so (Warp's own
    driver warnings and errors do not come first)."""
    import ctypes

    try:
        ctypes.CDLL("libcuda.so.1")
        pytest.skip("this machine has a CUDA driver")
    except OSError:
        pass
    r = subprocess.run(CLI + ["run", str(HANG), "--device", "cuda", "-o", str(tmp_path / "x.usdc")], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        "cloth-warp: error: --device cuda: no CUDA driver on this machine (libcuda.so.1 not found); use --device cpu"]


def test_no_room_for_the_first_frames_fails_before_simulating(tmp_path, monkeypatch, capsys):
    """Check a file system without room for the first saves exits 2 with the free and needed space, and leaves
    nothing behind."""
    import collections

    from cloth_warp.cli import main

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 50_000, 50_000))
    out = tmp_path / "x.usdc"
    assert main(["run", str(HANG), "--set", "cloth.grid.resolution=[32, 32]", "--frames", "2", "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert "MB free" in err and "first frames need about" in err and str(out) in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_folder_fails_before_simulating(tmp_path, capsys):
    """Check a read-only output folder exits 2 naming it."""
    from cloth_warp.cli import main

    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        assert main(["run", str(HANG), "--set", "cloth.grid.resolution=[4, 4]", "--frames", "2", "-o", str(ro / "x.usdc")]) == 2
        assert "not writable" in capsys.readouterr().err
    finally:
        ro.chmod(0o700)


def test_one_live_writer_per_output(tmp_path):
    """Check a second writer of the same output is refused while the first lives (it keeps its file), and
    that the lock of a process that died is free again."""
    model = _model()
    path = tmp_path / "x.usdc"
    with UsdCacheWriter(path, model, fps=24) as first:
        first.write(*_frame(model, 0))
        with pytest.raises(OutputBusy, match=f"pid {os.getpid()}"):
            UsdCacheWriter(path, model, fps=24)
        first.write(*_frame(model, 1))
    assert _frames_in(path, model) == 2
    child = subprocess.Popen([sys.executable, "-c", f"from cloth_warp.outputs import OutputLock; import time; "
                              f"OutputLock({str(path)!r}).acquire(); print('locked', flush=True); time.sleep(60)"],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "locked"
        with pytest.raises(OutputBusy):
            OutputLock(path).acquire()
    finally:
        child.kill()
        child.wait()
    OutputLock(path).acquire().release()  # the kernel dropped the dead process's lock


def _run(args, **kw):
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(CLI + args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, **kw)


def _wait_for(predicate, timeout=120.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError
        time.sleep(0.05)


def _catches_sigint(pid: int) -> bool:
    """Whether the command line's process `pid` has a SIGINT handler installed (Linux: /proc/PID/status's SigCgt
    mask, once /proc/PID/cmdline is the command's: between fork and exec the child still holds pytest's handler;
    elsewhere assumed once asked)."""
    try:
        if b"cloth_warp" not in pathlib.Path(f"/proc/{pid}/cmdline").read_bytes():
            return False
        text = pathlib.Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return not pathlib.Path("/proc/self").exists()
    except OSError:
        return True
    caught = next((line.split()[1] for line in text.splitlines() if line.startswith("SigCgt:")), None)
    return caught is None or bool(int(caught, 16) & (1 << (signal.SIGINT - 1)))


@pytest.mark.slow
def test_two_runs_on_one_output(tmp_path):
    """Check that a second `cloth-warp run` on an output a live run is writing exits 2 naming the other run,
    and that the first run's frames stay whole (stopped with Ctrl-C, its cache holds every frame it saved)."""
    out = tmp_path / "shared.usdc"
    args = ["run", str(HANG), "--set", "cloth.grid.resolution=[12, 12]", "--set", "output.save_every=2", "-o", str(out), "-q"]
    first = _run(args + ["--frames", "100000"])
    try:
        _wait_for(lambda: any(tmp_path.glob("shared.partial-*.usdc")) or first.poll() is not None)
        assert first.poll() is None, first.stderr.read()
        second = subprocess.run(CLI + args + ["--frames", "5"], capture_output=True, text=True, timeout=300)
        assert second.returncode == 2, second.stderr
        assert "another live run" in second.stderr and str(out) in second.stderr
        assert first.poll() is None  # the second run neither stopped the first nor touched its file
        first.send_signal(signal.SIGINT)
        assert first.wait(timeout=300) == 130, first.stderr.read()
    finally:
        first.kill()
    reader = CacheReader(out)
    assert reader.metadata["status"] == "interrupted" and reader.frame_count == reader.metadata["frames_written"] >= 3


def test_a_ctrl_c_while_the_command_line_loads_exits_130_without_a_traceback(monkeypatch, capsys):
    """Check the command (`python -m cloth_warp`, the `cloth-warp` script) interrupted while its modules load, before
    its handlers are in place, says so and exits 130: the interrupt raised by the import of cloth_warp.cli here. (It
    left a traceback and exit -2 in a full suite run on a loaded machine: test_ctrl_c_at_any_moment[0.3].)"""
    import builtins
    import importlib

    command_module = importlib.import_module("cloth_warp.__main__")
    real_import = builtins.__import__

    def interrupted(name, globals=None, locals=None, fromlist=(), level=0):
        if (name, level) in (("cli", 1), ("cloth_warp.cli", 0)):
            raise KeyboardInterrupt
        return real_import(name, globals, locals, fromlist, level)

    def leave(code):
        raise SystemExit(code)

    monkeypatch.setattr(builtins, "__import__", interrupted)
    monkeypatch.setattr(command_module.os, "_exit", leave)
    handler = signal.getsignal(signal.SIGINT)
    try:
        with pytest.raises(SystemExit) as leaving:
            command_module.command()
    finally:
        signal.signal(signal.SIGINT, handler)
    assert leaving.value.code == 130
    assert capsys.readouterr().err == "cloth-warp: interrupted\n"


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.3, 0.8, 1.2, 1.6, 4.0])
def test_ctrl_c_at_any_moment(tmp_path, delay):
    """Check SIGINT at any moment once the interpreter runs (while modules load, while kernels load, while
    simulating) exits 130 with no traceback, and that any cache left under the final name opens. (A SIGINT
    inside Python's own start-up, before it installs its handler or in its `site` module, is Python's to report:
    the delay counts from the handler's installation. Counted from the spawn, 0.3 s once fell before it on a loaded
    machine, and the process died of the signal, exit -2.)"""
    out = tmp_path / "c.usdc"
    proc = _run(["run", str(HANG), "--set", "cloth.grid.resolution=[16, 16]", "--set", "output.save_every=3",
                 "--frames", "5000", "-o", str(out)])
    _wait_for(lambda: proc.poll() is not None or _catches_sigint(proc.pid), timeout=60)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr, stderr
    if out.exists():
        assert np.isfinite(CacheReader(out).points(CacheReader(out).end_frame)).all()
    assert not list(tmp_path.glob("*.partial-*"))


def test_ctrl_c_while_a_frame_is_written_keeps_that_frame(tmp_path, monkeypatch):
    """Check a SIGINT that arrives while a frame's checkpoint is packed (inside numpy's zip writer, where a
    KeyboardInterrupt turned into "ValueError: Can't close the ZIP file" and exit 1): the frame is written whole, then
    the run stops as interrupted with a valid cache holding it."""
    import cloth_warp.cache as cache_module
    from cloth_warp.runner import run_scene

    pack = cache_module.pack_checkpoint
    calls = []

    def pack_interrupted(checkpoint):
        calls.append(1)
        if len(calls) == 3:  # the third save's checkpoint: the signal lands mid-write
            os.kill(os.getpid(), signal.SIGINT)
        return pack(checkpoint)

    monkeypatch.setattr(cache_module, "pack_checkpoint", pack_interrupted)
    out = tmp_path / "cut.usdc"
    with pytest.raises(KeyboardInterrupt) as info:
        run_scene(HANG, {"cloth.grid.resolution": [8, 8], "output.save_every": 2}, output=out, frames=40)
    assert info.value.summary["status"] == "interrupted"
    reader = CacheReader(out)
    assert reader.metadata["status"] == "interrupted" and reader.frame_count == info.value.summary["frames"] + 1
    assert reader.frame_count >= 4 and np.isfinite(reader.points(reader.end_frame)).all()


@pytest.mark.parametrize("where", ["first_save", "stage"])
def test_ctrl_c_while_a_writer_opens_leaves_no_partial_file(tmp_path, monkeypatch, where):
    """Check a KeyboardInterrupt inside a USD writer's construction (its first save, or while it defines the
    stage after the partial layer exists) drops the partial file and the lock instead of leaving them."""
    target = "_save_file" if where == "first_save" else "_write_collider_poses"

    def interrupted(self, *args):
        raise KeyboardInterrupt

    monkeypatch.setattr(UsdCacheWriter, target, interrupted)
    out = tmp_path / "w.usdc"
    with pytest.raises(KeyboardInterrupt):
        UsdCacheWriter(out, _model(), fps=24)
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    OutputLock(out).acquire().release()  # not held any more


def test_ctrl_c_between_the_writer_and_the_first_frame_leaves_no_partial_file(tmp_path, monkeypatch):
    """Check a SIGINT that lands while `run_scene` opens its cache (after the writer's partial file exists,
    before the frame loop) stops the run as interrupted with no file left, not a partial file."""
    import cloth_warp.cache as cache_module
    from cloth_warp.runner import run_scene

    opening = cache_module.open_cache

    def open_interrupted(*args, **kwargs):
        writer = opening(*args, **kwargs)
        assert list(tmp_path.glob("*.partial-*"))
        os.kill(os.getpid(), signal.SIGINT)
        return writer

    monkeypatch.setattr(cache_module, "open_cache", open_interrupted)
    out = tmp_path / "cut.usdc"
    with pytest.raises(KeyboardInterrupt) as info:
        run_scene(HANG, {"cloth.grid.resolution": [6, 6]}, output=out, frames=5)
    assert info.value.summary["status"] == "interrupted" and info.value.summary["frames"] == 0
    assert [p.name for p in tmp_path.iterdir() if not p.name.startswith(".")] == []


# -- resume and determinism ------------------------------------------------------------------------------------

def _cache_arrays(path):
    """Every frame's points and velocities of a cache (what must repeat bit for bit)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    out = []
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh) and "colliders" not in str(prim.GetPath()):
            mesh = UsdGeom.Mesh(prim)
            for tc in mesh.GetPointsAttr().GetTimeSamples():
                out.append(np.asarray(mesh.GetPointsAttr().Get(tc)))
                if mesh.GetVelocitiesAttr().HasAuthoredValue():
                    out.append(np.asarray(mesh.GetVelocitiesAttr().Get(tc)))
    return out


def _assert_same_frames(a, b):
    fa, fb = _cache_arrays(a), _cache_arrays(b)
    assert len(fa) == len(fb) and len(fa) > 2
    for x, y in zip(fa, fb):
        np.testing.assert_array_equal(x, y)


RESUME_CASES = {
    "implicit": (HANG, ["cloth.grid.resolution=[10, 10]"], 300),  # captured frames: long enough to be caught between saves
    "adaptive_explicit": (HANG, ["cloth.grid.resolution=[6, 6]", "solver.integrator='symplectic_euler'", "solver.substeps=16",
                                 "solver.adaptive=true"], 400),
    "self_collision": (ROOT / "scenes" / "pile.toml", ["cloth.grid.resolution=[10, 10]"], 150),  # captured: fast frames
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(RESUME_CASES))
def test_sigkill_then_resume_gives_the_uninterrupted_frames(tmp_path, case):
    """Check that a run killed with SIGKILL after some periodic saves, continued with --resume, gives a cache
    whose every frame equals (bit for bit) that of an uninterrupted run, and that --resume removes the
    killed run's partial file."""
    scene, sets, frames = RESUME_CASES[case]
    # on the CPU: bit for bit is its promise (CUDA's float atomics add in any order, benchmarks/bench_determinism.py);
    # without --device a GPU machine's runs would go to Warp's default device, cuda:0
    sets = [a for s in sets + ["output.save_every=4"] for a in ("--set", s)] + ["--device", "cpu"]
    whole, killed = tmp_path / "whole.usdc", tmp_path / "killed.usdc"
    ref = subprocess.run(CLI + ["run", str(scene), *sets, "--frames", str(frames), "-o", str(whole), "-q"],
                         capture_output=True, text=True, timeout=600)
    assert ref.returncode == 0, ref.stderr
    run = _run(["run", str(scene), *sets, "--frames", str(frames), "-o", str(killed), "-q"])
    try:
        def saved_enough():
            parts = list(tmp_path.glob("killed.partial-*.usdc"))
            try:
                return bool(parts) and read_checkpoint(parts[0])[0] >= 9
            except (ValueError, OSError):
                return False
        _wait_for(lambda: saved_enough() or run.poll() is not None, timeout=300)
        assert run.poll() is None, "the run ended before it could be killed"
        run.send_signal(signal.SIGKILL)
        run.wait()
    finally:
        run.kill()
    assert not killed.exists() and list(tmp_path.glob("killed.partial-*.usdc"))
    res = subprocess.run(CLI + ["run", str(scene), *sets, "--frames", str(frames), "-o", str(killed), "--resume", "-q"],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    assert not list(tmp_path.glob("killed.partial-*.usdc"))
    assert CacheReader(killed).metadata["status"] == "complete"
    _assert_same_frames(whole, killed)


def test_resume_refuses_what_it_cannot_continue(tmp_path, capsys):
    """Check --resume without an earlier cache, with other frames per second, another scene or fewer frames
    exits 2 saying why, and that a complete run can be extended."""
    from cloth_warp.cli import main

    out = tmp_path / "r.usdc"
    base = ["run", str(HANG), "--set", "cloth.grid.resolution=[4, 4]", "-o", str(out), "-q"]
    assert main(base + ["--frames", "3", "--resume"]) == 2
    assert "no cache of an earlier run" in capsys.readouterr().err
    assert main(base + ["--frames", "3"]) == 0
    assert main(base + ["--frames", "5", "--fps", "30", "--resume"]) == 2
    assert "fps" in capsys.readouterr().err
    assert main(base + ["--frames", "5", "--set", "material.areal_density=0.3", "--resume"]) == 2
    assert "material.areal_density" in capsys.readouterr().err
    assert main(base + ["--frames", "2", "--resume"]) == 2  # fewer frames than the cache holds
    assert "more than the 2 asked" in capsys.readouterr().err
    assert main(base + ["--frames", "6", "--resume"]) == 0  # a complete run extended by three frames
    assert CacheReader(out).frame_count == 7
    assert main(base + ["--frames", "8", "--resume", "--set", "output.save_every=2"]) == 0  # [output] keys may change
    assert CacheReader(out).frame_count == 9
    capsys.readouterr()
    assert main([a for a in base if a != "-q"] + ["--frames", "8", "--resume"]) == 0  # nothing left: a summary all the same
    assert "no new frame" in capsys.readouterr().out and CacheReader(out).frame_count == 9


@pytest.mark.slow
@pytest.mark.parametrize("name,sets", [("pile", ["cloth.grid.resolution=[12, 12]"]),
                                       ("drape_sphere", ["cloth.grid.resolution=[12, 12]"])])
def test_two_runs_give_bit_identical_caches(tmp_path, name, sets):
    """Check that a shipped scene (self-collision and colliders included) run twice on the CPU gives the same
    points and velocities in every frame, bit for bit."""
    sets = [a for s in sets for a in ("--set", s)] + ["--device", "cpu"]  # not Warp's default (cuda:0 on a GPU machine)
    paths = [tmp_path / f"{i}.usdc" for i in range(2)]
    for p in paths:
        r = subprocess.run(CLI + ["run", name, *sets, "--frames", "20", "-o", str(p), "-q"], capture_output=True, text=True,
                           timeout=600)
        assert r.returncode == 0, r.stderr
    _assert_same_frames(*paths)


# -- disk full on a real (small) file system -------------------------------------------------------------------

@pytest.fixture
def small_filesystem(tmp_path):
    """A 1 MiB tmpfs (needs root and mount permission; skipped with the reason otherwise)."""
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a small tmpfs needs root")
    mnt = tmp_path / "small"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


@pytest.mark.slow
@pytest.mark.parametrize("suffix", [".usdc", ".npz"])
def test_disk_full_keeps_the_last_good_save(small_filesystem, suffix):
    """Check that a run filling its disk exits 2 naming the file and 'No space left on device', and that the
    cache under the final name opens with the frames of the last good save (and --stats is valid JSON)."""
    out = small_filesystem / f"full{suffix}"
    stats = small_filesystem.parent / "stats.json"
    r = subprocess.run(CLI + ["run", str(HANG), "--set", "cloth.grid.resolution=[16, 16]", "--set", "output.save_every=5",
                              "--frames", "400", "-o", str(out), "--stats", str(stats), "-q"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 2, r.stderr
    assert "No space left on device" in r.stderr and str(out.stem) in r.stderr
    reader = CacheReader(out)
    summary = json.loads(stats.read_text())
    assert summary["status"] == "failed" and reader.frame_count == summary["frames_written"] >= 6
    assert np.isfinite(reader.points(reader.end_frame)).all()
    assert not list(small_filesystem.glob("*.partial-*"))


def test_signal_handlers_restored_when_closing_fails(tmp_path, monkeypatch):
    """Check run_scene hands SIGINT/SIGTERM back as it found them even when closing the cache raises something
    unexpected (they are held while the cache closes; a script going on after the error must still see Ctrl-C)."""
    from cloth_warp.runner import run_scene

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)

    def broken_close(self, *args, **kwargs):
        raise RuntimeError("injected")

    monkeypatch.setattr(UsdCacheWriter, "close", broken_close)
    with pytest.raises(RuntimeError, match="injected"):
        run_scene(HANG, {"cloth.grid.resolution": [4, 4]}, output=tmp_path / "x.usdc", frames=2)
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    OutputLock(tmp_path / "x.usdc").acquire().release()  # and the output's lock is free again
