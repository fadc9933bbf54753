"""Calibrate a fabric material from standard measurements (``cloth-warp calibrate``).

A :class:`FabricMeasurements` (a TOML file, checked at one gate that names the key path) holds what a textile
lab reports:

* ``fabric.areal_density`` [kg/m^2];
* ``bending``: the ASTM D1388 cantilever bending length c [m] of a strip cut along the warp and one cut along
  the weft (``length_warp``, ``length_weft``), or the flexural rigidity B [N m] itself (``rigidity_warp``,
  ``rigidity_weft``; D1388 defines B = w c^3, w = rho_A g);
* ``tensile``: the low-strain tensile stiffness of a free strip, tension per width per unit strain [N/m],
  cut along the warp and the weft (``warp``, ``weft``), optionally along the bias (``bias``, 45 deg);
* optionally ``shear.stiffness`` G [N/m per radian] (KES-FB1), used as given (not with ``tensile.bias``);
* optionally ``drape``: a Cusick drape coefficient and its set-up (specimen and pedestal radii), *reported*
  for the calibrated material on scenes/cusick.toml, not fitted.

:func:`calibrate` runs each test in the simulator, on scenes it generates, and fits the material so that the
simulated test gives the measured value on the simulator's own discretisation:

* bending: the D1388 cantilever (as scenes/fit_cantilever.toml): a strip clamped by its first two columns,
  overhang 2c, must droop to a chord angle of 41.5 deg (the heavy elastica's angle at l = 2c) from the clamp
  edge to the tip; one strip with the warp along it, one with the weft along it (``cloth.warp_angle`` 90);
  fits ``material.bend_stiffness`` and ``material.bend_stiffness_weft``;
* tension: a strip of length :data:`TENSILE_LENGTH` hangs from a clamped top edge, loaded by its own weight
  under a test gravity chosen so the measured stiffness strains its top by :data:`TENSILE_STRAIN`; its
  centroid must drop as far as the ideal strip's, u(s) = rho_A g (L s - s^2 / 2) / C (s from the clamp),
  averaged over the particles with the centroid's weights; warp, weft (and bias: ``cloth.warp_angle`` 45)
  strips fit ``material.stretch_stiffness``, ``material.stretch_stiffness_weft`` (and ``shear_stiffness``).

Closed forms give only the start: B = w c^3 (Peirce), stretch stiffness = the measured strip stiffness, the
shear stiffness that gives the measured bias stiffness in the continuum (``elasticity.membrane_tensor``). The
simulated tests differ from the closed forms by the discretisation (springs fitted per cell, the clamp, lumped
masses, a strip's width: see :data:`CANTILEVER_WIDTH`; 0.1-0.3 % in the strip stiffnesses of denim, 6 % in G from a
bias strip), which the fit removes.

The fit: each test is a :class:`~cloth_warp.fitting.SceneFit` (adjoint gradients through the implicit solve at
:data:`~cloth_warp.fitting.FIT_TOLERANCE`, the chain rule to the material keys by exact model builds). The
problem is square (one measurement per fitted value) and each loss is a squared residual, L_i = r_i^2, so
dL_i / dp_j = 2 r_i dr_i / dp_j gives the Jacobian of the residuals from the gradients SceneFit computes, and
Gauss-Newton in log space (steps clipped to :data:`MAX_LOG_STEP`) converges in a few evaluations; the tests
of one block (bending; tension) are solved together, with the cross terms (a weft bending rigidity changes a
warp strip through the plate's twist term; the shear stiffness changes every free strip's stiffness). Tension
is fitted first, so the cantilevers bend the fitted membrane.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import time
import tomllib
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from .materials import GRAVITY, PRESETS, FabricMaterial
from .scene import Key, SceneError, _check, parse_scene, read_scene_text
from .validation import LIMITS, Range

if TYPE_CHECKING:
    from .fitting import FitSolverTolerance, SceneFit

CHORD_ANGLE = 41.5
"""ASTM D1388: the chord angle [deg] below horizontal at an overhang of twice the bending length."""
CANTILEVER_SEGMENTS = 20
"""Cells along a cantilever's overhang (clamped by one more column)."""
CANTILEVER_WIDTH = 1.0 / 20.0
"""Width of the cantilever strip as a share of its overhang (2 cells across, cells 2:1). The simulated strip droops more
the wider it is: at the closed-form B (denim, warp 6.42e-5 / weft 9.7e-5 N m, 20 cells along) its chord angle says B
is 0.05 / 0.03 % off at a width of l/20, 0.9 / 2.4 % at l/10 and 4 / 7 % at l/5 (20 x 4 square cells), so the
calibration uses a narrow strip: the beam of Peirce's analysis, whose rigidity is the material's bend_stiffness (a free
strip's, :class:`~cloth_warp.materials.FabricMaterial`)."""
TENSILE_LENGTH = 0.1
"""Free length of the simulated tensile strip [m] (width a tenth of it, 2 cells across)."""
TENSILE_SEGMENTS = 20
"""Cells along the tensile strip."""
TENSILE_STRAIN = 0.01
"""Strain at the clamp of the hanging strip under its test gravity (the low-strain slope); the test gravity is
capped by validation.LIMITS["gravity"], which lowers the strain of very stiff fabrics."""
SETTLE_FRAMES, SETTLE_FPS = 20, 5.0
"""Each test settles for 4 s at 0.2 s steps (implicit Euler, mass-proportional damping 2 /s): the chord angle
then changes by less than 1e-4 deg from 40 frames at 10 fps."""
MAX_LOG_STEP = 1.0
"""Largest Gauss-Newton step of a value per iteration, in log space (a factor e = 2.7)."""
TOLERANCE = 1.0e-3
"""A block stops once every measurement's relative error is below this."""
ITERATIONS = 8
"""Default most Gauss-Newton iterations (simulations with gradient) per block."""

