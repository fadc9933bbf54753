"""Spatial hash grid of voxels for cloth self-collision (Choi & Ko 2002, section 5 of the survey).

Elements (particles, edges, triangles; rows of up to three vertex indices, -1 padded) are registered
in every voxel their swept, padded bounding box touches: the box of the element's vertices at the
step's start and at its end (start + dt x velocity), grown by `pad`. Voxels map to hash buckets; a bucket's entries
are found through the entries sorted by bucket (count -> scan -> fill -> radix sort -> ranges).

A candidate pair is emitted once, from the voxel that holds the lower corner of the two boxes'
intersection, and only when the boxes overlap and the elements share no vertex; entries of other
voxels that hash to the same bucket are skipped by their stored voxel coordinates. Elements carry ids
(their index in the full set), so the same search runs between the full grid and small grids of the
elements re-registered by a patch. Pair buffers
never truncate silently: the pair count is always the true count, pairs are written only while it
is below the buffer's capacity, and the host grows the buffer and searches again. The capturable
path (``*_listed`` kernels, launched over a buffer's capacity with the count in a device array) never
reads a count on the host: what does not fit is dropped and the need recorded as an overflow instead.
"""

import warp as wp

# An element whose box spans more voxels than this along one axis is clamped (and counted).
MAX_CELL_SPAN = wp.constant(64)


@wp.func
def cell_of(p: wp.vec3, inv_cell_size: float):
    return wp.vec3i(int(wp.floor(p[0] * inv_cell_size)), int(wp.floor(p[1] * inv_cell_size)), int(wp.floor(p[2] * inv_cell_size)))


@wp.func
def cell_hash(c: wp.vec3i, table_mask: int):
    h = (c[0] * 73856093) ^ (c[1] * 19349663) ^ (c[2] * 83492791)
    return h & table_mask


@wp.func
def boxes_overlap(lo_a: wp.vec3, hi_a: wp.vec3, lo_b: wp.vec3, hi_b: wp.vec3):
    return (lo_a[0] <= hi_b[0] and lo_b[0] <= hi_a[0] and lo_a[1] <= hi_b[1] and lo_b[1] <= hi_a[1]
            and lo_a[2] <= hi_b[2] and lo_b[2] <= hi_a[2])


@wp.func
def share_vertex(a: wp.vec3i, b: wp.vec3i):
    for i in range(3):
        if a[i] >= 0:
            for j in range(3):
                if a[i] == b[j]:
                    return True
    return False


@wp.func
def element_row(elements: wp.array2d(dtype=wp.int32), e: int):
    return wp.vec3i(elements[e, 0], elements[e, 1], elements[e, 2])


@wp.func
def swept_box(elements: wp.array2d(dtype=wp.int32), e: int, x_start: wp.array(dtype=wp.vec3), velocity: wp.array(dtype=wp.vec3),
              dt: float, pad: float):
    """(lo, hi) of element e's swept box, its vertices from x_start to x_start + dt velocity, grown by `pad`."""
    i0 = elements[e, 0]
    x_end = x_start[i0] + dt * velocity[i0]
    lo = wp.min(x_start[i0], x_end)
    hi = wp.max(x_start[i0], x_end)
    for k in range(1, 3):
        i = elements[e, k]
        if i >= 0:
            x_end = x_start[i] + dt * velocity[i]
            lo = wp.min(lo, wp.min(x_start[i], x_end))
            hi = wp.max(hi, wp.max(x_start[i], x_end))
    grow = wp.vec3(pad, pad, pad)
    return lo - grow, hi + grow


