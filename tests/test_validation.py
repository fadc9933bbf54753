"""One gate for every value: scene keys and API arguments are finite, float32-representable and physically
meaningful (messages name the key or argument and the allowed range); sizes and run lengths are bounded before
anything is allocated; unreadable scene and mesh files are named; mesh winding is made consistent."""

import pathlib
import warnings

import numpy as np
import pytest

import cloth_warp as cw
from cloth_warp import validation
from cloth_warp.cli import main
from cloth_warp.scene import SCHEMA, Key, SceneError, Tables, build_model, load_scene, parse_scene
from cloth_warp.validation import LIMITS, InvalidValue

ROOT = pathlib.Path(__file__).resolve().parents[1]
HANG = ROOT / "scenes" / "hanging_cloth.toml"
SCENES = sorted((ROOT / "scenes").glob("*.toml"))
NAN, INF = float("nan"), float("inf")
SMALL = {"cloth.grid.resolution": [4, 4]}


def scene_error(overrides, path=HANG) -> str:
    """The SceneError message of loading and building a scene with `overrides` (fails when it builds)."""
    with pytest.raises(SceneError) as info:
        build_model(load_scene(path, {**SMALL, **overrides}), "cpu")
    return str(info.value)


# -- scene keys: every class of bad number, with the key path and the allowed range in the message -----------------

PLANE = {"type": "plane"}
SPHERE = {"type": "sphere", "radius": 0.1}
HANDLE = {"select": "corners"}

