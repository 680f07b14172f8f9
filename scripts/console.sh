#!/usr/bin/env bash
# Set up (once) and start the therapist console on the embedded default: SQLite and the simulator.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/bootstrap_venv.sh
bootstrap_venv .venv ""
# The real-time kernels go into numba's cache now (minutes the first time, seconds after), so that the
# robot daemon's first start loads them instead of compiling while the console waits.
.venv/bin/ssp-rehab warm-up
exec .venv/bin/ssp-rehab serve "$@"
