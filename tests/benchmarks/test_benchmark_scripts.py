"""The benchmark suite's own correctness: the assembled-matrix alternative is exact (its A p is the
matrix-free product, its steps are the simulator's), the floor's byte count adds up, and every
figure script runs end to end with --quick (tiny sizes, CPU) and writes its md/json (and png
when matplotlib is installed)."""
from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch import ops

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"
for folder in (BENCH, BENCH / "suite", BENCH / "studies", BENCH / "probes"):  # the shared modules and the scripts
    sys.path.insert(0, str(folder))

import assembled  # noqa: E402
import common  # noqa: E402

HAS_MATPLOTLIB = importlib.util.find_spec("matplotlib") is not None

# (kind, model, form, rotation): every model, both forms where they exist, both rotation frames
CASES = [("tet", "hooke", "stress", "polar"), ("tet", "hooke", "tensor", "polar"),
         ("tet", "stvk", "stress", "polar"), ("tet", "stvk", "tensor", "polar"),
         ("tet", "corotational", "stress", "polar"), ("tet", "corotational", "stress", "qr"),
         ("tri", "hooke", "tensor", "polar"), ("tri", "stvk", "stress", "polar"),
         ("tri", "corotational", "stress", "qr")]


def small_mesh(kind):
    if kind == "tet":
        return tm.beam_mesh(3, 2, 2, size=(1.0, 0.5, 0.4), dtype=torch.float64)
    return tm.beam_tri_mesh(3, 2, size=(1.0, 0.6), dim=3, dtype=torch.float64)


@pytest.mark.parametrize("kind,model,form,rotation", CASES)
def test_assembled_matrix_is_the_matrix_free_product(kind, model, form, rotation):
    torch.manual_seed(0)
    mesh = small_mesh(kind)
    mat = tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model, rotation=rotation)
    model_ = tm.TensorMass(mesh, mat, form=form)
    V = mesh.vertices.shape[0]
    u = 0.05 * torch.randn(V, 3, dtype=torch.float64)  # a large deformation: K depends on u
    if kind == "tri":
        u = u * torch.tensor([1.0, 1.0, 0.3], dtype=torch.float64)
    free = mesh.vertices[:, 0] > 1e-6
    mass = model_.lumped_mass()
    c_mass, c_stiff = 1.1, 0.02
    system = assembled.SystemMatrix(model_, u, mass, free, c_mass, c_stiff)
    p = torch.randn(V, 3, dtype=torch.float64)
    p_free = p * free[:, None]
    expected = ops.system_matvec(model_.groups, u, p_free, mass, free.double(), c_mass, c_stiff)[0]
    scale = expected.abs().max()
    for layout in ("csr", "bsr"):
        got = assembled.sparse_matvec(assembled.matrix_for(layout, system))(p_free)
        assert torch.allclose(got, expected, rtol=0, atol=1e-12 * scale), (layout, float((got - expected).abs().max()))
    # constrained dofs: identity rows, so A p there is p itself
    full = assembled.sparse_matvec(system.csr())(p)
    assert torch.equal(full[~free], p[~free])


def test_assembled_steps_are_the_simulator_steps():
    """Two bodies of different stiffness, stvk (reassembled every step): the assembled CG with
    per-object scalars gives the simulator's positions to rounding."""
    meshes = [tm.beam_mesh(3, 2, 2, size=(1.0, 0.3, 0.3), dtype=torch.float64),
              tm.beam_mesh(4, 2, 2, size=(1.0, 0.3, 0.3), dtype=torch.float64)]
    bodies = [tm.Body(m, tm.Material(young=e, poisson=0.3, density=1000.0, model="stvk"),
                      fixed=m.vertices[:, 0] <= 1e-6) for m, e in zip(meshes, (1e5, 3e5))]
    sim = tm.Simulator(bodies, dt=0.01, gravity=(0, 0, -9.81), rayleigh_mass=0.1, rayleigh_stiffness=0.01,
                       cg_tol=0.0, cg_max_iter=6, require_convergence=False)
    stepper = assembled.AssembledStepper(sim, (0, 0, -9.81), "csr")
    for _ in range(3):
        sim.step(1)
        stepper.step(1)
    moved = (sim.x - sim.model.rest).abs().max()
    assert moved > 1e-4
    assert torch.allclose(stepper.x, sim.x, rtol=0, atol=1e-10 * moved)


def test_cg_iteration_bytes_counts_the_stress_form_buffers():
    mesh = tm.beam_mesh(2, 2, 1, dtype=torch.float32)
    model = tm.TensorMass(mesh, tm.Material(young=1e5, poisson=0.3, density=1e3, model="stvk"), form="stress")
    parts = common.cg_iteration_bytes(model)
    N, V, s = mesh.elements.shape[0], mesh.vertices.shape[0], 4
    assert parts["material"] == N * 4 * 3 * s + 3 * N * s   # shape vectors, measure, young, poisson
    assert parts["indices"] == 2 * N * 4 * 4 + V * 4        # index + ForceIndex (int32), incidences
    assert parts["partial_force"] == 2 * N * 4 * 3 * s
    assert parts["u"] == V * 3 * s                          # stvk's DForce reads u
    assert parts["total"] == sum(v for k, v in parts.items() if k != "total")