@wp.kernel(enable_backward=False)
def element_bounds(
    elements: wp.array2d(dtype=wp.int32),
    x_start: wp.array(dtype=wp.vec3),
    velocity: wp.array(dtype=wp.vec3),
    dt: float,
    pad: float,
    inv_cell_size: float,
    lo_out: wp.array(dtype=wp.vec3),
    hi_out: wp.array(dtype=wp.vec3),
    cell_lo_out: wp.array(dtype=wp.vec3i),
    cell_hi_out: wp.array(dtype=wp.vec3i),
    cell_count_out: wp.array(dtype=wp.int32),
    clamped_out: wp.array(dtype=wp.int32),
):
    """Swept, padded box of each element (its vertices from x_start to x_start + dt velocity) and the
    voxel range it touches."""
    e = wp.tid()
    lo, hi = swept_box(elements, e, x_start, velocity, dt, pad)
    lo_out[e] = lo
    hi_out[e] = hi
    c_lo = cell_of(lo, inv_cell_size)
    c_hi = cell_of(hi, inv_cell_size)
    finite = wp.isfinite(lo) and wp.isfinite(hi)
    clamped = False
    for k in range(3):
        if not finite:
            c_hi[k] = c_lo[k]
        elif c_hi[k] - c_lo[k] >= MAX_CELL_SPAN:
            c_hi[k] = c_lo[k] + MAX_CELL_SPAN - 1
            clamped = True
    if not finite:
        c_lo = wp.vec3i(0, 0, 0)
        c_hi = wp.vec3i(0, 0, 0)
        clamped = True
    if clamped:
        wp.atomic_add(clamped_out, 0, 1)
    cell_lo_out[e] = c_lo
    cell_hi_out[e] = c_hi
    cell_count_out[e] = (c_hi[0] - c_lo[0] + 1) * (c_hi[1] - c_lo[1] + 1) * (c_hi[2] - c_lo[2] + 1)


@wp.kernel(enable_backward=False)
def fill_cells(
    cell_lo: wp.array(dtype=wp.vec3i),
    cell_hi: wp.array(dtype=wp.vec3i),
    offsets: wp.array(dtype=wp.int32),
    table_mask: int,
    capacity: int,
    keys_out: wp.array(dtype=wp.int32),
    values_out: wp.array(dtype=wp.int32),
    entry_element_out: wp.array(dtype=wp.int32),
    entry_cell_out: wp.array(dtype=wp.vec3i),
):
    """One entry (bucket key, entry id) per voxel an element touches; entries past `capacity` are dropped
    (the capturable path's overflow, reported by :func:`entry_total`)."""
    e = wp.tid()
    lo = cell_lo[e]
    hi = cell_hi[e]
    slot = offsets[e]
    for i in range(lo[0], hi[0] + 1):
        for j in range(lo[1], hi[1] + 1):
            for k in range(lo[2], hi[2] + 1):
                if slot >= capacity:
                    return
                c = wp.vec3i(i, j, k)
                keys_out[slot] = cell_hash(c, table_mask)
                values_out[slot] = slot
                entry_element_out[slot] = e
                entry_cell_out[slot] = c
                slot += 1


@wp.func
def mark_bucket(i: int, keys: wp.array(dtype=wp.int32), total: int, bucket_start_out: wp.array(dtype=wp.int32),
                bucket_end_out: wp.array(dtype=wp.int32)):
    """Sorted entry i opens and/or closes its bucket's [start, end) run."""
    k = keys[i]
    if i == 0 or keys[i - 1] != k:
        bucket_start_out[k] = i
    if i == total - 1 or keys[i + 1] != k:
        bucket_end_out[k] = i + 1


@wp.kernel(enable_backward=False)
def bucket_ranges(keys: wp.array(dtype=wp.int32), total: int, bucket_start_out: wp.array(dtype=wp.int32),
                  bucket_end_out: wp.array(dtype=wp.int32)):
    """[start, end) of each bucket's run in the sorted keys (buckets must be zeroed: empty = [0, 0))."""
    mark_bucket(wp.tid(), keys, total, bucket_start_out, bucket_end_out)


