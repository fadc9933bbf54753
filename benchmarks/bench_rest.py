"""Benchmark: the rest set, piles and drapes over the ball at several resolutions and seeds, with the contacts in the solve.

One run of a piled or draped cloth is chaotic: a change at the level of float rounding moves its last frames' speed by
a factor of three and its CG iterations by four (README, 2026-11-29), so a change to the contacts is judged here on a
set of runs. Each run is `benchmarks/bench_contacts.py`'s (the shipped scene as `cloth-warp run` builds it, `--mode`
default "solve+self+friction", `--frames` default 300 = 5 s) with its grid resolution and `scene.seed` (the cloth's
jitter) set; `--jobs` runs go at a time, each in its own process. Reported per run and in sum: the largest particle
speed over the last 20 frames (median; at rest: <= 1 mm/s, issue 17's target), CG iterations per frame (mean over those
frames) and ms per frame (median over the run); the summary gives how many runs rest, the geometric mean of their
speeds, and the sums. With --ref REV the same runs are made at git revision REV (a temporary worktree), each next to
its counterpart, so that both see the same machine noise.

Run:  python benchmarks/bench_rest.py                         (30 runs, ~4-6 min on 2 cores)
      python benchmarks/bench_rest.py --extended              (and 30 more, other seeds: 60 runs)
      python benchmarks/bench_rest.py --ref HEAD~1            (and the revision before: ~12 min)
      python benchmarks/bench_rest.py --runs 12 --set solver.tolerance=1e-4
      python benchmarks/bench_rest.py --fine                  (the pile and drape at 64^2, seeds 0-5: ~10 min)
      python benchmarks/bench_rest.py --extended --against benchmarks/results/bench_rest_self_restick.json

A tree is compared with another on the same runs, paired (`--ref`, or `--against` a recorded .json): a change to the
contacts reshuffles which runs rest, so the count at rest is judged by McNemar's exact p on the runs at rest in one
tree only, not by its difference alone (docs/contacts-in-the-solve.md, "The rest set counts a rate").
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

# (scene, grid resolution, seed): 32^2 piles seeds 0-9, 48^2 piles seeds 0-1, 48^2 drapes seeds 0-4 and a 64^2 one
# (the set the 2026-11 sessions measured), then 32^2 piles seeds 10-19 and 40^2 drapes seeds 5-6
RUNS = ([("pile", 32, s) for s in range(10)] + [("pile", 48, s) for s in range(2)] + [("drape_sphere", 48, s) for s in range(5)]
        + [("drape_sphere", 64, 0)] + [("pile", 32, s) for s in range(10, 20)] + [("drape_sphere", 40, s) for s in (5, 6)])
# a second set of 30 (2026-11-29): 32^2 piles seeds 20-39 and 40^2 drapes seeds 7-16. Equivalent trees' counts of runs
# at rest moved by up to 3 on one set of 30 (README, Benchmarks); `--extended` runs both sets (60 runs)
MORE_RUNS = [("pile", 32, s) for s in range(20, 40)] + [("drape_sphere", 40, s) for s in range(7, 17)]
# issue 17's "finer resolutions" (2026-12-03, session 74): the shipped pile and drape over the ball at 64^2, seeds 0-5
# (`--fine`, on its own: 12 runs, ~70-110 s each on one core)
FINE_RUNS = [(scene, 64, s) for scene in ("pile", "drape_sphere") for s in range(6)]
REST = 1.0e-3
"""[m/s] a run rests when the median of its last 20 frames' largest particle speed is at most this."""
TAG = "BENCH_REST "


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=None, help="the first N runs of the set (default all)")
    p.add_argument("--extended", action="store_true", help=f"the set and {len(MORE_RUNS)} more runs (other seeds)")
    p.add_argument("--fine", action="store_true", help=f"only the {len(FINE_RUNS)} runs at 64^2 (pile and drape, seeds 0-5)")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--mode", default="solve+self+friction", help="bench_contacts.py's contact mode")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="scene override (TOML value), repeatable")
    p.add_argument("--jobs", type=int, default=2, help="runs at a time (one process each)")
    p.add_argument("--ref", metavar="REV", default=None, help="also run git revision REV (a temporary worktree)")
    p.add_argument("--against", metavar="JSON", default=None,
                   help="a recorded result (this benchmark's .json, the same runs) to pair this tree's runs with")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_rest.md"))
    p.add_argument("--one", nargs=3, metavar=("SCENE", "RES", "SEED"), help=argparse.SUPPRESS)
    return p.parse_args(argv)


def run_one(args) -> None:
    """A worker: one run, its numbers printed as one tagged JSON line."""
    import warp as wp

    wp.config.quiet = True
    from bench_contacts import run

    from cloth_warp.cli import parse_set

    scene, res, seed = args.one[0], int(args.one[1]), int(args.one[2])
    overrides = {**parse_set(args.set), "cloth.grid.resolution": [res, res], "scene.seed": seed}
    r = run(scene, args.mode, args.frames, overrides)
    print(TAG + json.dumps({"speed": r["rest_speed_median"], "iterations": r["iterations"], "ms": r["ms_per_frame"]}), flush=True)