SCENE_CASES = [
    # (overrides, the key path the message must start with, the LIMITS entry whose range it must show)
    # non-finite, or finite in float64 but 0 / inf in float32 after the unit conversion
    ({"material.areal_density": 1e-300}, "material.areal_density", "areal_density"),
    ({"material.areal_density": 0.0}, "material.areal_density", "areal_density"),
    ({"material.areal_density": NAN}, "material.areal_density", "areal_density"),
    ({"material.stretch_stiffness": 1e300}, "material.stretch_stiffness", "stretch_stiffness"),
    ({"material.stretch_stiffness": INF}, "material.stretch_stiffness", "stretch_stiffness"),
    ({"material.shear_stiffness": 1e-300}, "material.shear_stiffness", "shear_stiffness"),
    ({"material.bend_stiffness": 1e40}, "material.bend_stiffness", "bend_stiffness"),
    ({"material.damping": -1.0}, "material.damping", "damping_time"),
    ({"material.drag_coefficient": 1e300}, "material.drag_coefficient", "drag_coefficient"),
    ({"forces.gravity": [0.0, 1e300, 0.0]}, "forces.gravity", "gravity"),
    ({"forces.gravity": [0.0, -2000.0, 0.0]}, "forces.gravity", "gravity"),
    ({"forces.gravity": [0.0, NAN, 0.0]}, "forces.gravity", "gravity"),
    ({"forces.wind": [1e5, 0.0, 0.0]}, "forces.wind", "velocity"),
    ({"forces.global_damping": -1.0}, "forces.global_damping", "global_damping"),
    ({"forces.gusts.period": 0.0}, "forces.gusts.period", "gust_period"),
    ({"forces.gusts.strength": 1e300}, "forces.gusts.strength", "gust_strength"),
    ({"forces.gusts.turn": -5.0}, "forces.gusts.turn", "gust_turn"),
    ({"cloth.velocity": [0.0, 0.0, 1e300]}, "cloth.velocity", "velocity"),
    # positions not absurd
    ({"cloth.position": [1e300, 0.0, 0.0]}, "cloth.position[0]", "position"),
    ({"cloth.position": [0.0, -2e6, 0.0]}, "cloth.position[1]", "position"),
    ({"colliders": [{**SPHERE, "position": [0.0, INF, 0.0]}]}, "colliders[0].position", "position"),
    ({"pins": [{"box": {"min": [NAN, 0, 0], "max": [1, 1, 1]}}]}, "pins[0].box.min", "position"),
    ({"handles": [{**HANDLE, "keyframes": [{"time": 0.0, "translation": [0.0, 1e300, 0.0]}]}]},
     "handles[0].keyframes[0].translation[1]", "position"),
    # rotation axes non-zero, angles finite
    ({"cloth.rotation.axis": [0.0, 0.0, 0.0]}, "cloth.rotation.axis", "axis"),
    ({"cloth.rotation.angle": 1e300}, "cloth.rotation.angle", "angle"),
    ({"handles": [{**HANDLE, "keyframes": [{"time": 0.0, "rotation": {"axis": [0, 0, 0], "angle": 30.0}}]}]},
     "handles[0].keyframes[0].rotation.axis", "axis"),
    ({"colliders": [{"type": "capsule", "radius": 0.1, "height": 0.2, "axis": [0, 0, 0]}]}, "colliders[0].axis", "axis"),
    ({"colliders": [{"type": "box", "size": [1, 1, 1], "rotation": {"axis": [0, 0, 0], "angle": 10.0}}]},
     "colliders[0].rotation.axis", "axis"),
    ({"colliders": [{**PLANE, "keyframes": [{"time": 0.0, "rotation": {"axis": [1e-300, 0, 0], "angle": 5.0}}]}]},
     "colliders[0].keyframes[0].rotation.axis", "axis"),
    # keyframe times finite and inside the range
    ({"handles": [{**HANDLE, "keyframes": [{"time": -1.0}]}]}, "handles[0].keyframes[0].time", "time"),
    ({"handles": [{**HANDLE, "keyframes": [{"time": INF}]}]}, "handles[0].keyframes[0].time", "time"),
    ({"colliders": [{**PLANE, "keyframes": [{"time": 1e300}]}]}, "colliders[0].keyframes[0].time", "time"),
    # geometry: sizes, radii, thickness, friction, scale
    ({"cloth.grid.size": [1e-300, 1e-300]}, "cloth.grid.size[0]", "length"),
    ({"cloth.grid.size": [1.0, 1e300]}, "cloth.grid.size[1]", "length"),
    ({"colliders": [{"type": "sphere", "radius": 1e-300}]}, "colliders[0].radius", "length"),
    ({"colliders": [{"type": "box", "size": [1.0, 0.0, 1.0]}]}, "colliders[0].size[1]", "length"),
    ({"colliders": [{**PLANE, "thickness": 0.0}]}, "colliders[0].thickness", "thickness"),
    ({"colliders": [{**PLANE, "friction": 1e300}]}, "colliders[0].friction", "friction"),
    ({"collision.thickness": 1e-300}, "collision.thickness", "thickness"),
    ({"collision.stiffness": 1e300}, "collision.stiffness", "pin_stiffness"),
    ({"pins[0].stiffness": 1e-300}, "pins[0].stiffness", "pin_stiffness"),
    ({"cloth.jitter": 5.0}, "cloth.jitter", "jitter"),
    # integers: seeds, iteration caps, frame counts, time codes
    ({"scene.seed": -1}, "scene.seed", "seed"),
    ({"solver.max_iterations": 2**62}, "solver.max_iterations", "iterations"),
    ({"solver.max_iterations": 0}, "solver.max_iterations", "iterations"),
    ({"solver.strain_limit_iterations": 10**9}, "solver.strain_limit_iterations", "iterations"),
    ({"solver.substeps": 10**12}, "solver.substeps", "substeps"),
    ({"output.frames": 10**9}, "output.frames", "frames"),
    ({"output.start_frame": 2**62}, "output.start_frame", "start_frame"),
    ({"output.save_every": 0}, "output.save_every", "save_every"),
    ({"fit.iterations": 0}, "fit.iterations", "fit_iterations"),
    ({"cloth.grid.resolution": [0, 4]}, "cloth.grid.resolution[0]", "resolution"),
    # solver and output numbers
    ({"output.fps": 1e-300}, "output.fps", "fps"),
    ({"output.fps": 1e300}, "output.fps", "fps"),
    ({"solver.tolerance": 0.0}, "solver.tolerance", "tolerance"),
    ({"solver.dt_min": 1e-300}, "solver.dt_min", "dt_min"),
    ({"solver.strain_limit": -0.1}, "solver.strain_limit", "strain_limit"),
    ({"fit.learning_rate": INF}, "fit.learning_rate", "learning_rate"),
    ({"fit.betas": [0.9, 1.0]}, "fit.betas[1]", "adam_beta"),
    ({"fit.target.chord_angle": 200.0}, "fit.target.chord_angle", "chord_angle"),
    # wrong types still show the range
    ({"material.areal_density": "heavy"}, "material.areal_density", "areal_density"),
    ({"solver.substeps": 2.5}, "solver.substeps", "substeps"),
]


@pytest.mark.parametrize("overrides, key, limits", SCENE_CASES, ids=[f"{c[1]}={next(iter(c[0].values()))!r}"[:60] for c in SCENE_CASES])
def test_scene_values_name_the_key_and_the_range(overrides, key, limits):
    """Check each bad scene value raises a SceneError that starts with its key path and shows the allowed range."""
    message = scene_error(overrides)
    assert message.startswith(key), message
    assert str(LIMITS[limits]) in message, message