@wp.func
def gather_sorted_entry(s: int, sorted_entries: wp.array(dtype=wp.int32), entry_element: wp.array(dtype=wp.int32),
                        entry_cell: wp.array(dtype=wp.vec3i), lo: wp.array(dtype=wp.vec3), hi: wp.array(dtype=wp.vec3),
                        element_out: wp.array(dtype=wp.int32), cell_out: wp.array(dtype=wp.vec3i),
                        lo_out: wp.array(dtype=wp.vec3), hi_out: wp.array(dtype=wp.vec3)):
    """Sorted entry s's element, voxel and box."""
    e = sorted_entries[s]
    element = entry_element[e]
    element_out[s] = element
    cell_out[s] = entry_cell[e]
    lo_out[s] = lo[element]
    hi_out[s] = hi[element]


@wp.kernel(enable_backward=False)
def gather_sorted_entries(sorted_entries: wp.array(dtype=wp.int32), entry_element: wp.array(dtype=wp.int32),
                          entry_cell: wp.array(dtype=wp.vec3i), lo: wp.array(dtype=wp.vec3), hi: wp.array(dtype=wp.vec3),
                          element_out: wp.array(dtype=wp.int32), cell_out: wp.array(dtype=wp.vec3i),
                          lo_out: wp.array(dtype=wp.vec3), hi_out: wp.array(dtype=wp.vec3)):
    """Entries' element, voxel and box in bucket order, so that a bucket's scan reads memory sequentially."""
    gather_sorted_entry(wp.tid(), sorted_entries, entry_element, entry_cell, lo, hi, element_out, cell_out, lo_out, hi_out)


@wp.kernel(enable_backward=False)
def gather_sorted_entries_listed(total: wp.array(dtype=wp.int32), sorted_entries: wp.array(dtype=wp.int32),
                                 entry_element: wp.array(dtype=wp.int32), entry_cell: wp.array(dtype=wp.vec3i),
                                 lo: wp.array(dtype=wp.vec3), hi: wp.array(dtype=wp.vec3), element_out: wp.array(dtype=wp.int32),
                                 cell_out: wp.array(dtype=wp.vec3i), lo_out: wp.array(dtype=wp.vec3), hi_out: wp.array(dtype=wp.vec3)):
    """:func:`gather_sorted_entries` launched over the capacity: the first total[0] entries (capturable path)."""
    s = wp.tid()
    if s < total[0]:
        gather_sorted_entry(s, sorted_entries, entry_element, entry_cell, lo, hi, element_out, cell_out, lo_out, hi_out)


@wp.kernel(enable_backward=False)
def entry_total(cell_count: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), count: int, capacity: int, slot: int,
                total_out: wp.array(dtype=wp.int32), overflow_out: wp.array(dtype=wp.int32)):
    """One thread: the number of grid entries (exclusive scan's last offset plus the last count), clamped to the
    capacity; a larger need is recorded as overflow_out[slot] = max(overflow_out[slot], need)."""
    total = offsets[count - 1] + cell_count[count - 1]
    if total > capacity:
        wp.atomic_max(overflow_out, slot, total)
        total = capacity
    total_out[0] = total


@wp.kernel(enable_backward=False)
def pad_entry_keys(total: wp.array(dtype=wp.int32), sentinel: int, keys_out: wp.array(dtype=wp.int32)):
    """Keys past the entry count take `sentinel` (above every bucket), so that sorting the whole capacity
    leaves the entries first, in the order a sort of the entries alone gives (the sort is stable)."""
    i = wp.tid()
    if i >= total[0]:
        keys_out[i] = sentinel


@wp.kernel(enable_backward=False)
def bucket_ranges_listed(keys: wp.array(dtype=wp.int32), total: wp.array(dtype=wp.int32), bucket_start_out: wp.array(dtype=wp.int32),
                         bucket_end_out: wp.array(dtype=wp.int32)):
    """:func:`bucket_ranges` launched over the capacity, with the entry count total[0] on the device."""
    i = wp.tid()
    n = total[0]
    if i < n:
        mark_bucket(i, keys, n, bucket_start_out, bucket_end_out)


