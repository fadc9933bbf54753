"""Tape utilities shared by the solvers and the gradient tools."""

from __future__ import annotations

import contextlib

import warp as wp


def active_tape() -> wp.Tape | None:
    """The wp.Tape currently recording, if any."""
    from warp._src.context import runtime  # Warp keeps the recording tape on its runtime

    return None if runtime is None else runtime.tape


@contextlib.contextmanager
def paused_tape():
    """Run launches without recording them (an iterative solve whose gradient comes from an adjoint).

    Yields the paused tape (None when nothing was recording)."""
    from warp._src.context import runtime

    tape = None if runtime is None else runtime.tape
    if tape is None:
        yield None
        return
    runtime.tape = None
    try:
        yield tape
    finally:
        runtime.tape = tape
