"""Dressing: garments placed around a body are sewn onto it before the animation starts.

A garment's panels start where the pattern places them (wrapped round the body parts they cover, see
:class:`~cloth_warp.patterns.Wrap`), open at their seams. :func:`dress` simulates them without gravity, with strong
damping and without friction against the body held still in its first pose: the seam springs pull the panels together, the colliders
(and self-collision, between garments too) push whatever starts inside the body or another garment out, and the
settled positions become the builder's initial positions. A mesh body that cloth starts inside (panels placed into the
hips) starts shrunk under it, its surface moved inward along its normals, and grows back to its shape over the first
part of the sewing (:func:`growing_collider`): the cloth is pushed out as it grows, not in one step (which tore a
tube placed 4.7 cm into the hips in its first frame). Attachments (waistbands, straps) are bound afterwards, on
the dressed garment, and the animation then starts from rest.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .sewing import WELD_DISTANCE, widest_pair
from .topology import SpringKind, joined_roots
from .validation import LIMITS, InvalidValue, check_number


SEAM_CLOSED = WELD_DISTANCE  # [m]: a dressing goes on (up to twice its time) until every seam is closed this far
SEAM_FINISH = 3e-3  # [m]: sewn points within a stitch's length at the end are finished (their particles joined)
GROWTH_SPEED = 0.05  # [m/s]: a body shrunk under cloth placed inside it grows back this fast (or over the sewing's closing)
GROWTH_SHARE = 0.45  # a body shrinks at most this share of its inner thickness at a vertex (it must not turn inside out)
LAYER_CLEARANCE = 2.0  # [cloth thicknesses]: a held layer moved out of a dressed one's way clears it by this much
ZIP_REACH = 0.02  # [m]: a sewn point a settling leaves open by at most this much is zipped shut (_zip_seams)
ZIP_SPEED = 0.02  # [m/s]: ... its particles moved to their middle this fast
ZIP_HOLD = 0.1  # [s]: ... and held there this long while the cloth round them settles
LAYER_REACH = 0.15  # [m]: cloth farther than this from a held layer is not judged against it (nor moved further)


@dataclass(frozen=True)
class DressingReport:
    """How the dressing ended.

    Attributes:
        seconds: simulated dressing time [s]; steps: implicit steps taken.
        seam_gap: the largest distance between sewn points at the end [m] (0 without seams, and once all are finished).
        finished_from: the largest gap the finish closed [m] (0: none finished, or no seams).
        max_speed: the largest particle speed at the end [m/s] (the velocities are then zeroed).
        max_strain: the largest spring strain at the end (seams excluded).
        grown_from: how deep [m] cloth started inside a closed mesh collider (which then grew back under it; 0: none).
        inside: particles inside a closed mesh collider at the end (should be 0).
        layered_from: how deep [m] the dressed cloth started on the wrong side of a held layer (under one that goes over
            it, or over one that goes under it: that layer was then moved out of its way; 0: none).
        crossing: particles of the dressed cloth on the wrong side of a layer under it at the end (should be 0).
        self_crossings: (edge, triangle) pairs of the dressed cloth that cross at the end (:func:`self_crossings`;
            should be 0: self-collision keeps a tangle it is handed).
        open_seams: seam springs still longer than the run's weld distance at the end (they stay springs in the run).
        unfinished: sewn points closed within the finish's distance but left as they were, because moving their
            particles together would have moved cloth through cloth (:func:`finish_seams_clear`).
        zipped: sewn points a settling left open (beyond the weld distance, within ZIP_REACH) and closed by hand
            (:func:`_zip_seams`).
        body_crossings: edges of the dressed cloth through a triangle of the body, and the other way, at the end
            (:func:`body_crossings`; should be 0: the dressing's contacts hold particles, not edges, off the body; the
            run's also push out edges and triangles found inside it, from its first step).
        element_samples: whether the colliders pass kept the cloth's edges and triangles out of the body, as in the
            run (False: the dressing diverged with them and was run again with the particles' contacts alone).
    """

    seconds: float
    steps: int
    seam_gap: float
    max_speed: float
    max_strain: float
    finished_from: float = 0.0
    grown_from: float = 0.0
    inside: int = 0
    layered_from: float = 0.0
    crossing: int = 0
    self_crossings: int = 0
    open_seams: int = 0
    unfinished: int = 0
    zipped: int = 0
    body_crossings: int = 0
    element_samples: bool = True


def frozen_collider(collider, time: float = 0.0):
    """`collider` held still in its pose and shape at `time` [s]: no keyframes, no point cache."""
    position, rotation = collider.pose_at(time)
    changes = dict(keyframes=[], point_cache=None, point_cache_times=None, position=tuple(position), rotation=tuple(rotation))
    if collider.shape == "mesh":
        changes["vertices"] = np.asarray(collider.vertices_at(time), np.float64)
    return dataclasses.replace(collider, **changes)


def mesh_depths(collider, points: np.ndarray, time: float = 0.0, device=None) -> np.ndarray:
    """Signed distance [m] of world `points` to a mesh collider's surface in its pose and shape at `time` (negative
    inside; the union of its closed parts)."""
    import warp as wp

    from .kernels import collide as kc
    from .model import quat_to_matrix

    position, rotation = collider.pose_at(time)
    local = (np.asarray(points, np.float64) - np.asarray(position)) @ quat_to_matrix(rotation)
    mesh = _warp_mesh(collider.vertices_at(time), collider.triangles, device, winding=True)
    out = wp.zeros(len(local), dtype=float, device=mesh.device)
    wp.launch(kc.mesh_signed_distance, dim=len(local), inputs=[mesh.id, wp.array(local.astype(np.float32), dtype=wp.vec3, device=mesh.device),
                                                                 1.0e3], outputs=[out], device=mesh.device)
    return out.numpy().astype(np.float64)


def depth_inside(builder, particles=None, device=None) -> tuple[float, str]:
    """How deep [m] the builder's cloth (`particles`, a boolean mask; default all) lies inside its closed mesh colliders
    at t = 0, the deepest, and that collider's name (0 and "" when none is inside)."""
    x = builder.particle_positions if particles is None else builder.particle_positions[np.asarray(particles, bool)]
    deepest, name = 0.0, ""
    for c in builder.colliders:
        if _closed(c) and len(x):
            depth = -float(mesh_depths(c, x, device=device).min())
            if depth > deepest:
                deepest, name = depth, c.name
    return deepest, name


def _closed(collider) -> bool:
    """Whether a collider is a closed mesh (every edge in two triangles; a union of closed parts, as the mannequin, is):
    only such a body has an inside that cloth can start in (an open one is solid behind its triangles only near them)."""
    import trimesh

    return collider.shape == "mesh" and bool(trimesh.Trimesh(collider.vertices, collider.triangles, process=False).is_watertight)


def _warp_mesh(vertices, triangles, device, winding: bool = False):
    """A Warp mesh of `triangles`; `winding`: built for winding-number sign queries (without it Warp's
    mesh_query_point_sign_winding_number silently signs by three rays' nearest hits, which a point inside two overlapping
    parts of a body can fool: 49 of 2000 points in the mannequin's box, 15 % of those inside, up to 2.8 cm deep)."""
    import warp as wp

    return wp.Mesh(points=wp.array(np.asarray(vertices, np.float32), dtype=wp.vec3, device=device),
                   indices=wp.array(np.asarray(triangles, np.int32).reshape(-1), dtype=wp.int32, device=device),
                   support_winding_number=winding)


def growing_collider(collider, depth: float, seconds: float, device=None, start: float = 0.0):
    """A still mesh `collider` (:func:`frozen_collider`) that starts shrunk `depth` [m] (plus twice its thickness)
    inward along its vertex normals (at most :data:`GROWTH_SHARE` of its inner thickness at a vertex, so thin parts
    stay the right way out), stays so until `start` [s] and grows back to its shape at :data:`GROWTH_SPEED`, within
    `seconds`, as a point cache (the contacts then push cloth out with the surface's velocity)."""
    import trimesh
    import warp as wp

    from .kernels import collide as kc

    v = np.asarray(collider.vertices, np.float64)
    tris = np.asarray(collider.triangles, np.int64)
    body = trimesh.Trimesh(v, tris, process=False)
    normals = np.asarray(body.vertex_normals, np.float64)
    inner = np.full(len(v), 1.0e3)
    part = trimesh.graph.connected_component_labels(body.edges, node_count=len(v))
    for k in np.unique(part):  # each closed part's own thickness (overlapping parts would cut it short)
        own = np.flatnonzero(part == k)
        index = -np.ones(len(v), np.int64)
        index[own] = np.arange(len(own))
        faces = index[tris[part[tris[:, 0]] == k]]
        if len(faces) == 0:
            continue
        mesh = _warp_mesh(v[own], faces, device)
        out = wp.zeros(len(own), dtype=float, device=mesh.device)
        wp.launch(kc.mesh_inner_thickness, dim=len(own), inputs=[mesh.id, wp.array(v[own].astype(np.float32), dtype=wp.vec3, device=mesh.device),
                                                                   wp.array(normals[own].astype(np.float32), dtype=wp.vec3, device=mesh.device),
                                                                   1.0e3], outputs=[out], device=mesh.device)
        inner[own] = out.numpy()
    shrink = np.minimum(depth + 2.0 * collider.thickness, GROWTH_SHARE * inner)
    grow = min(max(seconds, 1e-3), float(shrink.max()) / GROWTH_SPEED)
    return dataclasses.replace(collider, point_cache=np.stack([v - shrink[:, None] * normals, v]),
                               point_cache_times=np.array([start, start + grow]))


def body_distance(colliders, points: np.ndarray, time: float = 0.0, device=None) -> np.ndarray:
    """Signed distance [m] of world `points` to the union of the closed mesh colliders (the body) in their shape at
    `time` [s]: negative inside, inf without any."""
    d = np.full(len(points), np.inf)
    for c in colliders:
        if _closed(c) and len(points):
            d = np.minimum(d, mesh_depths(c, points, time, device))
    return d


def outward_normals(x: np.ndarray, triangles: np.ndarray, colliders, device=None) -> np.ndarray:
    """Unit vertex normals of a cloth (positions `x` [m], its `triangles`) turned away from the body, a connected piece
    (a panel) at a time: the way most of its normals go up the gradient of the closed mesh colliders' signed distance
    (:func:`body_distance`), or without one away from the cloth's centroid. (A panel's winding says nothing of which side
    the body is on; vertex by vertex, the gradient points the wrong way where a hand is nearer than the hips.)"""
    import trimesh

    from .cache import vertex_normals

    n = vertex_normals(x, triangles).astype(np.float64)
    if any(_closed(c) for c in colliders):
        h = 5.0e-3  # [m]: central differences, the six probes of every vertex in one query
        steps = h * np.concatenate([np.eye(3), -np.eye(3)])
        d = body_distance(colliders, (x[None] + steps[:, None]).reshape(-1, 3), device=device).reshape(6, len(x))
        away = (d[:3] - d[3:]).T
    else:
        away = x - x.mean(axis=0)
    tris = np.asarray(triangles, np.int64)
    piece = trimesh.graph.connected_component_labels(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]]]), node_count=len(x))
    vote = np.bincount(piece, weights=np.sign(np.einsum("ij,ij->i", n, away)), minlength=piece.max() + 1)
    n[vote[piece] < 0.0] *= -1.0
    # a sewn point's particles (finished seams: one place) move as one: their pieces' normals averaged
    _, point = np.unique(np.round(x / 1.0e-6).astype(np.int64), axis=0, return_inverse=True)
    point = point.ravel()
    joined = np.stack([np.bincount(point, weights=n[:, k]) for k in range(3)], axis=1)[point]
    return joined / np.maximum(np.linalg.norm(joined, axis=1, keepdims=True), 1e-30)