DRAPE_COEFFICIENT = Range(0.0, 1.0)
_POSITIVE_BEND = dataclasses.replace(LIMITS["bend_stiffness"], lo=1e-12)

# The measurements file's schema (the scene schema's Key, checked by the scene's gate: type, range, unknown keys).
SCHEMA: dict = {
    "fabric": {
        "name": Key("str", "calibrated", "label of the material"),
        "preset": Key("str", "cotton", "preset for what is not measured (damping, drag; shear without a shear or bias "
                      "value)", allowed=tuple(PRESETS)),
        "areal_density": Key("float", None, "mass per area (required)", LIMITS["areal_density"]),
    },
    "bending": {
        "length_warp": Key("float", None, "ASTM D1388 bending length c of a strip cut along the warp", LIMITS["length"]),
        "length_weft": Key("float", None, "the same along the weft", LIMITS["length"]),
        "rigidity_warp": Key("float", None, "flexural rigidity B = w c^3 along the warp, instead of length_warp", _POSITIVE_BEND),
        "rigidity_weft": Key("float", None, "the same along the weft, instead of length_weft", _POSITIVE_BEND),
    },
    "tensile": {
        "warp": Key("float", None, "strip tensile stiffness along the warp (low-strain slope, tension per width per "
                    "strain; required)", LIMITS["stretch_stiffness"]),
        "weft": Key("float", None, "the same along the weft (required)", LIMITS["stretch_stiffness"]),
        "bias": Key("float", None, "the same for a strip cut at 45 deg: fits the shear stiffness", LIMITS["stretch_stiffness"]),
    },
    "shear": {
        "stiffness": Key("float", None, "in-plane shear stiffness G (KES-FB1), used as given", LIMITS["shear_stiffness"]),
    },
    "drape": {
        "coefficient": Key("float", None, "measured Cusick drape coefficient (reported for the calibrated material, "
                           "not fitted)", DRAPE_COEFFICIENT),
        "disc_radius": Key("float", 0.15, "specimen radius", LIMITS["length"]),
        "pedestal_radius": Key("float", 0.09, "pedestal radius", LIMITS["length"]),
    },
}


class MeasurementError(SceneError):
    """A measurements file that cannot be used; the message names the key path (exit code 2)."""


@dataclasses.dataclass(frozen=True)
class DrapeSetup:
    """A Cusick drape measurement (BS 5058 / ISO 9073-9) and its set-up."""

    coefficient: float
    """Measured drape coefficient (A_shadow - A_pedestal) / (A_disc - A_pedestal)."""
    disc_radius: float = 0.15
    """Specimen radius [m]."""
    pedestal_radius: float = 0.09
    """Pedestal radius [m]."""


