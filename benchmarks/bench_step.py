"""Benchmark: what one frame of each shipped fixed-step scene costs - ms, eager Warp work, graph replays, host reads.

For every shipped scene but the fitting ones (scenes/*.toml except fit_*), built as `cloth-warp run` builds it
(cloth_warp.scene.build_model / build_solver / build_wind, runner.load_kernels, a Simulator with the scene's
[solver] and [output] values): W warm-up frames, then F timed frames (each frame timed on its own, the device
synchronised around it; the median is the result), then C counted frames under cloth_warp.profiling.LaunchCounter
(eager kernel launches, copies and fills, device loops, graph replays, host reads, allocations per frame; counted
apart from the timed frames so that the counter's wrappers cost the timing nothing). Also reported: whether the
Simulator records the frame as a graph (`capture`), and the cold start: seconds from an empty kernel cache to
the first frame of drape_sphere (implicit Euler, colliders, self-collision: the most kernel modules a shipped
scene needs), compile and first frame apart.

With --ref REV the same is measured at git revision REV, checked out into a temporary `git worktree` (with the
`cloth_warp/kernels -> ../kernels` link an installed tree has) and run with PYTHONPATH pointing there. Both trees
run in worker processes of their own that stay up across scenes (kernels load once) and take turns frame by
frame, so that the noise of a shared machine falls on both alike; the result is the ratio new / ref per scene: the
median over the timed frames of frame k's new / ref (the same simulated frame, run back to back: a frame's own work
and the noise of its moment cancel), and beside it the ratio of the total times. (A ratio of the two medians of
ms/frame mixes frames of different work - early frames of a falling cloth take more CG iterations - and moved
0.54-0.77 between runs of hanging_cloth here where the paired ratio moved 0.54-0.69.)
The counter is this tree's cloth_warp/profiling.py in both (loaded by path where REV lacks it). Ratios, not
absolute times, are the result (these machines are noisy).

Run:  python benchmarks/bench_step.py --ref e899fc8 --frames 10        (all scenes; a few minutes on 2 cores)
      python benchmarks/bench_step.py --scenes hanging_cloth drape_sphere --frames 5 --no-cold-start
      python benchmarks/bench_step.py --scenes hanging_cloth --profile   (per-stage table, frames not captured)
      python benchmarks/bench_step.py --device cuda:0 --scenes pile --set cloth.grid.resolution=[128,128] --out X.md
                                                                          (scene values overridden as `cloth-warp run --set`)
      python benchmarks/bench_step.py --ref a34246f --scenes pile drape_sphere --warmup 1 --frames 300 --no-cold-start \
          --set-new solver.collider_contacts=\"solve\" --set-new solver.tolerance=1e-4    (a mode the ref lacks, this tree only)
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import pathlib
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import traceback

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent
PROFILING = ROOT / "cloth_warp" / "profiling.py"
COLD_SCENE = "drape_sphere"
TAG = "@@bench_step "  # worker replies start with this (Warp and others may print to stdout too)


def shipped_scenes() -> list[str]:
    return [p.stem for p in sorted((ROOT / "scenes").glob("*.toml")) if not p.stem.startswith("fit_")]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=None, help="shipped scene names (default: all but fit_*)")
    p.add_argument("--frames", type=int, default=20, help="timed frames per scene (default 20)")
    p.add_argument("--warmup", type=int, default=3, help="frames run before timing (graph capture happens here; default 3)")
    p.add_argument("--count-frames", type=int, default=2, help="frames counted with LaunchCounter after the timed ones (default 2)")
    p.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    p.add_argument("--ref", metavar="REV", default=None, help="also measure git revision REV (a temporary worktree) and print new/ref")
    p.add_argument("--profile", action="store_true", help="also time the step's stages (cloth_warp.profiling.stage) over --frames "
                   "more frames run without graph capture, and print the per-stage table")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene value in every scene measured, as `cloth-warp run --set` (repeatable)")
    p.add_argument("--set-new", action="append", default=[], metavar="KEY=VALUE",
                   help="scene override for this tree only (with --ref: a mode the ref does not have, measured against the ref's default)")
    p.add_argument("--no-cold-start", action="store_true", help="skip the cold-start measurement (empty kernel cache)")
    p.add_argument("--out", default=None, help="default benchmarks/results/bench_step[_cuda].md (and .json beside it)")
    # internal: the worker processes
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--cold-worker", action="store_true", help=argparse.SUPPRESS)
    return p.parse_args(argv)


# -- worker side: runs in the tree under test (PYTHONPATH), counts with this tree's profiling.py --------------------

def _load_counter_module():
    """This tree's cloth_warp/profiling.py: the package's own module when the tree under test is this one, else
    loaded by path (a revision without it)."""
    try:
        import cloth_warp.profiling as prof

        if pathlib.Path(prof.__file__).resolve() == PROFILING.resolve():
            return prof
    except ImportError:
        pass
    return _profiling_by_path()


def _profiling_by_path():
    """This tree's cloth_warp/profiling.py as a module of its own (it imports nothing from cloth_warp)."""
    name = "_bench_step_profiling"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, PROFILING)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod  # dataclasses look their module up while the file runs
        spec.loader.exec_module(mod)
    return sys.modules[name]


