"""Benchmark: how hard one step's linear system is with the contacts after the step or inside the implicit solve.

For each mode (as `benchmarks/bench_contacts.py` names them) the shipped scene is run to `--frame` as `cloth-warp run`
builds it; the first solve of that frame's first step is then read out column by column (the CG's own product
kernels: the filtered matrix S A S, the block-Jacobi preconditioner blocks, the starting residual and the stop) and
solved again in numpy (float64 PCG with the same start and stop). Reported per mode: the iterations in the run and in
numpy, the iterations in numpy with every contact's preconditioner block the filtered block's inverse (S A_ii S)^+,
the preconditioned spectrum (smallest and largest non-zero eigenvalue, how many lie above 2: block Jacobi on a
spring net stays within 2), and the three largest with whether their modes sit on collider contacts. Dense: a few
thousand unknowns (the shipped 32^2 pile, 3267) take seconds; a 48^2 drape (7203) about a minute.

Run:  python benchmarks/bench_contact_spectrum.py                          (the pile at frame 35: falling and folding)
      python benchmarks/bench_contact_spectrum.py --frame 250               (at rest)
      python benchmarks/bench_contact_spectrum.py --modes pass solve+friction solve+self+friction --frame 63
      python benchmarks/bench_contact_spectrum.py --scene drape_sphere --frame 40 --modes solve+self+friction --deflate 4 16 64
                                                                        (deflated by the k slowest exact modes)
"""

from __future__ import annotations

import argparse
import pathlib
import platform
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_contacts import MODES  # noqa: E402
from reports import write_results  # noqa: E402


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="pile")
    p.add_argument("--frame", type=int, default=35, help="the frame whose first solve is read out (0-based)")
    p.add_argument("--modes", nargs="+", default=["pass", "solve+friction", "solve+self+friction"], choices=list(MODES))
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="scene override (TOML value), repeatable")
    p.add_argument("--deflate", type=int, nargs="*", default=[], metavar="K",
                   help="also PCG deflated by the K slowest exact eigenvectors of the preconditioned system (each K)")
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_contact_spectrum.md"))
    return p.parse_args(argv)


def read_system(scene_name: str, mode: str, frame: int, overrides: dict) -> dict:
    """Run to `frame` and read out the first solve of its first step: S A S (dense, symmetrised), the preconditioner
    blocks, the contact normals, the starting residual, the stop (absolute) and the run's iterations for that solve."""
    import warp as wp

    from cloth_warp.kernels import implicit as ki
    from cloth_warp.runner import find_scene, load_kernels
    from cloth_warp.scene import build_model, build_solver, load_scene
    from cloth_warp.simulator import Simulator

    collider, self_contacts, friction = MODES[mode]
    scene = load_scene(find_scene(scene_name), {**overrides, "solver.collider_contacts": collider, "solver.self_contacts": self_contacts,
                                                "solver.contact_friction": friction})
    model = build_model(scene, "cpu")
    solver = build_solver(scene, model)
    load_kernels(solver, model.device)
    substeps = int(scene.get("solver.substeps"))
    dt = 1.0 / float(scene.get("output.fps")) / substeps
    sim = Simulator(model, solver, fps=float(scene.get("output.fps")), substeps=substeps, capture=False)
    for _ in range(frame):
        sim.step_frame()
    n = model.particle_count
    m, dev = model, model.device
    column, product = wp.zeros(n, dtype=wp.vec3, device=dev), wp.zeros(n, dtype=wp.vec3, device=dev)
    sums = wp.zeros_like(solver.cg_sums)

    def apply(x: np.ndarray) -> np.ndarray:  # S A x by the CG's own kernels (the one-kernel-per-element form)
        column.assign(x.reshape(n, 3).astype(np.float32))
        product.zero_()
        solver.scatter_element_product(column, dt, product)
        wp.launch(ki.cg_product, dim=n, inputs=[n, solver.effective_mass, m.particle_pinned, column, solver.contact_normal,
                                                solver.contact_crease, int(solver._contacts_on), m.particle_world, 1, solver.loop],
                  outputs=[product, sums], device=dev)
        return product.numpy().astype(np.float64).reshape(-1)

    read = {}
    begin, solve_cg = solver._begin_iterations, solver.solve_cg

    def begin_and_read(*args, **kwargs):
        begin(*args, **kwargs)
        if read:
            return
        status = solver.solve_status.numpy()
        identity = np.eye(3 * n)
        a = np.stack([apply(identity[j]) for j in range(3 * n)], axis=1)
        normal = solver.contact_normal.numpy().astype(np.float64) if solver._contacts_on else np.zeros((n, 3))
        crease = solver.contact_crease.numpy().astype(np.float64) if solver._contacts_on else np.zeros((n, 3))
        s = np.zeros((3 * n, 3 * n))
        for i in range(n):
            s[3 * i:3 * i + 3, 3 * i:3 * i + 3] = projector(normal[i], crease[i])
        a = s @ a @ s
        read.update(a=0.5 * (a + a.T), blocks=solver.precond.numpy().astype(np.float64), normal=normal, crease=crease,
                    r0=solver.residual.numpy().astype(np.float64).reshape(-1),
                    stop=float(status[ki.STATUS_STOP]) * float(np.sqrt(status[ki.STATUS_REFERENCE])),
                    start=float(status[ki.STATUS_RELATIVE]))

    def solve_and_count(*args, **kwargs):
        out = solve_cg(*args, **kwargs)
        if "iterations" not in read:
            read["iterations"] = int(solver.loop.numpy()[ki.LOOP_ITERATION])
        return out

    solver._begin_iterations, solver.solve_cg = begin_and_read, solve_and_count
    sim.step_frame()
    read["particles"] = n
    return read