@wp.kernel(enable_backward=False)
def clamp_count(capacity: int, slot: int, count_out: wp.array(dtype=wp.int32), overflow_out: wp.array(dtype=wp.int32)):
    """One thread: a buffer counted count_out[0] items and kept the first `capacity`: record a larger need in
    overflow_out[slot] (max over the frame) and clamp the count to what the buffer holds."""
    n = count_out[0]
    if n > capacity:
        wp.atomic_max(overflow_out, slot, n)
        count_out[0] = capacity


@wp.kernel(enable_backward=False)
def find_pairs(
    query_elements: wp.array2d(dtype=wp.int32),
    query_ids: wp.array(dtype=wp.int32),
    query_skip: wp.array(dtype=wp.int32),
    query_lo: wp.array(dtype=wp.vec3),
    query_hi: wp.array(dtype=wp.vec3),
    query_cell_lo: wp.array(dtype=wp.vec3i),
    query_cell_hi: wp.array(dtype=wp.vec3i),
    target_elements: wp.array2d(dtype=wp.int32),
    target_ids: wp.array(dtype=wp.int32),
    target_skip: wp.array(dtype=wp.int32),
    sorted_element: wp.array(dtype=wp.int32),
    sorted_cell: wp.array(dtype=wp.vec3i),
    sorted_lo: wp.array(dtype=wp.vec3),
    sorted_hi: wp.array(dtype=wp.vec3),
    bucket_start: wp.array(dtype=wp.int32),
    bucket_end: wp.array(dtype=wp.int32),
    table_mask: int,
    inv_cell_size: float,
    ordered: int,
    capacity: int,
    pairs_out: wp.array(dtype=wp.vec2i),
    pair_count_out: wp.array(dtype=wp.int32),
):
    """Pairs (query element, target element), as ids (`query_ids`, `target_ids` map a set's rows to the
    ids pairs report), whose boxes overlap and that share no vertex. Queries and targets whose id is
    flagged in `query_skip` / `target_skip` take no part; with `ordered`, each unordered pair is
    reported once (query id < target id; the target's ids must ascend with its rows). Appends to the buffer (counts every pair, writes those that fit)."""
    q = wp.tid()
    q_id = query_ids[q]
    if query_skip[q_id] != 0:
        return
    q_row = element_row(query_elements, q)
    q_lo = query_lo[q]
    q_hi = query_hi[q]
    lo = query_cell_lo[q]
    hi = query_cell_hi[q]
    for i in range(lo[0], hi[0] + 1):
        for j in range(lo[1], hi[1] + 1):
            for k in range(lo[2], hi[2] + 1):
                c = wp.vec3i(i, j, k)
                b = cell_hash(c, table_mask)
                first = bucket_start[b]
                end = bucket_end[b]
                if ordered != 0:
                    # a bucket's entries come in the order of the target's rows (stable sort of entries filled row by
                    # row), whose ids ascend: start at the first entry above q_id
                    last = end
                    while first < last:
                        mid = (first + last) // 2
                        if target_ids[sorted_element[mid]] <= q_id:
                            first = mid + 1
                        else:
                            last = mid
                for s in range(first, end):
                    ec = sorted_cell[s]
                    if ec[0] != i or ec[1] != j or ec[2] != k:
                        continue
                    # the box first (most entries fail it), then the indirect reads
                    t_lo = sorted_lo[s]
                    t_hi = sorted_hi[s]
                    if not boxes_overlap(q_lo, q_hi, t_lo, t_hi):
                        continue
                    t = sorted_element[s]
                    t_id = target_ids[t]
                    if target_skip[t_id] != 0:
                        continue
                    # report the pair only from the voxel of the boxes' intersection's lower corner
                    corner = cell_of(wp.max(q_lo, t_lo), inv_cell_size)
                    corner = wp.min(corner, hi)  # a clamped box may not reach the corner's voxel
                    if corner[0] != i or corner[1] != j or corner[2] != k:
                        continue
                    if share_vertex(q_row, element_row(target_elements, t)):
                        continue
                    slot = wp.atomic_add(pair_count_out, 0, 1)
                    if slot < capacity:
                        pairs_out[slot] = wp.vec2i(q_id, t_id)


