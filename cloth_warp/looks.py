"""How a cache looks in a DCC tool: a colour per fabric and per kind of collider, as UsdPreviewSurface materials.

Blender, Houdini, Maya, usdview and Omniverse all render ``UsdPreviewSurface``; ``displayColor`` is what
viewports without materials show. Each cloth is bound to its fabric's material and colliders to theirs, so cloth,
body and ground do not all render the same grey.
"""

from __future__ import annotations

import hashlib

import numpy as np

# linear RGB in [0, 1], a dyed look per preset (cloth_warp.materials.PRESETS)
FABRIC_COLORS: dict[str, tuple[float, float, float]] = {
    "cotton": (0.80, 0.76, 0.68),  # unbleached shirting
    "denim": (0.10, 0.17, 0.36),  # indigo
    "silk": (0.78, 0.52, 0.58),  # dusty rose
    "polyester": (0.72, 0.12, 0.10),  # tango red (Wang et al. 2011's jacket)
    "knit": (0.86, 0.83, 0.72),  # ivory rib knit
    "wool": (0.22, 0.22, 0.25),  # charcoal suiting
    "royal-target": (0.12, 0.22, 0.62),  # royal blue
    "white-dots-on-blk": (0.06, 0.06, 0.07),  # black
}

COLLIDER_COLORS: dict[str, tuple[float, float, float]] = {
    "ground": (0.32, 0.33, 0.35),  # planes
    "solid": (0.60, 0.62, 0.66),  # spheres, boxes, capsules, cylinders, rigid meshes
    "body": (0.78, 0.60, 0.50),  # deforming meshes (point-cache bodies)
}

ROUGHNESS = {"fabric": 0.85, "ground": 0.9, "solid": 0.5, "body": 0.6}


def fabric_color(name: str) -> tuple[float, float, float]:
    """The colour of a fabric preset, or a stable muted colour derived from a custom material's name."""
    if name in FABRIC_COLORS:
        return FABRIC_COLORS[name]
    h = hashlib.sha1(name.encode()).digest()
    hue = h[0] / 255.0
    k = np.array([0.0, 2.0 / 3.0, 1.0 / 3.0])
    rgb = 0.55 + 0.25 * np.cos(2.0 * np.pi * (hue + k))  # muted, never black or white
    return tuple(float(c) for c in rgb)


def collider_look(shape: str, deforming: bool) -> str:
    """The look of a collider: "ground" (planes), "body" (deforming meshes) or "solid"."""
    if shape == "plane":
        return "ground"
    return "body" if deforming else "solid"


def define_material(stage, path: str, color, roughness: float):
    """A UsdShade Material at `path` with a UsdPreviewSurface shader of that diffuse colour and roughness."""
    from pxr import Gf, Sdf, UsdShade

    material = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/PreviewSurface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*map(float, color)))
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(roughness))
    shader.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return material


def bind_look(geom, material, color) -> None:
    """Bind `material` to the gprim `geom` and set its displayColor to the same colour."""
    from pxr import UsdShade, Vt

    UsdShade.MaterialBindingAPI.Apply(geom.GetPrim()).Bind(material)
    geom.CreateDisplayColorAttr(Vt.Vec3fArray.FromNumpy(np.array([color], np.float32)))