def test_ranges_are_one_table_shared_by_scene_and_api():
    """Check every numeric scene key has a range from LIMITS (the same object the API checks), its default lies
    inside it, and the reference page shows each range."""
    docs = (ROOT / "docs" / "scenes.md").read_text()
    shared = {id(r) for r in LIMITS.values()}

    def keys(schema, prefix=""):
        for name, sub in schema.items():
            path = f"{prefix}.{name}" if prefix else name
            if isinstance(sub, Key):
                yield path, sub
            elif isinstance(sub, Tables):
                yield from keys(sub.schema, f"{path}[]")
            else:
                yield from keys(sub, path)

    numeric = [(p, k) for p, k in keys(SCHEMA) if k.kind in ("float", "int", "vec2", "vec3", "ivec2", "ints")]
    assert len(numeric) > 60
    for path, key in numeric:
        assert key.limits is not None and id(key.limits) in shared, path
        if key.default is not None:
            defaults = key.default if isinstance(key.default, list) else [key.default]
            if key.limits.norm:
                validation.check_vector(path, key.default, key.limits)
            else:
                for d in defaults:
                    validation.check_number(path, d, key.limits)
        row = next(line for line in docs.splitlines() if line.startswith(f"| `{path}` "))
        assert str(validation.Range(key.limits.lo, key.limits.hi, norm=key.limits.norm, hi_open=key.limits.hi_open)) in row, row
    # the API refuses with the same range text
    with pytest.raises(InvalidValue, match=r"allowed: \[1e-4, 1000\] kg/m\^2"):
        cw.FabricMaterial(areal_density=1e-300)
    assert "allowed: [1e-4, 1000] kg/m^2" in scene_error({"material.areal_density": 1e-300})


def schema_keys(schema, prefix=""):
    """(dotted path, Key) of every key outside arrays of tables."""
    for name, sub in schema.items():
        path = f"{prefix}.{name}" if prefix else name
        if isinstance(sub, Key):
            yield path, sub
        elif not isinstance(sub, Tables):
            yield from schema_keys(sub, path)


# Keys that need another table to mean anything (a disc, a mesh, a Cusick measurement) are covered by the cases above.
BOUNDARY_KEYS = [(p, k) for p, k in schema_keys(SCHEMA) if k.limits is not None
                 and not p.startswith(("cloth.disc", "measure.cusick", "cloth.scale", "cloth.position", "fit.target"))]


@pytest.mark.parametrize("path, key", BOUNDARY_KEYS, ids=[p for p, _ in BOUNDARY_KEYS])
def test_every_key_at_its_bounds_builds_or_is_refused_by_name(path, key):
    """Check each numeric key at both ends of its range either builds the model or raises a SceneError (never
    another exception later): what validation lets through, the builder can use."""
    r = key.limits
    for bound in (r.lo, r.hi):
        if bound is None:
            continue
        if r.hi_open and bound == r.hi:
            bound = bound * (1.0 - 1e-9)
        value = {"float": bound, "int": bound, "ints": [bound], "vec2": [bound] * 2, "ivec2": [bound] * 2}.get(
            key.kind, [bound, 0.0, 0.0] if r.norm else [bound] * 3)
        overrides = {path: value, **({} if path == "cloth.grid.resolution" else SMALL)}
        try:
            scene = load_scene(HANG, overrides)
            model = build_model(scene, "cpu")
            cw.scene.build_solver(scene, model)
            cw.scene.build_wind(scene)
        except SceneError as exc:
            # a key path, never a traceback (a stretch bound can break the shear rule, which names the shear)
            assert str(exc).startswith((path, "cloth:", "solver.dt_min:", "material.shear_stiffness:")), exc


def test_dt_min_must_be_below_the_step():
    """Check an adaptive floor at or above the step itself (every rejection would stop the run) is refused."""
    message = scene_error({"solver.adaptive": True, "solver.dt_min": 0.5})
    assert message.startswith("solver.dt_min: 0.5 s must be below the step") and "0.01667 s" in message


# -- the Python API: NaN, inf, zero quaternions, absurd values, with the argument named --------------------------

def grid_builder():
    b = cw.ModelBuilder()
    b.add_cloth_grid(resolution=(2, 2))
    return b


