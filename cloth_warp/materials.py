"""Fabric materials in SI units, independent of the mesh resolution, and presets.

A material describes the fabric, not the springs: the builder converts it into per-spring constants
with the geometric weights of :mod:`cloth_warp.topology`, so the same material gives the same shape at
16^2, 32^2 or 64^2.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from .validation import LIMITS, check_number

GRAVITY = 9.81
"""Standard gravity used by the presets' derived quantities [m/s^2]."""


# Each value's allowed range (cloth_warp.validation.LIMITS: the same ranges as the scene's [material] keys).
_LIMITS = {"areal_density": LIMITS["areal_density"], "stretch_stiffness": LIMITS["stretch_stiffness"],
           "stretch_stiffness_weft": LIMITS["stretch_stiffness"], "shear_stiffness": LIMITS["shear_stiffness"],
           "bend_stiffness": LIMITS["bend_stiffness"], "bend_stiffness_weft": LIMITS["bend_stiffness"],
           "damping": LIMITS["damping_time"], "drag_coefficient": LIMITS["drag_coefficient"]}


@dataclass(frozen=True)
class FabricMaterial:
    """A fabric in SI units; woven fabrics differ along the warp (lengthwise grain) and the weft.

    Where the warp lies on a cloth: the grid's x axis, a mesh's direction of increasing texture u, or an
    explicit direction (:meth:`~cloth_warp.builder.ModelBuilder.add_cloth_mesh`); the weft is
    perpendicular to it in the cloth's plane. Springs are fitted to these values on every cell shape
    and mesh (:mod:`cloth_warp.elasticity`, docs/physics.md section M).

    Attributes:
        name: label used in scenes and caches.
        areal_density: mass per area rho_A [kg/m^2].
        stretch_stiffness: membrane stiffness along the warp, tension per width per unit strain with the
            weft held [N/m] (a free strip measures stretch_stiffness (1 - G^2 / (C_warp C_weft)), within
            0.1 % for cloth).
        stretch_stiffness_weft: the same along the weft [N/m]; None: equal to the warp's.
        shear_stiffness: in-plane shear stiffness G, shear force per width per radian [N/m]; with the
            stretch values it sets the bias (45 deg) stiffness (:meth:`bias_stretch_stiffness`).
        bend_stiffness: flexural rigidity per unit width of a strip cut along the warp, B [N m]
            (Peirce/ASTM D1388: B = w c^3).
        bend_stiffness_weft: the same for a strip cut along the weft [N m]; None: equal to the warp's.
        damping: Kelvin-Voigt relaxation time tau [s]; each stretch/shear spring gets c = tau k.
        drag_coefficient: linear air drag c_A [N s/m^3]: force per area per normal relative speed.
    """

    name: str = "custom"
    areal_density: float = 0.15
    stretch_stiffness: float = 1000.0
    shear_stiffness: float = 20.0
    bend_stiffness: float = 1.0e-5
    damping: float = 0.0
    drag_coefficient: float = 0.0
    stretch_stiffness_weft: float | None = None
    bend_stiffness_weft: float | None = None

    def __post_init__(self):
        for f, limits in _LIMITS.items():
            if getattr(self, f) is not None or not f.endswith("_weft"):
                object.__setattr__(self, f, check_number(f"material {self.name!r} {f}", getattr(self, f), limits))

    @property
    def stretch_weft(self) -> float:
        """Stretch stiffness along the weft [N/m]."""
        return self.stretch_stiffness if self.stretch_stiffness_weft is None else self.stretch_stiffness_weft

    @property
    def bend_weft(self) -> float:
        """Bending rigidity of a strip cut along the weft [N m]."""
        return self.bend_stiffness if self.bend_stiffness_weft is None else self.bend_stiffness_weft

    def stretch_stiffness_at(self, angle_deg: float) -> float:
        """Tensile stiffness of a free strip cut at `angle_deg` from the warp [N/m] (45: the bias)."""
        from .elasticity import membrane_tensor

        return float(membrane_tensor(self).strip(math.radians(angle_deg)))

    def bend_stiffness_at(self, angle_deg: float) -> float:
        """Bending rigidity of a free strip cut at `angle_deg` from the warp [N m] (Huber plate, nu = 1/3)."""
        from .elasticity import plate_tensor

        return float(plate_tensor(self).strip(math.radians(angle_deg)))

    def replace(self, **changes) -> FabricMaterial:
        """A copy with some values changed (validated again)."""
        return dataclasses.replace(self, **changes)

    @property
    def bending_length(self) -> float:
        """Peirce bending length along the warp c = (B / (rho_A g))^(1/3) [m]."""
        return (self.bend_stiffness / (self.areal_density * GRAVITY)) ** (1.0 / 3.0)

    @property
    def bending_length_weft(self) -> float:
        """Peirce bending length along the weft [m]."""
        return (self.bend_weft / (self.areal_density * GRAVITY)) ** (1.0 / 3.0)


