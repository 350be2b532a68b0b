#!/usr/bin/env bash
# A `flownav sim --log` killed with SIGKILL: its log must be readable up to the last complete
# chunk, by flownav (`flownav log info`) and by the official Python `mcap` reader
# (bench/check_mcap.py --truncated). The cargo test `stop_paths` checks the flownav side; this
# script adds the independent reader, which CI installs in its own step.
#
# Usage:  bench/kill_log_check.sh [SECONDS_BEFORE_KILL]   (default 8)
# Needs:  a built flownav (FLOWNAV=path, default ${CARGO_TARGET_DIR:-target}/release/flownav) and
#         a Python with mcap 1.x (PYTHON=path, default /tmp/venv-mcap/bin/python; see check_mcap.py).
set -euo pipefail
cd "$(dirname "$0")/.."
FLOWNAV="${FLOWNAV:-${CARGO_TARGET_DIR:-target}/release/flownav}"
PYTHON="${PYTHON:-/tmp/venv-mcap/bin/python}"
WAIT="${1:-8}"
[ -x "$FLOWNAV" ] || { echo "no flownav at $FLOWNAV: build it (cargo build --release) or set FLOWNAV" >&2; exit 2; }
"$PYTHON" -c 'import mcap' 2>/dev/null || { echo "no mcap module in $PYTHON: python3 -m venv /tmp/venv-mcap && /tmp/venv-mcap/bin/pip install 'mcap==1.*'" >&2; exit 2; }
dir="$(mktemp -d)"
trap 'rm -rf "$dir"' EXIT
"$FLOWNAV" sim --quiet --size 320x180 --max-time 600 --log "$dir" >/dev/null 2>&1 &
pid=$!
sleep "$WAIT"
kill -KILL "$pid"
wait "$pid" 2>/dev/null || true
log="$(ls "$dir"/*.mcap)"
echo "killed after ${WAIT} s: $log ($(stat -c %s "$log") bytes)"
"$FLOWNAV" log info "$log"
"$PYTHON" bench/check_mcap.py "$log" --truncated
