"""cloth_warp: differentiable mass-spring cloth simulation in NVIDIA Warp.

Typical use::

    import cloth_warp as cw
    builder = cw.ModelBuilder()
    cloth = builder.add_cloth_grid(resolution=(32, 32), size=(1.0, 1.0), material="cotton",
                                   rotation=cw.quat_from_axis_angle((1, 0, 0), 90.0), position=(0, 1, 0))
    builder.pin(cloth.select("corner:top_left"))
    model = builder.finalize(device="cpu")
    sim = cw.Simulator(model, cw.SolverSymplecticEuler(model), fps=60, substeps=32)
    for _ in range(60):
        sim.step_frame()
"""

__version__ = "0.1.0"

import importlib as _importlib
import logging as _logging

# Names are imported on first use (PEP 562), so `cloth-warp --help` and a Ctrl-C in the first second do not
# wait for Warp, USD and every module to load.
_EXPORTS = {
    "builder": ["ClothRef", "ModelBuilder", "load_mesh_file", "quat_from_axis_angle"],
    "calibrate": ["CalibrationResult", "FabricMeasurements"],
    "cache": ["CacheError", "CacheReader", "UsdCacheWriter", "open_cache"],
    "diagnostics": ["Diagnostics", "StepStats", "StrainLimitReport"],
    "gradients": ["CentroidLoss", "ChamferLoss", "ChordAngleLoss", "Loss", "LossSum", "PositionLoss", "Rollout"],
    "materials": ["FabricMaterial"],
    "model": ["Control", "Handle", "Keyframe", "Model", "ModelFlags", "State"],
    "outputs": ["CacheWriteError", "OutputBusy"],
    "runner": ["run_scene"],
    "scene": ["SceneError", "load_scene"],
    "simulator": ["Simulator"],
    "solvers": ["AdaptiveStepper", "LinearSolver", "SimulationDiverged", "SolverExplicitEuler", "SolverImplicitEuler",
                "SolverMidpoint", "SolverRK4", "SolverSymplecticEuler", "StepCheck", "StrainLimitWarning", "StrainLimiter", "make_solver"],
    "topology": ["BendingModel", "MembraneModel", "MeshError", "SpringKind", "SpringLaw", "SpringModel"],
    "validation": ["InvalidValue", "LIMITS"],
    "wind": ["GustyWind"],
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}


def __getattr__(name):
    if name in _WHERE:
        value = getattr(_importlib.import_module(f".{_WHERE[name]}", __name__), name)
    elif name in ("materials", "topology"):
        value = _importlib.import_module(f".{name}", __name__)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))


# A library logs, it never prints: the application (or cloth-warp's CLI) configures handlers.
_logging.getLogger(__name__).addHandler(_logging.NullHandler())

__all__ = sorted([*_WHERE, "materials", "topology"])
