"""Gradient-based fitting of scene parameters to a target animation (``cloth-warp fit``).

A :class:`SceneFit` simulates a scene with a differentiable :class:`~cloth_warp.gradients.Rollout` and
fits chosen scene keys so the cloth matches a target cache, with Warp's Adam optimizer::

    fit = cw.SceneFit(load_scene("scenes/fit_hanging.toml"), "out/target.usdc",
                      ["material.stretch_stiffness", "material.bend_stiffness", "material.damping"])
    result = fit.run(iterations=60, learning_rate=0.05)

Parameters (scene key paths):

* ``material.<value>``: areal_density, stretch_stiffness(_weft), shear_stiffness, bend_stiffness(_weft), damping,
  drag_coefficient; positive, optimized in log space;
* ``forces.wind`` [m/s] and ``cloth.velocity`` (the initial velocity) [m/s]: vectors, optimized as they are;
* ``colliders[i].friction``: a collider's Coulomb coefficient (static and kinetic), log space.

Each model array depends linearly on each parameter alone (a stiffness, a mass, a damping c = tau k), so
the chain rule from the arrays' gradients to a parameter uses the difference of two host-side model
builds, which is exact; the model is rebuilt from the scene at every iteration and its values are written
into the fit's model, whose solver (and loss) are then told which fields changed
(``notify_model_changed(flags)``, :class:`~cloth_warp.model.ModelFlags`): the fit simulates exactly what a
fresh build of the scene with those values simulates, and after :meth:`SceneFit.run` its model and solver
hold the best values. Bounds clip the parameter after every step (default: 1/100 to 100 times the start for
log-space parameters).

Gradients are only as good as the implicit solve: the adjoint is exact up to the linear solve's tolerance, and
a loose solve makes the simulated map itself jagged. A fit therefore runs the implicit solve at
:data:`FIT_TOLERANCE` (or the scene's, when tighter); :class:`FitResult` reports the tolerance and why.

Losses: ``positions`` (mean squared vertex distance over every target frame), ``final`` (the last frame
only) and ``chamfer`` (symmetric Chamfer distance per frame: targets on a different mesh).
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import re
import time

import numpy as np
import warp as wp

from .cache import CacheError
from .gradients import CentroidLoss, ChamferLoss, ChordAngleLoss, Loss, PositionLoss, Rollout, model_grad_arrays
from .model import FIELD_FLAGS, Model, ModelFlags
from .scene import FIT_LOSSES, Scene, SceneError, build_material, build_model, build_solver, scene_selection, with_values
from .validation import LIMITS, check_number

MATERIAL_VALUES = ("areal_density", "stretch_stiffness", "stretch_stiffness_weft", "shear_stiffness", "bend_stiffness",
                   "bend_stiffness_weft", "damping", "drag_coefficient")
LOSSES = FIT_LOSSES
CHAIN_STEP = 1.0e-2
"""Relative step of the central difference that carries the model arrays' gradients to a material value."""
VECTOR_NOISE_FLOOR = 3.0e-2
"""A vector parameter's Adam eps relative to its gradient's running norm (see :meth:`SceneFit.run`): a component
whose gradient stays below this share of the vector's takes steps of at most (share / floor) x the learning rate.
Measured on scenes/fit_flag.toml (wind [0, 0, 1.5] -> [0, 1, 3] m/s): the along-pole component's share is
0.5-1.6e-4, float32 noise; in 30 iterations it moved 3 mm/s (plain Adam: 1.5 m/s) while the felt y component (share
2.6 % at the start) came within 7 % (the old first-gradient eps left it 62 % off). In 60 iterations a floor of 1e-2
let the along-pole wind drift 4 cm/s and left y 13 % off, 5e-2 left y 6 % off, 3e-2 1 %."""
FIT_TOLERANCE = 1.0e-6
"""Relative residual of the implicit linear solve (forward and adjoint) during a fit; a scene's tighter value is
kept. The adjoint is exact only up to the solve's tolerance, and a loose solve also biases the simulated map: on a
16^2 cotton cloth at one step per frame, d loss / d stretch_stiffness at the default 1e-3 is 23 % off the slope of
the map (an independent check found 24 %), 0.6 % at 1e-6 (tests/test_fits_converge.py); on scenes/fit_hanging.toml
the scene keys' gradients were 7 % off at 1e-4, within 1 % at 1e-6. The error grows with the system's
conditioning (h^2 k / m), so a fit takes float32 CG's floor, 1e-6 (WARM_START_FLOOR in solvers/implicit.py):
about 1.5x the CG iterations of 1e-4, 2x those of 1e-3."""
_COLLIDER_FRICTION = re.compile(r"colliders\[(\d+)\]\.friction$")


