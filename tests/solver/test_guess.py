"""solver.guess.SolutionSpace (``warm_start="project"``) against dense float64 references: the
basis stays A-orthonormal per object, the guess is the Galerkin projection on the span of the
solutions added (exact for a right-hand side whose solution lies in it), the row replaced once
full is the one the last guess used least, objects do not see each other, a non-finite
solution changes nothing; and the simulator's projected steps: converged steps (the same
trajectory to the tolerance) in fewer iterations, a batch's objects projected on their own, the
space emptied by a cut, bad input (the scene key: test_warm_start.py)."""
import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.ops.segments import Segments
from tensormass_torch.solver import guess as guess_module
from tensormass_torch.solver.guess import SolutionSpace, warm_start_mode

DT = torch.float64


def spd(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, n, generator=g, dtype=DT)
    return q @ q.T + n * torch.eye(n, dtype=DT)


def block_diagonal_system(lengths, seed=0):
    """A block-diagonal SPD matrix over objects of ``lengths`` nodes (3 unknowns a node)."""
    blocks = [spd(3 * n, seed + i) for i, n in enumerate(lengths)]
    return torch.block_diag(*blocks), Segments.from_lengths(lengths)


def product(a):
    return lambda x: (a @ x.reshape(-1)).reshape(x.shape)


def galerkin(a, solutions, b):
    """The A-orthogonal projection of A^-1 b on span(solutions): X (X^T A X)^-1 X^T b."""
    x = torch.stack([s.reshape(-1) for s in solutions], 1)
    return (x @ torch.linalg.solve(x.T @ a @ x, x.T @ b.reshape(-1))).reshape(b.shape)


def random_field(v, seed):
    return torch.randn(v, 3, generator=torch.Generator().manual_seed(seed), dtype=DT)


def test_the_guess_is_the_galerkin_projection_on_the_solutions():
    a, segments = block_diagonal_system([12])
    space = SolutionSpace(torch.zeros(12, 3, dtype=DT), segments, capacity=4)
    apply = product(a)
    solutions = []
    for k in range(3):
        x = random_field(12, k)
        space.guess(apply(x))  # (as a step does: a guess, then its solution added)
        space.add(x, apply)
        solutions.append(x)
        gram = torch.einsum("kvd,jvd->kj", space.basis, torch.stack([apply(w) for w in space.basis]))
        used = torch.diag(gram) > 0.5
        torch.testing.assert_close(gram[used][:, used], torch.eye(k + 1, dtype=DT), rtol=0, atol=1e-12)
    b = random_field(12, 99)
    torch.testing.assert_close(space.guess(b), galerkin(a, solutions, b), rtol=0, atol=1e-12)
    inside = 0.3 * solutions[0] - 2.0 * solutions[2]  # a solution in the span: guessed exactly
    torch.testing.assert_close(space.guess(apply(inside)), inside, rtol=0, atol=1e-12)
    # the energy norm of the guess's error is never above the solution's (zero's error)
    x_star = torch.linalg.solve(a, b.reshape(-1)).reshape(b.shape)
    err = x_star - space.guess(b)
    assert float((err.reshape(-1) @ a @ err.reshape(-1))) <= float(x_star.reshape(-1) @ a @ x_star.reshape(-1))
    space.reset()
    assert float(space.guess(b).abs().max()) == 0.0


def test_a_given_image_is_the_product_it_spares():
    """add(x, product, image=A x) (a refined solve's b - r) makes the basis add(x, product) makes."""
    a, segments = block_diagonal_system([10])
    apply = product(a)
    spaces = [SolutionSpace(torch.zeros(10, 3, dtype=DT), segments, capacity=3) for _ in range(2)]
    for k in range(4):
        x = random_field(10, k)
        for given, space in zip((False, True), spaces):
            space.guess(apply(x))
            space.add(x, apply, apply(x) if given else None)
    torch.testing.assert_close(spaces[1].basis, spaces[0].basis, rtol=0, atol=1e-14)


