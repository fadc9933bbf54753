"""Fabric materials in SI units, independent of the mesh resolution, and presets.

A material describes the fabric, not the springs: the builder converts it into per-spring constants
with the geometric weights of :mod:`cloth_warp.topology`, so the same material gives the same shape at
16^2, 32^2 or 64^2.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from .validation import LIMITS, InvalidValue, check_number

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
        # The membrane tensor couples warp and weft by G (C_12 = C_66 = G, elasticity.membrane_tensor): positive
        # definite only while G^2 < C_warp C_weft. Beyond it a stretched sheet gains energy by shrinking across
        # (the element's forces grow from round-off on a sheet at rest; the spring fit silently clips).
        limit = math.sqrt(self.stretch_stiffness * self.stretch_weft)
        if not self.shear_stiffness < limit:
            raise InvalidValue(f"material {self.name!r} shear_stiffness: {self.shear_stiffness:g} N/m must be below "
                               f"sqrt(stretch_stiffness x stretch_stiffness_weft) = {limit:.4g} N/m (a stiffer shear "
                               "makes the membrane unstable); lower it or raise the stretch stiffness")

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


# Published warp/weft measurements: Wang, O'Brien & Ramamoorthi, "Data-driven elastic models for cloth:
# modeling and measurement", ACM Trans. Graph. 30(4):71 (SIGGRAPH 2011), as shipped with ArcSim 0.3.1
# (materials/<fabric>.json, github.com/zhou13/arcsim commit 639ea0062d3a18101a87b568b49f26259635967b;
# fibre and use from its materials/README). Per fabric: areal density [kg/m^2]; the zero-strain stretching
# sample (c11, c12, c22, c33) in ArcSim's raw units [N/m]; the lowest-curvature bending sample of the
# 0, 45 and 90 deg rows [N m]. The unit analysis and its doubts are in docs/fabric-measurements.md.
# navy-sparkle-sweat is left out: its shear c33 exceeds sqrt(2 c11 2 c22), so no positive-definite
# membrane with these values exists in cloth_warp's spring lattice.
WANG_2011: dict[str, dict] = {
    "11oz-black-denim": dict(fibre="99 % cotton 1 % spandex (jeans)", density=0.324,
                             stretching=(205.352005, 10.234077, 1013.88629, 53.387184),
                             bending=(64.196457e-6, 73.384567e-6, 96.951576e-6)),
    "camel-ponte-roma": dict(fibre="60 % polyester 40 % rayon (jacket, knit)", density=0.284,
                             stretching=(31.146198, -12.802702, 44.028667, 31.896357),
                             bending=(36.348366e-6, 33.013252e-6, 37.157593e-6)),
    "gray-interlock": dict(fibre="60 % cotton 40 % polyester (t-shirt, knit)", density=0.187,
                           stretching=(16.593832, -14.695990, 34.477123, 36.860302),
                           bending=(23.191698e-6, 24.749964e-6, 14.267624e-6)),
    "ivory-rib-knit": dict(fibre="95 % cotton 5 % spandex (underwear, knit)", density=0.276,
                           stretching=(42.871021, -0.234556, 65.166023, 83.175644),
                           bending=(46.237591e-6, 30.015930e-6, 32.243889e-6)),
    "pink-ribbon-brown": dict(fibre="100 % polyester (blanket)", density=0.228,
                              stretching=(151.503906, 106.028160, 244.830673, 30.250183),
                              bending=(117.070122e-6, 87.509773e-6, 59.774277e-6)),
    "royal-target": dict(fibre="65 % cotton 35 % polyester (pants)", density=0.220,
                         stretching=(2016.55456, 9.170511, 2034.97644, 104.759674),
                         bending=(125.409805e-6, 107.997696e-6, 125.409805e-6)),
    "tango-red-jet-set": dict(fibre="100 % polyester (jacket)", density=0.113,
                              stretching=(43.067627, 54.373299, 171.424835, 14.314700),
                              bending=(14.293814e-6, 21.951700e-6, 20.345654e-6)),
    "white-dots-on-blk": dict(fibre="100 % polyester (tablecloth)", density=0.128,
                              stretching=(2002.08618, 0.345588, 2027.48559, 19.189022),
                              bending=(51.713814e-6, 40.659470e-6, 31.282822e-6)),
    "white-swim-solid": dict(fibre="87 % nylon 13 % spandex (swimsuit)", density=0.204,
                             stretching=(47.971176, 6.834521, 104.615456, 60.773663),
                             bending=(60.237942e-6, 58.803211e-6, 51.018833e-6)),
}


def wang_2011_material(fabric: str, name: str | None = None, **modelling) -> FabricMaterial:
    """A material from :data:`WANG_2011` in this convention (docs/fabric-measurements.md section 4):

    * warp = ArcSim's material u axis ("0 deg"), weft = v ("90 deg"); which of them is the fabric's warp
      (or, for knits, wale) is not stated by the source (unverified);
    * stretch = the tensile stiffness ArcSim simulates with, k = 2 c (c11 along u, c22 along v, zero-strain
      sample); the raw c is half of it (whether the paper's c is the 2c is unverified);
    * shear G = c33 (ArcSim's force: d^2 W / d gamma^2 = c33 per radian); c12 is not used (a spring
      lattice's coupling is G, Cauchy's relation; docs/physics.md section M);
    * bending of a strip cut along the warp = the 90 deg row, along the weft = the 0 deg row: ArcSim picks
      the row by the direction of the hinge (fold line) in material space (dde.cpp bending_stiffness), and a
      strip along u bends about hinges running along v.
    """
    d = WANG_2011[fabric]
    c11, _, c22, c33 = d["stretching"]
    b0, _, b90 = d["bending"]
    return FabricMaterial(name=name or fabric, areal_density=d["density"], stretch_stiffness=2.0 * c11,
                          stretch_stiffness_weft=2.0 * c22, shear_stiffness=c33, bend_stiffness=b90,
                          bend_stiffness_weft=b0, **modelling)


# Modelling choices, not measurements: Kelvin-Voigt damping time and linear air drag of every preset.
_MODELLING = dict(damping=2.0e-5, drag_coefficient=0.5)

# Isotropic presets (no warp/weft data for these fabrics): typical Kawabata (KES-FB) values for woven
# shirting/suiting (1 gf cm^2/cm = 9.80665e-5 N m; shear G of 0.5-2 gf/(cm deg) for wovens, 1 gf/(cm deg)
# = 56.19 N/m per radian, lower for knits). Stretch: the low-strain slope of KES-FB1 / strip tensile
# curves, of order 1e3 N/m for wovens; order-of-magnitude values (fabrics stiffen strongly with strain),
# kept with the strain limiter as the practical bound on stretch.
# Woven/knit presets with warp/weft data: Wang et al. 2011 through wang_2011_material (convention above).
PRESETS: dict[str, FabricMaterial] = {
    "cotton": FabricMaterial(
        name="cotton",
        areal_density=0.15,  # shirting cotton, 120-160 g/m^2
        stretch_stiffness=1500.0,  # woven, low-strain KES slope O(1e3) N/m
        shear_stiffness=30.0,  # KES G ~ 0.5 gf/(cm deg)
        bend_stiffness=1.0e-5,  # KES B ~ 0.1 gf cm^2/cm
        **_MODELLING,
    ),
    # Wang et al. 2011 "11oz-black-denim": warp/weft stretch 411 / 2028 N/m, shear 53.4 N/m, bending
    # 9.70e-5 / 6.42e-5 N m, 0.324 kg/m^2 (the warp/weft labels: see wang_2011_material).
    "denim": wang_2011_material("11oz-black-denim", "denim", **_MODELLING),
    "silk": FabricMaterial(
        name="silk",
        areal_density=0.06,  # crepe de chine, 50-70 g/m^2
        stretch_stiffness=500.0,
        shear_stiffness=5.0,  # KES G ~ 0.1 gf/(cm deg)
        bend_stiffness=2.0e-6,  # KES B ~ 0.02 gf cm^2/cm
        **_MODELLING,
    ),
    # Wang et al. 2011 "tango-red-jet-set" (100 % polyester jacket): 86 / 343 N/m, 14.3 N/m,
    # 2.03e-5 / 1.43e-5 N m, 0.113 kg/m^2. Its measured u-v coupling (2 c12 = 109 N/m) is not kept.
    "polyester": wang_2011_material("tango-red-jet-set", "polyester", **_MODELLING),
    # Wang et al. 2011 "ivory-rib-knit" (95/5 cotton/spandex): 86 / 130 N/m, 83.2 N/m, 3.22e-5 /
    # 4.62e-5 N m, 0.276 kg/m^2; warp/weft stand for the knit's u/v (wale/course unknown). Its shear is
    # high beside its stretch: a free strip measures only 0.38 x the stretch value (1 - G^2/(C_w C_f)).
    "knit": wang_2011_material("ivory-rib-knit", "knit", **_MODELLING),
    "wool": FabricMaterial(
        name="wool",
        areal_density=0.25,  # worsted suiting, 220-280 g/m^2
        stretch_stiffness=1500.0,
        shear_stiffness=35.0,  # KES G ~ 0.6 gf/(cm deg)
        bend_stiffness=1.0e-5,  # KES B ~ 0.1 gf cm^2/cm
        **_MODELLING,
    ),
    # Presets named after two more of Wang et al.'s measured fabrics (same convention):
    # "royal-target" (65/35 cotton/polyester pants): 4033 / 4070 N/m, 104.8 N/m, 1.25e-4 / 1.25e-4 N m,
    # 0.220 kg/m^2; "white-dots-on-blk" (polyester tablecloth): 4004 / 4055 N/m, 19.2 N/m,
    # 3.13e-5 / 5.17e-5 N m, 0.128 kg/m^2. Both stretch rows sit near 2000 raw, which may be a bound of the
    # fit rather than a measurement (docs/fabric-measurements.md 1.2).
    "royal-target": wang_2011_material("royal-target", **_MODELLING),
    "white-dots-on-blk": wang_2011_material("white-dots-on-blk", **_MODELLING),
}

WANG_2011_PRESETS = {"denim": "11oz-black-denim", "polyester": "tango-red-jet-set", "knit": "ivory-rib-knit",
                     "royal-target": "royal-target", "white-dots-on-blk": "white-dots-on-blk"}
"""The presets taken from :data:`WANG_2011`: preset name -> measured fabric."""


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
