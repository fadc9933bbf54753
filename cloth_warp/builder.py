"""ModelBuilder: cloths from grids or triangle meshes, raw particles and springs, pins, handles, colliders."""

from __future__ import annotations

import logging
import math
import os
import warnings
from dataclasses import dataclass, replace

import numpy as np
import warp as wp

from . import topology as topo
from .colliders import Collider, rotation_to_axis
from .elasticity import TWISTS, membrane_element_stiffness, membrane_tensor, plate_tensor
from .materials import FabricMaterial, preset
from .model import Attachment, ClothInfo, Handle, Keyframe, Model
from .outputs import USD_SUFFIXES, usd_error_text
from .plate import plate_stencils
from .topology import BendingModel, ClothTopology, MembraneModel, MeshError, SpringKind, SpringLaw, SpringModel
from .validation import (
    LIMITS,
    check_direction,
    check_float32,
    check_float32_resolution,
    check_keyframes,
    check_number,
    check_points,
    check_rotation,
    check_vector,
)

log = logging.getLogger(__name__)

UP_AXES = {"Y": (0.0, -9.81, 0.0), "Z": (0.0, 0.0, -9.81)}


@dataclass
class ClothRef:
    """A cloth added to a builder: its particle range and named selections.

    Selections return global particle indices. Grid names: "corners", "corner:<bottom|top>_<left|right>",
    "edge:<bottom|top|left|right>" (bottom is grid row 0, left is column 0, in the grid's own frame). A garment's
    (:meth:`ModelBuilder.add_cloth_pattern`): "edge:<label>" (every pattern edge with that GarmentCode label, e.g. a
    waistband's "waist"), "edge:<panel>:<index>" (one edge of a panel, counted from 0 in its edges' order) and
    "panel:<panel>" (a whole panel).
    """

    builder: ModelBuilder
    name: str
    particle_start: int
    topology: ClothTopology
    pattern_mesh: object = None  # a garment's PatternMesh (cloth_warp.patterns), None for other cloths
    seams: np.ndarray | None = None  # a garment's seam springs' particle pairs (s, 2), None for other cloths

    @property
    def particle_count(self) -> int:
        return self.topology.particle_count

    def indices(self, local=None) -> np.ndarray:
        """Global indices of local particle ids (all particles when None)."""
        if local is None:
            return np.arange(self.particle_count) + self.particle_start
        local = np.asarray(local, np.int64).ravel()
        if local.size and (local.min() < 0 or local.max() >= self.particle_count):
            raise IndexError(f"cloth {self.name!r}: particle index out of range [0, {self.particle_count})")
        return local + self.particle_start

    def select(self, name: str) -> np.ndarray:
        """Global indices of a named selection (see class docstring)."""
        shape = self.topology.grid_shape
        if shape is None and self.pattern_mesh is not None:
            return self._select_pattern(name, self.pattern_mesh)
        if shape is None:
            raise ValueError(f"cloth {self.name!r} is a mesh: named selections {name!r} need a grid or a pattern; use select_box or a vertex mask")
        nx, ny = shape

        def vid(i, j):
            return j * (nx + 1) + i

        corners = {
            "bottom_left": vid(0, 0),
            "bottom_right": vid(nx, 0),
            "top_left": vid(0, ny),
            "top_right": vid(nx, ny),
        }
        edges = {
            "bottom": [vid(i, 0) for i in range(nx + 1)],
            "top": [vid(i, ny) for i in range(nx + 1)],
            "left": [vid(0, j) for j in range(ny + 1)],
            "right": [vid(nx, j) for j in range(ny + 1)],
        }
        if name == "corners":
            return self.indices(list(corners.values()))
        kind, _, which = name.partition(":")
        if kind == "corner" and which in corners:
            return self.indices([corners[which]])
        if kind == "edge" and which in edges:
            return self.indices(edges[which])
        allowed = ["corners"] + [f"corner:{c}" for c in corners] + [f"edge:{e}" for e in edges]
        raise ValueError(f"unknown selection {name!r}; allowed: {', '.join(allowed)}")

    def _select_pattern(self, name: str, mesh) -> np.ndarray:
        """A garment's named selection (see the class docstring): its pattern mesh's vertices, as particles."""
        kind, _, which = name.partition(":")
        labels = sorted({label for label in mesh.edge_labels.values() if label})
        vertices = None
        if kind == "panel" and which in mesh.panel_names:
            vertices = np.flatnonzero(mesh.panel == mesh.panel_names.index(which))
        elif kind == "edge" and which in labels:
            vertices = np.concatenate([mesh.edge_vertices[key] for key, label in mesh.edge_labels.items() if label == which])
        elif kind == "edge":
            panel, _, index = which.rpartition(":")
            if index.isdigit() and (panel, int(index)) in mesh.edge_vertices:
                vertices = mesh.edge_vertices[(panel, int(index))]
        if vertices is None:
            allowed = [f"edge:{label}" for label in labels] + [f"panel:{p}" for p in mesh.panel_names] + ["edge:<panel>:<index>"]
            raise ValueError(f"unknown selection {name!r} on garment {self.name!r}; allowed: {', '.join(allowed)}")
        r2p = self.topology.render_to_particle
        return self.indices(np.unique(vertices if r2p is None else r2p[vertices]))

    def select_box(self, lower, upper) -> np.ndarray:
        """Global indices of particles whose initial world position lies inside an axis-aligned box [m]."""
        lower, upper = check_vector("lower", lower, LIMITS["position"]), check_vector("upper", upper, LIMITS["position"])
        p = self.builder.particle_positions[self.particle_start : self.particle_start + self.particle_count]
        inside = np.all((p >= np.asarray(lower)) & (p <= np.asarray(upper)), axis=1)
        return self.indices(np.flatnonzero(inside))

    def select_mask(self, mask) -> np.ndarray:
        """Global indices where a per-vertex attribute (of the original, unwelded mesh) is > 0.5."""
        m = np.asarray(mask, float).ravel()
        r2p = self.topology.render_to_particle
        if r2p is not None and len(m) == len(r2p):
            local = np.unique(r2p[m > 0.5])
        elif len(m) == self.particle_count:
            local = np.flatnonzero(m > 0.5)
        else:
            raise ValueError(f"cloth {self.name!r}: vertex mask has {len(m)} entries, expected {self.particle_count} (particles) or {0 if r2p is None else len(r2p)} (mesh vertices)")
        return self.indices(local)


def rotation_matrix(rotation, name: str = "rotation") -> np.ndarray:
    """3x3 rotation from None, a unit quaternion (x, y, z, w), or a proper rotation matrix (checked:
    :func:`cloth_warp.validation.check_rotation`)."""
    return check_rotation(name, rotation)