@dataclasses.dataclass(frozen=True)
class FabricMeasurements:
    """Standard measurements of a fabric (SI units); read with :func:`read_measurements` or :func:`parse_measurements`.

    A bending measurement is given as a bending length c [m] (ASTM D1388) or as the flexural rigidity B = w c^3
    [N m], w = areal_density x g; :attr:`bending_length` returns c either way.
    """

    areal_density: float
    """Mass per area rho_A [kg/m^2]."""
    tensile_warp: float
    """Strip tensile stiffness along the warp [N/m] (tension per width per unit strain, free to contract)."""
    tensile_weft: float
    """The same along the weft [N/m]."""
    bending_length_warp: float | None = None
    """ASTM D1388 bending length of a strip cut along the warp [m]."""
    bending_length_weft: float | None = None
    """The same along the weft [m]."""
    rigidity_warp: float | None = None
    """Flexural rigidity along the warp [N m], instead of the bending length."""
    rigidity_weft: float | None = None
    """The same along the weft [N m]."""
    tensile_bias: float | None = None
    """Strip tensile stiffness at 45 deg [N/m]; fits the shear stiffness."""
    shear_stiffness: float | None = None
    """Shear stiffness G [N/m per radian], used as given."""
    drape: DrapeSetup | None = None
    """A Cusick drape measurement, reported (not fitted)."""
    name: str = "calibrated"
    """Label of the calibrated material."""
    preset: str = "cotton"
    """Preset for the values not measured (damping, drag; shear without a shear or bias value)."""
    source: str | None = None
    """The file read, for reports."""

    def __post_init__(self):  # the API's gate: the same checks as the file's
        _check_measurements(self.table(), self.source or "measurements")

    def table(self) -> dict:
        """The measurements as the file's tables (:data:`SCHEMA`); values not given are left out."""
        data = {"fabric": {"name": self.name, "preset": self.preset, "areal_density": self.areal_density},
                "bending": {k: getattr(self, a) for k, a in (("length_warp", "bending_length_warp"), ("length_weft", "bending_length_weft"),
                                                             ("rigidity_warp", "rigidity_warp"), ("rigidity_weft", "rigidity_weft"))
                            if getattr(self, a) is not None},
                "tensile": {k: v for k, v in (("warp", self.tensile_warp), ("weft", self.tensile_weft), ("bias", self.tensile_bias))
                            if v is not None}}
        if self.shear_stiffness is not None:
            data["shear"] = {"stiffness": self.shear_stiffness}
        if self.drape is not None:
            data["drape"] = dataclasses.asdict(self.drape)
        return data

    def bending_length(self, direction: str) -> float:
        """Bending length c [m] along "warp" or "weft" (from B: c = (B / w)^(1/3))."""
        c = getattr(self, f"bending_length_{direction}")
        return c if c is not None else (getattr(self, f"rigidity_{direction}") / (self.areal_density * GRAVITY)) ** (1.0 / 3.0)

    def bending_key(self, direction: str) -> str:
        """The measurement's key path: bending.length_<direction> or bending.rigidity_<direction>."""
        return f"bending.length_{direction}" if getattr(self, f"bending_length_{direction}") is not None else f"bending.rigidity_{direction}"

    def to_toml(self) -> str:
        """The measurements as a measurements file (read back by :func:`parse_measurements`)."""
        import tomli_w

        return tomli_w.dumps(self.table())

    @classmethod
    def of_material(cls, material: FabricMaterial, *, bias: bool = False, **kwargs) -> FabricMeasurements:
        """The measurements an ideal (continuum) specimen of `material` gives: Peirce's c = (B / w)^(1/3), the free
        strip's stiffness of the membrane tensor (:meth:`FabricMaterial.stretch_stiffness_at`); with `bias`, the
        45 deg strip's instead of the shear stiffness. For tests and for measurement files of presets."""
        return cls(areal_density=material.areal_density, tensile_warp=material.stretch_stiffness_at(0.0),
                   tensile_weft=material.stretch_stiffness_at(90.0), bending_length_warp=material.bending_length,
                   bending_length_weft=material.bending_length_weft,
                   tensile_bias=material.stretch_stiffness_at(45.0) if bias else None,
                   shear_stiffness=None if bias else material.shear_stiffness, **kwargs)


def _check_measurements(data: dict, where: str):
    """The gate: types, ranges and unknown keys by the scene's checker, then the keys that depend on each other."""
    try:
        _check(data, SCHEMA, "")
    except SceneError as exc:
        raise MeasurementError(f"{where}: {exc}") from None

    def need(table, key, why):
        if data.get(table, {}).get(key) is None:
            raise MeasurementError(f"{where}: {table}.{key}: required ({why})")

    need("fabric", "areal_density", f"mass per area [kg/m^2], {SCHEMA['fabric']['areal_density'].limits}")
    for d in ("warp", "weft"):
        bend = data.get("bending", {})
        given = [k for k in (f"length_{d}", f"rigidity_{d}") if k in bend]
        if not given:
            raise MeasurementError(f"{where}: bending.length_{d}: required (the ASTM D1388 bending length [m]), "
                                   f"or bending.rigidity_{d} [N m]")
        if len(given) > 1:
            raise MeasurementError(f"{where}: bending.{given[1]}: give the bending length or the rigidity along the {d}, not both")
        need("tensile", d, "strip tensile stiffness [N/m]")
    if data.get("tensile", {}).get("bias") is not None and data.get("shear", {}).get("stiffness") is not None:
        raise MeasurementError(f"{where}: shear.stiffness: give tensile.bias (fitted) or shear.stiffness (used as given), not both")
    drape = data.get("drape")
    if drape is not None:
        if "coefficient" not in drape:
            raise MeasurementError(f"{where}: drape.coefficient: required in a [drape] table")
        if drape.get("pedestal_radius", 0.09) >= drape.get("disc_radius", 0.15):
            raise MeasurementError(f"{where}: drape.pedestal_radius: must be below drape.disc_radius")


