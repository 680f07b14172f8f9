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

.venv-test/bin/ruff check core server benchmarks tests migrations
.venv-test/bin/mypy
.venv-test/bin/python -m pytest "$@"
