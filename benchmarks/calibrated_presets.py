"""Calibrated presets: every material preset simulated in three textile tests and set against its published values.

    python benchmarks/calibrated_presets.py [--presets denim,knit] [--no-cusick] [--cusick-frames 240]
                                            [--device cpu|cuda] [--out benchmarks/results/calibrated_presets]

Per preset (cloth_warp.materials.PRESETS), with cloth_warp's Python API:

* ASTM D1388 cantilever, warp and weft: a strip 25 mm wide cut along the warp (grid ``warp_angle=0``) or the
  weft (``warp_angle=90``), clamped by its first two columns, overhang l = 2 c (c the material's Peirce
  bending length (B / (rho_A g))^(1/3)), 20 cells along the overhang, cells at most 3:1; implicit Euler with
  global damping 2 /s, 100 steps of 0.05 s, no strain limit. The chord angle from the clamp edge to the tip
  is measured and turned into a bending length through the heavy elastica (docs/physics.md 1(a)): the
  alpha = (l / c)^3 whose chord angle it is gives c_sim = l / alpha^(1/3) (41.5 deg <-> alpha = 8.004).
* Tensile stiffness, warp and weft: a strip 25 mm x 250 mm hanging from its clamped top row (5 x 40 cells)
  under a gravity g' chosen for 0.5 % strain at the top; its self-weight elongation rho_A g' L^2 / (2 C)
  gives C_sim [N/m]. Published: the material's stretch_stiffness (Wang et al.: ArcSim's 2 c); a free strip
  measures C (1 - G^2 / (C_warp C_weft)) (FabricMaterial.stretch_stiffness_at), shown beside it.
* Cusick drape coefficient: scenes/cusick.toml as shipped (30 cm disc of 20 rings on an 18 cm pedestal,
  self-collision, implicit Euler with 2 substeps at 60 fps) with ``material.preset`` set, run for
  --cusick-frames frames (default 240 = 4 s; with membrane elements and plate stencils on the disc, cotton, silk
  and wool still change by 0.03-0.04 over the last 60 frames); the coefficient of the last frame and of the frame
  60 earlier (a settling check).

Writes <out>.json and <out>.md (the table) and replaces the table in docs/calibrated-presets.md between its
``<!-- calibrated-presets:start -->`` / ``end`` markers, so one command regenerates the document's numbers.
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import platform
import sys
import tempfile
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

import cloth_warp as cw  # noqa: E402
from cloth_warp.materials import GRAVITY, PRESETS, WANG_2011, WANG_2011_PRESETS  # noqa: E402

DOC = ROOT / "docs" / "calibrated-presets.md"
MARK_START, MARK_END = "<!-- calibrated-presets:start -->", "<!-- calibrated-presets:end -->"

STRIP_WIDTH = 0.025  # ASTM D1388: 25 mm strips
CANTILEVER_SEGMENTS = 20
TENSILE_LENGTH, TENSILE_CELLS = 0.25, (5, 40)
TENSILE_STRAIN = 0.005  # strain at the clamp under the scaled self-weight

# Published drape coefficients for the presets' fabrics. None found for these fabrics (see
# docs/calibrated-presets.md, "Cusick"): the column stays empty rather than borrow a number.
PUBLISHED_DRAPE: dict[str, tuple[float, str]] = {}


# --- heavy elastica (docs/physics.md 1(a)) ---------------------------------------------------------------

def elastica_chord_angle(alpha: float, nodes: int = 100) -> float:
    """Chord angle [deg] below horizontal from the clamp to the tip of the heavy elastica at alpha = q L^3 / B:
    phi'' = -alpha (1 - s) cos phi, phi(0) = 0, phi'(1) = 0, solved by shooting with RK4 (1e-6 deg at 100 nodes)."""
    from scipy.optimize import brentq

    h = 1.0 / nodes

    def rhs(s, p, dp):
        return dp, -alpha * (1.0 - s) * math.cos(p), math.cos(p), math.sin(p)

    def shoot(slope):
        p, dp, x, z, s = 0.0, slope, 0.0, 0.0, 0.0
        for _ in range(nodes):
            k1 = rhs(s, p, dp)
            k2 = rhs(s + h / 2, p + h / 2 * k1[0], dp + h / 2 * k1[1])
            k3 = rhs(s + h / 2, p + h / 2 * k2[0], dp + h / 2 * k2[1])
            k4 = rhs(s + h, p + h * k3[0], dp + h * k3[1])
            p, dp = p + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]), dp + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
            x, z = x + h / 6 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2]), z + h / 6 * (k1[3] + 2 * k2[3] + 2 * k3[3] + k4[3])
            s += h
        return dp, x, z

    slope = brentq(lambda k: shoot(k)[0], 0.0, alpha, xtol=1e-12)  # phi'(0) = alpha int (1 - s) cos phi <= alpha / 2
    _, x, z = shoot(slope)
    return math.degrees(math.atan2(z, x))