def _stage_module(counter_module):
    """The module whose default timer the step's stages use: the tree's cloth_warp.profiling when it has one (a
    revision without stages gets the counter module's timer: only the benchmark's own "frame" stage)."""
    try:
        import cloth_warp.profiling as prof

        return prof
    except ImportError:
        return counter_module


class Bench:
    """One scene in a worker: the model, solver and Simulator built as `cloth-warp run` builds them."""

    def __init__(self, scene_name: str, device: str, overrides: dict | None = None):
        import warp as wp

        from cloth_warp.runner import find_scene, load_kernels
        from cloth_warp.scene import build_model, build_solver, load_scene

        self.wp = wp
        t = time.perf_counter()
        self.scene = load_scene(find_scene(scene_name), overrides or None)
        self.model = build_model(self.scene, device)
        self.solver = build_solver(self.scene, self.model)
        self.compile_s = load_kernels(self.solver, self.model.device)
        self.sim = self.simulator(self.solver)
        self.setup_s = time.perf_counter() - t

    def simulator(self, solver, **kwargs):
        from cloth_warp.scene import build_wind
        from cloth_warp.simulator import Simulator

        sc = self.scene
        return Simulator(self.model, solver, fps=float(sc.get("output.fps")), substeps=int(sc.get("solver.substeps")),
                         adaptive=bool(sc.get("solver.adaptive")), dt_min=float(sc.get("solver.dt_min")), wind=build_wind(sc), **kwargs)

    def frame(self, sim=None) -> float:
        """One frame's wall time [s], the device synchronised before and after."""
        sim = sim or self.sim
        self.wp.synchronize_device(self.model.device)
        t = time.perf_counter()
        sim.step_frame()
        self.wp.synchronize_device(self.model.device)
        return time.perf_counter() - t