def test_cg_iteration_bytes_counts_the_node_graph_where_it_is_smaller():
    """The stvk tensor form's CG may run on the node graph's tangent (one d x d block an edge
    instead of B, C, D and u): counted as the hooke tensor form's graph, whose items are the
    edges."""
    mesh = tm.beam_mesh(4, 2, 2, dtype=torch.float32)
    material = dict(young=1e5, poisson=0.3, density=1e3)
    stvk = common.cg_iteration_bytes(tm.TensorMass(mesh, tm.Material(model="stvk", **material), form="tensor"))
    hooke_model = tm.TensorMass(mesh, tm.Material(model="hooke", **material), form="tensor")
    hooke = common.cg_iteration_bytes(hooke_model)
    edges = hooke_model.groups[0].plan.index.shape[0]
    assert stvk == hooke and stvk["u"] == 0
    assert hooke["material"] == edges * 3 * 3 * 4 and hooke["partial_force"] == 2 * edges * 2 * 3 * 4


def _check_outputs(out, name):
    assert (out / f"{name}.md").read_text().startswith("# ")
    data = json.loads((out / f"{name}.json").read_text())
    assert data["meta"]["commit"] is None or isinstance(data["meta"]["commit"], str)
    records = data["records"]
    assert records and all(set(common.RECORD_FIELDS) <= set(r) for r in records)
    if HAS_MATPLOTLIB:
        assert (out / f"{name}.png").stat().st_size > 0
    else:
        assert "matplotlib is not installed" in (out / f"{name}.md").read_text()
    return records


def _ran(records, backend):
    return [r for r in records if r["backend"] == backend and r.get("steps_per_s")]


def test_figure2_quick(tmp_path, monkeypatch):
    monkeypatch.setenv("TENSORMASS_COMMIT", "test123")
    import figure2

    figure2.main(["--quick", "--device", "cpu", "--kinds", "tet", "--models", "stvk", "--backends", "torch,csr",
                  "--out", str(tmp_path)])
    records = _check_outputs(tmp_path, "figure2")
    assert json.loads((tmp_path / "figure2.json").read_text())["meta"]["commit"] == "test123"
    assert _ran(records, "torch") and _ran(records, "csr")
    assert all(r["cg_iterations"] == 5 for r in _ran(records, "torch"))


def test_sofa_beam_quick(tmp_path):
    import sofa_beam

    sofa_beam.main(["--quick", "--device", "cpu", "--models", "hooke", "--backends", "torch,bsr",
                    "--out", str(tmp_path)])
    records = _check_outputs(tmp_path, "sofa_beam")
    assert _ran(records, "torch")[0]["cg_iterations"] == 10
    assert _ran(records, "bsr")[0]["assembly_ms"] > 0


def test_batches_quick(tmp_path):
    import batches

    batches.main(["--quick", "--device", "cpu", "--backends", "torch,csr", "--out", str(tmp_path)])
    records = _check_outputs(tmp_path, "batches")
    runs = _ran(records, "torch")
    assert {r["objects"] for r in runs} == {1, 4}
    assert all(r["objects_steps_per_s"] == pytest.approx(r["objects"] * r["steps_per_s"]) for r in runs)


def test_cg_floor_quick(tmp_path):
    import cg_floor

    cg_floor.main(["--quick", "--device", "cpu", "--elements", "48", "--models", "hooke", "--backends", "torch",
                   "--out", str(tmp_path)])
    records = _check_outputs(tmp_path, "cg_floor")
    (rec,) = records
    assert rec["bytes_per_cg_iteration"] > 0 and rec["floor_ms_per_cg_iteration"] > 0
    assert rec["ms_per_cg_iteration"] is not None


def test_definite_tangent_quick(tmp_path):
    import definite_tangent

    definite_tangent.main(["--quick", "--device", "cpu", "--out", str(tmp_path)])
    records = json.loads((tmp_path / "definite_tangent.json").read_text())["records"]
    by = {(r["scene"], r["tangent"]): r for r in records}
    assert by[("compressed", "exact")]["failed"] and not by[("compressed", "definite")]["failed"]


def test_solve_to_tolerance_quick(tmp_path):
    pytest.importorskip("pyamg")
    pytest.importorskip("cholespy")
    import solve_to_tolerance

    solve_to_tolerance.main(["--quick", "--device", "cpu", "--steps", "2", "--max-seconds", "0.2", "--out",
                             str(tmp_path)])
    records = json.loads((tmp_path / "solve_to_tolerance.json").read_text())["records"]
    assert not any(r.get("error") for r in records)
    converged = [r for r in records if r["solver"] in ("none", "none+warm", "jacobi", "multigrid", "multigrid+warm",
                                                       "cholesky")]
    assert len(converged) == 18 and all(r["relative_residual"] <= 1e-6 for r in converged)
    by = {(r["scene"], r["young"], r["solver"]): r["cg_iterations"] for r in records}
    assert by[("paper_beam", 1e7, "multigrid")] * 5 < by[("paper_beam", 1e7, "none")]
    assert by[("paper_beam", 1e5, "cholesky")] == 1  # hooke without contact: the factor solves it
    scaling = json.loads((tmp_path / "multigrid_scaling.json").read_text())["records"]
    assert [r["elements"] for r in scaling] == [4800, 38400] and all(r["cg_iterations"] <= 20 for r in scaling)


