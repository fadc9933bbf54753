"""Benchmark: batched worlds (cloth_warp.worlds) against the same worlds run one by one, in one process.

W variants of one scene (materials cycled over --materials, the cloth at --resolution) are stepped for --frames frames
two ways, each with its frames recorded and replayed as graphs (the Simulator's default):

1. one by one: each world its own Model, solver and Simulator, run after the other;
2. batched: all W in one Model (``build_worlds``), one Simulator (on the CPU, also with the CG in CUDA's form, one
   thread per particle and element, ``SolverImplicitEuler.world_threads = False``, as a third row).

Each way is warmed up first (--warmup frames: graph recording, first solves), then timed over --frames. Reported:
simulated cloth-seconds per wall second of each and their ratio (batched / one by one), and whether every batched
world's positions equal its single run's bit for bit (the CPU's promise; on CUDA, where atomics add in any order,
the largest difference). Target (issue "many cloths"): on the CPU 64 x 32^2 batched at least as fast as one by one;
on CUDA 256 x 32^2 >= 20x.

Run:  python benchmarks/bench_worlds.py                                  (64 x 32^2 hanging cloths, CPU)
      python benchmarks/bench_worlds.py --worlds 256 --singles 32 --device cuda:0 --out benchmarks/results/bench_worlds_cuda.md
"""

from __future__ import annotations

import argparse
import pathlib
import platform
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))


from reports import write_results  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="hanging_cloth")
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--resolution", type=int, default=32)
    p.add_argument("--materials", default="cotton,silk,denim,wool")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--singles", type=int, default=None,
                   help="run only the first K worlds one by one and scale their time to all W (each single run is "
                        "independent and sequential, so the one-by-one time is the sum over worlds; default: all W)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default=str(HERE / "results" / "bench_worlds.md"))
    args = p.parse_args()

    import numpy as np
    import warp as wp

    wp.config.quiet = True
    from cloth_warp.runner import find_scene, load_kernels
    from cloth_warp.scene import build_model, build_solver, build_wind, load_scene
    from cloth_warp.simulator import Simulator
    from cloth_warp.worlds import build_worlds, split_worlds

    materials = args.materials.split(",")
    scenes = [load_scene(find_scene(args.scene), {"material.preset": materials[k % len(materials)],
                                                   "cloth.grid.resolution": [args.resolution, args.resolution]})
              for k in range(args.worlds)]

    def simulator(model, scene):
        solver = build_solver(scene, model)
        load_kernels(solver, model.device)
        return Simulator(model, solver, fps=float(scene.get("output.fps")), substeps=int(scene.get("solver.substeps")),
                         wind=build_wind(scene))

    def timed(sims) -> float:
        """Seconds for --frames frames of every simulator (each after its warm-up)."""
        total = 0.0
        for sim in sims:
            for _ in range(args.warmup):
                sim.step_frame()
            wp.synchronize_device(args.device)
            t0 = time.perf_counter()
            for _ in range(args.frames):
                sim.step_frame()
            wp.synchronize_device(args.device)
            total += time.perf_counter() - t0
        return total

    k = min(args.singles or args.worlds, args.worlds)
    singles = [simulator(build_model(s, args.device), s) for s in scenes[:k]]
    t_single = timed(singles) * args.worlds / k
    batch = simulator(build_worlds(scenes, args.device), scenes[0])
    t_batch = timed([batch])
    t_items = None
    if wp.get_device(args.device).is_cpu:  # the batch's CG in CUDA's form too: one thread per particle and element
        items = simulator(build_worlds(scenes, args.device), scenes[0])
        items.solver.world_threads = False
        t_items = timed([items])
    worlds = split_worlds(batch.model, batch.positions())
    differences = [float(np.abs(x - s.positions()).max()) for x, s in zip(worlds, singles)]
    equal = all(np.array_equal(x, s.positions()) for x, s in zip(worlds, singles))
    cloth_seconds = args.worlds * args.frames / float(scenes[0].get("output.fps"))
    report = {
        "scene": args.scene, "worlds": args.worlds, "resolution": args.resolution, "materials": materials, "frames": args.frames,
        "warmup": args.warmup, "device": str(wp.get_device(args.device)), "machine": platform.processor() or platform.machine(),
        "particles": batch.model.particle_count, "singles_run": k,
        "one_by_one_s": t_single, "batched_s": t_batch,
        "one_by_one_throughput": cloth_seconds / t_single, "batched_throughput": cloth_seconds / t_batch,
        "ratio": t_single / t_batch, "bitwise_equal": equal, "largest_difference_m": max(differences),
        "batched_item_threads_s": t_items, "ratio_item_threads": None if t_items is None else t_single / t_items,
    }
    lines = [
        f"# Batched worlds: {args.worlds} x {args.scene} {args.resolution}^2 ({', '.join(materials)} in turn), {report['device']}",
        "",
        f"`python benchmarks/bench_worlds.py --scene {args.scene} --worlds {args.worlds} --resolution {args.resolution} "
        f"--materials {args.materials} --frames {args.frames} --warmup {args.warmup} --device {args.device}"
        + (f" --singles {k}`" if k < args.worlds else "`"),
        "",
        *([f"One by one: the first {k} worlds run, their time scaled by {args.worlds}/{k}; the bit-for-bit check covers those {k}.", ""]
          if k < args.worlds else []),
        "| way | wall s | cloth-s / wall s |",
        "|---|---:|---:|",
        f"| one by one (captured) | {t_single:.2f} | {report['one_by_one_throughput']:.2f} |",
        f"| batched (captured) | {t_batch:.2f} | {report['batched_throughput']:.2f} |",
        *([f"| batched, CG with one thread per item (CUDA's form) | {t_items:.2f} | {cloth_seconds / t_items:.2f} |"]
          if t_items is not None else []),
        "",
        f"Batched / one by one throughput: **{report['ratio']:.2f}x**. Every world equal to its single run bit for bit: "
        f"{equal} (largest difference {max(differences):.3g} m).",
        *([f"With the CG's kernels one thread per item, as on CUDA (a world that stopped still costs its items until the "
           f"batch's slowest stops): {report['ratio_item_threads']:.2f}x.", ""] if t_items is not None else []),
        "",
    ]
    write_results(args.out, lines, report)


if __name__ == "__main__":
    main()
