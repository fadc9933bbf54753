"""Benchmark: taped implicit steps with the linear solves' loops replayed as graphs against launched one by one.

A taped step cannot be recorded whole (the tape records its kernels), so its solves (forward and adjoint) ran their
CG or Jacobi loops eagerly: ~10 launches an iteration from the host. ``SolverImplicitEuler.replay_loops`` (default)
records each loop once as a graph and replays it. Workloads, each run both ways in one process (after a warm-up),
the eager way first:

- calibrate: ``cloth_warp.calibrate`` of a known material from a start 0.5-2x off (tests/test_calibrate.py's far
  start: 4 + 4 iterations of taped cantilever and tensile tests, 63-particle strips);
- fit: 3 iterations of scenes/fit_hanging.toml (12^2, 60 steps) fitting stretch, bend and damping;
- gradient: one ``Rollout.gradient`` of a 32^2 hanging cloth, 30 steps.

Reported: seconds each way, the ratio, and whether the results agree bit for bit.

Run:  python benchmarks/bench_taped_solves.py [--device cpu] [--out benchmarks/results/bench_taped_solves.md]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(HERE))


from reports import write_results  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default=str(HERE / "results" / "bench_taped_solves.md"))
    args = p.parse_args()

    import numpy as np
    import warp as wp

    wp.config.quiet = True
    import cloth_warp as cw
    from cloth_warp.calibrate import FabricMeasurements, calibrate
    from cloth_warp.fitting import SceneFit
    from cloth_warp.scene import load_scene
    from cloth_warp.solvers.implicit import SolverImplicitEuler
    from test_calibrate import KNOWN

    def run_calibrate():
        start = {"material.bend_stiffness": 1.0e-5, "material.bend_stiffness_weft": 8.0e-5, "material.stretch_stiffness": 900.0,
                 "material.stretch_stiffness_weft": 1000.0}
        r = calibrate(FabricMeasurements.of_material(KNOWN), start=start, device=args.device)
        return [m.relative_error for m in r.measurements]

    target = ROOT / "benchmarks" / "results" / ".bench_taped_solves_target.npz"

    def run_fit():
        if not target.exists():
            cw.run_scene(ROOT / "scenes" / "fit_hanging.toml", {"material.stretch_stiffness": 150.0, "material.bend_stiffness": 2e-4,
                                                                 "material.damping": 0.02, "output.frames": 30}, output=target)
        fit = SceneFit(load_scene(ROOT / "scenes" / "fit_hanging.toml"), target,
                       ["material.stretch_stiffness", "material.bend_stiffness", "material.damping"], device=args.device)
        return fit.run(iterations=3, learning_rate=0.1).losses

    def run_gradient():
        b = cw.ModelBuilder()
        c = b.add_cloth_grid(resolution=(32, 32), size=(1.0, 1.0), rotation=(-0.7071068, 0.0, 0.0, 0.7071068), position=(0.0, 1.0, 0.0),
                             material=cw.materials.COTTON)
        b.pin(c.select("corner:top_left"))
        b.pin(c.select("corner:top_right"))
        model = b.finalize(args.device, requires_grad=True)
        rollout = cw.Rollout(model, SolverImplicitEuler(model, tolerance=1e-5), dt=1.0 / 60.0, steps=30)
        value = rollout.gradient(cw.PositionLoss({30: model.particle_q.numpy() + 0.01}, device=args.device))
        return [value, model.spring_stiffness.grad.numpy().tolist()]

    workloads = {"calibrate": run_calibrate, "fit": run_fit, "gradient": run_gradient}
    rows, report = [], {"device": str(wp.get_device(args.device)), "machine": platform.processor() or platform.machine(), "workloads": {}}
    try:
        for name, work in workloads.items():
            times, results = {}, {}
            for replay in (False, True):
                SolverImplicitEuler.replay_loops = replay
                if replay is False:
                    work()  # warm-up (kernel loading, the target)
                wp.synchronize_device(args.device)
                t0 = time.perf_counter()
                results[replay] = work()
                wp.synchronize_device(args.device)
                times[replay] = time.perf_counter() - t0
            same = json.dumps(results[False]) == json.dumps(results[True])
            report["workloads"][name] = {"eager_s": times[False], "replayed_s": times[True], "ratio": times[False] / times[True],
                                         "bitwise_equal": same}
            rows.append(f"| {name} | {times[False]:.2f} | {times[True]:.2f} | {times[False] / times[True]:.1f}x | {same} |")
            print(rows[-1], flush=True)
    finally:
        SolverImplicitEuler.replay_loops = True
        target.unlink(missing_ok=True)
    write_results(args.out, [f"# Taped solves: loops replayed as graphs against launched one by one, {report['device']}", "",
                             f"`python benchmarks/bench_taped_solves.py --device {args.device}`", "",
                             "| workload | eager loops s | replayed loops s | speed-up | same results bit for bit |",
                             "|---|---:|---:|---:|---|", *rows, ""], report)


if __name__ == "__main__":
    main()