def layer_offsets(points: np.ndarray, x: np.ndarray, triangles: np.ndarray, normals: np.ndarray, device=None) -> np.ndarray:
    """Signed distance [m] of `points` from a cloth's surface (positions `x`, `triangles`, `normals` from
    :func:`outward_normals`) along the outward normal of the triangle closest to each: negative under the cloth (on the
    body's side). NaN where that triangle is farther than :data:`LAYER_REACH` or the point lies beside the cloth rather
    than over or under it (beyond its border: its offset mostly along the surface)."""
    import warp as wp

    from .kernels import collide as kc

    points = np.asarray(points, np.float64)
    tris = np.asarray(triangles, np.int64)
    out = np.full(len(points), np.nan)
    if not len(points) or not len(tris):
        return out
    mesh = _warp_mesh(x, tris, device)
    face = wp.zeros(len(points), dtype=wp.int32, device=mesh.device)
    weights = wp.zeros(len(points), dtype=wp.vec3, device=mesh.device)
    wp.launch(kc.mesh_closest_points, dim=len(points), inputs=[mesh.id, wp.array(points.astype(np.float32), dtype=wp.vec3, device=mesh.device),
                                                              LAYER_REACH], outputs=[face, weights], device=mesh.device)
    face, weights = face.numpy(), weights.numpy().astype(np.float64)
    near = face >= 0
    corners = x[tris[face[near]]]
    q = np.einsum("pk,pkj->pj", weights[near], corners)
    fn = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    fn[np.einsum("ij,ij->i", fn, normals[tris[face[near]]].sum(axis=1)) < 0.0] *= -1.0  # the way the cloth's normals face
    d = points[near] - q
    s = np.einsum("ij,ij->i", d, fn)
    beside = np.linalg.norm(d - s[:, None] * fn, axis=1) > 0.5 * np.abs(s) + 1e-6
    out[np.flatnonzero(near)[~beside]] = s[~beside]
    return out


