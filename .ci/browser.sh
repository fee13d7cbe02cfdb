#!/usr/bin/env bash
# The browser app against real servers, in headless Chromium and in Firefox: the release
# binary serves on 127.0.0.1 with temporary data directories, once open and once with an
# API key, and .ci/browser.mjs runs the same checks in each browser (see there). Needs
# Debian's chromium, firefox-esr and xvfb (`apt-get install -y chromium firefox-esr xvfb`:
# Firefox has WebGL only with a display, so it runs under xvfb-run) and `cd .ci && npm ci`.
#
#   .ci/browser.sh [<data-set folder> [<screenshot dir>]]
#
# BROWSERS="chromium firefox" (the default) says which browsers run.
set -euo pipefail
cd "$(dirname "$0")/.."

set_dir="${1:-res/bump}"
shots="${2:-}"
key="browser-check-key"

cargo build --release --locked --quiet
bin="${CARGO_TARGET_DIR:-target}/release/photostereo"

work="$(mktemp -d)"
servers=()
cleanup() {
  for pid in "${servers[@]}"; do
    kill "$pid" 2>/dev/null || true
    wait "$pid" 2>/dev/null || true
  done
  rm -rf "$work"
}
trap cleanup EXIT

# start <name> [serve flags...]: a server on an ephemeral port; its URL in $url.
start() {
  local name="$1"
  shift
  "$bin" serve --listen 127.0.0.1:0 --data-dir "$work/$name" --workers 2 \
    --min-free-disk 0 --shutdown-grace 1s --log-format json "$@" >"$work/$name.log" 2>&1 &
  local pid=$!
  servers+=("$pid")
  local addr=""
  for _ in $(seq 300); do
    addr="$(sed -n 's/.*"addr":"\([0-9.]*:[0-9]*\)".*/\1/p' "$work/$name.log" | head -n 1)"
    [ -n "$addr" ] && break
    kill -0 "$pid" 2>/dev/null || { cat "$work/$name.log"; exit 1; }
    sleep 0.1
  done
  [ -n "$addr" ] || { echo "the $name server did not start"; cat "$work/$name.log"; exit 1; }
  url="http://$addr"
}
start open
open_url="$url"
start keyed --api-key "$key"
keyed_url="$url"

status=0
for browser in ${BROWSERS:-chromium firefox}; do
  run=(node .ci/browser.mjs --browser "$browser" --open "$open_url" --keyed "$keyed_url"
    --key "$key" --set "$set_dir")
  # The README's screenshots are Chromium's.
  if [ -n "$shots" ] && [ "$browser" = chromium ]; then run+=(--shots "$shots"); fi
  if [ "$browser" = firefox ]; then run=(xvfb-run -a -s "-screen 0 1600x1600x24" "${run[@]}"); fi
  "${run[@]}" || status=1
done
if [ "$status" -ne 0 ]; then
  for name in open keyed; do
    echo "$name server log:"
    grep -v '"status":200' "$work/$name.log" | tail -n 20
  done
fi
exit "$status"
