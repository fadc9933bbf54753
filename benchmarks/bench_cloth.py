"""Benchmark: a cotton cloth hanging from two corners, ms per frame and per substep, per integrator and size.

Shows: kernel compile time (cold cache, reported apart); for each resolution and integrator the smallest
substep count (of a doubling ladder) that stays stable with 1/60 s frames, its ms/frame and ms/substep
and the max strain at the end; in the same process, as references, the same semi-implicit substep in
vectorised numpy and in a tight single-threaded C loop (benchmarks/ref_step.c, built with the system
compiler), and - when the optional `bench` extra (Newton) is installed - Newton's own cloth solvers on
the same scene. Ratios, not absolute times, are the result (these machines are noisy).

Run:  python benchmarks/bench_cloth.py                  (32^2, 64^2, 128^2; ~10 min on 2 cores)
      python benchmarks/bench_cloth.py --sizes 32 64 --frames 10 --out benchmarks/results/quick.md
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import pathlib
import platform
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
FPS = 60.0
LADDER = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512)


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--frames", type=int, default=20, help="frames timed per configuration (halved above 64^2)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default=None, help="default benchmarks/results/bench_cloth[_cuda].md")
    p.add_argument("--no-newton", action="store_true", help="skip the Newton comparison even if installed")
    p.add_argument("--newton-solvers", nargs="+", default=None, help="Newton solvers to run (default: all; XPBD takes minutes at 128^2)")
    return p.parse_args()


def measure_compile_time(device):
    """Cold-compile each kernel module into a fresh cache; returns {module: seconds}."""
    import warp as wp

    cache = tempfile.mkdtemp(prefix="cw_bench_cache_")
    wp.config.kernel_cache_dir = cache
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    from cloth_warp.kernels import constraints, diagnostics, forces, implicit

    out = {}
    for mod in (forces, implicit, constraints, diagnostics):
        t = time.perf_counter()
        wp.load_module(mod, device=device)
        out[mod.__name__.rsplit(".", 1)[-1]] = time.perf_counter() - t
    return out, cache


def hanging_cloth(n, device):
    import cloth_warp as cw

    b = cw.ModelBuilder()
    c = b.add_cloth_grid(resolution=(n, n), size=(1.0, 1.0), material="cotton",
                         rotation=cw.quat_from_axis_angle((1, 0, 0), -90.0), position=(0.0, 1.0, 0.0))
    b.pin(c.select("corner:top_left"))
    b.pin(c.select("corner:top_right"))
    return b.finalize(device)


CONFIGS = [
    # label, solver name, options, substep ladder start
    ("semi-implicit (symplectic) Euler", "symplectic_euler", {}, 8),
    ("semi-implicit, no strain limit", "symplectic_euler", {"strain_limit": None}, 8),
    ("explicit Euler", "explicit_euler", {}, 8),
    ("explicit midpoint", "midpoint", {}, 8),
    ("RK4", "rk4", {}, 4),
    ("implicit Euler + CG", "implicit_euler", {"linear_solver": "cg"}, 1),
    # the fastest setting that still ends far below the stretch of Newton's one-step VBD (the peer it is compared with)
    ("implicit Euler + CG, tolerance 3e-2, no strain limit", "implicit_euler", {"linear_solver": "cg", "tolerance": 3e-2, "strain_limit": None}, 1),
    ("implicit Euler + Jacobi", "implicit_euler", {"linear_solver": "jacobi", "max_iterations": 300}, 1),
]


def stable(model, name, options, substeps, frames=4):
    """A short run counts as stable when it stays finite, slower than 10 m/s, with converged solves."""
    import cloth_warp as cw

    opts = dict(options)
    solver = cw.make_solver(name, model, **opts)
    sim = cw.Simulator(model, solver, fps=FPS, substeps=substeps)
    try:
        for _ in range(frames):
            s = sim.step_frame()
            if not s.finite or s.max_speed > 10.0 or s.max_strain > 0.5 or not getattr(solver, "converged", True):
                return False
    except cw.SimulationDiverged:
        return False
    return True


def time_config(model, name, options, substeps, frames):
    import warp as wp

    import cloth_warp as cw

    solver = cw.make_solver(name, model, **options)
    sim = cw.Simulator(model, solver, fps=FPS, substeps=substeps)
    sim.step_frame()  # warm-up (graph capture happens here)
    assert sim.frame == 1
    wp.synchronize()
    t = time.perf_counter()
    iters = []
    for _ in range(frames):
        stats = sim.step_frame()
        iters.append(getattr(solver, "last_iterations", 0))
    wp.synchronize()
    ms_frame = (time.perf_counter() - t) / frames * 1e3
    return {"ms_frame": ms_frame, "ms_substep": ms_frame / substeps, "max_strain": stats.max_strain,
            "iterations": float(np.mean(iters)), "finite": stats.finite, "captured": sim.capture,
            "state": (sim.state.particle_q.numpy().copy(), sim.state.particle_qd.numpy().copy())}


def numpy_reference(model, dt, state, steps=5):
    from cloth_warp.numpy_reference import NumpyCloth

    ref = NumpyCloth(model)
    x = state[0].astype(np.float64)
    v = state[1].astype(np.float64)
    target = model.particle_q.numpy().astype(np.float64)
    ref.step_symplectic(x, v, target, np.zeros(3), dt)
    t = time.perf_counter()
    for _ in range(steps):
        x, v = ref.step_symplectic(x, v, target, np.zeros(3), dt)
    return (time.perf_counter() - t) / steps * 1e3


def build_c_reference():
    cc = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        return None
    lib = pathlib.Path(tempfile.mkdtemp(prefix="cw_ref_")) / "ref_step.so"
    cmd = [cc, "-O3", "-march=native", "-ffast-math", "-shared", "-fPIC", str(HERE / "ref_step.c"), "-o", str(lib), "-lm"]
    try:
        subprocess.run(cmd, check=True, capture_output=True)
    except (subprocess.CalledProcessError, OSError):
        return None
    return ctypes.CDLL(str(lib))


def c_reference(lib, model, dt, state, steps=50):
    """ms per substep of the C loop on the model's arrays (same work as the Warp substep, no strain limit), run
    from `state` (the Warp run's last positions and velocities: the cost of a bend triple depends on whether it
    is straight) at the step `dt` [s] the Warp run found stable. The state must stay finite: an exploding
    run is cheaper (non-finite lengths skip the force math), which would flatter the reference."""
    P = ctypes.POINTER

    def ptr(a, ct):
        return a.ctypes.data_as(P(ct))

    springs = np.ascontiguousarray(model.spring_indices.numpy().astype(np.int32))
    middle = np.ascontiguousarray(model.spring_middle.numpy().astype(np.int32))
    rest = model.spring_rest_length.numpy().astype(np.float32)
    k = model.spring_stiffness.numpy().astype(np.float32)
    c = model.spring_damping.numpy().astype(np.float32)
    law = model.spring_law.numpy().astype(np.int32)
    tris = np.ascontiguousarray(model.tri_indices.numpy().astype(np.int32))
    drag = model.tri_drag.numpy().astype(np.float32)
    weights = np.ascontiguousarray(model.tri_corner_weights.numpy().astype(np.float32))
    mass = model.particle_mass.numpy().astype(np.float32)
    pinned = model.particle_pinned.numpy().astype(np.int32)
    target = np.ascontiguousarray(model.particle_q.numpy().astype(np.float32))
    x = np.ascontiguousarray(state[0].astype(np.float32))
    v = np.ascontiguousarray(state[1].astype(np.float32))
    f = np.zeros_like(x)
    g = model.gravity
    f32 = ctypes.c_float
    args = [model.particle_count, model.spring_count, model.tri_count, ptr(springs, ctypes.c_int), ptr(middle, ctypes.c_int),
            ptr(rest, f32), ptr(k, f32), ptr(c, f32), ptr(law, ctypes.c_int), ptr(tris, ctypes.c_int), ptr(drag, f32),
            ptr(weights, f32), ptr(mass, f32), ptr(pinned, ctypes.c_int), ptr(target, f32), f32(g[0]), f32(g[1]), f32(g[2]),
            f32(0), f32(0), f32(0), f32(dt), ptr(x, f32), ptr(v, f32), ptr(f, f32)]
    lib.substeps(ctypes.c_int(2), *[ctypes.c_int(a) if isinstance(a, int) else a for a in args])
    t = time.perf_counter()
    lib.substeps(ctypes.c_int(steps), *[ctypes.c_int(a) if isinstance(a, int) else a for a in args])
    ms = (time.perf_counter() - t) / steps * 1e3
    if not (np.isfinite(x).all() and np.isfinite(v).all()):
        raise RuntimeError(f"C reference diverged at dt = {dt:.3g} s: its timing would not be comparable")
    return ms


def newton_results(sizes, frames, solvers=None):
    """Run Newton's cloth solvers on the same scene in a subprocess (its own Warp module cache)."""
    script = HERE / "newton_cloth.py"
    try:
        import newton  # noqa: F401
    except ImportError:
        return None
    out = subprocess.run([sys.executable, str(script), "--sizes", *map(str, sizes), "--frames", str(frames),
                          *(["--solvers", *solvers] if solvers else [])],
                         capture_output=True, text=True)
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr.strip() else "failed"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    args = parse_args()
    compile_times, cache = measure_compile_time(args.device)


    rows = []
    refs = {}
    clib = build_c_reference()
    for n in args.sizes:
        model = hanging_cloth(n, args.device)
        frames = args.frames if n <= 64 else max(3, args.frames // 2)
        for label, name, options, start in CONFIGS:
            if options.get("linear_solver") == "jacobi" and n > 64:
                # Block Jacobi needs O(h^2 k / m) iterations: minutes per frame above 64^2.
                rows.append({"size": n, "config": label, "substeps": None, "skipped": True})
                continue
            ladder = [s for s in LADDER if s >= start]
            chosen = next((s for s in ladder if stable(model, name, options, s)), None)
            if chosen is None:
                rows.append({"size": n, "config": label, "substeps": None})
                print(f"{n}^2 {label}: unstable up to {ladder[-1]} substeps", flush=True)
                continue
            r = time_config(model, name, options, chosen, frames)
            r.update({"size": n, "config": label, "substeps": chosen})
            rows.append(r)
            print(f"{n}^2 {label}: {chosen} substeps, {r['ms_frame']:.1f} ms/frame, {r['ms_substep']:.3f} ms/substep, "
                  f"max strain {r['max_strain']:.3f}", flush=True)
        # references at the step the Warp semi-implicit run (no strain limit) found stable
        ref_row = next((r for r in rows if r["size"] == n and r["config"] == "semi-implicit, no strain limit" and r["substeps"]), None)
        if ref_row is None:
            continue
        dt = 1.0 / (FPS * ref_row["substeps"])
        refs[n] = {
            "particles": model.particle_count,
            "springs": model.spring_count,
            "dt": dt,
            "numpy_ms_substep": numpy_reference(model, dt, ref_row["state"], steps=3 if n >= 128 else 5),
            "c_ms_substep": c_reference(clib, model, dt, ref_row["state"], steps=50 if n >= 128 else 200) if clib else None,
        }
        for r in rows:
            r.pop("state", None)
    newton = None if args.no_newton else newton_results(args.sizes, args.frames, args.newton_solvers)
    shutil.rmtree(cache, ignore_errors=True)
    write_report(args, compile_times, rows, refs, newton)


def write_report(args, compile_times, rows, refs, newton):
    import warp as wp

    lines = [
        "# bench_cloth: cotton cloth (1 m, 1500 N/m, 0.15 kg/m^2) hanging from two corners, 1/60 s frames",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, Warp {wp.__version__}, "
        f"device {args.device}. Command: `python benchmarks/bench_cloth.py {' '.join(sys.argv[1:])}`",
        "",
        "Kernel compile (cold cache): " + ", ".join(f"{k} {v:.1f} s" for k, v in compile_times.items())
        + f"; total {sum(compile_times.values()):.1f} s.",
        "",
        "| size | integrator | substeps/frame | ms/frame | ms/substep | max strain (end) | solver its/step |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        if r.get("skipped"):
            lines.append(f"| {r['size']}^2 | {r['config']} | skipped (O(h^2 k/m) iterations) | | | | |")
        elif r["substeps"] is None:
            lines.append(f"| {r['size']}^2 | {r['config']} | unstable up to {LADDER[-1]} | | | | |")
        else:
            lines.append(f"| {r['size']}^2 | {r['config']} | {r['substeps']} | {r['ms_frame']:.1f} | {r['ms_substep']:.3f} | "
                         f"{r['max_strain']:.3f} | {r['iterations']:.0f} |")
    lines += ["", "References in the same process (semi-implicit substep, same forces, no strain limiting; each starts from the "
              "Warp run's last state, at its stable step, and must stay finite):", "",
              "| size | particles | springs+triples | Warp ms/substep | C loop ms/substep | Warp / C | numpy ms/substep | numpy / Warp |",
              "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for n, ref in refs.items():
        warp_row = next((r for r in rows if r["size"] == n and r["config"] == "semi-implicit, no strain limit" and r["substeps"]), None)
        w = warp_row["ms_substep"] if warp_row else float("nan")
        cms = ref["c_ms_substep"]
        lines.append(f"| {n}^2 | {ref['particles']} | {ref['springs']} | {w:.3f} | "
                     f"{cms if cms is None else f'{cms:.3f}'} | {'' if cms is None else f'{w / cms:.2f}'} | "
                     f"{ref['numpy_ms_substep']:.2f} | {ref['numpy_ms_substep'] / w:.1f} |")
    if newton:
        lines += ["", "Newton (its own solvers on the same scene; simulated seconds per wall second):", ""]
        if "error" in newton:
            lines.append(f"Newton run failed: {newton['error']}")
        else:
            lines += ["| size | solver | substeps/frame | ms/frame | sim s / wall s | max strain (end) |", "|---|---|---:|---:|---:|---:|"]
            for r in newton["rows"]:
                if r.get("substeps"):
                    lines.append(f"| {r['size']}^2 | Newton {r['solver']} | {r['substeps']} | {r['ms_frame']:.1f} | "
                                 f"{1000.0 / FPS / r['ms_frame']:.3f} | {r['max_strain']:.3f} |")
                else:
                    lines.append(f"| {r['size']}^2 | Newton {r['solver']} | unstable up to {r.get('tried', '?')} | | | |")
    text = "\n".join(lines) + "\n"
    print(text)
    out = pathlib.Path(args.out or HERE / "results" / f"bench_cloth{'' if args.device == 'cpu' else '_cuda'}.md")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(out.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, out)
    (out.with_suffix(".json")).write_text(json.dumps({"compile": compile_times, "rows": rows, "refs": refs, "newton": newton}, indent=1, default=str))


if __name__ == "__main__":
    main()