@dataclass
class _Layer:
    """A held cloth that the dressed one starts on the wrong side of: under it (`under`) or over it, `depth` [m] deep;
    its particles `indices`, positions `x` [m], `triangles` (local) and :func:`outward_normals`."""

    name: str
    under: bool
    depth: float
    indices: np.ndarray
    x: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray


def _misplaced_layers(trial, moving: np.ndarray, under, device) -> list[_Layer]:
    """The held cloths of `trial` that the dressed cloth (the `moving` particles) starts on the wrong side of: under a
    layer that goes over it, or over one that goes under it (`under`: names; None: those it mostly lies over)."""
    layers = []
    for ref, _, _ in trial.cloths:
        idx = ref.indices()
        if moving[idx].any():
            continue
        x = trial.particle_positions[idx].astype(np.float64)
        tris = np.asarray(ref.topology.triangles, np.int64)
        normals = outward_normals(x, tris, trial.colliders, device)
        offsets = layer_offsets(trial.particle_positions[moving], x, tris, normals, device)
        offsets = offsets[~np.isnan(offsets)]
        if not len(offsets):
            continue
        inner = ref.name in under if under is not None else float(np.median(offsets)) > 0.0
        depth = float(np.max(-offsets if inner else offsets))
        if depth > 0.0:
            layers.append(_Layer(ref.name, inner, depth, idx, x, tris, normals))
    return layers


def _layer_room(trial, layer: _Layer, device) -> np.ndarray:
    """How far [m] each particle of a layer under the dressed cloth may be pulled in: to 1.5 thicknesses from the body
    (`trial`'s colliders as they start; inf without a body)."""
    return np.clip(body_distance(trial.colliders, layer.x, device=device) - 1.5 * float(trial.cloth_thickness), 0.0, None)


def _clearance(trial) -> float:
    return LAYER_CLEARANCE * float(trial.cloth_thickness)