def test_gather_variants_quick(tmp_path):
    pytest.importorskip("tensormass_torch._C")
    import gather_variants

    gather_variants.main(["--quick", "--device", "cpu", "--models", "hooke", "--repeat", "2", "--out", str(tmp_path)])
    records = json.loads((tmp_path / "gather_variants.json").read_text())["records"]
    assert {r["backend"] for r in records} == {"padded", "csr", "atomics"}
    assert all(r["max_rel_diff"] < 1e-5 for r in records)  # the same forces, summed three ways


def test_carving_quick(tmp_path):
    import carving

    carving.main(["--device", "cpu", "--quick", "--out", str(tmp_path)])
    records = json.loads((tmp_path / "carving.json").read_text())["records"]
    assert {r["model"] for r in records} == {"hooke", "corotational"}
    assert all(r["remove_ms"] > 0 and r["rebuild_ms"] > 0 for r in records if r.get("removed"))
    assert {r.get("removed_per_step") for r in records if r["steps_per_s"]} == {0, 10}
    cuts = [r for r in records if r.get("cut_ms")]
    assert all(r["cut_elements"] > 0 and r["cut_nodes"] > 0 for r in cuts)
    # every model on the host; on the device where it serves the model (hooke)
    assert sorted((r["model"], r["note"].endswith("on the device")) for r in cuts) == [
        ("corotational", False), ("corotational", False), ("hooke", False), ("hooke", False), ("hooke", True),
        ("hooke", True)]
    scalpels = [r["note"] for r in records if r.get("note", "").startswith("a scalpel")]
    assert sum("cuts on the device" in note for note in scalpels) == 1  # hooke's


def test_contact_penetration_quick(tmp_path):
    import contact_penetration

    (row,) = contact_penetration.main(["--quick", "--out", str(tmp_path)])
    assert row["steps"] == 5 and row["max_penetration_m"] >= 0
    assert (tmp_path / "contact_penetration.md").exists() and (tmp_path / "contact_penetration.json").exists()


def test_contact_piles_quick(tmp_path):
    import contact_piles

    (row,) = contact_piles.main(["--quick", "--device", "cpu", "--out", str(tmp_path)])
    assert row["blocks"] == 8 and row["steps_per_s_with"] > 0 and row["surface_triangles"] > 0
    assert (tmp_path / "contact_piles.md").exists() and (tmp_path / "contact_piles.json").exists()
    # the stepping's windows cover the run's steps, each once, and leave the checks' time out
    assert [w[:2] for w in row["windows"]] == [[0, 3]]
    assert row["stepping_s"] == sum(w[2] for w in row["windows"]) and row["stepping_s"] + row["check_s"] <= row["run_s"]
    assert row["steps_per_s_run"] == 3 / row["stepping_s"] and "steps_per_s_without_run" not in row
    # --without-steps: the pile without contact over the run's steps too, and the run's cost against it
    (row,) = contact_piles.main(["--quick", "--device", "cpu", "--out", str(tmp_path), "--without-steps", "3"])
    assert row["steps_per_s_without_run"] > 0
    assert row["cost_ratio_run_against_run"] == row["steps_per_s_without_run"] * row["stepping_s"] / 3


def test_contact_piles_shift_sets_each_block_sideways_from_the_one_under_it():
    """contact_piles.pile(shift=...): each block of a column starts ``shift`` sideways (x) from the
    one under it, 13 cm above it; 0 gives straight stacks; ``levels`` blocks a column (by default
    as many as the columns a side)."""
    import contact_piles

    for shift, columns, levels in ((0.0, 3, None), (contact_piles.SHIFT, 3, None), (0.03, 3, None), (0.0, 1, 10),
                                   (0.01, 2, 4)):
        bodies, _ = contact_piles.pile(columns, (2, 2, 1), "cpu", torch.float64, shift=shift, levels=levels)
        levels = columns if levels is None else levels
        centroids = torch.stack([body.mesh.vertices.mean(0) for body in bodies]).reshape(columns ** 2, levels, 3)
        steps = centroids[:, 1:] - centroids[:, :-1]  # [column, level, 3]: from a block to the next up
        assert torch.allclose(steps, torch.tensor([shift, 0.0, 0.13], dtype=torch.float64).expand_as(steps))


def test_out_of_order_counts_a_block_half_a_thickness_below_the_one_it_started_on():
    """contact_piles.out_of_order: a pair of one column's blocks counts where the block that started
    above lies more than 5 cm below the other, over it in plan; two blocks level, side by side as
    two knocked on their edges, do not count, however the fraction of a millimetre falls."""
    import contact_piles

    bodies, block = contact_piles.pile(2, (2, 2, 1), "cpu", torch.float64)
    sim = contact_piles.simulator(bodies, tm.Contact(), "cpu", torch.float64)
    assert contact_piles.out_of_order(sim, 2) == 0
    nodes = block.num_vertices
    x = sim.x.clone()
    x[nodes:2 * nodes, 2] -= 0.13 + 0.0001  # column 0's upper block level with the lower, 0.1 mm under
    x[nodes:2 * nodes, 0] += 0.12  # beside it, 12 cm over in plan
    sim.x = x
    assert contact_piles.out_of_order(sim, 2) == 0
    x[nodes:2 * nodes, 2] -= 0.06  # 6 cm under it: reversed
    sim.x = x
    assert contact_piles.out_of_order(sim, 2) == 1


