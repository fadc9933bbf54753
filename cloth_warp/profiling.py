"""What a step costs: :class:`LaunchCounter` counts the Warp work issued from Python, :class:`StageTimer` times named stages.

Counting (how many eager launches, copies, graph replays and host reads a frame issues)::

    with LaunchCounter() as counts:
        sim.step_frame()
    counts.launches, counts.replays, counts.reads, counts.kernels.most_common(5)

Timing stages (solver code names its stages; nothing is measured until :func:`enable`)::

    from cloth_warp.profiling import stage

    with stage("integrate"):            # inside another stage the name is "outer/integrate"
        wp.launch(...)

    @timed("collide")                   # or a whole function as a stage
    def apply(self, ...): ...

    profiling.enable(device)            # e.g. `cloth-warp run --profile`
    ... run frames without graph capture (a replayed graph runs no Python, so no stage is timed) ...
    print(profiling.report().table(frames=n))

This module imports nothing from cloth_warp (only Warp and the standard library), so that
``benchmarks/bench_step.py`` can load it by path into runs of older revisions, where it does not exist.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import threading
import time

import warp as wp

__all__ = ["LaunchCounter", "LaunchCounts", "StageReport", "StageStats", "StageTimer", "default_timer", "disable", "enable",
           "enabled", "report", "reset", "stage", "timed"]


# -- counting -------------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class LaunchCounts:
    """Warp work issued from Python while a :class:`LaunchCounter` was active.

    Eager work (run when issued, outside a graph capture) is counted by kind; everything issued while its
    device was capturing a graph is counted once in :attr:`captured` (it runs later, in the replays).
    """

    launches: int = 0
    """Eager kernel launches: ``wp.launch``, ``wp.launch_tiled`` and Warp utilities that launch kernels of their own
    (``wp.utils.array_scan`` / ``array_sum`` / ``radix_sort_pairs`` / ``segmented_sort_pairs``, ``wp.Mesh.refit``)."""
    copies: int = 0
    """Eager ``wp.copy`` calls (``array.assign`` included)."""
    fills: int = 0
    """Eager ``array.zero_()`` / ``array.fill_()`` calls."""
    replays: int = 0
    """Graph replays (``wp.capture_launch``)."""
    reads: int = 0
    """Host reads of device arrays: ``array.numpy()``, ``array.list()``, ``str(array)`` (each waits for the device on
    CUDA; on the CPU ``numpy()`` is a view, still a point where the host looks at results)."""
    loops: int = 0
    """Eager ``wp.capture_while`` / ``wp.capture_if`` calls (outside a capture they test their condition on the host;
    the launches of their bodies count in :attr:`launches`)."""
    allocations: int = 0
    """Arrays allocated through ``wp.zeros`` / ``zeros_like`` / ``empty`` / ``empty_like`` / ``full`` / ``full_like`` /
    ``ones`` / ``ones_like`` / ``clone`` (eager or captured)."""
    captured: int = 0
    """Launches, copies, fills and loops recorded while their device was capturing a graph."""
    kernels: collections.Counter = dataclasses.field(default_factory=collections.Counter)
    """Eager launches by kernel name (``module.kernel``): where the eager launches that are left come from."""

    @property
    def eager(self) -> int:
        """Eager device operations: launches + copies + fills + loops (the work a replayed graph would save)."""
        return self.launches + self.copies + self.fills + self.loops

    def __add__(self, other: LaunchCounts) -> LaunchCounts:
        out = LaunchCounts(**{f.name: getattr(self, f.name) + getattr(other, f.name) for f in dataclasses.fields(self)
                              if f.name != "kernels"})
        out.kernels = self.kernels + other.kernels
        return out

    def to_dict(self) -> dict:
        """The counts as JSON-able values (``kernels`` sorted by count)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "kernels"}
        out["eager"] = self.eager
        out["kernels"] = dict(self.kernels.most_common())
        return out


_active: list[LaunchCounts] = []  # the counts of the counters now active (nested counters all count)
_originals: list[tuple[object, str, object]] = []  # (owner, attribute, original) of what is wrapped now
_local = threading.local()  # .depth: inside a counted call (its own inner calls are part of it)
_lock = threading.RLock()