API_CASES = [
    # (call, the argument the message must name, the allowed-range text or other phrase it must contain)
    (lambda: cw.ModelBuilder(gravity=(0.0, NAN, 0.0)), "gravity", str(LIMITS["gravity"])),
    (lambda: cw.ModelBuilder(gravity=(0.0, 1e300, 0.0)), "gravity", str(LIMITS["gravity"])),
    (lambda: cw.ModelBuilder(global_damping=INF), "global_damping", str(LIMITS["global_damping"])),
    (lambda: cw.ModelBuilder().add_cloth_grid(position=(NAN, 0.0, 0.0)), "position[0]", str(LIMITS["position"])),
    (lambda: cw.ModelBuilder().add_cloth_grid(position=(0.0, 1e300, 0.0)), "position[1]", str(LIMITS["position"])),
    (lambda: cw.ModelBuilder().add_cloth_grid(velocity=(INF, 0.0, 0.0)), "velocity", str(LIMITS["velocity"])),
    (lambda: cw.ModelBuilder().add_cloth_grid(velocity=(5e3, 0.0, 0.0)), "velocity", str(LIMITS["velocity"])),
    (lambda: cw.ModelBuilder().add_cloth_grid(size=(1e-300, 1.0)), "size[0]", str(LIMITS["length"])),
    (lambda: cw.ModelBuilder().add_cloth_grid(rotation=(0.0, 0.0, 0.0, 0.0)), "rotation", "length 1"),
    (lambda: cw.ModelBuilder().add_cloth_grid(rotation=(NAN, 0.0, 0.0, 1.0)), "rotation[0]", "finite"),
    (lambda: cw.ModelBuilder().add_cloth_grid(rotation=(1.0, 0.0, 0.0, 90.0)), "rotation", "quat_from_axis_angle"),
    (lambda: cw.ModelBuilder().add_cloth_grid(rotation=np.diag([1.0, 1.0, -1.0])), "rotation", "determinant +1"),
    (lambda: cw.ModelBuilder().add_cloth_grid(rotation=2.0 * np.eye(3)), "rotation", "orthonormal"),
    (lambda: cw.ModelBuilder().add_cloth_disc(radius=NAN), "radius", str(LIMITS["length"])),
    (lambda: cw.ModelBuilder().add_cloth_mesh([[0, 0, 0], [1, 0, 0], [0, 1e300, 0]], [[0, 1, 2]]), "vertices", str(LIMITS["position"])),
    (lambda: cw.ModelBuilder().add_cloth_mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], scale=0.0), "scale", str(LIMITS["scale"])),
    (lambda: cw.ModelBuilder().add_cloth_mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], uvs=[[0, 0], [1, 0], [NAN, 1]]),
     "uvs", "not finite"),
    (lambda: cw.ModelBuilder().add_particle((0.0, INF, 0.0)), "position[1]", str(LIMITS["position"])),
    (lambda: cw.ModelBuilder().add_particle((0.0, 0.0, 0.0), velocity=(NAN, 0.0, 0.0)), "velocity", str(LIMITS["velocity"])),
    (lambda: cw.ModelBuilder().add_particle((0.0, 0.0, 0.0), mass=1e-300), "mass", str(LIMITS["mass"])),
    (lambda: grid_builder().add_spring(0, 1, 1e300), "stiffness", str(LIMITS["spring_stiffness"])),
    (lambda: grid_builder().pin([0], stiffness=NAN), "stiffness", str(LIMITS["pin_stiffness"])),
    (lambda: grid_builder().pin([0], stiffness=0.0), "stiffness", str(LIMITS["pin_stiffness"])),
    (lambda: grid_builder().add_handle([0], [(NAN, (0.0, 0.0, 0.0))]), "keyframes[0].time", str(LIMITS["time"])),
    (lambda: grid_builder().add_handle([0], [(0.0, (0.0, INF, 0.0))]), "keyframes[0].translation[1]", str(LIMITS["position"])),
    (lambda: grid_builder().add_handle([0], [(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0))]), "keyframes[0].rotation", "length 1"),
    (lambda: grid_builder().add_handle([0], [(1.0, (0, 0, 0)), (0.5, (0, 0, 0))]), "keyframes", "increase"),
    (lambda: grid_builder().add_handle([0], [(0.0, (0, 0, 0))], pivot=(NAN, 0, 0)), "pivot[0]", str(LIMITS["position"])),
    (lambda: cw.quat_from_axis_angle((0.0, 0.0, 0.0), 30.0), "axis", "zero vector"),
    (lambda: cw.quat_from_axis_angle((NAN, 0.0, 1.0), 30.0), "axis", "finite"),
    (lambda: cw.quat_from_axis_angle((0.0, 0.0, 1.0), INF), "angle_deg", str(LIMITS["angle"])),
    (lambda: cw.ModelBuilder().add_sphere((NAN, 0.0, 0.0), 0.1), "position[0]", str(LIMITS["position"])),
    (lambda: cw.ModelBuilder().add_sphere((0.0, 0.0, 0.0), INF), "radius", str(LIMITS["length"])),
    (lambda: cw.ModelBuilder().add_sphere((0.0, 0.0, 0.0), 0.1, thickness=1e-300), "thickness", str(LIMITS["thickness"])),
    (lambda: cw.ModelBuilder().add_sphere((0.0, 0.0, 0.0), 0.1, friction=NAN), "friction", str(LIMITS["friction"])),
    (lambda: cw.ModelBuilder().add_plane(normal=(0.0, 0.0, 0.0)), "normal", "zero vector"),
    (lambda: cw.ModelBuilder().add_capsule((0, 0, 0), 0.1, 0.2, axis=(0.0, NAN, 0.0)), "axis", "finite"),
    (lambda: cw.ModelBuilder().add_box((0, 0, 0), (1.0, 1.0, 1.0), rotation=(0.0, 0.0, 0.0, 0.0)), "rotation", "length 1"),
    (lambda: cw.ModelBuilder().add_box((0, 0, 0), (1.0, INF, 1.0)), "size[1]", str(LIMITS["length"])),
    (lambda: cw.ModelBuilder().add_cylinder((0, 0, 0), 0.1, 0.0), "height", str(LIMITS["length"])),
    (lambda: cw.ModelBuilder().add_ground(keyframes=[(0.0, (0.0, NAN, 0.0))]), "keyframes[0].translation[1]", str(LIMITS["position"])),
    (lambda: cw.ModelBuilder().add_ground(keyframes=[(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0))]), "keyframes[0].rotation",
     "length 1"),
    (lambda: cw.ModelBuilder().add_collider_mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], scale=INF), "scale",
     str(LIMITS["scale"])),
    (lambda: cw.ModelBuilder().add_collider_mesh([[0, 0, 0], [1, 0, 0], [0, NAN, 0]], [[0, 1, 2]]), "vertices", "non-finite"),
    (lambda: grid_builder().enable_self_collision(thickness=NAN), "thickness", str(LIMITS["thickness"])),
    (lambda: grid_builder().enable_self_collision(stiffness=1e300), "stiffness", str(LIMITS["pin_stiffness"])),
    (lambda: cw.FabricMaterial(stretch_stiffness=1e300), "stretch_stiffness", str(LIMITS["stretch_stiffness"])),
    (lambda: cw.FabricMaterial(areal_density=1e-300), "areal_density", str(LIMITS["areal_density"])),
    (lambda: cw.FabricMaterial(damping=NAN), "damping", str(LIMITS["damping_time"])),
    # an indefinite membrane (C_12 = G above sqrt(C_warp C_weft)): the element's forces grow from round-off at rest
    (lambda: cw.FabricMaterial(stretch_stiffness=10.0), "shear_stiffness", "must be below sqrt(stretch_stiffness x stretch_stiffness_weft)"),
    (lambda: cw.GustyWind((NAN, 0.0, 0.0)), "mean", str(LIMITS["velocity"])),
    (lambda: cw.GustyWind((1.0, 0.0, 0.0), period=0.0), "period", str(LIMITS["gust_period"])),
    (lambda: cw.GustyWind((1.0, 0.0, 0.0), up=(0.0, 0.0, 0.0)), "up", "zero vector"),
    (lambda: cw.GustyWind((1.0, 0.0, 0.0), seed=-1), "seed", str(LIMITS["seed"])),
    (lambda: cw.ModelBuilder().add_cloth_grid().select_box((NAN, 0, 0), (1, 1, 1)), "lower[0]", str(LIMITS["position"])),
]


