"""Every example runs (small sizes, CPU). identify_contact runs at its README size, so its checks
are made on the README's run (tests/test_readme.py, OUTPUT_CHECKS)."""
import importlib.util
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def load(name):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_cantilever_static_example():
    rows = load("cantilever_static").main(["--cells", "1", "2"])
    assert rows[1][3] < 0 and abs(rows[1][3]) < abs(rows[0][3])  # too stiff, improving


def test_batch_example(tmp_path):
    sim = load("batch_of_bodies").main(["--bodies", "3", "--steps", "2", "--out", str(tmp_path)])
    assert sim.num_bodies == 3 and sim.steps_done == 2
    assert (tmp_path / "batch.pvd").exists()


def test_converged_steps_example():
    """The three warm starts, and the projection with float32 iterations (precision="mixed"),
    give the same converged steps; the projection takes the fewest iterations once its basis
    holds the motion."""
    runs = load("converged_steps").main(["--cells", "12", "3", "3", "--steps", "24"])
    cold = runs["none"]
    for mode in ("extrapolate", "project", "project, mixed"):
        assert float((runs[mode]["x"] - cold["x"]).abs().max()) < 1e-7
    late = {mode: sum(r["iterations"][12:]) for mode, r in runs.items() if mode != "project, mixed"}
    assert late["project"] < late["extrapolate"] < late["none"], late


def test_large_rotation_example():
    """hooke fails under a 180-degree twist and spin; corotational keeps the volume (issue 4)."""
    import math

    import pytest

    figures = load("large_rotation").main(["--resolution", "1", "--steps", "20", "--models", "hooke", "corotational"])
    hooke, corot = figures[("twist", "hooke")], figures[("twist", "corotational")]
    assert corot["volume_change_max_pct"] < 6.0 and corot["inverted_max"] == 0
    assert corot["min_element_volume_ratio"] > 0.5
    assert corot["elastic_end_over_reference"] == pytest.approx(1.0, abs=0.2)  # the mesh's torsion energy
    assert hooke["inverted_max"] > 0 and hooke["min_element_volume_ratio"] < 0.0  # crushed next to the turned end
    assert hooke["elastic_end_over_reference"] > 5.0
    assert hooke["volume_change_max_pct"] > 3 * corot["volume_change_max_pct"]
    hooke, corot = figures[("spin", "hooke")], figures[("spin", "corotational")]
    assert abs(corot["volume_change_end_pct"]) < 6.0 and corot["angle_deg"] > 160.0
    # hooke's nodes move on straight lines: volume x (1 + pi^2), turned atan(pi)
    assert hooke["volume_change_end_pct"] == pytest.approx(100 * math.pi ** 2, rel=0.02)
    assert hooke["angle_deg"] == pytest.approx(math.degrees(math.atan(math.pi)), abs=2.0)


def test_figure1_example(tmp_path):
    result = load("figure1").main(["--cells", "1", "--out", str(tmp_path)])
    hooke, stvk = result["tips"]["hooke"], result["tips"]["stvk"]
    # Linear elasticity drops the tip straight down (and further); St Venant-Kirchhoff keeps the
    # beam's length, so its tip comes back toward the wall.
    assert hooke[2] < stvk[2] < 0
    assert abs(float(hooke[0])) < 0.01 < -float(stvk[0])
    assert all(f.exists() for f in result["files"])
    png = tmp_path / "figure1.png"
    if png in result["files"]:  # pyvista present: the picture is not blank
        import numpy as np
        from PIL import Image

        pixels = np.asarray(Image.open(png).convert("RGB")).astype(int)
        assert pixels.std() > 5 and (pixels.sum(axis=2) < 600).mean() > 0.01


def test_rabbit_example(tmp_path):
    import torch

    sim, tool = load("rabbit").main(["--cell", "0.15", "--steps", "3", "--every", "1", "--out", str(tmp_path)])
    assert sim.steps_done == 3 and int(tool.sum()) > 0
    # The tool's nodes follow their prescribed motion exactly: 0.1 m/s down for 0.03 s.
    u = sim.displacements(0)
    assert torch.allclose(u[tool], torch.tensor([0.0, 0.0, -0.003]).expand(int(tool.sum()), 3), atol=1e-6)
    assert float(u[~tool, 2].mean()) < 0  # the rest sags under gravity
    assert len(list(tmp_path.glob("rabbit_0_*.vtu"))) == 4 and (tmp_path / "rabbit.pvd").exists()


def test_many_objects_example():
    import torch

    sim = load("many_objects").main(["--objects", "8", "--steps", "2"])
    assert sim.num_bodies == 8 and sim.steps_done == 2
    shapes = {b.name.rstrip("0123456789") for b in sim.bodies}
    assert shapes == {"box", "ball", "capsule", "rabbit"}
    assert {b.material.model for b in sim.bodies} == {"hooke", "stvk"}  # 8 objects: two rounds of shapes
    assert len({float(b.material.young) for b in sim.bodies}) == 8
    assert torch.isfinite(sim.x).all() and float(sim.kinetic_energy().min()) > 0


def test_every_builtin_scene_runs():
    """Each scene of ``tm.sim.builtin.SCENES`` (what ``tensormass run NAME`` runs) at its smallest size."""
    import torch

    from tensormass_torch.sim.builtin import SCENES

    smallest = {"cantilever": {"resolution": 1}, "sofa_beam": {"scale": 15}, "twist": {"resolution": 1},
                "spin": {"resolution": 1}, "paper_beam": {"resolution": 1}, "cut": {"resolution": 1}}
    assert set(SCENES) <= set(smallest), f"add the new scene to this test: {sorted(set(SCENES) - set(smallest))}"
    for name, make in SCENES.items():
        scene = make(**smallest[name], dtype=torch.float64)
        scene.simulator.step(2)
        assert bool(torch.isfinite(scene.simulator.x).all()), name


def test_mesh_tool_example():
    """The belt (a tool of a closed surface) brings the block up to its speed by friction."""
    import pytest

    _, rows = load("mesh_tool").main(["--steps", "20", "--resolution", "12", "--device", "cpu"])
    assert rows[-1][2] == pytest.approx(0.2, abs=2e-3)
    assert rows[-1][1][2] < 0  # the block weighs on the belt


def test_identify_moduli_example():
    """Two regions' moduli recovered from a trajectory; per element, the misfit falls."""
    result = load("identify_moduli").main(["--cells", "4", "1", "1", "--regions", "2", "--steps", "10",
                                           "--iterations", "15"])
    for found, truth in zip(result["recovered"], result["truth"]):
        assert abs(found / truth - 1) < 1e-4
    result = load("identify_moduli").main(["--cells", "4", "1", "1", "--per-element", "--steps", "10",
                                           "--iterations", "15", "--model", "hooke"])
    assert result["misfit"] < 1e-2 * result["first_misfit"]


def test_reach_target_example():
    result = load("reach_target").main(["--cells", "4", "1", "1", "--steps", "10", "--iterations", "15"])
    assert result["distance"][1] < 0.1 * result["distance"][0]


def test_push_with_tool_example():
    """The sphere's path found through the tool's gradient brings the end to its height, at rest."""
    result = load("push_with_tool").main(["--cells", "4", "2", "2", "--steps", "24", "--iterations", "20"])
    assert result["miss_after"] < 0.05 * result["miss_before"] and result["speed_after"] < 0.01