def parse_measurements(text: str, path=None) -> FabricMeasurements:
    """Measurements from TOML text (see :data:`SCHEMA`); a :class:`MeasurementError` names the key path."""
    where = str(path) if path else "measurements"
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise MeasurementError(f"{where}: TOML syntax error: {exc}") from None
    _check_measurements(data, where)
    fabric, bend, tens = data["fabric"], data.get("bending", {}), data["tensile"]
    drape = data.get("drape")
    return FabricMeasurements(
        areal_density=float(fabric["areal_density"]), tensile_warp=float(tens["warp"]), tensile_weft=float(tens["weft"]),
        bending_length_warp=bend.get("length_warp"), bending_length_weft=bend.get("length_weft"),
        rigidity_warp=bend.get("rigidity_warp"), rigidity_weft=bend.get("rigidity_weft"), tensile_bias=tens.get("bias"),
        shear_stiffness=data.get("shear", {}).get("stiffness"),
        drape=None if drape is None else DrapeSetup(**{k: float(v) for k, v in drape.items()}),
        name=fabric.get("name", SCHEMA["fabric"]["name"].default), preset=fabric.get("preset", SCHEMA["fabric"]["preset"].default),
        source=str(path) if path else None)


def read_measurements(path) -> FabricMeasurements:
    """Read and check a measurements TOML file."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise MeasurementError(f"measurements file not found: {path}")
    try:
        text = read_scene_text(path)
    except SceneError as exc:
        raise MeasurementError(str(exc)) from None
    return parse_measurements(text, path)


# -- results ------------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class MeasurementFit:
    """One measurement: its target, the simulated test's value at the calibrated material, and the relative error."""

    key: str
    """The measurement's key path in the measurements file (``bending.length_warp``)."""
    unit: str
    target: float
    """The measured value [unit]."""
    simulated: float
    """The simulated test's value at the calibrated material [unit]."""
    relative_error: float
    """simulated / target - 1."""
    test: str
    """The simulated test, in words."""
    observable: str
    """What the simulated test measures (``chord_angle_deg``, ``centroid_drop_m``, ``drape_coefficient``)."""
    observable_target: float
    observable_simulated: float
    parameter: str | None
    """The material key this measurement fits; None: reported only."""


@dataclasses.dataclass
class CalibrationResult:
    """What :func:`calibrate` found: the material, each measurement against its simulated test, cost and solver."""

    material: FabricMaterial
    """The calibrated material."""
    initial: dict
    """The closed-form start of each fitted key (``material.bend_stiffness``: Peirce's w c^3, ...)."""
    measurements: list[MeasurementFit]
    iterations: int
    """Simulations with gradient, all blocks together."""
    wall_s: float
    """Wall time [s]."""
    solver_tolerance: FitSolverTolerance
    """The implicit solve's tolerance during the fits and why (:class:`~cloth_warp.fitting.FitSolverTolerance`)."""
    status: str
    """``converged`` (every fitted measurement within :data:`TOLERANCE`) or ``not converged``."""
    notes: list[str] = dataclasses.field(default_factory=list)
    """Where each value not fitted came from."""
    source: str | None = None
    """The measurements file."""
    material_preset: str = "cotton"
    """The preset the values not measured came from (named in fabric.toml's [material] table)."""

    def report(self) -> dict:
        return dataclasses.asdict(self)

    def material_values(self) -> dict:
        """The [material] table of a scene (every value explicit; the preset only names the base)."""
        m = self.material
        return {"preset": self.material_preset, "areal_density": m.areal_density, "stretch_stiffness": m.stretch_stiffness,
                "stretch_stiffness_weft": m.stretch_weft, "shear_stiffness": m.shear_stiffness, "bend_stiffness": m.bend_stiffness,
                "bend_stiffness_weft": m.bend_weft, "damping": m.damping, "drag_coefficient": m.drag_coefficient}

    def material_toml(self) -> str:
        """fabric.toml: a [material] table a scene loads with ``[material] file = "fabric.toml"``, with a header."""
        import tomli_w

        lines = [f"# {self.material.name}: calibrated by cloth-warp calibrate"
                 + (f" from {pathlib.Path(self.source).name}" if self.source else ""),
                 "# Use in a scene:  [material] file = \"<this file>\"  (relative to the scene; the scene's [material] keys override these)"]
        for m in self.measurements:
            how = "fitted" if m.parameter else "reported, not fitted"
            lines.append(f"#   {m.key} = {m.target:.6g} {m.unit}: simulated {m.simulated:.6g} ({100 * m.relative_error:+.2f} %, {how})")
        lines.extend(f"#   {n}" for n in self.notes)
        return "\n".join(lines) + "\n\n" + tomli_w.dumps({"material": self.material_values()})


# -- the simulated tests ----------------------------------------------------------------------------------------

def _test_material(material: FabricMaterial) -> dict:
    """A [material] table of every value (statics: no Kelvin-Voigt damping, no drag)."""
    return {"areal_density": material.areal_density, "stretch_stiffness": material.stretch_stiffness,
            "stretch_stiffness_weft": material.stretch_weft, "shear_stiffness": material.shear_stiffness,
            "bend_stiffness": material.bend_stiffness, "bend_stiffness_weft": material.bend_weft, "damping": 0.0, "drag_coefficient": 0.0}


