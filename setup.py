"""Build script of tensormass_torch.

The package is pure Python plus one optional compiled extension, ``tensormass_torch._C``:

* C++ sources ``csrc/**/*.cpp`` are always compiled (CPU kernels, OpenMP, -O3);
* CUDA sources ``csrc/**/*.cu`` are added (one CUDAExtension) as ``tensormass_torch/_build.py``
  decides: when torch is a CUDA build, a matching CUDA toolkit is found (``CUDA_HOME``) and
  there is a GPU to build for (a visible one, or ``TORCH_CUDA_ARCH_LIST``); the macro
  ``TENSORMASS_WITH_CUDA`` is then defined for every translation unit;
* with no sources under ``csrc/`` the package is pure Python and nothing is compiled.

The extension is compiled against the torch that is importable here, so install with
``pip install --no-build-isolation -e .`` (or ``bash scripts/install.sh``): under pip's build
isolation a different torch would be used and the module would fail to import ("undefined
symbol"). That is why torch is in neither ``install_requires`` nor ``[build-system] requires``.

Environment switches:

* ``TENSORMASS_BUILD_EXT=0``       build no extension at all (pure Python, torch fallback);
* ``TENSORMASS_BUILD_CUDA=0|1``    force the CUDA part off / on (on without a CUDA build of
                                   torch and a toolkit is an error; on without a GPU or an
                                   architecture list builds for _build.DEFAULT_ARCH_LIST);
                                   unset = automatic;
* ``MAX_JOBS``, ``TORCH_CUDA_ARCH_LIST``, ``CUDA_HOME``: read by ``torch.utils.cpp_extension``.
"""
import functools
import glob
import os
import re
import sys

from setuptools import find_packages, setup

ROOT = os.path.dirname(os.path.abspath(__file__))
PACKAGE = "tensormass_torch"
EXT_NAME = PACKAGE + "._C"


def _version():
    """``__version__`` of tensormass_torch/__init__.py, without importing the package."""
    try:
        with open(os.path.join(ROOT, PACKAGE, "__init__.py"), encoding="utf-8") as fh:
            match = re.search(r"^__version__\s*=\s*['\"]([^'\"]+)['\"]", fh.read(), re.M)
    except OSError:
        match = None
    return match.group(1) if match else "0.1.0"


def _switch(name, allowed):
    """Value of an environment switch, lower-cased; '' when unset. Unknown values are errors."""
    value = os.environ.get(name, "").strip().lower()
    if value not in allowed:
        sys.exit(
            "error: %s=%r is not valid; use one of: %s"
            % (name, os.environ[name], ", ".join(repr(a) for a in allowed if a))
        )
    return value