def worker_main(args) -> None:
    """Serve commands (JSON lines on stdin), one reply line each on stdout."""
    import warp as wp

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    import cloth_warp
    import cloth_warp.kernels

    counter_mod = _load_counter_module()
    stages = _stage_module(counter_mod)
    bench = None
    out = sys.stdout

    def reply(obj):
        out.write(TAG + json.dumps(obj) + "\n")
        out.flush()

    reply({"ready": True, "cloth_warp": cloth_warp.__file__, "kernels": cloth_warp.kernels.__file__,
           "counter": counter_mod.__file__, "stages": getattr(stages, "__file__", None), "warp": wp.__version__})
    for line in sys.stdin:
        cmd = json.loads(line)
        try:
            op = cmd["op"]
            if op == "quit":
                return
            if op == "setup":
                bench = None
                bench = Bench(cmd["scene"], cmd["device"], cmd.get("overrides"))
                for _ in range(cmd["warmup"]):
                    bench.frame()
                sim = bench.sim
                reply({"particles": bench.model.particle_count, "substeps": sim.substeps, "capture": bool(getattr(sim, "capture", False)),
                       "setup_s": bench.setup_s, "compile_s": bench.compile_s, "integrator": bench.solver.name})
            elif op == "frame":
                if cmd.get("count"):
                    with counter_mod.LaunchCounter() as counts:
                        seconds = bench.frame()
                    reply({"s": seconds, "counts": counts.to_dict()})
                else:
                    seconds = bench.frame()
                    report = getattr(bench.sim, "frame_report", None)  # linear-solver iterations of the frame, re-runs
                    reply({"s": seconds, "its": getattr(report, "iterations", None), "reruns": getattr(report, "reruns", None)})
            elif op == "profile":
                from cloth_warp.scene import build_solver

                sim = bench.simulator(build_solver(bench.scene, bench.model), capture=False)  # stages run Python: no replay
                for _ in range(cmd["warmup"]):
                    sim.step_frame()
                stages.enable(bench.model.device)
                try:
                    for _ in range(cmd["frames"]):
                        with stages.stage("frame"):
                            sim.step_frame()
                    reply({"profile": stages.report(cmd["frames"]).to_dict()})
                finally:
                    stages.disable()
            else:
                reply({"error": f"unknown op {op!r}"})
        except Exception as exc:  # reported per scene; the worker goes on with the next
            reply({"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc(limit=6)})


def cold_worker_main(args) -> None:
    """From an empty kernel cache (WARP_CACHE_PATH, set by the caller) to the first frame of the cold-start scene."""
    t0 = time.perf_counter()
    import warp as wp

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    wp.config.kernel_cache_dir = os.environ["WARP_CACHE_PATH"]
    wp.init()
    import cloth_warp  # noqa: F401

    t_import = time.perf_counter()
    bench = Bench(COLD_SCENE, args.device)  # runner.load_kernels as `cloth-warp run` loads them (in parallel where the tree does)
    t_built = time.perf_counter()
    first = bench.frame()  # modules the runner's list misses load here, and a capture is recorded
    total = time.perf_counter() - t0
    cache = pathlib.Path(os.environ["WARP_CACHE_PATH"])
    found = (re.fullmatch(r"wp_(.+)_[0-9a-f]{6,}", p.name) for p in cache.rglob("wp_*") if p.is_dir())  # <version>/wp_<module>_<hash>
    modules = sorted({m.group(1).removeprefix("cloth_warp.kernels.") for m in found if m})
    print(TAG + json.dumps({"import_s": t_import - t0, "compile_s": bench.compile_s, "build_s": t_built - t_import - bench.compile_s,
                            "first_frame_s": first, "total_s": total, "modules": modules}), flush=True)


# -- parent side ------------------------------------------------------------------------------------------------------

class Worker:
    """A worker process for one tree (`pythonpath`: the worktree of a revision; None: this tree as installed)."""

    def __init__(self, label: str, pythonpath: str | None, device: str):
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        if pythonpath:
            env["PYTHONPATH"] = pythonpath + os.pathsep + env.get("PYTHONPATH", "") if env.get("PYTHONPATH") else pythonpath
        self.label = label
        self.proc = subprocess.Popen([sys.executable, str(pathlib.Path(__file__).resolve()), "--worker", "--device", device],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=pythonpath or ROOT)
        self.hello = self._read()

    def _read(self) -> dict:
        for line in self.proc.stdout:
            if line.startswith(TAG):
                return json.loads(line[len(TAG):])
        raise RuntimeError(f"{self.label} worker exited (code {self.proc.wait()})")

    def ask(self, **cmd) -> dict:
        self.proc.stdin.write(json.dumps(cmd) + "\n")
        self.proc.stdin.flush()
        return self._read()

    def close(self):
        if self.proc.poll() is None:
            try:
                self.proc.stdin.write(json.dumps({"op": "quit"}) + "\n")
                self.proc.stdin.close()
                self.proc.wait(timeout=30)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()


def make_worktree(rev: str) -> pathlib.Path:
    """REV checked out (detached) into a temporary worktree, with the cloth_warp/kernels link an installed tree has."""
    path = pathlib.Path(tempfile.mkdtemp(prefix="cw_bench_ref_")) / "tree"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "--quiet", str(path), rev], check=True)
    link = path / "cloth_warp" / "kernels"
    if not link.exists():
        link.symlink_to(pathlib.Path("..") / "kernels")
    return path


def remove_worktree(path: pathlib.Path) -> None:
    subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(path)], check=False, capture_output=True)
    subprocess.run(["git", "-C", str(ROOT), "worktree", "prune"], check=False, capture_output=True)
    shutil.rmtree(path.parent, ignore_errors=True)