def quat_from_axis_angle(axis, angle_deg: float) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) for a rotation of `angle_deg` degrees about `axis` (any non-zero length)."""
    a = check_direction("axis", axis)
    h = math.radians(check_number("angle_deg", angle_deg, LIMITS["angle"])) / 2.0
    s = math.sin(h)
    return (a[0] * s, a[1] * s, a[2] * s, math.cos(h))


class ModelBuilder:
    """Collects cloths, particles, springs, pins and handles, then builds a :class:`Model`.

    Args:
        up_axis: "Y" (default) or "Z"; sets gravity to -9.81 m/s^2 along it unless `gravity` is given.
        gravity: gravity vector [m/s^2].
        global_damping: mass-proportional damping rate [1/s] (f = -rate m v).
    """

    def __init__(self, *, up_axis: str = "Y", gravity=None, global_damping: float = 0.0):
        if up_axis not in UP_AXES:
            raise ValueError(f"up_axis must be one of {sorted(UP_AXES)}, got {up_axis!r}")
        self.up_axis = up_axis
        self.gravity = check_vector("gravity", gravity if gravity is not None else UP_AXES[up_axis], LIMITS["gravity"])
        self.global_damping = check_number("global_damping", global_damping, LIMITS["global_damping"])
        self.particle_positions = np.zeros((0, 3))
        self.particle_velocities = np.zeros((0, 3))
        self.particle_mass = np.zeros(0)
        self.particle_pinned = np.zeros(0, np.int32)
        self.particle_pin_stiffness = np.zeros(0)
        self.springs = np.zeros((0, 2), np.int64)
        self.spring_rest_length = np.zeros(0)
        self.spring_stiffness = np.zeros(0)
        self.spring_damping = np.zeros(0)
        self.spring_law = np.zeros(0, np.int32)
        self.spring_kind = np.zeros(0, np.int32)
        self.spring_middle = np.zeros(0, np.int64)
        self.spring_of_element_cloth = np.zeros(0, bool)  # the cloth's membrane is elements (its shear springs carry nothing)
        self.triangles = np.zeros((0, 3), np.int64)
        self.tri_drag = np.zeros(0)
        self.tri_corner_weights = np.zeros((0, 3))
        self.membrane_vertices = np.zeros((0, 3), np.int64)
        self.membrane_rest_inverse = np.zeros((0, 2, 2))
        self.membrane_rest_area = np.zeros(0)
        self.membrane_stiffness = np.zeros((0, 4))
        self.membrane_damping = np.zeros((0, 4))
        self.plate_offsets = np.zeros(1, np.int64)
        self.plate_points = np.zeros(0, np.int64)
        self.plate_weights = np.zeros((0, 3))
        self.plate_stiffness = np.zeros((0, 3, 3))
        self.plate_vertex = np.zeros(0, np.int64)
        # stretch constants the structural springs of element cloths would have had (default repulsion stiffness)
        self._element_structural_stiffness: list[np.ndarray] = []
        self.cloths: list[tuple[ClothRef, FabricMaterial, int]] = []
        self.handles: list[Handle] = []
        self.attachments: list = []
        self.colliders: list[Collider] = []
        self.self_collision = False
        self.cloth_thickness = 0.0
        self.cloth_friction = 0.0
        self.self_collision_stiffness = None
        self.world_starts: list[int] = []  # batched worlds (add_world): each world's first particle; empty: one world

    @property
    def up_vector(self) -> tuple[float, float, float]:
        return (0.0, 0.0, 1.0) if self.up_axis == "Z" else (0.0, 1.0, 0.0)

    @property
    def particle_count(self) -> int:
        return len(self.particle_positions)

    # -- low level -------------------------------------------------------------------------
    def add_particle(self, position, velocity=(0.0, 0.0, 0.0), mass: float = 1.0, pinned: bool = False) -> int:
        """Add one particle (mass [kg]); returns its index."""
        p = np.asarray(check_vector("position", position, LIMITS["position"])).reshape(1, 3)
        v = np.asarray(check_vector("velocity", velocity, LIMITS["velocity"])).reshape(1, 3)
        mass = check_number("mass", mass, LIMITS["mass"])
        self.particle_positions = np.concatenate([self.particle_positions, p])
        self.particle_velocities = np.concatenate([self.particle_velocities, v])
        self.particle_mass = np.append(self.particle_mass, mass)
        self.particle_pinned = np.append(self.particle_pinned, np.int32(pinned))
        self.particle_pin_stiffness = np.append(self.particle_pin_stiffness, 0.0)
        return self.particle_count - 1

    def add_spring(
        self,
        i: int,
        j: int,
        stiffness: float,
        damping: float = 0.0,
        rest_length: float | None = None,
        kind: SpringKind = SpringKind.STRUCTURAL,
        law: SpringLaw = SpringLaw.LINEAR,
    ) -> int:
        """Add a spring between particles i and j (rest length defaults to their current distance).

        stiffness is k [N/m] for the linear law and k_b [N m^2] for the buckling law; damping c [N s/m].
        """
        n = self.particle_count
        if not (0 <= i < n and 0 <= j < n) or i == j:
            raise IndexError(f"spring endpoints must be two different particles in [0, {n}), got ({i}, {j})")
        if rest_length is None:
            rest_length = float(np.linalg.norm(self.particle_positions[i] - self.particle_positions[j]))
        rest_length = check_number("rest_length", rest_length, LIMITS["rest_length"])
        if law == SpringLaw.BUCKLING:
            raise ValueError("buckling (Choi-Ko bend) springs need a middle particle; add them through a cloth")
        stiffness = check_number("stiffness", stiffness, LIMITS["spring_stiffness"])
        damping = check_number("damping", damping, LIMITS["spring_damping"])
        self._append_springs(
            np.array([[i, j]]), np.array([rest_length]), np.array([stiffness]), np.array([damping]),
            np.array([int(law)]), np.array([int(kind)]), np.array([-1]),
        )
        return len(self.springs) - 1

    def _append_springs(self, springs, rest, k, c, law, kind, middle, element_cloth: bool = False):
        self.spring_of_element_cloth = np.concatenate([self.spring_of_element_cloth, np.full(len(springs), element_cloth)])
        self.springs = np.concatenate([self.springs, springs.astype(np.int64)])
        self.spring_rest_length = np.concatenate([self.spring_rest_length, rest])
        self.spring_stiffness = np.concatenate([self.spring_stiffness, k])
        self.spring_damping = np.concatenate([self.spring_damping, c])
        self.spring_law = np.concatenate([self.spring_law, law.astype(np.int32)])
        self.spring_kind = np.concatenate([self.spring_kind, kind.astype(np.int32)])
        self.spring_middle = np.concatenate([self.spring_middle, middle.astype(np.int64)])

    # -- cloths ------------------------------------------------------------------------------
    def add_cloth_grid(
        self,
        *,
        resolution=(32, 32),
        size=(1.0, 1.0),
        position=(0.0, 0.0, 0.0),
        rotation=None,
        velocity=(0.0, 0.0, 0.0),
        material: FabricMaterial | str = "cotton",
        spring_model: SpringModel | str = SpringModel.CHOI_KO,
        warp_angle: float = 0.0,
        membrane: MembraneModel | str | None = None,
        bending: BendingModel | str | None = None,
        name: str | None = None,
    ) -> ClothRef:
        """Add a grid cloth of resolution (nx, ny) cells and size (sx, sy) [m].

        The grid is built in its local xy-plane with corner (0, 0) at the origin, then rotated by
        `rotation` (quaternion x, y, z, w or 3x3) and moved to `position` [m]. The material's warp runs
        along the local x axis turned by `warp_angle` [deg] about the local z axis (45: a bias cut).
        `membrane` (:class:`~cloth_warp.topology.MembraneModel`): what carries stretch and shear; default
        "springs" on cells up to 1.5:1 (exact for uniform strain, cheaper) and "element" on more elongated cells
        (where a spring lattice has soft modes at shear/stretch ratios >= 0.2, knits among them):
        :func:`~cloth_warp.topology.default_membrane_model`.
        `bending` (:class:`~cloth_warp.topology.BendingModel`): default "springs" (bend springs fitted per node,
        with Choi-Ko's immediate buckling); "stencil" as on meshes.
        """
        t = topo.grid_topology(resolution, size, SpringModel(spring_model), warp_angle)
        return self._add_cloth(t, position, rotation, velocity, material, name or f"cloth{len(self.cloths)}", membrane, bending)

    def add_cloth_mesh(
        self,
        vertices,
        triangles,
        *,
        uvs=None,
        position=(0.0, 0.0, 0.0),
        rotation=None,
        scale: float = 1.0,
        velocity=(0.0, 0.0, 0.0),
        material: FabricMaterial | str = "cotton",
        spring_model: SpringModel | str = SpringModel.CHOI_KO,
        warp_direction=None,
        membrane: MembraneModel | str | None = None,
        bending: BendingModel | str | None = None,
        name: str | None = None,
    ) -> ClothRef:
        """Add a cloth from a triangle mesh (vertices [m] before `scale`); seams are welded.

        The material's warp runs along `warp_direction` (the mesh's own coordinates) when given, else
        along increasing texture u where `uvs` are given, else along the mesh's x axis
        (:func:`~cloth_warp.topology.triangle_frames`).

        `membrane` (:class:`~cloth_warp.topology.MembraneModel`): what carries stretch and shear; default
        "element", one orthotropic triangle element per triangle, which stores the material's shear on any
        mesh (a spring net on triangles with edges at arbitrary angles obeys Cauchy's relation and shears
        3.6x too stiffly at G/C = 0.02); "springs" keeps the fitted spring net (cheaper, exact stretch only).
        `bending` (:class:`~cloth_warp.topology.BendingModel`): default "stencil", one plate-bending stencil per
        vertex (the plate energy on any mesh); "springs": bend triples, exact only where they are straight at rest.

        Raises :class:`~cloth_warp.topology.MeshError` for empty meshes, non-finite coordinates and
        out-of-range indices; degenerate/duplicate triangles are dropped and non-manifold edges kept,
        each with a warning (rules in :func:`cloth_warp.topology.mesh_topology`).
        """
        v, tri = topo.validate_mesh(vertices, triangles)
        scale = check_number("scale", scale, LIMITS["scale"])
        v = check_points("vertices (x scale)", v * scale)
        t = topo.mesh_topology(v, tri, SpringModel(spring_model), uvs=uvs, warp_direction=warp_direction)
        return self._add_cloth(t, position, rotation, velocity, material, name or f"cloth{len(self.cloths)}", membrane, bending)

    def add_cloth_disc(self, *, radius: float, rings: int = 16, **kwargs) -> ClothRef:
        """Add a circular cloth of `radius` [m] meshed in `rings` concentric rings
        (:func:`~cloth_warp.topology.disc_mesh`; e.g. the 30 cm specimen of a Cusick drape test). Placed
        like a grid (local xy-plane, centre at the origin, then `rotation` and `position`), with texture
        coordinates projected from that plane (u, v = x / 2r + 1/2, y / 2r + 1/2) and the warp along x unless
        given; other keyword arguments as for :meth:`add_cloth_mesh`."""
        v, t = topo.disc_mesh(radius, rings)
        kwargs.setdefault("name", f"disc{len(self.cloths)}")
        if kwargs.get("uvs") is None:
            kwargs["uvs"] = v[:, :2] / (2.0 * radius) + 0.5
            kwargs.setdefault("warp_direction", (1.0, 0.0, 0.0))
        return self.add_cloth_mesh(v, t, **kwargs)

    def add_cloth_pattern(self, pattern, *, edge_length: float = 0.02, wraps=(), seam_stiffness: float | None = None,
                          seam_damping: float | None = None, **kwargs) -> ClothRef:
        """Add a garment from a sewing pattern (:mod:`cloth_warp.patterns`): a GarmentCode specification (its JSON file
        or dict), a :class:`~cloth_warp.patterns.Pattern`, or a :class:`~cloth_warp.patterns.PatternMesh`.

        Its panels are meshed at `edge_length` [m] and placed as the pattern places them (and wrapped about the axes
        of `wraps`, :class:`~cloth_warp.patterns.Wrap`: round the body parts they cover), as one cloth whose texture
        coordinates are each panel's 2D coordinates [m] (so a woven fabric's warp runs along each panel's x axis);
        points that coincide where panels meet are welded. Each stitch is sewn by zero-length seam springs
        (:attr:`~cloth_warp.topology.SpringKind.SEAM`, never strain-limited) between its matching points: they pull
        the panels together over the first frames and then hold them, a stiff seam. `seam_stiffness` [N/m] (default:
        the material's stretch stiffness, as stiff as the cloth's own springs) and `seam_damping` [N s/m] (default:
        critical for the lightest seam point against that stiffness). Other keyword arguments as for
        :meth:`add_cloth_mesh` (no `uvs`: the pattern's are used); returns the cloth, with its mesh as
        ``ref.pattern_mesh`` and its seam springs' particle pairs as ``ref.seams``."""
        from . import patterns

        if isinstance(pattern, patterns.PatternMesh):
            mesh = pattern
        else:
            if not isinstance(pattern, patterns.Pattern):
                pattern = patterns.read_garmentcode(pattern)
            mesh = patterns.mesh_pattern(pattern, edge_length, wraps=wraps)
        if "uvs" in kwargs:
            raise ValueError("add_cloth_pattern: the texture coordinates are the panels' own; do not pass uvs")
        kwargs.setdefault("name", f"garment{len(self.cloths)}")
        ref = self.add_cloth_mesh(mesh.vertices, mesh.triangles, uvs=mesh.uvs, **kwargs)
        r2p = ref.topology.render_to_particle
        pairs = mesh.seams if r2p is None else r2p[mesh.seams]
        pairs = np.unique(np.sort(pairs[pairs[:, 0] != pairs[:, 1]], axis=1), axis=0)
        pairs = ref.indices(pairs.reshape(-1)).reshape(-1, 2)
        material = self.cloths[-1][1]
        k = check_number("seam_stiffness", material.stretch_stiffness if seam_stiffness is None else seam_stiffness, LIMITS["spring_stiffness"])
        if seam_damping is None:
            lightest = float(np.min(self.particle_mass[pairs])) if len(pairs) else 0.0
            seam_damping = 2.0 * math.sqrt(k * 0.5 * lightest)
        c = check_number("seam_damping", seam_damping, LIMITS["spring_damping"])
        for i, j in pairs:
            self.add_spring(int(i), int(j), k, c, rest_length=LIMITS["rest_length"].lo, kind=SpringKind.SEAM)
        ref.pattern_mesh = mesh
        ref.seams = pairs
        return ref

    def add_cloth_mesh_file(self, path: str | os.PathLike, *, prim_path: str | None = None, **kwargs) -> ClothRef:
        """Add a cloth from a mesh file: OBJ, PLY, STL, GLB/GLTF, OFF (trimesh) or USD (.usd/.usda/.usdc).

        All geometry in a trimesh file is concatenated with node transforms baked; from a USD file the
        Mesh at `prim_path` (default: the first one) is read (see :func:`read_usd_mesh`). UVs are kept
        when present (as face-varying corner UVs after welding), so textures survive seams.
        """
        if os.fspath(path).lower().endswith(USD_SUFFIXES):
            vertices, triangles, uvs = read_usd_mesh(path, prim_path)
        else:
            vertices, triangles, uvs = load_mesh_file(path)
        kwargs.setdefault("name", os.path.splitext(os.path.basename(str(path)))[0])
        return self.add_cloth_mesh(vertices, triangles, uvs=uvs, **kwargs)

    def _add_cloth(self, t: ClothTopology, position, rotation, velocity, material, name, membrane=None, bending=None) -> ClothRef:
        grid = t.grid_shape is not None
        aspect = 1.0
        if grid:  # cell width over height, from the rest extent
            extent = np.ptp(t.positions[:, :2], axis=0)
            aspect = float((extent[0] / t.grid_shape[0]) / (extent[1] / t.grid_shape[1]))
        membrane = _choice("membrane", membrane, MembraneModel, topo.default_membrane_model(grid, aspect))
        bending = _choice("bending", bending, BendingModel, topo.default_bending_model(grid))
        if isinstance(material, str):
            material = preset(material)
        if not isinstance(material, FabricMaterial):
            raise TypeError(f"material must be a FabricMaterial or a preset name, got {material!r}")
        if any(ref.name == name for ref, _, _ in self.cloths):
            raise ValueError(f"a cloth named {name!r} already exists")
        r = rotation_matrix(rotation)
        position = check_vector("position", position, LIMITS["position"])
        velocity = check_vector("velocity", velocity, LIMITS["velocity"])
        world = check_points(f"cloth {name!r}: positions (rotated, then moved by position)", t.positions @ r.T + np.asarray(position))
        start = self.particle_count
        n = t.particle_count
        area = t.particle_area.copy()
        if np.any(area <= 0.0):
            # Vertices on no triangle still need a mass: give them the mean.
            area[area <= 0.0] = float(area[area > 0.0].mean())
        self.particle_positions = np.concatenate([self.particle_positions, world])
        self.particle_velocities = np.concatenate([self.particle_velocities, np.tile(np.asarray(velocity, float), (n, 1))])
        self.particle_mass = np.concatenate([self.particle_mass, material.areal_density * area])
        self.particle_pinned = np.concatenate([self.particle_pinned, np.zeros(n, np.int32)])
        self.particle_pin_stiffness = np.concatenate([self.particle_pin_stiffness, np.zeros(n)])
        k, c = spring_constants(t, material)
        if membrane == MembraneModel.ELEMENT:
            # The elements carry stretch and shear; structural and shear springs stay (strain limiter, diagnostics)
            # with zero stiffness and damping.
            carried = np.isin(t.spring_kind, (SpringKind.STRUCTURAL, SpringKind.SHEAR)) & (t.spring_law == SpringLaw.LINEAR)
            self._element_structural_stiffness.append(k[carried & (t.spring_kind == SpringKind.STRUCTURAL)])
            k, c = np.where(carried, 0.0, k), np.where(carried, 0.0, c)
            self._add_membrane_elements(t, material, start)
        rest = np.linalg.norm(t.positions[t.springs[:, 0]] - t.positions[t.springs[:, 1]], axis=1)
        middle = np.where(t.spring_middle >= 0, t.spring_middle + start, -1)
        keep = np.ones(t.spring_count, bool)
        if bending == BendingModel.STENCIL:
            keep = t.spring_kind != SpringKind.BEND  # the stencils carry the bending
            self._add_plate_stencils(t, material, start)
        self._append_springs(t.springs[keep] + start, rest[keep], k[keep], c[keep], t.spring_law[keep], t.spring_kind[keep], middle[keep],
                             element_cloth=membrane == MembraneModel.ELEMENT)
        tri_start = len(self.triangles)
        self.triangles = np.concatenate([self.triangles, t.triangles.astype(np.int64) + start])
        self.tri_drag = np.concatenate([self.tri_drag, np.full(len(t.triangles), material.drag_coefficient)])
        weights = t.corner_weights if t.corner_weights is not None else np.full((len(t.triangles), 3), 1.0 / 3.0)
        self.tri_corner_weights = np.concatenate([self.tri_corner_weights, weights])
        ref = ClothRef(self, name, start, t)
        self.cloths.append((ref, material, tri_start))
        return ref

    def _add_membrane_elements(self, t: ClothTopology, material: FabricMaterial, start: int):
        """One membrane element per triangle of `t` (rest shape in the cloth's own frame: placing it does not
        change it), with the material's Voigt constants and Kelvin-Voigt damping tau C."""
        inverse, area = topo.triangle_rest_shapes(t.positions, t.triangles, t.triangle_warp)
        keep = area > 0.0
        c = membrane_element_stiffness(material)
        count = int(keep.sum())
        self.membrane_vertices = np.concatenate([self.membrane_vertices, t.triangles[keep].astype(np.int64) + start])
        self.membrane_rest_inverse = np.concatenate([self.membrane_rest_inverse, inverse[keep]])
        self.membrane_rest_area = np.concatenate([self.membrane_rest_area, area[keep]])
        self.membrane_stiffness = np.concatenate([self.membrane_stiffness, np.tile(c, (count, 1))])
        self.membrane_damping = np.concatenate([self.membrane_damping, np.tile(material.damping * c, (count, 1))])

    def _add_plate_stencils(self, t: ClothTopology, material: FabricMaterial, start: int):
        """One plate-bending stencil per vertex of `t` (:func:`~cloth_warp.plate.plate_stencils`), stiffness
        S = A_v D with D the Voigt matrix of the material's plate tensor in the vertex's warp/weft frame."""
        warp = t.triangle_warp if t.triangle_warp is not None else topo.triangle_frames(t.positions, t.triangles)[1]
        st, issues = plate_stencils(t.positions, t.triangles, warp, t.particle_area)
        for msg in issues:
            warnings.warn(f"cloth mesh: {msg}", stacklevel=4)
        d = plate_tensor(material).voigt()
        self.plate_offsets = np.concatenate([self.plate_offsets, st.offsets[1:] + self.plate_offsets[-1]])
        self.plate_points = np.concatenate([self.plate_points, st.points + start])
        self.plate_weights = np.concatenate([self.plate_weights, st.weights])
        self.plate_stiffness = np.concatenate([self.plate_stiffness, st.area[:, None, None] * d[None]])
        self.plate_vertex = np.concatenate([self.plate_vertex, st.vertex + start])

    # -- pins and handles --------------------------------------------------------------------
    def pin(self, indices, stiffness: float | None = None):
        """Pin particles: hard (stiffness None: they follow Control.pin_target exactly) or soft [N/m]."""
        idx = self._check_indices(indices)
        if stiffness is None:
            self.particle_pinned[idx] = 1
        else:
            self.particle_pin_stiffness[idx] = check_number("stiffness", stiffness, LIMITS["pin_stiffness"])
        return idx

    def attach(self, indices, collider: Collider, *, offset: float | None = None, name: str | None = None) -> Attachment:
        """Bind particles to a mesh collider's surface (a waistband, a strap, a cuff on a body): each is hard-pinned to
        the closest point of the collider's mesh in its initial pose (a triangle and barycentric weights) plus its
        offset from there in the triangle's frame, and follows them as the collider moves and deforms (its point
        cache). `offset` [m]: instead, put each particle that far along its triangle's normal (0: onto the surface)."""
        from .colliders import closest_mesh_points
        from .model import quat_to_matrix, triangle_frames

        if collider not in self.colliders or collider.shape != "mesh":
            raise ValueError("attach: the collider must be a mesh collider of this builder (add_collider_mesh / _file)")
        import trimesh

        idx = self._check_indices(indices)
        v = np.asarray(collider.vertices_at(0.0), np.float64)
        p, q = collider.pose_at(0.0)
        rot = quat_to_matrix(q)
        local = (self.particle_positions[idx] - p) @ rot  # world -> the collider's frame (row vectors)
        closest, tri = closest_mesh_points(v, collider.triangles, local)
        corners = v[collider.triangles[tri]]
        weights = trimesh.triangles.points_to_barycentric(corners, closest)
        frames = triangle_frames(corners)
        if offset is None:
            off = np.einsum("aij,aj->ai", frames, local - closest)
        else:
            off = np.zeros((len(idx), 3))
            off[:, 2] = check_number("offset", offset, LIMITS["position"])
            placed = (closest + np.einsum("aij,ai->aj", frames, off)) @ rot.T + p
            self.particle_positions[idx] = placed
        self.pin(idx)
        a = Attachment(name or f"attachment{len(self.attachments)}", self.colliders.index(collider), idx,
                       collider.triangles[tri].astype(np.int32), weights.astype(np.float64), off.astype(np.float64))
        self.attachments.append(a)
        return a

    def add_handle(self, indices, keyframes, *, pivot=None, name: str | None = None) -> Handle:
        """Hard-pin `indices` to a keyframed rigid transform (list of Keyframe or (t, translation[, quat])).

        The transform acts about `pivot` (default: the particles' centroid); translation is relative to
        the rest pose.
        """
        idx = self._check_indices(indices)
        kfs = _keyframes(keyframes)
        if not kfs:
            raise ValueError("keyframes: a handle needs at least one keyframe")
        p = self.particle_positions[idx]
        pivot = np.asarray(check_vector("pivot", pivot, LIMITS["position"])) if pivot is not None else p.mean(0)
        h = Handle(name or f"handle{len(self.handles)}", idx, kfs, pivot)
        self.particle_pinned[idx] = 1
        self.handles.append(h)
        return h

    # -- colliders and self-collision ---------------------------------------------------------
    def add_collider(self, collider: Collider) -> Collider:
        """Add a :class:`~cloth_warp.colliders.Collider` (the ``add_<shape>`` methods build one)."""
        names = {c.name for c in self.colliders}
        if collider.name in names:
            raise ValueError(f"a collider named {collider.name!r} exists already")
        self.colliders.append(collider)
        return collider

    def _collider(self, shape: str, name, position, rotation, thickness, friction, static_friction, kinetic_friction,
                  keyframes, **geometry) -> Collider:
        # Collider checks every value; the defaults below need friction and mu_s to be numbers first.
        friction = check_number("friction", friction, LIMITS["friction"])
        mu_s = friction if static_friction is None else check_number("static_friction", static_friction, LIMITS["friction"])
        mu_k = min(friction, mu_s) if kinetic_friction is None else kinetic_friction
        q = (0.0, 0.0, 0.0, 1.0) if rotation is None else rotation
        col = Collider(name or f"{shape}{len(self.colliders)}", shape, position=position, rotation=q, thickness=thickness,
                       static_friction=mu_s, kinetic_friction=mu_k, keyframes=keyframes or [], **geometry)
        return self.add_collider(col)

    def add_ground(self, height: float = 0.0, **common) -> Collider:
        """The plane `height` [m] along the up axis, solid below (keyword options as :meth:`add_plane`)."""
        return self.add_plane(normal=self.up_vector, point=tuple(height * u for u in self.up_vector), **common)

    def add_plane(self, normal=None, point=(0.0, 0.0, 0.0), *, name=None, thickness=0.004, friction=0.3, static_friction=None,
                  kinetic_friction=None, keyframes=None) -> Collider:
        """An infinite plane through `point` [m]; `normal` (default: up) points out of the solid half-space.

        Common options of every ``add_<shape>``: `thickness` [m] (contact offset), `friction` (Coulomb
        coefficient, both static and kinetic) or `static_friction` / `kinetic_friction`, `keyframes`
        (rigid animation: (time, translation[, quaternion]) or Keyframe), `name`.
        """
        q = rotation_to_axis(self.up_vector if normal is None else normal, "normal")
        return self._collider("plane", name, point, q, thickness, friction, static_friction, kinetic_friction, keyframes)

    def add_sphere(self, center, radius: float, *, name=None, thickness=0.004, friction=0.3, static_friction=None,
                   kinetic_friction=None, keyframes=None) -> Collider:
        """A solid sphere of `radius` [m] about `center` [m]."""
        return self._collider("sphere", name, center, None, thickness, friction, static_friction, kinetic_friction, keyframes,
                              radius=radius)

    def add_capsule(self, center, radius: float, height: float, axis=None, *, name=None, thickness=0.004, friction=0.3,
                    static_friction=None, kinetic_friction=None, keyframes=None) -> Collider:
        """A capsule: the points within `radius` [m] of a segment of length `height` [m] along `axis`
        (default: up) through `center` (height excludes the caps, as UsdGeom.Capsule)."""
        q = rotation_to_axis(self.up_vector if axis is None else axis)
        return self._collider("capsule", name, center, q, thickness, friction, static_friction, kinetic_friction, keyframes,
                              radius=radius, height=height)

    def add_box(self, center, size, rotation=None, *, name=None, thickness=0.004, friction=0.3, static_friction=None,
                kinetic_friction=None, keyframes=None) -> Collider:
        """A solid box with edge lengths `size` [m] centred at `center`, turned by `rotation` (x, y, z, w)."""
        return self._collider("box", name, center, rotation, thickness, friction, static_friction, kinetic_friction, keyframes,
                              size=size)

    def add_cylinder(self, center, radius: float, height: float, axis=None, *, name=None, thickness=0.004, friction=0.3,
                     static_friction=None, kinetic_friction=None, keyframes=None) -> Collider:
        """A solid cylinder (flat caps; a disc when short) of `radius` and full `height` [m] along `axis`
        (default: up) centred at `center`."""
        q = rotation_to_axis(self.up_vector if axis is None else axis)
        return self._collider("cylinder", name, center, q, thickness, friction, static_friction, kinetic_friction, keyframes,
                              radius=radius, height=height)

    def add_collider_mesh(self, vertices, triangles, position=(0.0, 0.0, 0.0), rotation=None, scale: float = 1.0, *, name=None,
                          thickness=0.004, friction=0.3, static_friction=None, kinetic_friction=None, keyframes=None,
                          point_cache=None, point_cache_times=None) -> Collider:
        """A triangle-mesh collider (vertices [m] x `scale` in its local frame, then rotated and placed).
        A watertight mesh is solid; an open one is solid behind its triangles (right-hand winding).
        `point_cache` (samples, vertices, 3) at `point_cache_times` [s] makes it deform (x `scale` too)."""
        scale = check_number("scale", scale, LIMITS["scale"])
        v = np.asarray(vertices, float) * scale
        pc = None if point_cache is None else np.asarray(point_cache, float) * scale
        return self._collider("mesh", name, position, rotation, thickness, friction, static_friction, kinetic_friction, keyframes,
                              vertices=v, triangles=np.asarray(triangles), point_cache=pc, point_cache_times=point_cache_times)

    def add_collider_mesh_file(self, path, *, prim_path: str | None = None, deforming: bool = False, **kwargs) -> Collider:
        """A mesh collider read with trimesh (OBJ, PLY, STL, GLB, OFF) or from a USD Mesh (options as
        :meth:`add_collider_mesh`); duplicate vertices are merged. `deforming`: follow the USD mesh's
        time-sampled points (a point cache, see :func:`read_usd_point_cache`)."""
        suffix = os.path.splitext(os.fspath(path))[1].lower()
        times = cache = None
        if deforming:
            if suffix not in (".usd", ".usda", ".usdc"):
                raise MeshError(f"{path}: a deforming collider reads a USD point cache (.usd, .usda, .usdc)")
            times, cache, t = read_usd_point_cache(path, prim_path)
            v = cache[0]
        elif suffix in (".usd", ".usda", ".usdc"):
            v, t, _ = read_usd_mesh(path, prim_path)
        else:
            v, t, _ = load_mesh_file(path)
        v, first, inverse = np.unique(np.round(np.asarray(v, float), 9), axis=0, return_index=True, return_inverse=True)
        t = inverse.reshape(-1)[np.asarray(t)]
        keep = (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])
        kwargs.setdefault("name", os.path.splitext(os.path.basename(os.fspath(path)))[0])
        if deforming:
            v = cache[0][first]  # unrounded
            kwargs.update(point_cache=cache[:, first], point_cache_times=times)
        return self.add_collider_mesh(v, t[keep], **kwargs)

    def enable_self_collision(self, thickness: float = 0.004, friction: float = 0.3, stiffness: float | None = None):
        """Keep non-adjacent parts of the cloth(s) at least `thickness` [m] apart (cloth-cloth contact,
        :mod:`cloth_warp.selfcollision`), with Coulomb `friction` between layers and repulsion
        `stiffness` [N/m] (default: the median stretch stiffness of the cloth's structural springs)."""
        self.cloth_thickness = check_number("thickness", thickness, LIMITS["thickness"])
        self.cloth_friction = check_number("friction", friction, LIMITS["friction"])
        self.self_collision_stiffness = None if stiffness is None else check_number("stiffness", stiffness, LIMITS["pin_stiffness"])
        self.self_collision = True

    # -- batched worlds --------------------------------------------------------------------
    def add_world(self, other: ModelBuilder) -> int:
        """Append everything `other` holds as one more independent world (its particles after this builder's, its
        indices moved along; cloths renamed ``world<k>/<name>``) and return the world's index. The worlds of a batch
        share the colliders (each world's must be the same), the up axis, gravity, damping and self-collision settings:
        they are one scene's variants in their cloths (materials, sizes, meshes, pins, handles, initial state)."""
        if self.particle_count and not self.world_starts:
            raise ValueError("add_world: this builder already holds a cloth that is no world; build batches from empty builders")
        for what in ("up_axis", "gravity", "global_damping", "self_collision", "cloth_thickness", "cloth_friction", "self_collision_stiffness"):
            mine, theirs = getattr(self, what), getattr(other, what)
            if self.world_starts and not np.array_equal(np.asarray(mine, dtype=object), np.asarray(theirs, dtype=object)):
                raise ValueError(f"add_world: world {len(self.world_starts)} has {what} {theirs!r} where the batch has {mine!r}; "
                                 "batched worlds share it")
            setattr(self, what, theirs)
        if self.world_starts and not _same_colliders(self.colliders, other.colliders):
            raise ValueError(f"add_world: world {len(self.world_starts)} has other colliders than the batch's first world; "
                             "batched worlds share their colliders")
        if not self.world_starts:
            self.colliders = list(other.colliders)
        k = len(self.world_starts)
        start, tri_start, points = self.particle_count, len(self.triangles), len(self.plate_points)
        self.world_starts.append(start)

        def cat(name, shift=None):
            a, b = getattr(self, name), getattr(other, name)
            if shift is not None:
                b = np.where(b >= 0, b + shift, b)
            setattr(self, name, np.concatenate([a, b]))

        for name in ("particle_positions", "particle_velocities", "particle_mass", "particle_pinned", "particle_pin_stiffness",
                     "spring_rest_length", "spring_stiffness", "spring_damping", "spring_law", "spring_kind", "spring_of_element_cloth",
                     "tri_drag", "tri_corner_weights", "membrane_rest_inverse", "membrane_rest_area", "membrane_stiffness",
                     "membrane_damping", "plate_weights", "plate_stiffness"):
            cat(name)
        for name in ("springs", "spring_middle", "triangles", "membrane_vertices", "plate_points", "plate_vertex"):
            cat(name, start)
        self.plate_offsets = np.concatenate([self.plate_offsets, other.plate_offsets[1:] + points])
        self._element_structural_stiffness.extend(other._element_structural_stiffness)
        for ref, material, t0 in other.cloths:
            self.cloths.append((ClothRef(self, f"world{k}/{ref.name}", ref.particle_start + start, ref.topology), material, t0 + tri_start))
        for h in other.handles:
            self.handles.append(Handle(f"world{k}/{h.name}", np.asarray(h.particles) + start, list(h.keyframes), np.asarray(h.pivot).copy()))
        for a in other.attachments:  # (the colliders are the batch's, in the same order)
            self.attachments.append(replace(a, name=f"world{k}/{a.name}", particles=np.asarray(a.particles) + start))
        return k

    def _check_indices(self, indices) -> np.ndarray:
        idx = np.unique(np.asarray(indices, np.int64).ravel())
        if idx.size == 0:
            raise ValueError("no particles selected")
        if idx.min() < 0 or idx.max() >= self.particle_count:
            raise IndexError(f"particle index out of range [0, {self.particle_count}): {idx.min()}..{idx.max()}")
        return idx

    # -- finalize ------------------------------------------------------------------------------
    def finalize(self, device=None, requires_grad: bool = False) -> Model:
        """Build the :class:`Model` on `device`; Model arrays get `requires_grad` here and only here."""
        if self.particle_count == 0:
            raise ValueError("the model has no particles")
        self._check_float32()
        device = wp.get_device(device)
        m = Model()
        m.device = device
        m.requires_grad = requires_grad
        m.gravity = self.gravity
        m.up_axis = self.up_axis
        m.global_damping = self.global_damping
        n = self.particle_count
        m.particle_count = n
        m.spring_count = len(self.springs)
        m.tri_count = len(self.triangles)
        m.rest_positions = self.particle_positions.copy()

        def arr(a, dtype, grad=False):
            return wp.array(np.ascontiguousarray(a), dtype=dtype, device=device, requires_grad=grad and requires_grad)

        m.particle_q = arr(self.particle_positions.astype(np.float32), wp.vec3, True)
        m.particle_qd = arr(self.particle_velocities.astype(np.float32), wp.vec3, True)
        m.particle_mass = arr(self.particle_mass.astype(np.float32), float, True)
        m.particle_pinned = arr(self.particle_pinned.astype(np.int32), wp.int32)
        m.particle_pin_stiffness = arr(self.particle_pin_stiffness.astype(np.float32), float)
        starts = self.world_starts or [0]
        m.world_count = len(starts)
        m.world_particle_start = np.array([*starts, n])
        m.particle_world = arr(np.repeat(np.arange(len(starts), dtype=np.int32), np.diff(m.world_particle_start)), wp.int32)
        # Linear springs first, bend triples after: each family is one kernel launch over a range. Within a
        # family, order by the first particle touched so consecutive springs touch nearby memory.
        low = np.minimum(self.springs[:, 0], self.springs[:, 1]) if len(self.springs) else np.zeros(0, np.int64)
        order = np.lexsort((low, self.spring_law))
        springs = self.springs[order].astype(np.int32).reshape(-1, 2)
        middle = self.spring_middle[order]
        law = self.spring_law[order]
        stiffness = clamp_boundary_bending(self.spring_stiffness[order], springs, middle, law, self.particle_pinned)
        m.linear_spring_count = int(np.sum(law == SpringLaw.LINEAR))
        m.spring_indices = arr(springs, wp.int32)
        m.spring_rest_length = arr(self.spring_rest_length[order].astype(np.float32), float, True)
        m.spring_stiffness = arr(stiffness.astype(np.float32), float, True)
        m.spring_damping = arr(self.spring_damping[order].astype(np.float32), float, True)
        m.spring_law = arr(law, wp.int32)
        m.spring_kind = arr(self.spring_kind[order], wp.int32)
        m.spring_middle = arr(middle.astype(np.int32), wp.int32)
        # the same indices as vector rows (the force kernels read one contiguous row per element)
        first = m.linear_spring_count
        m.spring_ends = arr(springs, wp.vec2i)
        m.bend_triples = arr(np.column_stack([springs[first:, 0], middle[first:], springs[first:, 1]]).astype(np.int32).reshape(-1, 3),
                             wp.vec3i)
        tris = self.triangles.astype(np.int32).reshape(-1, 3)
        m.tri_indices = arr(tris, wp.int32)
        m.tri_vertices = arr(tris, wp.vec3i)
        m.tri_drag = arr(self.tri_drag.astype(np.float32), float, True)
        m.tri_corner_weights = arr(self.tri_corner_weights.astype(np.float32).reshape(-1, 3), wp.vec3)
        m.membrane_count = len(self.membrane_vertices)
        mv = self.membrane_vertices.astype(np.int32).reshape(-1, 3)
        m.membrane_vertices = arr(mv, wp.vec3i)
        m.membrane_rest_inverse = arr(self.membrane_rest_inverse.astype(np.float32).reshape(-1, 2, 2), wp.mat22)
        m.membrane_rest_area = arr(self.membrane_rest_area.astype(np.float32), float)
        m.membrane_stiffness = arr(self.membrane_stiffness.astype(np.float32).reshape(-1, 4), wp.vec4, True)
        m.membrane_damping = arr(self.membrane_damping.astype(np.float32).reshape(-1, 4), wp.vec4, True)
        m.plate_count = len(self.plate_stiffness)
        m.plate_offsets = arr(self.plate_offsets.astype(np.int32), wp.int32)
        m.plate_points = arr(self.plate_points.astype(np.int32), wp.int32)
        m.plate_weights = arr(self.plate_weights.astype(np.float32).reshape(-1, 3), wp.vec3)
        plate_stiffness = clamp_boundary_plates(self.plate_stiffness, self.plate_offsets, self.plate_points, self.plate_vertex,
                                                self.particle_pinned, self.particle_positions)
        m.plate_stiffness = arr(plate_stiffness.astype(np.float32).reshape(-1, 3, 3), wp.mat33, True)
        mo, mid = topo.particle_triangles(mv, n)
        m.particle_membrane_offsets = arr(mo, wp.int32)
        m.particle_membrane_ids = arr(mid, wp.int32)
        so, sid, srole = topo.particle_springs(springs, middle, n)
        m.particle_spring_offsets = arr(so, wp.int32)
        m.particle_spring_ids = arr(sid, wp.int32)
        m.particle_spring_role = arr(srole, wp.int32)
        to, tid = topo.particle_triangles(tris, n)
        m.particle_tri_offsets = arr(to, wp.int32)
        m.particle_tri_ids = arr(tid, wp.int32)
        # The limiter holds structural springs and, where springs carry the shear, shear springs; on element cloths the
        # shear diagonals carry nothing, and holding them at the limit would cap the shear angle (~11 deg at 10 %) and
        # keep a draped cloth from coming to rest (tests/test_colliders.py).
        kind_sorted = self.spring_kind[order]
        limited = ((kind_sorted == SpringKind.STRUCTURAL) | ((kind_sorted == SpringKind.SHEAR) & ~self.spring_of_element_cloth[order])) \
            & (law == SpringLaw.LINEAR)
        colors = topo.color_springs(springs, n, limited)
        m.strain_limit_color_count = colors.shape[0]
        # The same colouring as spring lists (one launch per colour over its springs, forward path).
        color_of = np.full(len(springs), -1)
        for c in range(colors.shape[0]):
            ids = colors[c][colors[c] >= 0]
            color_of[ids] = c
        by_color = np.argsort(color_of, kind="stable")
        by_color = by_color[color_of[by_color] >= 0]
        m.strain_limit_color_offsets = np.concatenate([[0], np.cumsum(np.bincount(color_of[by_color], minlength=colors.shape[0]))]).astype(int)
        m.strain_limit_color_springs = arr(by_color.astype(np.int32) if len(by_color) else np.zeros(1, np.int32), wp.int32)
        m.strain_limit_colors = arr(colors if colors.size else np.full((1, n), -1, np.int32), wp.int32)
        m.spring_limited = arr(limited.astype(np.int32), wp.int32)
        for ref, material, tri_start in self.cloths:
            m.cloths.append(ClothInfo(ref.name, ref.particle_start, ref.particle_count, tri_start, len(ref.topology.triangles), material, ref.topology))
        m.handles = list(self.handles)
        m.attachments = list(self.attachments)
        self._finalize_colliders(m, arr)
        m.self_collision = self.self_collision
        m.cloth_thickness = self.cloth_thickness
        m.cloth_friction = self.cloth_friction
        k = self.self_collision_stiffness
        if k is None:
            structural = (self.spring_kind[order] == SpringKind.STRUCTURAL) & (law == SpringLaw.LINEAR)
            stiff = m.spring_stiffness.numpy()
            # element cloths' structural springs carry nothing: count what they would have carried
            values = np.concatenate([stiff[structural & (stiff > 0.0)], *self._element_structural_stiffness])
            k = float(np.median(values)) if len(values) else 1.0e3
        m.self_collision_stiffness = k
        return m

    def _check_float32(self):
        """Refuse what leaves float32 after the unit conversions (a mass is areal density x area, a spring constant
        a material value x a geometric weight) or what float32 positions cannot resolve."""
        check_float32("particle masses (areal_density x area) [kg]", self.particle_mass, positive=True,
                      hint=": raise the areal density or use larger cells")
        check_float32("spring constants (material stiffness x geometric weight)", self.spring_stiffness,
                      hint=": lower the stiffness or use fewer cells")
        check_float32("spring damping (material damping x spring constant)", self.spring_damping, hint=": lower the damping")
        check_float32("spring rest lengths [m]", self.spring_rest_length, positive=True)
        check_float32("triangle drag coefficients", self.tri_drag)
        check_float32("membrane element constants (material stiffness and damping)", np.concatenate([self.membrane_stiffness.ravel(),
                      self.membrane_damping.ravel()]), hint=": lower the stiffness or the damping")
        check_float32("plate-bending stiffness (material bend stiffness x dual area)", self.plate_stiffness,
                      hint=": raise the bend stiffness or use larger cells")
        # seams are zero-length by design (no strain to resolve)
        check_float32_resolution("springs", self.particle_positions, self.spring_rest_length[self.spring_kind != SpringKind.SEAM])

    def _finalize_colliders(self, m: Model, arr):
        from .colliders import SHAPE_IDS

        cols = list(self.colliders)
        m.colliders = cols
        m.collider_count = len(cols)
        n = max(len(cols), 1)
        shape = np.zeros(n, np.int32)
        size = np.zeros((n, 3), np.float32)
        thickness = np.zeros(n, np.float32)
        mu_s = np.zeros(n, np.float32)
        mu_k = np.zeros(n, np.float32)
        ids = np.zeros(n, np.uint64)
        deforming = np.zeros(n, np.int32)
        m.collider_meshes = {}  # collider index -> wp.Mesh (keeps the meshes and their BVHs alive)
        for k, c in enumerate(cols):
            shape[k] = SHAPE_IDS[c.shape]
            size[k] = c.local_size
            thickness[k], mu_s[k], mu_k[k] = c.thickness, c.static_friction, c.kinetic_friction
            if c.shape == "mesh":
                # Deforming meshes carry per-vertex velocities [m/s] (Model.update_control sets both per step).
                mesh = wp.Mesh(points=wp.array(c.vertices_at(0.0).astype(np.float32), dtype=wp.vec3, device=m.device),
                               indices=wp.array(c.triangles.reshape(-1).astype(np.int32), dtype=wp.int32, device=m.device),
                               velocities=wp.zeros(len(c.vertices), dtype=wp.vec3, device=m.device) if c.deforming else None)
                m.collider_meshes[k] = mesh
                ids[k] = mesh.id
                deforming[k] = int(c.deforming)
        m.collider_shape = arr(shape, wp.int32)
        m.collider_size = arr(size, wp.vec3)
        m.collider_thickness = arr(thickness, float)
        m.collider_static_friction = arr(mu_s, float, True)
        m.collider_kinetic_friction = arr(mu_k, float, True)
        m.collider_mesh = arr(ids, wp.uint64)
        m.collider_deforming = arr(deforming, wp.int32)
        extent = [np.ptp((c.point_cache if c.deforming else c.vertices[None]).reshape(-1, 3), axis=0).max() for c in cols if c.shape == "mesh"]
        lo, hi = self.particle_positions.min(0), self.particle_positions.max(0)
        # Mesh distance queries look this far: beyond it a vertex is "far" (its exact distance is not needed).
        m.collider_mesh_max_distance = float(10.0 * (max(extent, default=1.0) + np.linalg.norm(hi - lo) + 1.0))


