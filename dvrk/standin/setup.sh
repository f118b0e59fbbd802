#!/usr/bin/env bash
# The Cyclone DDS stand-in's Python environment (a venv with requirements.txt), made once:
# idempotent, safe to run from several tests at once; prints the venv's python.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
venv="${STITCH_STANDIN_VENV:-$here/.venv}"
mkdir -p "$(dirname "$venv")"
exec 9>"$venv.lock"
flock 9
if ! "$venv/bin/python" -c "import cyclonedds.domain" >/dev/null 2>&1; then
  python3 -m venv "$venv" >&2
  "$venv/bin/pip" install --quiet --disable-pip-version-check -r "$here/requirements.txt" >&2
fi
echo "$venv/bin/python"
