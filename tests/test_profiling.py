"""cloth_warp.profiling: LaunchCounter counts eager and captured Warp work, StageTimer times nested stages, run --profile."""

import json
import pathlib
import time

import numpy as np
import warp as wp

from cloth_warp import profiling
from cloth_warp.cli import main
from cloth_warp.kernels import constraints
from cloth_warp.profiling import LaunchCounter, StageTimer

ROOT = pathlib.Path(__file__).resolve().parents[1]
HANG = str(ROOT / "scenes" / "hanging_cloth.toml")
SMALL = ["--set", "cloth.grid.resolution=[8, 8]"]


def test_launch_counter_counts_eager_captured_and_reads():
    """Check a known sequence of launches, copies, fills, replays, reads and allocations is counted exactly, that work
    recorded during a graph capture counts as captured (not eager), that counters nest, and that Warp is restored."""
    a = wp.zeros(2, dtype=float, device="cpu")
    b = wp.zeros(2, dtype=float, device="cpu")
    wp.load_module(constraints, device="cpu")
    originals = (wp.launch, wp.copy, wp.array.numpy, wp.array.zero_)
    with LaunchCounter() as outer:
        with LaunchCounter() as counts:
            for _ in range(3):
                wp.launch(constraints.reset_strain_excess, dim=1, outputs=[a], device="cpu")
            wp.copy(b, a)
            b.assign(a)  # calls wp.copy inside: one copy, not two
            a.zero_()
            a.fill_(2.0)
            a.numpy()
            a.list()  # calls numpy() inside: one read
            with wp.ScopedCapture(device="cpu") as capture:
                wp.launch(constraints.reset_strain_excess, dim=1, outputs=[a], device="cpu")
                wp.copy(b, a)
            for _ in range(2):
                wp.capture_launch(capture.graph)
            c = wp.zeros(4, dtype=float, device="cpu")
        wp.launch(constraints.reset_strain_excess, dim=1, outputs=[c], device="cpu")
    assert (counts.launches, counts.copies, counts.fills, counts.replays, counts.reads) == (3, 2, 2, 2, 2)
    assert (counts.captured, counts.allocations, counts.loops, counts.eager) == (2, 1, 0, 7)
    assert counts.kernels == {"constraints.reset_strain_excess": 3}
    assert outer.launches == 4 and outer.replays == 2  # the outer counter saw everything, the last launch too
    assert (wp.launch, wp.copy, wp.array.numpy, wp.array.zero_) == originals
    np.testing.assert_array_equal(b.numpy(), a.numpy())  # the replays ran the captured launch and copy
    assert a.numpy()[0] != 2.0
    totals = counts + outer
    assert totals.launches == 7 and totals.to_dict()["kernels"]["constraints.reset_strain_excess"] == 7


def test_stage_timer_nested_and_disabled():
    """Check nested stages accumulate calls and time under "outer/inner" names, a stage inside a graph capture is not
    timed, and a disabled timer (the module default until enable()) is a shared no-op."""
    timer = StageTimer(enabled=True, device="cpu")
    for _ in range(2):
        with timer.stage("step"):
            with timer.stage("collide"):
                time.sleep(0.01)
            with timer.stage("integrate"):
                pass
    with wp.ScopedCapture(device="cpu"):
        with timer.stage("captured"):
            pass
    report = timer.report(frames=2)
    stats = {s.name: s for s in report.stages}
    assert list(stats) == ["step", "step/collide", "step/integrate"]
    assert all(s.calls == 2 for s in stats.values())
    assert stats["step/collide"].total_s >= 0.02 and stats["step"].total_s >= stats["step/collide"].total_s
    assert "step/collide" in report.table() and "ms/frame" in report.table()
    plain = report.table(markdown=False)
    assert "\n  collide " in plain
    assert profiling.StageReport.from_dict(json.loads(json.dumps(report.to_dict()))) == report

    off = StageTimer()
    assert off.stage("a") is off.stage("b")  # the same null context: nothing allocated, nothing timed
    with off.stage("a"):
        pass
    assert off.report().stages == []
    assert not profiling.enabled()
    t = time.perf_counter()
    for _ in range(10000):
        with profiling.stage("x"):
            pass
    assert time.perf_counter() - t < 0.5  # ~0.2 us per disabled stage
    assert profiling.report().stages == []
    inner = profiling.timed("inner")(lambda: 7)
    assert inner() == 7 and profiling.report().stages == []
    try:
        profiling.enable("cpu")
        with profiling.stage("outer"):
            assert inner() == 7
        assert [(s.name, s.calls) for s in profiling.report().stages] == [("outer", 1), ("outer/inner", 1)]
    finally:
        profiling.disable()
        profiling.reset()


def test_run_profile_writes_stage_table(tmp_path, capsys):
    """Check `cloth-warp run --profile --stats` prints the stage table and writes it under "profile"."""
    out, stats = tmp_path / "run.usdc", tmp_path / "stats.json"
    assert main(["run", HANG, "-o", str(out), "--frames", "2", "--profile", "--stats", str(stats), *SMALL]) == 0
    profile = json.loads(stats.read_text())["profile"]
    assert profile["frames"] == 2
    stages = {s["name"]: s for s in profile["stages"]}
    assert stages["frame"]["calls"] == 2 and stages["cache"]["calls"] == 2 and stages["frame"]["total_s"] > 0.0
    printed = capsys.readouterr().out
    assert "profile" in printed and "frame" in printed and "ms/call" in printed
    assert not profiling.enabled()
