#!/usr/bin/env bash
# The browser app in headless Chromium against a real server: the release binary serves on
# 127.0.0.1 with a temporary data directory, and .ci/browser.mjs submits res/bump through
# the page and checks the result views (see there). Needs Debian's chromium
# (`apt-get install -y chromium`) and `cd .ci && npm ci`.
#
#   .ci/browser.sh [<data-set folder> [<screenshot dir>]]
set -euo pipefail
cd "$(dirname "$0")/.."

set_dir="${1:-res/bump}"
shots="${2:-}"

cargo build --release --locked --quiet
bin="${CARGO_TARGET_DIR:-target}/release/photostereo"

work="$(mktemp -d)"
server=""
cleanup() {
  if [ -n "$server" ]; then
    kill "$server" 2>/dev/null || true
    wait "$server" 2>/dev/null || true
  fi
  rm -rf "$work"
}
trap cleanup EXIT

"$bin" serve --listen 127.0.0.1:0 --data-dir "$work/data" --workers 2 \
  --min-free-disk 0 --shutdown-grace 1s --log-format json >"$work/server.log" 2>&1 &
server=$!

addr=""
for _ in $(seq 300); do
  addr="$(sed -n 's/.*"addr":"\([0-9.]*:[0-9]*\)".*/\1/p' "$work/server.log" | head -n 1)"
  [ -n "$addr" ] && break
  kill -0 "$server" 2>/dev/null || { cat "$work/server.log"; exit 1; }
  sleep 0.1
done
[ -n "$addr" ] || { echo "the server did not start"; cat "$work/server.log"; exit 1; }

status=0
node .ci/browser.mjs "http://$addr" "$set_dir" $shots || status=$?
if [ "$status" -ne 0 ]; then
  echo "server log:"
  grep -v '"status":200' "$work/server.log" | tail -n 20
fi
exit "$status"