@functools.lru_cache(maxsize=None)
def _build_rules():
    """tensormass_torch/_build.py, loaded by its path: importing the package would need the
    extension this script builds."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("tensormass_build", os.path.join(ROOT, PACKAGE, "_build.py"))
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


def _sources(pattern):
    """Sorted source paths relative to ROOT (setuptools wants relative paths)."""
    return sorted(
        os.path.relpath(p, ROOT)
        for p in glob.glob(os.path.join(ROOT, "csrc", "**", pattern), recursive=True)
    )


def _extension():
    """(ext_modules, cmdclass) for the build: ([], {}) for a pure-Python package."""
    build_ext = _switch("TENSORMASS_BUILD_EXT", ("", "0", "1", "auto"))
    _switch("TENSORMASS_BUILD_CUDA", ("", "0", "1", "auto"))
    if build_ext == "0":
        print("tensormass_torch: TENSORMASS_BUILD_EXT=0, building no extension")
        return [], {}

    cpp_sources = _sources("*.cpp")
    cu_sources = _sources("*.cu")
    if not cpp_sources and not cu_sources:
        print("tensormass_torch: no sources under csrc/, building a pure-Python package")
        return [], {}

    # The toolkit torch's builder uses is read from CUDA_HOME when it is imported: set it first, so
    # that an nvcc wrapper on PATH (whose folder has no headers) does not stand for the toolkit.
    toolkit = _build_rules().find_toolkit()
    if toolkit and not os.environ.get("CUDA_HOME"):
        os.environ["CUDA_HOME"] = toolkit
    try:
        import torch
        from torch.utils import cpp_extension
    except ImportError as exc:
        sys.exit(
            "error: building tensormass_torch._C needs torch importable in the build environment "
            "(%s).\n  Install torch first, then install this package with "
            "'pip install --no-build-isolation -e .' (or run 'bash scripts/install.sh');\n"
            "  or set TENSORMASS_BUILD_EXT=0 for a pure-Python install (torch fallback)." % exc
        )

    # CUDA: decided by tensormass_torch/_build.py from the machine's facts (see its rules).
    choice = _build_rules().choose(_build_rules().machine_facts(bool(cu_sources)))
    if choice.error:
        sys.exit("error: " + choice.reason)
    with_cuda = choice.with_cuda
    if with_cuda:
        # torch's extension builder reads the list from the environment; set it so that a
        # machine without a GPU never reaches its own guess (which fails with no GPU to ask)
        os.environ["TORCH_CUDA_ARCH_LIST"] = choice.arch_list
    cuda_home = cpp_extension.CUDA_HOME
    print("tensormass_torch: " + choice.reason)

    if sys.platform == "win32":
        cxx_flags, link_flags = ["/O2", "/openmp"], []
    elif sys.platform == "darwin":  # Apple clang has no -fopenmp; the kernels run serially
        cxx_flags, link_flags = ["-O3"], []
    else:
        # -g0: Python's default flags add -g, which doubles the compile time of the kernels.
        cxx_flags, link_flags = ["-O3", "-g0", "-fopenmp"], ["-fopenmp"]
    # No -std flag: BuildExtension adds the standard the installed torch's headers need
    # (C++17 for older torch, C++20 for torch >= 2.10); csrc/ is written as C++17.
    macros = [("TENSORMASS_WITH_CUDA", "1")] if with_cuda else []
    include_dirs = [os.path.join(ROOT, "csrc")]

    if with_cuda:
        # Headers that complete the toolkit (torch's NVIDIA wheels) are searched after its own
        # (-isystem comes after every -I): the wheels' runtime headers may be of a newer CUDA
        # than nvcc, which refuses them.
        for folder in choice.include_dirs:
            cxx_flags = cxx_flags + ["-isystem", folder]
        nvcc_flags = ["-O3", "--expt-relaxed-constexpr"] + [f for d in choice.include_dirs for f in ("-isystem", d)]
        if sys.platform != "win32":
            nvcc_flags += ["-Xcompiler", "-fopenmp"]
        ext = cpp_extension.CUDAExtension(
            EXT_NAME,
            cpp_sources + cu_sources,
            include_dirs=include_dirs,
            define_macros=macros,
            extra_compile_args={"cxx": cxx_flags, "nvcc": nvcc_flags},
            extra_link_args=link_flags,
        )
        kind = "C++ + CUDA %s (CUDA_HOME=%s)" % (torch.version.cuda, cuda_home)
    else:
        if not cpp_sources:
            print("tensormass_torch: no C++ sources to build, building a pure-Python package")
            return [], {}
        ext = cpp_extension.CppExtension(
            EXT_NAME,
            cpp_sources,
            include_dirs=include_dirs,
            define_macros=macros,
            extra_compile_args={"cxx": cxx_flags},
            extra_link_args=link_flags,
        )
        kind = "C++ (CPU only)"
    print("tensormass_torch: building %s: %s against torch %s" % (EXT_NAME, kind, torch.__version__))

    base = cpp_extension.BuildExtension.with_options(use_ninja=cpp_extension.is_ninja_available())

    class BuildExtension(base):
        """BuildExtension that says how to get a pure-Python install when compilation fails."""

        def run(self):
            try:
                super().run()
            except Exception:
                cuda_hint = "; to skip only the CUDA part set TENSORMASS_BUILD_CUDA=0" if with_cuda else ""
                sys.stderr.write(
                    "\ntensormass_torch: compiling %s failed (see above); to install without the "
                    "extension (pure-torch fallback) set TENSORMASS_BUILD_EXT=0%s\n" % (EXT_NAME, cuda_hint)
                )
                raise

    return [ext], {"build_ext": BuildExtension}


ext_modules, cmdclass = _extension()

setup(
    name="tensormass_torch",
    version=_version(),
    description="GPU soft-body simulation with the Tensor-Mass model and an implicit solver, "
    "as a PyTorch extension",
    long_description=open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    if os.path.exists(os.path.join(ROOT, "README.md"))
    else "",
    long_description_content_type="text/markdown",
    packages=find_packages(include=[PACKAGE, PACKAGE + ".*"]),
    python_requires=">=3.9",
    # torch is deliberately absent: the user's torch (CPU or CUDA build) must be kept as it is.
    install_requires=["numpy", "meshio", "tqdm"],
    extras_require={"test": ["pytest", "hypothesis"], "render": ["pyvista"], "mesh": ["tetgen", "pytetwild"],
                    "multigrid": ["pyamg"], "direct": ["cholespy"], "viewer": ["viser"],
                    "distributed": ["pymetis"]},
    ext_modules=ext_modules,
    cmdclass=cmdclass,
    entry_points={"console_scripts": ["tensormass = tensormass_torch.app.cli:main"]},
    zip_safe=False,
)
