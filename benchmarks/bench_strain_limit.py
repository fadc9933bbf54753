"""Benchmark: what Provot strain limiting costs per step, before and after its sweeps became a capped,
device-checked loop, against the step without limiting, and the memory of a taped step.

    python benchmarks/bench_strain_limit.py [--quick] [--out FILE]      (~2 min on 2 cores; --quick ~40 s)

Per case (scenes/hanging_cloth.toml with overrides, scene-built solvers), in one process: the frame without
strain limiting (the reference), with the limiter as scenes ran it before (``strain_limit_iterations = 128``
was the *minimum*: 128 sweeps every step, the tolerance checked only on eager steps; emulated by
``strain_limit_tolerance=None``) and as it runs now (at most 128 sweeps, stopping on the device at 1e-3
excess strain, on every path). Limiter cost per step = (frame - reference frame) / steps per frame; median
frames. The worst excess strain l / L - 1 - 0.1 over structural and shear springs is measured from the
positions after every frame; "missed" counts the frames the new report flags.

Taped memory: the growth of the process's peak RSS per taped step (fresh process each, after a warm-up step),
64^2 cotton, scene-built symplectic solver, 16 steps of 1/3600 s from a state stretched 30 % in its plane (pins kept): before, every
pass of every sweep recorded on the tape with a fresh array and gradient (the old taped path, 128 sweeps);
now, the positions at the start of every 12th sweep (ceil(sqrt(128))) and a backward hook. Writes benchmarks/results/bench_strain_limit.md.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
HEAVY = {"material.areal_density": 0.5, "material.stretch_stiffness": 30.0, "material.shear_stiffness": 3.0, "material.bend_stiffness": 1e-6}
CASES = {  # name: (scene overrides, frames)
    "cotton 64^2, implicit, 1 step/frame": ({}, 12),
    "cotton 32^2, semi-implicit, 64 substeps, captured": ({"cloth.grid.resolution": [32, 32], "solver.integrator": "symplectic_euler",
                                                          "solver.substeps": 64}, 6),
    "heavy 24^2, semi-implicit, 20 substeps, captured": ({"cloth.grid.resolution": [24, 24], "solver.integrator": "symplectic_euler",
                                                         "solver.substeps": 20, **HEAVY}, 20),
    "heavy 24^2, implicit, 1 step/frame": ({"cloth.grid.resolution": [24, 24], **HEAVY}, 30),
}
QUICK = ("cotton 64^2, implicit, 1 step/frame", "heavy 24^2, semi-implicit, 20 substeps, captured")
MODES = {"no limiter": {"solver.strain_limit": 0.0}, "before": {}, "now": {}}  # before: see measure()


def excess(model, x, limit):
    sp = model.spring_indices.numpy()
    rest = model.spring_rest_length.numpy().astype(np.float64)
    lim = model.spring_limited.numpy() != 0
    length = np.linalg.norm(x[sp[lim, 0]].astype(np.float64) - x[sp[lim, 1]], axis=1)
    return float((length / rest[lim] - 1.0 - limit).max())


def measure(overrides, frames, mode, capture):
    import cloth_warp as cw
    from cloth_warp.runner import load_kernels
    from cloth_warp.scene import build_model, build_solver, load_scene
    from cloth_warp.solvers.strain_limit import StrainLimiter

    scene = load_scene(ROOT / "scenes" / "hanging_cloth.toml", {**overrides, **MODES[mode]})
    model = build_model(scene, "cpu")
    solver = build_solver(scene, model)
    lim = solver.strain_limiter
    if mode == "before":  # 128 sweeps every step (the scene key was the minimum), as the old captured and taped paths ran
        lim = solver.strain_limiter = StrainLimiter(model, lim.max_strain, lim.iterations, tolerance=None)
    load_kernels(solver, model.device)
    substeps = int(scene.get("solver.substeps"))
    sim = cw.Simulator(model, solver, fps=60.0, substeps=substeps, capture=capture)
    spent = [0.0]
    if lim is not None and not sim.capture:  # time inside the limiter (eager steps)
        apply = lim.apply

        def timed(*args):
            t = time.perf_counter()
            apply(*args)
            spent[0] += time.perf_counter() - t

        lim.apply = timed
    times, inside, worst = [], [], []
    for _ in range(frames):
        spent[0] = 0.0
        t = time.perf_counter()
        sim.step_frame()
        times.append(time.perf_counter() - t)
        inside.append(spent[0])
        worst.append(excess(model, sim.state.particle_q.numpy(), 0.1))
    total = sim.strain_limit_total
    return {"frame_ms": 1e3 * float(np.median(times[1:])), "frame_mean_ms": 1e3 * float(np.mean(times[1:])),
            "limiter_ms_per_step": 1e3 * float(np.mean(inside[1:])) / substeps,
            "substeps": substeps, "captured": bool(sim.capture), "worst_excess": max(worst),
            "frames_over": int(sum(w > 1e-3 + 1e-5 for w in worst)), "sweeps_mean": total.mean_sweeps if total else 0.0,
            "sweeps_max": total.most_sweeps if total else 0, "missed_frames": total.missed_frames if total else 0}


TAPED = r"""
import json, os, sys, time
import numpy as np, warp as wp
wp.config.quiet = True
import cloth_warp as cw
from cloth_warp.kernels import constraints as kc
from cloth_warp.scene import build_model, build_solver, load_scene
mode, steps = sys.argv[1], int(sys.argv[2])
scene = load_scene(sys.argv[3], json.loads(sys.argv[4]))
model = build_model(scene, "cpu", requires_grad=True)
solver = build_solver(scene, model)
lim = solver.strain_limiter
if mode == "before":  # the old taped path: every pass of `iterations` sweeps recorded, a fresh array (and gradient) each
    def apply(solver_, x_in, v_in, state_out, dt):
        m = model
        x = x_in
        for k in range(lim.iterations):
            y = wp.zeros_like(x, requires_grad=True)
            wp.launch(kc.apply_attachment_limit, dim=m.particle_count, inputs=[lim.attachment_particle, lim.attachment_rest_distance,
                      m.particle_pinned, x, lim.max_strain, m.particle_world, 1, lim._loop], outputs=[y])
            x = y
            for c in range(m.strain_limit_color_count):
                last = k == lim.iterations - 1 and c == m.strain_limit_color_count - 1
                y = state_out.particle_q if last else wp.zeros_like(x, requires_grad=True)
                wp.launch(kc.apply_strain_limit_color, dim=m.particle_count, inputs=[m.strain_limit_colors, m.spring_indices,
                          m.spring_rest_length, m.particle_mass, m.particle_pinned, lim.contact_normal, x, c, lim.max_strain, lim.relaxation,
                          m.particle_world, 1, lim._loop], outputs=[y])
                x = y
        wp.launch(kc.correct_velocity, dim=m.particle_count, inputs=[x_in, state_out.particle_q, v_in, dt], outputs=[state_out.particle_qd])
    lim.apply = apply