def elastica_alpha(chord_deg: float) -> float:
    """The alpha = (l / c)^3 whose heavy-elastica chord angle is `chord_deg` (0 < chord_deg < 90)."""
    from scipy.optimize import brentq

    return math.exp(brentq(lambda la: elastica_chord_angle(math.exp(la)) - chord_deg, math.log(0.01), math.log(300.0), xtol=1e-10))


# --- simulations ---------------------------------------------------------------------------------------

def _settle(model, steps: int, dt: float):
    solver = cw.SolverImplicitEuler(model, strain_limit=None, tolerance=1e-5, max_iterations=4000)
    s0, s1, control = model.state(), model.state(), model.control()
    for _ in range(steps):
        solver.step(s0, s1, control, dt)
        s0, s1 = s1, s0
    return s0


def cantilever_bending_length(material, direction: str, device=None, segments: int = CANTILEVER_SEGMENTS,
                              steps: int = 100, dt: float = 0.05) -> dict:
    """ASTM D1388 on a strip cut along `direction` ("warp" / "weft"): the simulated bending length [m]."""
    mat = material.replace(damping=0.0, drag_coefficient=0.0)
    c_material = mat.bending_length if direction == "warp" else mat.bending_length_weft
    overhang = 2.0 * c_material
    a = overhang / segments
    rows = max(2, math.ceil(STRIP_WIDTH / (3.0 * a) - 1e-9))  # cells at most 3:1 (long across the strip)
    b = cw.ModelBuilder(global_damping=2.0)
    strip = b.add_cloth_grid(resolution=(segments + 1, rows), size=(overhang + a, STRIP_WIDTH), position=(-a, 0.0, 0.0),
                             material=mat, rotation=cw.quat_from_axis_angle((1, 0, 0), 90.0),
                             warp_angle=0.0 if direction == "warp" else 90.0)
    idx = strip.indices().reshape(rows + 1, segments + 2)
    b.pin(idx[:, :2].ravel())
    model = b.finalize(device)
    state = _settle(model, steps, dt)
    tip = state.particle_q.numpy()[idx[:, -1]].mean(0)
    chord = math.degrees(math.atan2(-tip[1], tip[0]))
    speed = float(np.abs(state.particle_qd.numpy()).max())
    c_sim = overhang / elastica_alpha(chord) ** (1.0 / 3.0)
    return {"published": c_material, "simulated": c_sim, "chord_angle_deg": chord, "overhang": overhang,
            "cells": [segments, rows], "max_speed": speed}


def tensile_stiffness(material, direction: str, device=None, steps: int = 120, dt: float = 0.02) -> dict:
    """A strip cut along `direction` hanging under a scaled self-weight: the simulated stiffness [N/m]."""
    mat = material.replace(damping=0.0, drag_coefficient=0.0)
    c_material = mat.stretch_stiffness if direction == "warp" else mat.stretch_weft
    length = TENSILE_LENGTH
    g = TENSILE_STRAIN * c_material / (mat.areal_density * length)
    b = cw.ModelBuilder(gravity=(0.0, -g, 0.0), global_damping=5.0)
    nx, ny = TENSILE_CELLS
    # The strip hangs along the grid's y axis: the warp along it (90) for a warp strip, across (0) for a weft strip.
    strip = b.add_cloth_grid(resolution=(nx, ny), size=(STRIP_WIDTH, length), material=mat,
                             warp_angle=90.0 if direction == "warp" else 0.0)
    b.pin(strip.select("edge:top"))
    model = b.finalize(device)
    state = _settle(model, steps, dt)
    q = state.particle_q.numpy()
    top, bottom = strip.select("edge:top"), strip.select("edge:bottom")
    elongation = float(q[top, 1].mean() - q[bottom, 1].mean()) - length
    c_sim = mat.areal_density * g * length**2 / (2.0 * elongation)
    free = mat.stretch_stiffness_at(0.0 if direction == "warp" else 90.0)
    return {"published": c_material, "free_strip": free, "simulated": c_sim, "gravity": g,
            "max_speed": float(np.abs(state.particle_qd.numpy()).max())}


