#!/usr/bin/env bash
# Sets up .venv if needed and runs the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
ATGS_TEST_SETUP=1 ./scripts/setup.sh
exec .venv/bin/python -m pytest -q "$@"
