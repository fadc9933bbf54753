"""One gate for every value that enters the simulation: the allowed ranges, in one table, and their checkers.

Scene keys (the schema in :mod:`cloth_warp.scene`) and Python API arguments (:class:`~cloth_warp.ModelBuilder`,
:class:`~cloth_warp.FabricMaterial`, colliders, keyframes, :class:`~cloth_warp.GustyWind`,
:func:`~cloth_warp.quat_from_axis_angle`) go through the same functions against the same :data:`LIMITS`. A value
must be finite, representable in float32 (the kernels' precision: 1e-300 is 0 there and 1e300 is inf) and
physically meaningful. A refusal is an :class:`InvalidValue` (a ValueError) whose message names the key path or
argument, what went wrong and the allowed range; the scene loader turns it into a SceneError.

The ranges are generous: no real cloth scene comes near them. They exist to stop typos and overflows before
they become a frozen cloth or a NaN in the first frame. Sizes are bounded by memory and run time, estimated
before anything is allocated (:func:`check_build_size`, :func:`check_run_length`).

Pure Python and numpy (no Warp), so scene validation stays light.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)

FLOAT32_TINY = float(np.finfo(np.float32).tiny)  # smallest normal float32, 1.18e-38
FLOAT32_MAX = float(np.finfo(np.float32).max)  # 3.4e38


class InvalidValue(ValueError):
    """A value the simulation cannot use; the message names the key path or argument and the allowed range."""


def format_number(x) -> str:
    """A bound as people write it: 0.001, 1000, 1e4, 1e-5 (integers exactly)."""
    if isinstance(x, int | np.integer):
        x = int(x)
        power = len(str(abs(x))) - 1
        return f"{'-' if x < 0 else ''}1e{power}" if power >= 6 and abs(x) == 10**power else str(x)
    x = float(x)
    if x == 0.0 or 1e-3 <= abs(x) < 1e4:
        return f"{x:.4g}"
    mantissa, exp = f"{x:.3e}".split("e")
    return f"{mantissa.rstrip('0').rstrip('.')}e{int(exp)}"


@dataclass(frozen=True)
class Range:
    """Allowed values of one quantity: [lo, hi] in `unit` (either bound may be None: unbounded).

    norm: the bounds apply to a vector's length instead of to each component (gravity, velocities, axes).
    hi_open: hi itself is excluded. integer: whole numbers only.
    """

    lo: float | None
    hi: float | None
    unit: str = ""
    norm: bool = False
    hi_open: bool = False
    integer: bool = False

    def __str__(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        what = "length " if self.norm else ""
        if self.lo is None and self.hi is None:
            return f"any finite value{unit}"
        if self.hi is None:
            return f"{what}>= {format_number(self.lo)}{unit}"
        if self.lo is None:
            return f"{what}{'<' if self.hi_open else '<='} {format_number(self.hi)}{unit}"
        if self.norm and self.lo == 0:
            return f"length {'<' if self.hi_open else '<='} {format_number(self.hi)}{unit}"
        return f"{what}[{format_number(self.lo)}, {format_number(self.hi)}{')' if self.hi_open else ']'}{unit}"

    def violation(self, x) -> str | None:
        """'must be >= lo [unit]' (or the upper-bound equivalent) when x is outside, else None."""
        unit = f" {self.unit}" if self.unit else ""
        if self.lo is not None and x < self.lo:
            return f"must be >= {format_number(self.lo)}{unit}"
        if self.hi is not None and (x > self.hi or (self.hi_open and x == self.hi)):
            return f"must be {'<' if self.hi_open else '<='} {format_number(self.hi)}{unit}"
        return None


# Every range the gate uses, by quantity (scene keys and API arguments refer to these entries). A length or
# speed bound with norm=True limits the vector's length; otherwise each component.
LIMITS: dict[str, Range] = {
    # geometry and placement
    "position": Range(-1e6, 1e6, "m"),  # any coordinate; see also check_float32_resolution
    "length": Range(1e-5, 1e4, "m"),  # sizes, radii, box edges: 10 um .. 10 km
    "stature": Range(0.5, 2.5, "m"),  # the mannequin's standing height
    "edge_length": Range(1e-3, 1.0, "m"),  # a meshed sewing pattern's target edge length
    "height": Range(0.0, 1e4, "m"),  # capsule: straight part (0 = a sphere)
    "thickness": Range(1e-5, 1.0, "m"),  # contact offsets
    "scale": Range(1e-6, 1e6),  # mesh units to metres
    "jitter": Range(0.0, 1.0, "m"),
    "axis": Range(1e-9, 1e9, norm=True),  # a direction: any non-zero length
    "angle": Range(-1e5, 1e5, "deg"),
    "resolution": Range(1, None, integer=True),  # grid cells along one side; the memory estimate bounds it
    "rings": Range(1, None, integer=True),  # disc rings; the memory estimate bounds it
    "index": Range(0, 2**31 - 1, integer=True),
    # material (SI, per area / per width: independent of the resolution)
    "areal_density": Range(1e-4, 1e3, "kg/m^2"),
    "stretch_stiffness": Range(1e-3, 1e9, "N/m"),
    "shear_stiffness": Range(0.0, 1e9, "N/m"),
    "bend_stiffness": Range(0.0, 1e3, "N m"),
    "damping_time": Range(0.0, 10.0, "s"),
    "drag_coefficient": Range(0.0, 1e4, "N s/m^3"),
    # springs, pins, particles (low-level API)
    "pin_stiffness": Range(1e-3, 1e9, "N/m"),  # soft pins and self-collision repulsion
    "spring_stiffness": Range(0.0, 1e12, "N/m"),
    "spring_damping": Range(0.0, 1e9, "N s/m"),
    "rest_length": Range(1e-9, 1e4, "m"),
    "mass": Range(1e-15, 1e6, "kg"),
    # forces and motion
    "gravity": Range(0.0, 1e3, "m/s^2", norm=True),
    "velocity": Range(0.0, 1e3, "m/s", norm=True),
    "global_damping": Range(0.0, 1e4, "1/s"),
    "gust_strength": Range(0.0, 100.0),
    "gust_period": Range(1e-3, 1e6, "s"),
    "gust_turn": Range(0.0, 180.0, "deg"),
    "friction": Range(0.0, 10.0),
    "time": Range(0.0, 1e6, "s"),  # keyframe times
    "dressing_time": Range(0.0, 10.0, "s"),  # a garment's dressing / settling before the run
    "layer": Range(0, 99, integer=True),  # a garment's layer order (0 innermost)
    "seed": Range(0, None, integer=True),
    # solver and output
    "substeps": Range(1, 10_000, integer=True),
    "frames": Range(1, 1_000_000, integer=True),
    "fps": Range(1e-2, 1e5, "1/s"),
    "start_frame": Range(-10**9, 10**9, integer=True),
    "save_every": Range(1, 1_000_000, integer=True),
    "strain_limit": Range(0.0, 10.0),
    "iterations": Range(1, 100_000, integer=True),  # linear-solver and strain-limit caps per step
    "tolerance": Range(1e-10, 1.0),
    "velocity_tolerance": Range(0.0, 10.0, "m/s"),  # 0: none
    "dt_min": Range(1e-9, 1.0, "s"),
    # fitting
    "fit_iterations": Range(1, 1_000_000, integer=True),
    "learning_rate": Range(1e-9, 1e3),
    "adam_beta": Range(0.0, 1.0, hi_open=True),
    "chord_angle": Range(-90.0, 90.0, "deg"),
}

# Unit quaternions: a length off by more than this is a mistake (an angle in the w slot), not rounding.
QUATERNION_TOLERANCE = 1e-2

# Build cost of a cloth (peak resident memory and time on the CPU, builder + finalize), measured on 64^2..256^2
# grids (3.3 KB, 45 us per particle) and on meshes and discs of 4k..20k vertices (4.1-5.4 KB, 350 us).
BUILD_BYTES_PER_PARTICLE = 5000
GRID_SECONDS_PER_PARTICLE = 45e-6
MESH_SECONDS_PER_PARTICLE = 350e-6
# Run length: no run may take more steps than this. The cheapest step measured (a one-cell cloth, symplectic
# Euler, CPU) takes 15 us; a 64^2 cloth 2.4 ms (symplectic) to 42 ms (implicit, CG).
MAX_STEPS = 10**8
STEP_SECONDS_FLOOR = 10e-6
# Springs must be this many float32 spacings long at the cloth's distance from the origin (1 % strain resolution).
MIN_SPACINGS_PER_SPRING = 100


# -- scalars and vectors ---------------------------------------------------------------------------------------

def _is_number(v) -> bool:
    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool | np.bool_)


def _float32_problem(x: float) -> str | None:
    if x != 0.0 and abs(x) < FLOAT32_TINY:
        return f"is 0 in float32 (the smallest normal float32 is {FLOAT32_TINY:.3g})"
    if abs(x) > FLOAT32_MAX:
        return f"is inf in float32 (the largest float32 is {FLOAT32_MAX:.3g})"
    return None


def check_number(name: str, value, limits: Range) -> float | int:
    """`value` as a float (an int for integer ranges) if it is a finite number inside `limits` and
    representable in float32; else :class:`InvalidValue` naming `name` and the allowed range."""
    given, allowed = _show(value), f"(allowed: {limits})"
    if limits.integer:
        if isinstance(value, float | np.floating) and math.isfinite(value) and float(value).is_integer():
            value = int(value)
        if not isinstance(value, int | np.integer) or isinstance(value, bool | np.bool_):
            raise InvalidValue(f"{name}: expected an integer, got {given} {allowed}")
        value = int(value)
    else:
        if not _is_number(value):
            raise InvalidValue(f"{name}: expected a finite number{_unit(limits)}, got {given} {allowed}")
        value = float(value)
        if not math.isfinite(value):
            raise InvalidValue(f"{name}: must be finite, got {given} {allowed}")
    problem = limits.violation(value)
    if problem is None and not limits.integer:
        problem = _float32_problem(value)
    if problem is not None:
        raise InvalidValue(f"{name}: {problem}, got {given} {allowed}")
    return value


def check_vector(name: str, value, limits: Range, size: int = 3) -> tuple:
    """A tuple of `size` finite numbers, each inside `limits` (or, for a norm range, whose length is)."""
    items = None if isinstance(value, str | bytes | dict) else _items(value)
    if items is None or len(items) != size or not all(_is_number(c) for c in items):
        what = "integers" if limits.integer else "finite numbers"
        raise InvalidValue(f"{name}: expected {size} {what}{_unit(limits)}, got {_show(value)} (allowed: {limits})")
    if not limits.norm:
        return tuple(check_number(f"{name}[{k}]", c, limits) for k, c in enumerate(items))
    v = tuple(float(c) for c in items)
    if not all(math.isfinite(c) for c in v):
        raise InvalidValue(f"{name}: must be finite, got {_show(value)} (allowed: {limits})")
    length = math.hypot(*v)
    problem = limits.violation(length)
    if problem is not None:
        lead = "must not be the zero vector: its length " if limits.lo and length < limits.lo else "its length "
        raise InvalidValue(f"{name}: {lead}{problem}, got {_show(value)} (length {length:.4g}; allowed: {limits})")
    for c in v:
        if _float32_problem(c):
            raise InvalidValue(f"{name}: the component {c!r} {_float32_problem(c)}, got {_show(value)} (allowed: {limits})")
    return v


def _items(value) -> list | None:
    try:
        return list(value)
    except TypeError:
        return None


def check_direction(name: str, value) -> np.ndarray:
    """A unit 3-vector from a non-zero finite direction (an axis or a normal; need not be unit length)."""
    v = np.asarray(check_vector(name, value, LIMITS["axis"]), np.float64)
    return v / np.linalg.norm(v)


def check_quaternion(name: str, value) -> tuple[float, float, float, float]:
    """A unit quaternion (x, y, z, w): four finite numbers of length 1 (within QUATERNION_TOLERANCE, then
    normalised)."""
    q = check_vector(name, value, Range(None, None), size=4)
    length = math.sqrt(math.fsum(c * c for c in q))
    if abs(length - 1.0) > QUATERNION_TOLERANCE:
        hint = " (the zero quaternion is no rotation; use (0, 0, 0, 1) for none)" if length < 1e-12 else \
            " (an angle where w belongs? build it with quat_from_axis_angle(axis, degrees))"
        raise InvalidValue(f"{name}: a rotation quaternion (x, y, z, w) must have length 1 (within "
                           f"{QUATERNION_TOLERANCE:g}), got {_show(value)} of length {length:.4g}{hint}")
    return tuple(c / length for c in q)


def check_rotation(name: str, rotation) -> np.ndarray:
    """The 3x3 rotation matrix of None (identity), a unit quaternion (x, y, z, w) or a proper rotation matrix
    (orthonormal, determinant +1: a reflection would turn the cloth's faces inside out)."""
    if rotation is None:
        return np.eye(3)
    r = np.asarray(rotation, dtype=object)
    if r.shape == (4,):
        from .model import quat_to_matrix

        return quat_to_matrix(check_quaternion(name, rotation))
    if r.shape == (3, 3):
        try:
            m = np.asarray(rotation, np.float64)
        except (TypeError, ValueError):
            m = np.full((3, 3), np.nan)
        if not np.all(np.isfinite(m)):
            raise InvalidValue(f"{name}: a rotation matrix must be finite, got {m.tolist()}")
        if np.abs(m.T @ m - np.eye(3)).max() > 1e-3 or np.linalg.det(m) < 0.0:
            raise InvalidValue(f"{name}: a rotation matrix must be orthonormal with determinant +1 (no scale, no mirror), "
                               f"got {np.round(m, 6).tolist()} (determinant {np.linalg.det(m):.4g})")
        return m
    raise InvalidValue(f"{name}: expected a quaternion (x, y, z, w) or a 3x3 rotation matrix, got shape {r.shape}")


def check_points(name: str, points, limits: Range | None = None) -> np.ndarray:
    """An (n, 3) float64 array of finite positions inside `limits` (default: LIMITS['position'])."""
    limits = limits or LIMITS["position"]
    try:
        p = np.asarray(points, np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidValue(f"{name}: expected an (n, 3) array of numbers [m]: {exc}") from None
    if p.ndim != 2 or p.shape[1] != 3:
        raise InvalidValue(f"{name}: expected shape (n, 3), got {p.shape}")
    bad = ~np.all(np.isfinite(p), axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise InvalidValue(f"{name}: {int(bad.sum())} point(s) with non-finite coordinates (first: {first} = {p[first].tolist()})")
    outside = np.any((p < limits.lo) | (p > limits.hi), axis=1)
    if outside.any():
        first = int(np.flatnonzero(outside)[0])
        raise InvalidValue(f"{name}: {int(outside.sum())} point(s) outside the allowed range {limits} per coordinate "
                           f"(first: {first} = {p[first].tolist()})")
    return p


def check_keyframes(name: str, keyframes) -> list[tuple[float, tuple, tuple]]:
    """Keyframes as (time [s], translation [m], unit quaternion) from Keyframe objects or tuples
    (time, translation[, quaternion]): finite, inside the ranges, times strictly increasing (may be empty)."""
    out = []
    for k, kf in enumerate(keyframes or []):
        where = f"{name}[{k}]"
        if hasattr(kf, "time"):
            t, tr, q = kf.time, kf.translation, kf.rotation
        else:
            if not isinstance(kf, tuple | list) or len(kf) not in (2, 3):
                raise InvalidValue(f"{where}: expected (time, translation[, quaternion]) or a Keyframe, got {_show(kf)}")
            t, tr, q = kf[0], kf[1], kf[2] if len(kf) == 3 else (0.0, 0.0, 0.0, 1.0)
        out.append((check_number(f"{where}.time", t, LIMITS["time"]), check_vector(f"{where}.translation", tr, LIMITS["position"]),
                    check_quaternion(f"{where}.rotation", q)))
    times = [k[0] for k in out]
    if any(b <= a for a, b in itertools.pairwise(times)):
        raise InvalidValue(f"{name}: keyframe times must increase strictly, got {times}")
    return out


# -- float32 after the unit conversions ------------------------------------------------------------------------

def check_float32(name: str, values, positive: bool = False, hint: str = "") -> None:
    """Refuse an array whose float32 cast has inf/NaN (or, with `positive`, zeros or negatives): catches
    products of allowed values that leave float32 (a mass = areal density x a tiny cell area)."""
    v = np.asarray(values, np.float64)
    v32 = v.astype(np.float32)
    bad = ~np.isfinite(v32) | ((v32 <= 0.0) if positive else False)
    if np.any(bad):
        first = int(np.flatnonzero(bad.ravel())[0])
        what = "positive and finite" if positive else "finite"
        raise InvalidValue(f"{name}: {int(bad.sum())} value(s) are not {what} in float32 (first: {_show(v.ravel()[first])} -> "
                           f"{_show(v32.ravel()[first])}){hint}")


def check_float32_resolution(name: str, positions, rest_lengths) -> None:
    """Refuse springs too short to resolve in float32 this far from the origin: the median spring must be at
    least MIN_SPACINGS_PER_SPRING float32 spacings long (strain resolution 1 %); shorter single springs are
    logged."""
    if len(rest_lengths) == 0 or len(positions) == 0:
        return
    reach = float(np.abs(positions).max())
    spacing = float(np.spacing(np.float32(reach)))
    need = MIN_SPACINGS_PER_SPRING * spacing
    typical = float(np.median(rest_lengths))
    if typical < need:
        raise InvalidValue(f"{name}: too short for float32 positions this far from the origin: the median rest "
                           f"length {typical:.3g} m is below {MIN_SPACINGS_PER_SPRING} float32 spacings ({MIN_SPACINGS_PER_SPRING} x "
                           f"{spacing:.3g} m at {reach:.3g} m from the origin); move the cloth closer to the origin or use cells "
                           f"of at least {need:.3g} m")
    short = int(np.sum(np.asarray(rest_lengths) < need))
    if short:
        log.warning("%s: %d spring(s) shorter than %.3g m (%d float32 spacings at %.3g m from the origin) resolve strain "
                    "poorly", name, short, need, MIN_SPACINGS_PER_SPRING, reach)


# -- size and time bounds, estimated before allocating ---------------------------------------------------------

def memory_limit_bytes() -> int:
    """This machine's physical memory [bytes] (16 GiB when it cannot be read)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 16 * 2**30


def format_bytes(n: float) -> str:
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n / 1e3:.3g} kB"


def format_duration(seconds: float) -> str:
    for unit, size in (("years", 3.156e7), ("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= size:
            return f"{seconds / size:.3g} {unit}"
    return f"{seconds:.3g} s"


def check_build_size(name: str, what: str, particles: int, seconds_per_particle: float = GRID_SECONDS_PER_PARTICLE) -> None:
    """Refuse a cloth of `particles` whose build would not fit in memory (estimate: BUILD_BYTES_PER_PARTICLE);
    warn when it would take over a minute. `what` describes it ("a 20000 x 20000 grid")."""
    need = float(particles) * BUILD_BYTES_PER_PARTICLE
    seconds = float(particles) * seconds_per_particle
    limit = memory_limit_bytes()
    if need > limit:
        raise InvalidValue(f"{name}: {what} ({particles} particles) needs about {format_bytes(need)} of memory and "
                           f"{format_duration(seconds)} to build (limit: this machine's {format_bytes(limit)}, about "
                           f"{format_number(float(limit // BUILD_BYTES_PER_PARTICLE))} particles)")
    if seconds > 60.0:
        log.warning("%s: %s (%d particles) takes about %s and %s to build", name, what, particles, format_duration(seconds),
                    format_bytes(need))


def check_run_length(name: str, frames: int, substeps: int) -> int:
    """The number of steps, frames x substeps, if at most MAX_STEPS; else a refusal with a time estimate."""
    steps = int(frames) * int(substeps)
    if steps > MAX_STEPS:
        raise InvalidValue(f"{name}: {frames} frames x {substeps} substeps = {format_number(steps)} steps would take at least "
                           f"{format_duration(steps * STEP_SECONDS_FLOOR)} ({STEP_SECONDS_FLOOR * 1e6:g} us per step for the "
                           f"smallest cloth; a 64^2 cloth takes 2-40 ms); limit {format_number(MAX_STEPS)} steps")
    return steps


def _unit(limits: Range) -> str:
    return f" [{limits.unit}]" if limits.unit else ""


def _show(value) -> str:
    """A value as the user wrote it (numpy scalars and arrays as plain numbers and lists)."""
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_show(v) for v in value) + "]"
    return repr(value)
