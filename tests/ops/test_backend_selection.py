"""Backend selection (tensormass_torch._backend) and the `info` command."""
import json
import os
import subprocess
import sys

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch import _backend

KEYS = {"cpu", "cuda", "reason", "torch", "cuda_device", "forced"}


@pytest.fixture(autouse=True)
def fresh_backend(monkeypatch):
    """Each test starts from an unset TENSORMASS_BACKEND and an empty import cache."""
    monkeypatch.delenv("TENSORMASS_BACKEND", raising=False)
    _backend.reset_cache()
    yield
    _backend.reset_cache()


def _extension_importable():
    try:
        import tensormass_torch._C  # noqa: F401
    except ImportError:
        return False
    return True


def test_backend_info_is_exported():
    assert tm.backend_info is _backend.backend_info


def test_backend_info_keys_and_values():
    info = tm.backend_info()
    assert KEYS <= set(info)
    assert info["cpu"] in ("extension", "torch")
    assert info["cuda"] in ("extension", "torch", "unavailable")
    assert isinstance(info["reason"], str) and info["reason"]
    assert info["torch"] == torch.__version__
    assert info["forced"] is False
    assert info["mode"] == "auto"
    json.dumps(info)  # plain data only


def test_backend_info_matches_this_machine():
    info = tm.backend_info()
    if torch.cuda.is_available():
        assert info["cuda"] in ("extension", "torch")
        assert isinstance(info["cuda_device"], str) and info["cuda_device"]
    else:
        assert info["cuda"] == "unavailable"
        assert info["cuda_device"] is None
    if _extension_importable():
        assert info["cpu"] == "extension"
        assert _backend.use_extension(torch.device("cpu"))
    else:
        assert info["cpu"] == "torch"
        assert "extension" in info["reason"]
        assert not _backend.use_extension(torch.device("cpu"))
        assert _backend.load_extension() is None


def test_forced_torch(monkeypatch):
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    _backend.reset_cache()
    info = tm.backend_info()
    assert info["cpu"] == "torch"
    assert info["cuda"] == ("torch" if torch.cuda.is_available() else "unavailable")
    assert info["forced"] is True
    assert info["reason"] == "forced by TENSORMASS_BACKEND=torch"
    assert _backend.load_extension() is None
    assert not _backend.use_extension(torch.device("cpu"))
    assert not _backend.use_extension("cuda")


def test_mode_is_case_and_space_insensitive(monkeypatch):
    monkeypatch.setenv("TENSORMASS_BACKEND", " Torch ")
    assert _backend.backend_mode() == "torch"
    monkeypatch.setenv("TENSORMASS_BACKEND", "")
    assert _backend.backend_mode() == "auto"


@pytest.mark.parametrize("value", ["cuda", "ext", "pytorch", "1"])
def test_bad_value_is_a_clear_error(monkeypatch, value):
    monkeypatch.setenv("TENSORMASS_BACKEND", value)
    with pytest.raises(ValueError, match="TENSORMASS_BACKEND") as excinfo:
        tm.backend_info()
    assert isinstance(excinfo.value, _backend.BackendError)
    assert isinstance(excinfo.value, tm.TensorMassError)
    assert repr(value) in str(excinfo.value)
    with pytest.raises(_backend.BackendError, match="TENSORMASS_BACKEND"):
        _backend.use_extension(torch.device("cpu"))


def test_other_device_types_never_use_the_extension():
    assert not _backend.use_extension(torch.device("meta"))


def test_forced_extension(monkeypatch):
    monkeypatch.setenv("TENSORMASS_BACKEND", "extension")
    info = tm.backend_info()
    assert info["forced"] is True and info["mode"] == "extension"
    if _extension_importable():
        assert _backend.use_extension(torch.device("cpu"))
    else:
        with pytest.raises(_backend.BackendError, match="TENSORMASS_BACKEND=extension"):
            _backend.use_extension(torch.device("cpu"))


def test_load_is_cached(monkeypatch):
    first = _backend.load_extension()
    assert _backend._loaded
    calls = []
    monkeypatch.setattr(_backend.importlib, "import_module", lambda *a: calls.append(a))
    assert _backend.load_extension() is first
    assert calls == []


def _run_cli(*args, env_update=None):
    env = dict(os.environ)
    env.pop("TENSORMASS_BACKEND", None)
    env.update(env_update or {})
    # Run from outside the repo, with this tree first on the path (same as the editable install).
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = os.pathsep.join(p for p in (repo, env.get("PYTHONPATH")) if p)
    return subprocess.run(
        [sys.executable, "-m", "tensormass_torch", *args],
        capture_output=True, text=True, env=env, cwd=os.path.dirname(repo), timeout=300,
    )


def test_cli_info_prints_json():
    proc = _run_cli("info")
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert KEYS <= set(info)
    assert info["torch"] == torch.__version__


def test_cli_info_forced_torch():
    proc = _run_cli("info", env_update={"TENSORMASS_BACKEND": "torch"})
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["cpu"] == "torch" and info["forced"] is True


def test_cli_info_bad_value():
    proc = _run_cli("info", env_update={"TENSORMASS_BACKEND": "bogus"})
    assert proc.returncode == 2
    assert "TENSORMASS_BACKEND" in proc.stderr and "Traceback" not in proc.stderr
