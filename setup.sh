#!/usr/bin/env bash
# Set up mona-vo in ./.venv from a fresh clone. Idempotent; about 1 minute.
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null || PY=python3
"$PY" -m venv .venv
# torch first, exactly 2.13.0: pip finds the CPU wheel on this machine's disk; any other
# resolution of "torch" pulls a multi-GB CUDA build.
.venv/bin/pip install --quiet "torch==2.13.0"
.venv/bin/pip install --quiet -c constraints.txt -e '.[test]'
.venv/bin/pip check   # the installed set is consistent
.venv/bin/mona-vo --version