def _capturing(device) -> bool:
    try:
        return bool(wp.get_device(device).is_capturing)
    except Exception:  # a device Warp cannot name: count the work as eager
        return False


def _array_device(a):
    return getattr(a, "device", None)


def _launch_device(args, kwargs):
    """The device of a ``wp.launch(kernel, dim, inputs, outputs, adj_inputs, adj_outputs, device, ...)`` call (None: Warp's
    default device, as ``wp.launch`` itself takes it)."""
    return kwargs["device"] if kwargs.get("device") is not None else (args[6] if len(args) > 6 else None)


def _kernel_name(kernel) -> str:
    key = getattr(kernel, "key", None) or getattr(kernel, "__name__", None) or type(kernel).__name__
    module = getattr(getattr(kernel, "module", None), "name", None)
    return f"{module.rsplit('.', 1)[-1]}.{key}" if module else str(key)


def _note(kind: str, device, name: str | None = None) -> None:
    captured = kind not in ("replays", "reads", "allocations") and _capturing(device)
    for counts in _active:
        if captured:
            counts.captured += 1
        else:
            setattr(counts, kind, getattr(counts, kind) + 1)
            if name is not None:
                counts.kernels[name] += 1


def _counted(fn, kind: str, where, name=None, nests: bool = True):
    """`fn` wrapped to note one `kind` per outermost call; `where(args, kwargs)` gives the device. With `nests`, what
    the call itself issues through wrapped functions (``assign`` calls ``wp.copy``) is part of it, not counted again."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        depth = getattr(_local, "depth", 0)
        if depth == 0 and _active:
            _note(kind, where(args, kwargs), name(args) if name is not None else None)
        if not nests:
            return fn(*args, **kwargs)
        _local.depth = depth + 1
        try:
            return fn(*args, **kwargs)
        finally:
            _local.depth = depth

    wrapper.__cloth_warp_counted__ = True
    return wrapper


def _targets():
    """(owner, attribute, kind, device of a call, kernel name of a call, nests) of everything counted."""
    first = lambda args, kwargs: _array_device(args[0] if args else next(iter(kwargs.values()), None))  # noqa: E731  (methods: self)
    launch = lambda args, kwargs: _launch_device(args, kwargs)  # noqa: E731
    none = lambda args, kwargs: None  # noqa: E731
    out = [
        (wp, "launch", "launches", launch, lambda args: _kernel_name(args[0]) if args else "?", False),
        (wp, "launch_tiled", "launches", launch, lambda args: _kernel_name(args[0]) if args else "?", False),
        (wp, "copy", "copies", first, None, True),
        (wp.array, "assign", "copies", first, None, True),
        (wp.array, "zero_", "fills", first, None, True),
        (wp.array, "fill_", "fills", first, None, True),
        (wp, "capture_launch", "replays", none, None, True),
        (wp.array, "numpy", "reads", first, None, True),
        (wp.array, "list", "reads", first, None, True),
        (wp.array, "__str__", "reads", first, None, True),
        # their bodies' launches are counted one by one
        (wp, "capture_while", "loops", first, None, False),
        (wp, "capture_if", "loops", first, None, False),
        (wp.Mesh, "refit", "launches", lambda args, kwargs: getattr(args[0], "device", None), lambda args: "Mesh.refit", True),
    ]
    for util in ("array_scan", "array_sum", "radix_sort_pairs", "segmented_sort_pairs"):
        if hasattr(wp.utils, util):
            out.append((wp.utils, util, "launches", first, lambda args, util=util: f"utils.{util}", True))
    for alloc in ("zeros", "zeros_like", "empty", "empty_like", "full", "full_like", "ones", "ones_like", "clone"):
        if hasattr(wp, alloc):
            out.append((wp, alloc, "allocations", none, None, True))
    return out


def _install():
    for owner, attr, kind, where, name, nests in _targets():
        original = owner.__dict__.get(attr) if isinstance(owner, type) else getattr(owner, attr)
        if original is None or getattr(original, "__cloth_warp_counted__", False):
            continue
        setattr(owner, attr, _counted(original, kind, where, name, nests))
        _originals.append((owner, attr, original))


def _uninstall():
    while _originals:
        owner, attr, original = _originals.pop()
        current = owner.__dict__.get(attr) if isinstance(owner, type) else getattr(owner, attr, None)
        if getattr(current, "__cloth_warp_counted__", False):  # leave anything wrapped after us alone
            setattr(owner, attr, original)


class LaunchCounter:
    """Counts the Warp work issued from Python while active (a context manager whose ``as`` value is the
    :class:`LaunchCounts`, filled in as the block runs).

    It wraps the functions on the ``warp`` module and the ``warp.array`` class that Python code calls
    (``wp.launch``, ``wp.copy``, ``arr.zero_()``, ``arr.numpy()``, ...; see :class:`LaunchCounts`) and puts the
    originals back when the last active counter exits. Work issued while its device is capturing a graph is
    counted in ``captured``, not as eager work. Only calls made through the module or the class are seen
    (``from warp import launch`` taken before the counter started is not), and a wrapped call made by another
    wrapped call (``assign`` -> ``wp.copy``, ``list`` -> ``numpy``) counts once. Counters nest (each counts
    everything in its block); the wrapping is process-wide, so work issued by other threads counts too.
    """

    def __init__(self):
        self.counts = LaunchCounts()

    def __enter__(self) -> LaunchCounts:
        with _lock:
            if not _active:
                _install()
            _active.append(self.counts)
        return self.counts

    def __exit__(self, *exc) -> None:
        with _lock:
            for i in range(len(_active) - 1, -1, -1):
                if _active[i] is self.counts:
                    del _active[i]
                    break
            if not _active:
                _uninstall()


# -- timing ---------------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class StageStats:
    """One stage's totals."""

    name: str
    """The stage's full name, nested stages joined with "/" (``frame/collide``)."""
    calls: int
    total_s: float
    """Wall time inside the stage, summed over its calls [s] (device work included: the timer synchronises)."""

    @property
    def depth(self) -> int:
        return self.name.count("/")

    @property
    def mean_ms(self) -> float:
        return 1e3 * self.total_s / self.calls if self.calls else 0.0