def allowed_parameters() -> list[str]:
    return [f"material.{v}" for v in MATERIAL_VALUES] + ["forces.wind", "cloth.velocity", "colliders[i].friction"]


@dataclasses.dataclass
class FitParameter:
    """One fitted scene key: its current value, bounds and how it is encoded for the optimizer.

    Positive parameters are optimized as log(value): a step of the learning rate is a relative change.
    Vectors in m/s are optimized as value / scale, scale = the start's largest component (at least
    1 m/s), so the learning rate is a step relative to the start's magnitude for them too.
    """

    key: str
    value: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    log: bool
    scale: float = 1.0

    @property
    def size(self) -> int:
        return self.value.size

    def scene_value(self):
        return float(self.value[0]) if self.size == 1 else [float(v) for v in self.value]

    def encode(self, value: np.ndarray | None = None) -> np.ndarray:
        value = self.value if value is None else value
        return np.log(value) if self.log else value / self.scale

    def decode(self, theta: np.ndarray) -> np.ndarray:
        value = np.exp(theta) if self.log else theta * self.scale
        return np.clip(value, self.lower, self.upper)

    def encoded_gradient(self, grad: np.ndarray, value: np.ndarray) -> np.ndarray:
        """dL/dtheta from dL/dvalue."""
        return grad * value if self.log else grad * self.scale


# the validation.LIMITS entry of each fittable value (colliders' friction otherwise)
_LIMIT_OF = {"damping": "damping_time", "wind": "velocity", "velocity": "velocity", "areal_density": "areal_density",
             "stretch_stiffness": "stretch_stiffness", "stretch_stiffness_weft": "stretch_stiffness", "shear_stiffness": "shear_stiffness",
             "bend_stiffness": "bend_stiffness", "bend_stiffness_weft": "bend_stiffness",
             "drag_coefficient": "drag_coefficient"}


def parse_parameter(spec: str) -> tuple[str, float | None, float | None]:
    """``KEY`` or ``KEY=LOWER:UPPER`` (either bound may be empty)."""
    key, _, bounds = spec.partition("=")
    lower = upper = None
    if bounds:
        lo, sep, hi = bounds.partition(":")
        if not sep:
            raise SceneError(f"--param {spec}: bounds are written KEY=LOWER:UPPER")
        try:
            lower = float(lo) if lo.strip() else None
            upper = float(hi) if hi.strip() else None
        except ValueError:
            raise SceneError(f"--param {spec}: bounds must be numbers") from None
    return key.strip(), lower, upper


def _current_value(scene: Scene, key: str) -> tuple[np.ndarray, bool]:
    if key.startswith("material."):
        name = key.split(".", 1)[1]
        if name not in MATERIAL_VALUES:
            raise SceneError(f"--param {key}: not a fittable material value; allowed: {', '.join(allowed_parameters())}")
        material = build_material(scene)
        value = getattr(material, name)
        if value is None:  # a weft value not set is the warp's
            value = getattr(material, name.removesuffix("_weft"))
        value = float(value)
        if value <= 0.0:
            raise SceneError(f"--param {key}: the start value must be positive to fit in log space, got {value}")
        return np.array([value]), True
    if key in ("forces.wind", "cloth.velocity"):
        return np.asarray(scene.get(key), float).copy(), False
    m = _COLLIDER_FRICTION.match(key)
    if m:
        cols = scene.data.get("colliders", [])
        i = int(m.group(1))
        if i >= len(cols):
            raise SceneError(f"--param {key}: the scene has {len(cols)} colliders")
        if "static_friction" in cols[i] or "kinetic_friction" in cols[i]:
            raise SceneError(f"--param {key}: the collider sets static_friction/kinetic_friction; fit needs one friction value")
        value = float(cols[i].get("friction", 0.3))
        if value <= 0.0:
            raise SceneError(f"--param {key}: the start value must be positive to fit in log space, got {value}")
        return np.array([value]), True
    raise SceneError(f"--param {key}: cannot be fitted; allowed: {', '.join(allowed_parameters())}")


