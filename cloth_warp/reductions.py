"""Launching the kernels that reduce over particles or springs into a few numbers (dot products, maxima).

Such a kernel adds each thread's value to one address. On a GPU, a hundred thousand atomic adds to one float64
serialise in the memory system: at 256^2 particles the three per CG iteration took about 0.3 ms, most of an
iteration. On CUDA these kernels therefore come in a second form, ``<name>_blocks``, that sums (or takes the
maximum) within a block first (``wp.tile`` / ``tile_sum`` / ``tile_max``) and adds once per block. The CPU keeps
the one-thread-per-item form: its threads run one after the other, and the block form's tiles cost it about 9 %
of an implicit frame.
"""

from __future__ import annotations

import warp as wp

REDUCTION_BLOCK = 256  # threads per block of the CUDA form
USE_BLOCKS: bool | None = None  # None: the block form on CUDA only; True: on the CPU too (blocks of one thread; tests)


def launch_reduction(kernel, blocks_kernel, count: int, inputs: list, outputs: list, device, per_item: bool = False) -> None:
    """Launch a reducing `kernel` over `count` items (its first argument): on the CPU one thread per item; on CUDA
    `blocks_kernel`, its block form (``block, lane = wp.tid()``, item ``block * wp.block_dim() + lane``, threads
    past `count` contributing nothing). `per_item`: one thread per item on every device (batched worlds, whose sums
    are per world and a block may span two)."""
    device = wp.get_device(device)
    args = [int(count), *inputs]
    if per_item or not (device.is_cuda if USE_BLOCKS is None else USE_BLOCKS):
        wp.launch(kernel, dim=count, inputs=args, outputs=outputs, device=device, record_tape=False)
        return
    block = REDUCTION_BLOCK if device.is_cuda else 1  # a CPU block is one thread
    wp.launch_tiled(blocks_kernel, dim=[max((count + block - 1) // block, 1)], inputs=args, outputs=outputs, block_dim=block,
                    device=device, record_tape=False)