@dataclasses.dataclass
class StageReport:
    """What a :class:`StageTimer` measured, stages in the order first entered."""

    stages: list[StageStats]
    frames: int | None = None
    """Frames the stages ran over, when the caller knows (adds a ms/frame column)."""

    def to_dict(self) -> dict:
        return {"frames": self.frames,
                "stages": [{"name": s.name, "calls": s.calls, "total_s": s.total_s, "mean_ms": s.mean_ms} for s in self.stages]}

    @classmethod
    def from_dict(cls, data: dict) -> StageReport:
        return cls([StageStats(s["name"], int(s["calls"]), float(s["total_s"])) for s in data.get("stages", [])], data.get("frames"))

    def table(self, markdown: bool = True, frames: int | None = None) -> str:
        """The stages as a table (Markdown, or aligned plain text): calls, total ms, ms/call, ms/frame (with `frames`)
        and share of the enclosing stage (top-level stages: of their sum)."""
        frames = frames if frames is not None else self.frames
        if not self.stages:
            return "(no stages timed: profiling off, or every frame ran as a replayed graph)"
        totals = {s.name: s.total_s for s in self.stages}
        top = sum(s.total_s for s in self.stages if s.depth == 0)
        head = ["stage", "calls", "total ms", "ms/call"] + (["ms/frame"] if frames else []) + ["share"]
        rows = []
        for s in self.stages:
            parent = totals.get(s.name.rsplit("/", 1)[0]) if s.depth else top
            share = f"{100.0 * s.total_s / parent:.1f} %" if parent else ""
            label = s.name if markdown else "  " * s.depth + s.name.rsplit("/", 1)[-1]
            rows.append([f"`{label}`" if markdown else label, str(s.calls), f"{1e3 * s.total_s:.1f}", f"{s.mean_ms:.3f}"]
                        + ([f"{1e3 * s.total_s / frames:.2f}"] if frames else []) + [share])
        if markdown:
            lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
            return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])
        widths = [max(len(r[i]) for r in [head, *rows]) for i in range(len(head))]
        fmt = lambda r: "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))  # noqa: E731
        return "\n".join([fmt(head)] + [fmt(r) for r in rows])


