"""Sewing patterns: GarmentCode's JSON pattern specification, read and meshed into panels ready to sew.

The format (GarmentCode and GarmentCodeData, ``*_specification.json``): ``pattern.panels`` maps a name to a panel
with 2D ``vertices``, a closed loop of ``edges`` (``endpoints`` [i, j], an optional ``curvature`` and ``label``), a
3D placement (``translation``, ``rotation`` as XYZ Euler angles in degrees, applied to the panel's plane z = 0) and a
``label``; ``pattern.stitches`` lists pairs of ``{"panel", "edge"}`` to sew together, a third entry
``"right_wrong"`` where GarmentCode marks one (its collars); ``properties.units_in_meter`` gives the length unit (100:
centimetres), ``properties.curvature_coords`` says how control points are given, and
``properties.normalize_panel_translation`` (in GarmentCode's templates) moves each panel's origin to its vertices' mean
as GarmentCode does. Curvature:

* ``quadratic`` / ``cubic``: Bezier control points relative to the edge, (u, v) -> start + u e + v perp(e), with e the
  edge vector and perp(e) = (-e_y, e_x) (the edge's left); with ``curvature_coords = "absolute"`` (GarmentCode's older
  templates) they are points of the panel's frame, in its units;
* ``circle``: [radius, large_arc, right]: an SVG arc from start to end (``right`` is SVG's sweep flag: the arc runs
  counter-clockwise in the panel's y-up frame).

:func:`mesh_pattern` meshes every panel with Shewchuk's Triangle (the ``triangle`` package: a constrained Delaunay
mesher with quality bounds, not worth writing by hand) at a target edge length: each edge's outline is sampled
uniformly in arc length with as many segments on both sides of a stitch, no point added on the outline, so each
stitched pair of edges has matching vertices, paired as GarmentCode's mesher pairs them: the start of one edge with
the end of the other (two panels' outlines run opposite ways along a seam), and start with start in a
``"right_wrong"`` stitch. Where a stitch's edges are placed is no guide: in GarmentCode's own hoody the ends of the
hood's back seam lie 39 cm from the torso edge's ends one way round and 41 cm the other (summed), the nearer the wrong one.
Texture coordinates are the panel's own 2D coordinates [m] (a woven panel's warp along its x axis).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field

import numpy as np

from .validation import InvalidValue

CURVATURE_SAMPLES = 256  # points per edge on which a curve's arc length is measured
CURVE_KINDS = ("quadratic", "cubic", "circle")  # GarmentCode's curvature types


class PatternError(InvalidValue):
    """A pattern specification that cannot be read; the message names the key path."""


@dataclass(frozen=True)
class PatternEdge:
    """One edge of a panel's outline, in the panel's 2D frame [m].

    Attributes:
        start, end: endpoints (2,).
        kind: "line", "quadratic", "cubic" or "circle".
        controls: Bezier control points (absolute, [m]) for "quadratic" (1) and "cubic" (2).
        radius, large_arc, sweep: a "circle" arc's radius [m] and SVG flags.
        label: GarmentCode's edge label ("" when none).
    """

    start: np.ndarray
    end: np.ndarray
    kind: str = "line"
    controls: tuple = ()
    radius: float = 0.0
    large_arc: bool = False
    sweep: bool = False
    label: str = ""

    def points(self, t: np.ndarray) -> np.ndarray:
        """Points (len(t), 2) at curve parameters t in [0, 1]."""
        t = np.asarray(t, np.float64)[:, None]
        p0, p1 = self.start, self.end
        if self.kind == "quadratic":
            (c,) = self.controls
            return (1 - t) ** 2 * p0 + 2 * (1 - t) * t * c + t**2 * p1
        if self.kind == "cubic":
            c1, c2 = self.controls
            return (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * c1 + 3 * (1 - t) * t**2 * c2 + t**3 * p1
        if self.kind == "circle":
            centre, a0, sweep = self.arc()
            a = a0 + t[:, 0] * sweep
            return centre + self.arc_radius() * np.stack([np.cos(a), np.sin(a)], axis=1)
        return (1 - t) * p0 + t * p1

    def arc_radius(self) -> float:
        """The arc's radius [m], at least half the chord (SVG scales a radius too small to reach)."""
        return max(self.radius, 0.5 * float(np.linalg.norm(self.end - self.start)))

    def arc(self) -> tuple[np.ndarray, float, float]:
        """(centre, start angle, signed sweep angle [rad]) of a "circle" edge: SVG's endpoint-to-centre conversion
        with equal radii and no rotation, in a y-up frame (sweep flag 1: counter-clockwise)."""
        p0, p1 = self.start, self.end
        r = self.arc_radius()
        half = 0.5 * (p0 - p1)
        d2 = float(half @ half)
        k = math.sqrt(max(r * r - d2, 0.0) / d2) if d2 > 0.0 else 0.0
        if self.large_arc == self.sweep:
            k = -k
        centre = 0.5 * (p0 + p1) + k * np.array([half[1], -half[0]])
        a0 = math.atan2(*(p0 - centre)[::-1])
        a1 = math.atan2(*(p1 - centre)[::-1])
        sweep = a1 - a0
        if self.sweep and sweep < 0.0:
            sweep += 2.0 * math.pi
        elif not self.sweep and sweep > 0.0:
            sweep -= 2.0 * math.pi
        return centre, a0, sweep

    def length(self) -> float:
        """Arc length [m]."""
        p = self.points(np.linspace(0.0, 1.0, CURVATURE_SAMPLES + 1))
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())

    def sample(self, segments: int) -> np.ndarray:
        """`segments` + 1 points from start to end, uniform in arc length."""
        t = np.linspace(0.0, 1.0, CURVATURE_SAMPLES + 1)
        p = self.points(t)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        target = np.linspace(0.0, s[-1], segments + 1)
        out = self.points(np.interp(target, s, t))
        out[0], out[-1] = self.start, self.end
        return out