def make_parameter(scene: Scene, spec: str) -> FitParameter:
    key, lower, upper = parse_parameter(spec)
    value, log = _current_value(scene, key)
    if log:
        lo = np.full_like(value, value / 100.0 if lower is None else lower)
        hi = np.full_like(value, value * 100.0 if upper is None else upper)
        if not (lo > 0.0).all():
            raise SceneError(f"--param {spec}: the lower bound of a positive parameter must be > 0")
    else:
        lo = np.full_like(value, -np.inf if lower is None else lower)
        hi = np.full_like(value, np.inf if upper is None else upper)
    allowed = LIMITS[_LIMIT_OF.get(key.split(".")[-1], "friction")]  # the gate's range bounds every fit too
    if allowed.norm:  # a vector's length: each component within hi / sqrt(n) keeps the length inside
        cap = allowed.hi / math.sqrt(len(value))
        lo, hi = np.maximum(lo, -cap), np.minimum(hi, cap)
    else:
        lo = lo if allowed.lo is None else np.maximum(lo, allowed.lo)
        hi = hi if allowed.hi is None else np.minimum(hi, allowed.hi)
    if (lo > hi).any():
        raise SceneError(f"--param {spec}: lower bound above upper bound (allowed: {allowed})")
    scale = 1.0 if log else max(float(np.abs(value).max()), 1.0)
    return FitParameter(key, np.clip(value, lo, hi), lo, hi, log, scale)


def read_targets(target, substeps: int, frames: int | None) -> dict[int, np.ndarray]:
    """Target points by frame (1..N) from a cache path or reader, or a dict {frame: points} as given."""
    if isinstance(target, dict):
        out = {int(k): np.asarray(v, np.float32) for k, v in target.items()}
    else:
        from .cache import CacheReader

        reader = target if isinstance(target, CacheReader) else CacheReader(target)
        count = reader.frame_count - 1  # frame 0 of a cache is the initial state
        if count < 1:
            raise SceneError(f"target {reader.path}: needs at least one simulated frame")
        out = {f: reader.points(reader.start_frame + f) for f in range(1, count + 1)}  # points() takes time codes
    if frames is not None:
        out = {f: p for f, p in out.items() if f <= frames}
    if not out:
        raise SceneError("target: no frames to fit")
    return out


@dataclasses.dataclass
class FitSolverTolerance:
    """The implicit solve's tolerance during a fit, and why."""

    tolerance: float | None
    """Relative residual at which the fit's linear solves (forward and adjoint) stop; None: an explicit
    integrator (no linear solve, gradients exact up to float32)."""
    scene_tolerance: float | None
    """The scene's ``solver.tolerance`` (None for explicit integrators)."""
    reason: str
    """Why this tolerance."""


@dataclasses.dataclass
class FitResult:
    """What a fit did: loss and values per iteration, the best values found, and timings."""

    parameters: list[str]
    initial_values: dict
    final_values: dict
    initial_loss: float
    final_loss: float
    iterations: int
    losses: list
    values: list
    wall_s: float
    loss_kind: str
    frames: int
    status: str = "complete"
    measured: dict = dataclasses.field(default_factory=dict)
    """What the loss measures at the best values (a throw's landing distance, a chord angle), if it reports it."""
    solver_tolerance: FitSolverTolerance | None = None
    """The implicit solve's tolerance during the fit and why (:data:`FIT_TOLERANCE`)."""

    def report(self) -> dict:
        return dataclasses.asdict(self)


def fit_tolerance(scene: Scene, tolerance: float | None = None) -> FitSolverTolerance:
    """The implicit solve's tolerance for a fit of `scene`: `tolerance` when given, else :data:`FIT_TOLERANCE`
    or the scene's when tighter (explicit integrators have none)."""
    if scene.get("solver.integrator") != "implicit_euler":
        return FitSolverTolerance(None, None, f"{scene.get('solver.integrator')}: no linear solve")
    own = float(scene.get("solver.tolerance"))
    if tolerance is not None:
        tolerance = float(check_number("solver_tolerance", tolerance, LIMITS["tolerance"]))
        return FitSolverTolerance(tolerance, own, "set by the caller")
    if own <= FIT_TOLERANCE:
        return FitSolverTolerance(own, own, f"the scene's, at least as tight as the fit's default {FIT_TOLERANCE:g}")
    return FitSolverTolerance(FIT_TOLERANCE, own, f"tightened from the scene's {own:g}: the adjoint gradient is exact only up "
                              "to the solve's tolerance (d loss / d stretch stiffness up to 23 % off the slope of the simulated "
                              f"map at 1e-3, 0.6 % at {FIT_TOLERANCE:g})")


