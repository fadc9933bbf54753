"""A parametric mannequin: a body built from the repository's own geometry (no downloaded or licensed body model),
posed by a small skeleton, animated by a walk cycle or an arm raise and written as a USD point cache, the body a
garment is simulated on (a deforming mesh collider: ``ModelBuilder.add_collider_mesh_file`` or a scene's mesh
collider with ``deforming = true``).

The body is a ball-jointed figure in metres, y up, facing +z, feet on y = 0: each segment (pelvis, abdomen, chest, shoulders,
neck, head, upper arms, forearms, hands, thighs, shins, feet) is a closed capsule or ellipsoid mesh proportioned from
the height (a standing adult's segment ratios), moved rigidly by its bone; segments overlap at the joints, whose
round ends keep the surface closed in every pose. Run as a script to write a cache::

    python -m cloth_warp.mannequin out/mannequin_walk.usdc --motion walk --seconds 2 --fps 60
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

import numpy as np

MOTIONS = ("still", "walk", "arm_raise")


@dataclass(frozen=True)
class Segment:
    """A body segment: its bone (parent joint -> joint), its shape and the joint it turns about."""

    name: str
    parent: str | None  # the segment whose frame this one hangs from
    joint: tuple  # the joint's rest position [fraction of the height], (x, y, z)
    tip: tuple  # the segment's far end at rest [fraction of the height]
    radius: tuple  # (across x, across z) radii [fraction of the height] of its capsule, or the ellipsoid's (x, y, z)
    kind: str = "capsule"


def _segments() -> list[Segment]:
    """The segments at rest (fractions of the height; standing adult proportions, arms in an A-pose)."""
    s = []
    s.append(Segment("pelvis", None, (0.0, 0.53, 0.0), (0.0, 0.47, 0.0), (0.105, 0.075)))
    s.append(Segment("abdomen", "pelvis", (0.0, 0.53, 0.0), (0.0, 0.62, 0.0), (0.095, 0.065)))
    s.append(Segment("chest", "abdomen", (0.0, 0.62, 0.0), (0.0, 0.76, 0.0), (0.105, 0.070)))
    s.append(Segment("neck", "chest", (0.0, 0.80, 0.0), (0.0, 0.86, 0.0), (0.032, 0.032)))
    s.append(Segment("head", "neck", (0.0, 0.86, 0.0), (0.0, 1.0, 0.0), (0.056, 0.07, 0.064), "ellipsoid"))
    for side, x in (("left", 1.0), ("right", -1.0)):
        # the shoulder's top, from the neck's base out to the arm (sloping down 11 degrees): a ridge a strap or a
        # seam rests on, not the chest's dome (whose slope a strap slides off, under the arm)
        s.append(Segment(f"{side}_shoulder", "chest", (x * 0.029, 0.823, 0.0), (x * 0.114, 0.806, 0.0), (0.022, 0.030)))
        # arms in an A-pose, 25 degrees out from the sides: room for a sleeve round the arm and a bodice under it
        s.append(Segment(f"{side}_upper_arm", "chest", (x * 0.125, 0.80, 0.0), (x * 0.198, 0.643, 0.0), (0.030, 0.030)))
        s.append(Segment(f"{side}_forearm", f"{side}_upper_arm", (x * 0.198, 0.643, 0.0), (x * 0.262, 0.506, 0.0), (0.024, 0.024)))
        s.append(Segment(f"{side}_hand", f"{side}_forearm", (x * 0.262, 0.506, 0.0), (x * 0.288, 0.451, 0.0), (0.022, 0.032, 0.011), "ellipsoid"))
        s.append(Segment(f"{side}_thigh", "pelvis", (x * 0.055, 0.49, 0.0), (x * 0.055, 0.28, 0.0), (0.048, 0.048)))
        s.append(Segment(f"{side}_shin", f"{side}_thigh", (x * 0.055, 0.28, 0.0), (x * 0.055, 0.045, 0.0), (0.034, 0.034)))
        s.append(Segment(f"{side}_foot", f"{side}_shin", (x * 0.055, 0.045, 0.0), (x * 0.055, 0.0, 0.07), (0.026, 0.022, 0.062), "ellipsoid"))
    return s


def _capsule(p0, p1, rx: float, rz: float, count: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed capsule mesh from p0 to p1 with an elliptical cross-section (rx across x, rz across z)."""
    import trimesh

    d = np.asarray(p1, float) - np.asarray(p0, float)
    length = float(np.linalg.norm(d))
    r = max(rx, rz)
    m = trimesh.creation.capsule(height=max(length, 1e-6), radius=r, count=[count, count])  # along z, centred
    v = np.asarray(m.vertices, float)
    v[:, 0] *= rx / r
    v[:, 1] *= rz / r  # the capsule's local y becomes the body's z (depth) below
    # local z (the bone) -> the bone direction; local x -> world x; local y -> world z
    axis = d / max(length, 1e-12)
    across = np.array([1.0, 0.0, 0.0]) - axis * axis[0]
    across = across / np.linalg.norm(across) if np.linalg.norm(across) > 1e-9 else np.array([0.0, 0.0, 1.0])
    depth = np.cross(axis, across)
    v = v[:, [0]] * across + v[:, [1]] * depth + v[:, [2]] * axis
    return v + 0.5 * (np.asarray(p0, float) + np.asarray(p1, float)), np.asarray(m.faces, np.int64)


