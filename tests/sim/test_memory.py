"""The memory estimate before building (``tm.estimate_memory``) and the error where a scene cannot
fit on its GPU: at once, with the estimate, the free memory and the elements that would fit,
nothing allocated."""
import pytest
import torch
from conftest import live_tensors

import tensormass_torch as tm
from tensormass_torch.sim import memory
from tensormass_torch.sim.scene_file import load_scene


def beam_body(model="hooke", cells=(40, 10, 10)):
    mesh = tm.beam_mesh(*cells, size=(1.0, 0.25, 0.25))
    return tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model),
                   fixed=mesh.vertices[:, 0] <= 1e-9)


def test_estimate_adds_bodies_and_scales_with_the_dtype():
    body = beam_body()
    one = tm.estimate_memory(body)
    assert one.elements == body.mesh.num_elements and one.dtype == torch.float32
    assert 0 < one.held_bytes < one.peak_bytes
    two = tm.estimate_memory([body, body])
    assert (two.elements, two.peak_bytes, two.held_bytes) == (2 * one.elements, 2 * one.peak_bytes, 2 * one.held_bytes)
    wide = tm.estimate_memory(body, torch.float64)
    assert one.peak_bytes < wide.peak_bytes < 2 * one.peak_bytes  # indices do not grow with the dtype
    stvk = tm.estimate_memory(beam_body("stvk"))
    assert stvk.held_bytes > 2 * one.held_bytes  # the stress form's tangent graph and element data
    assert one.elements_that_fit(one.peak_bytes * 10) == 10 * one.elements
    assert "elements in float32: peak" in str(one)
    # warm_start="project" holds its float64 basis, and its operations make one more at the peak
    project = tm.estimate_memory(body, warm_start="project")
    sim = tm.Simulator([body], dt=0.01, warm_start="project")
    sim.step()
    basis = sum(space.basis.nbytes for _, _, space in sim.system._solution_spaces.values())
    assert project.held_bytes - one.held_bytes == basis
    assert project.peak_bytes - one.peak_bytes == 2 * basis


@pytest.mark.parametrize("shape", ["beam", "small bodies"])
@pytest.mark.parametrize("model", ["hooke", "stvk", "corotational"])
def test_estimate_is_what_a_simulator_holds(model, shape):
    """What a simulator of a 24,000-tet beam, or of 300 small cubes (a node an element where the
    beam has a fifth: the bytes a node count), holds after two steps (every tensor storage it
    added, counted on the CPU) is the estimate's held bytes to within 25 %, and the estimate
    says it."""
    if shape == "beam":
        bodies = [beam_body(model)]
    else:
        cube = tm.beam_mesh(2, 2, 2, size=(0.1, 0.1, 0.1))
        bodies = [tm.Body(cube, tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model),
                          fixed=cube.vertices[:, 0] <= 1e-9)] * 300
    estimate = tm.estimate_memory(bodies)
    before = live_tensors()[1]
    sim = tm.Simulator(bodies, dt=0.01, cg_tol=0.0, cg_max_iter=5, require_convergence=False)
    sim.step(2)
    held = live_tensors()[1] - before
    assert 0.75 < held / estimate.held_bytes < 1.25, (held, estimate)


@pytest.mark.parametrize("model", ["hooke", "corotational"])
def test_mixed_precision_holds_a_float32_copy(model):
    """precision="mixed" holds the float32 copy of the model its corrections run on: the estimate
    adds it, and is what a float64 simulator with it holds after two steps to within 25 %."""
    body = beam_body(model)
    full = tm.estimate_memory(body, torch.float64)
    mixed = tm.estimate_memory(body, torch.float64, precision="mixed")
    assert mixed.held_bytes == full.held_bytes + tm.estimate_memory(body).held_bytes
    before = live_tensors()[1]
    sim = tm.Simulator([body], dt=0.01, dtype=torch.float64, precision="mixed", cg_tol=1e-4)
    sim.step(2)
    held = live_tensors()[1] - before
    assert 0.75 < held / mixed.held_bytes < 1.25, (held, mixed)
    with pytest.raises(tm.SceneError, match="precision must be 'full' or 'mixed', got 'half'"):
        tm.estimate_memory(body, precision="half")
    # with the projection, also the copy of its basis that chained steps go back to
    project = tm.estimate_memory(body, torch.float64, warm_start="project")
    both = tm.estimate_memory(body, torch.float64, warm_start="project", precision="mixed")
    basis = tm.estimate_memory(body, warm_start="project").held_bytes - tm.estimate_memory(body).held_bytes
    assert both.held_bytes == project.held_bytes + tm.estimate_memory(body).held_bytes + basis


def test_a_scene_that_cannot_fit_fails_at_once_with_the_estimate(monkeypatch):
    """On a CUDA device whose free memory is below the estimated peak: one SceneError with the
    estimate, the free bytes and the elements that would fit, before anything is allocated
    (here: the CUDA device is never touched, free memory is what the check is told)."""
    body = beam_body()
    estimate = tm.estimate_memory(body)
    room = estimate.peak_bytes // 4
    free = int(room * memory.PEAK_MARGIN) + memory.FIXED_BYTES  # (a GPU simulator's size-independent bytes)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(memory, "free_bytes", lambda device: free)
    with pytest.raises(tm.SceneError, match="does not fit on cuda") as info:
        tm.Simulator([body], dt=0.01, device="cuda")
    text = str(info.value)
    assert f"about {estimate.elements_that_fit(int((free - memory.FIXED_BYTES) / memory.PEAK_MARGIN)):,} elements" in text
    assert f"{estimate.elements:,} elements in float32" in text and "check_memory=False" in text
    with pytest.raises(tm.SceneError, match="check_memory must be True or False"):
        tm.Simulator([body], dt=0.01, check_memory="no")


def test_estimate_bad_input():
    with pytest.raises(tm.SceneError, match="dtype must be"):
        tm.estimate_memory(beam_body(), torch.float16)
    with pytest.raises(tm.SceneError, match=r"bodies\[1\] is a str"):
        tm.estimate_memory([beam_body(), "beam"])


def test_scene_file_key(tmp_path):
    text = """
dt = 0.01
steps = 1
[solver]
check_memory = {value}
[[bodies]]
mesh = {{ generator = "beam", cells = [4, 1, 1], size = [1.0, 0.25, 0.25] }}
material = {{ model = "hooke", young = 1e5, poisson = 0.3 }}
"""
    for value, expected in (("false", False), ("true", True)):
        path = tmp_path / f"scene_{value}.toml"
        path.write_text(text.format(value=value))
        assert load_scene(path).simulator.check_memory is expected