def test_a_full_space_replaces_the_row_the_last_guess_used_least():
    a, segments = block_diagonal_system([8])
    apply = product(a)
    space = SolutionSpace(torch.zeros(8, 3, dtype=DT), segments, capacity=2)
    first, second = random_field(8, 1), random_field(8, 2)
    for x in (first, second):
        space.guess(apply(x))
        space.add(x, apply)
    kept = space.basis.clone()
    space.guess(apply(first))  # all of it along the first solution's row: the other is replaced
    share = space.share.clone()
    third = random_field(8, 3)
    space.add(third, apply)
    replaced = int(torch.argmin(share))
    torch.testing.assert_close(space.basis[1 - replaced], kept[1 - replaced], rtol=0, atol=0)
    torch.testing.assert_close(space.guess(apply(first)), first, rtol=0, atol=1e-12)  # still in the span
    assert replaced == 1
    # (the new row is the third solution less its parts along both old rows: the span is the rows')
    torch.testing.assert_close(space.guess(apply(third)), galerkin(a, list(space.basis), apply(third)),
                               rtol=0, atol=1e-12)


def test_objects_are_projected_on_their_own():
    a, segments = block_diagonal_system([5, 7])
    apply = product(a)
    space = SolutionSpace(torch.zeros(12, 3, dtype=DT), segments, capacity=3)
    alone_a, _ = block_diagonal_system([5])
    alone = SolutionSpace(torch.zeros(5, 3, dtype=DT), Segments.from_lengths([5]), capacity=3)
    for k in range(3):
        x = random_field(12, 10 + k)
        x[5:] *= 1e3 * (k + 1)  # the other object's scale and values must not matter
        space.guess(apply(x))
        space.add(x, apply)
        alone.guess(product(alone_a)(x[:5]))
        alone.add(x[:5], product(alone_a))
    b = random_field(12, 50)
    torch.testing.assert_close(space.guess(b)[:5], alone.guess(b[:5]), rtol=0, atol=1e-12)


def test_a_non_finite_solution_changes_nothing_and_a_solution_in_the_span_adds_nothing():
    a, segments = block_diagonal_system([6])
    apply = product(a)
    space = SolutionSpace(torch.zeros(6, 3, dtype=DT), segments, capacity=3)
    x = random_field(6, 0)
    space.guess(apply(x))
    space.add(x, apply)
    before = space.basis.clone()
    bad = x.clone()
    bad[2, 1] = float("nan")
    space.guess(apply(x))
    space.add(bad, apply)
    space.guess(apply(x))
    space.add(2.0 * x, apply)  # already in the span: its row stays zero
    assert torch.isfinite(space.basis).all()
    torch.testing.assert_close(space.basis, before, rtol=0, atol=0)


def test_a_change_of_the_node_stiffness_invalidates_the_rows():
    """The planes' and tools' penalties change the matrix: the rows made before no longer count
    (no guess from them, not in the next Gram-Schmidt, replaced first); the same stiffness keeps
    them, and so does its absence throughout."""
    a, segments = block_diagonal_system([6])
    apply = product(a)
    space = SolutionSpace(torch.zeros(6, 3, dtype=DT), segments, capacity=3)
    x = random_field(6, 0)
    penalty = torch.zeros(6, 3, 3, dtype=DT)
    for stiffness in (None, penalty):
        space.reset()
        space.watch(stiffness)
        space.guess(apply(x))
        space.add(x, apply)
        space.watch(None if stiffness is None else stiffness.clone())  # the same: kept
        torch.testing.assert_close(space.guess(apply(x)), x, rtol=0, atol=1e-12)
    touched = penalty.clone()
    touched[2] = 1e3 * torch.eye(3, dtype=DT)
    space.watch(touched)  # a node starts to touch
    assert float(space.guess(apply(x)).abs().max()) == 0.0 and float(space.valid.sum()) == 0.0
    space.add(x, apply)
    torch.testing.assert_close(space.guess(apply(x)), x, rtol=0, atol=1e-12)  # filled again
    space.watch(touched, changing=True)  # body contact pairs: changing at every step
    assert float(space.guess(apply(x)).abs().max()) == 0.0
    space.watch(None)  # the penalties gone
    space.add(x, apply)
    space.watch(touched)
    assert float(space.valid.sum()) == 0.0


