"""Nodes held where a caller puts them (Simulator.hold_nodes / release_nodes: a grab, the viewer's
dragged node): held at a prescribed motion's positions they give that motion's run; released,
they move freely again; a simulator built without constraints gets its mask; bad input raises
and changes nothing; CUDA equals the CPU."""
import math

import pytest
import torch

import tensormass_torch as tm

DT = torch.float64


def beam(device="cpu"):
    mesh = tm.beam_mesh(8, 2, 2, size=(0.8, 0.2, 0.2), dtype=DT, device=device)
    return mesh, tm.Material(young=2e5, poisson=0.3, density=1000.0, model="corotational")


def tip_path(mesh):
    tip = torch.nonzero(mesh.vertices[:, 0] > 0.8 - 1e-9).flatten()
    rest = mesh.vertices[tip].clone()
    return tip, (lambda t: rest + torch.tensor([0.0, 0.05 * math.sin(4 * t), -0.1 * t], dtype=DT, device=rest.device))


@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def test_held_nodes_follow_as_prescribed_nodes_do(device):
    mesh, mat = beam(device)
    fixed = mesh.vertices[:, 0] == 0
    tip, motion = tip_path(mesh)
    prescribed = tm.Simulator([tm.Body(mesh, mat, fixed=fixed, prescribed=tip, motion=motion)], dt=0.01,
                              cg_tol=1e-12, rayleigh_mass=0.2)
    held = tm.Simulator([tm.Body(mesh, mat, fixed=fixed)], dt=0.01, cg_tol=1e-12, rayleigh_mass=0.2)
    for k in range(15):
        prescribed.step()
        held.hold_nodes(0, tip, motion(0.01 * (k + 1)))
        held.step()
    torch.testing.assert_close(held.x, prescribed.x, rtol=0, atol=1e-11)
    torch.testing.assert_close(held.v, prescribed.v, rtol=0, atol=1e-9)
    held.release_nodes()
    before = held.x[tip].clone()
    held.step(3)
    assert float((held.x[tip] - before).norm()) > 1e-4  # free again
    assert bool((held.system.free[tip] == 1).all())


def test_a_simulator_without_constraints_and_releasing():
    """A free block (no constraint, no mask) grabbed at one node: it hangs from it under gravity;
    holding other nodes replaces the first; released, the block falls."""
    mesh, mat = beam()
    sim = tm.Simulator([tm.Body(mesh, mat)], dt=0.01, cg_tol=1e-10, rayleigh_mass=1.0)
    assert sim.system.free is None
    corner = int(torch.argmax(mesh.vertices.sum(1)))
    sim.hold_nodes(0, [corner], mesh.vertices[corner][None])
    sim.step(30)
    torch.testing.assert_close(sim.x[corner], mesh.vertices[corner], rtol=0, atol=1e-12)
    assert float(sim.x[:, 2].min()) < float(mesh.vertices[:, 2].min()) - 0.01  # the rest hangs below
    sim.hold_nodes(0, [0, 1], mesh.vertices[:2])
    assert sim._held[0].tolist() == [0, 1] and float(sim.system.free[corner]) == 1.0
    sim.release_nodes()
    z = sim.x[:, 2].mean().item()
    sim.step(5)
    assert sim.x[:, 2].mean().item() < z  # falling
    assert sim._held is None and bool((sim.system.free == 1).all())


def test_bad_input_changes_nothing():
    mesh, mat = beam()
    fixed = mesh.vertices[:, 0] == 0
    sim = tm.Simulator([tm.Body(mesh, mat, fixed=fixed)], dt=0.01)
    free = sim.system.free.clone()
    for nodes, positions, match in (([0], [[0.0, 0.0, 0.0]], "fixed and prescribed nodes are held already"),
                                    ([mesh.num_vertices], [[0.0, 0.0, 0.0]], "out of range"),
                                    ([40], [[0.0, 0.0]], "positions must be \\[1, 3\\] finite"),
                                    ([40], [[0.0, float("nan"), 0.0]], "positions must be \\[1, 3\\] finite")):
        with pytest.raises(tm.SceneError, match=match):
            sim.hold_nodes(0, nodes, positions)
        assert sim._held is None and torch.equal(sim.system.free, free)
    with pytest.raises(tm.SceneError, match="release them"):
        sim.hold_nodes(0, [40], [[0.5, 0.1, 0.1]])
        tm.rollout(sim, 2)
