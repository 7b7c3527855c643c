"""Scalpels that cut on the device (``Simulator(cut_on_device=True)``, ``sim.device_cut.DeviceCuts``):
each step equals the step of the same simulator cutting on the host (same nodes, same elements, the
positions to 1e-10 in float64), which the cuts-in-place tests hold against simulators built from
the cut meshes; through a whole section, with a slit left between strips, when the spare rows run
out (the simulator is built again from the cut mesh and the step run again), and before a removal
or a host cut (built again first). Where it cannot serve a simulator the host cuts. The scene file's
``[solver] cut_on_device``. On CUDA the cut is replayed from a captured graph and its steps equal
the CPU's."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.errors import SceneError, SolverError
from tensormass_torch.ops import library
from tensormass_torch.sim.device_cut import DeviceCuts
from tensormass_torch.sim.scene_file import load_scene

pytestmark = pytest.mark.skipif(not library.ensure_registered(), reason="the compiled extension is not available")

MATERIAL = tm.Material(young=2e5, poisson=0.3, density=1000.0)


def beam(device="cpu", spare=96, cut_on_device=True, dtype=torch.float64, material=MATERIAL, **kwargs):
    mesh = tm.beam_mesh(8, 3, 3, size=(1.0, 0.3, 0.3), dtype=dtype)
    fixed = mesh.vertices[:, 0] < 1e-9
    body = tm.Body(mesh.to(device), material, fixed=fixed.to(device), name="beam")
    cg_tol = 1e-10 if dtype == torch.float64 else 1e-5
    return tm.Simulator([body], dt=0.005, gravity=(0.0, -9.81, 0.0), cg_tol=cg_tol, spare_nodes=spare,
                        cut_on_device=cut_on_device, **kwargs)


def scalpel(steps, x=0.53, top=0.35, bottom=-0.05, dt=0.005):
    """An edge along z that goes down through the beam at x over ``steps`` steps."""
    return tm.Scalpel("beam", times=[0.0, steps * dt], edges=[[[x, top, -1.0], [x, top, 1.3]],
                                                             [[x, bottom, -1.0], [x, bottom, 1.3]]])


def assert_same(sim, want, tol=1e-10):
    assert sim.used_nodes == want.used_nodes
    torch.testing.assert_close(sim.positions(0).cpu(), want.positions(0).cpu(), rtol=0, atol=tol)
    torch.testing.assert_close(sim.velocities(0).cpu(), want.velocities(0).cpu(), rtol=0, atol=1e3 * tol)


def run_both(steps, knife, **kwargs):
    device_sim, host_sim = beam(**kwargs), beam(cut_on_device=False, **{k: v for k, v in kwargs.items()})
    for sim in (device_sim, host_sim):
        sim.add_scalpel(knife)
    for _ in range(steps):
        device_sim.step()
        host_sim.step()
        assert_same(device_sim, host_sim)
    return device_sim, host_sim


def test_a_scalpel_cut_on_the_device_steps_as_the_same_cut_on_the_host():
    device_sim, host_sim = run_both(24, scalpel(20))
    assert device_sim._device_cuts is not None and device_sim._device_cuts.added > 0
    assert device_sim.used_nodes[0] > tm.beam_mesh(8, 3, 3).num_vertices  # the beam was cut through
    # the meshes read back from the device are the host's
    assert torch.equal(device_sim.bodies[0].mesh.elements.cpu(), host_sim.bodies[0].mesh.elements.cpu())
    torch.testing.assert_close(device_sim.bodies[0].mesh.vertices, host_sim.bodies[0].mesh.vertices)
    assert torch.equal(device_sim.mesh(0).elements.cpu(), host_sim.mesh(0).elements.cpu())


def test_a_scalpel_that_names_its_body_does_not_read_the_meshes_back_each_step():
    sim = beam()
    sim.add_scalpel(scalpel(20))  # (its body given by name: "beam")
    sim.step(12)
    assert sim._device_cuts.added > 0 and sim._views_stale  # the mesh is read back only when asked for
    before = sim.used_nodes[0]
    sim.step()
    assert sim._views_stale and sim.used_nodes[0] >= before
    assert sim.bodies[0].mesh.num_vertices == sim.used_nodes[0] and not sim._views_stale


def test_a_partial_cut_leaves_a_slit_that_the_next_strips_part():
    knife = scalpel(30, top=0.35, bottom=0.1)  # stops inside the beam: a slit along its front
    device_sim, host_sim = run_both(34, knife)
    assert device_sim._device_cuts.added > 0


def test_when_the_spare_rows_run_out_the_simulator_is_built_again_and_the_step_is_the_same():
    device_sim, host_sim = run_both(24, scalpel(20), spare=6)
    assert device_sim.ptr[1] - device_sim.used_nodes[0] > 6  # built again with room


def test_a_removal_and_a_host_cut_after_cuts_on_the_device_build_the_simulator_again_first():
    device_sim, host_sim = run_both(10, scalpel(20))
    for sim in (device_sim, host_sim):
        sim.remove_elements(0, [5, 17])
        sim.cut(0, tm.Blade.swept((0.8, -1, -1), (0.8, 2, -1), (0.8, -1, 2), (0.8, 2, 2)))
    for _ in range(6):
        device_sim.step()
        host_sim.step()
        assert_same(device_sim, host_sim)


def test_it_cuts_on_the_host_where_it_cannot_serve_the_simulator():
    corotational = tm.Material(young=2e5, poisson=0.3, density=1000.0, model="corotational")
    for sim, why in [(beam(material=corotational), "not one hooke tensor-form group"),
                     (beam(warm_start="project"), "warm_start='project'"),
                     (beam(integrator="bdf2"), "the bdf2 integrator")]:
        assert DeviceCuts.unavailable(sim) == why
        sim.add_scalpel(scalpel(4))
        sim.step(3)
        assert sim._device_cuts is None
    assert DeviceCuts.unavailable(beam()) is None
    # no spare rows: the first cut builds the simulator again with room on the host, the next
    # ones are made on the device
    sim = beam(spare=0)
    assert DeviceCuts.unavailable(sim) == "no spare rows"
    sim.add_scalpel(scalpel(4))
    sim.step()
    assert sim._device_cuts is None and DeviceCuts.unavailable(sim) is None
    sim.step(2)
    assert sim._device_cuts is not None


def test_the_warm_start_of_the_steps_is_kept_across_cuts_on_the_device():
    device_sim, host_sim = run_both(16, scalpel(12), warm_start="extrapolate")
    assert device_sim._device_cuts.added > 0 and device_sim._solutions_before()


def test_a_failed_step_after_a_cut_on_the_device_leaves_the_cut_state_in_tensors_of_its_own(monkeypatch):
    sim = beam()
    sim.add_scalpel(scalpel(20))
    sim.step(12)
    cuts = sim._device_cuts
    assert cuts is not None and cuts.added > 0

    def failing():
        raise SolverError("a failed solve", ["breakdown"])
    monkeypatch.setattr(sim, "_advance", failing)
    with pytest.raises(SolverError):
        sim.step()
    assert sim.x is not cuts.positions and sim.v is not cuts.velocities
    assert torch.equal(sim.x, cuts.positions) and torch.equal(sim.v, cuts.velocities)  # the cut, made
    monkeypatch.undo()
    held, kept = sim.x, sim.x.clone()
    sim.step()  # cuts again: what the user held after the failure does not change
    assert torch.equal(held, kept) and sim.x is not cuts.positions


def test_cut_on_device_must_be_a_bool():
    with pytest.raises(SceneError, match="cut_on_device must be True or False"):
        beam(cut_on_device="yes")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
def test_on_cuda_the_captured_cut_steps_as_the_cpu(dtype):
    device_sim, cpu_sim = beam("cuda", dtype=dtype), beam("cpu", dtype=dtype)
    for sim in (device_sim, cpu_sim):  # two scalpels: two cuts queued before each step
        sim.add_scalpel(scalpel(20))
        sim.add_scalpel(scalpel(16, x=0.28))
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    for _ in range(24):
        device_sim.step()
        cpu_sim.step()
        assert_same(device_sim, cpu_sim, tol)
    assert device_sim._device_cuts.captured is not None and device_sim._device_cuts.added > 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_random_scalpels_and_removals_over_thousands_of_steps_on_cuda():
    """The long GPU fuzz of the cut on the device: a scalpel of random place, tilt, depth and speed
    every 30 steps, and now and then an element removed, over 3,000 captured steps of a beam whose
    pieces fall onto a floor. Every step equals that of a twin that cuts on the host (on CUDA
    too; to 1e-7: a row rebuilt on the device lists its neighbours as first met in the node's
    star, not in the host tables' order, so the solves round differently and a free piece carries
    that as a drift: 7e-9 after 3,000
    steps of this scene on the CPU), the state is finite, every node with an element has a positive mass, nodes with none
    have none, and the mass is kept (what the body holds plus what removals took)."""
    gen = torch.Generator().manual_seed(5)

    def rand(low, high):
        return low + (high - low) * float(torch.rand((), generator=gen, dtype=torch.float64))

    floor = [tm.Plane((0.0, 1.0, 0.0), -0.6, 1e5)]
    device_sim = beam("cuda", spare=400, planes=floor)
    host_sim = beam("cuda", cut_on_device=False, planes=floor)
    total = float(device_sim.model.lumped_mass().sum())
    removals = 0
    for step in range(3000):
        if step % 30 == 0:
            x0, x1, steps = rand(0.05, 0.95), rand(0.05, 0.95), int(rand(8, 30))
            knife = tm.Scalpel("beam", times=[device_sim.time, device_sim.time + steps * 0.005],
                               edges=[[[x0, 0.4, -1.0], [x0 + rand(-0.2, 0.2), 0.4, 1.3]],
                                      [[x1, rand(-0.7, 0.2), -1.0], [x1 + rand(-0.2, 0.2), rand(-0.7, 0.2), 1.3]]])
            for sim in (device_sim, host_sim):
                sim.add_scalpel(knife)
        if rand(0, 1) < 0.01:
            alive = torch.nonzero(device_sim.alive_elements(0)).flatten().cpu()
            if alive.numel() > 8:
                gone = [int(alive[int(rand(0, alive.numel() - 1))])]
                for sim in (device_sim, host_sim):
                    sim.remove_elements(0, gone)
                removals += 1
        device_sim.step()
        host_sim.step()
        assert_same(device_sim, host_sim, 1e-7)
        assert bool(torch.isfinite(device_sim.x).all()) and bool(torch.isfinite(device_sim.v).all())
        mass, isolated = device_sim.model.lumped_mass(), device_sim.model.isolated_nodes()
        assert bool((mass[~isolated] > 0).all()) and bool((mass[isolated] == 0).all()), step
        assert abs(float(mass.sum() + device_sim.removed_mass.sum()) - total) <= 1e-12 * total, step
    assert device_sim._device_cuts is not None and removals > 10
    assert device_sim.used_nodes[0] > tm.beam_mesh(8, 3, 3).num_vertices + 100  # cut many times


def test_the_scene_file_key(tmp_path):
    text = Path("scenes/cut.toml").read_text().replace('model = "corotational"', 'model = "hooke"')
    path = tmp_path / "cut.toml"
    path.write_text(text.replace("[solver]\n", "[solver]\ncut_on_device = true\n"))
    scene = load_scene(path, dtype="float64")
    sim = scene.simulator
    assert sim.cut_on_device
    sim.step(40)  # the scalpel reaches the ball at 0.1 s and cuts on the device from there
    assert sim._device_cuts is not None and sim._device_cuts.added > 0
    path.write_text(text.replace("[solver]\n", '[solver]\ncut_on_device = "yes"\n'))
    with pytest.raises(SceneError, match="cut_on_device"):
        load_scene(path)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_scalpels_cut_on_the_device_as_on_the_host(seed):
    """Scalpels of random position, tilt and speed, two of them crossing, with a removal between
    their cuts: every step equal to the host's."""
    gen = torch.Generator().manual_seed(seed)

    def rand(low, high):
        return low + (high - low) * float(torch.rand((), generator=gen, dtype=torch.float64))

    def knife():
        x0, x1 = rand(0.2, 0.9), rand(0.2, 0.9)
        steps = int(rand(8, 30))
        return tm.Scalpel("beam", times=[rand(0.0, 0.05), rand(0.0, 0.05) + steps * 0.005],
                          edges=[[[x0, 0.4, -1.0], [x0 + rand(-0.1, 0.1), 0.4, 1.3]],
                                 [[x1, rand(-0.1, 0.2), -1.0], [x1 + rand(-0.1, 0.1), rand(-0.1, 0.2), 1.3]]])

    knives = [knife(), knife()]
    device_sim, host_sim = beam(spare=int(rand(8, 200))), beam(cut_on_device=False)
    for sim in (device_sim, host_sim):
        for k in knives:
            sim.add_scalpel(k)
    removed = int(rand(0, device_sim.model.num_elements - 1))
    for step in range(40):
        if step == 20:
            for sim in (device_sim, host_sim):
                sim.remove_elements(0, [removed])
        device_sim.step()
        host_sim.step()
        assert_same(device_sim, host_sim)


def test_a_removal_before_any_node_split_on_the_device_is_seen_by_the_next_cut():
    """The cut on the device made (its tables, alive elements, captured buffers), no node split yet,
    then elements removed: the next cuts skip them as the host's do."""
    device_sim, host_sim = beam(), beam(cut_on_device=False)
    knife = scalpel(20)
    assert device_sim._device_cutter(0) is not None
    for sim in (device_sim, host_sim):
        sim.remove_elements(0, list(range(100, 160)))
        sim.add_scalpel(knife)
    assert device_sim._device_cuts is None  # made again at the next cut
    for _ in range(24):
        device_sim.step()
        host_sim.step()
        assert_same(device_sim, host_sim)
    assert device_sim._device_cuts is not None and device_sim._device_cuts.added > 0


def test_held_nodes_cut_on_the_host():
    sim = beam()
    sim.hold_nodes(0, [40], sim.positions(0)[40:41].clone())
    assert DeviceCuts.unavailable(sim) == "held nodes"
