#!/usr/bin/env bash
# Benchmarks the HTTP API of the release binary with wrk (Debian package
# `wrk`): cached status reads and the drive list, against `drivegate serve`
# on the built-in simulator (4 drives, 115200 baud, polling as fast as the
# bus allows). Then runs the in-process benchmark (`cargo bench --bench
# http_api`) for command latency on the saturated bus.
#
# Usage: scripts/bench-http.sh [seconds] [connections]
# Environment: PORT (default 18080), CARGO_TARGET_DIR (default target).
set -euo pipefail

seconds="${1:-10}"
connections="${2:-32}"
port="${PORT:-18080}"
target="${CARGO_TARGET_DIR:-target}"
cd "$(dirname "$0")/.."

command -v wrk >/dev/null || { echo "wrk is not installed (apt-get install wrk)" >&2; exit 1; }
cargo build --release --quiet --bin drivegate

config="$(mktemp --suffix=.toml)"
log="$(mktemp --suffix=.log)"
trap 'kill "$daemon" 2>/dev/null || true; wait "$daemon" 2>/dev/null || true; rm -f "$config" "$log"' EXIT
# The built-in default, on a port of its own and without Modbus TCP.
sed -e "s/127.0.0.1:8080/127.0.0.1:${port}/" -e 's/^listen = "127.0.0.1:5020"/enabled = false/' \
    config/default.toml >"$config"

"$target/release/drivegate" serve --config "$config" >"$log" 2>&1 &
daemon=$!
for _ in $(seq 100); do
    curl -fs "http://127.0.0.1:${port}/readyz" >/dev/null && break
    sleep 0.1
done
curl -fs "http://127.0.0.1:${port}/readyz" >/dev/null || { cat "$log" >&2; exit 1; }

echo "== cached status of one drive: ${connections} connections, ${seconds} s"
wrk -t2 -c"$connections" -d"${seconds}s" --latency "http://127.0.0.1:${port}/api/v1/drives/conveyor/status"
echo "== list of all drives with their status: ${connections} connections, ${seconds} s"
wrk -t2 -c"$connections" -d"${seconds}s" --latency "http://127.0.0.1:${port}/api/v1/drives"
echo "== the bus meanwhile"
curl -fs "http://127.0.0.1:${port}/api/v1/buses/sim"
echo

kill "$daemon"
wait "$daemon" 2>/dev/null || true

echo "== command latency on the saturated bus (in-process benchmark)"
BENCH_SECONDS="$seconds" BENCH_CLIENTS="$connections" cargo bench --quiet --bench http_api
