"""Parameter sweeps: the variants of a scene run on a distributed engine, resumable (``cloth-warp sweep``).

A sweep is the cartesian product of swept scene keys (``--param material.preset=cotton,silk``) and, with ``--seeds
K``, of ``scene.seed`` = 0 .. K-1. Each variant is one run, ``run-0000``, ``run-0001``, ... in the product's order
(the last key varying fastest), run as a ``cloth-warp run`` subprocess on a Dask worker:

    DIR/manifest.json      the sweep's definition and every run's record (status, exit class, attempts, seconds)
    DIR/results.csv        one row per run: its swept values, status, and the numbers of its summary
    DIR/runs/run-0003/     cache.usdc, summary.json (``--stats``), log.txt (the run's stderr)

Why Dask (``distributed``): the runs are independent processes, which is what a task scheduler does; Dask is pure
Python (a few MB), a ``LocalCluster`` starts in a second or two, and the same ``Client`` reaches a cluster started by
``dask scheduler`` / ``dask worker``, SSH, a job queue (dask-jobqueue) or Kubernetes. Ray would bring a runtime of
its own (an object store, a raylet, 100+ MB) for nothing a sweep uses. It is an optional extra
(``pip install "cloth-warp[sweep]"``).

Batched (``--batch K``): up to K pending runs go to a worker as one task, one process stepping them together as
batched worlds (:func:`~cloth_warp.worlds.run_worlds`: one model, one launch per stage; on the CPU each world bit for
bit its own run), each world's cache and summary in its run's folder, the process's stderr in the first run's
log.txt. Their swept keys must be ones worlds may differ in (not the forces, colliders, collision, solver or frame
rate): checked with every variant before any run. A batch saves each run's process start and
kernel load (short runs: 2.6x on 2 cores, ``benchmarks/results/bench_sweep_batch.md``), and on a GPU fills the device
(``benchmarks/bench_worlds.py`` on an H100: 256 worlds at 18.7x their one-by-one runs). Faults are per world: a diverged world is that run's failure, the others go on; a batch
killed or interrupted is run again whole, from its first frame (batched worlds keep no resume checkpoint).

Why a subprocess per run: Warp's CPU backend runs one thread per process, so a worker is one process with one
thread running one run at a time; the run's own process isolates what can go wrong in it (a crash, the kernel's
out-of-memory killer) from the worker and the sweep, and gives the command line's exit codes and its resumable
caches for free. On a cluster, the scene, the output folder and cloth_warp must be reachable from every worker at
the same paths (a shared file system).

Faults: a run that ends with exit code 3 (diverged) or 2 (bad input) failed for a reason a second try reproduces: it
is recorded with that class and not retried. A run that was killed (a signal: its worker or the machine's memory
killer), interrupted (130) or ended otherwise is retried once, continuing its cache from the last saved frame
(``cloth-warp run --resume``). The manifest is written (atomically) after every run; a sweep interrupted (Ctrl-C,
SIGTERM: the runs in flight stop with valid caches) and started again with the same definition skips the runs that
are done and continues the others.
"""

from __future__ import annotations

import csv
import ctypes
import io
import itertools
import json
import os
import pathlib
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field

from .outputs import atomic_write_text

MANIFEST = "manifest.json"
RESULTS = "results.csv"
RETRIED_CLASSES = ("killed", "interrupted", "error")
"""Exit classes of a run that a second try may not reproduce: retried once (see the module)."""
SUMMARY_COLUMNS = ("frames", "ms_per_frame", "max_strain", "particles", "wall_s")
"""Numbers of a run's summary (``cloth-warp run --stats``) copied into the results table (wall_s as `run_wall_s`)."""


class SweepError(Exception):
    """A sweep that cannot start: a bad --param, a scene key that does not validate, a manifest of another sweep."""


