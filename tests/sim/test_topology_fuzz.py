"""Random topology changes over many steps: removals and cuts (``Simulator.remove_elements``,
``Simulator.cut``) at random times on three bodies of one batch (a clamped corotational beam, a
free corotational block that falls onto the floor, a clamped hooke membrane), float64. After
every step: finite state, masses >= 0 (0 exactly on nodes left with no element, which are held),
the total mass kept (what the bodies hold plus what removals took); after every cut: no element
inverted by the split, every element with distinct nodes, the nodes' masses positive. Bad cuts
(a blade through nothing, the same blade twice) raise one error and change nothing.

The CPU run is a few thousand steps (CI); on CUDA the run is longer."""
from __future__ import annotations

import math

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.errors import MeshError
from tensormass_torch.sim.diagnostics import InversionCheck

FLOOR = -0.6


def scene(device):
    f64 = dict(dtype=torch.float64)
    beam = tm.beam_mesh(6, 2, 2, size=(1.2, 0.4, 0.4), origin=(0.0, -0.2, -0.2), **f64)
    block = tm.beam_mesh(3, 3, 2, size=(0.3, 0.3, 0.2), origin=(0.5, 0.5, 0.0), **f64)
    sheet = tm.beam_tri_mesh(6, 3, size=(0.6, 0.3), dim=3, **f64)
    sheet = tm.TriMesh(sheet.vertices + torch.tensor([0.0, -1.0, 0.3], **f64), sheet.elements)
    soft = tm.Material(model="corotational", young=3e4, poisson=0.3, density=600.0)
    bodies = [tm.Body(beam, soft, fixed=beam.vertices[:, 0] == 0, name="beam"),
              tm.Body(block, soft, name="block"),
              tm.Body(sheet, tm.Material(model="hooke", young=3e4, poisson=0.3, density=600.0, thickness=0.01),
                      fixed=sheet.vertices[:, 0] == 0, name="sheet")]
    return tm.Simulator(bodies, dt=0.005, planes=[tm.Plane((0.0, 0.0, 1.0), FLOOR, 1e5)], cg_tol=1e-8,
                        rayleigh_mass=0.5, substeps_on_failure=4, device=device)


def random_blade(sim, body, gen, partial):
    """A square blade through the body's current centre with a random normal: through the whole
    body, or (``partial``) a slit of a quarter of its size."""
    x = sim.positions(body)
    centre = x.mean(0) + 0.05 * torch.randn(3, generator=gen, dtype=x.dtype).to(x.device)
    normal = torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=x.dtype), dim=0)
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=x.dtype) if abs(float(normal[0])) < 0.9 else \
        torch.tensor([0.0, 1.0, 0.0], dtype=x.dtype)
    t1 = torch.nn.functional.normalize(torch.linalg.cross(normal, helper), dim=0).to(x.device)
    t2 = torch.linalg.cross(normal.to(x.device), t1)
    size = float((x.max(0).values - x.min(0).values).norm()) * (0.25 if partial else 2.0)
    corners = [(centre + size * (a * t1 + b * t2)).tolist() for a, b in ((-1, -1), (1, -1), (-1, 1), (1, 1))]
    return tm.Blade.swept(*corners, dtype=x.dtype, device=x.device)


def total_mass(sim):
    return float(sim.model.lumped_mass().sum() + sim.removed_mass.sum())


def check_state(sim, total):
    assert bool(torch.isfinite(sim.x).all()) and bool(torch.isfinite(sim.v).all())
    mass = sim.model.lumped_mass()
    isolated = sim.model.isolated_nodes()
    assert bool((mass[~isolated] > 0).all()) and bool((mass[isolated] == 0).all())
    assert not bool(sim.v[isolated].any())  # nodes with no element are held
    assert math.isclose(total_mass(sim), total, rel_tol=1e-12)


def fuzz(device, steps, seed=7):
    gen = torch.Generator().manual_seed(seed)
    sim = scene(device)
    total = total_mass(sim)
    counts = {"removed": 0, "cuts": 0, "cuts missed": 0}
    for step in range(steps):
        event = float(torch.rand(1, generator=gen))
        body = int(torch.randint(0, sim.num_bodies, (1,), generator=gen))
        if event < 0.04:  # a few elements go
            alive = torch.nonzero(sim.alive_elements(body)).flatten().cpu()
            if alive.numel() > 8:
                ids = alive[torch.randperm(alive.numel(), generator=gen)[:int(torch.randint(1, 4, (1,), generator=gen))]]
                sim.remove_elements(body, ids)
                counts["removed"] += ids.numel()
        elif event < 0.055:  # about 1.5 cuts per 100 steps, a third of them slits
            before = InversionCheck.for_simulator(sim)(sim.x).inverted  # alive elements only
            blade = random_blade(sim, body, gen, partial=event < 0.045)
            try:
                sim.cut(body, blade)
            except MeshError as exc:  # a slit that meets no interior face: one clear error
                assert "crosses no interior face" in str(exc)
                counts["cuts missed"] += 1
            else:
                counts["cuts"] += 1
                assert torch.equal(InversionCheck.for_simulator(sim)(sim.x).inverted, before)  # splitting inverts nothing
                for b in sim.bodies:
                    e = b.mesh.elements
                    assert bool((torch.sort(e, 1).values.diff(dim=1) > 0).all())  # distinct nodes
        sim.step()
        check_state(sim, total)
    lowest = float(sim.x[:, 2][~sim.model.isolated_nodes()].min())
    assert lowest > FLOOR - 0.05  # pieces rest on the floor, not through it
    return counts


def test_random_removals_and_cuts_over_a_thousand_steps():
    # (CUDA's run below takes 10,000 steps; the CPU's 1,000 keep the suite's time)
    counts = fuzz("cpu", 1000)
    assert counts["removed"] > 25 and counts["cuts"] >= 5, counts


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_random_removals_and_cuts_over_many_steps_on_cuda():
    counts = fuzz("cuda", 10000, seed=11)
    # the bodies are shredded long before the end (removals stop at 8 elements left, slits miss
    # small pieces): the counts are those of the first thousands of steps
    assert counts["removed"] > 100 and counts["cuts"] >= 15, counts


def test_bad_cuts_raise_one_error_and_change_nothing():
    sim = scene("cpu")
    sim.step(3)
    through = tm.Blade.swept((0.61, -1, -1), (0.61, 1, -1), (0.61, -1, 1), (0.61, 1, 1))  # across the beam
    far = tm.Blade.swept((5, -1, -1), (5, 1, -1), (5, -1, 1), (5, 1, 1))

    def state():
        return (sim.x.clone(), sim.v.clone(), sim.model.lumped_mass().clone(), sim.bodies[0].mesh.elements.clone(),
                sim.time)

    def assert_unchanged(before):
        after = state()
        for a, b in zip(before[:4], after[:4]):
            assert torch.equal(a, b)
        assert before[4] == after[4]

    before = state()
    for body, blade, error, message in [
            (0, far, MeshError, "crosses no interior face"), (0, "blade", tm.SceneError, "tm.Blade"),
            (5, through, tm.SceneError, "body index"), ("nobody", through, tm.SceneError, "no body named")]:
        with pytest.raises(error, match=message):
            sim.cut(body, blade)
        assert_unchanged(before)
    assert sim.cut(0, through) > 0
    before = state()
    with pytest.raises(MeshError, match="crosses no interior face"):  # the same blade again: nothing left to cut
        sim.cut(0, through)
    assert_unchanged(before)
