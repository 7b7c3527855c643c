#!/usr/bin/env bash
# The main job: set up (scripts/install.sh, idempotent), then run the package's entry point.
set -euo pipefail

source "$(dirname "${BASH_SOURCE[0]}")/setup_env.sh"

"$PYTHON" -m tensormass_torch run cantilever --out out/ "$@"
