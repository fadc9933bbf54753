"""Fabric materials in SI units, independent of the mesh resolution, and presets.

A material describes the fabric, not the springs: the builder converts it into per-spring constants
with the geometric weights of :mod:`cloth_warp.topology`, so the same material gives the same shape at
16^2, 32^2 or 64^2.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from .validation import LIMITS, check_number

GRAVITY = 9.81
"""Standard gravity used by the presets' derived quantities [m/s^2]."""


# Each value's allowed range (cloth_warp.validation.LIMITS: the same ranges as the scene's [material] keys).
_LIMITS = {"areal_density": LIMITS["areal_density"], "stretch_stiffness": LIMITS["stretch_stiffness"],
           "shear_stiffness": LIMITS["shear_stiffness"], "bend_stiffness": LIMITS["bend_stiffness"],
           "damping": LIMITS["damping_time"], "drag_coefficient": LIMITS["drag_coefficient"]}


@dataclass(frozen=True)
class FabricMaterial:
    """A fabric in SI units.

    Attributes:
        name: label used in scenes and caches.
        areal_density: mass per area rho_A [kg/m^2].
        stretch_stiffness: membrane (in-plane) stiffness, tension per width per unit strain [N/m].
        shear_stiffness: in-plane shear stiffness, shear force per width per radian [N/m].
        bend_stiffness: flexural rigidity per unit width B [N m] (Peirce/ASTM D1388: B = w c^3).
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

    def __post_init__(self):
        for f, limits in _LIMITS.items():
            object.__setattr__(self, f, check_number(f"material {self.name!r} {f}", getattr(self, f), limits))

    def replace(self, **changes) -> FabricMaterial:
        """A copy with some values changed (validated again)."""
        return dataclasses.replace(self, **changes)

    @property
    def bending_length(self) -> float:
        """Peirce bending length c = (B / (rho_A g))^(1/3) [m]."""
        return (self.bend_stiffness / (self.areal_density * GRAVITY)) ** (1.0 / 3.0)


# Sources. Areal densities and bending rigidities: Wang, O'Brien & Ramamoorthi, "Data-driven elastic
# models for cloth", SIGGRAPH 2011 (ArcSim materials/*.json; lowest-curvature bending sample, warp
# direction, read as N m per width; see reference/physics.md 1(b)) and typical Kawabata (KES-FB2)
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