def cold_start(pythonpath: str | None, device: str) -> dict:
    """Seconds from an empty kernel cache to the first frame of the cold-start scene, in a fresh process."""
    cache = tempfile.mkdtemp(prefix="cw_bench_cold_")
    env = dict(os.environ, WARP_CACHE_PATH=cache)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    try:
        t = time.perf_counter()
        p = subprocess.run([sys.executable, str(pathlib.Path(__file__).resolve()), "--cold-worker", "--device", device],
                           capture_output=True, text=True, env=env, cwd=pythonpath or ROOT)
        wall = time.perf_counter() - t
        for line in p.stdout.splitlines():
            if line.startswith(TAG):
                return {**json.loads(line[len(TAG):]), "process_s": wall}
        return {"error": (p.stderr.strip().splitlines() or ["failed"])[-1]}
    finally:
        shutil.rmtree(cache, ignore_errors=True)


def per_frame(counts: list[dict]) -> dict:
    """Mean per frame of the counted frames' counts (kernels: the eager launches by kernel, per frame)."""
    n = len(counts)
    out = {k: sum(c[k] for c in counts) / n for k in counts[0] if k != "kernels"}
    kernels: dict[str, float] = {}
    for c in counts:
        for k, v in c["kernels"].items():
            kernels[k] = kernels.get(k, 0.0) + v / n
    out["kernels"] = dict(sorted(kernels.items(), key=lambda kv: -kv[1]))
    return out


def measure_scene(workers: dict[str, Worker], scene: str, args) -> dict:
    row = {"scene": scene}
    for label, w in workers.items():
        overrides = {**args.overrides, **(args.new_overrides if label == "new" else {})}
        r = w.ask(op="setup", scene=scene, device=args.device, warmup=args.warmup, **({"overrides": overrides} if overrides else {}))
        row[label] = r
    live = [label for label in workers if "error" not in row[label]]
    times = {label: [] for label in live}
    its = {label: [] for label in live}
    for i in range(args.frames):  # take turns frame by frame, the first of each pair alternating
        for label in (live if i % 2 == 0 else live[::-1]):
            r = workers[label].ask(op="frame")
            if "error" in r:
                row[label] = {**row[label], **r}
                live.remove(label)
                continue
            times[label].append(r["s"])
            its[label].append(r.get("its"))
    for label in list(live):
        counts = []
        for _ in range(args.count_frames):
            r = workers[label].ask(op="frame", count=True)
            if "error" in r:
                row[label] = {**row[label], **r}
                live.remove(label)
                break
            counts.append(r["counts"])
        if counts:
            row[label]["per_frame"] = per_frame(counts)
    for label in live:
        t = times[label]
        row[label].update(ms_frame=1e3 * statistics.median(t), ms_frame_min=1e3 * min(t), ms_frames=[1e3 * x for x in t],
                          its_frame=statistics.median(its[label]) if None not in its[label] else None)
        if args.profile:
            r = workers[label].ask(op="profile", frames=args.frames, warmup=args.warmup)
            row[label]["profile"] = r.get("profile") or {"error": r.get("error")}
    return row


def main():
    args = parse_args()
    if args.worker:
        return worker_main(args)
    if args.cold_worker:
        return cold_worker_main(args)
    scenes = args.scenes or shipped_scenes()
    from cloth_warp.cli import parse_set

    args.overrides = parse_set(args.set)
    args.new_overrides = parse_set(args.set_new)
    unknown = [s for s in scenes if not (ROOT / "scenes" / f"{s}.toml").is_file()]
    if unknown:
        sys.exit(f"bench_step: unknown scene(s) {', '.join(unknown)}; shipped: {', '.join(shipped_scenes())}")
    tree = make_worktree(args.ref) if args.ref else None
    workers: dict[str, Worker] = {}
    rows, cold = [], {}
    try:
        if tree is not None:
            workers["ref"] = Worker("ref", str(tree), args.device)
        workers["new"] = Worker("new", None, args.device)
        for w in workers.values():
            print(f"{w.label}: cloth_warp from {pathlib.Path(w.hello['cloth_warp']).parent}, kernels from "
                  f"{pathlib.Path(w.hello['kernels']).parent}", flush=True)
        if tree is not None:  # the ref must run its own code and kernels
            for key in ("cloth_warp", "kernels"):
                assert pathlib.Path(workers["ref"].hello[key]).resolve().is_relative_to(tree.resolve()), workers["ref"].hello
        for scene in scenes:
            t = time.perf_counter()
            row = measure_scene(workers, scene, args)
            rows.append(row)
            print(summary_line(row) + f"  ({time.perf_counter() - t:.0f} s)", flush=True)
        for w in workers.values():
            w.close()
        if not args.no_cold_start:
            for label in (["ref"] if tree is not None else []) + ["new"]:
                cold[label] = cold_start(str(tree) if label == "ref" else None, args.device)
                print(f"cold start {label}: {cold_line(cold[label])}", flush=True)
    finally:
        for w in workers.values():
            w.close()
        if tree is not None:
            remove_worktree(tree)
    roots = {"ref": tree, "new": ROOT}
    write_report(args, rows, cold, {label: where_loaded(w.hello, roots[label]) for label, w in workers.items()})


