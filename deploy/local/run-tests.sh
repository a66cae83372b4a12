#!/usr/bin/env bash
# Installs navcrafter with its test tools, lints, then runs the test suite (no GPU needed).
# Extra arguments go to pytest. The tests run on both cores with pytest-xdist (NAVCRAFTER_TEST_WORKERS=0: one
# process); each worker starts its own Prefect test server for the system tests that need one.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
bash deploy/local/setup.sh test
export PREFECT_SERVER_ANALYTICS_ENABLED="${PREFECT_SERVER_ANALYTICS_ENABLED:-false}"
.venv/bin/ruff check --quiet .
.venv/bin/lint-imports --no-cache --no-logo  # the layers and no cycles ([tool.importlinter] in pyproject.toml)
# loadgroup: each module with module fixtures runs on one worker, long units first (tests/conftest.py)
exec .venv/bin/python -m pytest -n "${NAVCRAFTER_TEST_WORKERS:-2}" --dist loadgroup --no-loadscope-reorder "$@"