def cusick_drape(name: str, frames: int, device=None, workdir=None, settings: dict | None = None) -> dict:
    """The Cusick drape coefficient of preset `name` on scenes/cusick.toml (with `settings`: scene values set as
    `cloth-warp run --set` does), last frame and 60 frames before, and the largest particle speed over the last frame."""
    from cloth_warp.drape import drape_coefficient
    from cloth_warp.scene import build_model, load_scene

    out = pathlib.Path(workdir) / f"cusick_{name}.npz"
    overrides = {**(settings or {}), "material.preset": name, "output.frames": frames}
    t0 = time.perf_counter()
    summary = cw.run_scene(ROOT / "scenes" / "cusick.toml", overrides, output=out, device=device)
    wall = time.perf_counter() - t0
    scene = load_scene(ROOT / "scenes" / "cusick.toml", overrides)
    tri = build_model(scene, "cpu").tri_indices.numpy()
    reader = cw.CacheReader(out)
    earlier = max(0, reader.frame_count - 61)
    dc_earlier = drape_coefficient(reader.points(earlier), tri, pedestal_radius=float(scene.get("measure.cusick.pedestal_radius")),
                                   disc_radius=float(scene.get("cloth.disc.radius")))
    published = PUBLISHED_DRAPE.get(name)
    last = reader.frame_count - 1
    speed = float(np.linalg.norm(reader.points(last) - reader.points(last - 1), axis=1).max() * float(scene.get("output.fps")))
    return {"simulated": summary.get("drape_coefficient"), "simulated_60_frames_earlier": dc_earlier, "max_speed_last_frame": speed,
            "status": summary.get("status"), "frames": frames, "wall_s": wall,
            "published": published[0] if published else None, "source": published[1] if published else None}


# --- sources and table -----------------------------------------------------------------------------------

def source_of(name: str) -> str:
    fabric = WANG_2011_PRESETS.get(name)
    if fabric:
        return f"Wang et al. 2011 {fabric}"
    return "typical KES value (not a measurement of one fabric)"


def rel(sim, ref):
    return None if sim is None or ref in (None, 0.0) else sim / ref - 1.0