@pytest.mark.parametrize("call, argument, phrase", API_CASES, ids=[f"{i}-{c[1]}" for i, c in enumerate(API_CASES)])
def test_api_refuses_bad_values_naming_the_argument(call, argument, phrase):
    """Check the Python API refuses NaN/inf/zero quaternions and absurd values with a ValueError naming the argument."""
    with pytest.raises(ValueError) as info:
        call()
    message = str(info.value)
    assert argument in message and phrase in message, message


def test_quaternions_are_normalised_within_tolerance():
    """Check a slightly non-unit quaternion (rounded by hand) is accepted and stored normalised."""
    b = cw.ModelBuilder()
    col = b.add_box((0, 0, 0), (1, 1, 1), rotation=(0.0, 0.7071, 0.0, 0.7071))
    assert np.linalg.norm(col.rotation) == pytest.approx(1.0, abs=1e-12)
    h = grid_builder().add_handle([0], [(0.0, (0, 0, 0), (0.0, 0.0, 0.0, 1.001))])
    assert np.linalg.norm(h.keyframes[0].rotation) == pytest.approx(1.0, abs=1e-12)


def test_float32_products_are_refused_at_finalize():
    """Check values that are each allowed but whose products or positions leave float32 are refused by name."""
    b = cw.ModelBuilder()  # 1 cm cells 100 km from the origin: float32 spacing there is 8 mm
    b.add_cloth_grid(resolution=(8, 8), size=(0.08, 0.08), position=(1e5, 0.0, 0.0))
    with pytest.raises(InvalidValue, match=r"float32 .* use cells of at least"):
        b.finalize("cpu")
    message = scene_error({"cloth.position": [1e5, 0.0, 0.0]})  # 25 cm cells, 0.8 m needed there
    assert message.startswith("cloth:") and "float32" in message


