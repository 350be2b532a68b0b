#!/bin/sh
# Navigation on a real robot's terms: every shipped world with the default uncalibrated base
# (`--odometry-error` default) and the robot started 0.1 m, 0.1 m and 3° off its place, and the
# office with its map's lengths 5 % too long and 5 % too short (bench/scale_map.py). One JSON
# line per run, the aggregate line of each set last; the figures in docs/results.md come from it.
#
#   bench/nav_report.sh                  # seeds 0..100 (reporting); navigation is tuned on 100..199
#   SEEDS=0..10 bench/nav_report.sh      # a quicker look
#   OUT=/tmp/nav bench/nav_report.sh     # one file per set there (default: target/nav-report)
#   SETS="lshape hall" bench/nav_report.sh   # some of: office lshape narrow hall office-map dense mirror
#                                        # (dense: the crowded office, a stress test; mirror: the
#                                        # office and the L-shaped world mirrored by
#                                        # bench/mirror_world.py, every side swapped and the
#                                        # corner a right turn; neither in the default)
#   SIZE=320x180 bench/nav_report.sh     # another render size (default: the simulator's)
#   CONFIG=/tmp/design.toml bench/nav_report.sh   # a partial config over the defaults (a design to screen)
#
# bench/compare_runs.py BASE.jsonl OTHER.jsonl compares two sets with intervals, Fisher's test and,
# on the seeds they share, McNemar's test and the paired mission-time difference.
set -eu
cd "$(dirname "$0")/.."
cargo build --release --quiet
bin="${CARGO_TARGET_DIR:-target}/release/flownav"
out="${OUT:-target/nav-report}"
mkdir -p "$out"
seeds="${SEEDS:-0..100}"
jobs="${JOBS:-$(nproc 2>/dev/null || echo 1)}"
start="0.1,-0.1,3"
sets="${SETS:-office lshape narrow hall office-map}"
want() { case " $sets " in *" $1 "*) return 0 ;; *) return 1 ;; esac; }
run() { # NAME, then the flags of the set
    name="$1"; shift
    "$bin" ${CONFIG:+--config "$CONFIG"} sim --seeds "$seeds" --jobs "$jobs" --no-log --quiet --start-error "$start" ${SIZE:+--size "$SIZE"} "$@" >"$out/$name.jsonl" || true
    tail -n 1 "$out/$name.jsonl"
}
mission() { # each world's mission: out of a room, along its corridors, to a door place
    case $1 in office) echo R9:D2 ;; lshape) echo R5:D10 ;; narrow) echo R5:D4 ;; hall) echo R10:D2 ;; esac
}
if want office; then run office --mission "$(mission office)"; fi
for w in lshape narrow hall; do
    if want "$w"; then run "$w" --world "mocks/worlds/$w.toml" --map "maps/$w.toml" --mission "$(mission "$w")"; fi
done
if want mirror; then
    for w in office lshape; do
        python3 bench/mirror_world.py "mocks/worlds/$w.toml" >"$out/$w-mirror-world.toml"
        python3 bench/mirror_world.py "maps/$w.toml" >"$out/$w-mirror-map.toml"
        run "$w-mirror" --world "$out/$w-mirror-world.toml" --map "$out/$w-mirror-map.toml" --mission "$(mission "$w")"
    done
fi
if want dense; then run dense --world mocks/worlds/office-dense.toml --map maps/office.toml --mission "$(mission office)"; fi
if want office-map; then
    for f in 1.05 0.95; do
        python3 bench/scale_map.py maps/office.toml "$f" --anchor R9 >"$out/office-x$f.toml"
        run "office-map-x$f" --map "$out/office-x$f.toml" --mission "$(mission office)"
    done
fi