x0 = model.particle_q.numpy()
free = model.particle_pinned.numpy() == 0
stretched = x0.copy(); stretched[free] = x0.mean(0) + 1.3 * (x0[free] - x0.mean(0))  # 30 % in the plane, pins kept
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
def run(n, measure=False):
    states = [model.state(requires_grad=True) for _ in range(n + 1)]
    states[0].particle_q.assign(stretched)
    lim.reset_report()
    r0 = rss()
    t0 = time.perf_counter()
    tape = wp.Tape()
    with tape:
        for k in range(n):
            solver.step(states[k], states[k + 1], model.control(requires_grad=False), 1.0 / 3600.0)
    t1 = time.perf_counter()
    grown = rss() - r0
    tape.backward(grads={states[-1].particle_q: wp.ones(model.particle_count, dtype=wp.vec3)})
    return tape, grown, t1 - t0, time.perf_counter() - t1
run(1)
tape, grown, fwd, bwd = run(steps)
sweeps = lim.read_report().sweeps if mode == "now" else steps * lim.iterations
print(json.dumps({"mb_per_step": grown / 1e6 / steps, "sweeps_per_step": sweeps / steps, "launches_per_step": len(tape.launches) / steps,
                  "forward_ms_per_step": 1e3 * fwd / steps, "backward_ms_per_step": 1e3 * bwd / steps}))