def _same_colliders(a: list[Collider], b: list[Collider]) -> bool:
    """Whether two collider lists describe the same colliders (every field equal, arrays element by element)."""
    from dataclasses import fields

    def same(x, y):
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            return np.array_equal(np.asarray(x), np.asarray(y))
        if isinstance(x, (list, tuple)) and isinstance(y, (list, tuple)):
            return len(x) == len(y) and all(same(p, q) for p, q in zip(x, y))
        return x == y

    return len(a) == len(b) and all(same(getattr(x, f.name), getattr(y, f.name)) for x, y in zip(a, b) for f in fields(x))


def _keyframes(keyframes, name: str = "keyframes") -> list[Keyframe]:
    """Checked Keyframe objects (unit quaternions, increasing times) from Keyframes or (time, translation[, quaternion])."""
    return [Keyframe(t, tr, q) for t, tr, q in check_keyframes(name, keyframes)]


def _choice(key: str, value, kind, default):
    """`value` as a member of the enum `kind` (None: `default`), or a ValueError naming the allowed values."""
    if value is None:
        return default
    try:
        return kind(value)
    except ValueError:
        raise ValueError(f"unknown {key} {value!r}; allowed: {', '.join(m.value for m in kind)}") from None


def clamp_boundary_bending(stiffness, springs, middle, law, pinned) -> np.ndarray:
    """Double the bend triples at the edge of a clamped region (middle and exactly one end hard-pinned).

    A hinge's energy (1/2) B theta^2 / a assumes the node's dual length a of free cloth; where the cloth
    is clamped (two adjacent pinned rows), only a/2 of it bends, so the hinge is twice as stiff. Without
    this a cantilever's root counts the moment over a whole cell and the tip deflects 2a/L too far.
    """
    k = np.asarray(stiffness, np.float64).copy()
    tri = (np.asarray(law) == SpringLaw.BUCKLING) & (np.asarray(middle) >= 0)
    if tri.any():
        p = np.asarray(pinned) != 0
        ends = p[springs[tri, 0]].astype(int) + p[springs[tri, 1]].astype(int)
        edge = p[np.asarray(middle)[tri]] & (ends == 1)
        k[np.flatnonzero(tri)[edge]] *= 2.0
    return k


