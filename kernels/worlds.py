"""Batched worlds' indexing (cloth_warp.worlds): where a world's scalars sit in the arrays that hold one set per world."""

import warp as wp

# Rows of a batch's world ranges (cloth_warp.worlds.world_ranges, int32 (RANGE_KINDS, W + 1)): row k holds where each
# world's items of kind k start, and their count after the last world (a world's items are contiguous in each kind).
RANGE_PARTICLES = wp.constant(0)
RANGE_SPRINGS = wp.constant(1)  # linear springs (the first linear_spring_count springs)
RANGE_BENDS = wp.constant(2)  # bend triples (springs linear_spring_count + e)
RANGE_MEMBRANES = wp.constant(3)
RANGE_TRIANGLES = wp.constant(4)
RANGE_PLATES = wp.constant(5)
RANGE_KINDS = 6


@wp.func
def world_slot(w: int, worlds: int, size: int):
    """Where world w's `size` loop entries start in a loop-state array: with one world its entries are the first;
    with batched worlds the first `size` entries are the batch's (running while any world does) and world w's
    follow at size * (1 + w) (the batch's entries are cleared by their owner before the worlds set them)."""
    if worlds == 1:
        return 0
    return size * (1 + w)


def world_slots_length(size: int, worlds: int) -> int:
    """Length of a loop-state array of `size` entries per world laid out as :func:`world_slot` reads it."""
    return size * (1 if worlds == 1 else worlds + 1)


@wp.func
def particle_world_of(i: int, particle_world: wp.array(dtype=wp.int32), worlds: int):
    """The world of particle i (0 without batched worlds, with no read)."""
    if worlds == 1:
        return 0
    return particle_world[i]