"""


TAPED_CASES = {  # name: scene overrides (64^2, scene-built symplectic solver)
    "cotton 64^2": {"solver.integrator": "symplectic_euler"},
    "heavy 64^2": {"solver.integrator": "symplectic_euler", **HEAVY},
}


def taped_memory(mode, overrides, steps=16):
    out = subprocess.run([sys.executable, "-c", TAPED, mode, str(steps), str(ROOT / "scenes" / "hanging_cloth.toml"), json.dumps(overrides)],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="two cases")
    p.add_argument("--out", default=str(HERE / "results" / "bench_strain_limit.md"))
    args = p.parse_args()
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    cases = {k: v for k, v in CASES.items() if not args.quick or k in QUICK}
    rows = {}
    for name, (overrides, frames) in cases.items():
        rows[name] = {f"{mode} eager": measure(overrides, frames, mode, False) for mode in MODES}
        if "captured" in name:
            rows[name].update({f"{mode} captured": measure(overrides, frames, mode, True) for mode in MODES})
    taped = {name: {mode: taped_memory(mode, ov) for mode in ("before", "now")} for name, ov in TAPED_CASES.items()}
    print(json.dumps({"rows": rows, "taped": taped}))
    lines = ["# Strain limiting per step: before (128 sweeps every step) and now (at most 128, checked on the device)", "",
             f"`python benchmarks/bench_strain_limit.py{' --quick' if args.quick else ''}`; one process, 2-core CPU machine. "
             "Eager: mean time inside StrainLimiter.apply per step (the reference: the rest of the step, mean frame / steps - "
             "limiter). Captured: median "
             "frame of the replayed graph, limiter = (frame - frame without limiter) / steps per frame.", "",
             "| case | path | rest of the step | limiter before | limiter now | now / before | sweeps/step now (mean, max) | "
             "worst excess before / now | frames over 1e-3 before / now (flagged now) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        for path in ("eager", "captured"):
            if f"now {path}" not in r:
                continue
            ref, before, now = r[f"no limiter {path}"], r[f"before {path}"], r[f"now {path}"]
            n = now["substeps"]
            if path == "eager":
                rest = now["frame_mean_ms"] / n - now["limiter_ms_per_step"]
                cost_b, cost_n = before["limiter_ms_per_step"], now["limiter_ms_per_step"]
            else:
                rest = ref["frame_ms"] / n
                cost_b, cost_n = (before["frame_ms"] - ref["frame_ms"]) / n, max(0.0, (now["frame_ms"] - ref["frame_ms"]) / n)
            lines.append(f"| {name} | {path} | {rest:.3f} ms | {cost_b:.3f} ms | {cost_n:.3f} ms | {cost_n / cost_b:.3f} | "
                         f"{now['sweeps_mean']:.1f}, {now['sweeps_max']} | {before['worst_excess']:.4f} / {now['worst_excess']:.4f} | "
                         f"{before['frames_over']} / {now['frames_over']} ({now['missed_frames']}) |")
    lines += ["", "Taped steps, scene-built symplectic solver, 16 steps of 1/3600 s from a state stretched 30 % in its plane (RSS growth over "
              "the taped forward pass per step, fresh process each):", "",
              "| cloth | taped path | sweeps/step | tape launches/step | MB per step | forward ms/step | backward ms/step |",
              "|---|---|---|---|---|---|---|"]
    for name, t in taped.items():
        for mode in ("before", "now"):
            label = ("before: every pass on the tape, fresh array + gradient" if mode == "before"
                     else "now: a snapshot every 12 sweeps run, backward hook")
            lines.append(f"| {name} | {label} | {t[mode]['sweeps_per_step']:.1f} | {t[mode]['launches_per_step']:.0f} | "
                         f"{t[mode]['mb_per_step']:.2f} | {t[mode]['forward_ms_per_step']:.1f} | {t[mode]['backward_ms_per_step']:.1f} |")
    pathlib.Path(args.out).write_text("\n".join(lines) + "\n")
    pathlib.Path(args.out).with_suffix(".json").write_text(json.dumps({"rows": rows, "taped": taped}, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