def test_contact_step_phases_probe_quick():
    """The phases probe times a pile's step phase by phase and puts every function it wrapped back."""
    import contact_step_phases_probe as probe

    from tensormass_torch.physics.body_contact import SurfaceContact

    nearby = SurfaceContact.nearby
    out = probe.main(["--columns", "2", "--cells", "2", "2", "1", "--steps", "30", "--timed", "2", "--device",
                      "cpu"])
    assert SurfaceContact.nearby is nearby
    seconds, calls, iterations = out["phases"]["CGSolver.solve"]
    assert calls >= 2 and iterations > 0 and seconds > 0 and out["steps_per_s"] > 0
    assert out["phases"]["SurfaceContact.at_state"][1] >= 2


def test_contact_landing_probe_counts_what_the_steps_make(tmp_path):
    """The landing probe times each step of a pile dropped from the start, counts the solvers and
    the rigid correction's fresh loads the steps make (none before the blocks meet, some after),
    writes its rows, and puts every function it wrapped back."""
    import contact_landing_probe as probe

    from tensormass_torch.solver import implicit_euler, rigid_modes

    originals = (torch.cuda.CUDAGraph.capture_begin, implicit_euler.CGSolver, rigid_modes.lever_arms)
    rows = probe.main(["--columns", "2", "--cells", "2", "2", "1", "--steps", "0", "--timed", "30", "--window", "10",
                       "--contact", '{"friction": 0.5}', "--device", "cpu", "--out", str(tmp_path / "landing.json")])
    assert (torch.cuda.CUDAGraph.capture_begin, implicit_euler.CGSolver, rigid_modes.lever_arms) == originals
    assert [r["step"] for r in rows] == list(range(30)) and all(r["ms"] > 0 and r["iterations"] for r in rows)
    falling = [r for r in rows if r["pairs"] == 0]
    assert falling and sum(r["fresh_loads"] for r in falling) == 0  # no pairs: no rigid correction
    assert sum(r["fresh_loads"] for r in rows) > 0 and sum(r["solvers"] for r in rows) >= 1
    assert all(r["captures"] == 0 for r in rows)  # (the CPU captures nothing)
    assert len(json.loads((tmp_path / "landing.json").read_text())["blocks"]) == 30


def test_contact_pairs_step_length_probe_steps_both_paths_alike():
    """The probe steps the pairs' product in the fused step length and called whole from one
    state to the same state, and puts the method it swapped back."""
    import contact_pairs_step_length_probe as probe

    from tensormass_torch.solver import implicit_euler

    fused = implicit_euler._WithPairs.matvec_alpha
    blocks, apart, per_body = probe.main(["--columns", "2", "--cells", "2", "2", "1", "--steps", "20", "--timed", "2",
                                          "--repeats", "2", "--contact", '{"friction": 0.5}', "--device", "cpu"])
    assert implicit_euler._WithPairs.matvec_alpha is fused
    assert all(len(times) == 2 and all(t > 0 for t in times) for times in blocks.values())
    assert apart == 0.0 and per_body.shape == (8,) and int(per_body.max()) > 0


def test_contact_settings_probe_steps_each_setting_from_one_state(tmp_path):
    """The settings probe starts every setting from the pile's state and alternates their blocks:
    an exact alternative (skin) takes the default's iterations block by block; the state it keeps
    is the one a later run starts from; a malformed setting is refused."""
    import contact_settings_probe as probe

    common_args = ["--columns", "2", "--cells", "2", "2", "1", "--timed", "2", "--repeats", "2", "--device", "cpu",
                   "--contact", '{"friction": 0.5}']
    blocks = probe.main(common_args + ["--steps", "20", "--save-state", str(tmp_path / "state"), "--out",
                                       str(tmp_path / "settings.json"), "--setting", "default={}",
                                       "--setting", 'skin={"skin": 0.005}', "--setting", 'after={"check_ahead": 0}'])
    assert list(blocks) == ["without contact", "default", "skin", "after"]
    assert all(len(runs) == 2 and all(r["ms"] > 0 and r["solves"] >= 1 for r in runs) for runs in blocks.values())
    assert [r["iterations"] for r in blocks["skin"]] == [r["iterations"] for r in blocks["default"]]
    assert [r["iterations"] for r in blocks["after"]] == [r["iterations"] for r in blocks["default"]]
    assert json.loads((tmp_path / "settings.json").read_text())["blocks"] == blocks
    rigid = 'rigid={"preconditioner": "rigid", "rigid_grouping": "morton", "rigid_refresh": 3}'
    again = probe.main(common_args + ["--state", str(tmp_path / "state"), "--setting", "default={}",
                                      "--setting", rigid])
    assert [r["iterations"] for r in again["default"]] == [r["iterations"] for r in blocks["default"]]
    assert all(r["iterations"] > 0 for r in again["rigid"])
    with pytest.raises(SystemExit, match="NAME=JSON"):
        probe.setting("no-equals-sign")


