"""The frame record: a frame's device records packed into one block, read once; the typed frame report."""

import numpy as np
import warp as wp

from cloth_warp.diagnostics import FrameReport, LinearSolveReport, StepStats, StrainLimitReport
from cloth_warp.profiling import LaunchCounter
from cloth_warp.records import FrameRecord, record_values


class Part:
    """A part of a step with records of mixed types and shapes."""

    def __init__(self):
        self.counts = wp.array([3, 1, 4], dtype=wp.int32, device="cpu")
        self.sums = wp.array([2.5, -1.0], dtype=wp.float64, device="cpu")
        self.points = wp.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], dtype=wp.vec3, device="cpu")
        self.scratch = wp.zeros(4, dtype=float, device="cpu")  # not a record: stays where it is

    def record_arrays(self):
        return [(self, "counts"), (self, "sums"), (self, "points")]


def test_records_move_into_one_block_and_are_read_once():
    """Check the records keep their values, types and shapes in the block, device writes to them are what the
    fetched copy holds (one read for all), and outside the fetch each is read from the device again."""
    a, b = Part(), Part()
    scratch = b.scratch
    record = FrameRecord.of("cpu", [a, None, b])
    assert b.scratch is scratch
    for part in (a, b):
        assert part.counts.dtype == wp.int32 and part.sums.dtype == wp.float64 and part.points.dtype == wp.vec3
        np.testing.assert_array_equal(part.counts.numpy(), [3, 1, 4])
        np.testing.assert_array_equal(part.points.numpy(), [[1, 2, 3], [4, 5, 6]])
    b.counts.fill_(7)
    a.sums.zero_()
    wp.copy(a.points, wp.array([[9.0, 9.0, 9.0], [8.0, 8.0, 8.0]], dtype=wp.vec3, device="cpu"))
    with LaunchCounter() as counts:
        with record.fetched():
            vals = [record_values(getattr(p, n)) for p in (a, b) for n in ("counts", "sums", "points")]
    assert counts.reads == 1, counts.to_dict()
    assert [v.shape for v in vals] == [(3,), (2,), (2, 3)] * 2
    np.testing.assert_array_equal(vals[3], [7, 7, 7])
    np.testing.assert_array_equal(vals[1], [0.0, 0.0])
    np.testing.assert_array_equal(vals[2], [[9, 9, 9], [8, 8, 8]])
    np.testing.assert_array_equal(vals[4], [2.5, -1.0])
    assert vals[0].dtype == np.int32 and vals[1].dtype == np.float64 and vals[2].dtype == np.float32
    b.counts.fill_(2)  # written after the fetch: read from the device
    np.testing.assert_array_equal(record_values(b.counts), [2, 2, 2])


def test_frame_report_counters_flatten_the_reports():
    """Check the flat view names every pass's counters and the fixed-step re-runs or the adaptive rejections."""
    stats = StepStats(0.1, 1.0, 2.0, 0)
    limit = StrainLimitReport(max_strain=0.1, tolerance=1e-3, max_sweeps=8, structural_excess=0.0, shear_excess=0.0,
                              initial_excess=0.0, steps=2, missed_steps=0, sweeps=3, most_sweeps=2, frames=1, missed_frames=0)
    solves = LinearSolveReport(solves=2, iterations=40, most_iterations=25, failed=0, first_failed=0, unconverged=0,
                               worst_residual=1e-3, last_residual=5e-4, tolerance=1e-3)
    fixed = FrameReport(stats=stats, dt_min=0.01, dt_max=0.01, iterations=40, residual=5e-4, solves=solves,
                        passes={"strain_limit": limit}, reruns=1)
    c = fixed.counters()
    assert c["iterations"] == 40 and c["frame_reruns"] == 1 and "rejected" not in c
    assert c["strain_limit_sweeps"] == 3
    adaptive = FrameReport(stats=stats, dt_min=0.005, dt_max=0.01, rejected=2, reruns=None)
    assert adaptive.counters()["rejected"] == 2 and "frame_reruns" not in adaptive.counters()