def exit_class(code: int) -> str:
    """The class of a ``cloth-warp run`` exit code: ok, bad_input, diverged, interrupted, killed (a signal), error."""
    from .cli import EXIT_BAD_INPUT, EXIT_DIVERGED, EXIT_INTERRUPTED, EXIT_OK

    if code < 0:
        return "killed"
    return {EXIT_OK: "ok", EXIT_BAD_INPUT: "bad_input", EXIT_DIVERGED: "diverged", EXIT_INTERRUPTED: "interrupted"}.get(code, "error")


def split_values(text: str) -> list[str]:
    """The comma-separated values of ``--param key=v1,v2``: commas inside brackets or quotes belong to a value
    (``cloth.grid.resolution=[32,32],[64,64]``)."""
    out, depth, quote, start = [], 0, None, 0
    for i, ch in enumerate(text):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append(text[start:i])
            start = i + 1
    out.append(text[start:])
    return [v.strip() for v in out]


def parse_params(items) -> dict[str, list]:
    """``key=v1,v2,...`` strings to {key: [values]} (each read as ``--set`` reads a value; in the order given; a key given
    twice is an error)."""
    from .cli import parse_value

    out: dict[str, list] = {}
    for item in items or []:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or not key or not values.strip():
            raise SweepError(f"--param expects key.path=v1,v2,..., got {item!r}")
        if key in out:
            raise SweepError(f"--param {key} given twice")
        out[key] = [parse_value(v) for v in split_values(values)]
    return out


@dataclass(frozen=True)
class SweepRun:
    """One variant: its id and the scene values it sets (the swept keys, and scene.seed with --seeds)."""

    id: str
    values: dict


@dataclass(frozen=True)
class Sweep:
    """A sweep's definition: the scene, the swept keys' values, the seeds, the values every run sets, the frames."""

    scene: str
    params: dict
    seeds: int | None = None
    overrides: dict = field(default_factory=dict)
    frames: int | None = None
    device: str | None = None
    batch: int = 1
    """Runs per process: with K >= 2, up to K pending runs step together as batched worlds (:mod:`cloth_warp.worlds`;
    their swept keys must be ones worlds may differ in). How the runs are grouped is no part of the sweep's definition:
    a sweep started again may batch otherwise."""

    def runs(self) -> list[SweepRun]:
        """Every variant, in the product's order (the last key varying fastest, then the seed)."""
        keys = list(self.params)
        axes = [self.params[k] for k in keys]
        if self.seeds is not None:
            keys.append("scene.seed")
            axes.append(list(range(self.seeds)))
        combos = list(itertools.product(*axes)) if keys else [()]
        return [SweepRun(f"run-{i:04d}", dict(zip(keys, combo))) for i, combo in enumerate(combos)]

    def definition(self) -> dict:
        """What the manifest records to recognise the sweep on a resume."""
        return {"scene": self.scene, "params": self.params, "seeds": self.seeds, "overrides": self.overrides,
                "frames": self.frames, "device": self.device}

    def validate(self) -> None:
        """Every variant's scene values checked now, at one gate (a bad key fails the sweep before any run)."""
        from .runner import find_scene
        from .scene import SceneError, load_scene

        if self.seeds is not None and self.seeds < 1:
            raise SweepError(f"--seeds must be at least 1, got {self.seeds}")
        if "scene.seed" in self.params and self.seeds is not None:
            raise SweepError("--seeds and --param scene.seed both set the seed: give one")
        if int(self.batch) < 1:
            raise SweepError(f"--batch must be at least 1, got {self.batch}")
        path = find_scene(self.scene)
        scenes = []
        for run in self.runs():
            try:
                scenes.append(load_scene(path, {**self.overrides, **run.values}))
            except SceneError as exc:
                raise SweepError(f"{run.id} ({format_values(run.values)}): {exc}") from None
        if self.batch > 1:
            from .worlds import check_batchable

            try:
                check_batchable(scenes)
            except ValueError as exc:
                raise SweepError(f"--batch: {exc}") from None
            if self.frames is None and len({s.get("output.frames") for s in scenes}) > 1:
                raise SweepError("--batch: output.frames differs between the runs; batched worlds step the same frames "
                                 "(give --frames)")


