"""`cloth-warp sweep`: scene variants as `cloth-warp run` processes on a Dask cluster, with a manifest that makes the sweep
resumable, failures recorded by exit class and retried once, and a results table."""

import csv
import json
import os
import pathlib
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from cloth_warp.sweep import Sweep, SweepError, exit_class, parse_params, run_sweep, split_values

distributed = pytest.importorskip("distributed")

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_params_split_at_top_level_commas_and_runs_are_the_product():
    """Check --param parsing (TOML values, bare strings, lists whose commas belong to them) and the runs: the product of
    the swept values and the seeds, the last varying fastest, ids in that order; the exit classes of run's codes."""
    assert split_values("[32,32],[64, 64]") == ["[32,32]", "[64, 64]"]
    assert split_values('"a,b",c') == ['"a,b"', "c"]
    params = parse_params(["material.preset=cotton,silk", "cloth.grid.resolution=[8,8],[12,12]"])
    assert params == {"material.preset": ["cotton", "silk"], "cloth.grid.resolution": [[8, 8], [12, 12]]}
    runs = Sweep("catenary", params, seeds=2).runs()
    assert [r.id for r in runs] == [f"run-{i:04d}" for i in range(8)]
    assert runs[0].values == {"material.preset": "cotton", "cloth.grid.resolution": [8, 8], "scene.seed": 0}
    assert runs[1].values["scene.seed"] == 1 and runs[2].values["cloth.grid.resolution"] == [12, 12]
    assert runs[7].values == {"material.preset": "silk", "cloth.grid.resolution": [12, 12], "scene.seed": 1}
    for bad in (["material.preset"], ["material.preset="], ["a=1", "a=2"]):
        with pytest.raises(SweepError):
            parse_params(bad)
    with pytest.raises(SweepError, match="material.bogus"):
        Sweep("catenary", parse_params(["material.bogus=1,2"])).validate()
    assert [exit_class(c) for c in (0, 2, 3, 130, -9, 1)] == ["ok", "bad_input", "diverged", "interrupted", "killed", "error"]


def _saved_frames(partials) -> int:
    """Frames (the initial state counts as one) in the first readable one of a run's partial caches; 0 if none is readable."""
    from cloth_warp.cache import CacheReader

    for path in partials:
        try:
            r = CacheReader(path)
            return r.end_frame - r.start_frame + 1
        except Exception:
            continue
    return 0


def _frames(cache):
    from cloth_warp.cache import CacheReader

    r = CacheReader(cache)
    return np.stack([r.points(f) for f in range(r.start_frame, r.end_frame + 1)])


def test_a_sweep_on_a_local_cluster_gives_the_runs_of_the_command_line(tmp_path):
    """Check a sweep on a Dask cluster the test starts (two worker processes, reached by its address): every run done
    once, the manifest and the table say so with each run's swept values and summary numbers, each cache equals a
    `cloth-warp run` of that variant bit for bit, and a second start skips every run."""
    from distributed import LocalCluster

    sweep = Sweep("catenary", parse_params(["material.preset=cotton,silk"]), seeds=2, frames=4)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        report = run_sweep(sweep, tmp_path / "sw", address=cluster.scheduler_address)
        assert report.complete and report.done == 4 and report.skipped == 0
        again = run_sweep(sweep, tmp_path / "sw", address=cluster.scheduler_address)
    assert again.done == 0 and again.skipped == 4
    manifest = json.loads((tmp_path / "sw" / "manifest.json").read_text())
    assert all(e["status"] == "done" and e["attempts"] == 1 and e["exit_class"] == "ok" for e in manifest["runs"].values())
    rows = list(csv.DictReader(open(tmp_path / "sw" / "results.csv")))
    assert [r["run"] for r in rows] == ["run-0000", "run-0001", "run-0002", "run-0003"]
    assert [(r["material.preset"], r["scene.seed"]) for r in rows] == [("cotton", "0"), ("cotton", "1"), ("silk", "0"), ("silk", "1")]
    assert all(r["status"] == "done" and int(r["frames"]) == 4 and float(r["ms_per_frame"]) > 0 for r in rows)
    direct = tmp_path / "direct.usdc"
    subprocess.run([sys.executable, "-m", "cloth_warp", "run", "catenary", "--set", "material.preset=silk", "--set", "scene.seed=1",
                    "--frames", "4", "-o", str(direct), "-q"], check=True)
    np.testing.assert_array_equal(_frames(tmp_path / "sw" / rows[3]["cache"]), _frames(direct))