def clamp_boundary_plates(stiffness, offsets, points, vertex, pinned, positions) -> np.ndarray:
    """Double the plate stencils at the edge of a clamped region (their vertex hard-pinned, pinned points around it
    that span an area, and free points): as with bend triples (:func:`clamp_boundary_bending`), the stencil then
    straddles the clamp and measures half the free side's curvature over a dual area only half of which bends,
    which would leave the root a quarter as stiff as half its area is; doubling makes it that (a cantilever's tip
    otherwise deflects ~h/L too far: +10 % at 12 cells)."""
    out = np.asarray(stiffness, np.float64).copy()
    p = np.asarray(pinned) != 0
    for s in np.flatnonzero(p[vertex]):
        ids = points[offsets[s]:offsets[s + 1]]
        held = ids[p[ids]]
        if len(held) == len(ids) or len(held) < 3:
            continue
        spread = positions[held] - positions[held].mean(axis=0)
        sv = np.linalg.svd(spread, compute_uv=False)
        if sv[1] > 1e-3 * sv[0]:  # the pinned points are not on one line: a clamped area, not a pinned edge
            out[s] *= 2.0
    return out


def spring_constants(t: ClothTopology, material: FabricMaterial) -> tuple[np.ndarray, np.ndarray]:
    """Per-spring stiffness and damping: each region's springs fitted to the material's membrane and plate
    tensors (:mod:`cloth_warp.elasticity`)."""
    k = t.membrane.spring_constants(membrane_tensor(material), t.spring_count)
    k += t.bending.spring_constants([plate_tensor(material, twist) for twist in TWISTS], t.spring_count)
    # Kelvin-Voigt damping c = tau k on linear springs; buckling springs carry no damping.
    c = np.where(t.spring_law == SpringLaw.LINEAR, material.damping * k, 0.0)
    return k, c