# -- upper bounds: memory and time, estimated before allocating -------------------------------------------------

@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"cloth.grid.resolution": [20000, 20000]}, (r"cloth.grid.resolution: a 20000 x 20000 grid \(400040001 particles\) "
                                                     r"needs about 2 TB of memory and .* to build \(limit: this machine's")),
        ({"cloth.grid.resolution": [1, 10**12]}, r"cloth.grid.resolution: a 1 x 1000000000000 grid .* needs about"),
        ({"cloth.disc": {"radius": 0.5, "rings": 10**8}, "cloth.grid": None},
         r"cloth.disc.rings: a disc of 100000000 rings \(30000000300000001 particles\) needs about"),
        ({"output.frames": 10**6, "solver.substeps": 10**4},
         r"output.frames x solver.substeps: 1000000 frames x 10000 substeps = 1e10 steps would take at least .*; limit 1e8 steps"),
        ({"fit.frames": 10**6, "solver.substeps": 1000}, r"fit.frames x solver.substeps: .* limit 1e8 steps"),
    ],
)
def test_sizes_and_run_lengths_are_bounded_with_an_estimate(tmp_path, overrides, message):
    """Check a huge grid, disc or run is refused at validation (no allocation) with the memory / time estimate."""
    if overrides.get("cloth.grid", 1) is None:  # a disc instead of the shipped grid
        text = HANG.read_text().replace("grid = { resolution = [64, 64], size = [1.0, 1.0] }", "")
        text = text.replace('select = "corner:top_left"', "indices = [0]").replace('select = "corner:top_right"', "indices = [1]")
        path = tmp_path / "disc.toml"
        path.write_text(text)
        overrides = {k: v for k, v in overrides.items() if v is not None}
        with pytest.raises(SceneError, match=message):
            load_scene(path, overrides)
        return
    with pytest.raises(SceneError, match=message):
        load_scene(HANG, overrides)


def test_memory_bound_follows_the_machine(monkeypatch):
    """Check the memory limit is the machine's: with 10 MB a 64^2 grid (4225 particles, ~21 MB) is refused, through
    the scene and the API alike, and a 16^2 grid still builds."""
    v, t = cw.topology.disc_mesh(0.5, 40)
    monkeypatch.setattr(validation, "memory_limit_bytes", lambda: 10**7)
    with pytest.raises(SceneError, match=r"cloth.grid.resolution: a 64 x 64 grid \(4225 particles\) needs about 21.1 MB"):
        load_scene(HANG)
    with pytest.raises(InvalidValue, match=r"^resolution: a 64 x 64 grid"):
        cw.ModelBuilder().add_cloth_grid(resolution=(64, 64))
    with pytest.raises(InvalidValue, match=r"^rings: a disc of 100 rings"):
        cw.ModelBuilder().add_cloth_disc(radius=0.5, rings=100)
    with pytest.raises(InvalidValue, match=r"^vertices: a mesh of 4921 vertices"):
        cw.ModelBuilder().add_cloth_mesh(v, t)
    cw.ModelBuilder().add_cloth_grid(resolution=(16, 16))


# -- unreadable inputs: scene text and mesh files ---------------------------------------------------------------

def test_non_utf8_scene_names_the_file_and_the_byte(tmp_path):
    """Check a scene with a byte that is not UTF-8 raises a SceneError naming the file, the byte offset, line, column."""
    path = tmp_path / "latin1.toml"
    path.write_bytes('[scene]\ndescription = "caf\xe9"\n'.encode("latin-1"))
    with pytest.raises(SceneError, match=r"latin1.toml: not UTF-8 text .*byte 0xe9 at offset 26 \(line 2, column 19\)"):
        load_scene(path)
    assert main(["validate", str(path)]) == 2
    bom = tmp_path / "bom.toml"
    bom.write_bytes(b"\xef\xbb\xbf" + HANG.read_bytes())
    assert load_scene(bom).get("cloth.grid.resolution") == [64, 64]