def format_values(values: dict) -> str:
    return ", ".join(f"{k}={json.dumps(v)}" for k, v in values.items())


@dataclass(frozen=True)
class RunResult:
    """What one attempt of a run gave (returned by :func:`execute_run` on a worker)."""

    id: str
    exit_code: int
    wall_s: float
    summary: dict | None


def _die_with_parent():  # pragma: no cover - runs in the child between fork and exec
    """Linux: the run gets SIGTERM when its worker dies (it then closes its cache), instead of running on orphaned."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def run_command(scene: str, values: dict, overrides: dict, run_dir: pathlib.Path, frames: int | None, device: str | None,
                resume: bool) -> list[str]:
    """The ``cloth-warp run`` command line of one run."""
    cmd = [sys.executable, "-m", "cloth_warp", "run", scene, "-o", str(run_dir / "cache.usdc"), "--stats", str(run_dir / "summary.json"),
           "--quiet"]
    for key, value in {**overrides, **values}.items():
        cmd += ["--set", f"{key}={_toml_value(value)}"]
    if frames is not None:
        cmd += ["--frames", str(int(frames))]
    if device:
        cmd += ["--device", device]
    if resume:
        cmd.append("--resume")
    return cmd


def execute_batch(spec: dict) -> list[RunResult]:
    """One attempt of a batch of runs on a worker (``spec["runs"]``: their ids, folders and values): ``python -m
    cloth_warp.sweep SPEC`` (:func:`run_batch`, batched worlds in one process) as a subprocess, its stderr appended to
    the first run's log.txt. A run's exit code is its world's (0 complete, 3 diverged: from its summary.json), else the
    process's (killed, interrupted, bad input, error: every run of the batch alike)."""
    from .cli import EXIT_DIVERGED, EXIT_FAILED, EXIT_OK

    runs = spec["runs"]
    dirs = [pathlib.Path(r["dir"]) for r in runs]
    for d in dirs:
        d.mkdir(parents=True, exist_ok=True)
        (d / "summary.json").unlink(missing_ok=True)
    spec_path = dirs[0] / "batch.json"
    atomic_write_text(spec_path, json.dumps(spec, indent=1) + "\n")
    cmd = [sys.executable, "-m", "cloth_warp.sweep", str(spec_path)]
    ids = ", ".join(x["id"] for x in runs)
    for d, r in zip(dirs[1:], runs[1:]):
        with open(d / "log.txt", "a") as log:
            log.write(f"# attempt {r['attempt']}: batched with {ids} (log: ../{runs[0]['id']}/log.txt)\n")
    code, wall = _run_logged(cmd, dirs[0] / "log.txt", f"# attempt {runs[0]['attempt']} of the batch {ids}: {' '.join(cmd)}")
    out = []
    for r, d in zip(runs, dirs):
        stats = d / "summary.json"
        summary = json.loads(stats.read_text()) if stats.exists() else None
        if summary is None:
            run_code = code if code != EXIT_OK else EXIT_FAILED
        else:
            run_code = EXIT_OK if summary["status"] == "complete" else EXIT_DIVERGED
        out.append(RunResult(r["id"], run_code, wall, summary))
    return out


