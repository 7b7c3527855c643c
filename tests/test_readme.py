"""What a new user runs first is what the tests run: every code block of the README, as written,
to its full length, from the repository's root (as the README says), on the CPU.

* ```python blocks run in a fresh namespace;
* ```sh blocks run line by line through bash: the `tensormass` commands, the examples and
  `bash scripts/run.sh` (the README's first command). `bash scripts/test.sh` is the one line not
  run here: it runs this file (CI's `.ci/run` runs it, which is checked below);
* ```toml blocks are scene files, run with `tensormass run` to their end.

Every example under examples/ and every scene under scenes/ runs to its full length here too
(the examples through the README, which must list each one).
"""
import os
import re
import shlex
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text(encoding="utf-8")
BLOCK = re.compile(r"^```(\w*)\n(.*?)^```", re.M | re.S)
NOT_RUN = ("bash scripts/test.sh",)


def blocks(language):
    return [m.group(2) for m in BLOCK.finditer(README) if m.group(1) == language]


def commands():
    lines = []
    for block in blocks("sh"):
        for line in block.splitlines():
            command = line.split("#", 1)[0].strip() if not line.lstrip().startswith("#") else ""
            if command and not command.startswith(NOT_RUN):
                lines.append(command)
    return lines


def _env(tmp_path):
    """The environment of a user who installed the package into this python: its scripts folder
    (the `tensormass` entry point) first on PATH, `python` meaning this python."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    if not (bin_dir / "python").exists():
        # a script, not a symlink: a symlink to a virtual environment's python, outside that
        # environment, starts the base python (its pyvenv.cfg is looked for beside the link)
        (bin_dir / "python").write_text(f'#!/bin/sh\nexec {shlex.quote(sys.executable)} "$@"\n')
        (bin_dir / "python").chmod(0o755)
    path = os.pathsep.join([str(bin_dir), sysconfig.get_path("scripts"), os.environ.get("PATH", "")])
    env = {k: v for k, v in os.environ.items() if k not in ("TENSORMASS_BACKEND",)}
    return {**env, "PATH": path, "PYTHON": sys.executable, "PYTHONUNBUFFERED": "1"}


def _run(command, env, timeout=900):
    done = subprocess.run(["bash", "-c", command], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=timeout)
    assert done.returncode == 0, (f"{command!r} failed ({done.returncode}):\n{done.stdout[-3000:]}\n"
                                  f"{done.stderr[-3000:]}")
    return done


def test_the_readme_has_runnable_blocks_and_hides_none():
    assert blocks("python") and blocks("sh") and blocks("toml")
    # A tensormass command or a Python snippet outside a block that runs would escape the tests.
    for match in BLOCK.finditer(README):
        if match.group(1) not in ("python", "sh", "toml"):
            text = match.group(2)
            assert not re.search(r"^\s*(tensormass |python |import tensormass)", text, re.M), text
    assert "bash scripts/run.sh" in commands()


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    assert "scripts/test.sh" in ci and any("bash scripts/test.sh" in b for b in blocks("sh"))


@pytest.mark.parametrize("index", range(len(blocks("python"))))
def test_python_block(index, monkeypatch):
    monkeypatch.chdir(ROOT)
    monkeypatch.delenv("TENSORMASS_BACKEND", raising=False)
    code = blocks("python")[index]
    exec(compile(code, f"README.md python block {index}", "exec"), {"__name__": "__readme__"})


def _identify_contact_recovers_the_truth(stdout):
    """examples/identify_contact.py: each parameter within 1e-3 of the truth, the misfit down 1e6x
    (its printed lines: ``misfit A -> B ...``, ``  name: ... (truth ...; error e)``)."""
    before, after = map(float, re.search(r"misfit (\S+) -> (\S+) ", stdout).groups())
    assert after < 1e-6 * before, stdout
    found = re.findall(r"^  (\w+): .*; error (\S+)\)$", stdout, re.M)  # (relative, at full precision)
    assert [name for name, _ in found] == ["stiffness", "thickness"], stdout
    assert all(float(error) < 1e-3 for _, error in found), stdout


#: what a README command's output must show beyond running cleanly (the examples' own checks, on
#: the run the README makes rather than a second one)
OUTPUT_CHECKS = {"python examples/identify_contact.py": _identify_contact_recovers_the_truth}


@pytest.mark.parametrize("command", commands())
def test_command(command, tmp_path):
    done = _run(command, _env(tmp_path))
    if command.startswith("tensormass run") and "--out" in command:
        out = ROOT / shlex.split(command)[shlex.split(command).index("--out") + 1]
        assert list(out.glob("*.pvd")), f"{command}: no .pvd in {out}"
    if "--gif" in command:
        assert list(out.glob("*.gif")), f"{command}: no GIF in {out}"
    assert "Traceback" not in done.stderr
    check = OUTPUT_CHECKS.get(command.split("#", 1)[0].strip())
    if check is not None:
        check(done.stdout)


def test_every_output_check_is_of_a_readme_command():
    assert set(OUTPUT_CHECKS) <= set(commands())


@pytest.mark.parametrize("index", range(len(blocks("toml"))))
def test_scene_file_block(index, tmp_path):
    scene = tmp_path / f"readme_{index}.toml"
    scene.write_text(blocks("toml")[index])
    _run(f"tensormass run {scene} --out {tmp_path / 'out'} --quiet", _env(tmp_path))
    assert list((tmp_path / "out").glob("*.pvd"))


def test_every_example_is_in_the_readme():
    listed = {Path(shlex.split(c)[1]).name for c in commands() if c.startswith("python examples/")}
    assert listed == {p.name for p in (ROOT / "examples").glob("*.py")}


SCENES = sorted((ROOT / "scenes").glob("*.toml"))
#: the shipped scenes the README runs on their defaults (float32, the extension), to their end:
#: test_command runs them, so the scene test leaves that one case out
README_RUNS = {Path(shlex.split(c)[2]).stem for c in commands()
               if c.startswith("tensormass run scenes/") and "--dtype" not in c and "--steps" not in c}


@pytest.mark.parametrize("backend", ["auto", "torch"])
@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("scene", SCENES, ids=[p.stem for p in SCENES])
def test_every_shipped_scene_runs_to_its_end(scene, dtype, backend, tmp_path):
    """Each shipped scene, to its full length, on defaults, with the extension in both dtypes;
    on the pure-torch fallback, in both dtypes, its first 40 steps (past the scalpel's start and
    the sphere's descent). Its full runs are the slowest of the suite, and what they would add is
    checked elsewhere: the fallback's ops and steps equal the extension's (the op, step,
    cut and contact tests run both backends)."""
    if (dtype, backend) == ("float32", "auto") and scene.stem in README_RUNS:
        pytest.skip("the README runs this scene on its defaults (test_command)")
    env = {**_env(tmp_path), "TENSORMASS_BACKEND": backend}
    steps = " --steps 40" if backend == "torch" else ""
    _run(f"tensormass run {scene} --dtype {dtype} --out {tmp_path / 'out'} --quiet{steps}", env)
    frames = list((tmp_path / "out").glob("*.vtu"))
    assert frames and list((tmp_path / "out").glob("*.pvd"))
