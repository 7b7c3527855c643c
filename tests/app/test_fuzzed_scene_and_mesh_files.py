"""Random mistakes in scene files and mesh files (hypothesis): the command line answers each with
one line, ``tensormass: error: ...`` naming the file (and the key, for a key's mistake), exit
status 1 or 2, never a traceback; a scene that fails to load writes nothing, and a run that fails
part way leaves only complete files (every frame the .pvd lists, each readable)."""
import contextlib
import io
import json
import math
import string
from pathlib import Path

import pytest

hypothesis = pytest.importorskip("hypothesis")
meshio = pytest.importorskip("meshio")
import numpy as np  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import tensormass_torch as tm  # noqa: E402
from tensormass_torch.app.cli import main  # noqa: E402

FUZZ = settings(max_examples=300, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

BASE = {
    "name": "fuzz",
    "dt": 0.01,
    "steps": 3,
    "output_every": 1,
    "gravity": [0.0, 0.0, -9.81],
    "solver": {"cg_tol": 1e-5, "rayleigh_mass": 0.5},
    "planes": [{"normal": [0.0, 0.0, 1.0], "offset": -0.2, "stiffness": 1e4}],
    "bodies": [
        {"name": "beam", "mesh": {"generator": "beam", "cells": [3, 1, 1], "size": [0.3, 0.1, 0.1]},
         "material": {"model": "stvk", "young": 1e5, "poisson": 0.3, "density": 1000.0},
         "fixed": {"box": [[0.0, 0.0, 0.0], [0.0, 0.1, 0.1]]}},
        {"name": "block", "mesh": {"file": "block.vtu"},
         "material": {"model": "corotational", "young": 2e4, "poisson": 0.35},
         "prescribed": {"nodes": [0, 1], "velocity": [0.0, 0.0, -0.1], "stop": 0.5}, "velocity": [0.0, 0.0, 0.1]},
    ],
}


# ---------------------------------------------------------------------------------------------
# A TOML writer for the scene's shapes (top-level values, [tables], [[arrays of tables]])
# ---------------------------------------------------------------------------------------------


def _value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{json.dumps(k)} = {_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(type(v))


def to_toml(scene: dict) -> str:
    lines, tables, arrays = [], [], []
    for key, v in scene.items():
        if isinstance(v, dict):
            tables.append((key, v))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            arrays.append((key, v))
        else:
            lines.append(f"{json.dumps(key)} = {_value(v)}")
    for key, table in tables:
        lines += ["", f"[{json.dumps(key)}]"] + [f"{json.dumps(k)} = {_value(x)}" for k, x in table.items()]
    for key, items in arrays:
        for table in items:
            lines += ["", f"[[{json.dumps(key)}]]"] + [f"{json.dumps(k)} = {_value(x)}" for k, x in table.items()]
    return "\n".join(lines) + "\n"


def paths(node, prefix=()):
    """Every key path of ``node`` (dict keys and list indices)."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, child in items:
        yield prefix + (key,)
        yield from paths(child, prefix + (key,))


values = st.one_of(
    st.booleans(), st.integers(-3, 4), st.floats(-2.0, 2.0), st.sampled_from([0.0, -1.0, 1e300, math.nan, math.inf]),
    st.text(string.ascii_letters + "._-/", max_size=8), st.lists(st.floats(-1.0, 1.0), max_size=4),
    st.lists(st.integers(-2, 40), max_size=4), st.dictionaries(st.sampled_from(["a", "box", "x"]), st.integers(0, 3),
                                                              max_size=2))


@st.composite
def mutated_scenes(draw):
    scene = json.loads(json.dumps(BASE))
    for _ in range(draw(st.integers(1, 3))):
        where = draw(st.sampled_from(sorted(paths(scene), key=str)))
        parent = scene
        for key in where[:-1]:
            parent = parent[key]
        key = where[-1]
        action = draw(st.sampled_from(["delete", "rename", "replace", "replace", "add"]))
        if action == "delete" and isinstance(parent, dict):
            del parent[key]
        elif action == "rename" and isinstance(parent, dict):
            typo = draw(st.sampled_from([key + "s", key[:-1], key.upper(), key.replace("_", "")]))
            parent[typo or "x"] = parent.pop(key)
        elif action == "add" and isinstance(parent, dict):
            parent[draw(st.sampled_from(["colour", "youngs", "cg_tolerance", "mesh2"]))] = draw(values)
        else:
            parent[key] = draw(values)
    return scene


def block_mesh(path: Path):
    mesh = tm.beam_mesh(2, 1, 1, size=(0.2, 0.1, 0.1), origin=(0.5, 0.0, 0.0), dtype=__import__("torch").float64)
    tm.save_mesh(path, mesh)
    return mesh


def run_cli(args):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            status = main(args)
        except SystemExit as exc:  # argparse
            status = exc.code
    return status, err.getvalue()


def check_outcome(status, err, out: Path, scene: Path = None):
    if status == 0:
        return
    assert status in (1, 2), (status, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tensormass: error: "), err
    assert "Traceback" not in err
    if out.exists():
        files = {p.name for p in out.iterdir()}
        assert not any(".partial" in name for name in files), files
        pvd = [p for p in out.iterdir() if p.suffix == ".pvd"]
        if not pvd:  # failed before the first frame: nothing written
            assert not files, (err, files)
        for series in pvd:  # failed part way: the series lists complete, readable frames only
            listed = [line.split('file="')[1].split('"')[0] for line in series.read_text().splitlines()
                      if 'file="' in line]
            assert set(listed) == {name for name in files if name.endswith(".vtu")}
            for name in listed:
                meshio.read(out / name)


@FUZZ
@given(scene=mutated_scenes())
def test_mistakes_in_scene_files(scene, tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    block_mesh(folder / "block.vtu")
    path = folder / "fuzz.toml"
    path.write_text(to_toml(scene))
    out = folder / "out"
    status, err = run_cli(["run", str(path), "--out", str(out), "--quiet"])
    check_outcome(status, err, out)
    if status == 1 and "fuzz.toml" not in err:  # not a load error: the run itself failed
        assert "failed" in err or "NaN" in err or "inverted" in err, err


@FUZZ
@given(text=st.text(max_size=200), cut=st.integers(0, 2000))
def test_broken_toml_text(text, cut, tmp_path_factory):
    folder = tmp_path_factory.mktemp("text")
    block_mesh(folder / "block.vtu")
    base = to_toml(BASE)
    path = folder / "fuzz.toml"
    path.write_text(base[:cut % len(base)] + text + base[cut % len(base):])
    out = folder / "out"
    status, err = run_cli(["run", str(path), "--out", str(out), "--quiet"])
    check_outcome(status, err, out)


MESH_MISTAKES = ["nan", "inf", "index_high", "index_negative", "degenerate", "inverted", "no_cells", "bytes",
                 "truncated", "float_cells", "triangles_2d"]


@FUZZ
@given(mistake=st.sampled_from(MESH_MISTAKES), which=st.integers(0, 10_000), junk=st.binary(max_size=300),
       suffix=st.sampled_from([".vtu", ".msh", ".vtk"]))
def test_mistakes_in_mesh_files(mistake, which, junk, suffix, tmp_path_factory):
    folder = tmp_path_factory.mktemp("mesh")
    mesh = block_mesh(folder / "good.vtu")
    points = mesh.vertices.numpy().copy()
    cells = mesh.elements.numpy().copy()
    i, j = which % len(cells), which % len(points)
    kind = "tetra"
    if mistake == "nan":
        points[j, which % 3] = np.nan
    elif mistake == "inf":
        points[j, which % 3] = np.inf
    elif mistake == "index_high":
        cells[i, which % 4] = len(points) + which
    elif mistake == "index_negative":
        cells[i, which % 4] = -1 - which % 5
    elif mistake == "degenerate":
        cells[i, 1] = cells[i, 0]
    elif mistake == "inverted":
        cells[i, [0, 1]] = cells[i, [1, 0]]
    elif mistake == "triangles_2d":
        points, cells, kind = points[:, :2], cells[:, :3], "triangle"
    path = folder / f"m{suffix}"
    if mistake == "bytes":
        path.write_bytes(junk)
    elif mistake == "truncated":
        meshio.write(str(path), meshio.Mesh(points, [(kind, cells)]))
        data = path.read_bytes()
        path.write_bytes(data[: which % max(len(data), 1)])
    else:
        data = cells.astype(float) + 0.5 if mistake == "float_cells" else cells
        blocks = [] if mistake == "no_cells" else [(kind, data)]
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            try:
                meshio.write(str(path), meshio.Mesh(points, blocks))
            except Exception:  # meshio itself refuses (a negative index in gmsh...): junk instead
                path.write_bytes(junk)
    scene = json.loads(json.dumps(BASE))
    scene["bodies"][1]["mesh"] = {"file": path.name}
    scene["bodies"][1].pop("prescribed")
    (folder / "fuzz.toml").write_text(to_toml(scene))
    out = folder / "out"
    status, err = run_cli(["run", str(folder / "fuzz.toml"), "--out", str(out), "--quiet"])
    check_outcome(status, err, out)
    if status:
        assert "bodies[1].mesh.file" in err or "bodies[1]" in err, err
    converted = folder / "converted" / "c.vtu"
    status, err = run_cli(["convert", str(path), str(converted), "--quiet"])
    check_outcome(status, err, converted.parent)