def _move_layers(trial, moving: np.ndarray, layers: list[_Layer], seconds: float, device, start: float = 0.0) -> float:
    """Move `layers` (:func:`_misplaced_layers`) out of the dressed cloth's way in `trial`: a layer under it is pulled
    in along its normals by the depth plus :data:`LAYER_CLEARANCE` thicknesses (as far as :func:`_layer_room` lets it),
    held there until `start` [s] and moved back out by one handle a particle within `seconds` [s] (at
    :data:`GROWTH_SPEED` if that is sooner): its pinned particles push the dressed cloth out as a growing body does. A
    layer over it (dressed later, from where the builder has it) is pushed out as far and left there. Returns the depth
    [m] (0: no layer)."""
    from .model import Keyframe

    names = [ref.name for ref, _, _ in trial.cloths if moving[ref.indices()].any()]
    for layer in layers:
        shift = np.full(len(layer.x), layer.depth + _clearance(trial))
        if layer.under:
            shift = np.minimum(shift, _layer_room(trial, layer, device))
        placed = layer.x + (-shift if layer.under else shift)[:, None] * layer.normals
        left = layer_offsets(trial.particle_positions[moving], placed, layer.triangles, layer.normals, device)
        left = left[~np.isnan(left)]
        if len(left) and float(np.max(-left if layer.under else left)) > 0.0:
            raise InvalidValue(f"dress: {', '.join(map(repr, names))} starts {100.0 * layer.depth:.1f} cm on the wrong side of "
                               f"{layer.name!r}, which goes {'under' if layer.under else 'over'} it, and {layer.name!r} cannot be "
                               f"moved that far out of its way: place the panels further {'out' if layer.under else 'in'}")
        trial.particle_positions[layer.indices] = placed
        if layer.under:
            grow = min(max(seconds, 1e-3), float(shift.max()) / GROWTH_SPEED)
            for p, d, n in zip(layer.indices, shift, layer.normals):
                if d > 0.0:
                    trial.add_handle([int(p)], [Keyframe(0.0), Keyframe(start), Keyframe(start + grow, tuple(float(c) for c in d * n))],
                                     name=f"layer{p}")
    return max((layer.depth for layer in layers), default=0.0)


def crossing_layers(builder, moving: np.ndarray, under, device=None) -> int:
    """How many of the `moving` particles lie under (on the body's side of) a cloth named in `under`."""
    count = 0
    for ref, _, _ in builder.cloths:
        if ref.name in under and not moving[ref.indices()].any():
            x = builder.particle_positions[ref.indices()].astype(np.float64)
            tris = np.asarray(ref.topology.triangles, np.int64)
            s = layer_offsets(builder.particle_positions[moving], x, tris, outward_normals(x, tris, builder.colliders, device), device)
            count += int(np.count_nonzero(s < 0.0))
    return count


def crossing_pairs(x: np.ndarray, triangles: np.ndarray, roots: np.ndarray, device=None) -> set[tuple[int, int, int]]:
    """The (edge's first particle, edge's second particle, triangle) triples of a cloth (positions `x` [m], its
    `triangles`) whose edge crosses the triangle, the triangle touching neither end of the edge, a particle touching
    the triangles of every particle that shares its `roots` entry (a sewn point's: :func:`~cloth_warp.topology.joined_roots`)
    (:func:`_edge_crossings`). Empty for cloth free of intersections."""
    tris = np.asarray(triangles, np.int64).reshape(-1, 3)
    if len(tris) == 0:
        return set()
    roots = np.asarray(roots, np.int32)
    edges, crossed = _edge_crossings(x, tris, roots, x, tris, roots, device)
    e, k = np.nonzero(crossed >= 0)
    return {(int(edges[i, 0]), int(edges[i, 1]), int(f)) for i, f in zip(e, crossed[e, k])}


def _edge_crossings(x, triangles, roots, edge_points, edge_triangles, edge_roots, device):
    """The edges of `edge_triangles` (at `edge_points`) and, per edge, the triangles of the mesh (`x`, `triangles`) it
    crosses, touching neither of its ends (`edge_roots` against the mesh's `roots`), -1 padded (kernels/collide.py
    `find_edge_crossings`): ((edges, 2), (edges, EDGE_CROSSING_HITS)) numpy arrays."""
    import warp as wp

    from .broadphase import unique_edges
    from .kernels import collide as kc

    edges = unique_edges(np.asarray(edge_triangles, np.int64))
    mesh = _warp_mesh(x, triangles, device)
    crossed = wp.empty((len(edges), int(kc.EDGE_CROSSING_HITS)), dtype=wp.int32, device=mesh.device)
    wp.launch(kc.find_edge_crossings, dim=len(edges),
              inputs=[mesh.id, wp.array(np.asarray(edge_points, np.float32), dtype=wp.vec3, device=mesh.device),
                      wp.array(edges.astype(np.int32), dtype=wp.vec2i, device=mesh.device), mesh.indices,
                      wp.array(roots, dtype=wp.int32, device=mesh.device), wp.array(edge_roots, dtype=wp.int32, device=mesh.device)],
              outputs=[crossed], device=mesh.device)
    return edges, crossed.numpy()


def self_crossings(builder, particles=None, device=None) -> int:
    """How many (edge, triangle) pairs of the builder's cloth (the triangles among `particles`, a boolean mask; default
    all) cross at its positions, a joined sewn point's particles counted as one vertex (a garment is one surface there;
    the two sides of a seam still open are two edges of the cloth): 0 for cloth free of intersections
    (:func:`crossing_pairs`)."""
    tris = np.asarray(builder.triangles, np.int64).reshape(-1, 3)
    if particles is not None:
        tris = tris[np.asarray(particles, bool)[tris].all(axis=1)]
    x = builder.particle_positions
    seams = builder.springs[builder.spring_kind == int(SpringKind.SEAM)]
    joined = seams[np.all(x[seams[:, 0]] == x[seams[:, 1]], axis=1)]  # (finished: moved onto one point)
    return len(crossing_pairs(x, tris, joined_roots(joined, len(x)), device))