# Model scalars a build derives from fitted values (not differentiated): the default self-collision stiffness is
# the median structural spring constant, so it follows material.stretch_stiffness.
_DERIVED_SCALARS = ("self_collision_stiffness", "cloth_thickness", "cloth_friction", "global_damping", "gravity")


def scene_target(scene: Scene, frames: int):
    """The target a scene's ``[fit.target]`` table names: a cache path, or a loss factory (model -> Loss)
    evaluated at the last of `frames` frames; None when the table names none."""
    target = scene.data.get("fit", {}).get("target", {})
    step = frames * int(scene.get("solver.substeps"))
    if "cache" in target:
        path = scene.resolve(target["cache"])
        if path.is_dir():
            raise SceneError(f"fit.target.cache: {path} is a directory, not a cache file")
        if not path.is_file():
            raise SceneError(f"fit.target.cache: file not found: {path} (paths are relative to the scene file; simulate the "
                             "target first, see the scene's header)")
        return path
    if "centroid" in target:
        return lambda model: CentroidLoss(target["centroid"], step, model)
    if "chord_angle" in target:
        tip = scene_selection(scene, target["tip"], "fit.target.tip")
        return lambda model: ChordAngleLoss(target["chord_angle"], tip, step, model, origin=scene.get("fit.target.chord_origin"))
    return None


