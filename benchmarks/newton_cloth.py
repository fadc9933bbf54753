"""Newton's own cloth solvers on bench_cloth's scene (called by bench_cloth.py; needs `pip install -e ".[bench]"`).

Same cloth as bench_cloth: 1 m square, n x n cells, 0.15 kg/m^2, membrane stiffness 1500 N/m (tri_ke =
tri_ka), bending 1e-5 N m (edge_ke), hanging from two corners, Y up, 1/60 s frames. For each solver the
smallest stable substep count of a doubling ladder is timed; max strain is over the grid's structural
edges. Prints one JSON line.

Run:  python benchmarks/newton_cloth.py --sizes 32 64 --frames 10 [--solvers VBD SemiImplicit]
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
import warp as wp

import newton

FPS = 60.0
SOLVERS = ("SemiImplicit", "XPBD", "VBD")
LADDER = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512)


def build(n, springs=False):
    """The scene; XPBD in Newton works on springs (as in Newton's own hanging-cloth example), the others on triangles."""
    b = newton.ModelBuilder(up_axis=newton.Axis.Y)
    a = 1.0 / n
    material = {"add_springs": True, "spring_ke": 1500.0, "spring_kd": 0.03} if springs else {"tri_ke": 1500.0, "tri_ka": 1500.0, "tri_kd": 0.03}
    b.add_cloth_grid(pos=wp.vec3(0.0, 1.0, 0.0), rot=wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), -math.pi / 2),
                     vel=wp.vec3(0.0), dim_x=n, dim_y=n, cell_x=a, cell_y=a, mass=0.15 * a * a,
                     edge_ke=1e-5, edge_kd=0.0, particle_radius=0.25 * a, **material)
    for idx in (n * (n + 1), n * (n + 1) + n):  # the two corners of the last row (our "top" corners)
        b.particle_mass[idx] = 0.0
    b.color(include_bending=True)  # graph colouring, required by VBD
    model = b.finalize(device="cpu")
    return model


def structural_edges(n):
    ids = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    return np.concatenate([np.stack([ids[:, :-1].ravel(), ids[:, 1:].ravel()], 1), np.stack([ids[:-1].ravel(), ids[1:].ravel()], 1)])


def make_solver(name, model):
    if name == "SemiImplicit":
        return newton.solvers.SolverSemiImplicit(model, enable_tri_contact=False)
    if name == "XPBD":
        return newton.solvers.SolverXPBD(model, iterations=10)
    if name == "VBD":
        return newton.solvers.SolverVBD(model, iterations=10)
    raise ValueError(name)


def run(model, solver_name, substeps, frames, edges, rest):
    solver = make_solver(solver_name, model)
    s0, s1 = model.state(), model.state()
    control = model.control()
    dt = 1.0 / (FPS * substeps)

    def frame():
        nonlocal s0, s1
        for _ in range(substeps):
            s0.clear_forces()
            solver.step(s0, s1, control, None, dt)
            s0, s1 = s1, s0

    frame()
    wp.synchronize()
    t = time.perf_counter()
    for _ in range(frames):
        frame()
    wp.synchronize()
    ms = (time.perf_counter() - t) / frames * 1e3
    x = s0.particle_q.numpy()
    v = s0.particle_qd.numpy()
    strain = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1) / rest - 1.0
    ok = np.isfinite(x).all() and np.abs(v).max() < 10.0
    return ms, float(strain.max()), bool(ok)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--sizes", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--solvers", nargs="+", default=list(SOLVERS), choices=list(SOLVERS))
    args = p.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    rows = []
    for n in args.sizes:
        edges = structural_edges(n)
        frames = args.frames if n <= 64 else max(3, args.frames // 2)
        for solver in args.solvers:
            model = build(n, springs=solver == "XPBD")
            rest = np.linalg.norm(model.particle_q.numpy()[edges[:, 0]] - model.particle_q.numpy()[edges[:, 1]], axis=1)
            chosen = None
            for sub in LADDER:
                try:
                    _, _, ok = run(model, solver, sub, 4, edges, rest)
                except Exception:  # a solver that cannot run this scene at all
                    ok = False
                if ok:
                    chosen = sub
                    break
            if chosen is None:
                rows.append({"size": n, "solver": solver, "substeps": None, "tried": LADDER[-1]})
                continue
            ms, strain, ok = run(model, solver, chosen, frames, edges, rest)
            rows.append({"size": n, "solver": solver, "substeps": chosen, "ms_frame": ms, "max_strain": strain, "finite": ok})
    print(json.dumps({"newton": newton.__version__, "rows": rows}))


if __name__ == "__main__":
    main()