def _solver_table() -> dict:
    return {"integrator": "implicit_euler", "substeps": 1, "strain_limit": 0, "tolerance": 1e-4, "max_iterations": 2000}


def cantilever_scene(material: FabricMaterial, bending_length: float, direction: str, segments: int = CANTILEVER_SEGMENTS):
    """The ASTM D1388 test of a strip cut along `direction` ("warp" or "weft") as a scene: horizontal along +x, clamped by
    its first two columns (x <= 0), overhang 2c in `segments` cells, :data:`CANTILEVER_WIDTH` of it wide in 2 cells;
    target: the chord from the clamp edge (the origin) to the free edge at 41.5 deg below horizontal after
    :data:`SETTLE_FRAMES` frames."""
    import tomli_w

    overhang = 2.0 * bending_length
    a = overhang / segments
    data = {"scene": {"description": f"ASTM D1388 cantilever, {direction} strip, overhang {1e3 * overhang:.1f} mm"},
            "cloth": {"grid": {"resolution": [segments + 1, 2], "size": [overhang + a, CANTILEVER_WIDTH * overhang]},
                      "position": [-a, 0.0, 0.0], "rotation": {"axis": [1.0, 0.0, 0.0], "angle": 90.0}, "warp_angle": 0.0 if direction == "warp" else 90.0},
            "material": _test_material(material),
            "pins": [{"box": {"min": [-1.0, -1.0, -1.0], "max": [1e-3 * a, 1.0, 1.0]}}],
            "forces": {"global_damping": 2.0},
            "solver": _solver_table(),
            "fit": {"target": {"chord_angle": CHORD_ANGLE, "chord_origin": [0.0, 0.0, 0.0], "tip": {"select": "edge:right"}}},
            "output": {"frames": SETTLE_FRAMES, "fps": SETTLE_FPS}}
    return parse_scene(tomli_w.dumps(data))


def tensile_gravity(material_density: float, stiffness: float) -> float:
    """The test gravity [m/s^2] that strains the hanging strip's top by :data:`TENSILE_STRAIN` at `stiffness` [N/m]."""
    return min(TENSILE_STRAIN * stiffness / (material_density * TENSILE_LENGTH), float(LIMITS["gravity"].hi))


def tensile_scene(material: FabricMaterial, angle: float, gravity: float, segments: int = TENSILE_SEGMENTS):
    """A strip cut at `angle` [deg] from the warp, hanging from its clamped top edge (y = 0) down to y = -L, under
    gravity `gravity` [m/s^2]; no target in the scene (:func:`calibrate` gives a centroid)."""
    import tomli_w

    a = TENSILE_LENGTH / segments
    data = {"scene": {"description": f"strip tensile test at {angle:g} deg from the warp, test gravity {gravity:.4g} m/s^2"},
            "cloth": {"grid": {"resolution": [segments, 2], "size": [TENSILE_LENGTH, 2 * a]},
                      "rotation": {"axis": [0.0, 0.0, 1.0], "angle": -90.0}, "warp_angle": float(angle)},
            "material": _test_material(material),
            "pins": [{"box": {"min": [-1.0, -1e-3 * a, -1.0], "max": [1.0, 1.0, 1.0]}}],
            "forces": {"global_damping": 2.0, "gravity": [0.0, -gravity, 0.0]},
            "solver": _solver_table(),
            "output": {"frames": SETTLE_FRAMES, "fps": SETTLE_FPS}}
    return parse_scene(tomli_w.dumps(data))


def _peirce(angle_rad: float) -> float:
    """Peirce's c / l = (cos(theta / 2) / (8 tan theta))^(1/3) at chord angle theta."""
    return (math.cos(0.5 * angle_rad) / (8.0 * math.tan(angle_rad))) ** (1.0 / 3.0)


def _peirce_slope() -> float:
    """d theta / d log B [rad] at 41.5 deg and a fixed overhang by Peirce's formula (B ~ c^3): -0.45 rad (the
    simulated strip: -0.42); the Jacobian's fallback where a residual is too small to divide by."""
    theta = math.radians(CHORD_ANGLE)
    return 1.0 / (-0.5 * math.tan(0.5 * theta) - 1.0 / (math.sin(theta) * math.cos(theta)))


@dataclasses.dataclass
class _Test:
    """One simulated test inside a block: its fit, residual and conversion to the measurement's units."""

    measurement: MeasurementFit
    fit: SceneFit
    residual: Callable  # fit.last_measured -> (observable, residual in the loss's units)
    to_measurement: Callable  # observable -> the measurement's value
    slope: Callable  # closed-form d residual / d log(own parameter): the Jacobian's fallback
    prepare: Callable | None = None  # called before each evaluation (e.g. the centroid target's lateral part)


