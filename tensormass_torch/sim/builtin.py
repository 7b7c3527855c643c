"""Built-in scenes: ready-made simulators for the command line, examples and benchmarks."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Dict

import torch

from ..errors import SceneError
from ..mesh.beams import beam_mesh
from ..physics.contact import Plane
from ..physics.materials import Material
from .scalpel import Scalpel
from .simulator import Body, Simulator


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
                    cg_tol=1e-4)
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


def paper_beam(resolution: int = 2, model: str = "stvk", device=None, dtype=torch.float32, steps: int = 150) -> Scene:
    """The beam of the paper's Figures 1 and 2: 1 m x 0.4 m x 0.25 m, E = 1e5 Pa, nu = 0.3,
    rho = 1000, clamped at x = 0 and falling under gravity (-z), dt = 0.01 s, everything else on
    the simulator's defaults (a converged CG, stvk on its definite tangent).

    ``resolution`` r: 20 r x 8 r x 5 r cells, 4,800 r^3 tets (r = 2: 38,400; r = 4: the paper's
    307,200). Soft for its size, the beam swings down past the vertical: the exact stvk tangent
    is indefinite there (``Material(tangent="exact")`` breaks CG down within 30 steps).
    """
    r = int(resolution)
    if r < 1:
        raise SceneError(f"resolution must be a positive integer, got {resolution!r}")
    mesh = beam_mesh(20 * r, 8 * r, 5 * r, size=(1.0, 0.4, 0.25), dtype=dtype, device=device)
    material = Material(young=1e5, poisson=0.3, density=1000.0, model=model)
    body = Body(mesh, material, fixed=mesh.vertices[:, 0] <= 1e-6, name="beam")
    sim = Simulator([body], dt=0.01, gravity=(0.0, 0.0, -9.81))
    return Scene("paper_beam", sim, steps=steps, output_every=10,
                 description=f"the paper's beam, {model}, {mesh.num_elements} tets, dt 0.01 s, {steps} steps")


def _smooth_ramp(s: float) -> float:
    """0 -> 1 over s in [0, 1] with zero slope at both ends (s - sin(2 pi s) / 2 pi), clamped outside."""
    s = min(max(s, 0.0), 1.0)
    return s - math.sin(2.0 * math.pi * s) / (2.0 * math.pi)


def twist(resolution: int = 2, model: str = "corotational", device=None, dtype=torch.float32,
          angle: float = math.pi, steps: int = 100, dt: float = 0.01, rotation: str = "polar") -> Scene:
    """A large-rotation test: a 1 m x 0.1 m x 0.1 m rubber-like beam along x, its section centred on
    the x axis, clamped at x = 0 while the nodes of its far end (x = 1) are turned about the x axis
    through ``angle`` (default 180 degrees) along a smooth ramp over the first 80 % of the run, then
    held. No gravity; light mass damping so that the end state is close to static.

    Exact behaviour: a twisted bar of unchanged volume, with the torsion energy
    ``G J angle^2 / (2 L)`` (Saint-Venant, J = 0.1406 a^4 for a square section of side a) while the
    twist rate is small. ``hooke`` measures strain in the fixed frame and pinches the middle of the
    beam instead (its cross-section shrinks to a point at 180 degrees).

    ``resolution`` cells across the section (10x along the length); ``steps`` of ``dt`` seconds.
    """
    n = int(resolution)
    length, side = 1.0, 0.1
    mesh = beam_mesh(10 * n, n, n, size=(length, side, side), origin=(0.0, -side / 2, -side / 2),
                     dtype=dtype, device=device)
    material = Material(young=5e6, poisson=0.3, density=1000.0, model=model, rotation=rotation)
    clamped = mesh.vertices[:, 0] <= 1e-6
    turned = mesh.vertices[:, 0] >= length - 1e-6
    end_rest = mesh.vertices[turned].to(torch.float64)
    ramp_time = 0.8 * steps * dt

    def motion(t: float) -> torch.Tensor:
        theta = angle * _smooth_ramp(t / ramp_time)
        c, s = math.cos(theta), math.sin(theta)
        y, z = end_rest[:, 1], end_rest[:, 2]
        return torch.stack((end_rest[:, 0], c * y - s * z, s * y + c * z), dim=1)

    body = Body(mesh, material, fixed=clamped, prescribed=turned, motion=motion, name="beam")
    sim = Simulator([body], dt=dt, gravity=(0.0, 0.0, 0.0), rayleigh_mass=1.0, cg_tol=1e-6)
    return Scene("twist", sim, steps=steps, output_every=max(1, steps // 20),
                 description=f"twist through {math.degrees(angle):.0f} deg, {model}, {mesh.num_elements} tets, "
                             f"dt {dt} s, {steps} steps")


def spin(resolution: int = 2, model: str = "corotational", device=None, dtype=torch.float32,
         angle: float = math.pi, steps: int = 100, dt: float = 0.01, rotation: str = "polar") -> Scene:
    """A large-rotation test: a free 1 m x 0.1 m x 0.1 m rubber-like beam centred at the origin,
    spinning about the z axis at the rate that turns it through ``angle`` (default 180 degrees) in
    ``steps * dt`` seconds. No gravity, no damping, nothing fixed.

    Exact behaviour: a rigid rotation at constant angular velocity (the centrifugal stretch is
    ~1e-4): volume and kinetic energy unchanged, elastic energy ~0. ``hooke`` sees no strain in a
    linearised rotation, so its nodes fly off along straight lines: the beam shears and grows
    (volume x (1 + angle^2) at the end) and turns only atan(angle).
    """
    n = int(resolution)
    length, side = 1.0, 0.1
    mesh = beam_mesh(10 * n, n, n, size=(length, side, side), origin=(-length / 2, -side / 2, -side / 2),
                     dtype=dtype, device=device)
    material = Material(young=5e6, poisson=0.3, density=1000.0, model=model, rotation=rotation)
    omega = angle / (steps * dt)
    x = mesh.vertices
    velocity = torch.stack((-omega * x[:, 1], omega * x[:, 0], torch.zeros_like(x[:, 2])), dim=1)
    body = Body(mesh, material, velocity=velocity, name="beam")
    sim = Simulator([body], dt=dt, gravity=(0.0, 0.0, 0.0), cg_tol=1e-6)
    return Scene("spin", sim, steps=steps, output_every=max(1, steps // 20),
                 description=f"free spin through {math.degrees(angle):.0f} deg about z, {model}, "
                             f"{mesh.num_elements} tets, dt {dt} s, {steps} steps")


def cut(resolution: int = 2, model: str = "corotational", device=None, dtype=torch.float32) -> Scene:
    """A slab (1 m x 0.3 m x 0.2 m, rubber-like, E = 5 MPa) clamped at x = 0 over a floor: a
    scalpel held upright sweeps across it at x = 0.33 m from t = 0.1 s to 0.5 s, cutting a strip
    per step (``Scalpel``); once through, the far piece falls onto the floor. 1.2 s at dt 0.01 s.

    ``resolution`` r: 10 r x 3 r x 2 r cells (r = 2: 2,880 tets).
    """
    r = int(resolution)
    if r < 1:
        raise SceneError(f"resolution must be a positive integer, got {resolution!r}")
    mesh = beam_mesh(10 * r, 3 * r, 2 * r, size=(1.0, 0.3, 0.2), origin=(0.0, -0.15, -0.1), dtype=dtype,
                     device=device)
    material = Material(young=5e6, poisson=0.3, density=500.0, model=model)
    body = Body(mesh, material, fixed=mesh.vertices[:, 0] <= 1e-6, name="slab")
    sim = Simulator([body], dt=0.01, gravity=(0.0, 0.0, -9.81), planes=[Plane((0.0, 0.0, 1.0), -0.5, 1e5)],
                    rayleigh_mass=0.5, cg_tol=1e-5)
    edge = [[0.33, -0.3, -0.3], [0.33, -0.3, 0.3]]  # upright, beside the slab; it moves along +y
    sim.add_scalpel(Scalpel("slab", times=[0.1, 0.5], edges=[edge, [[p[0], 0.3, p[2]] for p in edge]]))
    return Scene("cut", sim, steps=120, output_every=4,
                 description=f"a slab cut through by a scalpel, {model}, {mesh.num_elements} tets, dt 0.01 s, "
                             "120 steps")


SCENES: Dict[str, Callable[..., Scene]] = {"cantilever": cantilever, "sofa_beam": sofa_beam, "twist": twist,
                                           "spin": spin, "paper_beam": paper_beam, "cut": cut}
