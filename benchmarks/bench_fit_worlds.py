"""Benchmark: N targets fitted at once (cloth_warp.batch_fit.BatchFit) against N fits one by one (SceneFit), in one process.

The fit scene (default scenes/fit_hanging.toml, its start 2x off) is fitted to N targets: the scene simulated with
stretch stiffness and damping spread over 0.5-2x the start's. Each way runs --iterations Adam iterations per target
after a warm-up evaluation (kernel loading); reported: wall seconds, target-iterations per wall second and their ratio
(batched / one by one), the time spent in the hosts' chain-rule builds, and whether every batched target's losses
and values equal its single fit's bit for bit (the CPU's promise).

Run:  python benchmarks/bench_fit_worlds.py                     (16 targets, CPU)
      python benchmarks/bench_fit_worlds.py --targets 64 --device cuda:0 --out benchmarks/results/bench_fit_worlds_cuda.md
"""

from __future__ import annotations

import argparse
import pathlib
import platform
import sys
import tempfile
import time

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))
KEYS = ["material.stretch_stiffness", "material.damping"]


from reports import write_results  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default=str(ROOT / "scenes" / "fit_hanging.toml"))
    p.add_argument("--targets", type=int, default=16)
    p.add_argument("--iterations", type=int, default=3)
    p.add_argument("--frames", type=int, default=None, help="fitted frames (default: the scene's output.frames)")
    p.add_argument("--singles", type=int, default=None, help="fit only the first K targets one by one, scaled to all N")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default=str(HERE / "results" / "bench_fit_worlds.md"))
    args = p.parse_args()

    import numpy as np
    import warp as wp

    wp.config.quiet = True
    import cloth_warp as cw
    from cloth_warp.batch_fit import BatchFit
    from cloth_warp.fitting import SceneFit
    from cloth_warp.scene import load_scene

    overrides = {} if args.frames is None else {"output.frames": args.frames}
    scene = load_scene(args.scene, overrides)
    start = [float(scene.get(k)) for k in KEYS]
    spread = np.geomspace(0.5, 2.0, args.targets)
    folder = pathlib.Path(tempfile.mkdtemp(prefix="bench_fit_worlds_"))
    targets = []
    for k in range(args.targets):
        truth = {KEYS[0]: start[0] * spread[k], KEYS[1]: start[1] * spread[::-1][k]}
        path = folder / f"target{k}.npz"
        cw.run_scene(pathlib.Path(args.scene), {**overrides, **truth}, output=path)
        targets.append(path)

    # warm-up: every kernel loaded once (both ways use the same modules)
    SceneFit(scene, targets[0], KEYS, device=args.device).loss_and_gradient([np.array([v]) for v in start])

    k = min(args.singles or args.targets, args.targets)
    wp.synchronize_device(args.device)
    t0 = time.perf_counter()
    singles = [SceneFit(scene, t, KEYS, device=args.device).run(iterations=args.iterations) for t in targets[:k]]
    wp.synchronize_device(args.device)
    t_single = (time.perf_counter() - t0) * args.targets / k
    t0 = time.perf_counter()
    batch = BatchFit(scene, targets, KEYS, device=args.device)
    results = batch.run(iterations=args.iterations)
    wp.synchronize_device(args.device)
    t_batch = time.perf_counter() - t0
    # the hosts' chain rule alone (two single-world builds per key and target per iteration, the same both ways)
    t0 = time.perf_counter()
    for fit, r in zip(batch.fits, results):
        values = [np.array([r.final_values[key]]) for key in KEYS]
        fit.chain_rule(values, {name: np.zeros(a.shape) for name, a in fit._arrays(fit._values(values)).items()} | {"forces.wind": np.zeros(3)})
    t_chain = (time.perf_counter() - t0) * args.iterations
    equal = all(r.losses == s.losses and r.values == s.values for r, s in zip(results, singles))
    worst = max(max(abs(a - b) / max(abs(b), 1e-30) for a, b in zip(r.losses, s.losses)) for r, s in zip(results, singles))
    work = args.targets * args.iterations
    report = {"scene": pathlib.Path(args.scene).name, "targets": args.targets, "iterations": args.iterations, "frames": batch.frames,
              "steps": batch.rollout.steps, "particles_per_world": batch.fits[0].model.particle_count, "keys": KEYS,
              "device": str(wp.get_device(args.device)), "machine": platform.processor() or platform.machine(), "singles_run": k,
              "one_by_one_s": t_single, "batched_s": t_batch, "chain_rule_s": t_chain,
              "one_by_one_throughput": work / t_single, "batched_throughput": work / t_batch, "ratio": t_single / t_batch,
              "bitwise_equal": equal, "largest_relative_loss_difference": worst}
    lines = [
        f"# Batched fitting: {args.targets} targets of {report['scene']} ({report['particles_per_world']} particles, "
        f"{batch.frames} frames, {batch.rollout.steps} steps), {report['device']}",
        "",
        f"`python benchmarks/bench_fit_worlds.py --targets {args.targets} --iterations {args.iterations} --device {args.device}"
        + (f" --frames {args.frames}" if args.frames else "") + (f" --singles {k}`" if k < args.targets else "`"),
        "",
        f"Keys fitted: {', '.join(KEYS)}; targets simulated with them spread over 0.5-2x the start.",
        *([f"One by one: the first {k} targets fitted, their time scaled by {args.targets}/{k}; the comparison covers those {k}."]
          if k < args.targets else []),
        "",
        "| way | wall s | target-iterations / wall s |",
        "|---|---:|---:|",
        f"| one by one (SceneFit) | {t_single:.2f} | {report['one_by_one_throughput']:.2f} |",
        f"| batched (BatchFit) | {t_batch:.2f} | {report['batched_throughput']:.2f} |",
        "",
        f"Batched / one by one: **{report['ratio']:.2f}x**. Of either way's time, {t_chain:.2f} s is the hosts' chain rule (model "
        f"builds per key and target, the same both ways). Every target's losses and values equal to its single fit bit for bit: "
        f"{equal} (largest relative loss difference {worst:.3g}).",
        "",
    ]
    write_results(args.out, lines, report)


if __name__ == "__main__":
    main()
