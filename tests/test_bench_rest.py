"""The rest set's paired comparison (benchmarks/bench_rest.py): McNemar's exact p and the summary it writes."""

import math
import pathlib
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "benchmarks"))

import bench_rest  # noqa: E402


@pytest.mark.parametrize("a,b,p", [(5, 11, 0.2101), (4, 13, 0.0490), (9, 8, 1.0), (0, 6, 0.03125), (0, 0, 1.0)])
def test_mcnemar_exact_p_is_the_binomial_tail_doubled(a, b, p):
    """Check the exact two-sided p against the binomial tail summed by hand (5 : 11 of 16 discordant runs: 2 * 0.105)
    and that it does not depend on the order of the split."""
    assert bench_rest.exact_two_sided_p(a, b) == pytest.approx(p, abs=5e-5)
    assert bench_rest.exact_two_sided_p(b, a) == bench_rest.exact_two_sided_p(a, b)


def test_paired_comparison_counts_runs_at_rest_in_one_tree_only():
    """Check the paired summary on four runs: one rests in the new tree only, one in the reference only, the speed ratio's
    geometric mean is that of the four ratios."""
    mm = 1.0e-3
    new = [{"speed": 0.5 * mm}, {"speed": 2.0 * mm}, {"speed": 0.4 * mm}, {"speed": 3.0 * mm}]
    ref = [{"speed": 4.0 * mm}, {"speed": 0.5 * mm}, {"speed": 0.4 * mm}, {"speed": 3.0 * mm}]
    (line,) = bench_rest.paired_comparison(new, ref, "ref")
    assert "2 against 2 of 4 at rest" in line
    assert "in this tree only 1, in ref only 1" in line
    assert "p = 1.00" in line
    ratio = math.exp((math.log(0.5 / 4.0) + math.log(2.0 / 0.5)) / 4)
    assert f"geometric mean {ratio:.2f}" in line