def test_bad_input():
    with pytest.raises(ValueError, match="capacity must be >= 1, got 0"):
        SolutionSpace(torch.zeros(3, 3), Segments.from_lengths([3]), capacity=0)
    assert warm_start_mode(False) == "none" and warm_start_mode(True) == "extrapolate"
    assert warm_start_mode("project") == "project"
    for bad in ("projection", 1, None):
        with pytest.raises(ValueError, match="warm_start must be True, False or one of"):
            warm_start_mode(bad)


# ------------------------------------------------------------------------------ the simulator


def beam_sim(warm_start, preconditioner="none", model="hooke", bodies=1, **options):
    mesh = tm.beam_mesh(12, 3, 3, size=(1.0, 0.25, 0.25), dtype=DT)
    body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model),
                   fixed=mesh.vertices[:, 0] == 0)
    options = {"cg_tol": 1e-10, "cuda_graphs": False, **options}
    return tm.Simulator([body] * bodies, dt=0.01, preconditioner=preconditioner, warm_start=warm_start, **options)


def step_iterations(sim, steps: int) -> list:
    """Step ``sim`` ``steps`` times; each step's CG iterations."""
    counts = []
    for _ in range(steps):
        sim.step()
        counts.append(int(sim.last_report.cg[0].iterations.max()))
    return counts


@pytest.mark.parametrize("model,planes", [("hooke", False), ("hooke", True), ("corotational", False)])
def test_projected_steps_are_the_converged_steps_in_fewer_iterations(model, planes):
    runs, iterations = [], []
    for warm in ("none", "project"):
        sim = beam_sim(warm, model=model, planes=[tm.Plane((0, 0, 1), -0.05, 1e4)] if planes else [])
        iterations.append(step_iterations(sim, 25))
        runs.append(sim.x.clone())
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-8)
    assert iterations[1][0] == iterations[0][0]  # the first step has nothing to project on
    assert sum(iterations[1][5:]) < sum(iterations[0][5:]), iterations


def scene(kind: str, warm_start: str):
    """Small scenes of the step's other paths, each with ``warm_start``."""
    import math

    mesh = tm.beam_mesh(8, 2, 2, size=(1.0, 0.25, 0.25), dtype=DT)
    material = tm.Material(young=1e5, poisson=0.3, density=1000.0)
    fixed = mesh.vertices[:, 0] == 0
    options = dict(dt=0.01, cg_tol=1e-10, warm_start=warm_start)
    if kind in ("bdf2", "newmark"):
        return tm.Simulator([tm.Body(mesh, material, fixed=fixed)], integrator=kind, **options)
    if kind == "prescribed":
        tip = mesh.vertices[:, 0] > 1.0 - 1e-9
        rest = mesh.vertices[tip].clone()
        body = tm.Body(mesh, material, fixed=fixed, prescribed=tip,
                       motion=lambda t: rest + torch.tensor([0.0, 0.0, -0.1 * math.sin(5 * t)], dtype=DT))
        return tm.Simulator([body], **options)
    if kind == "tool":
        return tm.Simulator([tm.Body(mesh, material, fixed=fixed)], tools=[tm.Sphere(0.1, position=(0.8, 0.125, 0.3))],
                            **options)
    if kind == "membrane":
        tri = tm.beam_tri_mesh(8, 3, size=(1.0, 0.375), dtype=DT)
        return tm.Simulator([tm.Body(tri, material, fixed=tri.vertices[:, 0] == 0)], gravity=(0.0, -9.81, 0.0),
                            **options)
    blocks = [tm.beam_mesh(3, 3, 3, size=(0.2, 0.2, 0.2), origin=origin, dtype=DT)
              for origin in ((0.0, 0.0, 0.205), (0.02, 0.02, 0.0))]  # 5 mm apart: touching within the steps
    return tm.Simulator([tm.Body(block, material) for block in blocks], planes=[tm.Plane((0, 0, 1), -0.001, 1e5)],
                        contact=tm.Contact(), **dict(options, dt=0.005))


