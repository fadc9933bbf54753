"""Benchmark: the cost of writing a frame of cache (.usdc, .usda, .npz) and of a preview, relative to simulating it.

For each resolution, the hanging-cloth scene (implicit Euler, one step per 1/60 s frame) is simulated for
`--frames` frames; in the same process each frame is then written to each format (points, normals,
velocities, extent and diagnostics, as `cloth-warp run` writes them) and rendered by the preview ray
caster. Reported: ms per frame for each, the ratio to simulating the frame, file sizes and the final
save/rename time. A second part measures memory: peak RSS of a process writing 300 frames of a 128^2
cloth with periodic crate saves (every 25 frames) against one save at the end (synthetic frames: the
write path does not depend on the physics).

Run:  python benchmarks/bench_cache.py                    (32^2, 64^2, 128^2; ~3 min on 2 cores)
      python benchmarks/bench_cache.py --sizes 32 --frames 10 --out benchmarks/results/quick_cache.md
"""

from __future__ import annotations

import argparse
import json
import pathlib
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--out", default=str(HERE / "results" / "bench_cache.md"))
    p.add_argument("--long-frames", type=int, default=1500, help="frames of the long-cache comparison (64^2 cloth)")
    p.add_argument("--memory-child", choices=["periodic", "end"], help=argparse.SUPPRESS)
    p.add_argument("--long-child", choices=["rollback", "plain"], help=argparse.SUPPRESS)
    return p.parse_args()


def simulate(n, frames):
    import cloth_warp as cw
    from cloth_warp.runner import load_kernels
    from cloth_warp.scene import build_model, build_solver, load_scene

    scene = load_scene(ROOT / "scenes" / "hanging_cloth.toml", {"cloth.grid.resolution": [n, n]})
    model = build_model(scene, "cpu")
    solver = build_solver(scene, model)
    load_kernels(solver, model.device)
    sim = cw.Simulator(model, solver, fps=60.0)
    states, diags, times = [], [], []
    for _ in range(frames):
        t = time.perf_counter()
        stats = sim.step_frame()
        q, qd = sim.state.particle_q.numpy().copy(), sim.state.particle_qd.numpy().copy()
        times.append(time.perf_counter() - t)
        states.append((q, qd))
        diags.append({"maxStrain": stats.max_strain, "dt": sim.frame_info["dt_min"],
                      "solverIterations": sim.frame_info["iterations"], "solverResidual": sim.frame_info["residual"]})
    return model, states, diags, float(np.median(times))


def time_writes(model, states, diags, folder):
    from cloth_warp.cache import open_cache

    out = {}
    for suffix in (".usdc", ".usda", ".npz"):
        path = pathlib.Path(folder) / f"bench{suffix}"
        w = open_cache(path, model, fps=60.0)
        per = []
        for (q, qd), d in zip(states, diags):
            t = time.perf_counter()
            w.write(q, qd, d)
            per.append(time.perf_counter() - t)
        t = time.perf_counter()
        w.close()
        out[suffix] = {"ms_per_frame": 1e3 * float(np.mean(per)), "close_s": time.perf_counter() - t,
                       "mb": path.stat().st_size / 1e6}
    return out


def time_preview(states, model, size=512):
    from cloth_warp.preview import Renderer

    r = Renderer(states[0][0], model.tri_indices.numpy(), size=(size, size))
    r.render(states[0][0])  # compile / warm up
    per = []
    for q, _ in states[: min(10, len(states))]:
        t = time.perf_counter()
        r.render(q)
        per.append(time.perf_counter() - t)
    return 1e3 * float(np.median(per))


def memory_child(mode):
    """Write 300 synthetic frames of a 128^2 cloth; print the peak RSS [MB]."""
    import cloth_warp as cw
    from cloth_warp.cache import UsdCacheWriter

    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(127, 127), size=(1.0, 1.0))
    model = b.finalize("cpu")
    q0 = model.rest_positions.astype(np.float32)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    with tempfile.TemporaryDirectory() as d:
        w = UsdCacheWriter(pathlib.Path(d) / "m.usdc", model, fps=60, save_every=25 if mode == "periodic" else 10**9)
        for k in range(300):
            q = q0 + np.float32(1e-3 * k)
            w.write(q, np.zeros_like(q))
        w.close()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"before_mb": before, "peak_mb": peak}))


def long_child(mode, frames):
    """Write `frames` synthetic frames of a 64^2 cloth with a crate save every 25 frames, each save guarded by
    a CrateRollback (as shipped) or not ("plain": the rollback replaced by a no-op); print wall time, time
    in saves and peak RSS growth."""
    import cloth_warp as cw
    import cloth_warp.cache as cache

    if mode == "plain":
        cache.CrateRollback = lambda path: None
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(64, 64), size=(1.0, 1.0))
    model = b.finalize("cpu")
    q0 = model.rest_positions.astype(np.float32)
    saves = []
    save = cache.UsdCacheWriter._save_file

    def timed(self):
        t = time.perf_counter()
        save(self)
        saves.append(time.perf_counter() - t)

    cache.UsdCacheWriter._save_file = timed
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    with tempfile.TemporaryDirectory() as d:
        t = time.perf_counter()
        w = cache.UsdCacheWriter(pathlib.Path(d) / "long.usdc", model, fps=60, save_every=25)
        for k in range(frames):
            q = q0 + np.float32(1e-4 * k)
            w.write(q, q, {"maxStrain": 0.01}, checkpoint={"particle_q": q, "particle_qd": q} if w.save_due else None)
        w.close()
        wall = time.perf_counter() - t
        mb = w.path.stat().st_size / 1e6
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"wall_s": wall, "save_s": sum(saves), "saves": len(saves), "rss_growth_mb": peak - before, "mb": mb}))