def pcg(a: np.ndarray, blocks: np.ndarray, r: np.ndarray, stop: float, cap: int = 5000) -> int:
    """Block-preconditioned CG iterations from residual r (zero correction) until |r| <= stop."""
    return deflated_pcg(a, blocks, np.zeros((r.size, 0)), r, stop, cap)


def projector(normal: np.ndarray, crease: np.ndarray) -> np.ndarray:
    """A particle's filter S_i = I - n n^T - m m^T (kernels/implicit.py `contact_projector`)."""
    return np.eye(3) - np.outer(normal, normal) - np.outer(crease, crease)


def filtered_inverse_blocks(a: np.ndarray, blocks: np.ndarray, normal: np.ndarray, crease: np.ndarray) -> np.ndarray:
    """Every contact's block the filtered block's inverse (S_i A_ii S_i)^+ (kernels/implicit.py `filtered_block_inverse`)."""
    out = blocks.copy()
    for i in np.flatnonzero((normal * normal).sum(axis=1) > 0.0):
        t = projector(normal[i], crease[i])
        b = t @ a[3 * i:3 * i + 3, 3 * i:3 * i + 3] @ t
        out[i] = np.linalg.pinv(0.5 * (b + b.T), rcond=1e-7)
    return out


def spectrum(a: np.ndarray, blocks: np.ndarray, normal: np.ndarray, r0: np.ndarray, stop: float, deflate: list[int]) -> dict:
    """The non-zero eigenvalues of P^1/2 A P^1/2 (P the block-diagonal preconditioner): bounds, how many lie below
    1e-3 and 1e-2 and above 2, the three largest and whether each mode's largest part is on a collider contact; and for each k in
    `deflate` the iterations of PCG from r0 to `stop` deflated by the k smallest non-zero modes (`deflated_pcg`)."""
    n = blocks.shape[0]
    p = np.zeros_like(a)
    for i in range(n):
        p[3 * i:3 * i + 3, 3 * i:3 * i + 3] = 0.5 * (blocks[i] + blocks[i].T)
    w, v = np.linalg.eigh(p)
    half = v @ np.diag(np.sqrt(np.maximum(w, 0.0))) @ v.T
    values, vectors = np.linalg.eigh(half @ a @ half)
    keep = np.abs(values) > 1e-9 * np.abs(values).max()
    nonzero = values[keep]
    top = np.argsort(np.where(keep, values, -np.inf))[-3:][::-1]
    on_contact = []
    for k in top:
        mode = (half @ vectors[:, k]).reshape(n, 3)
        i = int(np.argmax(np.linalg.norm(mode, axis=1)))
        on_contact.append(bool(normal[i] @ normal[i] > 0.0))
    slowest = np.flatnonzero(keep)[np.argsort(values[keep])]
    deflated = {k: deflated_pcg(a, blocks, half @ vectors[:, slowest[:k]], r0.copy(), stop) for k in deflate}
    return {"smallest": float(nonzero.min()), "largest": float(nonzero.max()), "above_2": int((nonzero > 2.0).sum()),
            "below_1e-3": int((nonzero < 1e-3).sum()), "below_1e-2": int((nonzero < 1e-2).sum()),
            "top": [float(values[k]) for k in top], "top_on_contact": on_contact, "deflated": deflated}