def test_cg_fusions_probe_quick():
    """The fusions probe steps the old and the new path from one state in alternated blocks: the
    accumulate is exact (the same iterations), and the old paths are taken out again."""
    import cg_fusions_probe as probe

    from tensormass_torch.ops import contact as contact_ops
    from tensormass_torch.solver import implicit_euler
    from tensormass_torch.solver.cg import CGSolver

    kept = (CGSolver._projects_in_one_op, contact_ops.pair_product, implicit_euler.BlockJacobi,
            CGSolver._block_iterate)
    common_args = ["--columns", "2", "--cells", "2", "2", "1", "--steps", "20", "--timed", "2", "--repeats", "2",
                   "--device", "cpu", "--contact", '{"friction": 0.5}']
    for change in probe.CHANGES:
        rigid = ["--preconditioner", "rigid"] if change == "coarse_direction" else []
        blocks = probe.main(common_args + ["--change", change] + rigid)
        assert list(blocks) == ["old", "new"] and all(r["ms"] > 0 for runs in blocks.values() for r in runs)
        if change == "accumulate":
            assert [r["iterations"] for r in blocks["old"]] == [r["iterations"] for r in blocks["new"]]
    assert (CGSolver._projects_in_one_op, contact_ops.pair_product, implicit_euler.BlockJacobi,
            CGSolver._block_iterate) == kept
    with pytest.raises(SystemExit):
        probe.main(common_args + ["--change", "nothing"])


def test_contact_rounds_probe_quick():
    """The rounds probe counts each check's misses and re-linearisations as relinearise tests them,
    and puts relinearise back."""
    import contact_rounds_probe as probe

    from tensormass_torch.physics.body_contact import SurfaceContact

    relinearise = SurfaceContact.relinearise
    steps = probe.main(["--columns", "2", "--cells", "2", "2", "1", "--steps", "30", "--timed", "3", "--device",
                        "cpu"])
    assert SurfaceContact.relinearise is relinearise
    assert len(steps) == 3 and all(len(s["iterations"]) >= 1 for s in steps)
    for s in steps:  # a check for each solve but the last; every count past the check's tolerance
        assert len(s["checks"]) >= len(s["iterations"]) - 1
        for check in s["checks"]:
            assert all(e > check["tolerance"] for e in check["misses"] + check["relinearised"])


def test_contact_pile_flips_probe_measures_a_pair_exactly(tmp_path):
    """The flips probe's pair measure is the simulator's interpenetration for two blocks pushed 3 cm
    into each other, 0 apart; the probe runs a pile end to end."""
    import contact_pile_flips_probe as probe
    import contact_piles

    bodies, block = contact_piles.pile(2, (4, 4, 2), "cpu", torch.float64)
    sim = contact_piles.simulator(bodies, tm.Contact(), "cpu", torch.float64)
    faces = sim.surface_triangles()
    surface = {body: torch.unique(f) for body, f in faces.items()}
    assert probe.inside(sim.x, surface[1], faces[0]) == 0.0
    nodes = block.num_vertices
    x = sim.x.clone()
    x[nodes:2 * nodes, 2] -= 0.16  # column 0's upper block 3 cm into the lower
    sim.x = x
    depth = sim.interpenetration()
    assert probe.inside(sim.x, surface[1], faces[0]) == pytest.approx(float(depth[1]), abs=1e-12)
    assert probe.inside(sim.x, surface[0], faces[1]) == pytest.approx(float(depth[0]), abs=1e-12)
    assert float(depth[0]) == pytest.approx(0.03, abs=1e-9)
    events = probe.main(["--columns", "2", "--cells", "2", "2", "1", "--steps", "3", "--device", "cpu",
                         "--out", str(tmp_path / "events.json")])
    assert json.loads((tmp_path / "events.json").read_text()) == events


def test_contact_pile_flips_probe_tilts():
    """A block's tilt is the angle of its thin axis from the vertical, whatever its position,
    its scale and the sense of the turn: 0, 30, 90 and 30 degrees (turned by 150) about x."""
    import contact_pile_flips_probe as probe

    rest = tm.beam_mesh(4, 4, 2, size=(0.2, 0.2, 0.1), dtype=torch.float64).vertices

    def turned(degrees):
        c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
        return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64)

    x = torch.cat([rest, rest @ turned(30).T + 1.0, 1.1 * rest @ turned(90).T, rest @ turned(150).T])
    assert probe.tilts(x, rest).tolist() == pytest.approx([0.0, 30.0, 90.0, 30.0], abs=1e-6)


