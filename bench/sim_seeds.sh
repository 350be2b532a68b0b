#!/bin/sh
# The closed-loop mission benchmark: mission R9:D2 in the built-in office, one run per
# seed (random obstacle placement + sensor/encoder noise), release build, no logs. Prints one JSON
# summary per seed, then the aggregate line (success rate, collisions, time, clearance, wall time,
# realtime factor). Extra arguments go to `flownav sim` (e.g. --size 320x180, --max-time 120).
#
#   bench/sim_seeds.sh            # seeds 0..20
#   SEEDS=0..5 bench/sim_seeds.sh --noise 0
#   SEEDS=0..100 JOBS=8 bench/sim_seeds.sh   # 8 missions at a time (default: one per CPU core)
# Exit status 3 when a run did not reach its goal or touched something (README, "Exit codes").
set -eu
cd "$(dirname "$0")/.."
cargo build --release --quiet
exec "${CARGO_TARGET_DIR:-target}/release/flownav" sim --seeds "${SEEDS:-0..20}" --jobs "${JOBS:-$(nproc 2>/dev/null || echo 1)}" --no-log --quiet "$@"
