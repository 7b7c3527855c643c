#!/usr/bin/env bash
# Lint: ruff over the repository (rules in pyproject.toml), installed into the python you use if
# missing (PYTHON, default python3). Exit status non-zero on any finding.
set -euo pipefail
PYTHON="${PYTHON:-python3}"
cd "$(dirname "${BASH_SOURCE[0]}")/.."
if ! "$PYTHON" -m ruff --version >/dev/null 2>&1; then
    echo "[lint] installing ruff" >&2
    "$PYTHON" -m pip install -q ruff >/dev/null 2>&1 || { echo "[lint] ERROR: pip install ruff failed" >&2; exit 1; }
fi
"$PYTHON" -m ruff check .