@wp.kernel(enable_backward=False)
def take_escaped(velocity: wp.array(dtype=wp.vec3), dt: float, margin: float, velocity_ref_out: wp.array(dtype=wp.vec3),
                 escaped_out: wp.array(dtype=wp.int32), count_out: wp.array(dtype=wp.int32)):
    """Particles whose end point left the margin around their reference step's end point: flag them, count
    them and make their current velocity their reference (updated in place: forward-only broad phase)."""
    i = wp.tid()
    escaped_out[i] = 0
    if wp.length(dt * (velocity[i] - velocity_ref_out[i])) > margin:
        escaped_out[i] = 1
        velocity_ref_out[i] = velocity[i]
        wp.atomic_add(count_out, 0, 1)


@wp.kernel(enable_backward=False)
def mark_dirty(elements: wp.array2d(dtype=wp.int32), escaped: wp.array(dtype=wp.int32), dirty_out: wp.array(dtype=wp.int32),
               fresh_out: wp.array(dtype=wp.int32)):
    """An element with an escaped vertex is fresh (registered again now) and dirty (flags accumulate until the next full build)."""
    e = wp.tid()
    fresh_out[e] = 0
    for k in range(3):
        i = elements[e, k]
        if i >= 0:
            if escaped[i] != 0:
                fresh_out[e] = 1
                dirty_out[e] = 1


@wp.kernel(enable_backward=False)
def mark_changed_elements(elements: wp.array2d(dtype=wp.int32), weight: wp.array(dtype=float), zone: wp.array(dtype=wp.int32),
                          flags_out: wp.array(dtype=wp.int32)):
    """An element changed when a vertex did: it received a velocity change (weight > 0) or is in an impact zone."""
    e = wp.tid()
    flags_out[e] = 0
    for k in range(3):
        i = elements[e, k]
        if i >= 0:
            if weight[i] > 0.0 or zone[i] >= 0:
                flags_out[e] = 1


@wp.func
def select_if_flagged(p: wp.vec2i, first_flags: wp.array(dtype=wp.int32), second_flags: wp.array(dtype=wp.int32), flagged: int,
                      selected_out: wp.array(dtype=wp.vec2i), count_out: wp.array(dtype=wp.int32)):
    """Append pair p when it has a flagged element (`flagged` = 1) or neither element flagged (0)."""
    hit = first_flags[p[0]] != 0 or second_flags[p[1]] != 0
    if hit == (flagged != 0):
        slot = wp.atomic_add(count_out, 0, 1)
        selected_out[slot] = p


@wp.kernel(enable_backward=False)
def select_flagged_pairs(pairs: wp.array(dtype=wp.vec2i), first_flags: wp.array(dtype=wp.int32), second_flags: wp.array(dtype=wp.int32),
                         flagged: int, selected_out: wp.array(dtype=wp.vec2i), count_out: wp.array(dtype=wp.int32)):
    """Compact the pairs with a flagged element (`flagged` = 1) or with neither element flagged (0)."""
    select_if_flagged(pairs[wp.tid()], first_flags, second_flags, flagged, selected_out, count_out)


@wp.kernel(enable_backward=False)
def select_flagged_pairs_listed(count: wp.array(dtype=wp.int32), pairs: wp.array(dtype=wp.vec2i), first_flags: wp.array(dtype=wp.int32),
                                second_flags: wp.array(dtype=wp.int32), flagged: int, selected_out: wp.array(dtype=wp.vec2i),
                                count_out: wp.array(dtype=wp.int32)):
    """:func:`select_flagged_pairs` launched over the capacity: the first count[0] pairs (capturable path; the
    selection is a subset, so it never exceeds the capacity)."""
    tid = wp.tid()
    if tid < count[0]:
        select_if_flagged(pairs[tid], first_flags, second_flags, flagged, selected_out, count_out)