# What each mesh format's bytes look like: (name, first bytes or "text"). Random bytes are refused here with what
# is wrong, before a reader that could only say "missing module" or fail deep inside its parser.
MESH_FORMATS = {
    ".obj": ("Wavefront OBJ", "text"), ".off": ("OFF", "text"), ".gltf": ("glTF (JSON)", "text"), ".xyz": ("XYZ", "text"),
    ".dxf": ("DXF", "text"), ".dae": ("COLLADA (XML)", "text"), ".step": ("STEP", "text"), ".stp": ("STEP", "text"),
    ".ply": ("PLY", (b"ply",)), ".glb": ("binary glTF", (b"glTF",)), ".stl": ("STL", "stl"),
    ".3mf": ("3MF (zip)", (b"PK\x03\x04",)), ".zip": ("zip", (b"PK\x03\x04",)), ".gz": ("gzip", (b"\x1f\x8b",)),
    ".bz2": ("bzip2", (b"BZh",)), ".usdc": ("USD crate", (b"PXR-USDC",)), ".usda": ("USD text", (b"#usda",)),
    ".usd": ("USD", (b"PXR-USDC", b"#usda")),
}


def _mesh_suffix(path: str) -> str:
    name = os.path.basename(path).lower()
    return ".tar" + os.path.splitext(name)[1] if name.endswith((".tar.gz", ".tar.bz2")) else os.path.splitext(name)[1]


