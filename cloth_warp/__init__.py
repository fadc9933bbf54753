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

import logging as _logging

from . import materials, topology
from .builder import ClothRef, ModelBuilder, load_mesh_file, quat_from_axis_angle
from .cache import CacheReader, UsdCacheWriter, open_cache
from .diagnostics import Diagnostics, StepStats
from .gradients import CentroidLoss, ChamferLoss, ChordAngleLoss, Loss, PositionLoss, Rollout
from .materials import FabricMaterial
from .model import Control, Handle, Keyframe, Model, State
from .runner import run_scene
from .scene import SceneError, load_scene
from .simulator import Simulator
from .solvers import (
    AdaptiveStepper,
    LinearSolver,
    SimulationDiverged,
    SolverExplicitEuler,
    SolverImplicitEuler,
    SolverMidpoint,
    SolverRK4,
    SolverSymplecticEuler,
    StepCheck,
    StrainLimiter,
    make_solver,
)
from .topology import MeshError, SpringKind, SpringLaw, SpringModel
from .wind import GustyWind

# A library logs, it never prints: the application (or cloth-warp's CLI) configures handlers.
_logging.getLogger(__name__).addHandler(_logging.NullHandler())

__all__ = [
    "CentroidLoss",
    "ChordAngleLoss",
    "ChamferLoss",
    "Loss",
    "PositionLoss",
    "Rollout",
    "AdaptiveStepper",
    "CacheReader",
    "GustyWind",
    "SceneError",
    "UsdCacheWriter",
    "load_scene",
    "open_cache",
    "run_scene",
    "ClothRef",
    "Control",
    "Diagnostics",
    "FabricMaterial",
    "Handle",
    "Keyframe",
    "LinearSolver",
    "MeshError",
    "Model",
    "ModelBuilder",
    "SimulationDiverged",
    "Simulator",
    "SolverExplicitEuler",
    "SolverImplicitEuler",
    "SolverMidpoint",
    "SolverRK4",
    "SolverSymplecticEuler",
    "SpringKind",
    "SpringLaw",
    "SpringModel",
    "State",
    "StepCheck",
    "StepStats",
    "StrainLimiter",
    "load_mesh_file",
    "make_solver",
    "materials",
    "quat_from_axis_angle",
    "topology",
]
