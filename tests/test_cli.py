"""The command line: `tensormass run` does real work and writes a ParaView series."""
import subprocess
import sys

import pytest

from tensormass_torch.cli import main


def test_run_cantilever_writes_frames(tmp_path):
    pytest.importorskip("meshio")
    out = tmp_path / "out"
    assert main(["run", "cantilever", "--steps", "2", "--every", "1", "--out", str(out), "--quiet"]) == 0
    frames = sorted(out.glob("cantilever_0_*.vtu"))
    assert len(frames) == 3  # the rest state and two steps
    pvd = (out / "cantilever.pvd").read_text()
    assert all(f.name in pvd for f in frames)
    import meshio

    last = meshio.read(frames[-1])
    assert last.point_data["displacement"][:, 2].min() < 0  # it sagged under gravity


def test_run_unknown_scene_fails_cleanly(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "tensormass_torch", "run", "no_such_scene", "--out", str(tmp_path / "o")],
                          capture_output=True, text=True)
    assert proc.returncode != 0
    assert "no_such_scene" in proc.stderr
    assert not (tmp_path / "o").exists()
