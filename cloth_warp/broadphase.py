"""Broad phase of self-collision: a spatial hash grid of voxels rebuilt every step (Choi & Ko 2002).

Particles and edges are registered in the voxels their swept, padded boxes touch; triangles query the
particle grid (point-triangle candidates) and edges query the edge grid (edge-edge candidates). Only
elements sharing a voxel become candidates, pairs sharing a vertex are skipped, and each pair is
reported once. Buffers grow: the pair count is always exact, and when it exceeds the buffer the
buffer is enlarged and the search repeated (``grown`` counts how often).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .kernels import broadphase as kb


def _next_pow2(n: int) -> int:
    return 1 << max(int(n) - 1, 1).bit_length()


def exclusive_scan(counts: wp.array, offsets_out: wp.array, tile_totals: wp.array, tiled: bool | None = None) -> None:
    """offsets_out[i] = sum of counts[:i] (int32), allocating nothing: on CUDA three launches over fixed buffers
    (`tile_totals`: ceil(n / SCAN_TILE) entries), so a graph can record it inside a conditional node, where
    ``wp.utils.array_scan`` (CUB's temporary storage, allocated per call) is refused; on the CPU (`tiled` None)
    ``wp.utils.array_scan``, which allocates nothing there and keeps CPU frames bit-identical to earlier ones."""
    dev = counts.device
    n = counts.shape[0]
    if not (dev.is_cuda if tiled is None else tiled):
        wp.utils.array_scan(counts, offsets_out, inclusive=False)
        return
    tiles = (n + kb.SCAN_TILE - 1) // kb.SCAN_TILE
    wp.launch_tiled(kb.scan_tiles, dim=[tiles], inputs=[counts], outputs=[offsets_out, tile_totals], block_dim=256, device=dev,
                    record_tape=False)
    wp.launch(kb.scan_tile_totals, dim=1, inputs=[tiles], outputs=[tile_totals], device=dev, record_tape=False)
    wp.launch(kb.add_tile_offsets, dim=n, inputs=[tile_totals], outputs=[offsets_out], device=dev, record_tape=False)


class ElementSet:
    """Elements (rows of up to three vertex indices, -1 padded) and their per-step boxes and voxels;
    with `grid=True` also the hash-grid entries other elements search."""

    def __init__(self, elements: np.ndarray, device, grid: bool, ids: np.ndarray | None = None, particle_root: np.ndarray | None = None):
        rows = np.full((max(len(elements), 1), 3), -1, np.int32)
        if len(elements):
            e = np.asarray(elements, np.int32).reshape(len(elements), -1)
            rows[: len(e), : e.shape[1]] = e
        self.count = len(elements)
        self.device = device
        self.elements = wp.array(rows, dtype=wp.int32, device=device)
        self.particle_root = particle_root
        # the rows as vertex identities, what "sharing a vertex" compares: a sewn pair of particles is one vertex
        self.adjacency = self.elements
        if particle_root is not None:
            self.adjacency = wp.array(np.where(rows >= 0, np.asarray(particle_root, np.int32)[np.maximum(rows, 0)], -1).astype(np.int32),
                                      dtype=wp.int32, device=device)
        # the id pairs report for each row (its index in the full set; a patch's subsets keep the full set's ids)
        ids = np.arange(self.count) if ids is None else np.asarray(ids)
        self.ids = wp.array(np.append(ids, 0).astype(np.int32)[: max(self.count, 1)], dtype=wp.int32, device=device)
        n = max(self.count, 1)
        self.lo = wp.zeros(n, dtype=wp.vec3, device=device)
        self.hi = wp.zeros(n, dtype=wp.vec3, device=device)
        self.cell_lo = wp.zeros(n, dtype=wp.vec3i, device=device)
        self.cell_hi = wp.zeros(n, dtype=wp.vec3i, device=device)
        self.cell_count = wp.zeros(n, dtype=wp.int32, device=device)
        self.offsets = wp.zeros(n, dtype=wp.int32, device=device)
        self.tile_totals = wp.zeros((n + kb.SCAN_TILE - 1) // kb.SCAN_TILE, dtype=wp.int32, device=device)  # exclusive_scan's
        self.grid = grid
        self.entries = 0
        if grid:
            self._allocate_entries(_next_pow2(4 * n))

    def _allocate_entries(self, capacity: int):
        """Entry arrays for `capacity` entries and a hash table of 2 x capacity buckets (a bucket then
        holds about one voxel's entries)."""
        dev = self.device
        self.entry_capacity = int(capacity)
        self.table_size = _next_pow2(max(2 * self.entry_capacity, 64))
        self.bucket_start = wp.zeros(self.table_size, dtype=wp.int32, device=dev)
        self.bucket_end = wp.zeros(self.table_size, dtype=wp.int32, device=dev)
        self.keys = wp.zeros(2 * self.entry_capacity, dtype=wp.int32, device=dev)  # radix sort needs 2x
        self.values = wp.zeros(2 * self.entry_capacity, dtype=wp.int32, device=dev)
        self.entry_element = wp.zeros(self.entry_capacity, dtype=wp.int32, device=dev)
        self.entry_cell = wp.zeros(self.entry_capacity, dtype=wp.vec3i, device=dev)
        self.sorted_element = wp.zeros(self.entry_capacity, dtype=wp.int32, device=dev)
        self.sorted_cell = wp.zeros(self.entry_capacity, dtype=wp.vec3i, device=dev)
        self.sorted_lo = wp.zeros(self.entry_capacity, dtype=wp.vec3, device=dev)
        self.sorted_hi = wp.zeros(self.entry_capacity, dtype=wp.vec3, device=dev)
        self.entry_count = wp.zeros(1, dtype=wp.int32, device=dev)
        """The entry count of the last :meth:`update_fixed`, on the device (clamped to the capacity)."""

    def subset(self, ids: np.ndarray, grid: bool) -> "ElementSet":
        """The elements with these ids, keeping their ids."""
        return ElementSet(self.elements.numpy()[ids], self.device, grid, ids=ids, particle_root=self.particle_root)

    def update(self, x_start: wp.array, velocity: wp.array, dt: float, pad: float, inv_cell_size: float, clamped: wp.array):
        """Boxes of the step x_start -> x_start + dt velocity grown by `pad` [m]; re-registers the grid's entries."""
        if self.count == 0:
            self.entries = 0
            return
        dev = self.device
        wp.launch(kb.element_bounds, dim=self.count, inputs=[self.elements, x_start, velocity, dt, pad, inv_cell_size],
                  outputs=[self.lo, self.hi, self.cell_lo, self.cell_hi, self.cell_count, clamped], device=dev, record_tape=False)
        if not self.grid:
            return
        wp.utils.array_scan(self.cell_count, self.offsets, inclusive=False)
        total = int(self.offsets.numpy()[self.count - 1]) + int(self.cell_count.numpy()[self.count - 1])
        if total > self.entry_capacity:
            self._allocate_entries(_next_pow2(total))
        wp.launch(kb.fill_cells, dim=self.count, inputs=[self.cell_lo, self.cell_hi, self.offsets, self.table_size - 1, self.entry_capacity],
                  outputs=[self.keys, self.values, self.entry_element, self.entry_cell], device=dev, record_tape=False)
        wp.utils.radix_sort_pairs(self.keys, self.values, total)
        wp.launch(kb.gather_sorted_entries, dim=total, inputs=[self.values, self.entry_element, self.entry_cell, self.lo, self.hi],
                  outputs=[self.sorted_element, self.sorted_cell, self.sorted_lo, self.sorted_hi], device=dev, record_tape=False)
        self.bucket_start.zero_()
        self.bucket_end.zero_()
        wp.launch(kb.bucket_ranges, dim=total, inputs=[self.keys, total], outputs=[self.bucket_start, self.bucket_end], device=dev,
                  record_tape=False)
        self.entries = total

    def update_fixed(self, x_start: wp.array, velocity: wp.array, dt: float, pad: float, inv_cell_size: float, clamped: wp.array,
                     overflow: wp.array, slot: int):
        """:meth:`update` without reading the device: the entry count stays on the device (:attr:`entry_count`),
        at most :attr:`entry_capacity` entries are registered, and a larger need is recorded in overflow[slot]
        (the entries kept are then incomplete: the caller re-runs after :meth:`grow_entries`). The whole capacity
        is sorted, entries past the count keyed above every bucket, so the entries come out in the order of
        :meth:`update`'s sort (the radix sort is stable) and the same pairs are found in the same order."""
        if self.count == 0:
            self.entries = 0
            return
        dev = self.device
        wp.launch(kb.element_bounds, dim=self.count, inputs=[self.elements, x_start, velocity, dt, pad, inv_cell_size],
                  outputs=[self.lo, self.hi, self.cell_lo, self.cell_hi, self.cell_count, clamped], device=dev, record_tape=False)
        if not self.grid:
            return
        cap = self.entry_capacity
        exclusive_scan(self.cell_count, self.offsets, self.tile_totals)
        wp.launch(kb.entry_total, dim=1, inputs=[self.cell_count, self.offsets, self.count, cap, slot], outputs=[self.entry_count, overflow],
                  device=dev, record_tape=False)
        wp.launch(kb.fill_cells, dim=self.count, inputs=[self.cell_lo, self.cell_hi, self.offsets, self.table_size - 1, cap],
                  outputs=[self.keys, self.values, self.entry_element, self.entry_cell], device=dev, record_tape=False)
        wp.launch(kb.pad_entry_keys, dim=cap, inputs=[self.entry_count, self.table_size], outputs=[self.keys], device=dev,
                  record_tape=False)
        wp.utils.radix_sort_pairs(self.keys, self.values, cap, 0, self.table_size.bit_length())
        wp.launch(kb.gather_sorted_entries_listed, dim=cap, inputs=[self.entry_count, self.values, self.entry_element, self.entry_cell, self.lo,
                                                                   self.hi],
                  outputs=[self.sorted_element, self.sorted_cell, self.sorted_lo, self.sorted_hi], device=dev, record_tape=False)
        self.bucket_start.zero_()
        self.bucket_end.zero_()
        wp.launch(kb.bucket_ranges_listed, dim=cap, inputs=[self.keys, self.entry_count], outputs=[self.bucket_start, self.bucket_end],
                  device=dev, record_tape=False)
        self.entries = None  # on the device


class PairBuffer:
    """Candidate pairs (vec2i) of one kind with an exact count; grows instead of dropping pairs."""

    def __init__(self, device, capacity: int = 1024):
        self.device = device
        self.count_array = wp.zeros(1, dtype=wp.int32, device=device)
        self._allocate(capacity)
        self.count = 0
        self.grown = 0

    def _allocate(self, capacity: int):
        self.capacity = int(capacity)
        self.pairs = wp.zeros(self.capacity, dtype=wp.vec2i, device=self.device)

    def search(self, searches: list, inv_cell_size: float):
        """Every overlapping, vertex-disjoint pair of the `searches` into :attr:`pairs` [: :attr:`count`]:
        each is (query set, target set with grid entries, ordered, query skip flags, target skip flags) and
        appends its (query id, target id) pairs (with `ordered`, each unordered pair once)."""
        self.count = 0
        searches = [s for s in searches if s[0].count and s[1].count and s[1].entries]
        if not searches:
            return
        while True:
            self.count_array.zero_()
            for query, target, ordered, query_skip, target_skip in searches:
                wp.launch(kb.find_pairs, dim=query.count,
                          inputs=[query.adjacency, query.ids, query_skip, query.lo, query.hi, query.cell_lo, query.cell_hi,
                                  target.adjacency, target.ids, target_skip, target.sorted_element, target.sorted_cell,
                                  target.sorted_lo, target.sorted_hi, target.bucket_start, target.bucket_end,
                                  target.table_size - 1, inv_cell_size, int(ordered), self.capacity],
                          outputs=[self.pairs, self.count_array], device=self.device, record_tape=False)
            n = int(self.count_array.numpy()[0])
            if n <= self.capacity:
                self.count = n
                return
            self._allocate(_next_pow2(n))
            self.grown += 1

    def search_fixed(self, searches: list, inv_cell_size: float, overflow: wp.array, slot: int):
        """:meth:`search` without reading the device: one pass, the count in :attr:`count_array` (clamped to the
        capacity), a larger need recorded in overflow[slot] (the pairs kept are then incomplete). Targets'
        entries may be on the device (empty buckets give no pairs)."""
        self.count = None  # on the device
        self.count_array.zero_()
        for query, target, ordered, query_skip, target_skip in searches:
            if not (query.count and target.count):
                continue
            wp.launch(kb.find_pairs, dim=query.count,
                      inputs=[query.adjacency, query.ids, query_skip, query.lo, query.hi, query.cell_lo, query.cell_hi,
                              target.adjacency, target.ids, target_skip, target.sorted_element, target.sorted_cell,
                              target.sorted_lo, target.sorted_hi, target.bucket_start, target.bucket_end,
                              target.table_size - 1, inv_cell_size, int(ordered), self.capacity],
                      outputs=[self.pairs, self.count_array], device=self.device, record_tape=False)
        wp.launch(kb.clamp_count, dim=1, inputs=[self.capacity, slot], outputs=[self.count_array, overflow], device=self.device,
                  record_tape=False)

    def grow(self, needed: int) -> bool:
        """Make room for `needed` pairs (a power of two); False when they fit already."""
        if needed <= self.capacity:
            return False
        self._allocate(_next_pow2(needed))
        self.grown += 1
        return True

    def numpy(self) -> np.ndarray:
        return self.pairs.numpy()[: self.count].copy()


class SelfCollisionGrid:
    """The per-step broad phase of a cloth mesh: point-triangle and edge-edge candidate pairs.

    Args:
        triangles: (T, 3) vertex indices; edges: (E, 2) (the unique edges of the triangles by default).
        particle_count: number of particles.
        particle_root: (particle_count,) per particle, the vertex it is one with (a seam's particles: the smallest of
            them); elements sharing such a vertex are adjacent and never paired. Default: each particle its own.
        cell_size: voxel edge [m] (Choi & Ko: about an element's size; default twice the mean edge length,
            the fastest on piled cloth: 30 % less pair search than one edge length, same pairs).
    """

    def __init__(self, triangles: np.ndarray, particle_count: int, device, cell_size: float | None = None, edges: np.ndarray | None = None,
                 rest_positions: np.ndarray | None = None, pair_capacity: int = 1024, particle_root: np.ndarray | None = None):
        tris = np.asarray(triangles, np.int64).reshape(-1, 3)
        if edges is None:
            edges = unique_edges(tris)
        self.edges_np = np.asarray(edges, np.int64).reshape(-1, 2)
        if cell_size is None:
            if rest_positions is None or not len(self.edges_np):
                raise ValueError("give cell_size or rest_positions to size the voxels")
            p = np.asarray(rest_positions, float)
            cell_size = 2.0 * float(np.mean(np.linalg.norm(p[self.edges_np[:, 0]] - p[self.edges_np[:, 1]], axis=1)))
        if not (cell_size > 0.0):
            raise ValueError(f"voxel size must be positive [m], got {cell_size!r}")
        self.cell_size = float(cell_size)
        self.device = device
        root = None if particle_root is None else np.asarray(particle_root, np.int64)
        self.points = ElementSet(np.arange(particle_count).reshape(-1, 1), device, grid=True, particle_root=root)
        self.edges = ElementSet(self.edges_np, device, grid=True, particle_root=root)
        self.triangles = ElementSet(tris, device, grid=False, particle_root=root)
        self.vertex_face = PairBuffer(device, pair_capacity)
        self.edge_edge = PairBuffer(device, pair_capacity)
        # pairs with an element the last patch registered again
        self.patch_vertex_face = PairBuffer(device)
        self.patch_edge_edge = PairBuffer(device)
        # per element of each set: registered again by a patch since the last full build (dirty) / by the last patch (fresh)
        self.dirty = {name: wp.zeros(max(s.count, 1), dtype=wp.int32, device=device) for name, s in self.element_sets()}
        self.fresh = {name: wp.zeros(max(s.count, 1), dtype=wp.int32, device=device) for name, s in self.element_sets()}
        self._none = {name: wp.zeros(max(s.count, 1), dtype=wp.int32, device=device) for name, s in self.element_sets()}
        self._escaped_particles = wp.zeros(max(particle_count, 1), dtype=wp.int32, device=device)
        # elements whose box spanned more than MAX_CELL_SPAN voxels along an axis (or was not finite), summed over updates
        self.clamped = wp.zeros(1, dtype=wp.int32, device=device)
        self._escaped = wp.zeros(1, dtype=wp.int32, device=device)
        self._reference = None
        self.fixed_reference = None
        """Per particle, the velocity [m/s] the last :meth:`build_fixed` registered (its own buffer)."""
        self.builds = 0
        self.patches = 0

    def element_sets(self):
        """(name, :class:`ElementSet`) of the points, edges and triangles."""
        return (("points", self.points), ("edges", self.edges), ("triangles", self.triangles))

    def update(self, x_start: wp.array, velocity: wp.array, dt: float, pad: float, margin: float = 0.0):
        """Rebuild the grid for the step x_start -> x_start + dt velocity [m/s] and find the candidate pairs
        (boxes grown by `pad` [m]). With a `margin` [m] the boxes grow by that much more, and :meth:`refresh`
        keeps the pairs for later velocities on the same start positions, patching them where end points leave the margin."""
        inv = 1.0 / self.cell_size
        for _, s in self.element_sets():
            s.update(x_start, velocity, dt, pad + margin, inv, self.clamped)
        for flags in (*self.dirty.values(), *self.fresh.values()):
            flags.zero_()
        none = self._none
        self.vertex_face.search([(self.triangles, self.points, False, none["triangles"], none["points"])], inv)
        self.edge_edge.search([(self.edges, self.edges, True, none["edges"], none["edges"])], inv)
        self.patch_vertex_face.count = self.patch_edge_edge.count = 0
        self._reference = (x_start, wp.clone(velocity), float(dt), float(margin), float(pad))
        self.builds += 1

    def invalidate(self):
        """Forget the last update (the start positions it was built on have changed)."""
        self._reference = None

    def build_fixed(self, x_start: wp.array, velocity: wp.array, dt: float, pad: float, margin: float, overflow: wp.array, slots: dict):
        """:meth:`update` without reading the device (capturable): fixed capacities, counts on the device
        (:attr:`PairBuffer.count_array`), the need of a buffer that overflowed recorded in overflow[slots[name]]
        (names: "points", "edges" (grid entries), "vertex_face", "edge_edge"). The trajectories' velocity is
        copied into :attr:`fixed_reference`. Patches and :meth:`refresh` do not apply to such a build (it
        invalidates the host path's reference)."""
        inv = 1.0 / self.cell_size
        for name, s in self.element_sets():
            s.update_fixed(x_start, velocity, dt, pad + margin, inv, self.clamped, overflow, slots.get(name, 0))
        none = self._none
        self.vertex_face.search_fixed([(self.triangles, self.points, False, none["triangles"], none["points"])], inv, overflow,
                                      slots["vertex_face"])
        self.edge_edge.search_fixed([(self.edges, self.edges, True, none["edges"], none["edges"])], inv, overflow, slots["edge_edge"])
        if self.fixed_reference is None or self.fixed_reference.shape != velocity.shape:
            self.fixed_reference = wp.zeros_like(velocity, requires_grad=False)
        wp.copy(self.fixed_reference, velocity)
        self.invalidate()

    def grow(self, needed: dict) -> bool:
        """Grow the buffers named in `needed` (name -> count, names as in :meth:`build_fixed`) to hold that many
        (powers of two); True when any changed (arrays are new: graphs recorded before must be recorded again).
        A grid's hash table grows with its entries (so its pairs come in a new order)."""
        changed = False
        sets = dict(self.element_sets())
        for name, n in needed.items():
            if name in ("points", "edges"):
                if n > sets[name].entry_capacity:
                    sets[name]._allocate_entries(_next_pow2(n))
                    changed = True
            elif name in ("vertex_face", "edge_edge"):
                changed |= getattr(self, name).grow(n)
        return changed

    def refresh(self, x_start: wp.array, velocity: wp.array, dt: float, pad: float, margin: float, max_fresh: float = 0.25) -> str:
        """Make the pairs valid for the step x_start -> x_start + dt velocity: "kept" when no particle's end
        point moved more than the margin from its reference (the end point it was registered with; then no
        point of any trajectory moved more, so every element's swept box lies inside its registered one);
        "patched" when some did: those particles take the new end point as their reference, the elements
        touching them (:meth:`fresh_flags`) are registered again in small grids of their own, and their
        pairs against everything are searched again (:attr:`patch_vertex_face`, :attr:`patch_edge_edge`):
        the caller's pairs without a fresh element plus these are the pairs of the registered boxes.
        "built" (a full :meth:`update`) on new start positions, or when more than `max_fresh` of the
        elements would be registered again."""
        ref = self._reference
        if ref is None or ref[0] is not x_start or ref[2] != float(dt) or ref[3] != float(margin) or ref[4] != float(pad) or margin <= 0.0:
            self.update(x_start, velocity, dt, pad, margin)
            return "built"
        self._escaped.zero_()
        wp.launch(kb.take_escaped, dim=x_start.shape[0], inputs=[velocity, dt, margin], outputs=[ref[1], self._escaped_particles, self._escaped],
                  device=self.device, record_tape=False)
        if int(self._escaped.numpy()[0]) == 0:
            return "kept"
        fresh_ids, old_ids = {}, {}
        for name, s in self.element_sets():
            wp.launch(kb.mark_dirty, dim=s.count, inputs=[s.elements, self._escaped_particles], outputs=[self.dirty[name], self.fresh[name]],
                      device=self.device, record_tape=False)
            fresh = self.fresh[name].numpy()[: s.count] != 0
            fresh_ids[name] = np.flatnonzero(fresh)
            old_ids[name] = np.flatnonzero((self.dirty[name].numpy()[: s.count] != 0) & ~fresh)
        total = sum(s.count for _, s in self.element_sets())
        if sum(len(i) for i in fresh_ids.values()) > max_fresh * total:
            self.update(x_start, velocity, dt, pad, margin)
            return "built"
        self._patch(x_start, dt, pad + margin, fresh_ids, old_ids)
        return "patched"

    def _patch(self, x_start: wp.array, dt: float, grow: float, fresh_ids: dict, old_ids: dict):
        """Register the fresh elements (at the reference velocities) in grids of their own and search every
        pair with a fresh element: against the full grid's never-patched elements, against each other, and
        against the elements earlier patches registered (their boxes are still valid: none of their
        vertices moved since)."""
        inv = 1.0 / self.cell_size
        velocity = self._reference[1]
        fresh_points = self.points.subset(fresh_ids["points"], grid=True)
        fresh_edges = self.edges.subset(fresh_ids["edges"], grid=True)
        fresh_triangles = self.triangles.subset(fresh_ids["triangles"], grid=False)
        dirty_points = self.points.subset(np.concatenate([fresh_ids["points"], old_ids["points"]]), grid=True)
        old_edges = self.edges.subset(old_ids["edges"], grid=True)
        old_triangles = self.triangles.subset(old_ids["triangles"], grid=False)
        for s in (fresh_points, fresh_edges, fresh_triangles, dirty_points, old_edges, old_triangles):
            s.update(x_start, velocity, dt, grow, inv, self.clamped)
        dirty, none = self.dirty, self._none
        self.patch_vertex_face.search([
            (fresh_triangles, self.points, False, none["triangles"], dirty["points"]),
            (fresh_triangles, dirty_points, False, none["triangles"], none["points"]),
            (self.triangles, fresh_points, False, dirty["triangles"], none["points"]),
            (old_triangles, fresh_points, False, none["triangles"], none["points"]),
        ], inv)
        self.patch_edge_edge.search([
            (fresh_edges, self.edges, False, none["edges"], dirty["edges"]),
            (fresh_edges, fresh_edges, True, none["edges"], none["edges"]),
            (fresh_edges, old_edges, False, none["edges"], none["edges"]),
        ], inv)
        self.patches += 1

    def fresh_flags(self, kind: int) -> tuple[wp.array, wp.array]:
        """The flags of the elements the last patch registered again, for the first and second element of a
        vertex-face (0) or edge-edge (1) pair: the caller's earlier pairs with a flagged element are stale."""
        if kind == 0:
            return self.fresh["triangles"], self.fresh["points"]
        return self.fresh["edges"], self.fresh["edges"]

    # -- checkpoints ---------------------------------------------------------------------------------------------
    def checkpoint_state(self) -> dict:
        """Buffer capacities and counters (they grow and are kept from step to step; every step starts with a
        full build, so nothing else carries over). Restoring them makes a restored run allocate, hash and
        count exactly as the run it continues."""
        out = {f"{name}_entry_capacity": s.entry_capacity for name, s in self.element_sets() if s.grid}
        for name, buf in self.pair_buffers():
            out[f"{name}_capacity"] = buf.capacity
            out[f"{name}_grown"] = buf.grown
        out.update(builds=self.builds, patches=self.patches)
        return out

    def restore_state(self, state: dict) -> None:
        for name, s in self.element_sets():
            key = f"{name}_entry_capacity"
            if s.grid and key in state and int(state[key]) != s.entry_capacity:
                s._allocate_entries(int(state[key]))
        for name, buf in self.pair_buffers():
            if int(state[f"{name}_capacity"]) != buf.capacity:
                buf._allocate(int(state[f"{name}_capacity"]))
            buf.grown = int(state[f"{name}_grown"])
        self.builds, self.patches = int(state["builds"]), int(state["patches"])
        self.invalidate()

    def pair_buffers(self):
        """(name, :class:`PairBuffer`) of the full and the patch searches."""
        return (("vertex_face", self.vertex_face), ("edge_edge", self.edge_edge), ("patch_vertex_face", self.patch_vertex_face),
                ("patch_edge_edge", self.patch_edge_edge))

    @property
    def reference_velocity(self) -> wp.array:
        """Per particle, the velocity [m/s] its registered trajectory was built with."""
        return self._reference[1]


def unique_edges(triangles: np.ndarray) -> np.ndarray:
    """The undirected edges of a triangle list, (E, 2) sorted."""
    t = np.asarray(triangles, np.int64).reshape(-1, 3)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    e.sort(axis=1)
    return np.unique(e, axis=0)
