"""Every example runs (small sizes, CPU)."""
import importlib.util
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


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
