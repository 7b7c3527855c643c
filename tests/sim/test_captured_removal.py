"""Removals replayed from captured graphs (``sim.captured_removal.CapturedRemovals``): on CUDA with
CUDA graphs, every removal, step and cut in place equals that of the same simulator with
``cuda_graphs=False`` (which removes eagerly, as on the CPU), whatever the number of ids (each
capacity captured once, then replayed with the ids padded), across a cut in place that moves the
tables (captured again), for hooke (tensor form), corotational and stvk; the caches keyed on
versions see a replayed removal as they see an eager one. Where it cannot serve a simulator, the
removal runs eagerly."""
from __future__ import annotations

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.ops import library
from tensormass_torch.sim.captured_removal import CapturedRemovals

pytestmark = pytest.mark.skipif(not library.ensure_registered(), reason="the compiled extension is not available")

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def beam(device, model="hooke", **kwargs):
    mesh = tm.beam_mesh(10, 3, 3, size=(1.0, 0.3, 0.3), dtype=torch.float64)
    material = tm.Material(young=2e5, poisson=0.3, density=1000.0, model=model)
    fixed = mesh.vertices[:, 0] < 1e-9
    body = tm.Body(mesh.to(device), material, fixed=fixed.to(device), name="beam")
    return tm.Simulator([body], dt=0.005, gravity=(0.0, -9.81, 0.0), cg_tol=1e-12, **kwargs)


def test_on_the_cpu_removals_run_eagerly():
    sim = beam("cpu")
    assert CapturedRemovals.unavailable(sim) == "not on CUDA"
    sim.step()
    sim.remove_elements(0, [3, 4])
    assert sim._captured_removals is None


@CUDA
def test_with_cuda_graphs_off_removals_run_eagerly():
    sim = beam("cuda", cuda_graphs=False)
    sim.step()
    sim.remove_elements(0, [3, 4])
    assert sim._captured_removals is None and CapturedRemovals.unavailable(sim) == "cuda_graphs is off"


@CUDA
@pytest.mark.parametrize("model", ["hooke", "corotational", "stvk"])
def test_replayed_removals_step_as_eager_ones(model):
    replayed, eager = beam("cuda", model), beam("cuda", model, cuda_graphs=False)
    gen = torch.Generator().manual_seed(7)
    counts = [1, 1, 3, 16, 17, 2, 40, 5, 16, 9, 1, 30]  # capacities 16, 32 and 64, each replayed
    sims = (replayed, eager)
    for k, count in enumerate(counts):
        alive = torch.nonzero(eager.alive_elements(0)).flatten().cpu()
        ids = alive[torch.randperm(alive.numel(), generator=gen)[:count]]
        for sim in sims:
            sim.remove_elements(0, ids)
        if k == 6:  # a cut in place between removals: what the graphs hold may move (captured again)
            for sim in sims:
                sim.cut(0, tm.Blade.swept((0.55, -1, -1), (0.55, 2, -1), (0.55, -1, 2), (0.55, 0.15, 2)))
        for sim in sims:
            sim.step()
        torch.testing.assert_close(replayed.x, eager.x, rtol=0, atol=1e-11)
        torch.testing.assert_close(replayed.v, eager.v, rtol=0, atol=1e-8)
        for name in ("mass", "node_elements", "removed"):
            assert torch.equal(getattr(replayed.model, name), getattr(eager.model, name)), (k, name)
        torch.testing.assert_close(replayed.system.external, eager.system.external, rtol=0, atol=0)
        torch.testing.assert_close(replayed.system.free, eager.system.free, rtol=0, atol=0)
        torch.testing.assert_close(replayed.removed_mass, eager.removed_mass, rtol=1e-15, atol=0)
    captured = replayed._captured_removals
    assert captured is not None and eager._captured_removals is None
    assert set(captured.captures) <= {16, 32, 64} and captured.captures


@CUDA
def test_a_replayed_removal_changes_the_versions_an_eager_one_does():
    replayed, eager = beam("cuda"), beam("cuda", cuda_graphs=False)
    for sim in (replayed, eager):
        sim.step()
        sim.remove_elements(0, [0])  # the first: the removal tables made
        sim.remove_elements(0, [5])  # (replayed: its capacity's graph captured)
    tensors = {sim: dict(sim.model.named_buffers()) for sim in (replayed, eager)}
    before = {sim: {name: t._version for name, t in tensors[sim].items()} for sim in tensors}
    for sim in (replayed, eager):
        sim.remove_elements(0, [9, 11])  # replayed
    changed = {sim: {name for name, t in tensors[sim].items() if t._version != before[sim][name]} for sim in tensors}
    assert changed[replayed] == changed[eager] and {"removed", "mass", "groups.0.edge_k"} <= changed[eager]


@CUDA
def test_a_capture_that_fails_warns_and_leaves_removals_eager(monkeypatch):
    from tensormass_torch.sim import captured_removal

    class Failing:
        def __init__(self, graph):
            pass

        def __enter__(self):
            raise RuntimeError("CUDA error: operation not permitted when stream is capturing")

        def __exit__(self, *exc):
            return False

    monkeypatch.setattr(captured_removal.torch.cuda, "graph", Failing)
    failing, eager = beam("cuda"), beam("cuda", cuda_graphs=False)
    for sim in (failing, eager):
        sim.step()
    with pytest.warns(RuntimeWarning, match="could not be captured"):
        failing.remove_elements(0, [1, 2, 3])
    eager.remove_elements(0, [1, 2, 3])
    assert CapturedRemovals.unavailable(failing).startswith("a capture failed")
    for ids in ([7], [8, 9]):  # eager from now on (no second warning)
        for sim in (failing, eager):
            sim.remove_elements(0, ids)
            sim.step()
        torch.testing.assert_close(failing.x, eager.x, rtol=0, atol=1e-11)
        assert torch.equal(failing.model.mass, eager.model.mass)
