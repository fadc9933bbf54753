"""Check: cloth_warp caches imported into Blender come in as they are.

Blender itself runs headless here as the `bpy` module from PyPI (Blender built as a Python module) in a Python of its
own, not in the project's environment (bpy pins its Python version and is ~400 MB): `--blender-python` names it. Three
shipped scenes, coarsened, are run and cached by this Python (`run_scene`); each cache is then imported into an empty
Blender scene with `cloth_warp/blender_import.py` (loaded from its file, as a user's Blender loads it) and compared, frame
by frame, with what the cache holds:
- the scene's frame rate and range (Blender's importer alone leaves 24 fps);
- every mesh's world-space points at every frame (cloth, and the colliders: the walking body's point cache, the ball
  tessellated within 0.5 mm, the Cusick pedestal), after Blender's y-up to z-up turn;
- the per-vertex strain primvar at every frame (a Blender attribute), the velocities (the `velocity` attribute), UVs
  (the Cusick disc's too);
- each mesh's material: the UsdPreviewSurface colour as the Principled BSDF's base colour.

Run:  python3.11 -m venv .bpy && .bpy/bin/pip install bpy==5.0.1
      python benchmarks/check_blender.py --blender-python .bpy/bin/python
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import subprocess
import sys
import tempfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

# (scene, overrides, frames): coarse enough to run in seconds, each with what a DCC must show
SCENES = [("skirt_walk", {"cloth.edge_length": 0.04, "dressing.settle": 0.5}, 8),   # garment, walking body, attachments
          ("drape_sphere", {"cloth.grid.resolution": [16, 16]}, 6),                 # a round collider
          ("cusick", {"cloth.disc.rings": 8}, 4)]                                      # the disc's UVs, the pedestal


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--blender-python", help="a Python with the bpy module (pip install bpy)")
    p.add_argument("--inside", help=argparse.SUPPRESS)  # (the Blender side: the expectations' JSON file)
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "check_blender.md"))
    return p.parse_args(argv)


def expectations(path: pathlib.Path) -> dict:
    """What the cache at `path` holds, read with pxr: its timing and, per mesh prim, per frame, the world-space points
    turned z-up as Blender shows a y-up stage ((x, y, z) -> (x, -z, y)), strain and velocities, its UVs and material."""
    from pxr import Usd, UsdGeom, UsdShade

    stage = Usd.Stage.Open(str(path))
    first, last = int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode())
    meshes = {}
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        mesh, xf = UsdGeom.Mesh(prim), UsdGeom.Xformable(prim)
        frames = []
        for tc in range(first, last + 1):
            m = np.asarray(xf.ComputeLocalToWorldTransform(tc), float)
            x = np.asarray(mesh.GetPointsAttr().Get(tc), float) @ m[:3, :3] + m[3, :3]
            strain = UsdGeom.PrimvarsAPI(prim).GetPrimvar("strain")
            vel = mesh.GetVelocitiesAttr().Get(tc)
            frames.append({"points": np.stack([x[:, 0], -x[:, 2], x[:, 1]], 1).tolist(),
                           "strain": np.asarray(strain.ComputeFlattened(tc), float).tolist() if strain and strain.HasValue() else None,
                           "velocity": None if vel is None else np.asarray(vel, float).tolist()})
        shader = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0].ComputeSurfaceSource()[0]
        meshes[prim.GetName()] = {"frames": frames, "uv": UsdGeom.PrimvarsAPI(prim).HasPrimvar("st"),
                                  "color": list(shader.GetInput("diffuseColor").Get())}
    return {"path": str(path), "fps": stage.GetTimeCodesPerSecond(), "first": first, "last": last, "meshes": meshes}


def inside_blender(expected_path: str) -> None:
    """The Blender side: import each cache with cloth_warp/blender_import.py into an empty scene and compare (prints
    one JSON line of results)."""
    import importlib.util

    import bpy

    spec = importlib.util.spec_from_file_location("blender_import", ROOT / "cloth_warp" / "blender_import.py")
    helper = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(helper)
    results = []
    for exp in json.loads(pathlib.Path(expected_path).read_text()):
        bpy.ops.wm.read_factory_settings(use_empty=True)
        helper.import_cache(exp["path"], fps=exp["fps"])  # (Blender's Python has no pxr to read the rate from)
        scene = bpy.context.scene
        row = {"path": exp["path"], "fps": scene.render.fps / scene.render.fps_base,
               "range": [scene.frame_start, scene.frame_end], "meshes": {}}
        objects = {o.name: o for o in scene.objects if o.type == "MESH"}
        for name, m in exp["meshes"].items():
            obj = objects.get(name)
            if obj is None:
                row["meshes"][name] = {"found": False, "objects": sorted(objects)}
                continue
            worst = {"points": 0.0, "strain": 0.0, "velocity": 0.0}
            seen = {"strain": False, "velocity": False}
            for k, frame in enumerate(m["frames"]):
                scene.frame_set(exp["first"] + k)
                ev = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
                me = ev.to_mesh()
                co = np.empty(len(me.vertices) * 3)
                me.vertices.foreach_get("co", co)
                w = np.asarray(ev.matrix_world)
                x = co.reshape(-1, 3) @ w[:3, :3].T + w[:3, 3]
                want = np.asarray(frame["points"])
                worst["points"] = max(worst["points"], float(np.abs(x - want).max()) if x.shape == want.shape else float("inf"))
                for key, attr in (("strain", "strain"), ("velocity", "velocity")):
                    a = me.attributes.get(attr)
                    if frame[key] is not None and a is not None and a.domain == "POINT":
                        n = 3 if a.data_type == "FLOAT_VECTOR" else 1
                        v = np.empty(len(a.data) * n)
                        a.data.foreach_get("vector" if n == 3 else "value", v)
                        ref = np.asarray(frame[key], float).reshape(-1)
                        worst[key] = max(worst[key], float(np.abs(v - ref).max()) if ref.size == v.size else float("inf"))
                        seen[key] = True
                ev.to_mesh_clear()
            mat = obj.active_material
            bsdf = next((n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED"), None) if mat and mat.use_nodes else None
            color = list(bsdf.inputs["Base Color"].default_value)[:3] if bsdf else None
            row["meshes"][name] = {"found": True, "vertices": len(obj.data.vertices), "points_error": worst["points"],
                                   "strain_error": worst["strain"] if seen["strain"] else None,
                                   "velocity_error": worst["velocity"] if seen["velocity"] else None,
                                   "uv_layers": [u.name for u in obj.data.uv_layers], "material": mat.name if mat else None,
                                   "color_error": None if color is None else float(np.abs(np.subtract(color, m["color"])).max())}
        results.append(row)
    print("RESULTS " + json.dumps(results), flush=True)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.inside:
        inside_blender(args.inside)
        return 0
    if not args.blender_python:
        raise SystemExit("--blender-python: a Python with the bpy module is needed (see the docstring)")
    import warp as wp

    wp.config.quiet = True
    from cloth_warp.runner import run_scene

    tmp = pathlib.Path(tempfile.mkdtemp(prefix="cw_blender_"))
    expected, runs = [], {}
    for name, overrides, frames in SCENES:
        out = tmp / f"{name}.usdc"
        summary = run_scene(name, overrides, output=out, frames=frames, device="cpu")
        assert summary["status"] == "complete", summary
        expected.append(expectations(out))
        runs[str(out)] = name
    (tmp / "expected.json").write_text(json.dumps(expected))
    proc = subprocess.run([args.blender_python, str(pathlib.Path(__file__).resolve()), "--inside", str(tmp / "expected.json")],
                          capture_output=True, text=True, timeout=1800)
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("RESULTS ")), None)
    if line is None:
        raise SystemExit(f"Blender side failed (exit {proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    results = json.loads(line[len("RESULTS "):])
    version = subprocess.run([args.blender_python, "-c", "import bpy; print(bpy.app.version_string)"], capture_output=True,
                             text=True).stdout.strip().splitlines()[-1]
    command = "python benchmarks/check_blender.py --blender-python BPY_PYTHON"
    lines = ["# check_blender: caches imported into Blender, frame by frame", "",
             f"Blender {version} (the `bpy` module from PyPI, headless), imported with `cloth_warp/blender_import.py`; "
             f"caches written by cloth_warp on {platform.machine()}, Python {platform.python_version()}, Warp {wp.config.version}. "
             f"Command: `{command}`", "",
             "Errors are the largest over every frame and vertex: points [m] in world space against the cache's (turned "
             "z-up), strain against the cache's primvar, velocity [m/s], the material's base colour against its "
             "UsdPreviewSurface diffuseColor.", "",
             "| scene | frame rate in Blender (cache) | frame range (cache) | mesh | vertices | points error [m] | strain error | "
             "velocity error | UV layers (the cache's) | material | colour error |",
             "|---|---|---|---|---:|---:|---:|---:|---|---|---:|"]
    for exp, row in zip(expected, results):
        for name, m in row["meshes"].items():
            if not m["found"]:
                lines.append(f"| {runs[row['path']]} | | | {name} | not found (meshes: {', '.join(m['objects'])}) | | | | | | |")
                continue
            fmt = lambda v: "not read" if v is None else f"{v:.2g}"  # noqa: E731
            lines.append(f"| {runs[row['path']]} | {row['fps']:g} ({exp['fps']:g}) | {row['range'][0]}-{row['range'][1]} "
                         f"({exp['first']}-{exp['last']}) | {name} | {m['vertices']} | {m['points_error']:.2g} | {fmt(m['strain_error'])} | "
                         f"{fmt(m['velocity_error'])} | {', '.join(m['uv_layers']) or 'none'} ({'st' if exp['meshes'][name]['uv'] else 'none'}) | {m['material']} | {fmt(m['color_error'])} |")
    for row in results:
        row["path"] = runs[row["path"]]
    from reports import write_results

    write_results(args.out, lines, {"command": command, "blender": version, "scenes": [s[:2] for s in SCENES], "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