def _bending_tests(meas: FabricMeasurements, material: FabricMaterial, segments: int, device) -> list[_Test]:
    from .fitting import SceneFit

    tests = []
    w = meas.areal_density * GRAVITY
    target = math.radians(CHORD_ANGLE)
    for d, key in (("warp", "material.bend_stiffness"), ("weft", "material.bend_stiffness_weft")):
        c = meas.bending_length(d)
        scene = cantilever_scene(material, c, d, segments)
        fit = SceneFit(scene, None, ["material.bend_stiffness", "material.bend_stiffness_weft"], device=device)
        mkey = meas.bending_key(d)
        rigidity = mkey.startswith("bending.rigidity")
        given = getattr(meas, f"rigidity_{d}") if rigidity else c

        def to_measurement(angle_deg, c=c, rigidity=rigidity):
            c_sim = c * _peirce(math.radians(angle_deg)) / _peirce(target)  # Peirce's slope about D1388's 41.5 deg <-> l = 2c
            return w * c_sim**3 if rigidity else c_sim

        m = MeasurementFit(mkey, "N m" if rigidity else "m", given, math.nan, math.nan,
                           f"ASTM D1388 cantilever, {d} strip, overhang 2c = {2e3 * c:.2f} mm in {segments} x 2 cells, "
                           f"{2e3 * c * CANTILEVER_WIDTH:.2f} mm wide",
                           "chord_angle_deg", CHORD_ANGLE, math.nan, key)
        tests.append(_Test(m, fit, lambda measured: (measured["chord_angle_deg"], math.radians(measured["chord_angle_deg"]) - target),
                           to_measurement, _peirce_slope))
    return tests


def _tensile_tests(meas: FabricMeasurements, material: FabricMaterial, device) -> list[_Test]:
    from .fitting import SceneFit

    strips = [("tensile.warp", 0.0, meas.tensile_warp, "material.stretch_stiffness"),
              ("tensile.weft", 90.0, meas.tensile_weft, "material.stretch_stiffness_weft")]
    keys = ["material.stretch_stiffness", "material.stretch_stiffness_weft"]
    if meas.tensile_bias is not None:
        strips.append(("tensile.bias", 45.0, meas.tensile_bias, "material.shear_stiffness"))
        keys.append("material.shear_stiffness")
    tests = []
    for mkey, angle, stiffness, key in strips:
        g = tensile_gravity(meas.areal_density, stiffness)
        scene = tensile_scene(material, angle, g)
        from .scene import build_model

        model = build_model(scene, "cpu")
        x0 = model.particle_q.numpy().astype(np.float64)
        mass = model.particle_mass.numpy().astype(np.float64)
        weights = mass / mass.sum()
        s = -x0[:, 1]  # distance below the clamp
        ideal = meas.areal_density * g * (TENSILE_LENGTH * s - 0.5 * s * s) / stiffness  # the ideal strip's displacement [m]
        drop = float(weights @ ideal)
        c0 = weights @ x0
        target = c0 - np.array([0.0, drop, 0.0])
        fit = SceneFit(scene, lambda model, t=target: _centroid_loss(t, model), keys, frames=SETTLE_FRAMES, device=device)

        def residual(measured, c0=c0, drop=drop):
            sim_drop = float(c0[1] - measured["centroid"][1])
            return sim_drop, drop - sim_drop  # the loss's vertical residual: centroid_y - target_y

        def prepare(fit=fit, target=target):
            # the strip may also move sideways (a bias strip shears): aim the target's lateral part at the last simulated
            # centroid so the loss's gradient is the vertical residual's (the residual itself is read exactly)
            import warp as wp

            last = fit.last_measured.get("centroid")
            if last is not None:
                fit.loss.target = wp.vec3(float(last[0]), float(target[1]), float(last[2]))

        m = MeasurementFit(mkey, "N/m", stiffness, math.nan, math.nan,
                           f"hanging strip at {angle:g} deg from the warp, {1e3 * TENSILE_LENGTH:g} mm x {1e2 * TENSILE_LENGTH:g} mm "
                           f"in {TENSILE_SEGMENTS} x 2 cells, test gravity {g:.4g} m/s^2",
                           "centroid_drop_m", drop, math.nan, key)
        tests.append(_Test(m, fit, residual, lambda sim_drop, stiffness=stiffness, drop=drop: stiffness * drop / sim_drop,
                           lambda drop=drop: drop, prepare))  # drop ~ 1 / C: d (c_y - t_y) / d log C = drop
    return tests


def _centroid_loss(target, model):
    from .gradients import CentroidLoss

    return CentroidLoss(target, SETTLE_FRAMES, model)  # one substep per frame


