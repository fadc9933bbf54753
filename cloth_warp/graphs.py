"""Device-side control flow that runs the same whether a frame is recorded as a graph or run eagerly."""

from __future__ import annotations

import warp as wp


def device_while(condition: wp.array, body, **kwargs) -> None:
    """Run ``body(**kwargs)`` while ``condition[0]`` is non-zero; the body updates the condition on the device.

    Inside a graph capture this is ``wp.capture_while`` (a loop node, no host work at replay). Eagerly the host
    tests the condition before each pass: on the CPU through a zero-copy view of the array (Warp's eager
    ``capture_while`` copies it, a launch per pass), elsewhere through ``capture_while``'s pinned copy. Both run
    the same kernels in the same order, so eager and replayed results are bit for bit the same."""
    device = condition.device
    if device.is_capturing or not device.is_cpu:
        # a one-element view: eagerly, Warp copies the whole condition array into a one-element pinned buffer
        wp.capture_while(condition[:1], body, **kwargs)
        return
    flag = condition.numpy()  # a view: it sees every kernel's write
    while flag[0]:
        body(**kwargs)