def check_mesh_file(path) -> str:
    """The format suffix of a readable mesh file; MeshError naming the file and what is wrong (unknown format,
    empty, bytes that are not that format, a truncated binary STL), FileNotFoundError when it is missing."""
    import trimesh

    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"mesh file not found: {path}")
    if os.path.isdir(path):
        raise IsADirectoryError(f"mesh file {path} is a folder")
    suffix = _mesh_suffix(path)
    readable = sorted({f".{f}" for f in trimesh.available_formats() if "_" not in f} | set(USD_SUFFIXES))
    known = suffix.removeprefix(".tar")
    if known not in MESH_FORMATS and suffix not in readable:
        raise MeshError(f"{path}: unknown mesh format {suffix or '(no extension)'!r}; readable here: {', '.join(readable)}")
    size = os.path.getsize(path)
    if size == 0:
        raise MeshError(f"{path}: the file is empty (0 bytes)")
    with open(path, "rb") as f:
        head = f.read(65536)
    name, signature = MESH_FORMATS.get(known, (known, None))
    problem = None
    if signature == "text" and not _looks_like_text(head):
        problem = "that format is text, this file is binary data"
    elif signature == "stl" and not (head.startswith(b"solid") and _looks_like_text(head)):
        count = int.from_bytes(head[80:84], "little") if len(head) >= 84 else -1
        if count < 0:
            problem = f"{size} bytes is shorter than a binary STL header (84 bytes), and it is not ASCII STL"
        elif size != 84 + 50 * count:
            problem = (f"not ASCII STL, and as binary STL its header counts {count} triangles ({84 + 50 * count} bytes) but "
                       f"the file has {size} bytes (truncated, or not STL)")
    elif isinstance(signature, tuple) and not head.startswith(signature):
        problem = f"it should start with {' or '.join(repr(m) for m in signature)}, it starts with {head[:8]!r}"
    if problem:
        raise MeshError(f"{path}: not a valid {name} file: {problem}")
    return suffix