class SceneFit:
    """Fit scene keys so the simulated cloth matches target frames.

    Args:
        scene: the scene (its values are the start).
        target: a cache path / :class:`~cloth_warp.cache.CacheReader` (frame k = the scene's frame k),
            {frame: points}, or a :class:`~cloth_warp.gradients.Loss` of its own or a function model -> Loss
            (then give `frames`; a loss's steps count substeps). None: the scene's ``[fit.target]``
            (a cache, a centroid for the last frame, or a chord angle).
        parameters: specs ``KEY`` or ``KEY=LOWER:UPPER`` (see the module docstring); None: ``fit.params``.
        loss: ``positions``, ``final`` or ``chamfer`` (None: ``fit.loss``).
        frames: fit the first `frames` frames only (default: ``fit.frames``, else all the target cache has,
            else ``output.frames``).
        checkpoint_every: passed to :class:`Rollout`; default: every state kept up to 240 steps, about
            sqrt(steps) of them beyond (one extra forward pass, memory ~sqrt(T)).
        device: Warp device.
        solver_tolerance: relative residual of the implicit solve during the fit (default: :data:`FIT_TOLERANCE`,
            or the scene's ``solver.tolerance`` when tighter); reported in :attr:`FitResult.solver_tolerance`.
    """

    def __init__(self, scene: Scene, target=None, parameters: list[str] | None = None, *, loss: str | None = None,
                 frames: int | None = None, checkpoint_every=None, device=None, solver_tolerance: float | None = None):
        loss = scene.get("fit.loss") if loss is None else loss
        parameters = scene.get("fit.params") if parameters is None else parameters
        frames = scene.get("fit.frames") if frames is None else frames
        from_scene = target is None
        if target is None:
            target = scene_target(scene, int(frames or scene.get("output.frames")))
            if target is None:
                raise SceneError("fit: no target; give --target CACHE or a [fit.target] table (cache, centroid or chord_angle)")
            if callable(target) and frames is None:
                frames = int(scene.get("output.frames"))
        if not isinstance(target, Loss) and loss not in LOSSES:
            raise SceneError(f"loss: {loss!r} is not a loss; allowed: {', '.join(LOSSES)}")
        if not parameters:
            raise SceneError("fit: give at least one --param (or fit.params in the scene)")
        if float(scene.get("forces.gusts.strength")) > 0.0:
            raise SceneError("forces.gusts.strength: gusty wind is not differentiable here; set it to 0 to fit")
        targets = None
        if not callable(target) and not isinstance(target, Loss):  # read the target before any work: a bad file exits early
            try:
                targets = read_targets(target, int(scene.get("solver.substeps")), frames)
            except CacheError as exc:
                if from_scene:
                    raise SceneError(f"fit.target.cache: {exc}") from exc
                raise
        self.scene = scene
        self.parameters = [make_parameter(scene, p) for p in parameters]
        keys = [p.key for p in self.parameters]
        if len(set(keys)) != len(keys):
            raise SceneError(f"--param: a key is given twice: {keys}")
        self.loss_kind = loss
        self.substeps = int(scene.get("solver.substeps"))
        self.fps = float(scene.get("output.fps"))
        self.dt = 1.0 / (self.fps * self.substeps)
        self.device = wp.get_device(device)
        self.model = build_model(self._scene_with(self._values()), self.device, requires_grad=True)
        n = self.model.particle_count
        if callable(target) and not isinstance(target, Loss):
            target = target(self.model)  # a loss factory (losses that need the model, e.g. CentroidLoss)
        if isinstance(target, Loss):
            named = {CentroidLoss: "centroid", ChordAngleLoss: "chord_angle"}
            if frames is None:
                raise SceneError("fit: a custom loss needs the number of frames to simulate")
            self.frames, self.loss, self.loss_kind = int(frames), target, named.get(type(target), type(target).__name__)
            targets = {}
        else:
            if targets is None:  # a factory that gave targets rather than a Loss
                targets = read_targets(target, self.substeps, frames)
            self.frames = max(targets)
        if loss == "final" and targets:
            targets = {self.frames: targets[self.frames]}
        steps = {f * self.substeps: p for f, p in targets.items()}
        if loss == "chamfer" and targets:
            self.loss = ChamferLoss(steps, device=self.device)
        elif targets:
            bad = [f for f, p in targets.items() if p.shape[0] != n]
            if bad:
                raise SceneError(f"target: frame {bad[0]} has {targets[bad[0]].shape[0]} points, the scene's cloth {n}; "
                                 "use --loss chamfer for a target on a different mesh")
            self.loss = PositionLoss(steps, device=self.device)
        self.tolerance = fit_tolerance(scene, solver_tolerance)
        tight = self.tolerance.tolerance
        self.solver = build_solver(scene if tight is None else with_values(scene, {"solver.tolerance": tight}), self.model)
        steps = self.frames * self.substeps
        if checkpoint_every is None and steps > 240:
            checkpoint_every = "auto"
        self.rollout = Rollout(self.model, self.solver, dt=self.dt, steps=steps, checkpoint_every=checkpoint_every)
        self.evaluations = 0
        self.last_measured: dict = {}

    # -- values <-> model ------------------------------------------------------------------------
    def _values(self, values: list[np.ndarray] | None = None) -> dict:
        values = values if values is not None else [p.value for p in self.parameters]
        return {p.key: (float(v[0]) if p.size == 1 else [float(x) for x in v]) for p, v in zip(self.parameters, values)}

    def _scene_with(self, values: dict) -> Scene:
        return with_values(self.scene, values)

    def _arrays(self, values: dict) -> dict[str, np.ndarray]:
        """The differentiable arrays (float64) of a fresh build of the scene with `values` (the chain rule's ends)."""
        m = build_model(self._scene_with(values), "cpu", requires_grad=True)
        return {name: a.numpy().astype(np.float64) for name, a in model_grad_arrays(m).items() if name != "particle_q"}

    def _apply(self, values: dict):
        """Write what a fresh build of the scene with `values` holds into the fit's model (:func:`load_build`) and set
        the wind."""
        load_build(build_model(self._scene_with(values), "cpu", requires_grad=True), self.model, (self.rollout, self.loss))
        wind = values.get("forces.wind", self.scene.get("forces.wind"))
        self.rollout.control.wind.assign(np.asarray(wind, np.float32).reshape(1, 3))

    def set_values(self, values: list[np.ndarray]):
        """Put parameter values (one array per parameter, as :attr:`parameters` orders them) into the fit's model
        and solver, as :meth:`loss_and_gradient` does before it simulates."""
        self._apply(self._values(values))

    def loss_and_gradient(self, values: list[np.ndarray]) -> tuple[float, list[np.ndarray]]:
        """The loss at parameter values and its gradient with respect to each of them."""
        self._apply(self._values(values))
        state0 = self.model.state(requires_grad=True)  # the model's initial velocity is the fitted one
        loss = self.rollout.gradient(self.loss, state0)
        self.evaluations += 1
        measure = getattr(self.loss, "measure", None)
        self.last_measured = measure(self.rollout.final_state) if measure is not None else {}
        grads = {name: a.grad.numpy().astype(np.float64) for name, a in model_grad_arrays(self.model).items() if name != "particle_q"}
        grads["particle_qd"] = state0.particle_qd.grad.numpy().astype(np.float64)
        grads["forces.wind"] = self.rollout.control.wind.grad.numpy().astype(np.float64).reshape(3)
        return loss, self.chain_rule(values, grads)

    def chain_rule(self, values: list[np.ndarray], grads: dict[str, np.ndarray]) -> list[np.ndarray]:
        """d loss / d each parameter at `values`, from the loss's gradients with respect to the model's differentiable
        arrays (`grads`: name -> float64 array in this fit's model's layout, ``particle_qd`` the initial state's,
        ``forces.wind`` the wind's)."""
        out = []
        for p, v in zip(self.parameters, values):
            if p.key == "forces.wind":
                out.append(grads["forces.wind"])
                continue
            g = np.zeros(p.size)
            for k in range(p.size):
                # d array / d value by a central difference of two builds (CHAIN_STEP of the value apart): exact
                # for the values the arrays are linear in, second order for the twist terms of a weft bending
                # rigidity set apart from the warp's (sqrt(B_warp B_weft), cloth_warp/elasticity.py).
                step = CHAIN_STEP * (abs(float(v[k])) if abs(float(v[k])) > 0.0 else 1.0)
                ends = []
                for sign in (1.0, -1.0):
                    moved = [x.copy() for x in values]
                    moved[self.parameters.index(p)][k] += sign * step
                    ends.append(self._arrays(self._values(moved)))
                g[k] = sum(float(np.sum(grads[name] * (ends[0][name] - ends[1][name]))) for name in ends[0]) / (2.0 * step)
            out.append(g)
        return out

    # -- the optimization --------------------------------------------------------------------
    def run(self, iterations: int = 50, learning_rate: float = 0.05, decay: float = 0.1, progress=None,
            betas: tuple[float, float] | None = None) -> FitResult:
        """Adam on the encoded parameters (log space for positive ones); keeps the best values seen and leaves
        them in the fit's model and solver (:attr:`model`, :attr:`solver`).

        The step size decays geometrically from `learning_rate` to `decay` times it over the iterations
        (damps Adam's overshoot near the optimum). Each parameter has its own Warp Adam. A vector's Adam has
        eps = VECTOR_NOISE_FLOOR x R_t, R_t the running RMS of its gradient's norm with the memory of Adam's
        first moment (beta1), so eps follows the gradient as the loss falls: a component the loss feels moves
        as in plain Adam, while one whose gradient stays a share rho of the vector's (wind along a banner's
        pole, which a normal-only drag cannot feel: rho ~ 1e-4, float32 noise) steps at most rho /
        VECTOR_NOISE_FLOOR of the learning rate. (An eps fixed by the first gradient stalls a vector once its
        gradient has fallen: a 3-D wind stopped 50 % off.) `progress(iteration, iterations, loss, values)` is
        called after every evaluation. `betas`: Adam's moment decay rates (default: the scene's fit.betas,
        (0.9, 0.999)); a one-parameter fit settles with less overshoot at lower ones. Ctrl-C ends the fit
        early with the best values so far (status ``interrupted``)."""
        run = FitRun(self, iterations, learning_rate, decay, betas, progress)
        status = "complete"
        try:
            for it in range(iterations):
                values = run.values()
                loss, grads = self.loss_and_gradient(values)
                run.step(it, values, loss, grads, self.last_measured)
        except KeyboardInterrupt:
            status = "interrupted"
        return run.result(status)

    # -- outputs -------------------------------------------------------------------------------
    def fitted_scene_toml(self, output: pathlib.Path) -> str:
        """The scene with the fitted values, as TOML; relative mesh paths are rewritten for `output`'s folder."""
        import os

        import tomli_w

        scene = self._scene_with(self._values())
        data = scene.data
        out_dir = pathlib.Path(output).resolve().parent

        def rebase(table):
            if isinstance(table, dict) and isinstance(table.get("mesh"), str):
                table["mesh"] = os.path.relpath(scene.resolve(table["mesh"]).resolve(), out_dir)

        rebase(data.get("cloth"))
        for col in data.get("colliders", []):
            rebase(col)
        header = (f"# Fitted by cloth-warp fit from {scene.path.name if scene.path else 'a scene'}: "
                  + ", ".join(f"{p.key} = {p.scene_value()}" for p in self.parameters) + "\n")
        if self.tolerance.tolerance is not None:
            header += f"# The fit ran the implicit solve at tolerance {self.tolerance.tolerance:g}: {self.tolerance.reason}\n"
        return header + tomli_w.dumps(data)