@dataclass(frozen=True)
class Panel:
    """A pattern piece: its outline (a closed loop of edges) in its own 2D frame [m] and its 3D placement."""

    name: str
    edges: tuple[PatternEdge, ...]
    translation: np.ndarray  # [m]
    rotation: np.ndarray  # XYZ Euler angles [deg]
    label: str = ""

    def placement(self) -> np.ndarray:
        """The 3x3 rotation of the panel's plane: extrinsic rotations about x, then y, then z (R = Rz Ry Rx)."""
        ax, ay, az = np.radians(self.rotation)
        cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
        rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
        ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
        return rz @ ry @ rx

    def place(self, points2d: np.ndarray) -> np.ndarray:
        """3D positions [m] of points in the panel's 2D frame."""
        p = np.c_[np.asarray(points2d, np.float64), np.zeros(len(points2d))]
        return p @ self.placement().T + self.translation


@dataclass(frozen=True)
class Pattern:
    """A sewing pattern: panels by name, stitches as pairs of (panel name, edge index)."""

    panels: dict
    stitches: tuple
    units_in_meter: float = 100.0
    aligned: frozenset = frozenset()
    """indices of the stitches whose two edges run the same way (GarmentCode's "right_wrong"): start sewn to start"""


def _error(path: str, message: str) -> PatternError:
    return PatternError(f"{path}: {message}")


