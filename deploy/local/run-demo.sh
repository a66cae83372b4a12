#!/usr/bin/env bash
# The main job on the embedded default: installs, writes the demo collection (demo/photos), and
# explores it into a local Zarr store (demo/store) with a local Prefect (temporary SQLite server) in
# SIMULATION MODE (no model weights exist here). Extra arguments go to `navcrafter explore`.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
bash deploy/local/setup.sh
export PREFECT_SERVER_ANALYTICS_ENABLED="${PREFECT_SERVER_ANALYTICS_ENABLED:-false}"
.venv/bin/navcrafter demo-data demo/photos
.venv/bin/navcrafter explore demo/photos --store demo/store "$@"