def body_crossings(builder, particles=None, device=None) -> int:
    """How many times an edge of the builder's cloth (the triangles among `particles`, a boolean mask; default all)
    crosses a triangle of its closed mesh colliders (the body, in its pose and shape at t = 0), or an edge of those a
    cloth triangle: 0 where the garment and the body do not intersect. Contacts hold particles off a body, not edges:
    an edge longer than a crease of the body is wide can span it through the body (a T-shirt at 3.5 cm edges at the
    armpit) (:func:`_edge_crossings`, both ways)."""
    from .model import quat_to_matrix

    tris = np.asarray(builder.triangles, np.int64).reshape(-1, 3)
    if particles is not None:
        tris = tris[np.asarray(particles, bool)[tris].all(axis=1)]
    if not len(tris):
        return 0
    x = builder.particle_positions
    count = 0
    for c in builder.colliders:
        if not _closed(c):
            continue
        position, rotation = c.pose_at(0.0)
        body = np.asarray(c.vertices_at(0.0), np.float64) @ quat_to_matrix(rotation).T + np.asarray(position)
        body_tris = np.asarray(c.triangles, np.int64)
        cloth_roots = np.arange(len(x), dtype=np.int32)
        body_roots = np.arange(len(x), len(x) + len(body), dtype=np.int32)  # (no end of one touches the other)
        for mesh, edges_of in (((body, body_tris, body_roots), (x, tris, cloth_roots)),
                               ((x, tris, cloth_roots), (body, body_tris, body_roots))):
            count += int(np.count_nonzero(_edge_crossings(*mesh, *edges_of, device)[1] >= 0))
    return count


def seam_gap(builder, positions=None, particles=None) -> float:
    """The largest distance [m] between the two ends of the builder's seam springs (at `positions`, default its own;
    with `particles`, a boolean mask over the particles, only the seams of those)."""
    x = builder.particle_positions if positions is None else np.asarray(positions)
    seams = builder.springs[builder.spring_kind == int(SpringKind.SEAM)]
    if particles is not None:
        seams = seams[np.asarray(particles)[seams[:, 0]]]
    return widest_pair(x, seams)


def dress(builder, seconds: float = 1.0, *, closing: float = 0.6, fps: float = 60.0, substeps: int = 2, damping: float = 6.0,
          device=None, solver_options: dict | None = None, garments=None, under=None) -> DressingReport:
    """Sew the builder's garments onto its colliders: simulate `seconds` [s] without gravity, with mass-proportional
    `damping` [1/s], the colliders still in their pose at t = 0 and frictionless (a T-shirt's sleeve caps must slide over
    the shoulders: with friction its dressing diverged; handles held where they start), the seams closing
    steadily over the first `closing` fraction of the time (their rest lengths shrink to zero; a seam still open by
    more than :data:`SEAM_CLOSED` at the end gets up to as long again; every sewn point then within :data:`SEAM_FINISH`
    is finished exactly, its particles moved to their middle, and the run welds it: :mod:`~cloth_warp.sewing`),
    then write the positions back into `builder` with zero velocities. Call
    it before :meth:`ModelBuilder.attach` (attachments are bound on the dressed garment), then :func:`settle`.
    `solver_options`: keyword arguments of the implicit Euler solver (the scene's; its collider contacts are resolved
    after each step while dressing). `garments`: the names of
    the cloths to dress (default all); the others are held still where they are, as obstacles (a layered outfit is
    dressed a layer at a time from the inside out, each over the layers already dressed). `under`: the names of the
    held cloths that go under the dressed ones (default: those they mostly lie over); a held layer they start on the
    wrong side of is moved out of their way first (:func:`_move_layers`: one under them grows back under them)."""
    if builder.attachments:
        raise InvalidValue("dress: bind attachments after dressing (the builder already has some)")
    # Contacts after the step: held inside the solve, a seam's two particles touching the body on differently
    # inclined facets were measured to chatter 2-5 mm apart instead of closing.
    # (and their friction, which the sewing turns off anyway: in the solve it needs the contacts there)
    # Cloth-cloth contacts after the step too, whatever the run's: with them in the solve, the T-shirt's armpit corner,
    # where four panels meet, stayed 5.8 mm open, and a run's garment must not depend on how the run resolves contacts.
    options = {**(solver_options or {}), "collider_contacts": "pass", "contact_friction": "after", "self_contacts": "pass"}
    return _still_run(builder, seconds, closing, False, fps, substeps, damping, device, options, _cloth_particles(builder, garments),
                      under)


def finish_seams(x: np.ndarray, pairs: np.ndarray, within: float = SEAM_FINISH) -> tuple[np.ndarray, float]:
    """Finish every sewn point the dressing closed to within a stitch (:data:`SEAM_FINISH`): the particles of each group
    joined by seam `pairs` ((k, 2) particle indices) closer than that move to their middle, so that the run starts with
    them welded (:mod:`~cloth_warp.sewing`: a seam closed at the start stays closed). Pairs left wider stay apart (their
    seam springs pull on in the run): snapping wider gaps shut, 8 mm at a T-shirt's armpit, dragged cloth through cloth
    (:func:`finish_seams_clear` also leaves those whose finish would). Returns the positions (a copy) and the largest
    gap finished [m] (0: none)."""
    x = np.array(x, np.float64)
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    gaps = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
    closed = pairs[gaps < within]
    if not len(closed):
        return x, 0.0
    roots = joined_roots(closed, len(x))
    sewn_point = np.unique(closed)
    middle = np.zeros_like(x)
    np.add.at(middle, roots[sewn_point], x[sewn_point])
    middle /= np.maximum(np.bincount(roots[sewn_point], minlength=len(x)), 1)[:, None]
    x[sewn_point] = middle[roots[sewn_point]]
    return x, float(gaps[gaps < within].max())


