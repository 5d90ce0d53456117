#!/usr/bin/env bash
# What the Dockerfile does, without a container (tests/test_container.py runs the image itself):
# build the wheel, install it (not editable) into a clean venv, start the server from it with
# the Dockerfile's command line (a config mounted as a file, the health check's PING), and run
# the conformance suite against it.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-python3}"
work=$(mktemp -d)
server_pid=""
cleanup() {
    if [ -n "$server_pid" ] && kill -0 "$server_pid" 2>/dev/null; then
        kill -TERM "$server_pid" 2>/dev/null || true
        wait "$server_pid" 2>/dev/null || true
    fi
    rm -rf "$work"
}
trap cleanup EXIT

echo "check-wheel: building the wheel"
"$PYTHON" -m pip wheel --no-deps --no-build-isolation -q -w "$work/dist" . >"$work/build.log" 2>&1 \
    || "$PYTHON" -m pip wheel --no-deps -q -w "$work/dist" . >"$work/build.log" 2>&1 \
    || { cat "$work/build.log"; exit 1; }
wheel=$(ls "$work"/dist/cellvision-*.whl)
echo "check-wheel: installing $(basename "$wheel") into a clean venv"
"$PYTHON" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install -q "$wheel" >"$work/install.log" 2>&1 \
    || { cat "$work/install.log"; exit 1; }

# What the container mounts at /config.
mkdir -p "$work/config" "$work/data"
cat >"$work/config/cell.yaml" <<YAML
server: {name: wheel-check}
results: {path: $work/data/results.sqlite3}
cameras:
  tool: {source: request}
  depth_cam: {source: request, depth: true,
              intrinsics: {width: 320, height: 240, fx: 300, fy: 300, cx: 159.5, cy: 119.5}}
inspections:
  - {name: brightness, type: presence, camera: tool, measure: mean_intensity, min: 0}
  - {name: pose, type: qr_pose, camera: depth_cam}
YAML

cd "$work"   # nothing from the source tree may be importable: only the installed wheel
"$work/venv/bin/vision-server" check-config "$work/config/cell.yaml" >/dev/null
# The JSON Schemas are package data (SPEC §6.3.1): one per message type, readable from the wheel.
"$work/venv/bin/python" -c "from protocol import MessageType; from protocol.schema import \
message_schema_path as path, schemas; assert all(path(t) in schemas() for t in MessageType)"
# The Dockerfile's CMD, on loopback and a free port instead of 0.0.0.0:7878.
"$work/venv/bin/vision-server" serve --config "$work/config/cell.yaml" \
    --host 127.0.0.1 --port 0 >"$work/server.out" 2>"$work/server.err" &
server_pid=$!
port=""
for _ in $(seq 1 100); do
    port=$(sed -n 's/.*listening on [^ ]*:\([0-9]*\).*/\1/p' "$work/server.out" | head -n1)
    [ -n "$port" ] && break
    kill -0 "$server_pid" 2>/dev/null || { cat "$work/server.err"; exit 1; }
    sleep 0.1
done
[ -n "$port" ] || { echo "check-wheel: the server did not start"; cat "$work/server.err"; exit 1; }
echo "check-wheel: server from the wheel listens on 127.0.0.1:$port"
"$work/venv/bin/vision-server" ping --server "127.0.0.1:$port"          # the HEALTHCHECK
"$work/venv/bin/python" -m protocol.conformance "127.0.0.1:$port" | tail -n 1
echo "check-wheel: ok"
