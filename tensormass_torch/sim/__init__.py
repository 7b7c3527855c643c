"""The simulation layer: bodies, the simulator, scenes and what a run writes.

    simulator       Body, Simulator (a packed batch stepped by implicit Euler)
    scalpel         Scalpel: a blade edge cutting a body as it moves, between steps
    rollout         rollout: a trajectory as tensors, differentiable by the adjoint step
    builtin         the built-in scenes (cantilever, twist, spin, sofa_beam, paper_beam, cut)
    scene_file      TOML scene files, checked key by key
    diagnostics     inverted elements, volume change, allocations
    output          .vtu frames and .pvd series

It calls the solver, physics and mesh layers.
"""
from .rollout import Rollout, rollout
from .scalpel import Scalpel
from .scene_file import load_scene
from .simulator import Body, InvertedElementsWarning, Simulator

__all__ = ["Body", "InvertedElementsWarning", "Rollout", "Scalpel", "Simulator", "load_scene", "rollout"]