def _ellipsoid(centre, radii, count: int) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.uv_sphere(radius=1.0, count=[count, count])
    return np.asarray(m.vertices, float) * np.asarray(radii, float) + np.asarray(centre, float), np.asarray(m.faces, np.int64)


class Mannequin:
    """The body at a given `height` [m]: its rest vertices, triangles, and per-vertex segment; :meth:`vertices_at`
    poses it for a motion at a time.

    Args:
        height: standing height [m].
        resolution: segments around each capsule / ellipsoid (the body has ~30 x resolution^2 triangles).
    """

    def __init__(self, height: float = 1.75, resolution: int = 16):
        from .validation import LIMITS, check_number

        self.height = float(check_number("height", height, LIMITS["stature"]))
        self.segments = _segments()
        self.index = {s.name: k for k, s in enumerate(self.segments)}
        verts, tris, owner = [], [], []
        offset = 0
        for k, s in enumerate(self.segments):
            j, tip = np.asarray(s.joint) * height, np.asarray(s.tip) * height
            if s.kind == "capsule":
                v, t = _capsule(j, tip, s.radius[0] * height, s.radius[1] * height, resolution)
            else:
                v, t = _ellipsoid(0.5 * (j + tip), np.asarray(s.radius) * height, resolution)
            verts.append(v)
            tris.append(t + offset)
            owner.append(np.full(len(v), k))
            offset += len(v)
        self.rest_vertices = np.concatenate(verts)
        """(n, 3) vertices at rest [m]."""
        self.triangles = np.concatenate(tris).astype(np.int32)
        """(t, 3) triangles (each segment closed and outward-facing)."""
        self.segment_of_vertex = np.concatenate(owner)
        """(n,) the segment moving each vertex."""

    # -- posing ------------------------------------------------------------------------------------------
    def joint_angles(self, motion: str, time: float) -> dict:
        """Per segment, its rotation about its joint (axis, degrees) for `motion` at `time` [s]."""
        if motion not in MOTIONS:
            raise ValueError(f"motion: {motion!r} is not allowed; allowed: {', '.join(MOTIONS)}")
        x = (1.0, 0.0, 0.0)
        z = (0.0, 0.0, 1.0)
        if motion == "still":
            return {}
        if motion == "walk":  # in place (a treadmill): a 1.1 s stride
            phase = 2.0 * math.pi * time / 1.1
            ramp = min(1.0, time / 0.4)  # from standing into the stride
            out = {}
            for side, shift in (("left", 0.0), ("right", math.pi)):
                swing = math.sin(phase + shift)  # > 0: this leg swings forward (a negative turn about x moves it to +z)
                out[f"{side}_thigh"] = (x, -ramp * 25.0 * swing)
                out[f"{side}_shin"] = (x, ramp * 35.0 * max(0.0, math.sin(phase + shift + 0.6)))  # the knee bends in the swing
                out[f"{side}_upper_arm"] = (x, ramp * 18.0 * swing)  # arms swing against the legs
                out[f"{side}_forearm"] = (x, -ramp * 12.0)
            # the torso (pelvis, abdomen, chest) moves as one: a turn of the chest against the pelvis would shear the
            # overlapping segments under a waistband bound to both (attachments bind to one triangle each)
            return out
        # arm_raise: both arms raised sideways to 75 degrees over 2 s (smooth), elbows straight
        s = min(1.0, max(0.0, time / 2.0))
        lift = 75.0 * (3 * s * s - 2 * s * s * s)
        return {"left_upper_arm": (z, lift), "right_upper_arm": (z, -lift)}

    def segment_transforms(self, motion: str, time: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per segment, (rotation 3x3, translation) mapping its rest points to posed world points [m]."""
        from .builder import quat_from_axis_angle
        from .model import quat_to_matrix

        angles = self.joint_angles(motion, time)
        bob = 0.0
        if motion == "walk":
            bob = 0.008 * self.height / 1.75 * math.cos(4.0 * math.pi * time / 1.1) * min(1.0, time / 0.4)
        out = []
        for s in self.segments:
            joint = np.asarray(s.joint) * self.height
            local = quat_to_matrix(quat_from_axis_angle(*angles[s.name])) if s.name in angles else np.eye(3)
            if s.parent is None:
                r, t = local, np.array([0.0, bob, 0.0]) + joint - local @ joint
            else:
                pr, pt = out[self.index[s.parent]]
                r = pr @ local
                t = pr @ joint + pt - r @ joint
            out.append((r, t))
        return out

    def vertices_at(self, motion: str, time: float) -> np.ndarray:
        """(n, 3) posed vertices [m] for `motion` at `time` [s]."""
        out = np.empty_like(self.rest_vertices)
        for k, (r, t) in enumerate(self.segment_transforms(motion, time)):
            sel = self.segment_of_vertex == k
            out[sel] = self.rest_vertices[sel] @ r.T + t
        return out

    def point_cache(self, motion: str, seconds: float, fps: float) -> tuple[np.ndarray, np.ndarray]:
        """(times [s] (f,), vertices [m] (f, n, 3)) sampled at `fps` over `seconds`."""
        times = np.arange(int(round(seconds * fps)) + 1) / fps
        return times, np.stack([self.vertices_at(motion, t) for t in times])

    def write_usd(self, path, motion: str = "walk", seconds: float = 2.0, fps: float = 60.0) -> None:
        """Write the body as a USD Mesh (/World/mannequin) with its points time-sampled at `fps` (time code = frame,
        starting at 0), metres, y up: a point cache a scene reads as a deforming mesh collider."""
        from pxr import Sdf, Usd, UsdGeom, Vt

        times, cache = self.point_cache(motion, seconds, fps)
        layer = Sdf.Layer.CreateNew(str(path))
        stage = Usd.Stage.Open(layer)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        stage.SetTimeCodesPerSecond(fps)
        stage.SetFramesPerSecond(fps)
        stage.SetStartTimeCode(0)
        stage.SetEndTimeCode(len(times) - 1)
        root = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(root.GetPrim())
        mesh = UsdGeom.Mesh.Define(stage, "/World/mannequin")
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(self.triangles), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(self.triangles.reshape(-1))))
        points = mesh.CreatePointsAttr()
        extent = mesh.CreateExtentAttr()
        points.Set(Vt.Vec3fArray.FromNumpy(self.rest_vertices.astype(np.float32)))
        for k, x in enumerate(cache):
            x32 = x.astype(np.float32)
            points.Set(Vt.Vec3fArray.FromNumpy(x32), k)
            extent.Set(Vt.Vec3fArray.FromNumpy(np.stack([x32.min(0), x32.max(0)])), k)
        mesh.GetPrim().SetCustomDataByKey("clothWarp:mannequin", {"height": self.height, "motion": motion})
        layer.Save()


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description="Write the parametric mannequin as a USD point cache.")
    p.add_argument("output", help="a .usdc / .usda path")
    p.add_argument("--motion", choices=MOTIONS, default="walk")
    p.add_argument("--seconds", type=float, default=2.0)
    p.add_argument("--fps", type=float, default=60.0)
    p.add_argument("--height", type=float, default=1.75)
    p.add_argument("--resolution", type=int, default=16)
    args = p.parse_args(argv)
    Mannequin(args.height, args.resolution).write_usd(args.output, args.motion, args.seconds, args.fps)


if __name__ == "__main__":
    main()