def finish_seams_clear(x: np.ndarray, pairs: np.ndarray, triangles: np.ndarray, within: float = SEAM_FINISH,
                       device=None) -> tuple[np.ndarray, float, int]:
    """:func:`finish_seams`, less the sewn points whose finish would move cloth through cloth: a point's particles
    moved to their middle turn their triangles about it, and where cloth lies folded flat against them (a sleeve
    under an armpit, a fraction of a millimetre from the panel it is sewn to) that turn carried a triangle through a
    particle of the fold (the T-shirt at 2.6 and 3.0 cm edges: 0.3-1.0 mm moves, 4 and 5 edges through triangles that
    self-collision then kept for the whole run). An edge crossing a triangle after the finish that did not before
    (:func:`crossing_pairs`, every sewn point of `pairs` one vertex) leaves the points it moved as they were, until no
    new crossing is left; their seam springs, and in a run the sewing pass's weld under self-collision's CCD, close
    them. Returns the positions (a copy), the largest gap finished [m] (0: none) and how many sewn points were left
    open so."""
    x = np.asarray(x, np.float64)
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    tris = np.asarray(triangles, np.int64).reshape(-1, 3)
    roots = joined_roots(pairs, len(x))
    before = crossing_pairs(x, tris, roots, device)
    left = np.zeros(len(x), bool)
    while True:
        y, finished = finish_seams(x, pairs[~left[pairs[:, 0]]], within)
        new = crossing_pairs(y, tris, roots, device) - before
        ends = np.array([[a, b, *tris[f]] for a, b, f in new], np.int64).reshape(-1)
        moved = ends[np.any(y[ends] != x[ends], axis=1)]
        if not len(moved):
            return y, finished, len(np.unique(roots[left]))
        left |= np.isin(roots, roots[moved])


def _cloth_particles(builder, names) -> np.ndarray | None:
    """A boolean mask of the particles of the builder's cloths named in `names` (None for all)."""
    if names is None:
        return None
    known = {ref.name: ref for ref, _, _ in builder.cloths}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise InvalidValue(f"dress: no cloth named {unknown[0]!r}; cloths: {', '.join(known)}")
    mask = np.zeros(len(builder.particle_positions), bool)
    for n in names:
        mask[known[n].indices()] = True
    return mask


def settle(builder, seconds: float = 1.0, *, fps: float = 60.0, substeps: int = 2, damping: float = 3.0, device=None,
           solver_options: dict | None = None) -> DressingReport:
    """Let the dressed garments hang: simulate `seconds` [s] with gravity and mass-proportional `damping` [1/s], the
    colliders still in their pose at t = 0 and the attachments holding, then write the positions back into `builder`
    with zero velocities: the animation starts from a garment at rest instead of one falling from where it was sewn.
    A seam still open (a sewn point the dressing left beyond a stitch: its seam springs pull it in under gravity) keeps
    it going, up to half as long again, until every seam is within :data:`~cloth_warp.sewing.WELD_DISTANCE`; the
    points then within a stitch (:data:`SEAM_FINISH`) are joined, as the dressing's are, and the run welds them."""
    return _still_run(builder, seconds, 0.0, True, fps, substeps, damping, device, solver_options)


def _still_simulator(trial, fps, substeps, device, solver_options, samples: bool = True):
    """The model of a dressing's or settling's `trial` builder and an implicit Euler :class:`Simulator` of it with
    `solver_options` (strain limit 0.1 unless given), as the dressing was tuned; without `samples`, its colliders pass
    keeps the particles alone out of the body (no element samples)."""
    from .simulator import Simulator
    from .solvers import make_solver

    model = trial.finalize(device)
    options = dict(solver_options or {})
    options.setdefault("strain_limit", 0.1)
    solver = make_solver("implicit_euler", model, **options)
    if solver.strain_limiter is not None:
        # the limiter sweeps as if there were no colliders, as the dressing was tuned: panels start in and round a body
        # that grows back under them, the colliders pass pushes them out; held off the body's surfaces while they
        # slide together, the shipped T-shirt dressed into a fold at its shoulder seam that self-collision then pushed
        # at every frame of its walk (7-16 impulses a frame, none without)
        solver.strain_limiter.colliders = False
    collisions = solver.pass_named("self_collision")
    if collisions is not None:
        # the broad phase built at every step, as the dressing was tuned: the shipped T-shirt's armpit seams close to a
        # stitch at its 2.5 cm edges by round-off luck (docs/garments.md, the Known limits entry on sewing), which
        # other candidate orders lose
        collisions.self_collision.keep_broad_phase = False
    # (the colliders pass keeps the cloth's elements out of the body here as in the run: docs/garments.md, "The
    # dressing keeps the elements out of the body")
    colliders = solver.pass_named("colliders")
    if colliders is not None and not samples:
        colliders.samples_on = False
    return model, Simulator(model, solver, fps=fps, substeps=substeps)


