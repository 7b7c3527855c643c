# Sourced by run.sh and test.sh: resolve PYTHON (a relative path is taken from the caller's
# directory), move to the repository root, and set the package up (install.sh, idempotent).
PYTHON="${PYTHON:-python3}"
if [[ "$PYTHON" == */* && "$PYTHON" != /* ]]; then PYTHON="$PWD/$PYTHON"; fi
export PYTHON
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
bash "$ROOT/scripts/install.sh"
