#!/usr/bin/env bash
# Run the test suite: set up (scripts/install.sh, idempotent), then pytest on tests/.
# Extra arguments go to pytest, e.g. `bash scripts/test.sh -k backend -x`.
# "No tests collected" (pytest exit status 5) counts as a failure.
set -euo pipefail

source "$(dirname "${BASH_SOURCE[0]}")/setup_env.sh"

status=0
"$PYTHON" -m pytest -q tests "$@" || status=$?
if [[ "$status" == 5 ]]; then
    echo "[test] ERROR: pytest collected no tests" >&2
    exit 1
fi
exit "$status"