def test_contact_host_reads_probe_counts_each_read_once():
    """The host-reads probe counts a scalar read, a nonzero, a mask index, a repeat_interleave
    without its output size and a tolist once each, and nothing for the same work without reads;
    it runs a pile end to end, the detection's reads among its counts, ops in the CG's iterations
    and outside them."""
    import contact_host_reads_probe as probe

    values = torch.arange(6.0)
    reads = probe.HostReads()
    with reads, probe.ListReads(reads.counts):
        float(values.sum())
        torch.nonzero(values > 2)
        values[values > 2]
        torch.repeat_interleave(torch.tensor([1, 2]))
        values.tolist()
        torch.repeat_interleave(values, torch.tensor([1, 1, 1, 1, 1, 1]), output_size=6)
        values[torch.tensor([0, 2])] * 2
        values.cumsum(0).clamp(max=3.0)
    by_op = {op: n for (op, _), n in reads.counts.items()}
    assert by_op == {"_local_scalar_dense": 1, "nonzero": 1, "index": 1, "repeat_interleave": 1, "tolist": 1}
    # (no skin: the step's detection searches, its reads among the counts)
    counts, ops, iterations = probe.main(["--columns", "2", "--cells", "2", "2", "1", "--steps", "3", "--timed", "1",
                                          "--contact", '{"skin": 0}', "--device", "cpu"])
    assert len(iterations) == 1 and iterations[0]
    assert any("covered_cells" in site for _, site in counts)
    assert ops["in the CG's iterations"] > 0 and ops["outside"] > 0


def test_contact_piles_resumes_a_paused_run(tmp_path):
    """--state with --budget-s 0 pauses after each step, saving the state; the same command goes
    on from it to the end, at the state an uninterrupted run reaches; two preconditioners and two
    rounds, the pile without contact measured once for each preconditioner."""
    import contact_piles

    whole = contact_piles.main(["--quick", "--device", "cpu", "--dtype", "float64", "--out", str(tmp_path / "a"),
                                "--preconditioners", "auto", "none", "--rounds", "2", "1"])
    assert [(r["preconditioner"], r["rounds"]) for r in whole] == [("auto", 2), ("auto", 1), ("none", 2), ("none", 1)]
    assert whole[0]["steps_per_s_without"] == whole[1]["steps_per_s_without"]
    assert whole[2]["steps_per_s_without"] == whole[3]["steps_per_s_without"]
    command = ["--quick", "--device", "cpu", "--dtype", "float64", "--out", str(tmp_path / "b"),
               "--state", str(tmp_path / "state"), "--budget-s", "0"]
    assert contact_piles.main(command) == []  # paused after step 1
    meta = json.loads((tmp_path / "state" / "columns2_auto" / "meta.json").read_text())
    assert meta["step"] == 1
    assert contact_piles.main(command) == []  # after step 2
    (row,) = contact_piles.main(command)  # step 3 ends the run
    assert row["steps"] == 3
    inside, kinetic = whole[0]["checks"][-1][1:3]
    assert row["checks"][-1][0] == 3
    assert abs(row["checks"][-1][2] - kinetic) <= 1e-9 * max(1.0, kinetic)
    assert abs(row["interpenetration_m"] - inside) <= 1e-9


def test_rollout_gradients_quick(tmp_path):
    import rollout_gradients

    records = rollout_gradients.main(["--device", "cpu", "--quick", "--out", str(tmp_path),
                                      "--scenes", "sofa_beam", "--models", "hooke"])
    rows = [(r["mode"], r.get("leaves")) for r in records]
    assert rows == [("sim.step", None), ("budget", "young, x0"), ("budget", "x0"), ("exact", "young, x0"),
                    ("exact", "x0"), ("per element", None)]
    assert all(r["backward_ms"] > 0 and r["forward_ms"] > 0 for r in records[1:5])
    assert records[-1]["scene"] == "identify_moduli" and records[-1]["rollouts"] > 1
    assert (tmp_path / "rollout_gradients.md").exists()


def test_rollout_gradients_of_the_contact_scene(tmp_path):
    import rollout_gradients

    records = rollout_gradients.main(["--device", "cpu", "--quick", "--out", str(tmp_path), "--scenes", "stack",
                                      "--models", "hooke", "--identify", "", "--modes", "budget"])
    assert [r["mode"] for r in records] == ["sim.step", "budget", "budget"]
    assert all(r["backward_ms"] > 0 for r in records[1:])


def test_distributed_scaling_quick(tmp_path, monkeypatch):
    pytest.importorskip("pymetis")
    import socket

    import distributed_scaling

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    # (the script makes a group of one through these: set here, so that they are undone after)
    for name, value in dict(RANK="0", WORLD_SIZE="1", LOCAL_RANK="0", MASTER_ADDR="127.0.0.1",
                            MASTER_PORT=str(port)).items():
        monkeypatch.setenv(name, value)
    distributed_scaling.main(["--quick", "--device", "cpu", "--out", str(tmp_path)])
    records = json.loads((tmp_path / "distributed_scaling.json").read_text())["records"]
    by = {(r["kind"], r["path"]): r for r in records}
    # one rank's partitioned CG is the one-process CG: the same iterations to the same tolerance
    assert by[("beam", "partitioned (metis)")]["cg_iterations"] == by[("beam", "single")]["cg_iterations"] > 0
    assert by[("batch", "40 bodies")]["body_steps_per_s"] > 0
    assert "| beam | 1 | 4800 | partitioned (metis) |" in (tmp_path / "distributed_scaling.md").read_text()


