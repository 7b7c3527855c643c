"""The command line: `tensormass run` does real work and writes a ParaView series; bad input gives
one error line, a non-zero status and no files; the progress line reads the solver's report only
when it redraws."""
import io
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.app.cli import main
from tensormass_torch.app.progress import Progress

SCENES_DIR = Path(__file__).resolve().parents[2] / "scenes"

SMALL_SCENE = """
name = "bar"
dt = 0.01
steps = 4
output_every = 2
[solver]
cg_tol = 1e-5
[[bodies]]
mesh = { generator = "beam", cells = [4, 1, 1], size = [1.0, 0.25, 0.25] }
material = { model = "stvk", young = 1e5, poisson = 0.3 }
fixed = { box = [[0, 0, 0], [0, 0.25, 0.25]] }
"""


def scene_file(tmp_path, text=SMALL_SCENE, name="bar.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


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


def test_run_scene_file_with_progress(tmp_path, capsys):
    pytest.importorskip("meshio")
    out = tmp_path / "out"
    assert main(["run", str(scene_file(tmp_path)), "--out", str(out), "--dtype", "float64"]) == 0
    # output_every = 2 over 4 steps: the rest state and steps 2 and 4.
    assert sorted(p.name for p in out.iterdir()) == ["bar.pvd", "bar_0_00000.vtu", "bar_0_00001.vtu",
                                                     "bar_0_00002.vtu"]
    err = capsys.readouterr().err
    final = [line for line in err.replace("\r", "\n").splitlines() if "4/4" in line][-1]
    assert "steps/s" in final and "CG" in final and "res " in final, err
    assert "float64" in err


def test_run_quiet_prints_nothing(tmp_path, capsys):
    assert main(["run", str(scene_file(tmp_path)), "--steps", "1", "--quiet"]) == 0
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "tensormass_torch", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


def test_run_unknown_scene_fails_cleanly(tmp_path):
    proc = _cli("run", "no_such_scene", "--out", str(tmp_path / "o"))
    assert proc.returncode == 2
    assert proc.stderr.startswith("tensormass: error: unknown scene 'no_such_scene'")
    assert not (tmp_path / "o").exists()


BAD_SCENES = {
    "bad TOML": (SMALL_SCENE.replace("steps = 4", "steps = = 4"), "invalid TOML"),
    "unknown model": (SMALL_SCENE.replace('"stvk"', '"stvkk"'),
                      "bodies[0].material.model: unknown model 'stvkk'; expected one of hooke, stvk, corotational"),
    "missing mesh": (SMALL_SCENE.replace('generator = "beam", cells = [4, 1, 1], size = [1.0, 0.25, 0.25]',
                                         'file = "missing.vtu"'), "bodies[0].mesh.file: mesh file not found"),
    "empty box": (SMALL_SCENE.replace("[[0, 0, 0], [0, 0.25, 0.25]]", "[[3, 3, 3], [4, 4, 4]]"),
                  "bodies[0].fixed.box: selects no node"),
}


@pytest.mark.parametrize("case", sorted(BAD_SCENES))
def test_bad_scene_one_line_status_1_nothing_written(tmp_path, capsys, case):
    text, expected = BAD_SCENES[case]
    out = tmp_path / "out"
    assert main(["run", str(scene_file(tmp_path, text)), "--out", str(out), "--png"]) == 1
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and captured.out == "", captured.err
    assert lines[0].startswith("tensormass: error: ") and expected in lines[0]
    assert not out.exists()


def test_bad_scene_through_the_real_command(tmp_path):
    text, expected = BAD_SCENES["unknown model"]
    out = tmp_path / "out"
    proc = _cli("run", str(scene_file(tmp_path, text)), "--out", str(out))
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines() == [f"tensormass: error: {tmp_path / 'bar.toml'}: {expected}"]
    assert not out.exists()


def test_missing_scene_file_and_bad_flags(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "o")]) == 1
    assert "scene file not found" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:  # argparse: usage errors exit 2
        main(["run", "cantilever", "--steps", "0"])
    assert info.value.code == 2
    assert main(["run", "cantilever", "--png"]) == 2  # pictures need a folder
    assert "--png and --gif need --out" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_solver_failure_exits_1(tmp_path, capsys):
    # One CG iteration cannot reach 1e-12: with require_convergence (the default) the step fails.
    text = SMALL_SCENE.replace("cg_tol = 1e-5", "cg_tol = 1e-12\ncg_max_iter = 1")
    assert main(["run", str(scene_file(tmp_path, text)), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("tensormass: error: ") and len(err.strip().splitlines()) == 1


def test_bench_reports_steps_per_second(tmp_path, capsys):
    assert main(["bench", str(scene_file(tmp_path)), "--steps", "2", "--warmup", "1", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["scene"] == "bar" and result["steps"] == 2 and result["steps_per_s"] > 0
    assert result["cg_iterations_per_step"] >= 1 and result["elements"] == 24


def test_bench_help_points_to_the_suite(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    assert "benchmarks/" in capsys.readouterr().out


def test_convert_round_trip(tmp_path, capsys):
    pytest.importorskip("meshio")
    mesh = tm.beam_mesh(3, 2, 1, size=(1.0, 0.5, 0.2), dtype=torch.float64)
    tm.save_mesh(tmp_path / "a.vtu", mesh, u=torch.ones(mesh.num_vertices))
    assert main(["convert", str(tmp_path / "a.vtu"), str(tmp_path / "b.msh")]) == 0
    back, data = tm.load_mesh(tmp_path / "b.msh", with_point_data=True)
    assert torch.equal(back.vertices, mesh.vertices) and torch.equal(back.elements, mesh.elements)
    assert torch.equal(data["u"], torch.ones(mesh.num_vertices, dtype=data["u"].dtype))
    assert main(["convert", str(tmp_path / "a.vtu"), str(tmp_path / "c.mesh")]) == 0  # medit: data dropped
    assert "dropped u" in capsys.readouterr().err
    assert tm.load_mesh(tmp_path / "c.mesh").num_elements == mesh.num_elements


def test_convert_errors(tmp_path, capsys):
    assert main(["convert", str(tmp_path / "missing.vtu"), str(tmp_path / "b.vtu")]) == 1
    assert "mesh file not found" in capsys.readouterr().err
    (tmp_path / "junk.vtu").write_text("not a mesh")
    assert main(["convert", str(tmp_path / "junk.vtu"), str(tmp_path / "b.vtu")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("tensormass: error: could not read mesh file") and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "b.vtu").exists()


def test_info_reports_build_and_devices(capsys):
    assert main(["info"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert {"cpu", "cuda", "version", "cuda_devices", "build"} <= set(info)
    assert len(info["cuda_devices"]) == torch.cuda.device_count()
    assert info["build"]["cpu_threads"] >= 1


# -- the progress line ------------------------------------------------------------------------


class _CountingSimulator:
    """Stands in for a Simulator: counts reads of ``last_report`` (each one a device sync on a GPU)."""

    def __init__(self):
        self.time = 0.0
        self.reads = 0
        result = type("CG", (), {"iterations": torch.tensor([7]), "relative_residual": torch.tensor([3e-5])})
        self._report = type("Report", (), {"cg": [result]})

    @property
    def last_report(self):
        self.reads += 1
        return self._report


def test_progress_reads_the_report_only_when_it_redraws():
    clock = iter([0.01 * i for i in range(1000)])
    stream = io.StringIO()
    bar = Progress(200, stream=stream, interval=0.5, clock=lambda: next(clock), label="bar")
    sim = _CountingSimulator()
    for done in range(1, 201):  # 2 s of fake time, 10 ms per step, 8 ms of them stepping
        sim.time = 0.01 * done
        bar.update(done, sim, 0.008 * done)
    bar.finish(200, sim, 1.6)
    assert sim.reads == bar.reads == 5  # at 0.5, 1.0, 1.5, 2.0 s, and the final state
    final = stream.getvalue().replace("\r", "\n").splitlines()[-1]
    assert final.startswith("bar: 100%") and "200/200" in final
    # the rate counts the stepping time only (200 steps in 1.6 s), not the frames written between
    assert "t=2.000 s, 125.0 steps/s, CG 7 it, res 3.0e-05" in final


# -- pictures ---------------------------------------------------------------------------------


def test_run_renders_png_and_gif(tmp_path):
    pytest.importorskip("pyvista")
    import numpy as np
    from PIL import Image

    out = tmp_path / "out"
    assert main(["run", str(scene_file(tmp_path)), "--steps", "2", "--every", "1", "--out", str(out),
                 "--png", "--gif", "--quiet"]) == 0
    pngs = sorted(out.glob("bar_*.png"))
    assert len(pngs) == 3
    pixels = np.asarray(Image.open(pngs[-1]).convert("RGB")).astype(int)
    assert pixels.std() > 5  # not blank: the body is drawn on the white background
    assert (pixels.sum(axis=2) < 600).mean() > 0.005
    gif = Image.open(out / "bar.gif")
    assert gif.n_frames == 3
