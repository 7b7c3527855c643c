"""Whether, and for which GPUs, the build compiles the CUDA kernels: one decision from the facts
of the machine, with its reason in one line.

``setup.py`` loads this file by its path (it must import nothing from the package, which needs
the built extension) and ``scripts/install.sh`` fingerprints the decision, so a rebuild happens
when the decision changes, not when a switch that decides the same is set or forgotten.

The rules, for ``TENSORMASS_BUILD_CUDA`` unset or ``auto``:

* CPU only when CUDA cannot be built: no ``.cu`` sources, a CPU build of torch, no CUDA toolkit,
  a toolkit whose major version differs from torch's CUDA, or no headers for the CUDA math
  libraries that torch's own CUDA headers include (the build would fail). A toolkit that ships
  without them (nvcc and the runtime only) is completed by the headers of torch's NVIDIA wheels
  (``site-packages/nvidia/*/include``);
* CUDA for ``TORCH_CUDA_ARCH_LIST`` when it is set, else for the GPUs torch sees;
* CPU only when no GPU is visible and no architecture list is set: the kernels could run
  nowhere here, and compiling them for every architecture takes tens of minutes on a small
  machine. The reason line says how to build them for a GPU elsewhere.

``TENSORMASS_BUILD_CUDA=1`` makes a CPU-only outcome an error (with the reason), and builds for
``DEFAULT_ARCH_LIST`` when no GPU is visible and no list is set; ``=0`` never builds CUDA.
"""
from __future__ import annotations

import glob
import os
import re
import shutil
import subprocess
from dataclasses import dataclass
from typing import Optional, Tuple

#: Values of ``TENSORMASS_BUILD_CUDA``.
SWITCH_VALUES = ("", "auto", "0", "1")
#: Headers that torch's ATen/cuda/CUDAContextLight.h includes besides the CUDA runtime's.
MATH_HEADERS = ("cusparse.h", "cublas_v2.h", "cublasLt.h", "cusolverDn.h")
#: Architectures of a forced CUDA build with no GPU visible and no ``TORCH_CUDA_ARCH_LIST``:
#: Ampere (A100, RTX 30), Ada (RTX 40, L4), Hopper (H100, H200), with PTX for newer GPUs.
DEFAULT_ARCH_LIST = "8.0;8.6;8.9;9.0+PTX"


@dataclass(frozen=True)
class BuildFacts:
    """What the decision depends on.

    Attributes:
        switch: ``TENSORMASS_BUILD_CUDA`` (one of SWITCH_VALUES).
        torch_version, torch_cuda: ``torch.__version__``, ``torch.version.cuda`` (None: CPU build).
        toolkit: the CUDA toolkit torch found (``CUDA_HOME``), or None.
        toolkit_version: its nvcc's ``"major.minor"``, or None when unknown.
        cu_sources: whether ``csrc/`` has ``.cu`` files.
        gpu_archs: the visible GPUs' compute capabilities, ``("9.0",)``; empty when none.
        arch_list: ``TORCH_CUDA_ARCH_LIST`` when set and not blank, else None.
        include_dirs: folders that complete the toolkit with MATH_HEADERS (torch's NVIDIA wheels).
        missing_headers: MATH_HEADERS found neither in the toolkit nor in those folders.
    """

    switch: str
    torch_version: str
    torch_cuda: Optional[str]
    toolkit: Optional[str]
    toolkit_version: Optional[str]
    cu_sources: bool
    gpu_archs: Tuple[str, ...]
    arch_list: Optional[str]
    include_dirs: Tuple[str, ...] = ()
    missing_headers: Tuple[str, ...] = ()