def where_loaded(hello: dict, root) -> dict:
    """A worker's hello with the files it loaded named relative to its tree (this repository or the ref's worktree;
    the ref loads this tree's counter): no machine paths in the report."""
    out = dict(hello)
    for key, value in hello.items():
        if isinstance(value, str) and key != "warp":
            path = pathlib.Path(value).resolve()
            for base, name in ((pathlib.Path(root).resolve(), "tree"), (ROOT.resolve(), "repo")):
                if path.is_relative_to(base):
                    out[key] = f"{name}:{path.relative_to(base).as_posix()}"
                    break
    return out


def paired_ratios(new: dict, ref: dict) -> tuple[float, float]:
    """(median over frames of new / ref of the same frame, total new / total ref) of two workers' timed frames."""
    pairs = list(zip(new["ms_frames"], ref["ms_frames"]))
    return statistics.median(a / b for a, b in pairs), sum(a for a, _ in pairs) / sum(b for _, b in pairs)


def summary_line(row: dict) -> str:
    new, ref = row.get("new", {}), row.get("ref")
    if "error" in new:
        return f"{row['scene']}: new failed: {new['error']}"
    text = f"{row['scene']}: {new['ms_frame']:.1f} ms/frame, {new['per_frame']['eager']:.0f} eager ops/frame, capture {new['capture']}"
    if ref is not None:
        text += (f"; ref failed: {ref['error']}" if "error" in ref else
                 f"; ref {ref['ms_frame']:.1f} ms/frame, {ref['per_frame']['eager']:.0f} eager ops/frame; new/ref "
                 "{:.2f} per frame, {:.2f} in total".format(*paired_ratios(new, ref)))
    return text


def cold_line(c: dict) -> str:
    if "error" in c:
        return f"failed: {c['error']}"
    return (f"{c['total_s']:.1f} s to the first frame ({c['compile_s']:.1f} s compiling the runner's modules, first frame "
            f"{c['first_frame_s']:.1f} s, import {c['import_s']:.1f} s; {len(c['modules'])} modules: {_modules_text(c)})")


def _modules_text(c: dict) -> str:
    """The modules compiled (with their compile seconds where an older record measured them)."""
    times = c.get("module_s", {})
    return ", ".join(f"{m} {times[m]:.1f} s" if m in times else m for m in c["modules"])


def _num(x, fmt="{:.1f}"):
    return "" if x is None else fmt.format(x)


