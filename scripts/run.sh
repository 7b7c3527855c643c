#!/usr/bin/env bash
# The main job: set up (scripts/install.sh, idempotent), then run the package's entry point.
set -euo pipefail

PYTHON="${PYTHON:-python3}"
if [[ "$PYTHON" == */* && "$PYTHON" != /* ]]; then PYTHON="$PWD/$PYTHON"; fi
export PYTHON
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

bash "$ROOT/scripts/install.sh"



"$PYTHON" -m tensormass_torch run cantilever --out out/ "$@"
