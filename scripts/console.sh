#!/usr/bin/env bash
# Set up (once) and start the therapist console on the embedded default: SQLite and the simulator.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/bootstrap_venv.sh
bootstrap_venv .venv ""
exec .venv/bin/ssp-rehab serve "$@"
