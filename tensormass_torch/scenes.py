"""Built-in scenes: ready-made simulators for the command line, examples and benchmarks."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict

import torch

from .contact import Plane
from .materials import Material
from .mesh import beam_mesh
from .scene import Body, Simulator


@dataclass
class Scene:
    """A simulator with the run length and output cadence it is meant for."""

    name: str
    simulator: Simulator
    steps: int
    output_every: int
    description: str


def cantilever(resolution: int = 2, model: str = "stvk", device=None, dtype=torch.float32) -> Scene:
    """A 1 m x 0.1 m x 0.1 m rubber-like beam clamped at x = 0, swinging down under gravity (-z) for 1 s.

    ``resolution`` cells across the section (10x along the length).
    """
    n = int(resolution)
    mesh = beam_mesh(10 * n, n, n, size=(1.0, 0.1, 0.1), dtype=dtype, device=device)
    material = Material(young=5e6, poisson=0.3, density=1000.0, model=model)
    body = Body(mesh, material, fixed=mesh.vertices[:, 0] <= 1e-6, name="beam")
    sim = Simulator([body], dt=0.01, gravity=(0.0, 0.0, -9.81), rayleigh_mass=0.5, rayleigh_stiffness=0.002,
                    cg_tol=1e-4, cg_max_iter=500)
    return Scene("cantilever", sim, steps=100, output_every=5,
                 description=f"cantilever, {model}, {mesh.num_elements} tets, dt 0.01 s, 100 steps")


def sofa_beam(model: str = "hooke", device=None, dtype=torch.float32, scale: int = 1) -> Scene:
    """SOFA's GPU benchmark beam (``TetrahedronFEMForceField_beam16x16x76_gpu.scn``).

    76 x 16 x 16 nodes (101,250 tets) over x in [0, 19], y in [6, 10], z in [-2, 2]; E = 1000,
    nu = 0.3, total mass 50, gravity -9 along y, dt = 0.04, r_M = r_K = 0.1, 10 CG iterations
    (tolerance 1e-6, the cap is a budget as in SOFA), nodes with x <= 0.1 fixed, a plane of normal
    (0, 1, 0) at d = 2 with k = 1e4. ``scale`` > 1 divides the resolution (for quick runs).
    """
    nx, nyz = max(75 // scale, 1), max(15 // scale, 1)
    mesh = beam_mesh(nx, nyz, nyz, size=(19.0, 4.0, 4.0), origin=(0.0, 6.0, -2.0), dtype=dtype, device=device)
    density = 50.0 / (19.0 * 4.0 * 4.0)
    # SOFA's "large" method extracts rotations with its QR frame: the same here.
    material = Material(young=1000.0, poisson=0.3, density=density, model=model, rotation="qr")
    body = Body(mesh, material, fixed=mesh.vertices[:, 0] <= 0.1, name="sofa-beam")
    sim = Simulator([body], dt=0.04, gravity=(0.0, -9.0, 0.0), rayleigh_mass=0.1, rayleigh_stiffness=0.1,
                    planes=[Plane((0.0, 1.0, 0.0), 2.0, 1e4)], cg_tol=1e-6, cg_max_iter=10,
                    require_convergence=False)
    return Scene("sofa_beam", sim, steps=100, output_every=10,
                 description=f"SOFA GPU benchmark beam, {model}, {mesh.num_elements} tets, 10 CG iterations")


SCENES: Dict[str, Callable[..., Scene]] = {"cantilever": cantilever, "sofa_beam": sofa_beam}
