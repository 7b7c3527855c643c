#!/usr/bin/env bash
# GPU check, in ONE command on the GPU machine (no network needed):
#   1. build tensormass_torch._C with its CUDA kernels against the torch in use
#      (pip install --no-build-isolation --no-deps -e .; python setup.py build_ext --inplace
#      if pip cannot);
#   2. run the test suite, GPU tests included (tests/test_gpu.py; junit xml kept);
#   3. run the ops benchmark on the paper's 307,200-tet beam (benchmarks/suite/ops_bench.py);
#   4. write $OUT/gpu_check.md (environment, build, tests, benchmark) and print the table last.
# The output of each step is also kept in $OUT/<step>.log. A failing step is reported and the
# next steps still run; the exit status is non-zero if any step failed.
#
#   OUT=/some/dir bash scripts/gpu_check.sh            # OUT defaults to ./out/gpu_check
#   TENSORMASS_COMMIT=$(git rev-parse --short HEAD) ... # names the commit when the copy has no .git
# Switches: PYTHON (python3), TORCH_CUDA_ARCH_LIST (9.0), MAX_JOBS (16), CUDA_HOME (/usr/local/cuda),
#           GPU_CHECK_PYTEST_ARGS (extra pytest arguments), GPU_CHECK_BENCH_ARGS (extra benchmark
#           arguments), GPU_CHECK_SKIP_BUILD=1 (use the extension already built),
#           GPU_CHECK_DEVICE=cpu (a dry run of the script without a GPU: benchmark on the CPU),
#           GPU_CHECK_BUDGET (seconds for the whole run, default 560: each step gets a time
#           limit within it, so that the report is written even when a step hangs).
set -uo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
source "$ROOT/scripts/lib.sh"   # run_limited
PYTHON="${PYTHON:-python3}"
OUT="${OUT:-$ROOT/out/gpu_check}"
mkdir -p "$OUT"
export CUDA_HOME="${CUDA_HOME:-/usr/local/cuda}"
export PATH="$CUDA_HOME/bin:$PATH"
export TORCH_CUDA_ARCH_LIST="${TORCH_CUDA_ARCH_LIST:-9.0}"
export MAX_JOBS="${MAX_JOBS:-16}"
export TENSORMASS_BUILD_CUDA=1
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"   # the tree, whichever way it was built
unset TENSORMASS_BACKEND
export PYTHONDONTWRITEBYTECODE=1
export PYTHON ROOT OUT
DEVICE="${GPU_CHECK_DEVICE:-cuda}"   # cpu: a dry run of this script on a machine without a GPU

FAILED=()
STATUS_LINES=()
DEADLINE=$((SECONDS + ${GPU_CHECK_BUDGET:-560}))
# step NAME RESERVE COMMAND...: run with a time limit that leaves RESERVE seconds of the budget
# to the later steps (output shown and kept in $OUT/NAME.log), time it, record the result.
step() {
    local name="$1" reserve="$2"; shift 2
    local limit=$((DEADLINE - SECONDS - reserve))
    if ((limit < 10)); then limit=10; fi
    run_limited gpu_check "$name" "$limit" "" "$@"
}

# ---------------------------------------------------------------- 0. environment
env_info() {
    "$PYTHON" - <<'EOF'
import platform, subprocess, sys
import torch
print("python", sys.version.split()[0], platform.platform())
print("torch", torch.__version__, "cuda", torch.version.cuda, "available", torch.cuda.is_available())
if torch.cuda.is_available():
    p = torch.cuda.get_device_properties(0)
    print("device", p.name, "sm_%d%d" % (p.major, p.minor), "%.1f GiB" % (p.total_memory / 2**30))
EOF
    command -v nvcc >/dev/null && nvcc --version | tail -2
    command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv
    git -C "$ROOT" log -1 --format='commit %h %s' 2>/dev/null || true
    return 0
}
export -f env_info 2>/dev/null || true
step environment 500 bash -c env_info

# ---------------------------------------------------------------- 1. build
build() {
    rm -f "$ROOT"/tensormass_torch/_C*.so
    if "$PYTHON" -m pip install --no-build-isolation --no-deps -e "$ROOT"; then
        :
    else
        echo "[gpu_check] pip install failed; trying python setup.py build_ext --inplace"
        "$PYTHON" setup.py build_ext --inplace || return 1
    fi
    "$PYTHON" - <<'EOF'
import json, sys
import tensormass_torch as tm
from tensormass_torch import _C
info = tm.backend_info()
print(json.dumps(info, indent=1))
if not _C.has_cuda() or info["cuda"] != "extension":
    sys.exit("the extension was built without CUDA, or CUDA tensors do not use it")
EOF
}
if [[ "${GPU_CHECK_SKIP_BUILD:-0}" == "1" ]]; then
    STATUS_LINES+=("| build | skipped | |")
else
    export -f build
    step build 330 bash -c build
fi

# ---------------------------------------------------------------- 2. tests
# shellcheck disable=SC2086
step tests 150 "$PYTHON" -m pytest -q -rs -p no:cacheprovider --junitxml="$OUT/pytest.xml" \
    --durations=15 tests ${GPU_CHECK_PYTEST_ARGS:-}

# ---------------------------------------------------------------- 3. benchmark
# shellcheck disable=SC2086
step benchmark 5 "$PYTHON" benchmarks/suite/ops_bench.py --device "$DEVICE" --out "$OUT" ${GPU_CHECK_BENCH_ARGS:-}

# ---------------------------------------------------------------- 4. report
{
    echo "# gpu_check report"
    echo
    echo '```'
    cat "$OUT/environment.log" 2>/dev/null
    echo '```'
    echo
    echo "| step | result | time |"
    echo "|---|---|---|"
    printf '%s\n' "${STATUS_LINES[@]}"
    echo
    echo "## tests"
    echo
    echo '```'
    grep -E "passed|failed|error|FAILED|ERROR|SKIPPED" "$OUT/tests.log" 2>/dev/null | tail -60
    echo '```'
    echo
    echo "## benchmark"
    echo
    cat "$OUT/ops_bench.md" 2>/dev/null || echo "(no benchmark output)"
} >"$OUT/gpu_check.md"

echo
echo "=== [gpu_check] report: $OUT/gpu_check.md; failed steps: ${FAILED[*]:-none}"
echo
cat "$OUT/ops_bench.md" 2>/dev/null || true
[[ ${#FAILED[@]} -eq 0 ]]