MESH_SUFFIXES = ["obj", "ply", "stl", "glb", "gltf", "off", "dae", "3mf", "xyz", "zip", "usd", "usda", "usdc"]


@pytest.mark.parametrize("suffix", MESH_SUFFIXES)
def test_random_bytes_as_a_mesh_name_the_file_and_the_problem(tmp_path, suffix):
    """Check random bytes under any mesh extension give a MeshError naming the file and the format it is not
    (never a missing module), for cloths, colliders and scenes."""
    path = tmp_path / f"noise.{suffix}"
    path.write_bytes(np.random.default_rng(14).bytes(3000))
    with pytest.raises(cw.MeshError) as info:
        cw.ModelBuilder().add_cloth_mesh_file(path)
    message = str(info.value)
    assert str(path) in message and "not a valid" in message, message
    assert "module" not in message and "pip" not in message, message
    with pytest.raises(cw.MeshError, match="not a valid"):
        cw.ModelBuilder().add_collider_mesh_file(path)
    scene = tmp_path / "s.toml"
    scene.write_text(f'[cloth]\nmesh = "noise.{suffix}"\n')
    with pytest.raises(SceneError, match=rf"^cloth.mesh: .*noise.{suffix}: not a valid"):
        build_model(load_scene(scene), "cpu")


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("empty.obj", b"", "the file is empty"),
        ("short.stl", b"solid?\x00\x01", "shorter than a binary STL header"),
        ("points.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "3 points but no faces"),
        ("words.obj", b"hello world\n", "holds no triangle geometry"),
        ("shape.svg", b"<svg/>", "unknown mesh format '.svg'; readable here: "),
        ("broken.usda", b"#usda 1.0\ndef Mesh {{{\n", "cannot open .*broken.usda as USD: .*parse error"),
        ("nomesh.usda", b"#usda 1.0\n", "holds no UsdGeom.Mesh"),
    ],
)
def test_malformed_mesh_files_say_what_is_wrong(tmp_path, name, content, message):
    """Check empty, truncated, point-only, unsupported and unparsable files are MeshErrors saying what is wrong."""
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(cw.MeshError, match=message):
        cw.ModelBuilder().add_cloth_mesh_file(path)


