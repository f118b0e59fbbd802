#!/usr/bin/env bash
# The Python packages the tests use (requirements.txt, pinned: the Cyclone DDS dVRK stand-in,
# and the MCAP readers the project did not write) in a venv, made once and remade when
# requirements.txt changes; safe to run from several tests at once. Prints the venv's python.
# `setup.sh bench` makes the benchmarks' venv instead (tests/bench/requirements.txt: OpenCV to
# compare against, never a dependency of the project or its tests).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
if [ "${1:-}" = bench ]; then
  here=$(cd "$here/../bench" && pwd)
  venv="${STITCH_BENCH_VENV:-$here/.venv}"
else
  venv="${STITCH_PYTHON_VENV:-$here/.venv}"
fi
mkdir -p "$(dirname "$venv")"
exec 9>"$venv.lock"
flock 9
if ! cmp -s "$here/requirements.txt" "$venv/requirements.installed" 2>/dev/null; then
  [ -x "$venv/bin/python" ] || python3 -m venv "$venv" >&2
  "$venv/bin/pip" install --quiet --disable-pip-version-check -r "$here/requirements.txt" >&2
  cp "$here/requirements.txt" "$venv/requirements.installed"
fi
echo "$venv/bin/python"