# Sources. Areal densities and bending rigidities: Wang, O'Brien & Ramamoorthi, "Data-driven elastic
# models for cloth", SIGGRAPH 2011 (ArcSim materials/*.json; lowest-curvature bending sample, warp
# direction, read as N m per width; see docs/physics.md 1(b)) and typical Kawabata (KES-FB2)
# values for woven shirting/suiting (1 gf cm^2/cm = 9.80665e-5 N m). Shear: KES-FB1 G of 0.5-2
# gf/(cm deg) for wovens (1 gf/(cm deg) = 56.19 N/m per radian), lower for knits. Stretch: the
# low-strain slope of KES-FB1 / strip tensile curves, which is of order 1e2 N/m for knits and 1e3 N/m
# for wovens; these are order-of-magnitude values (fabrics stiffen strongly with strain), kept with
# the strain limiter as the practical bound on stretch. Damping and drag are modelling choices.
PRESETS: dict[str, FabricMaterial] = {
    "cotton": FabricMaterial(
        name="cotton",
        areal_density=0.15,  # shirting cotton, 120-160 g/m^2
        stretch_stiffness=1500.0,  # woven, low-strain KES slope O(1e3) N/m
        shear_stiffness=30.0,  # KES G ~ 0.5 gf/(cm deg)
        bend_stiffness=1.0e-5,  # KES B ~ 0.1 gf cm^2/cm
        damping=2.0e-5,
        drag_coefficient=0.5,
    ),
    "denim": FabricMaterial(
        name="denim",
        areal_density=0.324,  # Wang et al. 2011 "11oz-black-denim": 324 g/m^2
        stretch_stiffness=5000.0,  # heavy twill
        shear_stiffness=100.0,  # KES G ~ 1.8 gf/(cm deg)
        bend_stiffness=6.42e-5,  # Wang et al. 2011: 64.2e-6 (warp)
        damping=2.0e-5,
        drag_coefficient=0.5,
    ),
    "silk": FabricMaterial(
        name="silk",
        areal_density=0.06,  # crepe de chine, 50-70 g/m^2
        stretch_stiffness=500.0,
        shear_stiffness=5.0,  # KES G ~ 0.1 gf/(cm deg)
        bend_stiffness=2.0e-6,  # KES B ~ 0.02 gf cm^2/cm
        damping=2.0e-5,
        drag_coefficient=0.5,
    ),
    "polyester": FabricMaterial(
        name="polyester",
        areal_density=0.113,  # Wang et al. 2011 "tango-red-jet-set" (100 % poly): 113 g/m^2
        stretch_stiffness=1200.0,
        shear_stiffness=15.0,
        bend_stiffness=1.43e-5,  # Wang et al. 2011: 14.3e-6 (warp)
        damping=2.0e-5,
        drag_coefficient=0.5,
    ),
    "knit": FabricMaterial(
        name="knit",
        areal_density=0.276,  # Wang et al. 2011 "ivory-rib-knit": 276 g/m^2
        stretch_stiffness=200.0,  # knits are soft in extension
        shear_stiffness=5.0,
        bend_stiffness=4.62e-5,  # Wang et al. 2011: 46.2e-6 (warp)
        damping=2.0e-5,
        drag_coefficient=0.5,
    ),
    "wool": FabricMaterial(
        name="wool",
        areal_density=0.25,  # worsted suiting, 220-280 g/m^2
        stretch_stiffness=1500.0,
        shear_stiffness=35.0,  # KES G ~ 0.6 gf/(cm deg)
        bend_stiffness=1.0e-5,  # KES B ~ 0.1 gf cm^2/cm
        damping=2.0e-5,
        drag_coefficient=0.5,
    ),
}


def preset(name: str) -> FabricMaterial:
    """The preset called `name` (case-insensitive); the error lists the known names."""
    key = name.strip().lower()
    if key not in PRESETS:
        raise KeyError(f"unknown material preset {name!r}; known presets: {', '.join(sorted(PRESETS))}")
    return PRESETS[key]


COTTON = PRESETS["cotton"]
DENIM = PRESETS["denim"]
SILK = PRESETS["silk"]
POLYESTER = PRESETS["polyester"]
KNIT = PRESETS["knit"]
WOOL = PRESETS["wool"]