def run_batch(spec: dict) -> int:
    """The batch process (``python -m cloth_warp.sweep SPEC``): the runs' scenes as batched worlds
    (:func:`~cloth_warp.worlds.run_worlds`), each world's cache and summary.json in its run's folder; returns the
    exit code (0 when every world is written, 130 interrupted: SIGTERM too, the caches closed as such)."""
    from .cli import EXIT_INTERRUPTED, EXIT_OK
    from .outputs import stale_partials
    from .scene import load_scene
    from .worlds import run_worlds

    def stop(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)
    runs = spec["runs"]
    outputs = [pathlib.Path(r["dir"]) / "cache.usdc" for r in runs]
    for out in outputs:  # a killed attempt's partial files: the batch starts again from the first frame
        for stale in stale_partials(out):
            stale.unlink(missing_ok=True)
    scenes = [load_scene(spec["scene"], {**spec["overrides"], **r["values"]}) for r in runs]
    frames = int(spec["frames"] if spec["frames"] is not None else scenes[0].get("output.frames"))
    t = time.perf_counter()
    try:
        results = run_worlds(scenes, outputs, frames=frames, device=spec["device"])
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    wall = time.perf_counter() - t
    for r, result in zip(runs, results):
        stepped = result.frames_written - 1
        summary = {"status": result.status, "frames": stepped, "ms_per_frame": 1e3 * wall / max(stepped, 1),
                   "max_strain": result.max_strain, "particles": result.particles, "wall_s": wall,
                   "batch": {"world": result.world, "worlds": len(runs)}}
        if result.message:
            summary["message"] = result.message
        atomic_write_text(pathlib.Path(r["dir"]) / "summary.json", json.dumps(summary, indent=1) + "\n")
    return EXIT_OK