def test_newton_comparison_quick(tmp_path):
    """Our rows always; Newton's where newton and warp are installed (not a dependency), else one
    line in the notes saying they were skipped."""
    import newton_comparison

    newton_comparison.main(["--quick", "--device", "cpu", "--models", "hooke", "--cg-budgets", "10,converged",
                            "--vbd-budgets", "5", "--seconds", "0.05", "--stable-dts", "0.01,0.04",
                            "--scenes", "paper_beam,drop", "--out", str(tmp_path)])
    data = json.loads((tmp_path / "newton_comparison.json").read_text())
    ours = {r["budget"]: r for r in data["records"] if r["engine"] == "tensormass_torch" and r["scene"] == "paper_beam"}
    assert ours["CG converged"]["solver_error"] == 0.0 and 0 < ours["CG 10"]["solver_error"] < 1
    assert ours["CG 10"]["max_tip"] > 0 and ours["CG 10: largest stable dt"]["dt"] in (0.01, 0.04)
    # the drop: 4 bodies of 72 tets falling (0.05 s: 1.2 cm) in one batch
    drop = {r["budget"]: r for r in data["records"] if r["engine"] == "tensormass_torch" and r["scene"] == "drop"}
    assert drop["CG 10"]["elements"] == 4 * 72 and 0.005 < drop["CG 10"]["max_tip"] < 0.02
    # the ratios at equal error follow the table, and the json rebuilds the same md
    md = (tmp_path / "newton_comparison.md").read_text()
    assert "ours / Newton" in md
    newton_comparison.main(["--replot", "--out", str(tmp_path)])
    assert (tmp_path / "newton_comparison.md").read_text() == md
    newton_rows = [r for r in data["records"] if r["engine"] == "newton"]
    skipped = newton_comparison.newton_available()
    assert bool(newton_rows) == (skipped is None)
    if skipped:
        assert any("skipped" in note for note in data["meta"].get("notes", [])) or \
            "skipped" in (tmp_path / "newton_comparison.md").read_text()


def test_setup_memory_quick(tmp_path):
    """Each (model, size) measured in a process of its own: positive bytes a tet, the peak at
    least what is held and at least the construction's, a set-up time; a size that fails is a
    row with its error, not a lost run."""
    import setup_memory

    setup_memory.main(["--quick", "--device", "cpu", "--out", str(tmp_path)])
    setup_memory.main(["--device", "cpu", "--models", "nonsense", "--elements", "3000", "--steps", "2",
                       "--out", str(tmp_path / "bad")])
    rows = json.loads((tmp_path / "setup_memory.json").read_text())["records"]
    assert [r["model"] for r in rows] == ["hooke", "stvk"]
    for r in rows:
        assert r["elements"] > 2000 and r["setup_s"] > 0 and r["ms_per_step"] > 0
        assert 0 < r["held_b"] <= r["peak_b"] and r["construction_peak_b"] <= r["peak_b"]
    bad = json.loads((tmp_path / "bad" / "setup_memory.json").read_text())["records"]
    assert len(bad) == 1 and "nonsense" in bad[0]["error"]


def test_memory_parts_quick_are_the_estimate_s_parts(tmp_path):
    """The study that measured ``sim.memory.HELD``, on small meshes: its parts are the table's
    within 15 % (the element and node parts of the estimate are what a CPU count gives)."""
    import memory_parts

    from tensormass_torch.sim.memory import HELD

    rows = memory_parts.main(["--quick", "--kinds", "tet", "--models", "hooke,stvk", "--out", str(tmp_path)])
    assert (tmp_path / "memory_parts.md").exists() and (tmp_path / "memory_parts.json").exists()
    for row in rows:
        form = "tensor" if row["model"] == "hooke" else "stress"
        element, node = HELD[(row["kind"], row["model"], form)]
        measured = (sum(row["element"]), sum(row["node"]))
        for got, table in zip(measured, (sum(element), sum(node))):
            assert abs(got / table - 1) < 0.15, (row, element, node)