def test_truncated_binary_files(tmp_path):
    """Check a binary STL and a USD crate cut in half are refused with the file and the reason."""
    import trimesh

    t = cw.topology.grid_topology((6, 4), (0.6, 0.4))
    trimesh.Trimesh(t.positions, t.triangles, process=False).export(tmp_path / "patch.stl")
    data = (tmp_path / "patch.stl").read_bytes()
    (tmp_path / "cut.stl").write_bytes(data[: len(data) // 2])
    with pytest.raises(cw.MeshError, match=r"cut.stl: not a valid STL file: .*48 triangles \(2484 bytes\) but the file has 1242"):
        cw.ModelBuilder().add_cloth_mesh_file(tmp_path / "cut.stl")
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(tmp_path / "patch.usdc"))
    mesh = UsdGeom.Mesh.Define(stage, "/patch")
    mesh.GetPointsAttr().Set(t.positions.tolist())
    mesh.GetFaceVertexCountsAttr().Set([3] * len(t.triangles))
    mesh.GetFaceVertexIndicesAttr().Set(t.triangles.ravel().tolist())
    stage.Save()
    data = (tmp_path / "patch.usdc").read_bytes()
    (tmp_path / "cut.usdc").write_bytes(data[: len(data) // 2])
    with pytest.raises(cw.MeshError, match=r"cannot open .*cut.usdc as USD: .*truncated"):
        cw.ModelBuilder().add_cloth_mesh_file(tmp_path / "cut.usdc")


# -- winding: made consistent, outward on closed surfaces, following the UVs or the majority otherwise ----------

def face_normals(vertices, triangles):
    x = np.asarray(vertices, float)[np.asarray(triangles)]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_flipped_faces_are_reoriented_with_a_warning():
    """Check a flat sheet with a third of its triangles flipped gets every normal along +z (the majority), with a
    warning; a consistent sheet loads silently and unchanged."""
    t = cw.topology.grid_topology((6, 6), (1.0, 1.0))
    tris = t.triangles.copy()
    flipped = np.arange(len(tris)) % 3 == 0
    tris[flipped] = tris[flipped][:, ::-1]
    with pytest.warns(UserWarning, match=r"reoriented 24 of 72 triangle\(s\) so the winding is consistent \(following the majority"):
        cloth = cw.ModelBuilder().add_cloth_mesh(t.positions, tris)
    assert np.allclose(face_normals(cloth.topology.positions, cloth.topology.triangles)[:, 2], 1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cloth = cw.ModelBuilder().add_cloth_mesh(t.positions, t.triangles)
    np.testing.assert_array_equal(cloth.topology.triangles, t.triangles)


def test_winding_follows_the_uvs_and_corner_uvs_follow_the_flip():
    """Check a sheet wound the wrong way round everywhere (normals -z) but with UVs laid out counter-clockwise is
    turned to follow its UVs, and each corner keeps its UV."""
    t = cw.topology.grid_topology((4, 4), (1.0, 1.0))
    tris = t.triangles[:, ::-1].copy()
    uvs = t.positions[:, :2]
    with pytest.warns(UserWarning, match="reoriented 32 of 32 .*following the UV layout"):
        cloth = cw.ModelBuilder().add_cloth_mesh(t.positions, tris, uvs=uvs)
    topo = cloth.topology
    assert np.allclose(face_normals(topo.positions, topo.triangles)[:, 2], 1.0)
    np.testing.assert_allclose(topo.corner_uv, topo.positions[topo.triangles][:, :, :2])  # UV = xy at every corner


def test_closed_meshes_face_outward():
    """Check a closed box with one face flipped, and one wound inside out, end outward for cloths and colliders."""
    import trimesh

    box = trimesh.creation.box((1.0, 1.0, 1.0))
    one = np.asarray(box.faces).copy()
    one[0] = one[0][::-1]
    inside_out = np.asarray(box.faces)[:, ::-1]
    for faces, count in ((one, 1), (inside_out, 12)):
        with pytest.warns(UserWarning, match=rf"reoriented {count} of 12 .*outward on closed surfaces"):
            cloth = cw.ModelBuilder().add_cloth_mesh(box.vertices, faces)
        x = cloth.topology.positions[cloth.topology.triangles]
        outward = np.einsum("ij,ij->i", face_normals(cloth.topology.positions, cloth.topology.triangles), x.mean(1))
        assert np.all(outward > 0.0)
        with pytest.warns(UserWarning, match="outward"):
            col = cw.ModelBuilder().add_collider_mesh(box.vertices, faces)
        assert col.distance([[0.0, 0.0, 0.0]])[0] < 0.0 and col.distance([[0.0, 0.0, 2.0]])[0] > 0.0


def test_a_moebius_band_is_reported_as_not_orientable():
    """Check a Moebius band (no consistent winding exists) loads with a warning saying so."""
    n = 24
    u = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    verts = []
    for w in (-0.1, 0.1):
        verts.append(np.stack([(1 + w * np.cos(u / 2)) * np.cos(u), (1 + w * np.cos(u / 2)) * np.sin(u), w * np.sin(u / 2)], 1))
    v = np.concatenate(verts)  # rows 0..n-1 at w = -0.1, n..2n-1 at w = +0.1
    tris = []
    for i in range(n):
        j = (i + 1) % n
        a, b = (i, i + n)
        c, d = (j, j + n) if j else (n, 0)  # the half twist: the strip's sides swap where it closes
        tris += [(a, c, d), (a, d, b)]
    with pytest.warns(UserWarning, match="not orientable"):
        cw.ModelBuilder().add_cloth_mesh(v, tris)


# -- the shipped scenes still validate ---------------------------------------------------------------------------

@pytest.mark.parametrize("path", SCENES, ids=lambda p: p.stem)
def test_shipped_scenes_pass_cloth_warp_validate(path, capsys):
    """Check `cloth-warp validate NAME` accepts every shipped scene, with no winding repair on its meshes."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        assert main(["validate", path.stem]) == 0
    assert "valid" in capsys.readouterr().out


def test_validate_checks_a_garment_scene_without_dressing_it(capsys, monkeypatch):
    """Check `cloth-warp validate` builds a garment scene (patterns, body, attachments checked) without running its
    dressing (a simulation of seconds), and says that the run will."""
    from cloth_warp import dressing

    def refuse(*args, **kwargs):
        raise AssertionError("validate ran the dressing")

    monkeypatch.setattr(dressing, "dress", refuse)
    monkeypatch.setattr(dressing, "settle", refuse)
    assert main(["validate", "skirt_walk"]) == 0
    out = capsys.readouterr().out
    assert "valid" in out and "1 s sewing, 1.5 s settling (run by `cloth-warp run`, not by validate)" in out


def test_scene_text_parses_inline(tmp_path):
    """Check parse_scene applies the same gate as load_scene (text given directly)."""
    with pytest.raises(SceneError, match=r"forces.gravity: its length must be <= 1000 m/s\^2"):
        parse_scene("[forces]\ngravity = [0.0, 1e300, 0.0]\n")
