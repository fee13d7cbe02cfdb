#!/usr/bin/env bash
# Property-based API testing with Schemathesis against the committed OpenAPI document
# (openapi/openapi.json): the release binary serves on 127.0.0.1 with a temporary data
# directory, holding one succeeded and one failed job so that listings carry full job
# resources; Schemathesis then sends generated requests (valid and invalid) to every
# operation and checks that no answer is a 5xx and that every answer matches the document
# (status, content type, schema).
#
#   .ci/schemathesis.sh                     the bounded run CI does (about 3 minutes)
#   ST_MAX_EXAMPLES=200 ST_MAX_TIME=900 .ci/schemathesis.sh    a longer one
#
# Needs python3 + pip (installs schemathesis 4 if missing) and curl. Exits non-zero when a
# check fails.
set -euo pipefail
cd "$(dirname "$0")/.."

max_examples="${ST_MAX_EXAMPLES:-30}"
max_time="${ST_MAX_TIME:-150}"

if ! command -v schemathesis >/dev/null 2>&1; then
  pip install --quiet 'schemathesis>=4,<5'
fi

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

# Every generated request comes from the one open tenant: its per-minute submission quota
# (120 by default) can be reached within the run, and 429s would then stand in for the
# answers under test, so it is raised here.
"$bin" serve --listen 127.0.0.1:0 --data-dir "$work/data" --workers 2 \
  --min-free-disk 0 --max-body-bytes 64MiB --upload-timeout 30s --shutdown-grace 1s \
  --tenant-submissions-per-minute 100000 \
  --log-format json >"$work/server.log" 2>&1 &
server=$!

addr=""
for _ in $(seq 300); do
  addr="$(sed -n 's/.*"addr":"\([0-9.]*:[0-9]*\)".*/\1/p' "$work/server.log" | head -n 1)"
  [ -n "$addr" ] && break
  kill -0 "$server" 2>/dev/null || { cat "$work/server.log"; exit 1; }
  sleep 0.1
done
[ -n "$addr" ] || { echo "the server did not start"; cat "$work/server.log"; exit 1; }
base="http://$addr"
echo "== schemathesis against $base"

# One job that succeeds, one that fails in the worker (coplanar lights).
job_id() { sed -n 's/^{"id":"\([^"]*\)".*/\1/p'; }
succeeded="$(curl -sS --fail-with-body \
  -F lights=@res/bump/light_directions.csv \
  -F images=@res/bump/im1.png -F images=@res/bump/im2.png \
  -F images=@res/bump/im3.png -F images=@res/bump/im4.png \
  "$base/v1/jobs" | job_id)"
failed="$(curl -sS --fail-with-body \
  -F 'lights=im1.png, 1, 0, 1
im2.png, -1, 0, 1
im3.png, 0.5, 0, 1
im4.png, 0, 0, 1' \
  -F images=@res/bump/im1.png -F images=@res/bump/im2.png \
  -F images=@res/bump/im3.png -F images=@res/bump/im4.png \
  "$base/v1/jobs" | job_id)"
for _ in $(seq 300); do
  curl -sS "$base/v1/jobs" | grep -Eq '"status":"(queued|running)"' || break
  sleep 0.2
done

# Most generated job ids and artifact names are these real ones, so that the job and
# artifact operations get past their 404s.
cat >"$work/schemathesis.toml" <<EOF
cache = { enabled = false }

[dictionaries.jobs]
values = ["$succeeded", "$failed"]

[dictionaries.artifacts]
values = ["albedo.png", "shaded.png", "normal.png", "mesh.glb", "result.json", "albedo_rgb.png"]

[[operations]]
include-path = "/v1/jobs/{id}/artifacts/{name}"
parameters = { "path.id" = { dictionary = "jobs", probability = 0.8 }, "path.name" = { dictionary = "artifacts", probability = 0.7 } }

[[operations]]
include-path = "/v1/jobs/{id}"
include-method = "GET"
parameters = { "path.id" = { dictionary = "jobs", probability = 0.8 } }
EOF

status=0
timeout --signal=INT "$((max_time + 60))" \
  schemathesis --config-file "$work/schemathesis.toml" run openapi/openapi.json \
  --url "$base" \
  --checks not_a_server_error,response_schema_conformance,status_code_conformance,content_type_conformance \
  --max-examples "$max_examples" \
  --max-time "$max_time" \
  --phases examples,coverage,fuzzing \
  --workers 2 \
  --request-timeout 30 \
  --generation-database none \
  --seed "${ST_SEED:-20251125}" \
  --no-color || status=$?

# The server must have survived all of it.
if ! curl -sS --fail -o /dev/null "$base/healthz"; then
  echo "the server no longer answers /healthz"
  status=1
fi
if grep -q '"level":"ERROR"' "$work/server.log"; then
  echo "the server logged errors:"
  grep '"level":"ERROR"' "$work/server.log" | head -n 20
  status=1
fi
if grep -qi 'panicked' "$work/server.log"; then
  echo "the server panicked:"
  grep -i 'panicked' "$work/server.log" | head -n 20
  status=1
fi
exit "$status"
