#!/usr/bin/env bash
# Idempotent set-up of tensormass_torch in the python you use (PYTHON, default python3):
#   1. torch: kept as it is when importable (never reinstalled, upgraded or downgraded, so a
#      CUDA build stays); otherwise `pip install ${TORCH_SPEC:-torch}` (CI: TORCH_SPEC=torch==2.13.0);
#   2. build tools for --no-build-isolation (setuptools>=64, wheel), only if missing;
#   3. `pip install --no-build-isolation -e .` (compiles tensormass_torch._C against that torch
#      when csrc/ has sources), skipped when nothing it depends on changed since the last run;
#   4. test dependencies (pytest, meshio, numpy, tqdm, hypothesis for the fuzz tests, tetgen for
#      tm.tetrahedralize, pyamg and cholespy for the multigrid and Cholesky preconditioners,
#      pyvista for the off-screen rendering tests, viser and playwright for the viewer and its
#      browser test, which drives the system's Chromium, pymetis for partitioning one mesh over
#      several processes), only if missing. pyvista's vtk wheel
#      renders headless through EGL (Mesa's libEGL and llvmpipe on a machine without a GPU;
#      see tensormass_torch/app/render.py).
# Quiet when all goes well; on a failure prints pip's output and exits non-zero.
# Switches: PYTHON, TORCH_SPEC, TENSORMASS_BUILD_EXT, TENSORMASS_BUILD_CUDA, TENSORMASS_REINSTALL=1
# (force step 3).
set -euo pipefail

# Resolve a relative PYTHON path before leaving the caller's directory.
PYTHON="${PYTHON:-python3}"
if [[ "$PYTHON" == */* && "$PYTHON" != /* ]]; then PYTHON="$PWD/$PYTHON"; fi
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

say() { echo "[install] $*" >&2; }
die() { echo "[install] ERROR: $*" >&2; exit 1; }

command -v "$PYTHON" >/dev/null 2>&1 || die "python not found: PYTHON=$PYTHON"
"$PYTHON" -m pip --version >/dev/null 2>&1 || die "pip is not available for $PYTHON (try: $PYTHON -m ensurepip)"

LOG="$(mktemp "${TMPDIR:-/tmp}/tensormass-install.XXXXXX")"
trap 'rm -f "$LOG"' EXIT

# pip quietly; on failure show its output and stop with one line saying what failed.
# ON_PIP_FAILURE: a command run before stopping (install step 3 puts the previous build back).
ON_PIP_FAILURE=""
pip_q() {
    if ! "$PYTHON" -m pip install -q "$@" >"$LOG" 2>&1; then
        cat "$LOG" >&2
        [[ -z "$ON_PIP_FAILURE" ]] || eval "$ON_PIP_FAILURE"
        if grep -q "externally-managed-environment" "$LOG"; then
            die "pip refuses to install into this python ($PYTHON is externally managed): use a virtual environment, python3 -m venv .venv && PYTHON=.venv/bin/python bash scripts/$(basename "${0}")"
        fi
        local why
        why="$(grep -E "^[[:space:]]*(error: |tensormass_torch: )" "$LOG" | tail -n 1 | sed 's/^[[:space:]]*//' || true)"
        die "pip install $* failed (python: $PYTHON)${why:+: $why}"
    fi
}

# Import checks run outside the repo so that the source tree is not what gets imported.
py_out() { (cd / && "$PYTHON" -c "$1") ; }

# 1. torch
torch_version() { py_out 'import torch; print(torch.__version__, torch.version.cuda)' 2>/dev/null; }
if TORCH_VERSION="$(torch_version)"; then
    say "torch ${TORCH_VERSION% *} found: kept as it is"
else
    # TORCH_SPEC is split on spaces, so it may carry pip options:
    #   TORCH_SPEC="torch --index-url https://download.pytorch.org/whl/cu128"
    spec="${TORCH_SPEC:-torch}"
    read -r -a spec_args <<<"$spec"
    say "torch not importable: pip install $spec (set TORCH_SPEC to choose another build)"
    pip_q "${spec_args[@]}"
    if ! TORCH_VERSION="$(torch_version)"; then
        py_out 'import torch' || true
        die "torch still not importable after 'pip install $spec' (see above)"
    fi
    say "installed torch ${TORCH_VERSION% *}"
fi

# 2. build tools (with --no-build-isolation pip does not provide them)
if ! py_out '
import sys, setuptools
v = tuple(int(p) for p in setuptools.__version__.split(".")[:2] if p.isdigit())
if v < (64,): sys.exit(1)
if v < (70, 1):  # bdist_wheel moved into setuptools in 70.1
    import wheel
' >/dev/null 2>&1; then
    say "installing build tools (setuptools>=64, wheel)"
    pip_q "setuptools>=64" wheel
fi

# 3. the package itself, editable, compiled against the torch above.
# Whether the build compiles CUDA kernels, and for which GPUs (tensormass_torch/_build.py
# decides from the machine: torch's CUDA, the toolkit, visible GPUs, TORCH_CUDA_ARCH_LIST).
if ! cuda_choice="$("$PYTHON" "$ROOT/tensormass_torch/_build.py" "$ROOT" 2>"$LOG")"; then
    cat "$LOG" >&2
    die "could not decide how to build the CUDA kernels (see above)"
fi
CUDA_FINGERPRINT="$(sed -n 1p <<<"$cuda_choice")"
# Fingerprint of everything else the build depends on. The install is skipped when it and the
# CUDA decision are unchanged, pip has the package installed from this tree and (when csrc/ has
# sources) the built extension file is there. The decision counts, not the switches behind it:
# forgetting a switch that decides the same rebuilds nothing, and a CUDA build made for a
# TORCH_CUDA_ARCH_LIST is kept when the list is later unset on a machine with no GPU ("soft").
STAMP="$ROOT/build/tensormass-install.stamp"
fingerprint="$(TORCH_VERSION="$TORCH_VERSION" "$PYTHON" - <<'EOF'
import glob, hashlib, os, sys
h = hashlib.sha256()
for item in (sys.executable, os.environ["TORCH_VERSION"], os.environ.get("TENSORMASS_BUILD_EXT", "")):
    h.update(item.encode() + b"\0")
files = ["setup.py", "pyproject.toml"] + sorted(
    p for p in glob.glob("csrc/**/*", recursive=True) if os.path.isfile(p))
for path in files:
    h.update(path.encode() + b"\0")
    if os.path.exists(path):
        with open(path, "rb") as fh:
            h.update(hashlib.sha256(fh.read()).digest())
print(h.hexdigest())
EOF
)"
want_ext=0
if [[ "${TENSORMASS_BUILD_EXT:-}" != "0" ]] \
   && [[ -n "$(find csrc \( -name '*.cpp' -o -name '*.cu' \) -print -quit 2>/dev/null)" ]]; then
    want_ext=1
