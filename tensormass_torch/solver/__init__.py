"""Solvers: batched conjugate gradient, implicit Euler, static equilibrium."""
from ..ops.segments import Segments
from .cg import CGResult, batched_cg
from .implicit_euler import DynamicsSystem, StepOptions, StepReport, implicit_euler_step
from .static import solve_static

__all__ = ["CGResult", "batched_cg", "DynamicsSystem", "StepOptions", "StepReport", "implicit_euler_step",
           "Segments", "solve_static"]
