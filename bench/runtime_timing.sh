#!/usr/bin/env bash
# The runtime's real-time figures, which the tests do not assert (a loaded machine would break
# them): over real pseudo-terminals against the simulated FNP/1 base, for RUNS repetitions:
#   - stall stop: ms from the last frame's capture to the first zero set-point (rule: 150 ms, <200 ms);
#   - set-point rate: SETPOINTs per second of the base's clock with a 10 fps camera (rule: >=20 Hz);
#   - alarm reaction: ms of the base's clock from the STATUS that raises the bumper / the e-stop
#     to the first zero it receives (rule: within one control period, 40 ms at 25 Hz; 50 ms budget).
# They come from the `runtime` tests' own measurements (printed with --nocapture).
#
# Usage:  bench/runtime_timing.sh [RUNS]        (default 5)
#         PROFILE=dev bench/runtime_timing.sh   (default release; dev builds faster, runs slower)
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS="${1:-5}"
PROFILE="${PROFILE:-release}"
flag=(); [ "$PROFILE" = release ] && flag=(--release)
bin="$(cargo test "${flag[@]}" --no-run --test runtime --message-format=json 2>/dev/null \
  | python3 -c 'import json,sys
for l in sys.stdin:
    m = json.loads(l)
    if m.get("reason") == "compiler-artifact" and m.get("executable") and m["target"]["name"] == "runtime":
        print(m["executable"])')"
echo "profile $PROFILE, $RUNS runs, $(nproc) cores, load $(cut -d' ' -f1 /proc/loadavg)"
for i in $(seq "$RUNS"); do
  "$bin" --nocapture --test-threads=1 \
    a_stalled_camera the_command_is_refreshed the_bases_bumper_and_estop 2>&1 \
    | grep -E "^(stall:|bumper:|e-stop:|set-point rate:)" | sed -E 's/;.*//' \
    | sed "s/^/run $i: /"
done
