"""Import a cloth_warp USD cache into Blender at the cache's own frame rate.

Blender's USD importer leaves the scene at its frame rate (24 fps for a new scene) whatever the cache's
``timeCodesPerSecond``: a 60 fps cache then plays 2.5x too slowly. This helper imports the cache and sets the scene's
frame rate and range from the stage. Run it inside Blender, from a shell::

    blender --python "$(python -c 'import cloth_warp.blender_import as m; print(m.__file__)')" -- out/cache.usdc

(add ``--fps 60`` where Blender's Python has no ``pxr`` module to read the rate from), or from Blender's Python
console: ``import cloth_warp.blender_import as m; m.import_cache("out/cache.usdc")`` (with cloth_warp on Blender's
``sys.path``). Only this file is needed; it imports nothing else from cloth_warp.
"""

from __future__ import annotations

import math
import sys


def blender_frame_rate(fps: float) -> tuple[int, float]:
    """Blender's (render.fps, render.fps_base) for a rate in frames per second: Blender plays fps / fps_base, with an
    integer fps (29.97 -> (30, 1.001), 60 -> (60, 1.0))."""
    if not (math.isfinite(fps) and fps > 0.0):
        raise ValueError(f"the frame rate must be a number > 0, got {fps!r}")
    whole = max(1, round(fps))
    return whole, whole / fps


def cache_timing(path: str) -> tuple[float, float, float]:
    """(timeCodesPerSecond, start time code, end time code) of a USD stage (needs the ``pxr`` module)."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    return float(stage.GetTimeCodesPerSecond()), float(stage.GetStartTimeCode()), float(stage.GetEndTimeCode())


def import_cache(path: str, fps: float | None = None) -> None:
    """Import the cache with Blender's USD importer, then set the scene's frame rate (`fps`, default: the cache's)
    and frame range to the cache's."""
    import bpy

    start = end = None
    if fps is None:
        fps, start, end = cache_timing(path)
    bpy.ops.wm.usd_import(filepath=str(path))
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = blender_frame_rate(fps)
    if start is not None:
        scene.frame_start, scene.frame_end = int(start), int(end)


def main(argv: list[str]) -> None:
    args = argv[argv.index("--") + 1:] if "--" in argv else argv[1:]
    fps = None
    if "--fps" in args:
        k = args.index("--fps")
        fps = float(args[k + 1])
        del args[k:k + 2]
    if len(args) != 1:
        raise SystemExit("usage: blender --python blender_import.py -- CACHE.usdc [--fps FPS]")
    import_cache(args[0], fps)


if __name__ == "__main__":
    main(sys.argv)