@pytest.mark.parametrize("kind", ["bdf2", "newmark", "prescribed", "tool", "membrane", "contact"])
def test_projected_steps_on_the_other_paths_are_the_cold_steps(kind):
    """BDF2 (two step matrices), Newmark, prescribed nodes, a tool's penalties, a 2-D membrane
    and body contact (its pairs leave the space empty): the same converged steps as from zero."""
    runs = []
    for warm in ("none", "project"):
        sim = scene(kind, warm)
        sim.step(12)
        runs.append(sim.x.clone())
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-8)
    if kind == "contact":  # (the bodies did touch)
        assert max(len(pairs) for pairs, _ in sim.last_report.contact_solves) > 0


def test_a_batch_projects_each_object_on_its_own(monkeypatch):
    """The guess of body 0 in a batch of two equals its guess alone: the other body (pushed at
    another speed) does not enter its projection."""
    seen = {}
    real = guess_module.SolutionSpace.guess

    def spy(self, rhs):
        out = real(self, rhs)
        seen.setdefault(self.basis.shape[1], []).append(out.clone())
        return out

    monkeypatch.setattr(guess_module.SolutionSpace, "guess", spy)
    pair, alone = beam_sim("project", bodies=2), beam_sim("project")
    nodes = alone.model.num_nodes
    pair.v[nodes:] = torch.tensor([0.0, 0.3, -0.2], dtype=DT)
    for _ in range(6):
        pair.step()
        alone.step()
    for in_pair, by_itself in zip(seen[2 * nodes], seen[nodes]):
        torch.testing.assert_close(in_pair[:nodes], by_itself, rtol=0, atol=1e-9)


def test_a_cut_empties_the_space():
    sim = beam_sim("project")
    sim.step(3)
    space = sim.system.solution_space(sim.options, sim.x)
    assert float(space.basis.abs().max()) > 0
    sim.remove_elements(0, torch.arange(0, 6))
    assert sim.system.solution_space(sim.options, sim.x) is space and float(space.basis.abs().max()) == 0
    sim.step(2)  # and the steps after it converge
    assert bool(sim.last_report.cg[0].converged.all())


def test_bad_warm_start():
    with pytest.raises(tm.SceneError, match="warm_start must be True, False or one of"):
        beam_sim("projection")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("preconditioner", ["none", "multigrid"])
def test_cuda_captured_steps_match_the_cpu(preconditioner):
    """On CUDA the guess is formed in the captured start and the solution joins the space in a
    captured graph: the same steps as the CPU's eager ones, in float64, the graphs replayed."""
    if preconditioner == "multigrid":
        pytest.importorskip("pyamg")
    runs, counts = [], []
    for device in ("cpu", "cuda"):
        sim = beam_sim("project", preconditioner, device=device, cuda_graphs=True,
                       planes=[tm.Plane((0, 0, 1), -0.02, 1e4)])
        counts.append(step_iterations(sim, 20))
        runs.append(sim.x.cpu())
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-9)
    assert all(abs(a - b) <= 2 for a, b in zip(*counts)), counts
    graphs = list(sim.system._step_graphs.values())
    assert len(graphs) == 1 and "add" in graphs[0]._graphs and graphs[0]._graphs["add"] is not None