def _solve_block(tests: list[_Test], keys: list[str], values: dict, iterations: int, progress, block: str) -> tuple[dict, int]:
    """Gauss-Newton in log space on the tests' residuals with the Jacobian from SceneFit's gradients; returns the best values
    (smallest largest relative error) and the number of evaluations."""
    n = len(keys)
    start = {k: values[k] for k in keys}
    jac_prev = np.zeros((n, n))
    best = (math.inf, dict(values), [None] * n)
    evaluations = 0
    for it in range(iterations):
        p = np.array([values[k] for k in keys])
        r, jac, rel, observed = np.zeros(n), np.zeros((n, n)), np.zeros(n), []
        for i, t in enumerate(tests):
            if t.prepare is not None:
                t.prepare()
            loss, grads = t.fit.loss_and_gradient([np.array([v]) for v in p])
            obs, r[i] = t.residual(t.fit.last_measured)
            if not (math.isfinite(loss) and math.isfinite(r[i])):
                raise FloatingPointError(f"calibrate: the simulated {t.measurement.key} test is not finite at "
                                         + ", ".join(f"{k} = {v:.6g}" for k, v in zip(keys, p)))
            observed.append(obs)
            rel[i] = t.to_measurement(obs) / t.measurement.target - 1.0
            g = np.array([float(gr[0]) for gr in grads]) * p  # dL / d log p
            if abs(r[i]) > 0.0 and abs(rel[i]) > 0.1 * TOLERANCE:
                jac[i] = g / (2.0 * r[i])
            elif jac_prev[i].any():
                jac[i] = jac_prev[i]
            else:
                jac[i, i] = t.slope()
        evaluations += 1
        worst = float(np.max(np.abs(rel)))
        if worst < best[0]:
            best = (worst, dict(values), observed)
        if progress is not None:
            progress(block, it + 1, iterations, {t.measurement.key: float(e) for t, e in zip(tests, rel)})
        if worst < TOLERANCE:
            break
        jac_prev = jac
        try:
            step = np.linalg.solve(jac, -r)
        except np.linalg.LinAlgError:
            step = -r / np.diag(jac)
        step = np.clip(step, -MAX_LOG_STEP, MAX_LOG_STEP)
        for k, s in zip(keys, step):
            values[k] = float(np.clip(values[k] * math.exp(s), start[k] / 100.0, start[k] * 100.0))
    _, best_values, observed = best
    for t, obs in zip(tests, observed):
        t.measurement.observable_simulated = float(obs)
        t.measurement.simulated = float(t.to_measurement(obs))
        t.measurement.relative_error = t.measurement.simulated / t.measurement.target - 1.0
    return best_values, evaluations


def _material(meas: FabricMeasurements, values: dict) -> FabricMaterial:
    base = PRESETS[meas.preset]
    return base.replace(name=meas.name, areal_density=meas.areal_density,
                        **{k.split(".", 1)[1]: v for k, v in values.items()})


def _bias_shear(meas: FabricMeasurements, base: FabricMaterial) -> float:
    """Closed-form start of the shear stiffness: the G whose continuum bias strip is as stiff as measured (the lower
    branch: the bias stiffness rises with G, then falls towards G^2 = C_warp C_weft)."""
    cw, cf = meas.tensile_warp, meas.tensile_weft
    top = math.sqrt(cw * cf)
    grid = np.linspace(1e-6, 0.999, 400) * top
    bias = np.array([base.replace(stretch_stiffness=cw, stretch_stiffness_weft=cf, shear_stiffness=float(g)).stretch_stiffness_at(45.0)
                     for g in grid])
    peak = int(np.argmax(bias))
    if meas.tensile_bias >= bias[peak]:
        raise MeasurementError(f"{meas.source or 'measurements'}: tensile.bias: {meas.tensile_bias:g} N/m is above the stiffest bias "
                               f"strip ({bias[peak]:.4g} N/m) a membrane with these warp and weft stiffnesses has")
    return float(np.interp(meas.tensile_bias, bias[:peak + 1], grid[:peak + 1]))


