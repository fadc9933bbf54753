"""The frame record: the device arrays a frame's reports are read from, packed into one block read once per frame.

Every part of a step keeps its counters on the device (the statistics of the new state, the linear solves'
record, each pass's counters), written by the recorded frame and read after it. Read one by one they cost a
host round trip each (on CUDA a synchronisation and a copy). :class:`FrameRecord` moves them into one device
block: each part names its record arrays (``record_arrays()``: (owner, attribute) pairs), the block takes
their place as typed views (the owner's attribute is replaced, so a frame recorded afterwards writes into the
block), :meth:`FrameRecord.fetch` copies the block to the host once, and the parts' ``read_report`` take their
values from that copy through :func:`record_values` (from the device, as before, when no fetched block holds
the array).
"""

from __future__ import annotations

import contextlib

import numpy as np
import warp as wp

ALIGNMENT = 16  # bytes: every record starts on it (float64 and vector types)


class FrameRecord:
    """One device block holding the record arrays of a frame's parts, fetched to the host with one read.

    Args:
        device: the Warp device of the arrays.
        owners: (object, attribute name) pairs, each attribute a contiguous ``wp.array`` to move into the block.
    """

    def __init__(self, device, owners=()):
        self.device = wp.get_device(device)
        self._slots: dict[int, tuple[int, np.dtype, tuple]] = {}  # id(view) -> (byte offset, numpy dtype, numpy shape)
        self._views: list[wp.array] = []  # kept alive with the block (the ids above stay valid)
        self._host: np.ndarray | None = None
        layout, size = [], 0
        for owner, name in owners:
            a = getattr(owner, name)
            size = -(-size // ALIGNMENT) * ALIGNMENT
            layout.append((owner, name, a, size))
            size += a.capacity
        self.block = wp.zeros(max(size, 1), dtype=wp.uint8, device=self.device)
        for owner, name, a, offset in layout:
            view = wp.array(ptr=self.block.ptr + offset, dtype=a.dtype, shape=a.shape, device=self.device, copy=False)
            view._frame_record = self  # the block outlives every view handed out
            wp.copy(view, a)
            setattr(owner, name, view)
            host = a.numpy()  # the numpy layout of a record: dtype and shape (vectors as trailing dimensions)
            self._slots[id(view)] = (offset, host.dtype, host.shape)
            self._views.append(view)

    @classmethod
    def of(cls, device, parts) -> "FrameRecord":
        """The record of `parts` (objects with ``record_arrays()``; None entries skipped)."""
        return cls(device, [pair for p in parts if p is not None for pair in p.record_arrays()])

    @contextlib.contextmanager
    def fetched(self):
        """Within: the block copied to the host once, :func:`record_values` serving from the copy (outside, the
        parts read the device as before, so a step run by hand between frames is never read stale)."""
        self._host = self.block.numpy().copy()
        try:
            yield self
        finally:
            self._host = None

    def values(self, view: wp.array) -> np.ndarray | None:
        """The fetched values of one of this block's arrays (None outside :meth:`fetched`)."""
        if self._host is None:
            return None
        offset, dtype, shape = self._slots[id(view)]
        count = int(np.prod(shape))
        return np.frombuffer(self._host, dtype=dtype, count=count, offset=offset).reshape(shape)


def record_values(array: wp.array) -> np.ndarray:
    """A record array's values on the host: from its frame record's fetched copy when there is one, else read
    from the device (``array.numpy()``)."""
    record = getattr(array, "_frame_record", None)
    values = record.values(array) if record is not None else None
    return array.numpy() if values is None else values