@dataclass(frozen=True)
class CudaChoice:
    """The decision: ``with_cuda`` for ``arch_list``; ``error`` when a forced build cannot be;
    ``reason``: one line for the build log; ``soft``: CPU only for want of a GPU to build for
    (no GPU visible, no architecture list), which keeps a CUDA build already made here: it was
    asked for once, and nothing asks for another now."""

    with_cuda: bool
    arch_list: Optional[str]
    reason: str
    error: bool = False
    soft: bool = False
    include_dirs: Tuple[str, ...] = ()

    def fingerprint(self) -> str:
        """What a rebuild depends on: CUDA or not, and for which architectures."""
        return f"cuda={self.arch_list}" if self.with_cuda else "cpu"


def _major(version: Optional[str]) -> Optional[str]:
    return None if not version else version.split(".")[0]


def choose(facts: BuildFacts) -> CudaChoice:
    """The CUDA decision for ``facts`` (see the module's rules)."""
    if facts.switch not in SWITCH_VALUES:
        return CudaChoice(False, None, f"TENSORMASS_BUILD_CUDA={facts.switch!r} is not valid; use 0, 1 or auto",
                          error=True)
    if facts.switch == "0":
        return CudaChoice(False, None, "CUDA kernels not built: TENSORMASS_BUILD_CUDA=0")
    forced = facts.switch == "1"
    blocker = None
    if not facts.cu_sources:
        blocker = "there are no csrc/**/*.cu sources"
    elif not facts.torch_cuda:
        blocker = (f"torch {facts.torch_version} is a CPU build (install a CUDA build of torch to get the CUDA "
                   "kernels)")
    elif not facts.toolkit:
        blocker = f"no CUDA toolkit was found (set CUDA_HOME to a CUDA {facts.torch_cuda} toolkit with bin/nvcc)"
    elif facts.toolkit_version and _major(facts.toolkit_version) != _major(facts.torch_cuda):
        blocker = (f"the CUDA toolkit at {facts.toolkit} is {facts.toolkit_version} but torch was built with CUDA "
                   f"{facts.torch_cuda} (the major versions must match: set CUDA_HOME to a CUDA "
                   f"{_major(facts.torch_cuda)}.x toolkit)")
    elif facts.missing_headers:
        blocker = (f"the CUDA toolkit at {facts.toolkit} has no {', '.join(facts.missing_headers)}, which torch's "
                   "CUDA headers include (install the toolkit's math library headers, or a full CUDA toolkit)")
    if blocker:
        if forced:
            return CudaChoice(False, None, f"TENSORMASS_BUILD_CUDA=1 but {blocker}", error=True)
        return CudaChoice(False, None, f"CUDA kernels not built: {blocker}")
    extra = tuple(facts.include_dirs)
    if facts.arch_list:
        return CudaChoice(True, facts.arch_list, f"CUDA kernels for TORCH_CUDA_ARCH_LIST={facts.arch_list}",
                          include_dirs=extra)
    if facts.gpu_archs:
        archs = ";".join(sorted(set(facts.gpu_archs), key=lambda a: tuple(int(p) for p in a.split("."))))
        return CudaChoice(True, archs, f"CUDA kernels for the visible GPUs ({archs})", include_dirs=extra)
    if forced:
        return CudaChoice(True, DEFAULT_ARCH_LIST, f"CUDA kernels for {DEFAULT_ARCH_LIST}: TENSORMASS_BUILD_CUDA=1, "
                                                   "no GPU visible and TORCH_CUDA_ARCH_LIST unset", include_dirs=extra)
    return CudaChoice(False, None, "CUDA kernels not built: no GPU is visible and TORCH_CUDA_ARCH_LIST is unset "
                                   "(to build them for a GPU elsewhere, set TORCH_CUDA_ARCH_LIST, e.g. 9.0 for "
                                   "an H100, and reinstall)", soft=True)


def nvcc_version(toolkit: Optional[str]) -> Optional[str]:
    """``"major.minor"`` of ``toolkit``'s nvcc, or None when it cannot be run."""
    if not toolkit:
        return None
    try:
        out = subprocess.run([os.path.join(toolkit, "bin", "nvcc"), "--version"], capture_output=True, text=True,
                             timeout=60).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    match = re.search(r"release (\d+\.\d+)", out)
    return match.group(1) if match else None