def load_build(fresh: Model, model: Model, listeners=()) -> ModelFlags:
    """Write a fresh build's differentiable arrays, and the scalars a build derives from them (the default
    self-collision stiffness follows the stretch stiffness), into `model`, which simulates exactly what the fresh
    build would; each listener (a rollout, a loss) is told which fields changed. Returns those fields' flags."""
    flags = ModelFlags(0)
    for name, a in model_grad_arrays(fresh).items():
        if name == "particle_q":
            continue
        new = a.numpy()
        target = getattr(model, name)
        if not np.array_equal(target.numpy(), new):
            target.assign(new)
            flags |= FIELD_FLAGS[name]
    for name in _DERIVED_SCALARS:
        if getattr(fresh, name) != getattr(model, name):
            setattr(model, name, getattr(fresh, name))
            flags |= FIELD_FLAGS[name]
    for mine, theirs in zip(model.cloths, fresh.cloths):
        mine.material = theirs.material  # the host-side description, for reports
    if flags:
        for listener in listeners:
            listener.notify_model_changed(flags)  # the solver and its passes; a loss's derived values
    return flags


class FitRun:
    """One fit's optimizer over a run (:meth:`SceneFit.run`): a Warp Adam per parameter on its encoded value, the
    loss and values of every evaluation, and the best seen. :class:`~cloth_warp.batch_fit.BatchFit` keeps one per
    world."""

    def __init__(self, fit: SceneFit, iterations: int, learning_rate: float, decay: float, betas=None, progress=None):
        from warp.optim import Adam

        if iterations < 1:
            raise SceneError(f"iterations: must be >= 1, got {iterations}")
        self.fit, self.iterations, self.learning_rate, self.decay, self.progress = fit, iterations, learning_rate, decay, progress
        self.t0 = time.perf_counter()
        self.thetas = [wp.array(p.encode().astype(np.float32), dtype=float, device="cpu") for p in fit.parameters]
        self.betas = tuple(fit.scene.get("fit.betas")) if betas is None else tuple(betas)
        self.optimizers = [Adam([theta], lr=learning_rate, betas=self.betas) for theta in self.thetas]
        self.initial = {p.key: p.scene_value() for p in fit.parameters}
        self.losses: list[float] = []
        self.history: list[dict] = []
        self.best = (math.inf, [p.value for p in fit.parameters], {})
        self.norm_sq = [0.0] * len(fit.parameters)  # per vector parameter: the running mean of |gradient|^2 (memory beta1)

    def values(self) -> list[np.ndarray]:
        """The values to evaluate next (decoded from the optimizer's encoded ones)."""
        return [p.decode(theta.numpy().astype(np.float64)) for p, theta in zip(self.fit.parameters, self.thetas)]

    def step(self, it: int, values: list[np.ndarray], loss: float, grads: list[np.ndarray], measured: dict):
        """Record evaluation `it` (the loss and gradients at `values`) and take each parameter's Adam step."""
        params = self.fit.parameters
        named = self.fit._values(values)
        self.losses.append(loss)
        self.history.append(named)
        if not math.isfinite(loss):
            raise FloatingPointError(f"fit: the loss is not finite at iteration {it} with {named}")
        if loss < self.best[0]:
            self.best = (loss, values, measured)
        if self.progress is not None:
            self.progress(it + 1, self.iterations, loss, named)
        beta1 = self.betas[0]
        for k, (p, g, v, theta, opt) in enumerate(zip(params, grads, values, self.thetas, self.optimizers)):
            g_theta = p.encoded_gradient(g, v)
            if not np.isfinite(g_theta).all():
                raise FloatingPointError(f"fit: non-finite gradient of {p.key} at iteration {it} with {named}")
            if p.size > 1:
                self.norm_sq[k] = beta1 * self.norm_sq[k] + (1.0 - beta1) * float(np.dot(g_theta, g_theta))
                running = math.sqrt(self.norm_sq[k] / (1.0 - beta1 ** (it + 1)))  # bias-corrected, as Adam's moments
                opt.eps = max(VECTOR_NOISE_FLOOR * running, 1.0e-30)
            opt.lr = self.learning_rate * self.decay ** (it / max(self.iterations - 1, 1))
            opt.step([wp.array(g_theta.astype(np.float32), dtype=float, device="cpu")])
            theta.assign(p.encode(p.decode(theta.numpy().astype(np.float64))).astype(np.float32))  # clip to the bounds

    def result(self, status: str) -> FitResult:
        """The run's :class:`FitResult`; the fit's parameters, model and solver left at the best values."""
        if not self.losses:
            raise KeyboardInterrupt
        fit = self.fit
        loss, values, measured = self.best
        for p, v in zip(fit.parameters, values):
            p.value = v
        fit.set_values(values)  # the model and solver handed back simulate the best values
        final = {p.key: p.scene_value() for p in fit.parameters}
        return FitResult([p.key for p in fit.parameters], self.initial, final, self.losses[0], loss, len(self.losses), self.losses,
                         self.history, time.perf_counter() - self.t0, fit.loss_kind, fit.frames, status, measured, fit.tolerance)