def check_costs(model, states, sim_ms):
    """Per-frame cost of what guards a frame [ms]: the writer's finite and shape checks, and the simulator
    checkpoint taken at every save (amortised over save_every = 25 frames)."""
    q, qd = states[-1]
    t = time.perf_counter()
    for _ in range(50):
        bool(np.isfinite(q).all()) and bool(np.isfinite(qd).all())
    finite_ms = 1e3 * (time.perf_counter() - t) / 50
    return {"finite_ms": finite_ms, "sim_ms": sim_ms, "ratio": finite_ms / sim_ms}


def _median(runs, key):
    return float(np.median([r[key] for r in runs]))


def main():
    args = parse_args()
    if args.memory_child:
        memory_child(args.memory_child)
        return
    if args.long_child:
        long_child(args.long_child, args.long_frames)
        return
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for n in args.sizes:
            model, states, diags, sim_s = simulate(n, args.frames)
            writes = time_writes(model, states, diags, folder)
            preview_ms = time_preview(states, model)
            rows.append({"size": n, "particles": model.particle_count, "simulate_ms": 1e3 * sim_s, "writes": writes,
                         "preview_ms_512": preview_ms, "checks": check_costs(model, states, 1e3 * sim_s)})
            print(json.dumps(rows[-1]), flush=True)
    memory = {}
    for mode in ("periodic", "end"):
        res = subprocess.run([sys.executable, __file__, "--memory-child", mode], capture_output=True, text=True, check=True)
        memory[mode] = json.loads(res.stdout.strip().splitlines()[-1])
    print(json.dumps(memory))
    long = {"rollback": [], "plain": []}
    for _ in range(3):  # interleaved repeats: the machine is noisy
        for mode in ("plain", "rollback"):
            res = subprocess.run([sys.executable, __file__, "--long-child", mode, "--long-frames", str(args.long_frames)],
                                 capture_output=True, text=True, check=True)
            long[mode].append(json.loads(res.stdout.strip().splitlines()[-1]))
    print(json.dumps(long))

    lines = ["# Cache write cost vs simulation (hanging cloth, implicit Euler, 1 step per 1/60 s frame)", "",
             f"`python benchmarks/bench_cache.py --sizes {' '.join(map(str, args.sizes))} --frames {args.frames}`; "
             "ms per frame (simulate: median; writes: mean, periodic crate saves included), one process, 2-core CPU "
             "machine; the ratio is write / simulate.", "",
             "| cloth | particles | simulate | .usdc write | ratio | .usda write | ratio | .npz write | ratio | "
             ".usdc MB / close s | .usda MB / close s | preview 512^2 |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        w = r["writes"]
        s = r["simulate_ms"]
        lines.append(
            f"| {r['size']}^2 | {r['particles']} | {s:.1f} ms | {w['.usdc']['ms_per_frame']:.2f} ms | {w['.usdc']['ms_per_frame'] / s:.3f} | "
            f"{w['.usda']['ms_per_frame']:.2f} ms | {w['.usda']['ms_per_frame'] / s:.3f} | {w['.npz']['ms_per_frame']:.2f} ms | "
            f"{w['.npz']['ms_per_frame'] / s:.3f} | {w['.usdc']['mb']:.1f} / {w['.usdc']['close_s']:.2f} | "
            f"{w['.usda']['mb']:.1f} / {w['.usda']['close_s']:.2f} | {r['preview_ms_512']:.0f} ms |")
    lines += ["", f"Memory, 300 synthetic frames of a 128^2 cloth (16,384 points; points + normals + velocities + extent): "
              f"peak RSS grows by {memory['periodic']['peak_mb'] - memory['periodic']['before_mb']:.0f} MB with a crate save "
              f"every 25 frames vs {memory['end']['peak_mb'] - memory['end']['before_mb']:.0f} MB saving once at the end "
              f"(above {memory['periodic']['before_mb']:.0f} MB after imports and the model).", "",
              f"Long caches, {args.long_frames} synthetic frames of a 64^2 cloth (4,225 points), a crate save every 25 "
              f"frames with a checkpoint, three interleaved repeats each (median): every save guarded by a "
              f"CrateRollback (as shipped) {_median(long['rollback'], 'wall_s'):.2f} s in all, "
              f"{_median(long['rollback'], 'save_s'):.2f} s in saves, RSS +{_median(long['rollback'], 'rss_growth_mb'):.0f} MB; "
              f"unguarded {_median(long['plain'], 'wall_s'):.2f} s, {_median(long['plain'], 'save_s'):.2f} s in saves, "
              f"RSS +{_median(long['plain'], 'rss_growth_mb'):.0f} MB; file {long['rollback'][0]['mb']:.0f} MB "
              f"(ratio of totals {_median(long['rollback'], 'wall_s') / _median(long['plain'], 'wall_s'):.3f}).", "",
              "Checks per frame (the writer refuses non-finite frames): "
              + ", ".join(f"{r['size']}^2 {r['checks']['finite_ms']:.3f} ms = {100 * r['checks']['ratio']:.2f} % of a frame"
                          for r in rows) + ".", "",
              "Notes: .usda and .npz rewrite the whole file at each save (to a temporary name renamed over the last), so "
              "they save at 25 x 1, 2, 4, ... frames and at close; their per-frame cost above is authoring plus those "
              "saves, and their close time grows with the cache; .npz holds frames in memory."]
    pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    pathlib.Path(args.out).write_text("\n".join(lines) + "\n")
    pathlib.Path(args.out).with_suffix(".json").write_text(json.dumps({"rows": rows, "memory": memory, "long": long}, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
