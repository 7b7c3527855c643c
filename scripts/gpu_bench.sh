#!/usr/bin/env bash
# The benchmark suite of issue 5 in ONE command on the GPU machine, within a time budget:
#   sofa_beam   SOFA's benchmark beam, steps/s (target >= 10,000)
#   figure2     the paper's Figure 2: GPU/CPU speedup against element count (tets, triangles;
#               hooke, stvk, corotational), with the pure-torch path, assembled CSR/BSR/CuPy CG,
#               the C++ extension on all CPU threads and the pure-torch CPU path
#   cg_floor    time per CG iteration against the memory floor, 10^3 .. 10^7 elements
#   batches     1 .. 10,000 objects of 1k-5k tets against a Python loop
#   gather_variants  kernel 2 layouts: padded PartialForce against CSR + segment_reduce and atomics
#   step_bench  the paper's and SOFA's beams, extension vs pure torch (the earlier table)
#   ops_bench   the element ops against the floor on the 307,200-tet beam
# Each writes <name>.md/.json/.png (+ <name>.log) under $OUT; $OUT/gpu_bench.md gathers them
# with the status of every step. Each script gets a share of the budget (--budget-s: it skips
# the measurements that would not fit, and says so) and a hard time limit a little above it;
# the md/json of a script are rewritten after every measurement, so a step that is cut short
# still leaves what it measured.
#
#   OUT=/some/dir TENSORMASS_COMMIT=$(git rev-parse --short HEAD) bash scripts/gpu_bench.sh
# Switches: PYTHON (python3), GPU_BENCH_BUDGET (seconds for everything, default 440),
#           GPU_BENCH_DEVICE=cpu (a dry run without a GPU: every script with --quick on the CPU),
#           GPU_BENCH_BUILD=auto|1|0 (build the extension with CUDA first: auto = only when the
#           installed one has no CUDA kernels; the build's time comes out of the budget),
#           GPU_BENCH_ONLY="sofa_beam figure2" (run only these steps).
set -uo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
source "$ROOT/scripts/lib.sh"   # run_limited
PYTHON="${PYTHON:-python3}"
OUT="${OUT:-$ROOT/out/gpu_bench}"
mkdir -p "$OUT"
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONDONTWRITEBYTECODE=1
unset TENSORMASS_BACKEND
if [[ -z "${TENSORMASS_COMMIT:-}" ]]; then
    TENSORMASS_COMMIT="$(git -C "$ROOT" rev-parse --short HEAD 2>/dev/null || echo unknown)"
fi
export TENSORMASS_COMMIT
DEVICE="${GPU_BENCH_DEVICE:-cuda}"
BUDGET="${GPU_BENCH_BUDGET:-440}"
ONLY="${GPU_BENCH_ONLY:-}"
DEADLINE=$((SECONDS + BUDGET))
NPROC="$(nproc 2>/dev/null || echo 1)"
QUICK=()
if [[ "$DEVICE" == "cpu" ]]; then QUICK=(--quick); fi

STATUS_LINES=()
FAILED=()

wanted() { [[ -z "$ONLY" || " $ONLY " == *" $1 "* ]]; }

# run NAME SHARE COMMAND...: SHARE seconds of budget for this step (capped by what is left);
# the command gets --budget-s SHARE-15 (python start-up and the final writes take the rest)
# and a hard limit of SHARE+20 s.
run() {
    local name="$1" share="$2"; shift 2
    wanted "$name" || return 0
    local left=$((DEADLINE - SECONDS))
    if ((share > left)); then share=$left; fi
    if ((share < 20)); then
        STATUS_LINES+=("| $name | skipped (budget spent) | |")
        return 0
    fi
    local soft=$((share - 15)) hard=$((share + 20))
    run_limited gpu_bench "$name" "$hard" "partial results kept" "$@" --budget-s "$soft" || true
}

# ------------------------------------------------------------------ environment and build
{
    "$PYTHON" - <<'EOF'
import os, platform, sys
import torch
print("python", sys.version.split()[0], platform.platform())
print("torch", torch.__version__, "cuda", torch.version.cuda, "available", torch.cuda.is_available())
if torch.cuda.is_available():
    p = torch.cuda.get_device_properties(0)
    print("device", p.name, "sm_%d%d" % (p.major, p.minor), "%.1f GiB" % (p.total_memory / 2**30))
print("cpu threads (torch)", torch.get_num_threads(), "cpu count", os.cpu_count())
for name in ("cupy", "scipy", "matplotlib"):
    try:
        module = __import__(name)
        print(name, getattr(module, "__version__", "?"))
    except Exception as exc:
        print(name, "not importable:", type(exc).__name__)
EOF
    echo "commit $TENSORMASS_COMMIT"
} 2>&1 | tee "$OUT/environment.log"

