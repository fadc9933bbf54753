"""Backward/forward time and peak memory of differentiable rollouts, with and without checkpointing.

    python benchmarks/bench_gradients.py [--quick] [--config RES:STEPS:none|auto|S:implicit|symplectic ...] [--out FILE]

Hanging cotton cloth (two corners pinned, strain limit 10 %). Per configuration, in a fresh process:
forward = one rollout on the taped code path without a tape; gradient = Rollout.gradient (forward and
backward, plus the extra forward pass when checkpointed); ratio = (gradient - forward) / forward, the
backward pass alone. Peak memory: the process's peak RSS growth over its state after one warm-up
rollout (Warp's CPU arrays live in process memory). Writes benchmarks/results/bench_gradients.md.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys

CHILD = r"""
import json, resource, sys, time
import numpy as np, warp as wp
wp.config.quiet = True
import cloth_warp as cw
res, steps, every, integrator = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
every = None if every == "none" else ("auto" if every == "auto" else int(every))
b = cw.ModelBuilder()
c = b.add_cloth_grid(resolution=(res, res), size=(1.0, 1.0), rotation=(-0.7071068, 0.0, 0.0, 0.7071068), position=(0.0, 1.0, 0.0),
                     material=cw.materials.COTTON)
b.pin(c.select("corner:top_left")); b.pin(c.select("corner:top_right"))
model = b.finalize("cpu", requires_grad=True)
if integrator == "implicit":
    solver, dt = cw.SolverImplicitEuler(model, tolerance=1e-3), 1.0 / 60.0
else:
    solver, dt = cw.SolverSymplecticEuler(model), 1.0 / 60.0 / 32
target = model.particle_q.numpy() + 0.01
loss = cw.PositionLoss({steps: target})
warm = cw.Rollout(model, solver, dt=dt, steps=2)
warm.gradient(cw.PositionLoss({2: target}))
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
r = cw.Rollout(model, solver, dt=dt, steps=steps, checkpoint_every=every)
t0 = time.perf_counter(); r.forward(loss); fwd = time.perf_counter() - t0
t0 = time.perf_counter(); r.gradient(loss); grad = time.perf_counter() - t0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"forward_s": fwd, "gradient_s": grad, "peak_mb": (peak - base) / 1024.0, "segment": r.segment,
                  "adjoint_iterations": getattr(solver, "adjoint_iterations", 0)}))
"""


def measure(res, steps, every, integrator):
    out = subprocess.run([sys.executable, "-c", CHILD, str(res), str(steps), str(every), integrator], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer configurations")
    ap.add_argument("--config", action="append", metavar="RES:STEPS:CHECKPOINT:INTEGRATOR",
                    help="run only these configurations, e.g. 64:1000:auto:symplectic (repeatable)")
    ap.add_argument("--out", help="results file (default benchmarks/results/bench_gradients.md)")
    args = ap.parse_args()
    configs = [(64, 60, "none", "implicit"), (64, 60, "auto", "implicit"), (64, 320, "none", "symplectic"), (64, 320, "auto", "symplectic")]
    configs += [(32, t, e, "symplectic") for t in (100, 1000) for e in ("none", "auto")] + [(32, 10000, "auto", "symplectic")]
    if args.quick:
        configs = configs[:2] + [(32, 100, "none", "symplectic"), (32, 1000, "none", "symplectic"), (32, 1000, "auto", "symplectic")]
    if args.config:
        configs = [(int(res), int(steps), every, integ) for res, steps, every, integ in (c.split(":") for c in args.config)]
    rows = ["| cloth | integrator | steps T | checkpoint | forward s | gradient s | backward / forward | peak memory MB | MB per step |",
            "|---|---|---|---|---|---|---|---|---|"]
    for res, steps, every, integ in configs:
        m = measure(res, steps, every, integ)
        back = (m["gradient_s"] - m["forward_s"] * (2 if every != "none" else 1)) / m["forward_s"]
        row = (f"| {res}x{res} | {integ} | {steps} | {every if every == 'none' else 'every ' + str(m['segment'])} | {m['forward_s']:.2f} | "
               f"{m['gradient_s']:.2f} | {back:.2f} | {m['peak_mb']:.0f} | {m['peak_mb'] / steps:.3f} |")
        print(row, flush=True)
        rows.append(row)
    path = pathlib.Path(args.out) if args.out else pathlib.Path(__file__).parent / "results" / "bench_gradients.md"
    path.write_text("# bench_gradients\n\n`python benchmarks/bench_gradients.py " + " ".join(sys.argv[1:]) + "`\n\n"
                    "backward / forward = (gradient time - forward passes in it) / forward time.\n\n" + "\n".join(rows) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
