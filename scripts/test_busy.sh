#!/usr/bin/env bash
# The suite with a second job busy on one core the whole time (a build, another run: how a shared machine looks),
# as the tests' bounds must hold then too. Usage: make test-busy [ARGS="-k pattern"]
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/python -c "while True: pass" &
busy=$!
trap 'kill $busy 2>/dev/null || true' EXIT
.venv/bin/python -m pytest -q -p no:cacheprovider "$@"
