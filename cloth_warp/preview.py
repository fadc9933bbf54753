"""Previews of a cache without a GPU or a display: a Warp ray caster (kernels/render.py), Pillow for PNG/GIF.

The camera frames the union of all frames' bounds from the front, a little to the side and above (in the
cache's up axis); a key light casts shadows on the cloth and on a checkered ground plane below it.
"""

from __future__ import annotations

import logging
import pathlib

import numpy as np
import warp as wp

from .cache import CacheError, CacheReader, usd_errors, vertex_normals
from .outputs import atomic_path
from .kernels import render as kr

log = logging.getLogger(__name__)

FRONT_COLOR = (0.80, 0.42, 0.26)
BACK_COLOR = (0.55, 0.62, 0.72)
COLLIDER_COLOR = (0.62, 0.64, 0.66)


class Camera:
    """A pinhole camera looking at `target` from `eye`; `up` is the world up direction."""

    def __init__(self, eye, target, up, fov_deg: float = 35.0):
        self.eye = np.asarray(eye, np.float64)
        self.forward = np.asarray(target, np.float64) - self.eye
        self.forward /= np.linalg.norm(self.forward)
        self.right = np.cross(self.forward, up)
        self.right /= np.linalg.norm(self.right)
        self.up = np.cross(self.right, self.forward)
        self.tan_half_fov = float(np.tan(np.radians(fov_deg) / 2.0))

    @classmethod
    def framing(cls, lower, upper, up_axis: str = "Y", fov_deg: float = 35.0) -> Camera:
        """A camera that sees the box [lower, upper] whole, from the front, right and above."""
        lower, upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
        center = 0.5 * (lower + upper)
        radius = max(0.5 * float(np.linalg.norm(upper - lower)), 1e-3)
        up, side, depth = _axes(up_axis)
        direction = 0.55 * side + 0.35 * up + 1.0 * depth
        direction /= np.linalg.norm(direction)
        distance = 1.1 * radius / np.sin(np.radians(fov_deg) / 2.0)
        return cls(center + distance * direction, center, up, fov_deg)


def _axes(up_axis: str):
    """(up, side, towards-the-viewer) unit vectors for a Y-up or Z-up scene."""
    if up_axis.upper() == "Z":
        return np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, -1.0, 0.0])
    return np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])


class Renderer:
    """Renders frames of one triangle mesh whose points change (BVH refit per frame)."""

    def __init__(self, points: np.ndarray, triangles: np.ndarray, *, size=(512, 512), up_axis: str = "Y",
                 bounds=None, device=None, collider_triangles=None, ground_height=None, colors=None):
        """`bounds` (lower, upper) [m] frames the camera, ground and checker size (default: `points`');
        `collider_triangles` (bool per triangle) are drawn grey; `ground_height` overrides the ground's level;
        `colors` (per triangle, linear RGB) the cloth's front (default :data:`FRONT_COLOR`)."""
        self.device = wp.get_device(device)
        self.width, self.height = int(size[0]), int(size[1])
        if self.width < 8 or self.height < 8:
            raise ValueError(f"image size must be at least 8 x 8 pixels, got {size}")
        self.triangles = np.ascontiguousarray(triangles, np.int32)
        self.points = wp.array(np.asarray(points, np.float32), dtype=wp.vec3, device=self.device)
        self.indices = wp.array(self.triangles.reshape(-1), dtype=wp.int32, device=self.device)
        self.normals = wp.zeros(len(points), dtype=wp.vec3, device=self.device)
        material = np.zeros(len(self.triangles), np.int32) if collider_triangles is None else np.asarray(collider_triangles, np.int32)
        self.tri_material = wp.array(material, dtype=wp.int32, device=self.device)
        front = np.tile(np.asarray(FRONT_COLOR, np.float32), (len(self.triangles), 1)) if colors is None else colors
        self.front_colors = wp.array(np.asarray(front, np.float32).reshape(-1, 3), dtype=wp.vec3, device=self.device)
        self.mesh = wp.Mesh(points=self.points, indices=self.indices)
        self.pixels = wp.zeros(self.width * self.height, dtype=wp.vec3, device=self.device)
        self.up, _, depth = _axes(up_axis)
        lo, hi = bounds if bounds is not None else (np.min(points, 0), np.max(points, 0))
        self.camera = Camera.framing(lo, hi, up_axis)
        radius = 0.5 * float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
        # The ground: at the scene's zero level, or just below the cloth's lowest point if that is lower.
        self.ground_height = min(0.0, float(np.dot(lo, self.up)) - 0.05 * radius) if ground_height is None else float(ground_height)
        light = 1.0 * self.up - 0.3 * _axes(up_axis)[1] + 0.35 * depth
        self.light_dir = light / np.linalg.norm(light)
        self.checker = float(10.0 ** np.round(np.log10(max(radius, 1e-3) / 4.0)))

    def render(self, points: np.ndarray | None = None) -> np.ndarray:
        """An (height, width, 3) uint8 sRGB image of the mesh at `points` (default: as constructed)."""
        if points is not None:
            self.points.assign(np.asarray(points, np.float32))
            self.mesh.refit()
        pts = self.points.numpy()
        self.normals.assign(vertex_normals(pts, self.triangles))
        c = self.camera
        wp.launch(kr.render_cloth, dim=self.width * self.height,
                  inputs=[self.mesh.id, self.indices, self.normals, wp.vec3(*c.eye), wp.vec3(*c.forward), wp.vec3(*c.right),
                          wp.vec3(*c.up), c.tan_half_fov, self.width, self.height, wp.vec3(*self.up),
                          wp.vec3(*self.light_dir), self.ground_height, self.checker, self.front_colors,
                          wp.vec3(*BACK_COLOR), self.tri_material, wp.vec3(*COLLIDER_COLOR)],
                  outputs=[self.pixels], device=self.device)
        rgb = np.clip(self.pixels.numpy().reshape(self.height, self.width, 3), 0.0, 1.0)
        return (255.0 * rgb ** (1.0 / 2.2) + 0.5).astype(np.uint8)


