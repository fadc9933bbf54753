"""The garments benchmark's sweep over edge lengths (benchmarks/bench_garments.py): its runs and its summary."""

import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "benchmarks"))

import bench_garments  # noqa: E402


def test_a_sweep_runs_every_scene_at_every_edge_length_walked_and_held_still():
    """Check the runs of `--edges`: each edge length, each scene, the walk then the still pose; `--frames 0` skips walks."""
    args = bench_garments.parse_args(["--scenes", "tshirt_walk", "dress_walk", "--edges", "0.02", "0.03"])
    assert bench_garments.tasks_of(args) == [("tshirt_walk", 0.02, False), ("tshirt_walk", 0.02, True), ("dress_walk", 0.02, False),
                                             ("dress_walk", 0.02, True), ("tshirt_walk", 0.03, False), ("tshirt_walk", 0.03, True),
                                             ("dress_walk", 0.03, False), ("dress_walk", 0.03, True)]
    args = bench_garments.parse_args(["--scenes", "tshirt_walk", "--frames", "0"])
    assert bench_garments.tasks_of(args) == [("tshirt_walk", None, True)]


def test_the_summary_counts_runs_held_still_at_rest_by_the_median():
    """Check the summary line: a run is at rest when the median of its last frames' largest speed is at most 1 mm/s (its
    max may be above), walks count only for the strain."""
    rows = [{"max_strain": 0.0999, "rest_speed_mm_s": 2.4, "rest_speed_median_mm_s": 0.52},
            {"max_strain": 0.1043, "rest_speed_mm_s": 50.5, "rest_speed_median_mm_s": 18.2},
            {"max_strain": 0.0950, "rest_speed_mm_s": 1.0, "rest_speed_median_mm_s": 1.0},
            {"max_strain": 0.1010}]
    line = bench_garments.rest_summary(rows)
    assert line.startswith("Held still: 2 of 3 at rest")
    assert "over the 4 runs: 10.43 %" in line
