#!/usr/bin/env bash
# The live view's cost on `flownav run`'s capture → set-point latency: the same frame folder,
# played in a loop against the simulated base, with and without `--live` (with a headless viewer
# subscribed to every topic, bench/live_viewer.py), with and without the MCAP log. Runs the
# configurations in turn, ROUNDS times, and prints one line per run: the configuration, the
# latency median/p90/max and the live view's sent/dropped counts (from run's JSON line).
#
#   FLOWNAV=target/release/flownav DURATION=20 ROUNDS=2 bench/live_cost.sh
#
# Needs a Python with `websocket-client` in $VIEWER_PY (default /tmp/venv-ws/bin/python:
# python3 -m venv /tmp/venv-ws && /tmp/venv-ws/bin/pip install -q websocket-client).
set -euo pipefail
cd "$(dirname "$0")/.."
FLOWNAV="${FLOWNAV:-target/release/flownav}"
DURATION="${DURATION:-20}"
ROUNDS="${ROUNDS:-2}"
OUT="${OUT:-target/live-cost}"
VIEWER_PY="${VIEWER_PY:-/tmp/venv-ws/bin/python}"
PORT="${PORT:-8799}"
mkdir -p "$OUT"

frames="$OUT/frames"
if [ ! -f "$frames/odometry.csv" ]; then
  "$FLOWNAV" render --out "$frames" --frames 60 --fps 10 --velocity 0.3 >/dev/null 2>"$OUT/render.log"
fi
link="$OUT/base.link"
rm -f "$link"
"$FLOWNAV" sim-base --link "$link" >"$OUT/sim-base.out" 2>"$OUT/sim-base.log" &
base_pid=$!
cleanup() { kill "$base_pid" 2>/dev/null || true; }
trap cleanup EXIT
for _ in $(seq 100); do [ -s "$OUT/sim-base.out" ] && break; sleep 0.1; done

one() { # NAME ARGS...
  local name="$1"; shift
  local viewer_pid=""
  rm -rf "$OUT/logs"
  if [[ " $* " == *" --live "* ]]; then
    "$VIEWER_PY" bench/live_viewer.py "ws://127.0.0.1:$PORT" >"$OUT/$name.viewer.json" 2>"$OUT/$name.viewer.log" &
    viewer_pid=$!
  fi
  "$FLOWNAV" run --camera "frames:$frames" --loop --base "fnp:$link" --duration "$DURATION" "$@" \
    >"$OUT/$name.json" 2>"$OUT/$name.log"
  [ -n "$viewer_pid" ] && wait "$viewer_pid" || true
  python3 - "$name" "$OUT/$name.json" "$OUT/$name.viewer.json" <<'EOF'
import json, sys
name, path, viewer = sys.argv[1:]
r = json.loads(open(path).read().strip().splitlines()[-1])
l, live = r["latency"], r.get("live", {})
got = ""
try:
    v = json.load(open(viewer))
    got = f' viewer got {sum(v["messages"].values())} msgs, {sum(v["bytes"].values()) / 1e6:.0f} MB'
except (OSError, ValueError):
    pass
print(f'{name:14s} latency median {l["median_ms"]:.2f} p90 {l["p90_ms"]:.2f} max {l["max_ms"]:.2f} ms over {l["count"]}'
      f' set-points; live sent {live.get("sent", "-")} dropped {live.get("dropped", "-")}{got}')
EOF
}

for round in $(seq "$ROUNDS"); do
  one "nolog-r$round" --no-log
  one "nolog-live-r$round" --no-log --live "127.0.0.1:$PORT"
  one "log-r$round" --log "$OUT/logs"
  one "log-live-r$round" --log "$OUT/logs" --live "127.0.0.1:$PORT"
done