def _combined(reader: CacheReader, frame: int) -> np.ndarray:
    return np.concatenate([reader.points(frame, i) for i in range(len(reader.meshes))])


def render_cache(cache, output, *, frame: int | None = None, size=(512, 512), every: int = 1, device=None) -> pathlib.Path:
    """Render a cache to `output`: a ``.png`` still of `frame` (default: the last) or an animated ``.gif``.

    Returns the path written (atomically: temporary name, then rename).
    """
    from PIL import Image

    reader = CacheReader(cache)
    out = pathlib.Path(output)
    suffix = out.suffix.lower()
    if suffix not in (".png", ".gif"):
        raise ValueError(f"preview output must end in .png or .gif, got {out.name!r}")
    if not reader.meshes:  # the reader refuses such a file; kept for readers built otherwise
        raise CacheError(f"{cache}: holds no mesh to render")
    offsets = np.cumsum([0] + [len(m["points"]) for m in reader.meshes])
    triangles = np.concatenate([m["triangles"] + o for m, o in zip(reader.meshes, offsets)])
    # each cloth in its fabric's colour (the displayColor its cache binds), or the default where it has none
    colors = np.concatenate([np.tile(m.get("color") or FRONT_COLOR, (len(m["triangles"]), 1)) for m in reader.meshes])
    first, last = reader.start_frame, reader.end_frame
    if suffix == ".png":
        frames = [last if frame is None else int(frame)]
        if not first <= frames[0] <= last:
            raise ValueError(f"frame {frames[0]} is outside the cache's frames {first}..{last}")
    else:
        frames = list(range(first, last + 1, max(1, int(every))))
    clouds = [_combined(reader, f) for f in frames]
    allpts = np.concatenate(clouds)
    lo, hi = allpts.min(0), allpts.max(0)
    up = _axes(reader.up_axis)[0]
    try:
        with usd_errors(reader.path, "corrupt collider: "):
            ground, solid = _collider_geometry(reader, frames, lo, hi, up)
    except CacheError:
        raise
    except (TypeError, ValueError, IndexError, AttributeError) as exc:  # a collider prim without its size, radius ...
        raise CacheError(f"{reader.path}: a collider cannot be drawn: {exc}") from exc
    if solid:
        n_cloth = len(clouds[0])
        tris = [triangles] + [t + n_cloth + off for t, off in zip(solid["triangles"], solid["offsets"])]
        material = np.concatenate([np.zeros(len(triangles), np.int32), np.ones(sum(len(t) for t in solid["triangles"]), np.int32)])
        triangles = np.concatenate(tris)
        colors = np.concatenate([colors, np.tile(COLLIDER_COLOR, (len(triangles) - len(colors), 1))])
        clouds = [np.concatenate([c, v]) for c, v in zip(clouds, solid["points"])]
        allpts = np.concatenate([allpts, *solid["points"]])
        lo, hi = allpts.min(0), allpts.max(0)
    else:
        material = None
    renderer = Renderer(clouds[0], triangles, size=size, up_axis=reader.up_axis, bounds=(lo, hi), device=device,
                        collider_triangles=material, ground_height=ground, colors=colors)
    images = [Image.fromarray(renderer.render(c)) for c in clouds]
    with atomic_path(out) as tmp:
        if suffix == ".png":
            images[0].save(tmp, format="PNG")
        else:
            duration = max(20, int(round(1000.0 * max(1, int(every)) / reader.fps)))
            images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0)
    log.info("rendered %d frame(s) of %s to %s", len(images), cache, out)
    return out


def _collider_geometry(reader: CacheReader, frames, lo, hi, up):
    """The colliders of a cache as triangles per frame. A plane whose normal is the up axis becomes the
    checkered ground at its level; other planes become a square around the cloth. Returns
    (ground height or None, {"points": [per-frame vertices], "triangles": [...], "offsets": [...]} or {})."""
    from .cache import collider_surface

    ground = None
    meshes = []
    centre, radius = 0.5 * (lo + hi), max(0.5 * float(np.linalg.norm(hi - lo)), 0.05)
    for col in reader.colliders:
        prim = col["prim"]
        if col.get("shape") == "plane":
            v, _ = collider_surface(prim, frames[0])
            normal = np.cross(v[1] - v[0], v[2] - v[0])
            normal /= np.linalg.norm(normal)
            if abs(float(np.dot(normal, up))) > 0.999:
                ground = float(np.dot(v[0], up))
                continue
            a = np.cross(normal, up if abs(np.dot(normal, up)) < 0.9 else np.roll(up, 1))
            a /= np.linalg.norm(a)
            b = np.cross(normal, a)
            per = []
            for f in frames:
                v, _ = collider_surface(prim, f)
                c = centre - np.dot(centre - v[0], normal) * normal
                s = 1.5 * radius
                per.append(np.array([c - s * a - s * b, c + s * a - s * b, c + s * a + s * b, c - s * a + s * b]))
            meshes.append((per, np.array([[0, 1, 2], [0, 2, 3]], np.int32)))
        else:
            per = [collider_surface(prim, f) for f in frames]
            meshes.append(([p for p, _ in per], per[0][1]))
    if not meshes:
        return ground, {}
    counts = [len(m[0][0]) for m in meshes]
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int)
    points = [np.concatenate([m[0][k] for m in meshes]).astype(np.float32) for k in range(len(frames))]
    return ground, {"points": points, "triangles": [m[1] for m in meshes], "offsets": list(offsets)}
