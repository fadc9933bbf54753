"""The cloth-warp command line: run a scene, with progress on a terminal and a summary at the end."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tomllib

from . import __version__

EXIT_OK, EXIT_BAD_INPUT, EXIT_DIVERGED, EXIT_INTERRUPTED = 0, 2, 3, 130


def _parse_set(items):
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set expects key.path=value, got {item!r}")
        try:
            out[key] = tomllib.loads(f"v = {value}")["v"]
        except tomllib.TOMLDecodeError:
            out[key] = value  # a bare string
    return out


def _progress(quiet: bool):
    tty = sys.stderr.isatty()

    def show(frame, total, stats, elapsed):
        if quiet:
            return
        ms = 1e3 * elapsed / frame
        eta = ms * (total - frame) / 1e3
        line = f"frame {frame}/{total}  {ms:.1f} ms/frame  ETA {eta:.1f} s  max strain {stats.max_strain:.3f}"
        if tty:
            sys.stderr.write("\r" + line + ("\n" if frame == total else ""))
        elif frame == total or frame % max(1, total // 10) == 0:
            sys.stderr.write(line + "\n")
        sys.stderr.flush()

    return show


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="cloth-warp", description="Differentiable cloth simulation in NVIDIA Warp.")
    parser.add_argument("--version", action="version", version=f"cloth-warp {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="simulate a scene file and write its frames")
    run.add_argument("scene")
    run.add_argument("-o", "--output", help="output file (.npz); default from the scene")
    run.add_argument("--frames", type=int)
    run.add_argument("--fps", type=float)
    run.add_argument("--device", help="cpu or cuda")
    run.add_argument("--set", action="append", metavar="KEY.PATH=VALUE", help="override a scene key (TOML value)")
    run.add_argument("--stats", help="write the summary as JSON to this file")
    run.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from .scene import SceneError, run_scene
    from .topology import MeshError

    try:
        summary = run_scene(args.scene, _parse_set(args.set), output=args.output, frames=args.frames, fps=args.fps,
                            device=args.device, progress=_progress(args.quiet))
    except (SceneError, MeshError, ValueError, KeyError, FileNotFoundError) as exc:
        print(f"cloth-warp: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if args.stats:
        with open(args.stats, "w") as fh:
            json.dump(summary, fh, indent=1)
    print(f"{summary['status']}: {summary['frames']} frames of {summary['particles']} particles ({summary['integrator']}), "
          f"{summary['wall_s']:.2f} s wall, {summary['ms_per_frame']:.1f} ms/frame, max strain {summary['max_strain']:.3f}, "
          f"solver iterations/step {summary['mean_solver_iterations']:.0f} -> {summary['output']}")
    if summary["status"] == "diverged":
        print(summary.get("message", ""), file=sys.stderr)
        return EXIT_DIVERGED
    if summary["status"] == "interrupted":
        return EXIT_INTERRUPTED
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