# -- the capturable path's patch: a few particles left the margin, so only the elements touching them are registered
# again; their pairs are found by testing them against every element (see kernels.selfcollide.patch_*).


@wp.kernel(enable_backward=False)
def take_moved(x_start: wp.array(dtype=wp.vec3), velocity: wp.array(dtype=wp.vec3), dt: float, margin: float,
               start_ref_out: wp.array(dtype=wp.vec3), velocity_ref_out: wp.array(dtype=wp.vec3), escaped_out: wp.array(dtype=wp.int32),
               count_out: wp.array(dtype=wp.int32)):
    """:func:`take_escaped` for a registration kept from step to step (the capturable path): particles whose start
    point x_start or end point x_start + dt velocity is farther than the margin from their registered trajectory's
    (start_ref, start_ref + dt velocity_ref); flag them, count them and register their current trajectory (updated in
    place: forward-only broad phase). While no particle escapes, every point of every trajectory is within the margin
    of its registered one (a convex combination of the two ends), so the pairs found on the registered trajectories
    with boxes grown by the margin hold every pair of the current ones."""
    i = wp.tid()
    escaped_out[i] = 0
    x0 = x_start[i]
    s = start_ref_out[i]
    moved_end = x0 + dt * velocity[i] - (s + dt * velocity_ref_out[i])
    if wp.length(x0 - s) > margin or wp.length(moved_end) > margin:
        escaped_out[i] = 1
        start_ref_out[i] = x0
        velocity_ref_out[i] = velocity[i]
        wp.atomic_add(count_out, 0, 1)


REGISTRATION_VALID = wp.constant(0)  # 1 while the registration below holds (a build sets it)
REGISTRATION_DT = wp.constant(1)  # the step [s], pad, margin and reach [m] the broad phase was registered with
REGISTRATION_PAD = wp.constant(2)
REGISTRATION_MARGIN = wp.constant(3)
REGISTRATION_REACH = wp.constant(4)
REGISTRATION_SIZE = 5


@wp.kernel(enable_backward=False)
def register_broad_phase(dt: float, pad: float, margin: float, reach: float, registration_out: wp.array(dtype=float)):
    """One thread, after a full build: the broad phase holds for trajectories within the margin of the registered ones
    while the step, pad, margin and reach stay these."""
    registration_out[REGISTRATION_VALID] = 1.0
    registration_out[REGISTRATION_DT] = dt
    registration_out[REGISTRATION_PAD] = pad
    registration_out[REGISTRATION_MARGIN] = margin
    registration_out[REGISTRATION_REACH] = reach


@wp.kernel(enable_backward=False)
def patch_or_build(escaped: wp.array(dtype=wp.int32), limit: int, registration: wp.array(dtype=float), dt: float, pad: float,
                   margin: float, reach: float, build_out: wp.array(dtype=wp.int32), patch_out: wp.array(dtype=wp.int32)):
    """One thread: after :func:`take_moved`, build the broad phase again when it was never registered (or with another
    step, pad, margin or reach: the thickness changed) or when more than `limit` particles left the margin, patch it
    when some (at most `limit`) did, else keep it."""
    n = escaped[0]
    same = (registration[REGISTRATION_VALID] == 1.0 and registration[REGISTRATION_DT] == dt and registration[REGISTRATION_PAD] == pad
            and registration[REGISTRATION_MARGIN] == margin and registration[REGISTRATION_REACH] == reach)
    build = n > limit or not same
    build_out[0] = wp.where(build, 1, 0)
    patch_out[0] = wp.where(n > 0 and not build, 1, 0)