def _number(value, path: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _error(path, f"expected a finite number, got {value!r}")
    return float(value)


def _vector(value, size: int, path: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != size:
        raise _error(path, f"expected {size} numbers, got {value!r}")
    return np.array([_number(v, f"{path}[{k}]") for k, v in enumerate(value)])


def _edge(spec, vertices: np.ndarray, path: str, scale: float = 1.0, absolute: bool = False, origin=0.0) -> PatternEdge:
    """One edge of a panel (vertices already in metres; `scale`: the pattern's length unit in metres; `absolute`:
    control points are points of the panel's frame, in the pattern's unit, not relative to the edge, that frame's
    origin moved to `origin` [m] as the vertices were)."""
    if not isinstance(spec, dict):
        raise _error(path, "expected a table with 'endpoints'")
    ends = spec.get("endpoints")
    if (not isinstance(ends, (list, tuple)) or len(ends) != 2
            or not all(isinstance(i, int) and not isinstance(i, bool) and 0 <= i < len(vertices) for i in ends)):
        raise _error(f"{path}.endpoints", f"expected two vertex indices in [0, {len(vertices)}), got {ends!r}")
    p0, p1 = vertices[ends[0]], vertices[ends[1]]
    label = str(spec.get("label", ""))
    curvature = spec.get("curvature")
    if curvature is None:
        return PatternEdge(p0, p1, label=label)
    cpath = f"{path}.curvature"
    if isinstance(curvature, list):  # GarmentCode's older form: one relative quadratic control point
        curvature = {"type": "quadratic", "params": [curvature]}
    if not isinstance(curvature, dict):
        raise _error(cpath, f"expected a table with 'type' and 'params', got {curvature!r}")
    kind, params = curvature.get("type"), curvature.get("params")
    e = p1 - p0
    perp = np.array([-e[1], e[0]])
    if kind in ("quadratic", "cubic"):
        count = 1 if kind == "quadratic" else 2
        if not isinstance(params, list) or len(params) != count:
            raise _error(f"{cpath}.params", f"a {kind} edge needs {count} control point(s), got {params!r}")
        points = [_vector(c, 2, f"{cpath}.params[{k}]") for k, c in enumerate(params)]
        controls = tuple(c * scale - origin if absolute else p0 + c[0] * e + c[1] * perp for c in points)
        return PatternEdge(p0, p1, kind, controls=controls, label=label)
    if kind == "circle":
        if not isinstance(params, list) or len(params) != 3:
            raise _error(f"{cpath}.params", f"a circle edge needs [radius, large_arc, right], got {params!r}")
        radius = _number(params[0], f"{cpath}.params[0]")
        if radius <= 0.0:
            raise _error(f"{cpath}.params[0]", f"the radius must be > 0, got {radius}")
        flags = []
        for k in (1, 2):
            if params[k] not in (0, 1, True, False):
                raise _error(f"{cpath}.params[{k}]", f"expected 0 or 1, got {params[k]!r}")
            flags.append(bool(params[k]))
        return PatternEdge(p0, p1, "circle", radius=radius * scale, large_arc=flags[0], sweep=flags[1], label=label)
    raise _error(f"{cpath}.type", f"{kind!r} is not allowed; allowed: {', '.join(CURVE_KINDS)}")


def read_garmentcode(source) -> Pattern:
    """A :class:`Pattern` from a GarmentCode specification: a path to its JSON file, or the parsed dict. Lengths are
    converted to metres (``properties.units_in_meter``); bad input raises :class:`PatternError` naming the key."""
    if isinstance(source, (str, os.PathLike)):
        try:
            with open(source, encoding="utf-8") as f:
                spec = json.load(f)
        except OSError as exc:
            raise PatternError(f"{os.fspath(source)}: cannot read: {exc.strerror or exc}") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise PatternError(f"{os.fspath(source)}: not JSON: {exc}") from None
    else:
        spec = source
    if not isinstance(spec, dict) or not isinstance(spec.get("pattern"), dict):
        raise PatternError("pattern: a GarmentCode specification holds a 'pattern' table")
    props = spec.get("properties", {}) or {}
    unit = _number(props.get("units_in_meter", 100), "properties.units_in_meter")
    if unit <= 0.0:
        raise _error("properties.units_in_meter", f"must be > 0, got {unit}")
    coords = props.get("curvature_coords", "relative")
    if coords not in ("relative", "absolute"):
        raise _error("properties.curvature_coords", f"{coords!r} is not allowed; allowed: relative, absolute")
    scale = 1.0 / unit
    panels_spec = spec["pattern"].get("panels")
    if not isinstance(panels_spec, dict) or not panels_spec:
        raise PatternError("pattern.panels: expected a table of panels")
    panels = {}
    for name, p in panels_spec.items():
        path = f"pattern.panels.{name}"
        if not isinstance(p, dict):
            raise _error(path, "expected a table")
        raw = p.get("vertices")
        if not isinstance(raw, list) or len(raw) < 3:
            raise _error(f"{path}.vertices", "expected at least 3 points")
        vertices = np.array([_vector(v, 2, f"{path}.vertices[{k}]") for k, v in enumerate(raw)]) * scale
        # GarmentCode's "normalize_panel_translation": the panel's origin moved to its vertices' mean, and the
        # translation's x and y shifted by it (unrotated, as GarmentCode does)
        origin = vertices.mean(axis=0) if props.get("normalize_panel_translation") else np.zeros(2)
        vertices = vertices - origin
        edges_spec = p.get("edges")
        if not isinstance(edges_spec, list) or len(edges_spec) < 2:
            raise _error(f"{path}.edges", "expected a loop of at least 2 edges")
        edges = tuple(_edge(e, vertices, f"{path}.edges[{k}]", scale, coords == "absolute", origin) for k, e in enumerate(edges_spec))
        for k, (a, b) in enumerate(zip(edges, edges[1:] + edges[:1])):
            if not np.array_equal(a.end, b.start):
                raise _error(f"{path}.edges[{(k + 1) % len(edges)}]", "the edges do not form a loop: an edge must start where "
                             "the one before it ends")
        translation = _vector(p.get("translation", [0, 0, 0]), 3, f"{path}.translation") * scale + np.r_[origin, 0.0]
        panels[name] = Panel(name, edges, translation,
                             _vector(p.get("rotation", [0, 0, 0]), 3, f"{path}.rotation"), str(p.get("label", "")))
    stitches, aligned, sewn = [], set(), {}
    for k, st in enumerate(spec["pattern"].get("stitches", []) or []):
        path = f"pattern.stitches[{k}]"
        if not isinstance(st, list) or len(st) not in (2, 3):
            raise _error(path, "expected two {panel, edge} sides (and optionally \"right_wrong\")")
        if len(st) == 3:
            if st[2] != "right_wrong":
                raise _error(f"{path}[2]", f"{st[2]!r} is not allowed; allowed: right_wrong")
            aligned.add(k)
        sides = []
        for j, side in enumerate(st[:2]):
            spath = f"{path}[{j}]"
            if not isinstance(side, dict) or side.get("panel") not in panels:
                raise _error(f"{spath}.panel", f"{(side or {}).get('panel') if isinstance(side, dict) else side!r} is not a panel "
                             f"of the pattern; panels: {', '.join(panels)}")
            edge = side.get("edge")
            n = len(panels[side["panel"]].edges)
            if not isinstance(edge, int) or isinstance(edge, bool) or not 0 <= edge < n:
                raise _error(f"{spath}.edge", f"expected an edge index in [0, {n}), got {edge!r}")
            sides.append((side["panel"], edge))
        for j, side in enumerate(sides):
            if side in sewn:
                raise _error(f"{path}[{j}]", f"edge {side[1]} of {side[0]!r} is already sewn by stitch {sewn[side]} (an edge takes "
                             "one stitch, as in GarmentCode)")
            sewn[side] = k
        stitches.append(tuple(sides))
    return Pattern(panels, tuple(stitches), unit, frozenset(aligned))


def pattern_from_tables(panels: list, stitches: list = (), where: str = "cloth") -> Pattern:
    """A :class:`Pattern` from a scene's panel table, in metres: each panel a table with ``name``, ``vertices`` (its
    outline's corners in its own 2D frame; edge k runs from corner k to corner k + 1, the last one back to the first),
    ``translation`` and ``rotation`` (XYZ Euler angles [deg], as GarmentCode places a panel) and optional ``curves``
    (tables of ``edge``, ``type`` and ``params``: GarmentCode's curvature of that edge, control points relative to the
    edge); each stitch a table with ``panels`` (two names), ``edges`` (their two edge indices) and ``aligned`` (the two
    edges run the same way: GarmentCode's "right_wrong"). It is read as :func:`read_garmentcode` reads GarmentCode's
    specification; a bad value raises :class:`PatternError` naming the scene's key under `where`."""
    spec_panels, rename = {}, {}
    for i, table in enumerate(panels):
        path = f"{where}.panels[{i}]"
        name = table.get("name")
        if not isinstance(name, str) or not name:
            raise _error(f"{path}.name", "every panel needs a name")
        if name in spec_panels:
            raise _error(f"{path}.name", f"{name!r} is the name of another panel")
        corners = table.get("vertices")
        if not isinstance(corners, list) or len(corners) < 3:
            raise _error(f"{path}.vertices", f"expected at least 3 corners [x, y], got {corners!r}")
        n = len(corners)
        edges = [{"endpoints": [k, (k + 1) % n]} for k in range(n)]
        for j, curve in enumerate(table.get("curves", [])):
            edge = curve.get("edge")
            if not isinstance(edge, int) or isinstance(edge, bool) or not 0 <= edge < n:
                raise _error(f"{path}.curves[{j}].edge", f"expected an edge index in [0, {n}), got {edge!r}")
            if "curvature" in edges[edge]:
                raise _error(f"{path}.curves[{j}].edge", f"edge {edge} is curved twice")
            edges[edge]["curvature"] = {"type": curve.get("type"), "params": curve.get("params")}
            rename[f"pattern.panels.{name}.edges[{edge}].curvature"] = f"{path}.curves[{j}]"
        rename[f"pattern.panels.{name}"] = path
        spec_panels[name] = {"vertices": corners, "edges": edges, "translation": table.get("translation", [0.0, 0.0, 0.0]),
                             "rotation": table.get("rotation", [0.0, 0.0, 0.0])}
    spec_stitches = []
    for k, table in enumerate(stitches):
        path = f"{where}.stitches[{k}]"
        names, edges = table.get("panels"), table.get("edges")
        if not isinstance(names, list) or len(names) != 2:
            raise _error(f"{path}.panels", f"expected the two panels' names, got {names!r}")
        if not isinstance(edges, list) or len(edges) != 2:
            raise _error(f"{path}.edges", f"expected the two panels' edge indices, got {edges!r}")
        spec_stitches.append([{"panel": a, "edge": e} for a, e in zip(names, edges)] + (["right_wrong"] if table.get("aligned") else []))
        for j, key in ((0, "panel"), (1, "panel"), (0, "edge"), (1, "edge")):
            rename[f"pattern.stitches[{k}][{j}].{key}"] = f"{path}.{key}s[{j}]"
    try:
        return read_garmentcode({"pattern": {"panels": spec_panels, "stitches": spec_stitches},
                                 "properties": {"units_in_meter": 1.0, "curvature_coords": "relative"}})
    except PatternError as exc:
        message = str(exc)
        for old in sorted(rename, key=len, reverse=True):  # the most specific key first
            if message.startswith(old):
                message = rename[old] + message[len(old):]
                break
        raise PatternError(message) from None


@dataclass(frozen=True)
class Wrap:
    """Panels wrapped about an axis when placed (a garment arranged round the body parts it covers, as a designer
    puts panels on a body's arrangement cylinders), without stretching them: a panel placed parallel to the axis is
    bent onto the cylinder about it at the plane's own distance; a panel tilted to it, onto the cone whose apex is
    where the axis meets the plane and whose half-angle is the tilt (an A-line or flared panel: a cone's development).
    The panel's line nearest the axis stays where it is placed. `point`, `direction`: the axis [m]."""

    panels: tuple
    point: tuple
    direction: tuple = (0.0, 1.0, 0.0)


def wrap_points(points: np.ndarray, normal, point, direction) -> np.ndarray:
    """`points` [m] of a plane with unit `normal`, bent about the axis (`point`, `direction`) without stretching.

    Parallel to the axis, at distance R: a point at in-plane distance s from the plane's line nearest the axis goes
    to angle s / R round the axis at the same height. Tilted by alpha: the axis meets the plane at the apex; a point
    at distance rho from the apex and angle psi from the plane's steepest line through it goes to the cone of
    half-angle alpha, at distance rho from the apex along the generator at angle psi / sin(alpha) round the axis."""
    x = np.asarray(points, np.float64)
    a = np.asarray(direction, np.float64)
    a = a / np.linalg.norm(a)
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    c = np.asarray(point, np.float64)
    tilt = float(n @ a)
    if abs(tilt) < 1e-9:  # a cylinder
        depth = float((x[0] - c) @ n)  # signed distance of the plane from the axis
        if abs(depth) < 1e-9:
            raise InvalidValue("wrap: the panel's plane passes through the wrap axis (place it at a distance from the axis)")
        out = n if depth > 0.0 else -n  # from the axis to the plane
        side = np.cross(a, out)
        rel = x - c
        theta = (rel @ side) / abs(depth)
        return c + np.outer(rel @ a, a) + abs(depth) * (np.outer(np.cos(theta), out) + np.outer(np.sin(theta), side))
    apex = c + a * float((x[0] - c) @ n) / tilt  # where the axis meets the plane
    rel = x - apex
    if float(np.mean(rel @ a)) < 0.0:
        a = -a  # the cone opens towards the panel
    generator = a - (a @ n) * n
    generator /= np.linalg.norm(generator)
    sin_alpha = math.sqrt(max(0.0, 1.0 - float(generator @ a) ** 2))
    cos_alpha = float(generator @ a)
    out = generator - cos_alpha * a
    out /= np.linalg.norm(out)
    side = np.cross(a, out)  # also the plane's direction across its steepest line (n lies in the span of a and out)
    rho = np.linalg.norm(rel, axis=1)
    theta = np.arctan2(rel @ side, rel @ generator) / sin_alpha
    ring = np.outer(np.cos(theta), out) + np.outer(np.sin(theta), side)
    return apex + rho[:, None] * (cos_alpha * a + sin_alpha * ring)


@dataclass
class PatternMesh:
    """A pattern meshed panel by panel, placed in 3D, with its seams.

    Attributes:
        vertices: (n, 3) placed positions [m]; uvs: (n, 2) the panels' own 2D coordinates [m].
        triangles: (t, 3) vertex indices (each panel's outline counter-clockwise in its frame).
        panel: (n,) the panel index of each vertex; panel_names: the panels in that order.
        seams: (s, 2) vertex pairs to sew, one pair per matching point of each stitch (a pair per stitch end too).
        outline: per panel, its outline's vertex indices in order (the loop of its edges' samples).
        edge_vertices: (panel name, edge index) -> that edge's vertex indices from its start to its end.
        edge_labels: (panel name, edge index) -> the edge's GarmentCode label ("" when none).
    """

    vertices: np.ndarray
    uvs: np.ndarray
    triangles: np.ndarray
    panel: np.ndarray
    panel_names: list
    seams: np.ndarray
    outline: list = field(default_factory=list)
    edge_vertices: dict = field(default_factory=dict)
    edge_labels: dict = field(default_factory=dict)


def edge_segments(pattern: Pattern, edge_length: float) -> dict:
    """(panel, edge) -> segments: ceil(length / edge_length), at least 1; both sides of a stitch get the larger."""
    counts = {(name, k): max(1, math.ceil(e.length() / edge_length)) for name, p in pattern.panels.items() for k, e in enumerate(p.edges)}
    for a, b in pattern.stitches:
        counts[a] = counts[b] = max(counts[a], counts[b])
    return counts


OVERLAP_DISTANCE = 0.5  # [edge lengths]: two panels with inner points this close along their surfaces ...
OVERLAP_GAP = 0.1  # [edge lengths]: ... and this close across them are placed into each other (a layer laid over
# another panel, a pocket or a collar, keeps a gap of the cloth's thickness, a few millimetres, and is not refused)


def _check_apart(x: np.ndarray, triangles: np.ndarray, panel: np.ndarray, names: list, edge_length: float, outline: list):
    """Refuse panels placed into each other: an inner point of one (off its outline) within :data:`OVERLAP_DISTANCE`
    edge lengths of another's and within :data:`OVERLAP_GAP` of that one's tangent plane (panels side by side, even
    touching, keep their inner points a mesh row apart; panels laid over each other keep a gap). The sewing cannot
    pull such panels apart, and self-collision, which keeps cloth from passing through itself, cannot undo a start that
    already has (a skirt wrapped too close round its axis, its hems overlapping, ended its run 101 % stretched with
    its seams 7 cm open)."""
    inner = np.ones(len(x), bool)
    inner[np.concatenate(outline)] = False
    idx = np.flatnonzero(inner)
    if len(idx) < 2:
        return
    from .cache import vertex_normals

    normal = vertex_normals(x, triangles).astype(np.float64)
    reach = OVERLAP_DISTANCE * edge_length
    cell = np.floor((x[idx] - x[idx].min(0)) / reach).astype(np.int64) + 1

    def key(c):
        return (c[:, 0] * 2_097_152 + c[:, 1]) * 2_097_152 + c[:, 2]

    order = np.argsort(key(cell), kind="stable")
    sorted_keys = key(cell)[order]
    for offset in np.stack(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij"), -1).reshape(-1, 3):
        wanted = key(cell + offset)
        lo, hi = np.searchsorted(sorted_keys, wanted, "left"), np.searchsorted(sorted_keys, wanted, "right")
        count = hi - lo
        a = np.repeat(np.arange(len(idx)), count)
        b = order[np.repeat(lo, count) + np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)]
        i, j = idx[a], idx[b]
        d = x[i] - x[j]
        close = np.flatnonzero((panel[i] != panel[j]) & (np.linalg.norm(d, axis=1) < reach)
                               & (np.abs(np.einsum("ij,ij->i", d, normal[j])) < OVERLAP_GAP * edge_length))
        if len(close):
            i, j = i[close[0]], j[close[0]]
            where = ", ".join(f"{c:.3f}" for c in x[i])
            raise PatternError(f"pattern.panels: {names[panel[i]]!r} and {names[panel[j]]!r} are placed into each other (at "
                               f"[{where}] m): move them apart, or wrap them round the body further out")


def mesh_pattern(pattern: Pattern, edge_length: float, min_angle: float = 25.0, wraps=()) -> PatternMesh:
    """Mesh every panel (Triangle: constrained Delaunay with quality, triangles of area at most that of an
    equilateral one of side `edge_length` [m], smallest angle `min_angle` [deg] away from the outline, no point added
    on the outline), place it in 3D (wrapped about an axis when one of `wraps` (:class:`Wrap`) names it) and pair the
    vertices of stitched edges (one edge's start with the other's end; start with start where the stitch is aligned)."""
    import triangle

    if not (math.isfinite(edge_length) and edge_length > 0.0):
        raise InvalidValue(f"edge_length: must be a length > 0 m, got {edge_length!r}")
    wrap_of = {}
    for k, w in enumerate(wraps):
        for name in w.panels:
            if name not in pattern.panels:
                raise InvalidValue(f"wraps[{k}].panels: {name!r} is not a panel of the pattern; panels: {', '.join(pattern.panels)}")
            if name in wrap_of:
                raise InvalidValue(f"wraps[{k}].panels: {name!r} is wrapped twice")
            wrap_of[name] = w
    segments = edge_segments(pattern, edge_length)
    area = math.sqrt(3.0) / 4.0 * edge_length**2
    vertices, uvs, tris, panel_of, outline, edge_vertices, edge_labels = [], [], [], [], [], {}, {}
    offset = 0
    names = list(pattern.panels)
    for index, name in enumerate(names):
        panel = pattern.panels[name]
        loop, spans = [], []
        for k, e in enumerate(panel.edges):
            pts = e.sample(segments[(name, k)])
            spans.append((len(loop), len(pts) - 1))
            loop.extend(pts[:-1])
        loop = np.asarray(loop)
        n = len(loop)
        signed = 0.5 * float(np.sum(loop[:, 0] * np.roll(loop[:, 1], -1) - np.roll(loop[:, 0], -1) * loop[:, 1]))
        ring = np.c_[np.arange(n), (np.arange(n) + 1) % n]
        # the area in fixed point: Triangle's switch parser stops at an exponent ("a9.7e-05" read as 9.7 m^2), which
        # left panels meshed at edges under 1.55 cm with their outline's points alone
        out = triangle.triangulate({"vertices": loop, "segments": ring}, f"pq{min_angle:g}a{area:.15f}YQ")
        pts2d = np.asarray(out["vertices"], np.float64)
        if len(pts2d) < n or not np.allclose(pts2d[:n], loop):
            raise PatternError(f"pattern.panels.{name}: the mesher moved the outline (self-intersecting outline?)")
        t = np.asarray(out["triangles"], np.int64)
        if signed < 0.0:  # the outline runs clockwise in the panel's frame: keep its triangles' winding consistent
            t = t[:, [0, 2, 1]]
        placed = panel.place(pts2d)
        if name in wrap_of:
            w = wrap_of[name]
            placed = wrap_points(placed, panel.placement()[:, 2], w.point, w.direction)
        vertices.append(placed)
        uvs.append(pts2d)
        tris.append(t + offset)
        panel_of.append(np.full(len(pts2d), index))
        outline.append(np.arange(n) + offset)
        for k, (start, count) in enumerate(spans):
            edge_vertices[(name, k)] = (np.arange(start, start + count + 1) % n) + offset
            edge_labels[(name, k)] = panel.edges[k].label
        offset += len(pts2d)
    x = np.concatenate(vertices)
    seams = []
    for k, (a, b) in enumerate(pattern.stitches):
        va, vb = edge_vertices[a], edge_vertices[b]
        seams.append(np.c_[va, vb if k in pattern.aligned else vb[::-1]])
    triangles = np.concatenate(tris).astype(np.int32)
    _check_apart(x, triangles, np.concatenate(panel_of), names, edge_length, outline)
    return PatternMesh(x, np.concatenate(uvs), triangles, np.concatenate(panel_of), names,
                       np.concatenate(seams).astype(np.int32) if seams else np.zeros((0, 2), np.int32), outline, edge_vertices,
                       edge_labels)
