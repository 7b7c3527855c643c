"""The build's CUDA decision (tensormass_torch/_build.py, used by setup.py and scripts/install.sh)
over every combination a new user can bring: a CUDA or CPU build of torch, a CUDA toolkit or
none (or one of another major version), a GPU visible or not, TORCH_CUDA_ARCH_LIST set or not,
and the TENSORMASS_BUILD_CUDA switch unset, forced on or off."""
import itertools
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tensormass_torch import _build
from tensormass_torch._build import DEFAULT_ARCH_LIST, BuildFacts, choose

ROOT = Path(__file__).resolve().parents[2]


def facts(switch="", torch_cuda="13.0", toolkit="/usr/local/cuda", toolkit_version="13.0", cu_sources=True,
          gpu_archs=(), arch_list=None):
    return BuildFacts(switch, "2.15.0+cu130" if torch_cuda else "2.15.0+cpu", torch_cuda, toolkit, toolkit_version,
                      cu_sources, tuple(gpu_archs), arch_list)


MATRIX = list(itertools.product(["13.0", None], ["/usr/local/cuda", None], [(), ("9.0",)], [None, "8.0;9.0"],
                                ["", "auto", "1", "0"]))


@pytest.mark.parametrize("torch_cuda,toolkit,gpus,arch_list,switch", MATRIX)
def test_the_decision_over_every_combination(torch_cuda, toolkit, gpus, arch_list, switch):
    choice = choose(facts(switch, torch_cuda, toolkit, "13.0" if toolkit else None, True, gpus, arch_list))
    assert choice.reason and "\n" not in choice.reason
    if switch == "0":
        assert not choice.with_cuda and not choice.error and "TENSORMASS_BUILD_CUDA=0" in choice.reason
        return
    possible = torch_cuda is not None and toolkit is not None
    if not possible:  # a CPU torch or no toolkit: CPU only, or an error when forced on
        assert not choice.with_cuda and choice.error == (switch == "1")
        assert ("CPU build" in choice.reason) if torch_cuda is None else ("CUDA_HOME" in choice.reason)
        return
    assert not choice.error
    if arch_list:  # the user's list wins
        assert choice.with_cuda and choice.arch_list == arch_list
    elif gpus:  # the GPUs this machine has
        assert choice.with_cuda and choice.arch_list == "9.0"
    elif switch == "1":  # forced with nothing to build for: the documented default list
        assert choice.with_cuda and choice.arch_list == DEFAULT_ARCH_LIST
    else:  # nothing to run the kernels on and no list: CPU only, and the line says how to get CUDA
        assert not choice.with_cuda and "TORCH_CUDA_ARCH_LIST" in choice.reason
        assert choice.soft  # a CUDA build made earlier for a list is kept
        return
    assert not choice.soft


def test_a_toolkit_of_another_major_version_is_not_used():
    mismatch = dict(torch_cuda="13.2", toolkit_version="12.8", gpu_archs=("9.0",))
    choice = choose(facts(**mismatch))
    assert not choice.with_cuda and not choice.error and "12.8" in choice.reason and "13.2" in choice.reason
    assert choose(facts(switch="1", **mismatch)).error
    # a minor difference is fine (torch warns, the build works)
    assert choose(facts(torch_cuda="13.2", toolkit_version="13.0", gpu_archs=("9.0",))).with_cuda


def test_missing_math_headers_stop_the_cuda_build():
    choice = choose(BuildFacts("", "2.15.0+cu132", "13.2", "/usr/local/cuda", "13.0", True, ("9.0",), None, (),
                               ("cusparse.h",)))
    assert not choice.with_cuda and "cusparse.h" in choice.reason
    complete = choose(BuildFacts("", "2.15.0+cu132", "13.2", "/usr/local/cuda", "13.0", True, ("9.0",), None,
                                 ("/site/nvidia/cu13/include",), ()))
    assert complete.with_cuda and complete.include_dirs == ("/site/nvidia/cu13/include",)


def test_math_headers_come_from_the_toolkit_or_the_nvidia_wheels(tmp_path):
    toolkit, site = tmp_path / "cuda", tmp_path / "site"
    (toolkit / "include").mkdir(parents=True)
    (site / "nvidia" / "cu13" / "include").mkdir(parents=True)
    for header in _build.MATH_HEADERS[:2]:
        (toolkit / "include" / header).write_text("")
    (site / "nvidia" / "cu13" / "include" / "cublasLt.h").write_text("")
    extra, missing = _build.math_header_dirs(str(toolkit), str(site))
    assert extra == (str(site / "nvidia" / "cu13" / "include"),) and missing == ("cusolverDn.h",)


def test_an_nvcc_wrapper_on_path_is_not_the_toolkit(tmp_path, monkeypatch):
    wrapper_bin, toolkit = tmp_path / "local" / "bin", tmp_path / "cuda-13.0"
    wrapper_bin.mkdir(parents=True)
    (wrapper_bin / "nvcc").write_text(f"#!/bin/sh\nexec {toolkit}/bin/nvcc \"$@\"\n")
    (wrapper_bin / "nvcc").chmod(0o755)
    monkeypatch.delenv("CUDA_HOME", raising=False)
    monkeypatch.delenv("CUDA_PATH", raising=False)
    monkeypatch.setenv("PATH", str(wrapper_bin))
    found = _build.find_toolkit()
    assert found != str(tmp_path / "local")  # the wrapper's folder has no headers
    assert found is None or _build._is_toolkit(found)
    monkeypatch.setenv("CUDA_HOME", "/somewhere")  # as the user says, even if wrong (the build then says so)
    assert _build.find_toolkit() == "/somewhere"


def test_several_gpus_build_for_each_architecture_once():
    choice = choose(facts(gpu_archs=("9.0", "8.6", "9.0")))
    assert choice.arch_list == "8.6;9.0"


def test_the_fingerprint_changes_with_the_decision_only():
    cpu = choose(facts(gpu_archs=()))
    assert cpu.fingerprint() == choose(facts(switch="0")).fingerprint() == "cpu"  # same outcome, same build
    assert choose(facts(gpu_archs=("9.0",))).fingerprint() == "cuda=9.0"
    assert choose(facts(arch_list="8.0")).fingerprint() == "cuda=8.0"


def test_an_invalid_switch_is_an_error():
    assert choose(facts(switch="yes")).error


def test_the_script_prints_the_decision_for_install_sh():
    out = subprocess.run([sys.executable, str(ROOT / "tensormass_torch" / "_build.py"), str(ROOT)],
                         capture_output=True, text=True, timeout=120, env={**os.environ, "TENSORMASS_BUILD_CUDA": "0"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == ["cpu", "CUDA kernels not built: TENSORMASS_BUILD_CUDA=0", "firm"]


def test_setup_py_stops_with_the_reason_when_forced_on_and_impossible():
    import torch

    if torch.version.cuda:
        pytest.skip("this torch is a CUDA build")
    out = subprocess.run([sys.executable, "setup.py", "--name"], cwd=ROOT, capture_output=True, text=True,
                         timeout=120, env={**os.environ, "TENSORMASS_BUILD_CUDA": "1"})
    assert out.returncode != 0
    assert out.stderr.strip().splitlines()[-1].startswith("error: TENSORMASS_BUILD_CUDA=1 but torch")


def test_cu_sources_are_found():
    assert _build.has_cu_sources(str(ROOT))