def _looks_like_text(head: bytes) -> bool:
    """No NUL byte and under 1 % control characters (random bytes have about 12 %)."""
    if b"\x00" in head:
        return False
    control = sum(head.count(bytes([c])) for c in range(32) if c not in (9, 10, 12, 13))
    return control <= 0.01 * len(head)


def load_mesh_file(path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a triangle mesh with trimesh; returns (vertices, triangles, uvs or None) without merging.

    Vertices are kept as in the file (seam duplicates included) so that UVs stay correct; welding for
    simulation happens in :func:`cloth_warp.topology.mesh_topology`. The file is checked first
    (:func:`check_mesh_file`): errors name it and what is wrong.
    """
    import trimesh

    path = os.fspath(path)
    suffix = check_mesh_file(path)
    try:
        loaded = trimesh.load(path, process=False)
    except ImportError as exc:  # the format's optional reader is missing (the bytes looked right)
        raise MeshError(f"{path}: reading {suffix} files needs an optional Python package that is not installed ({exc})") from exc
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f"cannot read mesh {path} ({MESH_FORMATS.get(suffix, (suffix,))[0]}): {type(exc).__name__}: {exc}") from exc
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if loaded.geometry else []
        if not geoms:
            raise MeshError(f"mesh file {path} holds no triangle geometry")
        verts, tris, uvs, off = [], [], [], 0
        for g in geoms:
            verts.append(np.asarray(g.vertices))
            tris.append(np.asarray(g.faces) + off)
            off += len(g.vertices)
            uv = getattr(getattr(g, "visual", None), "uv", None)
            uvs.append(None if uv is None or len(uv) != len(g.vertices) else np.asarray(uv))
        uv_all = np.concatenate(uvs) if all(u is not None for u in uvs) else None
        return np.concatenate(verts), np.concatenate(tris), uv_all
    if isinstance(loaded, trimesh.PointCloud):
        raise MeshError(f"mesh file {path} has {len(loaded.vertices)} points but no faces (truncated, or a point cloud)")
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f"mesh file {path} is not a triangle mesh (trimesh returned {type(loaded).__name__})")
    uv = getattr(getattr(loaded, "visual", None), "uv", None)
    uv = None if uv is None or len(uv) != len(loaded.vertices) else np.asarray(uv)
    return np.asarray(loaded.vertices), np.asarray(loaded.faces), uv


def _usd_mesh_prim(path: str, prim_path: str | None):
    """(stage, the UsdGeom.Mesh prim at `prim_path` or the first one) of a USD file."""
    from pxr import Usd, UsdGeom

    check_mesh_file(path)
    try:
        stage = Usd.Stage.Open(path)
    except Exception as exc:  # pxr.Tf.ErrorException: the layer does not parse
        raise MeshError(f"cannot open {path} as USD: {usd_error_text(exc)}") from exc
    if stage is None:
        raise MeshError(f"cannot open {path} as USD")
    if prim_path is not None:
        prim = stage.GetPrimAtPath(prim_path)
        if not prim or not prim.IsA(UsdGeom.Mesh):
            meshes = [str(p.GetPath()) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
            raise MeshError(f"{path}: no Mesh at {prim_path!r}; meshes: {', '.join(meshes) or 'none'}")
        return stage, prim
    prim = next((p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)), None)
    if prim is None:
        raise MeshError(f"{path} holds no UsdGeom.Mesh")
    return stage, prim


def read_usd_point_cache(path, prim_path: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A deforming UsdGeom.Mesh (a point cache) as (times [s], vertices [m] per time (T, V, 3), triangles).

    Every time sample of the points (the stage's start time code is t = 0, timeCodesPerSecond sets the
    rate), in world space with the prim's transform at that time and scaled by metersPerUnit; the
    topology must not change. A mesh without time samples gives one sample at t = 0.
    """
    from pxr import Usd, UsdGeom

    from .cache import fan_triangulate

    path = os.fspath(path)
    stage, prim = _usd_mesh_prim(path, prim_path)
    mesh = UsdGeom.Mesh(prim)
    codes = mesh.GetPointsAttr().GetTimeSamples() or [Usd.TimeCode.Default()]
    scale = UsdGeom.GetStageMetersPerUnit(stage)
    frames = []
    for code in codes:
        p = np.asarray(mesh.GetPointsAttr().Get(code), np.float64)
        if frames and p.shape != frames[0].shape:
            raise MeshError(f"{path}: mesh {prim.GetPath()} changes its point count over time ({len(frames[0])} -> {len(p)})")
        xform = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(code), np.float64)
        frames.append((p @ xform[:3, :3] + xform[3, :3]) * scale)
    if not len(frames[0]):
        raise MeshError(f"{path}: mesh {prim.GetPath()} has no points")
    start, rate = stage.GetStartTimeCode(), stage.GetTimeCodesPerSecond()
    times = np.array([0.0 if isinstance(c, Usd.TimeCode) else (c - start) / rate for c in codes])
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], np.int64)
    if counts.sum() != len(indices):
        raise MeshError(f"{path}: faceVertexCounts sum {counts.sum()} != {len(indices)} faceVertexIndices")
    tris = fan_triangulate(counts, indices)
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        tris = tris[:, ::-1]
    return times, np.stack(frames), np.asarray(tris, np.int64)