def test_contact_step_kernels_probe_gives_each_wait_to_the_frame_that_launched_next():
    """The kernels probe's trace reading (the probe itself needs CUDA): kernel time is the kernels'
    durations; each idle gap goes to the innermost library frame open at the launch of the kernel
    after it; a launch outside any library frame, or unknown, to its own row; each kernel's time to
    the innermost frame open at its launch, and to every frame open then; the host's own time by
    frame, nested frames left out, and its waits for the device."""
    import contact_step_kernels_probe as probe

    def frame(start, end, name):
        return {"ph": "X", "cat": "python_function", "ts": start, "dur": end - start, "name": f"tensormass_torch/{name}"}

    def kernel(start, end, correlation):
        return {"ph": "X", "cat": "kernel", "ts": start, "dur": end - start, "name": "k", "args": {"correlation": correlation}}

    def launch(at, correlation):
        return {"ph": "X", "cat": "cuda_runtime", "ts": at, "dur": 1, "name": "cudaLaunchKernel",
                "args": {"correlation": correlation}}

    events = [frame(0, 100, "step"), frame(10, 40, "detect"), frame(50, 90, "solve"), frame(55, 60, "load"),
              kernel(20, 30, 1), launch(12, 1),     # the first kernel: no gap before it
              kernel(45, 50, 2), launch(35, 2),     # idle 15, launched in detect
              kernel(60, 70, 3), launch(57, 3),     # idle 10, launched in load (inside solve)
              kernel(75, 80, 4), launch(95, 4),     # idle 5, launched in step only
              kernel(90, 95, 5), launch(120, 5),    # idle 10, launched outside the library
              kernel(99, 100, 6)]                   # idle 4, no launch recorded
    busy, idle, by_frame = probe.gaps_by_frame(events)
    assert busy == 10 + 5 + 10 + 5 + 5 + 1
    assert idle == 15 + 10 + 5 + 10 + 4
    assert by_frame == {"detect": 15, "load": 10, "step": 5, "(no library frame)": 14}
    inner, inclusive = probe.kernels_by_frame(events)  # each kernel's time to the frames open at its launch
    assert inner == {"detect": 10 + 5, "load": 10, "step": 5, "(no library frame)": 5 + 1}
    assert inclusive == {"step": 10 + 5 + 10 + 5, "detect": 10 + 5, "solve": 10, "load": 10}
    waits = [{"ph": "X", "cat": "cuda_runtime", "ts": at, "dur": wait, "name": name, "args": {}}
             for at, wait, name in ((15, 5, "cudaStreamSynchronize"), (56, 2, "cudaMemcpyAsync"))]
    own, waited = probe.host_by_frame(events + waits)  # each frame's time less its nested frames'
    assert own == {"step": 100 - 30 - 40, "detect": 30, "solve": 40 - 5, "load": 5}
    assert waited == {"detect": 5, "load": 2}


def test_rigid_modes_probe_times_the_load_and_its_pieces():
    """The rigid correction's probe times its loads and their pieces (the pieces within the load)
    and puts the library's functions back."""
    import rigid_modes_probe as probe

    from tensormass_torch.solver import rigid_modes

    plain = {name: getattr(rigid_modes, name) for name in probe.PIECES}
    medians = probe.main(["--columns", "2", "--cells", "2", "2", "1", "--steps", "20", "--timed", "2",
                          "--device", "cpu", "--contact", '{"friction": 0.5}'])
    assert {"load", "lever_arms", "own_blocks", "group_matrices"} <= set(medians)
    assert all(ms > 0 for ms in medians.values())
    assert medians["own_blocks"] < medians["load"]
    assert all(getattr(rigid_modes, name) is function for name, function in plain.items())


def test_segment_reduce_probe_quick():
    """The segment_reduce probe's columns laid end to end reduce as torch does (every case)."""
    import segment_reduce_probe as probe

    rows = probe.main(["--bodies", "3", "--nodes", "70", "--surface", "30", "--pairs", "40", "--repeats", "1",
                       "--device", "cpu"])
    assert len(rows) == 7 and all(row[3] < 1e-4 for row in rows)


def test_interpenetration_probe_quick():
    """The interpenetration probe's batched check equals the body-by-body one on a small pile."""
    import interpenetration_probe as probe

    out = probe.main(["--columns", "2", "--cells", "2", "2", "1", "--steps", "10", "--repeats", "1",
                      "--device", "cpu"])
    assert out["difference"] == 0.0 and len(out["batched_s"]) == 1


def test_mixed_precision_probe_refines_every_step_to_the_tolerance(tmp_path):
    """mixed_precision_probe: the float32 corrections with float64 residuals end every step at a
    float64 relative residual of at most 1e-6, in as many float64 products as corrections plus one,
    and the probe writes its JSON."""
    import mixed_precision_probe

    records = mixed_precision_probe.main(["--young", "1e5", "--elements", "300", "--steps", "6", "--settle", "2",
                                          "--out", str(tmp_path)])
    (record,) = records
    assert record["worst_mixed_residual"] <= mixed_precision_probe.TOL
    for row in record["steps_detail"]:
        assert row["float64_products"] == len(row["float32_iterations"]) + 1
        assert row["float64_iterations"] > 0 and sum(row["float32_iterations"]) > 0
    assert json.loads((tmp_path / "mixed_precision.json").read_text())["records"][0]["young"] == 1e5


def test_warm_start_probe_quick():
    """The warm-start probe steps SOFA's beam cold and warm, and warm with the classic CG beside
    (--classic): on the CPU (no pipelined kernel) both warm CGs are the same solve."""
    import warm_start_probe as probe

    measured = probe.main(["--device", "cpu", "--settle", "2", "--steps", "2", "--classic", "--no-profile"])
    assert list(measured) == ["none", "extrapolate", "project", "extrapolate, classic CG", "project, classic CG"]
    assert all(ms > 0 for ms, _ in measured.values())
    for warm in ("extrapolate", "project"):
        assert measured[warm][1] == measured[f"{warm}, classic CG"][1]
        assert sum(measured[warm][1]) < sum(measured["none"][1])


def test_mixed_step_probe_quick():
    """The mixed-step probe times the float32 25-iteration, mixed and float64 steps of a small paper
    beam, alternated (CPU, eager)."""
    import mixed_step_probe as probe

    medians = probe.main(["--device", "cpu", "--elements", "1200", "--young", "1e5", "--no-profile", "--repeats", "2"])
    assert set(medians) == {(1e5, probe.BASELINE), (1e5, "mixed"), (1e5, "float64, full")}
    assert all(ms > 0 for ms in medians.values())