def calibrate(measurements: FabricMeasurements, *, iterations: int = ITERATIONS, segments: int = CANTILEVER_SEGMENTS,
              start: dict | None = None, drape: bool = True, drape_overrides: dict | None = None, device=None,
              progress=None) -> CalibrationResult:
    """Fit a :class:`FabricMaterial` to `measurements` by simulating each test (see the module docstring).

    Args:
        iterations: the most Gauss-Newton iterations per block (tension, then bending); each simulates every
            test of the block once with its adjoint.
        segments: cells along a cantilever's overhang.
        start: start values of fitted material keys (``{"material.bend_stiffness": 1e-5}``) instead of the closed forms.
        drape: run the Cusick test (scenes/cusick.toml) for the calibrated material when the measurements give a
            drape coefficient (reported, not fitted); `drape_overrides`: scene keys for it (``output.frames``).
        device: Warp device.
        progress: ``progress(block, iteration, iterations, {measurement key: relative error})`` after each iteration.
    """
    from .fitting import fit_tolerance
    from .validation import InvalidValue, check_number

    try:
        iterations = int(check_number("iterations", iterations, LIMITS["fit_iterations"]))
        segments = int(check_number("segments", segments, LIMITS["resolution"]))
    except InvalidValue as exc:
        raise MeasurementError(str(exc)) from None
    t0 = time.perf_counter()
    base = PRESETS[measurements.preset]
    notes = []
    shear = measurements.shear_stiffness
    if measurements.tensile_bias is not None:
        shear = _bias_shear(measurements, base)
    elif shear is None:
        shear = base.shear_stiffness
        notes.append(f"shear_stiffness {shear:g} N/m from the {base.name} preset (no shear or bias measurement)")
    else:
        notes.append(f"shear_stiffness {shear:g} N/m as measured (shear.stiffness)")
    notes.append(f"damping {base.damping:g} s and drag_coefficient {base.drag_coefficient:g} N s/m^3 from the {base.name} preset")
    w = measurements.areal_density * GRAVITY
    values = {"material.stretch_stiffness": measurements.tensile_warp, "material.stretch_stiffness_weft": measurements.tensile_weft,
              "material.shear_stiffness": shear,
              "material.bend_stiffness": w * measurements.bending_length("warp") ** 3,
              "material.bend_stiffness_weft": w * measurements.bending_length("weft") ** 3}
    fitted_keys = [k for k in values if k != "material.shear_stiffness" or measurements.tensile_bias is not None]
    for key, value in (start or {}).items():
        if key not in fitted_keys:
            raise MeasurementError(f"start: {key} is not fitted; fitted: {', '.join(fitted_keys)}")
        try:
            values[key] = float(check_number(f"start: {key}", value, LIMITS[key.split(".")[1].removesuffix("_weft")]))
        except InvalidValue as exc:
            raise MeasurementError(str(exc)) from None
        if not values[key] > 0.0:
            raise MeasurementError(f"start: {key} must be > 0 (fitted in log space), got {value!r}")
    initial = {k: values[k] for k in fitted_keys}

    evaluations = 0
    tension = _tensile_tests(measurements, _material(measurements, values), device)
    keys = [t.measurement.parameter for t in tension]
    fitted, n = _solve_block(tension, keys, values, iterations, progress, "tension")
    values.update(fitted)
    evaluations += n
    bending = _bending_tests(measurements, _material(measurements, values), segments, device)
    keys = [t.measurement.parameter for t in bending]
    fitted, n = _solve_block(bending, keys, values, iterations, progress, "bending")
    values.update(fitted)
    evaluations += n
    material = _material(measurements, values)
    results = [t.measurement for t in tension + bending]
    converged = all(abs(m.relative_error) < TOLERANCE for m in results)
    if measurements.drape is not None and drape:
        results.append(cusick_drape(material, measurements.drape, drape_overrides, device))
    return CalibrationResult(material, initial, results, evaluations, time.perf_counter() - t0,
                             fit_tolerance(bending[0].fit.scene), "converged" if converged else "not converged", notes,
                             measurements.source, material_preset=base.name)


def cusick_drape(material: FabricMaterial, setup: DrapeSetup, overrides: dict | None = None, device=None) -> MeasurementFit:
    """The drape coefficient of `material` on the Cusick set-up (scenes/cusick.toml with `setup`'s radii), against the
    measured one: reported, not fitted (no material key is fitted to it)."""
    import tempfile

    from .runner import run_scene, shipped_scenes

    path = shipped_scenes().get("cusick")
    if path is None:
        raise MeasurementError("drape: scenes/cusick.toml (the Cusick set-up) is not available")
    values = {f"material.{k}": v for k, v in _test_material(material).items()}
    values.update({"material.damping": material.damping, "material.drag_coefficient": material.drag_coefficient,
                   "cloth.disc.radius": setup.disc_radius, "measure.cusick.pedestal_radius": setup.pedestal_radius,
                   "colliders[0].radius": setup.pedestal_radius, **(overrides or {})})
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_scene(path, values, output=pathlib.Path(tmp) / "cusick.npz", device=device)
    dc = summary.get("drape_coefficient")
    if summary["status"] != "complete" or dc is None:
        raise MeasurementError(f"drape: the Cusick run ended {summary['status']}: {summary.get('message', '')}")
    return MeasurementFit("drape.coefficient", "", setup.coefficient, float(dc), float(dc) / setup.coefficient - 1.0,
                          f"Cusick drape (scenes/cusick.toml), disc radius {setup.disc_radius:g} m on a {setup.pedestal_radius:g} m "
                          f"pedestal, {summary['frames']} frames", "drape_coefficient", setup.coefficient, float(dc), None)


def write_calibration(result: CalibrationResult, output) -> dict[str, pathlib.Path]:
    """fabric.toml at `output` and the JSON report beside it (same stem, .json); atomic writes."""
    from .outputs import atomic_write_text

    output = pathlib.Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    report = output.with_suffix(".json")
    atomic_write_text(output, result.material_toml())
    atomic_write_text(report, json.dumps(result.report(), indent=1, default=str) + "\n")
    return {"material": output, "report": report}
