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