def _toml_value(value) -> str:
    """A value as TOML text (strings quoted), so that ``--set`` reads back exactly this value."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def execute_run(spec: dict) -> RunResult:
    """One attempt of a run on a worker: ``cloth-warp run`` as a subprocess (its stderr appended to log.txt), continuing
    the cache an earlier attempt left (``--resume``: killed, interrupted, or a sweep stopped before it was recorded)."""
    from .runner import can_resume

    run_dir = pathlib.Path(spec["dir"])
    run_dir.mkdir(parents=True, exist_ok=True)
    cache = run_dir / "cache.usdc"
    resume = can_resume(cache)  # an earlier attempt's saved frames (a run not done has no other cache)
    cmd = run_command(spec["scene"], spec["values"], spec["overrides"], run_dir, spec["frames"], spec["device"], resume)
    stats = run_dir / "summary.json"
    if stats.exists():
        stats.unlink()
    code, wall = _run_logged(cmd, run_dir / "log.txt", f"# attempt {spec['attempt']}: {' '.join(cmd)}")
    summary = json.loads(stats.read_text()) if stats.exists() else None
    return RunResult(spec["id"], code, wall, summary)


def _run_logged(cmd: list[str], log_path: pathlib.Path, header: str) -> tuple[int, float]:
    """Run `cmd` as a subprocess, its stderr appended to `log_path` after the line `header` (on Linux it gets SIGTERM
    when its worker dies); returns its exit code and wall seconds."""
    t = time.perf_counter()
    with open(log_path, "a") as log:
        log.write(header + "\n")
        log.flush()
        preexec = _die_with_parent if sys.platform.startswith("linux") else None
        code = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=log, preexec_fn=preexec).returncode
    return code, time.perf_counter() - t


@dataclass
class SweepReport:
    """How a sweep ended: runs done, failed (after their retries), skipped as done by an earlier start, and pending
    (interrupted); the wall time [s] and where the manifest and the table are."""

    done: int
    failed: int
    skipped: int
    pending: int
    wall_s: float
    manifest: pathlib.Path
    results: pathlib.Path

    @property
    def complete(self) -> bool:
        return self.pending == 0 and self.failed == 0


class Manifest:
    """The sweep's record in DIR/manifest.json: its definition and, per run, status (pending, done, failed), the exit
    code and class of its last attempt, attempts, the seconds of its last attempt, its swept values."""

    def __init__(self, out_dir: pathlib.Path, sweep: Sweep):
        self.path = out_dir / MANIFEST
        self.sweep = sweep
        definition = sweep.definition()
        if self.path.exists():
            data = json.loads(self.path.read_text())
            if data.get("sweep") != json.loads(json.dumps(definition)):
                raise SweepError(f"{self.path} records another sweep ({data.get('sweep')}); give a new output folder")
            self.runs = data["runs"]
        else:
            self.runs = {r.id: {"values": r.values, "status": "pending", "exit_code": None, "exit_class": None, "attempts": 0,
                                "wall_s": None} for r in sweep.runs()}
        self.definition = definition

    def save(self) -> None:
        atomic_write_text(self.path, json.dumps({"sweep": self.definition, "runs": self.runs}, indent=1) + "\n")

    def record(self, result: RunResult) -> dict:
        entry = self.runs[result.id]
        entry["attempts"] += 1
        entry["exit_code"] = result.exit_code
        entry["exit_class"] = exit_class(result.exit_code)
        entry["wall_s"] = result.wall_s
        if entry["exit_class"] == "ok":
            entry["status"] = "done"
        elif entry["exit_class"] in RETRIED_CLASSES and entry["attempts"] < 2:
            entry["status"] = "pending"
        else:
            entry["status"] = "failed"
        return entry


def write_results(out_dir: pathlib.Path, manifest: Manifest) -> pathlib.Path:
    """DIR/results.csv: per run its id, swept values, status, exit class, attempts, seconds, and summary numbers."""
    keys = list(manifest.sweep.params) + (["scene.seed"] if manifest.sweep.seeds is not None else [])
    columns = ["run", *keys, "status", "exit_class", "attempts", "wall_s",
               *[("run_" + c if c == "wall_s" else c) for c in SUMMARY_COLUMNS], "cache"]
    rows = []
    for run_id, entry in manifest.runs.items():
        run_dir = out_dir / "runs" / run_id
        stats = run_dir / "summary.json"
        summary = json.loads(stats.read_text()) if stats.exists() else {}
        row = {"run": run_id, **{k: json.dumps(entry["values"][k]) if isinstance(entry["values"][k], list) else entry["values"][k]
                                for k in keys},
               "status": entry["status"], "exit_class": entry["exit_class"] or "", "attempts": entry["attempts"],
               "wall_s": "" if entry["wall_s"] is None else f"{entry['wall_s']:.3f}",
               "cache": str(pathlib.Path("runs") / run_id / "cache.usdc") if (run_dir / "cache.usdc").exists() else ""}
        for c in SUMMARY_COLUMNS:
            row["run_" + c if c == "wall_s" else c] = summary.get(c, "")
        rows.append(row)
    path = out_dir / RESULTS
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=columns)
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(path, text.getvalue())
    return path


def _client(workers: int | None, address: str | None):
    """A Dask client: of the cluster at `address`, else of a local cluster of `workers` one-thread processes."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:  # pragma: no cover - the optional extra
        raise SweepError('cloth-warp sweep needs Dask: pip install "cloth-warp[sweep]"') from None
    import logging

    if logging.getLogger().getEffectiveLevel() > logging.INFO:  # Dask logs at INFO on its own handlers (cloth-warp -v: shown)
        logging.getLogger("distributed").setLevel(logging.WARNING)
    if address:
        return Client(address), None
    n = int(workers or os.cpu_count() or 1)
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None)
    return Client(cluster), cluster