def read_usd_mesh(path, prim_path: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a UsdGeom.Mesh as (vertices [m], triangles, per-vertex uvs or None), like :func:`load_mesh_file`.

    Points are taken at the default time (else the earliest sample), moved to world space with the prim's
    transform and scaled by the stage's metersPerUnit; polygons are fan-triangulated and a leftHanded
    mesh is re-wound. A face-varying ``st`` primvar gives every corner its own vertex (welded again by
    position, so seams survive); vertex-interpolated ``st`` is used as is. Points are not rotated for
    the stage's up axis: place the cloth with the builder's rotation.
    """
    from pxr import Usd, UsdGeom

    from .cache import fan_triangulate

    path = os.fspath(path)
    stage, prim = _usd_mesh_prim(path, prim_path)
    mesh = UsdGeom.Mesh(prim)
    time = Usd.TimeCode.Default()
    points = mesh.GetPointsAttr().Get(time)
    if points is None:
        time = Usd.TimeCode.EarliestTime()
        points = mesh.GetPointsAttr().Get(time)
    if points is None or len(points) == 0:
        raise MeshError(f"{path}: mesh {prim.GetPath()} has no points")
    p = np.asarray(points, np.float64)
    xform = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time), np.float64)  # row vectors
    p = p @ xform[:3, :3] + xform[3, :3]
    p *= UsdGeom.GetStageMetersPerUnit(stage)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time) or [], np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time) or [], np.int64)
    if counts.sum() != len(indices):
        raise MeshError(f"{path}: faceVertexCounts sum {counts.sum()} != {len(indices)} faceVertexIndices")
    # Triangulate corner numbers (positions in faceVertexIndices) so face-varying data can follow.
    corner_tris = fan_triangulate(counts, np.arange(len(indices)))
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        corner_tris = corner_tris[:, ::-1]
    st = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
    uv_values = st.ComputeFlattened(time) if st and st.HasValue() else None
    interp = st.GetInterpolation() if uv_values is not None else None
    if uv_values is not None and interp == UsdGeom.Tokens.faceVarying and len(uv_values) == len(indices):
        # One vertex per triangle corner; mesh_topology welds them by position and keeps per-corner UVs.
        corners = corner_tris.reshape(-1)
        return p[indices[corners]], np.arange(len(corners), dtype=np.int64).reshape(-1, 3), np.asarray(uv_values, np.float64)[corners]
    uvs = None
    if uv_values is not None and interp in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying) and len(uv_values) == len(p):
        uvs = np.asarray(uv_values, np.float64)
    elif uv_values is not None:
        log.warning("%s: st primvar with %s interpolation and %d values is not used", path, interp, len(uv_values))
    return p, indices[corner_tris], uvs