def _zip_seams(builder, x: np.ndarray, pairs: np.ndarray, fps, substeps, damping, device,
               solver_options, samples: bool = True) -> tuple[np.ndarray, int]:
    """Close the sewn points that a settling leaves open beyond the weld distance, but by no more than
    :data:`ZIP_REACH`, by hand: each of their particles (of seam `pairs`, at positions `x` [m]) is moved by a handle to
    its point's middle at :data:`ZIP_SPEED`, and held there :data:`ZIP_HOLD`, while the cloth round it is simulated as
    the settling was (gravity, the attachments, the colliders still, self-collision: cloth is pushed aside, not
    crossed). A T-shirt at 3.2 cm edges kept a sleeve-hem pair 8 mm open against the panel compressed beside it, which
    its seam springs could not pull in. Returns the positions (the zipped points' particles at their middles) and how
    many points were zipped (`samples`: the colliders pass's element samples, as in :func:`_still_simulator`)."""
    from .model import Keyframe

    gaps = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
    roots = joined_roots(pairs, len(x))
    widest = np.zeros(len(x))  # per sewn point (at its root), its widest pair
    np.maximum.at(widest, roots[pairs[:, 0]], gaps)
    points = np.flatnonzero((widest > WELD_DISTANCE) & (widest <= ZIP_REACH))
    if not len(points):
        return x, 0
    members = np.unique(pairs[np.isin(roots[pairs[:, 0]], points)])
    middle = np.zeros_like(x)
    np.add.at(middle, roots[members], x[members])
    middle /= np.maximum(np.bincount(roots[members], minlength=len(x)), 1)[:, None]
    shift = middle[roots[members]] - x[members]
    seconds = max(float(np.linalg.norm(shift, axis=1).max()) / ZIP_SPEED, 1.0 / fps)
    trial = copy.deepcopy(builder)
    trial.particle_positions[:] = x
    trial.particle_velocities[:] = 0.0
    trial.global_damping = damping
    trial.colliders = [frozen_collider(c) for c in trial.colliders]
    trial.handles = []  # their particles stay pinned where they are
    for p, d in zip(members, shift):
        trial.add_handle([int(p)], [Keyframe(0.0), Keyframe(seconds, tuple(float(c) for c in d))], name=f"zip{p}")
    _, sim = _still_simulator(trial, fps, substeps, device, solver_options, samples)
    for _ in range(math.ceil((seconds + ZIP_HOLD) * fps)):
        sim.step_frame()
    y = np.asarray(sim.positions(), np.float64)
    y[members] = middle[roots[members]]
    return y, len(points)


def _still_run(builder, seconds, closing, gravity, fps, substeps, damping, device, solver_options, moving=None,
               under=None) -> DressingReport:
    """Simulate a copy of `builder` against its colliders held still at t = 0 and write the end positions back
    (`moving`: a mask of the particles that may move, the others pinned where they are, those of layers the moving ones
    start on the wrong side of moved out of their way (`under`, see :func:`dress`); default all). Where it diverges
    with the colliders pass's element samples, it is run again with the particles' contacts alone (the report's
    `element_samples` False); where that diverges too, the first divergence is raised: the T-shirt at 2.6 cm edges,
    caught at an armpit while its edges were pushed out of the body, tore there (strain 1.5 at 1.4 s) and dresses
    without them (docs/garments.md, "The dressing's element samples give way where they tear a garment")."""
    from .solvers import SimulationDiverged

    args = (builder, seconds, closing, gravity, fps, substeps, damping, device, solver_options, moving, under)
    try:
        return _still_pass(*args, samples=True)
    except SimulationDiverged as first:
        try:
            return _still_pass(*args, samples=False)
        except SimulationDiverged:
            raise first from None


