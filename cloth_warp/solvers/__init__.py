"""Integrators behind one interface: ``solver.step(state_in, state_out, control, dt)``."""

from .adaptive import AdaptiveStepper, DivergenceBounds, SimulationDiverged, StepCheck
from .base import SolverBase
from .explicit import (
    SolverExplicitEuler,
    SolverMidpoint,
    SolverRK4,
    SolverSymplecticEuler,
)
from .implicit import LinearSolver, SolverImplicitEuler
from .strain_limit import StrainLimiter, StrainLimitWarning

SOLVERS = {
    "explicit_euler": SolverExplicitEuler,
    "symplectic_euler": SolverSymplecticEuler,
    "midpoint": SolverMidpoint,
    "rk4": SolverRK4,
    "implicit_euler": SolverImplicitEuler,
}


def make_solver(name: str, model, **options) -> SolverBase:
    """Create a solver by name (one of SOLVERS) with keyword options."""
    try:
        cls = SOLVERS[name]
    except KeyError:
        raise ValueError(f"unknown integrator {name!r}; allowed: {', '.join(SOLVERS)}") from None
    return cls(model, **options)


__all__ = [
    "AdaptiveStepper",
    "DivergenceBounds",
    "LinearSolver",
    "SOLVERS",
    "SimulationDiverged",
    "SolverBase",
    "SolverExplicitEuler",
    "SolverImplicitEuler",
    "SolverMidpoint",
    "SolverRK4",
    "SolverSymplecticEuler",
    "StepCheck",
    "StrainLimitWarning",
    "StrainLimiter",
    "make_solver",
]
