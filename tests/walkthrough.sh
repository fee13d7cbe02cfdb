#!/usr/bin/env bash
# The README's curl walk-through, as a script: submit res/bump to the HTTP API, wait until
# the job has succeeded, download albedo.png, normal.png, height.png and mesh.glb.
#
#   tests/walkthrough.sh [BASE_URL]      (default http://127.0.0.1:8080)
#
# Run it from the repository root (it reads res/bump/); the downloads land in the current
# directory. Needs only curl and sed. tests/http/api.rs runs it against a real server.
set -euo pipefail
BASE=${1:-http://127.0.0.1:8080}

# 1. Submit the four images and their light table. The answer is 202 Accepted with the
#    job as JSON; its first field is the job's id.
job=$(curl -sS --fail-with-body \
  -F lights=@res/bump/light_directions.csv \
  -F images=@res/bump/im1.png -F images=@res/bump/im2.png \
  -F images=@res/bump/im3.png -F images=@res/bump/im4.png \
  "$BASE/v1/jobs")
id=$(printf '%s' "$job" | sed -n 's/^{"id":"\([^"]*\)".*/\1/p')
echo "job $id"

# 2. Poll the job until it is no longer queued or running.
for _ in $(seq 600); do
  status=$(curl -sS --fail-with-body "$BASE/v1/jobs/$id" | sed -n 's/^{"id":"[^"]*","status":"\([a-z]*\)".*/\1/p')
  echo "status $status"
  case "$status" in
    queued | running) sleep 1 ;;
    *) break ;;
  esac
done
test "$status" = succeeded

# 3. Download the pictures and the mesh.
for name in albedo.png normal.png height.png mesh.glb; do
  curl -sS --fail-with-body -o "$name" "$BASE/v1/jobs/$id/artifacts/$name"
  echo "saved $name"
done
