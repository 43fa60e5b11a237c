#!/usr/bin/env bash
# Set up (venv + editable install with test extras) and run the test suite.
# The test files run side by side, one per CPU this process may use (pytest-xdist, at most 4
# workers; a file's tests stay on one worker, so its module fixtures are made once):
# COSIM_TEST_WORKERS=N sets the number, 0 runs every test in this one process.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e ".[test]"
workers=${COSIM_TEST_WORKERS:-$(.venv/bin/python -c 'import os; print(min(4, len(os.sched_getaffinity(0))))')}
dist=()
[ "$workers" -gt 1 ] && dist=(-n "$workers" --dist loadfile)
exec .venv/bin/python -m pytest -q -ra ${dist[@]+"${dist[@]}"} "$@"