@wp.kernel(enable_backward=False)
def mark_fresh(elements: wp.array2d(dtype=wp.int32), escaped: wp.array(dtype=wp.int32), flags_out: wp.array(dtype=wp.int32),
               list_out: wp.array(dtype=wp.int32), count_out: wp.array(dtype=wp.int32)):
    """Flag the elements with an escaped vertex (1, else 0) and list them (count_out zeroed before)."""
    e = wp.tid()
    fresh = 0
    for k in range(3):
        i = elements[e, k]
        if i >= 0:
            if escaped[i] != 0:
                fresh = 1
    flags_out[e] = fresh
    if fresh != 0:
        list_out[wp.atomic_add(count_out, 0, 1)] = e


@wp.kernel(enable_backward=False)
def fresh_bounds(flags: wp.array(dtype=wp.int32), elements: wp.array2d(dtype=wp.int32), x_start: wp.array(dtype=wp.vec3),
                 velocity: wp.array(dtype=wp.vec3), dt: float, pad: float, lo_out: wp.array(dtype=wp.vec3), hi_out: wp.array(dtype=wp.vec3)):
    """:func:`element_bounds`' swept, padded box (:func:`swept_box`) of the flagged elements; the others keep theirs."""
    e = wp.tid()
    if flags[e] == 0:
        return
    lo, hi = swept_box(elements, e, x_start, velocity, dt, pad)
    lo_out[e] = lo
    hi_out[e] = hi


@wp.kernel(enable_backward=False)
def copy_pairs_listed(count: wp.array(dtype=wp.int32), pairs: wp.array(dtype=wp.vec2i), pairs_out: wp.array(dtype=wp.vec2i),
                      count_out: wp.array(dtype=wp.int32)):
    """Launched over the capacity: the first count[0] pairs and the count."""
    tid = wp.tid()
    n = count[0]
    if tid == 0:
        count_out[0] = n
    if tid < n:
        pairs_out[tid] = pairs[tid]


# -- an exclusive prefix sum that allocates nothing (capturable inside a conditional graph node) ----------------------
# wp.utils.array_scan takes CUB's temporary storage from the allocator on every call; inside a CUDA graph's
# conditional body (a `wp.capture_if`/`capture_while` branch) an allocation node is not allowed. Three launches
# with fixed buffers instead: each tile of SCAN_TILE counts scanned in shared memory and its total kept, the
# totals scanned by one thread (a 128^2 cloth's 32 k triangles are 32 tiles), the tile's offset added.
SCAN_TILE = wp.constant(1024)


@wp.kernel(enable_backward=False)
def scan_tiles(counts: wp.array(dtype=wp.int32), scanned_out: wp.array(dtype=wp.int32), tile_totals_out: wp.array(dtype=wp.int32)):
    """Launched tiled over ceil(n / SCAN_TILE) blocks: exclusive scan within each tile, and its total."""
    b = wp.tid()
    t = wp.tile_load(counts, shape=SCAN_TILE, offset=b * SCAN_TILE)  # past the end: zeros
    wp.tile_store(scanned_out, wp.tile_scan_exclusive(t), offset=b * SCAN_TILE)  # past the end: not stored
    wp.tile_store(tile_totals_out, wp.tile_sum(t), offset=b)


@wp.kernel(enable_backward=False)
def scan_tile_totals(tile_count: int, tile_totals_out: wp.array(dtype=wp.int32)):
    """One thread: the tile totals in place to their exclusive prefix sums."""
    total = int(0)
    for b in range(tile_count):
        c = tile_totals_out[b]
        tile_totals_out[b] = total
        total += c


@wp.kernel(enable_backward=False)
def add_tile_offsets(tile_offsets: wp.array(dtype=wp.int32), scanned_out: wp.array(dtype=wp.int32)):
    i = wp.tid()
    scanned_out[i] = scanned_out[i] + tile_offsets[i // SCAN_TILE]