def write_report(args, rows, cold, hellos):
    import warp as wp

    has_ref = args.ref is not None
    argv = " ".join(sys.argv[1:])
    lines = [
        "# bench_step: one frame of each shipped fixed-step scene - time, eager Warp work, replays, host reads",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, Warp {wp.__version__}, "
        f"device {args.device}. Command: `python benchmarks/bench_step.py {argv}`",
        "",
        f"Per scene: {args.warmup} warm-up frames, {args.frames} timed frames (median; device synchronised around each), then "
        f"{args.count_frames} frames counted with `cloth_warp.profiling.LaunchCounter`."
        + (f" Reference: git revision `{args.ref}` in a temporary worktree, its worker taking turns with this tree's frame by "
           "frame (both see the same machine noise)." if has_ref else ""),
        "",
        "| scene | particles | steps/frame | captured | solver its/frame | ms/frame | "
        + ("ref ms/frame | new / ref (median per frame) | new / ref (total) |" if has_ref else ""),
        "|---|---:|---:|---|---:|---:|" + ("---:|---:|---:|" if has_ref else ""),
    ]
    for r in rows:
        new, ref = r.get("new", {}), r.get("ref", {})
        if "error" in new:
            lines.append(f"| {r['scene']} | failed: {new['error']} | | | | |" + (" | | |" if has_ref else ""))
            continue
        cap = ("yes" if new["capture"] else "no") + (f" (ref {'yes' if ref.get('capture') else 'no'})" if has_ref and "capture" in ref else "")
        line = f"| {r['scene']} | {new['particles']} | {new['substeps']} | {cap} | {_num(new.get('its_frame'), '{:.0f}')} | {new['ms_frame']:.1f} |"
        if has_ref:
            line += (f" failed: {ref['error']} | | |" if "error" in ref else
                     f" {ref['ms_frame']:.1f} | " + "{:.2f} | {:.2f} |".format(*paired_ratios(new, ref)))
        lines.append(line)
    lines += ["", "Warp work issued from Python per frame after warm-up (mean of the counted frames): eager kernel launches, "
              "eager copies + fills, device loops run from the host (`capture_while`), graph replays, host reads, array "
              "allocations" + ("; ref in brackets" if has_ref else "") + ":", "",
              "| scene | eager launches | copies + fills | host loops | replays | host reads | allocations | most launched eager kernels |",
              "|---|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        new, ref = r.get("new", {}), r.get("ref", {})
        if "per_frame" not in new:
            continue
        a, b = new["per_frame"], ref.get("per_frame") if has_ref else None

        def cell(key, fn=lambda pf, k: pf[k]):
            v = f"{fn(a, key):.0f}"
            return v + (f" [{fn(b, key):.0f}]" if b else "")

        fills = lambda pf, k: pf["copies"] + pf["fills"]  # noqa: E731
        top = ", ".join(f"{k} {v:.0f}" for k, v in list(a["kernels"].items())[:3])
        lines.append(f"| {r['scene']} | {cell('launches')} | {cell('', fills)} | {cell('loops')} | {cell('replays')} | "
                     f"{cell('reads')} | {cell('allocations')} | {top} |")
    if cold:
        lines += ["", f"Cold start (empty kernel cache, a fresh process; `{COLD_SCENE}`: implicit Euler, colliders, "
                  "self-collision): seconds to the first frame done; compile = `runner.load_kernels` as `cloth-warp run` calls it "
                  "(modules compiled in parallel where the tree does), the first frame includes modules loaded on first use:", "",
                  "| tree | to first frame [s] | compile [s] | first frame [s] | import [s] | modules compiled |", "|---|---:|---:|---:|---:|---|"]
        for label, c in cold.items():
            name = "this tree" if label == "new" else f"ref `{args.ref}`"
            if "error" in c:
                lines.append(f"| {name} | failed: {c['error']} | | | | |")
            else:
                lines.append(f"| {name} | {c['total_s']:.1f} | {c['compile_s']:.1f} | {c['first_frame_s']:.1f} | {c['import_s']:.1f} | "
                             f"{len(c['modules'])}: {_modules_text(c)} |")
    if args.profile:
        for r in rows:
            new = r.get("new", {})
            prof = new.get("profile")
            if not prof:
                continue
            lines += ["", f"Stages of `{r['scene']}` ({args.frames} frames without graph capture, device synchronised at every "
                      "stage boundary; `frame` is the benchmark's own stage around `step_frame`):", ""]
            if "error" in prof:
                lines.append(f"profile failed: {prof['error']}")
            else:
                lines.append(_stage_report(prof).table(markdown=True))
    text = "\n".join(lines) + "\n"
    print(text)
    out = pathlib.Path(args.out or HERE / "results" / f"bench_step{'' if args.device == 'cpu' else '_cuda'}.md")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(out.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, out)
    out.with_suffix(".json").write_text(json.dumps({"command": f"python benchmarks/bench_step.py {argv}", "ref": args.ref,
                                                    "device": args.device, "workers": hellos, "rows": rows, "cold_start": cold},
                                                   indent=1, default=str))


def _stage_report(data: dict):
    return _profiling_by_path().StageReport.from_dict(data)


if __name__ == "__main__":
    main()