_NULL = contextlib.nullcontext()


class _Scope:
    __slots__ = ("timer", "name", "device", "t0", "timed")

    def __init__(self, timer: StageTimer, name: str, device):
        self.timer, self.name, self.device = timer, name, device

    def __enter__(self):
        timer = self.timer
        stack = timer._stack
        self.name = f"{stack[-1]}/{self.name}" if stack else self.name
        stack.append(self.name)
        device = wp.get_device(self.device if self.device is not None else timer.device)
        self.device = device
        self.timed = not device.is_capturing  # a capture records work: its wall time is not the stage's
        if self.timed:
            timer._totals.setdefault(self.name, [0, 0.0])  # reports list stages in the order first entered
            if timer.synchronize:
                wp.synchronize_device(device)
            self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        timer = self.timer
        if self.timed:
            if timer.synchronize:
                wp.synchronize_device(self.device)
            timer._add(self.name, time.perf_counter() - self.t0)
        timer._stack.pop()
        return False


class StageTimer:
    """Wall time and calls per named stage: ``with timer.stage("collide"): ...``.

    Enabled, a stage synchronises its device on entry and exit (so that the device work issued inside counts in the
    stage, asynchronous CUDA launches too) and adds the time between to its name's total; stages opened inside
    another get "outer/inner" names. While the device captures a graph nothing is timed (the work runs later, in the
    replays, where no Python runs). Disabled, :meth:`stage` returns a shared no-op context (no synchronisation, no
    clock). The synchronisations serialise CPU and GPU, so a profiled run is slower than a plain one: compare its
    stages with each other, and time whole frames without it.

    Args:
        enabled: start enabled.
        device: the device to synchronise (default: Warp's default device at each stage).
        synchronize: synchronise at stage boundaries (off: host time only, for host-only stages).
    """

    def __init__(self, enabled: bool = False, device=None, synchronize: bool = True):
        self.enabled = enabled
        self.device = device
        self.synchronize = synchronize
        self._stack: list[str] = []
        self._totals: dict[str, list] = {}  # name -> [calls, seconds], in first-entered order

    def stage(self, name: str, device=None):
        """A context manager timing `name` (nested: "outer/name"); a no-op when the timer is disabled."""
        if not self.enabled:
            return _NULL
        return _Scope(self, name, device)

    def _add(self, name: str, seconds: float):
        entry = self._totals.setdefault(name, [0, 0.0])
        entry[0] += 1
        entry[1] += seconds

    def reset(self) -> None:
        """Forget what was measured (the enabled flag stays)."""
        self._totals.clear()
        self._stack.clear()

    def report(self, frames: int | None = None) -> StageReport:
        return StageReport([StageStats(name, calls, seconds) for name, (calls, seconds) in self._totals.items() if calls], frames)


_default = StageTimer()


def default_timer() -> StageTimer:
    """The timer :func:`stage` uses."""
    return _default


def stage(name: str, device=None):
    """``with stage("integrate"):`` times a stage on the module's default timer; a shared no-op until :func:`enable`."""
    if not _default.enabled:
        return _NULL
    return _Scope(_default, name, device)


def timed(name: str | None = None):
    """Decorator: the function's calls as a stage of the default timer (named `name`, default the function's name);
    disabled, one flag test per call."""

    def decorate(fn):
        label = name or fn.__name__

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            if not _default.enabled:
                return fn(*args, **kwargs)
            with _Scope(_default, label, None):
                return fn(*args, **kwargs)

        return wrapper

    return decorate


def enable(device=None, synchronize: bool = True, reset_totals: bool = True) -> StageTimer:
    """Turn the default timer on (synchronising `device`, default Warp's), by default from zero; returns it."""
    _default.device = device
    _default.synchronize = synchronize
    if reset_totals:
        _default.reset()
    _default.enabled = True
    return _default


def disable() -> None:
    """Turn the default timer off (its totals stay readable through :func:`report`)."""
    _default.enabled = False


def enabled() -> bool:
    return _default.enabled


def reset() -> None:
    _default.reset()


def report(frames: int | None = None) -> StageReport:
    """The default timer's :class:`StageReport`."""
    return _default.report(frames)