def _is_toolkit(folder: Optional[str]) -> bool:
    return bool(folder) and os.path.isfile(os.path.join(folder, "bin", "nvcc")) and \
        os.path.isfile(os.path.join(folder, "include", "cuda_runtime.h"))


def find_toolkit() -> Optional[str]:
    """The CUDA toolkit to build with (a folder with bin/nvcc and include/cuda_runtime.h), found
    without importing torch: ``CUDA_HOME`` or ``CUDA_PATH`` as set (even if not a toolkit: the
    build then says so); else the toolkit of the nvcc on PATH (a wrapper script in /usr/local/bin
    is not one); else /usr/local/cuda. None when there is none."""
    for name in ("CUDA_HOME", "CUDA_PATH"):
        if os.environ.get(name):
            return os.environ[name]
    nvcc = shutil.which("nvcc")
    candidates = [os.path.dirname(os.path.dirname(os.path.realpath(nvcc)))] if nvcc else []
    candidates.append("/usr/local/cuda")
    return next((c for c in candidates if _is_toolkit(c)), None)


def math_header_dirs(toolkit: Optional[str], site_packages: str) -> Tuple[Tuple[str, ...], Tuple[str, ...]]:
    """(folders to add to the include path, MATH_HEADERS found nowhere): the toolkit's own
    include folder first, then those of torch's NVIDIA wheels under ``site_packages/nvidia``."""
    missing = [h for h in MATH_HEADERS if not (toolkit and os.path.isfile(os.path.join(toolkit, "include", h)))]
    extra = []
    wheels = sorted(glob.glob(os.path.join(site_packages, "nvidia", "*", "include")))
    for header in list(missing):
        found = next((d for d in wheels if os.path.isfile(os.path.join(d, header))), None)
        if found:
            missing.remove(header)
            if found not in extra:
                extra.append(found)
    return tuple(extra), tuple(missing)


def machine_facts(cu_sources: bool) -> BuildFacts:
    """The facts of this machine (imports torch)."""
    import torch
    from torch.utils import cpp_extension

    toolkit = cpp_extension.CUDA_HOME if torch.version.cuda else None
    gpu_archs = ()
    if torch.version.cuda and torch.cuda.is_available():
        gpu_archs = tuple("%d.%d" % torch.cuda.get_device_capability(i) for i in range(torch.cuda.device_count()))
    arch_list = os.environ.get("TORCH_CUDA_ARCH_LIST", "").strip() or None
    site_packages = os.path.dirname(os.path.dirname(os.path.abspath(torch.__file__)))
    include_dirs, missing = math_header_dirs(toolkit, site_packages) if toolkit else ((), ())
    return BuildFacts(os.environ.get("TENSORMASS_BUILD_CUDA", "").strip().lower(), torch.__version__,
                      torch.version.cuda, toolkit, nvcc_version(toolkit), cu_sources, gpu_archs, arch_list,
                      include_dirs, missing)


def has_cu_sources(root: str) -> bool:
    """Whether ``root/csrc`` holds ``.cu`` files."""
    for _, _, files in os.walk(os.path.join(root, "csrc")):
        if any(f.endswith(".cu") for f in files):
            return True
    return False


if __name__ == "__main__":  # scripts/install.sh: the decision's fingerprint, reason, soft/firm: a line each
    import sys

    toolkit = find_toolkit()
    if toolkit and not os.environ.get("CUDA_HOME"):  # as setup.py does, before torch reads it
        os.environ["CUDA_HOME"] = toolkit
    choice = choose(machine_facts(has_cu_sources(sys.argv[1] if len(sys.argv) > 1 else ".")))
    print(choice.fingerprint())
    print(choice.reason)
    print("soft" if choice.soft else "firm")
