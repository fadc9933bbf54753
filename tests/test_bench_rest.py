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


def test_the_worker_pool_returns_results_in_order_and_names_a_worker_that_gave_none():
    """benchmarks/reports.py `run_workers` (bench_rest's and bench_garments' pool): results come back in the commands'
    order whichever finishes first, and a worker that exits without a result is named by its own command (it named the
    last one started)."""
    from reports import run_workers

    def command(*args):
        return [sys.executable, "-c", "import sys, time; time.sleep(float(sys.argv[1])); sys.argv[2] == 'ok' and print('TAG {\"k\": ' + sys.argv[3] + '}')", *args], None, None

    assert run_workers([command("0.3", "ok", "0"), command("0.0", "ok", "1"), command("0.0", "ok", "2")], 2, "TAG ") == [
        {"k": 0}, {"k": 1}, {"k": 2}]
    with pytest.raises(RuntimeError, match="silent"):
        run_workers([command("0.0", "silent", "0"), command("0.2", "ok", "1")], 2, "TAG ")
