"""Device-side control flow that runs the same whether a frame is recorded as a graph or run eagerly, and the
recording of a frame: graphs, with the host calls a graph cannot hold between them."""

from __future__ import annotations

import contextlib

import warp as wp


class _Bodies:
    depth = 0  # device loop and branch bodies being run or recorded now (nested)


def in_device_body() -> bool:
    """Whether a :func:`device_while` or :func:`device_if` body is being run or recorded now. CUDA refuses to record an
    allocation in such a body ("Conditional body graph contains an unsupported operation"), where the CPU runs it:
    the tests fail every allocation made here on any device (tests/conftest.py), so the CPU suite catches it."""
    return _Bodies.depth > 0


def _body(body):
    def run(**kwargs):
        _Bodies.depth += 1
        try:
            body(**kwargs)
        finally:
            _Bodies.depth -= 1

    return run


def device_if(condition: wp.array, body, **kwargs) -> None:
    """``body(**kwargs)`` if ``condition[0]`` is non-zero when the work reaches it (``wp.capture_if``: a branch node in a
    graph, a host test eagerly). The body must not allocate (see :func:`in_device_body`)."""
    wp.capture_if(condition[:1], on_true=_body(body), **kwargs)


def device_while(condition: wp.array, body, **kwargs) -> None:
    """Run ``body(**kwargs)`` while ``condition[0]`` is non-zero; the body updates the condition on the device.

    Inside a graph capture this is ``wp.capture_while`` (a loop node, no host work at replay). Eagerly the host
    tests the condition before each pass: on the CPU through a zero-copy view of the array (Warp's eager
    ``capture_while`` copies it, a launch per pass), elsewhere through ``capture_while``'s pinned copy. Both run
    the same kernels in the same order, so eager and replayed results are bit for bit the same. The body must not
    allocate (see :func:`in_device_body`)."""
    body = _body(body)
    device = condition.device
    if device.is_capturing or not device.is_cpu:
        # a one-element view: eagerly, Warp copies the whole condition array into a one-element pinned buffer
        wp.capture_while(condition[:1], body, **kwargs)
        return
    flag = condition.numpy()  # a view: it sees every kernel's write
    while flag[0]:
        body(**kwargs)


class LoopGraphs:
    """Device loops recorded once as graphs and replayed where they run eagerly (a taped step's solves, an uncaptured
    run): :meth:`run` is :func:`device_while`, but outside a capture the loop with its `key` is recorded on first use
    and replayed after, so its kernels are not launched one by one from the host each pass (20-70 us each on the
    CPU). The same kernels in the same order: bit for bit the eager loop. The key must name everything the body's
    launches bake in that can change between calls (scalar arguments, arrays that may be reallocated); the owner
    calls :meth:`clear` when it reallocates what the graphs hold."""

    def __init__(self):
        self._graphs: dict = {}

    def run(self, key, condition: wp.array, body, **kwargs) -> None:
        device = condition.device
        if device.is_capturing:
            device_while(condition, body, **kwargs)
            return
        graph = self._graphs.get(key)
        if graph is None:
            with wp.ScopedCapture(device=device, force_module_load=False) as capture:
                device_while(condition, body, **kwargs)
            graph = self._graphs[key] = capture.graph
        wp.capture_launch(graph)

    def clear(self) -> None:
        self._graphs.clear()


class FrameGraph:
    """A frame recorded by :func:`record`: graphs, and between them the host calls :func:`host_call` met (none: one
    graph). :meth:`replay` runs them in their order."""

    def __init__(self, device):
        self.device = device
        self.parts: list = []  # wp.Graph or a callable, in order

    @property
    def host_calls(self) -> int:
        """Host calls between the graphs per replay."""
        return sum(1 for p in self.parts if not isinstance(p, wp.Graph))

    def replay(self) -> None:
        for part in self.parts:
            if isinstance(part, wp.Graph):
                wp.capture_launch(part)
            else:
                part()


_recording: dict[str, FrameGraph] = {}  # device alias -> the FrameGraph being recorded there


@contextlib.contextmanager
def record(device):
    """Record what the block launches on `device` as a :class:`FrameGraph` (``with record(d) as frame: ...``, then
    ``frame.replay()``): as ``wp.ScopedCapture``, except that a :func:`host_call` inside ends the graph being
    recorded, keeps the call, and starts the next graph. (Warp 1.19's CPU graphs replay kernels and
    ``wp.Bvh.refit`` but not ``wp.Mesh.refit``: a deforming mesh collider refits its BVH by a host call between
    graphs.) Host calls belong at the top level of the recorded work, never inside a device loop's body."""
    device = wp.get_device(device)
    if device.alias in _recording:
        raise RuntimeError(f"a frame is already being recorded on {device}")
    frame = FrameGraph(device)
    wp.capture_begin(device=device)
    _recording[device.alias] = frame
    try:
        yield frame
    finally:
        del _recording[device.alias]
        frame.parts.append(wp.capture_end(device=device))


def host_call(device, call, *args) -> None:
    """``call(*args)`` now, or, while :func:`record` records on `device`, between the graph recorded so far and the
    next (at every replay). Raises inside a plain graph capture, which would not replay it."""
    device = wp.get_device(device)
    if not device.is_capturing:
        call(*args)
        return
    frame = _recording.get(device.alias)
    if frame is None:
        raise RuntimeError(f"{getattr(call, '__qualname__', call)} is a host call: a graph captured with wp.ScopedCapture "
                           "would not replay it; record the frame with cloth_warp.graphs.record")
    frame.parts.append(wp.capture_end(device=device))
    frame.parts.append(lambda: call(*args))  # (not called now: a recording runs nothing, its replays do)
    wp.capture_begin(device=device)
