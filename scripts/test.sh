#!/usr/bin/env bash
# Set up (once) and run every check: lint, types, unit/integration tests, PostgreSQL and browser tests.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/bootstrap_venv.sh
bootstrap_venv .venv-test "[test]"

# Browser tests drive Debian's chromium; Playwright never downloads a browser here.
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing Debian chromium for the browser tests" >&2
  apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
fi

# The local PostgreSQL when present; tests that need it skip with a reason when it cannot be reached.
export SSP_REHAB_TEST_POSTGRES_URL="${SSP_REHAB_TEST_POSTGRES_URL:-postgresql+psycopg://postgres@127.0.0.1:5432/test}"

# One warm numba cache for the whole run, compiled beside the lint and type checks (minutes on a clean clone):
# the tests' workers and daemons then load the real-time kernels rather than each compiling them at its start.
.venv-test/bin/python -m server.cli.main warm-up --json &
warm_up=$!
trap 'kill "$warm_up" 2>/dev/null || true' EXIT
.venv-test/bin/ruff check core server benchmarks tests migrations
.venv-test/bin/mypy
wait "$warm_up"
.venv-test/bin/python -m pytest "$@"
