#!/usr/bin/env bash
# The Node packages of tests/node/package.json (pinned by package-lock.json) in a directory
# outside the clone, installed once and again when the lock file changes; safe to run from
# several tests at once. Prints the directory to put in NODE_PATH.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
dir="${STITCH_NODE_MODULES:-${HOME:-/tmp}/.cache/stitch-node-tests}"
mkdir -p "$dir"
exec 9>"$dir.lock"
flock 9
if ! cmp -s "$here/package-lock.json" "$dir/package-lock.json" 2>/dev/null; then
  cp "$here/package.json" "$here/package-lock.json" "$dir/"
  (cd "$dir" && npm ci --silent --no-audit --no-fund >&2)
fi
echo "$dir/node_modules"