fi
# Installed, editable, from this tree? (find_spec does not run the package's __init__.)
installed_here() {
    py_out "
import importlib.metadata as md, importlib.util as iu, os, sys
md.distribution('tensormass_torch')
spec = iu.find_spec('tensormass_torch')
here = os.path.realpath(os.path.dirname(spec.origin)) if spec and spec.origin else ''
sys.exit(0 if here == os.path.realpath('$ROOT/tensormass_torch') else 1)
" >/dev/null 2>&1 || return 1
    if [[ "$want_ext" == 1 ]] && ! compgen -G "$ROOT/tensormass_torch/_C*.so" >/dev/null \
       && ! compgen -G "$ROOT/tensormass_torch/_C*.pyd" >/dev/null; then
        return 1
    fi
    return 0
}
up_to_date=0
if [[ "${TENSORMASS_REINSTALL:-0}" != "1" && -f "$STAMP" && "$(sed -n 1p "$STAMP")" == "$fingerprint" ]] \
   && installed_here; then
    built_cuda="$(sed -n 2p "$STAMP")"
    if [[ "$built_cuda" == "$CUDA_FINGERPRINT" ]]; then
        up_to_date=1
        say "tensormass_torch already installed from $ROOT and up to date"
    elif [[ "$(sed -n 3p <<<"$cuda_choice")" == "soft" && "$built_cuda" == cuda=* ]]; then
        up_to_date=1
        say "tensormass_torch already installed from $ROOT; keeping its CUDA kernels for ${built_cuda#cuda=} (no GPU is visible and TORCH_CUDA_ARCH_LIST is unset: nothing asks for another build)"
    fi
fi
if [[ "$up_to_date" == 0 ]]; then
    say "pip install --no-build-isolation -e . (this compiles tensormass_torch._C when csrc/ has sources)"
    [[ "$want_ext" == 0 ]] || say "$(sed -n 2p <<<"$cuda_choice")"
    rm -f "$STAMP"
    # The previous build is set aside, not deleted: a stale in-tree build would be imported even
    # when no extension is built now, but a failed build must leave the working one in place.
    KEPT="$ROOT/build/previous-extension"
    rm -rf "$KEPT" && mkdir -p "$KEPT"
    for f in "$ROOT"/tensormass_torch/_C*.so "$ROOT"/tensormass_torch/_C*.pyd; do
        if [[ -e "$f" ]]; then mv "$f" "$KEPT/"; fi
    done
    ON_PIP_FAILURE='if compgen -G "$KEPT/*" >/dev/null; then mv "$KEPT"/* "$ROOT/tensormass_torch/"; say "the previous build of tensormass_torch._C was kept"; fi'
    pip_q --no-build-isolation -e "$ROOT"
    ON_PIP_FAILURE=""
    rm -rf "$KEPT"
    installed_here || die "tensormass_torch is not installed from $ROOT after the install"
    mkdir -p "$(dirname "$STAMP")"
    printf '%s\n%s\n' "$fingerprint" "$CUDA_FINGERPRINT" >"$STAMP"
fi

# 4. test dependencies
read -r -a missing <<<"$(py_out '
import importlib
for name in ("pytest", "meshio", "numpy", "pyvista", "tqdm", "hypothesis", "tetgen", "pyamg", "cholespy", "viser",
             "playwright", "pymetis"):
    try:
        importlib.import_module(name)
    except Exception:
        print(name, end=" ")
')"
if ((${#missing[@]})); then
    say "installing missing test dependencies: ${missing[*]}"
    pip_q "${missing[@]}"
fi

if ! info="$(py_out 'import json, tensormass_torch as tm; print(json.dumps(tm.backend_info()))' 2>"$LOG")"; then
    cat "$LOG" >&2
    die "installed, but 'import tensormass_torch; tm.backend_info()' fails (see above)"
fi
say "ok: $info"