def loss_curve_png(losses: list[float], path, title: str = "fit loss", size=(640, 400)) -> pathlib.Path:
    """A log-scale loss curve as a PNG (Pillow; no plotting library needed)."""
    from PIL import Image, ImageDraw

    from .outputs import atomic_path

    w, h = size
    img = Image.new("RGB", size, "white")
    draw = ImageDraw.Draw(img)
    left, right, top, bottom = 70, w - 20, 30, h - 40
    draw.rectangle([left, top, right, bottom], outline="black")
    values = np.log10(np.maximum(np.asarray(losses, float), 1e-300))
    lo, hi = float(values.min()), float(values.max())
    if hi - lo < 1e-9:
        lo, hi = lo - 0.5, hi + 0.5
    lo, hi = math.floor(lo), math.ceil(hi)
    for e in range(lo, hi + 1):
        y = bottom - (e - lo) / (hi - lo) * (bottom - top)
        draw.line([left, y, right, y], fill=(225, 225, 225))
        draw.text((8, y - 6), f"1e{e}", fill="black")
    n = len(values)
    pts = [(left + (i / max(n - 1, 1)) * (right - left), bottom - (v - lo) / (hi - lo) * (bottom - top)) for i, v in enumerate(values)]
    if len(pts) > 1:
        draw.line(pts, fill=(200, 40, 40), width=2)
    for p in pts:
        draw.ellipse([p[0] - 2, p[1] - 2, p[0] + 2, p[1] + 2], fill=(200, 40, 40))
    draw.text((left, 8), f"{title}: {losses[0]:.3e} -> {min(losses):.3e} in {n} iterations", fill="black")
    draw.text((left + (right - left) // 2 - 20, bottom + 12), "iteration", fill="black")
    path = pathlib.Path(path)
    with atomic_path(path) as tmp:
        img.save(tmp, format="PNG")
    return path


def write_fit_outputs(fit: SceneFit, result: FitResult, output) -> dict[str, pathlib.Path]:
    """fitted scene TOML at `output`, the JSON report and the loss-curve PNG beside it (atomic writes)."""
    from .outputs import atomic_write_text

    output = pathlib.Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    report = output.with_suffix(".json")
    curve = output.with_name(output.stem + "_loss.png")
    atomic_write_text(output, fit.fitted_scene_toml(output))
    atomic_write_text(report, json.dumps(result.report(), indent=1) + "\n")
    loss_curve_png(result.losses, curve, title=f"{result.loss_kind} loss")
    return {"scene": output, "report": report, "loss_curve": curve}