def _processes(pattern: str, command: str = "cloth_warp run") -> list[int]:
    """Pids of this machine's processes whose command line contains `pattern` and `command`."""
    out = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                cmd = pathlib.Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
            except OSError:
                continue
            if pattern in cmd and command in cmd:
                out.append(int(pid))
    return out


def _wait_for(predicate, timeout=120.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        found = predicate()
        if found:
            return found
        time.sleep(0.05)
    raise AssertionError("timed out")


def _stopped_once(folder, command: str, saved, timeout=120.0) -> list[int]:
    """Pids of the processes running `command` into `folder`, left stopped (SIGSTOP) at the first look at which
    `saved()` holds. Each look is taken with them stopped, so it reads no file while it is written and the run
    cannot end between the look and the kill (a short run on a busy machine did, and no look ever found it)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        pids = _processes(str(folder), command)
        stopped = [pid for pid in pids if _signal(pid, signal.SIGSTOP)]
        if stopped and saved():
            return stopped
        for pid in stopped:
            _signal(pid, signal.SIGCONT)
        time.sleep(0.02)
    raise AssertionError("timed out")


def _signal(pid: int, sig) -> bool:
    """Send `sig` to `pid`; False if the process has ended."""
    try:
        os.kill(pid, sig)
        return True
    except ProcessLookupError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the run's process in /proc")
def test_a_killed_run_is_retried_once_from_its_saved_frames(tmp_path):
    """Check a run whose process is killed (SIGKILL, as the memory killer would) once it has saved frames: the manifest
    records the kill, the run is retried once, continuing its cache (--resume), and ends done after two attempts with
    every frame; the other run is untouched (one attempt)."""
    out = tmp_path / "sw"
    frames = 400
    sweep = Sweep("hanging_cloth", parse_params(["material.preset=cotton,silk"]), overrides={"cloth.grid.resolution": [24, 24]},
                  frames=frames)
    seen = []
    done = threading.Event()
    thread = threading.Thread(target=lambda: (seen.append(run_sweep(sweep, out, workers=1)), done.set()))
    thread.start()
    partial = out / "runs" / "run-0000"
    from cloth_warp.runner import can_resume

    pids = _stopped_once(partial, "cloth_warp run", lambda: can_resume(partial / "cache.usdc"))  # frames saved
    for pid in pids:
        os.kill(pid, signal.SIGKILL)
    thread.join(timeout=300)
    assert done.is_set()
    report = seen[0]
    assert report.complete and report.done == 2
    runs = json.loads((out / "manifest.json").read_text())["runs"]
    assert runs["run-0000"]["attempts"] == 2 and runs["run-0000"]["status"] == "done"
    assert runs["run-0001"]["attempts"] == 1
    log = (partial / "log.txt").read_text()
    assert "# attempt 2" in log and "--resume" in log.split("# attempt 2")[1]
    assert len(_frames(partial / "cache.usdc")) == frames + 1  # the initial state and every frame
    summary = json.loads((partial / "summary.json").read_text())
    assert summary["resumed_frames"] > 0


def test_an_interrupted_sweep_continues_where_it_stopped(tmp_path):
    """Check `cloth-warp sweep` stopped by SIGINT after its first run is done: it exits 130 with the manifest written;
    started again it skips the done run (its cache untouched), finishes the others and exits 0."""
    out = tmp_path / "sw"
    cmd = [sys.executable, "-m", "cloth_warp", "sweep", "hanging_cloth", "--param", "material.preset=cotton,silk,wool",
           "--set", "cloth.grid.resolution=[16,16]", "--frames", "30", "--workers", "1", "-o", str(out), "-q"]
    p = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    manifest = out / "manifest.json"

    def one_done():
        if not manifest.exists():
            return False
        runs = json.loads(manifest.read_text())["runs"]
        return sum(e["status"] == "done" for e in runs.values()) >= 1 and sum(e["status"] == "done" for e in runs.values()) < 3

    _wait_for(one_done)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    runs = json.loads(manifest.read_text())["runs"]
    finished = [rid for rid, e in runs.items() if e["status"] == "done"]
    assert 1 <= len(finished) < 3
    stamps = {rid: (out / "runs" / rid / "cache.usdc").stat().st_mtime_ns for rid in finished}
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert f"{len(finished)} done before" in again.stdout
    runs = json.loads(manifest.read_text())["runs"]
    assert all(e["status"] == "done" for e in runs.values())
    assert {rid: (out / "runs" / rid / "cache.usdc").stat().st_mtime_ns for rid in finished} == stamps
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert [r["status"] for r in rows] == ["done"] * 3


def test_a_batched_sweep_gives_the_runs_of_the_command_line(tmp_path):
    """Check `--batch 3` steps the variants as batched worlds, three runs a process: every run done once, each table
    row with its world's own numbers, every cache equal bit for bit to a `cloth-warp run` of its variant (one per batch
    checked, the last world of the second), and a sweeping of a key the worlds share refused before anything runs."""
    from distributed import LocalCluster

    sweep = Sweep("catenary", parse_params(["material.preset=cotton,silk,denim"]), seeds=2, frames=4, batch=3)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        report = run_sweep(sweep, tmp_path / "sw", address=cluster.scheduler_address)
    assert report.complete and report.done == 6
    rows = list(csv.DictReader(open(tmp_path / "sw" / "results.csv")))
    assert all(r["status"] == "done" and r["attempts"] == "1" and int(r["frames"]) == 4 and int(r["particles"]) > 0 for r in rows)
    summaries = [json.loads((tmp_path / "sw" / "runs" / r["run"] / "summary.json").read_text()) for r in rows]
    assert [s["batch"] for s in summaries] == [{"world": k % 3, "worlds": 3} for k in range(6)]
    assert len({float(r["max_strain"]) for r in rows}) > 1  # each world's own
    for k, (preset, seed) in ((0, ("cotton", 0)), (5, ("denim", 1))):
        direct = tmp_path / f"direct{k}.usdc"
        subprocess.run([sys.executable, "-m", "cloth_warp", "run", "catenary", "--set", f"material.preset={preset}",
                        "--set", f"scene.seed={seed}", "--frames", "4", "-o", str(direct), "-q"], check=True)
        np.testing.assert_array_equal(_frames(tmp_path / "sw" / rows[k]["cache"]), _frames(direct))
    shared = Sweep("catenary", parse_params(["solver.substeps=1,2"]), frames=4, batch=2)
    with pytest.raises(SweepError, match="--batch: world 1: solver differs"):
        run_sweep(shared, tmp_path / "refused", workers=1)
    assert not (tmp_path / "refused").exists()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the batch's process in /proc")
def test_a_killed_batch_is_run_again_whole(tmp_path):
    """Check a batch whose process is killed (SIGKILL) once it has saved frames: both of its runs are recorded killed
    and retried once as a batch again (from the start: a batch does not resume), and end done after two attempts with
    every frame in their caches."""
    out = tmp_path / "sw"
    frames = 300
    sweep = Sweep("hanging_cloth", parse_params(["material.preset=cotton,silk"]), overrides={"cloth.grid.resolution": [24, 24]},
                  frames=frames, batch=2)
    seen = []
    done = threading.Event()
    thread = threading.Thread(target=lambda: (seen.append(run_sweep(sweep, out, workers=1)), done.set()))
    thread.start()
    first = out / "runs" / "run-0000"
    pids = _stopped_once(first, "cloth_warp.sweep", lambda: _saved_frames(first.glob("cache.partial-*")) > 1)
    for pid in pids:
        os.kill(pid, signal.SIGKILL)
    thread.join(timeout=300)
    assert done.is_set()
    assert seen[0].complete and seen[0].done == 2
    runs = json.loads((out / "manifest.json").read_text())["runs"]
    assert all(e["attempts"] == 2 and e["status"] == "done" for e in runs.values()), runs
    assert "# attempt 2 of the batch run-0000, run-0001" in (first / "log.txt").read_text()
    for rid in runs:
        assert len(_frames(out / "runs" / rid / "cache.usdc")) == frames + 1
        assert not list((out / "runs" / rid).glob("cache.partial-*"))  # the killed attempt's partial files removed
