#!/usr/bin/env bash
# Installs navcrafter with its test tools, lints, then runs the test suite (no GPU needed).
# Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
bash deploy/local/setup.sh test
export PREFECT_SERVER_ANALYTICS_ENABLED="${PREFECT_SERVER_ANALYTICS_ENABLED:-false}"
.venv/bin/ruff check --quiet .
.venv/bin/lint-imports --no-cache --no-logo  # the layers and no cycles ([tool.importlinter] in pyproject.toml)
exec .venv/bin/python -m pytest "$@"
