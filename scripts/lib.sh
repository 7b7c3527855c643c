# Shared by scripts/gpu_check.sh and scripts/gpu_bench.sh (source it; needs OUT, STATUS_LINES, FAILED).
#
# run_limited TAG NAME LIMIT NOTE COMMAND...: run COMMAND with a hard time limit of LIMIT seconds,
# its output shown and kept in $OUT/NAME.log; time it and record "| NAME | ok / FAILED (why) | Ns |"
# in STATUS_LINES (NAME in FAILED on failure; NOTE is added to a time-limit failure). Returns the
# command's exit status.
run_limited() {
    local tag="$1" name="$2" limit="$3" note="$4"; shift 4
    echo
    echo "=== [$tag] $name (time limit ${limit}s): $*"
    local t0=$SECONDS
    timeout --kill-after=10 "$limit" "$@" 2>&1 | tee "$OUT/$name.log"
    local rc=${PIPESTATUS[0]}
    local dt=$((SECONDS - t0))
    if [[ $rc -eq 0 ]]; then
        STATUS_LINES+=("| $name | ok | ${dt}s |")
    else
        local why="exit $rc"
        if [[ $rc -eq 124 || $rc -eq 137 ]]; then why="time limit ${limit}s${note:+ ($note)}"; fi
        STATUS_LINES+=("| $name | FAILED ($why) | ${dt}s |")
        FAILED+=("$name")
    fi
    echo "=== [$tag] $name: exit $rc after ${dt}s"
    return $rc
}