def worker(tree: pathlib.Path | None, spec, args) -> tuple:
    """The worker process (argv, env, cwd) for run `spec` in `tree` (None: this tree as installed)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if tree is not None:
        env["PYTHONPATH"] = str(tree) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--one", *map(str, spec), "--frames", str(args.frames),
           "--mode", args.mode] + [a for kv in args.set for a in ("--set", kv)]
    return cmd, env, tree or ROOT


def summary(rows: list[dict]) -> str:
    resting = sum(r["speed"] <= REST for r in rows)
    geo = math.exp(sum(math.log(max(r["speed"], 1e-9)) for r in rows) / len(rows))
    return (f"{resting} of {len(rows)} at rest, geometric mean {1e3 * geo:.2f} mm/s, "
            f"{sum(r['iterations'] for r in rows):.0f} CG iterations and {sum(r['ms'] for r in rows):.0f} ms per frame in sum")


def exact_two_sided_p(a: int, b: int) -> float:
    """The exact two-sided p of McNemar's test: the chance, under equal odds, of a split of a + b discordant runs at least
    as uneven as a : b."""
    n, k = a + b, min(a, b)
    return 1.0 if n == 0 else min(1.0, 2.0 * sum(math.comb(n, i) for i in range(k + 1)) / 2.0 ** n)


def paired_comparison(new: list[dict], ref: list[dict], ref_name: str) -> list[str]:
    """Two trees' results on the same runs, paired: the runs at rest in one tree only, McNemar's exact p, and how many
    such runs two trees whose runs rest independently at their pooled rate would have. Each change to the contacts reshuffles
    which runs rest (2026-12-01: the recorded pairs split near that count), so the count at rest is a rate with a
    binomial spread, and a difference is judged by p, not by its sign."""
    rest_new = [r["speed"] <= REST for r in new]
    rest_ref = [r["speed"] <= REST for r in ref]
    only_new = sum(a and not b for a, b in zip(rest_new, rest_ref))
    only_ref = sum(b and not a for a, b in zip(rest_new, rest_ref))
    n = len(new)
    rate = (sum(rest_new) + sum(rest_ref)) / (2 * n)
    log_ratio = [math.log(max(a["speed"], 1e-9) / max(b["speed"], 1e-9)) for a, b in zip(new, ref)]
    mean = sum(log_ratio) / n
    spread = math.sqrt(sum((x - mean) ** 2 for x in log_ratio) / max(n - 1, 1) / n)
    return [f"Paired against {ref_name}: {sum(rest_new)} against {sum(rest_ref)} of {n} at rest; at rest in this tree only "
            f"{only_new}, in {ref_name} only {only_ref} (McNemar's exact two-sided p = {exact_two_sided_p(only_new, only_ref):.2f}; "
            f"independent runs at the pooled rate would split {2 * n * rate * (1 - rate):.1f}); speed ratio, geometric mean "
            f"{math.exp(mean):.2f} (x/ {math.exp(2 * spread):.2f} for two standard errors)."]


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.one:
        run_one(args)
        return 0
    from bench_step import make_worktree, remove_worktree
    from reports import run_workers

    runs = (FINE_RUNS if args.fine else RUNS + MORE_RUNS if args.extended else RUNS)[:args.runs]
    tree = make_worktree(args.ref) if args.ref else None
    t0 = time.perf_counter()
    try:
        trees = [None] + ([tree] if tree else [])
        results = run_workers([worker(t, spec, args) for spec in runs for t in trees], args.jobs, TAG)
    finally:
        if tree is not None:
            remove_worktree(tree)
    new = results[::len(trees)]
    ref = results[1::len(trees)] if tree else None
    command = "python benchmarks/bench_rest.py " + " ".join(sys.argv[1:] if argv is None else argv)
    import warp as wp

    from reports import write_results

    head = "| scene | resolution | seed | speed [mm/s] | CG its/frame | ms/frame |" + (" ref speed | ref its | ref ms |" if ref else "")
    lines = ["# bench_rest: piles and drapes over the ball, at rest or not after the run", "",
             f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, Warp {wp.config.version}. "
             f"Command: `{command.strip()}`. Mode {args.mode}, {args.frames} frames a run, {args.jobs} at a time "
             f"({time.perf_counter() - t0:.0f} s in all); speed: the median of the last 20 frames' largest particle speed "
             f"(at rest: <= {1e3 * REST:g} mm/s).", "",
             head, "|---|---:|---:|---:|---:|---:|" + ("---:|---:|---:|" if ref else "")]
    for k, (scene, res, seed) in enumerate(runs):
        r = new[k]
        row = f"| {scene} | {res} | {seed} | {1e3 * r['speed']:.2f} | {r['iterations']:.0f} | {r['ms']:.1f} |"
        if ref:
            row += f" {1e3 * ref[k]['speed']:.2f} | {ref[k]['iterations']:.0f} | {ref[k]['ms']:.1f} |"
        lines.append(row)
    lines += ["", f"This tree: {summary(new)}."] + ([f"`{args.ref}`: {summary(ref)}."] if ref else [])
    if args.extended and len(runs) > len(RUNS):  # each set on its own
        for name, part in (("the first set", slice(0, len(RUNS))), ("the second set", slice(len(RUNS), None))):
            lines.append(f"On {name}: this tree {summary(new[part])}" + (f"; `{args.ref}` {summary(ref[part])}." if ref else "."))
    if ref:
        lines += [""] + paired_comparison(new, ref, f"`{args.ref}`")
    if args.against:
        recorded = json.loads(pathlib.Path(args.against).read_text())
        by_run = {tuple(spec): row for spec, row in zip(recorded["runs"], recorded["new"])}
        pairs = [(row, by_run[tuple(spec)]) for spec, row in zip(runs, new) if tuple(spec) in by_run]
        if pairs:
            lines += [""] + paired_comparison([a for a, _ in pairs], [b for _, b in pairs], f"`{pathlib.Path(args.against).name}`")
    write_results(args.out, lines, {"command": command.strip(), "runs": [list(s) for s in runs], "new": new, "ref": ref})
    return 0


if __name__ == "__main__":
    sys.exit(main())