def run_sweep(sweep: Sweep, out_dir, workers: int | None = None, address: str | None = None, progress=None) -> SweepReport:
    """Run every variant of `sweep` not done yet into `out_dir` (see the module): on the Dask cluster at `address`, else
    on a local cluster of `workers` processes (default: the machine's cores). `progress(entry_id, entry, done, total)`
    is called after each attempt. Ctrl-C / SIGTERM stop the sweep with its manifest and table written (KeyboardInterrupt
    is raised again after)."""
    from .runner import find_scene

    if workers is not None and int(workers) < 1:
        raise SweepError(f"--workers must be at least 1, got {workers}")
    sweep.validate()
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    manifest = Manifest(out_dir, sweep)
    scene = str(find_scene(sweep.scene).resolve())
    skipped = sum(1 for e in manifest.runs.values() if e["status"] == "done")
    manifest.save()
    t0 = time.perf_counter()
    todo = [rid for rid, e in manifest.runs.items() if e["status"] == "pending"]
    interrupted = None
    if todo:
        client, cluster = _client(workers, address)
        try:
            _run_pending(client, manifest, scene, sweep, out_dir, todo, progress)
        except KeyboardInterrupt as exc:
            interrupted = exc
        finally:
            manifest.save()
            client.close()
            if cluster is not None:
                cluster.close()
    results = write_results(out_dir, manifest)
    statuses = [e["status"] for e in manifest.runs.values()]
    report = SweepReport(done=statuses.count("done") - skipped, failed=statuses.count("failed"), skipped=skipped,
                         pending=statuses.count("pending"), wall_s=time.perf_counter() - t0, manifest=manifest.path, results=results)
    if interrupted is not None:
        interrupted.report = report
        raise interrupted
    return report


def _run_pending(client, manifest: Manifest, scene: str, sweep: Sweep, out_dir: pathlib.Path, todo: list[str], progress) -> None:
    """Submit the pending runs, record each attempt as it ends (the manifest saved each time), resubmit the retried."""
    from distributed import as_completed

    def spec_of(rid):
        entry = manifest.runs[rid]
        return {"id": rid, "dir": str(out_dir / "runs" / rid), "values": entry["values"], "attempt": entry["attempts"] + 1}

    def submit(rids):
        """One run (`cloth-warp run`), or with --batch the runs `rids` as one batch (:func:`execute_batch`)."""
        common = {"scene": scene, "overrides": sweep.overrides, "frames": sweep.frames, "device": sweep.device}
        key = f"{rids[0]}-attempt{manifest.runs[rids[0]]['attempts'] + 1}-{os.getpid()}-{time.time_ns()}"
        if sweep.batch > 1:
            return client.submit(execute_batch, {**common, "runs": [spec_of(r) for r in rids]}, key=key, pure=False)
        return client.submit(execute_run, {**common, **spec_of(rids[0])}, key=key, pure=False)

    def groups(rids):
        return [rids[k:k + sweep.batch] for k in range(0, len(rids), sweep.batch)]

    members = {}  # a batch's first run -> its runs (what a failed worker's task held)
    for g in groups(todo):
        members[g[0]] = g
    futures = as_completed([submit(g) for g in groups(todo)])
    total = len(manifest.runs)
    try:
        for future in futures:
            first = future.key.split("-attempt")[0]
            try:
                results = future.result()
                results = results if isinstance(results, list) else [results]
            except Exception as exc:  # the worker died under the run (Dask gave up on it), or the task failed
                results = [RunResult(rid, -int(signal.SIGKILL), 0.0, None) for rid in members.get(first, [first])]
                for r in results:
                    (out_dir / "runs" / r.id).mkdir(parents=True, exist_ok=True)
                    with open(out_dir / "runs" / r.id / "log.txt", "a") as log:
                        log.write(f"# the worker failed: {type(exc).__name__}: {exc}\n")
            retry = []
            for result in results:
                entry = manifest.record(result)
                manifest.save()
                if progress is not None:
                    done = sum(1 for e in manifest.runs.values() if e["status"] != "pending")
                    progress(result.id, entry, done, total)
                if entry["status"] == "pending":
                    retry.append(result.id)
            for g in groups(retry):
                members[g[0]] = g
                futures.add(submit(g))
    except KeyboardInterrupt:
        client.cancel(list(futures.futures))
        raise


if __name__ == "__main__":  # the batch process of a batched sweep (execute_batch)
    sys.exit(run_batch(json.loads(pathlib.Path(sys.argv[1]).read_text())))