def table_rows(results: dict) -> list[str]:
    lines = ["| preset | quantity | published / material value | source | simulated | rel. error |",
             "|---|---|---:|---|---:|---:|"]
    for name, r in results.items():
        src = source_of(name)
        for d in ("warp", "weft"):
            c = r["cantilever"][d]
            lines.append(f"| {name} | bending length c, {d} [cm] | {100 * c['published']:.3f} | {src} (Peirce c from B, rho_A) "
                         f"| {100 * c['simulated']:.3f} (chord {c['chord_angle_deg']:.1f} deg) | {100 * rel(c['simulated'], c['published']):+.2f} % |")
        for d in ("warp", "weft"):
            t = r["tensile"][d]
            lines.append(f"| {name} | tensile stiffness, {d} [N/m] | {t['published']:.1f} (free strip {t['free_strip']:.1f}) | {src} "
                         f"| {t['simulated']:.1f} | {100 * rel(t['simulated'], t['published']):+.2f} % (vs free strip "
                         f"{100 * rel(t['simulated'], t['free_strip']):+.2f} %) |")
        cu = r.get("cusick")
        if cu:
            pub = "—" if cu["published"] is None else f"{cu['published']:.2f}"
            src_dc = cu["source"] or "no published value found for this fabric"
            sim = "—" if cu["simulated"] is None else f"{cu['simulated']:.3f} ({cu['simulated_60_frames_earlier']:.3f} at -1 s" + (
                f"; {1e3 * cu['max_speed_last_frame']:.1f} mm/s)" if "max_speed_last_frame" in cu else ")")
            err = "—" if cu["published"] is None or cu["simulated"] is None else f"{100 * rel(cu['simulated'], cu['published']):+.1f} %"
            lines.append(f"| {name} | Cusick drape coefficient | {pub} | {src_dc} | {sim} | {err} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", default=",".join(PRESETS), help="comma-separated preset names (default: all)")
    ap.add_argument("--no-cusick", action="store_true", help="skip the Cusick drape runs (the slow part)")
    ap.add_argument("--cusick-frames", type=int, default=240)
    ap.add_argument("--cusick-set", action="append", default=[], metavar="KEY=VALUE",
                    help="a value of scenes/cusick.toml for the drape runs, as `cloth-warp run --set` (repeatable)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default=str(HERE / "results" / "calibrated_presets"))
    ap.add_argument("--no-doc", action="store_true", help="do not rewrite the table in docs/calibrated-presets.md")
    args = ap.parse_args(argv)

    from cloth_warp.cli import parse_set

    settings = parse_set(args.cusick_set)
    names = [n.strip() for n in args.presets.split(",") if n.strip()]
    results, timings = {}, {}
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory() as work:
        for name in names:
            mat = PRESETS[name]
            t0 = time.perf_counter()
            r = {"cantilever": {d: cantilever_bending_length(mat, d, args.device) for d in ("warp", "weft")},
                 "tensile": {d: tensile_stiffness(mat, d, args.device) for d in ("warp", "weft")}}
            timings[name] = {"strips_s": time.perf_counter() - t0}
            if not args.no_cusick:
                r["cusick"] = cusick_drape(name, args.cusick_frames, args.device, work, settings)
                timings[name]["cusick_s"] = r["cusick"]["wall_s"]
            results[name] = r
            print(f"{name}: " + ", ".join(f"{k} {v:.1f} s" for k, v in timings[name].items()), flush=True)
    total = time.perf_counter() - t_all

    rows = table_rows(results)
    command = "python benchmarks/calibrated_presets.py" + (" --no-cusick" if args.no_cusick else "") + \
        (f" --cusick-frames {args.cusick_frames}" if args.cusick_frames != 240 else "") + \
        "".join(f" --cusick-set {item}" for item in args.cusick_set)
    if set(names) != set(PRESETS):
        command += f" --presets {','.join(names)}"
    head = [f"Generated by `{command}` ({total:.0f} s on {platform.processor() or platform.machine()}, "
            f"device {args.device or 'default'}, cloth_warp {getattr(cw, '__version__', '?')}).", ""]
    text = "\n".join(head + rows) + "\n"
    print(text)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text("# Calibrated presets\n\n" + text)
    meta = {"command": command, "total_s": total, "timings_s": timings, "device": args.device,
            "setup": {"strip_width_m": STRIP_WIDTH, "cantilever_segments": CANTILEVER_SEGMENTS,
                      "tensile_length_m": TENSILE_LENGTH, "tensile_cells": TENSILE_CELLS,
                      "tensile_strain": TENSILE_STRAIN, "cusick_frames": args.cusick_frames, "cusick_settings": settings,
                      "g": GRAVITY},
            "sources": {n: source_of(n) for n in names}, "wang_2011": {WANG_2011_PRESETS[n]: WANG_2011[WANG_2011_PRESETS[n]]
                                                                        for n in names if n in WANG_2011_PRESETS},
            "results": results}
    out.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n")
    if not args.no_doc and DOC.is_file() and set(names) == set(PRESETS):
        doc = DOC.read_text()
        if MARK_START in doc and MARK_END in doc:
            pre, rest = doc.split(MARK_START, 1)
            _, post = rest.split(MARK_END, 1)
            DOC.write_text(pre + MARK_START + "\n" + text + MARK_END + post)
    return 0


if __name__ == "__main__":
    sys.exit(main())