needs_build() {
    "$PYTHON" -c "import sys, tensormass_torch as tm; from tensormass_torch import _C; sys.exit(0 if _C.has_cuda() else 1)" \
        >/dev/null 2>&1 && return 1
    return 0
}
BUILD="${GPU_BENCH_BUILD:-auto}"
if [[ "$DEVICE" != "cpu" && ( "$BUILD" == "1" || ( "$BUILD" == "auto" && $(needs_build; echo $?) == 0 ) ) ]]; then
    echo "=== [gpu_bench] building the extension with CUDA (time out of the budget)"
    t0=$SECONDS
    if TENSORMASS_BUILD_CUDA=1 TORCH_CUDA_ARCH_LIST="${TORCH_CUDA_ARCH_LIST:-9.0}" MAX_JOBS="${MAX_JOBS:-16}" \
        "$PYTHON" -m pip install --no-build-isolation --no-deps -e "$ROOT" >"$OUT/build.log" 2>&1; then
        STATUS_LINES+=("| build | ok | $((SECONDS - t0))s |")
    else
        STATUS_LINES+=("| build | FAILED (see build.log) | $((SECONDS - t0))s |")
        FAILED+=("build")
    fi
fi
"$PYTHON" -c "import json, tensormass_torch as tm; print(json.dumps(tm.backend_info()))" 2>&1 | tee -a "$OUT/environment.log"

# ------------------------------------------------------------------ the benchmarks
# Shares of the default 440 s: 40 + 165 + 70 + 75 + 45 + 35 = 430. Each share is capped by what
# is left, so a slow build or a slow step shortens the later ones instead of overrunning.
run sofa_beam 40 "$PYTHON" benchmarks/suite/sofa_beam.py --device "$DEVICE" --out "$OUT" "${QUICK[@]}"
run figure2 165 "$PYTHON" benchmarks/suite/figure2.py --device "$DEVICE" --out "$OUT" --cpu-threads "$NPROC" "${QUICK[@]}"
run cg_floor 70 "$PYTHON" benchmarks/suite/cg_floor.py --device "$DEVICE" --out "$OUT" "${QUICK[@]}"
run batches 75 "$PYTHON" benchmarks/suite/batches.py --device "$DEVICE" --out "$OUT" "${QUICK[@]}"
run gather_variants 30 "$PYTHON" benchmarks/studies/gather_variants.py --device "$DEVICE" --out "$OUT" "${QUICK[@]}"
if [[ "$DEVICE" == "cpu" ]]; then
    run step_bench 45 "$PYTHON" benchmarks/suite/step_bench.py --device cpu --out "$OUT" --steps 1 --scenes sofa_beam \
        --backends extension
    run ops_bench 40 "$PYTHON" benchmarks/suite/ops_bench.py --device cpu --out "$OUT" --mesh 8 4 4 --repeat 3
else
    run step_bench 45 "$PYTHON" benchmarks/suite/step_bench.py --device "$DEVICE" --out "$OUT" --steps 10 --max-seconds 3
    run ops_bench 35 "$PYTHON" benchmarks/suite/ops_bench.py --device "$DEVICE" --out "$OUT" --repeat 30
fi

# ------------------------------------------------------------------ the report
{
    echo "# gpu_bench report (commit $TENSORMASS_COMMIT)"
    echo
    echo '```'
    cat "$OUT/environment.log" 2>/dev/null
    echo '```'
    echo
    echo "| step | result | time |"
    echo "|---|---|---|"
    printf '%s\n' "${STATUS_LINES[@]}"
    for name in sofa_beam figure2 cg_floor batches step_bench ops_bench; do
        if [[ -f "$OUT/$name.md" ]]; then
            echo
            sed 's/^# /## /' "$OUT/$name.md"
        fi
    done
} >"$OUT/gpu_bench.md"

echo
echo "=== [gpu_bench] report: $OUT/gpu_bench.md; failed steps: ${FAILED[*]:-none}; $((SECONDS))s in all"
[[ ${#FAILED[@]} -eq 0 ]]