def _still_pass(builder, seconds, closing, gravity, fps, substeps, damping, device, solver_options, moving, under,
                samples: bool) -> DressingReport:
    """One :func:`_still_run`, the colliders pass's element samples on or off (`samples`)."""
    seconds = check_number("dressing seconds", seconds, LIMITS["dressing_time"])
    damping = check_number("dressing damping", damping, LIMITS["global_damping"])
    if len(builder.particle_positions) == 0:
        raise InvalidValue("dress: the builder has no cloth")
    trial = copy.deepcopy(builder)
    if not gravity:
        trial.gravity = (0.0, 0.0, 0.0)
    trial.global_damping = damping
    trial.colliders = [frozen_collider(c) for c in trial.colliders]
    moving = np.ones(len(builder.particle_positions), bool) if moving is None else np.asarray(moving, bool)
    grown_from, layers, start = 0.0, [], 0.0
    if closing > 0.0:  # sewing: panels slide into place (a sleeve cap over the shoulder) without friction
        trial.colliders = [dataclasses.replace(c, static_friction=0.0, kinetic_friction=0.0) for c in trial.colliders]
        if trial.self_collision and not moving.all():  # held layers it starts on the wrong side of (moved aside below)
            layers = _misplaced_layers(trial, moving, under, device)
        # room the layers under it need beyond the body's: the body starts that much shrunk too
        room = max((float(np.max(layer.depth + _clearance(trial) - _layer_room(trial, layer, device)))
                    for layer in layers if layer.under), default=0.0)
        # With a layer pulled in under it, the layer and the body grow back once its seams are closed (or over the
        # run's last half closing, at the latest): growing back while the seams closed, the skirt's side seam at the
        # waist came out between an overskirt's two open corners there and held them 5 mm apart
        # (tests/test_dressing.py, layers placed into each other); the body waits too, not to push the dressed cloth
        # into the layer still pulled in.
        start = min(closing, 1.0 - 0.5 * closing) * seconds if any(layer.under for layer in layers) else 0.0
        for k, c in enumerate(trial.colliders):  # a closed body cloth starts inside grows back under it
            if _closed(c):
                depth = -float(mesh_depths(c, builder.particle_positions[moving], device=device).min(initial=0.0))
                if max(depth, room) > 0.0:
                    trial.colliders[k] = growing_collider(c, max(depth, room), 0.5 * closing * seconds, device, start)
                    grown_from = max(grown_from, depth)
    trial.handles = []  # their particles stay pinned where they start
    trial.particle_pinned[~moving] = 1
    layered_from = _move_layers(trial, moving, layers, 0.5 * closing * seconds, device, start)
    below = list(under) if under is not None else [layer.name for layer in layers if layer.under]
    model, sim = _still_simulator(trial, fps, substeps, device, solver_options, samples)
    frames = max(1, math.ceil(seconds * fps))
    # The seams close at a walking pace: their rest lengths shrink from the gaps they start at to zero over the first
    # `closing` of the run (a seam spring pulling a 20 cm gap shut in one step would tear the cloth beside it).
    seam = model.spring_kind.numpy() == int(SpringKind.SEAM)
    ends = model.spring_indices.numpy()[seam]
    rest = model.spring_rest_length.numpy()
    x0 = model.particle_q.numpy().astype(np.float64)
    gap0 = np.linalg.norm(x0[ends[:, 0]] - x0[ends[:, 1]], axis=1)
    floor = LIMITS["rest_length"].lo
    stats = None
    for k in range(frames):
        if closing > 0.0 and seam.any():
            rest[seam] = np.maximum(floor, gap0 * max(0.0, 1.0 - (k + 1) / (closing * frames)))
            model.spring_rest_length.assign(rest.astype(np.float32))
        stats = sim.step_frame()
    # a seam still open (cloth caught on the body while it closed): go on until it is closed, a dressing up to as long
    # again, a settling up to half as long again (under gravity, cloth caught in a crease is pulled through it: the
    # T-shirt's settle diverged at 0.6 s of 1.5), and end at the frame whose widest seam is the narrowest (the panels
    # meeting at an armpit can close and open again by millimetres from frame to frame: the T-shirt at 2.4 cm edges
    # had its corner's four particles within 1.75 mm of each other 8 frames before the dressing's last, 5.4 mm at it)
    extra = 0
    limit = frames if closing > 0.0 else frames // 2
    x = np.asarray(sim.positions(), np.float64)
    v = np.asarray(sim.state.particle_qd.numpy(), np.float64)
    narrowest = seam_gap(builder, x, moving) if seam.any() else 0.0
    gap, last = narrowest, True
    while seam.any() and extra < limit and gap >= SEAM_CLOSED:
        stats = sim.step_frame()
        extra += 1
        y = np.asarray(sim.positions(), np.float64)
        gap = seam_gap(builder, y, moving)
        last = gap <= narrowest
        if last:
            x, v, narrowest = y, np.asarray(sim.state.particle_qd.numpy(), np.float64), gap
    frames += extra
    free = (builder.particle_pinned == 0) & moving
    finished, unfinished, zipped = 0.0, 0, 0
    if seam.any():
        # the stitches are finished, so that the run starts with them one point and welds them: a settling's too (one
        # with the contacts in the solve left one 0.34 mm open, and a T-shirt's at 2.0 and 3.5 cm edges two each, 1.0 and
        # 1.7 mm, beyond the run's weld distance: springs for the whole run)
        free_pairs = ends[free[ends[:, 0]] & free[ends[:, 1]]]
        x, finished, unfinished = finish_seams_clear(x, free_pairs, builder.triangles, SEAM_FINISH, device)
        if closing == 0.0:  # the settling hands the run its start: what it leaves open is zipped shut
            x, zipped = _zip_seams(builder, x, free_pairs, fps, substeps, damping, device, solver_options, samples)
            if zipped:
                x, _, unfinished = finish_seams_clear(x, free_pairs, builder.triangles, SEAM_FINISH, device)
    builder.particle_positions[free] = x[free]
    builder.particle_velocities[:] = 0.0
    inside = sum(int(np.count_nonzero(mesh_depths(c, builder.particle_positions[moving], device=device) < 0.0))
                 for c in builder.colliders if _closed(c)) if closing > 0.0 else 0
    crossing = crossing_layers(builder, moving, below, device) if below else 0
    # (not the held layers moved aside; the solver's measure when the last frame is kept)
    strain = float(stats.max_strain) if moving.all() and last and not zipped else _max_strain(builder, x, moving)
    sewn = ends[moving[ends[:, 0]]]
    y = builder.particle_positions
    gaps = np.linalg.norm(y[sewn[:, 0]] - y[sewn[:, 1]], axis=1)
    return DressingReport(frames / fps, frames * substeps, float(gaps.max(initial=0.0)),
                          float(np.linalg.norm(v[moving], axis=1).max()), strain, finished, grown_from, inside, layered_from, crossing,
                          self_crossings(builder, moving, device), int(np.count_nonzero(gaps > WELD_DISTANCE)), unfinished,
                          zipped, body_crossings(builder, moving, device), samples)


def _max_strain(builder, x: np.ndarray, particles: np.ndarray) -> float:
    """The largest strain l / L - 1 of the builder's structural and shear springs between `particles` (a mask) at `x`
    (0 if none is stretched)."""
    kind = builder.spring_kind
    ends = builder.springs
    pick = (((kind == int(SpringKind.STRUCTURAL)) | (kind == int(SpringKind.SHEAR))) & particles[ends[:, 0]]
            & particles[ends[:, 1]])
    ends, rest = ends[pick], builder.spring_rest_length[pick]
    if not len(ends):
        return 0.0
    return max(0.0, float((np.linalg.norm(x[ends[:, 0]] - x[ends[:, 1]], axis=1) / rest - 1.0).max()))