def deflated_pcg(a: np.ndarray, blocks: np.ndarray, z: np.ndarray, r: np.ndarray, stop: float, cap: int = 5000) -> int:
    """`pcg` deflated by the columns of z (Saad, Yeung, Erhel and Guyomarc'h 2000): the start takes the answer's part
    in span(z), x0 = z E^-1 z^T r (E = z^T A z), and every preconditioned residual is projected by I - z E^-1 (A z)^T,
    keeping the search A-orthogonal to z. With no columns it is `pcg`."""
    n = blocks.shape[0]
    az = a @ z
    e = z.T @ az

    def project(v):
        return v - z @ np.linalg.solve(e, az.T @ v) if z.shape[1] else v  # (no columns: nothing to project)

    def precondition(v):
        return project(np.einsum("nij,nj->ni", blocks, v.reshape(n, 3)).reshape(-1))

    if z.shape[1]:
        r = r - az @ np.linalg.solve(e, z.T @ r)
    w = precondition(r)
    p, rw = w.copy(), r @ w
    for k in range(cap):
        q = a @ p
        alpha = rw / (p @ q)
        r = r - alpha * q
        if np.linalg.norm(r) <= stop:
            return k + 1
        w = precondition(r)
        rw_next = r @ w
        p, rw = w + (rw_next / rw) * p, rw_next
    return cap


def main(argv=None) -> int:
    import warp as wp

    args = parse_args(argv)
    wp.config.quiet = True
    wp.init()
    from cloth_warp.cli import parse_set

    overrides = parse_set(args.set)
    rows = []
    for mode in args.modes:
        s = read_system(args.scene, mode, args.frame, overrides)
        row = {"mode": mode, "particles": s["particles"], "contacts": int(((s["normal"] ** 2).sum(axis=1) > 0).sum()),
               "start": s["start"], "run": s["iterations"], "numpy": pcg(s["a"], s["blocks"], s["r0"].copy(), s["stop"]),
               "filtered_inverse": pcg(s["a"], filtered_inverse_blocks(s["a"], s["blocks"], s["normal"], s["crease"]), s["r0"].copy(),
                                       s["stop"]),
               **spectrum(s["a"], s["blocks"], s["normal"], s["r0"], s["stop"], args.deflate)}
        rows.append(row)
        print(row, flush=True)
    command = ("python benchmarks/bench_contact_spectrum.py " + " ".join(sys.argv[1:] if argv is None else argv)).strip()
    lines = [f"# bench_contact_spectrum: one step's linear system, `{args.scene}` frame {args.frame}, first solve", "",
             f"Machine: {platform.machine()}, Python {platform.python_version()}, Warp {wp.config.version}, device cpu. "
             f"Command: `{command}`", "",
             "Modes as in bench_contacts.py. Iterations: the run's float32 CG, then float64 PCG in numpy on the read-out system "
             "with the same start and stop, as run and with every contact's preconditioner block the filtered block's inverse. "
             "Spectrum: the non-zero eigenvalues of P^1/2 (S A S) P^1/2.", "",
             "| mode | particles | collider contacts in the solve | start (relative residual) | CG its in the run | numpy | numpy, filtered-inverse "
             "blocks | smallest eigenvalue | below 1e-3 | below 1e-2 | largest | eigenvalues > 2 | three largest (on a contact?) | "
             "deflated by the k slowest modes (k: its) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|"]
    for r in rows:
        top = ", ".join(f"{v:.2f}{' (c)' if c else ''}" for v, c in zip(r["top"], r["top_on_contact"]))
        lines.append(f"| {r['mode']} | {r['particles']} | {r['contacts']} | {r['start']:.2f} | {r['run']} | {r['numpy']} | "
                     f"{r['filtered_inverse']} | {r['smallest']:.2e} | {r['below_1e-3']} | {r['below_1e-2']} | {r['largest']:.2f} | "
                     f"{r['above_2']} | {top} | {', '.join(f'{k}: {v}' for k, v in r['deflated'].items()) or '-'} |")
    write_results(args.out, lines, {"command": command, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
