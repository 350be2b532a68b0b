#!/usr/bin/env bash
# Soak: `flownav run` on a looping frame folder against `flownav sim-base` with link faults
# (dropped bytes, corrupted bytes, disconnects), for DURATION seconds. Ends with one JSON line and
# exits 1 when a criterion is missed:
#   - every fault → stop gap, measured by the simulated base on its own clock, is <= 200 ms
#     (a fault is settled when the base is commanded to zero or receives an intact command;
#     docs/serial.md, "Soak");
#   - the run's RSS grows by less than 5 % from the end of the warm-up to the end;
#   - every fault is counted: each injected disconnect is a loss the host's OS reported (the
#     driver's `disconnects_os` plus `hangups_reconnecting` equal the disconnects injected, exactly),
#     the losses the driver's silence timeout declared are reported on their own, and the frames
#     the faults made undeliverable show up as lost packets in the decoder of the side that should
#     have got them (docs/serial.md, "Soak").
# The 1-minute load average is sampled with the RSS and reported (the machine may be shared).
#
# Usage:  bench/soak.sh                   (one hour)
#         DURATION=300 bench/soak.sh      (a quick one)
# Settings (environment): DURATION (s, 3600), FAULTS (sim-base --faults, see below), WATCHDOG_MS
# (the base's watchdog the host sets in HELLO, 150), WARMUP (s before the first RSS figure, 30),
# SAMPLE (s between RSS samples, 5), OUT (working folder, target/soak), FLOWNAV (a flownav binary;
# default: a release build of this checkout, copied into OUT so a rebuild cannot swap it mid-run).
set -euo pipefail
cd "$(dirname "$0")/.."
DURATION="${DURATION:-3600}"
FAULTS="${FAULTS:-drop=0.0005,corrupt=0.0005,disconnect=0.02:1s,seed=7}"
WATCHDOG_MS="${WATCHDOG_MS:-150}"
WARMUP="${WARMUP:-30}"
SAMPLE="${SAMPLE:-5}"
OUT="${OUT:-target/soak}"
mkdir -p "$OUT"

if [ -z "${FLOWNAV:-}" ]; then
  built="$(cargo build --release --bin flownav --message-format=json 2>/dev/null | python3 -c 'import json,sys
for l in sys.stdin:
    m = json.loads(l)
    if m.get("reason") == "compiler-artifact" and m.get("executable") and m["target"]["name"] == "flownav":
        print(m["executable"])')"
  cp "$built" "$OUT/flownav"
  FLOWNAV="$OUT/flownav"
fi
"$FLOWNAV" run --help | grep -q -- '--loop' || { echo "soak: $FLOWNAV has no run --loop" >&2; exit 2; }

# A 6 s lap: 60 rendered frames of the office at 10 fps, the camera's full size.
frames="$OUT/frames"
if [ ! -f "$frames/odometry.csv" ]; then
  "$FLOWNAV" render --out "$frames" --frames 60 --fps 10 --velocity 0.3 >/dev/null 2>"$OUT/render.log"
fi
# The watchdog must be shorter than 200 ms for a disconnect to stop the base within 200 ms: the
# host cannot reach the base while the link is down, only the firmware's watchdog stops it.
cat >"$OUT/soak.toml" <<EOF
[base]
watchdog_ms = $WATCHDOG_MS
EOF

link="$OUT/base.link"
rm -f "$link"
"$FLOWNAV" sim-base --faults "$FAULTS" --link "$link" >"$OUT/sim-base.out" 2>"$OUT/sim-base.log" &
base_pid=$!
cleanup() { kill "$base_pid" 2>/dev/null || true; }
trap cleanup EXIT
for _ in $(seq 100); do [ -s "$OUT/sim-base.out" ] && break; sleep 0.1; done
echo "soak: sim-base on $(head -n1 "$OUT/sim-base.out") (link $link), faults $FAULTS, ${DURATION} s" >&2

"$FLOWNAV" --config "$OUT/soak.toml" run --camera "frames:$frames" --loop --base "fnp:$link" \
  --duration "$DURATION" --no-log >"$OUT/run.json" 2>"$OUT/run.log" &
run_pid=$!
start=$(date +%s)
: >"$OUT/rss.tsv"
: >"$OUT/load.tsv"
next=0
# Polled often, so the base stops right after the run: faults injected after the host has gone
# cannot be counted by it.
while kill -0 "$run_pid" 2>/dev/null; do
  now=$(( $(date +%s) - start ))
  if [ "$now" -ge "$next" ]; then
    rss=$(awk '/^VmRSS:/ {print $2}' "/proc/$run_pid/status" 2>/dev/null || true)
    [ -n "$rss" ] && printf '%s\t%s\n' "$now" "$rss" >>"$OUT/rss.tsv"
    printf '%s\t%s\n' "$now" "$(cut -d' ' -f1 /proc/loadavg)" >>"$OUT/load.tsv"
    next=$(( now + SAMPLE ))
  fi
  sleep 0.2
done
run_rc=0
wait "$run_pid" || run_rc=$?
kill -TERM "$base_pid"
wait "$base_pid" || true
trap - EXIT

python3 - "$OUT" "$DURATION" "$WARMUP" "$run_rc" "$FAULTS" "$WATCHDOG_MS" <<'EOF'
import json, sys
out, duration, warmup, run_rc, faults_spec, watchdog_ms = sys.argv[1:]
run = json.loads(open(f"{out}/run.json").read().strip().splitlines()[-1])
base = json.loads(open(f"{out}/sim-base.out").read().strip().splitlines()[-1])
rss = [tuple(map(int, l.split())) for l in open(f"{out}/rss.tsv") if l.strip()]
after = [kb for t, kb in rss if t >= float(warmup)] or [kb for _, kb in rss]
rss_start, rss_end = after[0], after[-1]
growth = 100.0 * (rss_end - rss_start) / rss_start
f, gaps, link = base["faults"], base["stop_gaps"], run["link"]
kinds = ("drop", "corrupt", "disconnect")
gap_max = max(gaps[k]["max_ms"] for k in kinds)
gap_p99 = max(gaps[k]["p99_ms"] for k in kinds)
# A receiver that starts afresh on each new link cannot see the hit frames before its first
# intact one on that link: allow one per connection.
slack = link["reconnects"] + 1
to_host_expected = f["to_host"]["frames_hit"] - f["to_host"]["frames_hit_unseen"]
# The simulated base injects a disconnect only while the host has the port open, so each one is a
# hang-up the host's OS reports: on a link that was up (disconnects_os) or during a reconnect's
# handshake (hangups_reconnecting). Losses the host's silence timeout declared are link silences
# it handled (a starved process, a run of dropped bytes), reported on their own.
host_os = link["disconnects_os"] + link["hangups_reconnecting"]
load = [float(l.split()[1]) for l in open(f"{out}/load.tsv") if l.strip()]
counted = {
    "disconnects": {"injected": f["disconnects"], "host_os": host_os, "host_os_link_up": link["disconnects_os"],
                    "host_os_reconnecting": link["hangups_reconnecting"],
                    "host_silence": link["disconnects_silence"], "host_link_losses": link["disconnects"]},
    "frames_to_host": {"hit": to_host_expected, "host_lost": link["lost_rx"], "host_dropped": link["dropped_rx"]},
    "frames_to_base": {"hit": f["to_base"]["frames_hit"], "base_lost": base["base"]["frames_lost"],
                       "base_dropped": base["base"]["frames_dropped"]},
}
all_counted = (
    f["disconnects"] == host_os
    and link["disconnects"] == link["disconnects_os"] + link["disconnects_silence"]
    and abs(link["lost_rx"] - to_host_expected) <= slack
    and abs(base["base"]["frames_lost"] - f["to_base"]["frames_hit"]) <= slack
)
summary = {
    "duration_s": run["duration_s"],
    "faults_spec": faults_spec,
    "watchdog_ms": int(watchdog_ms),
    "faults": {
        "bytes_dropped": f["to_host"]["bytes_dropped"] + f["to_base"]["bytes_dropped"],
        "bytes_corrupted": f["to_host"]["bytes_corrupted"] + f["to_base"]["bytes_corrupted"],
        "disconnects": f["disconnects"],
    },
    "counted": counted,
    "stop_gaps": gaps,
    "gap_max_ms": gap_max,
    "gap_p99_ms_worst_kind": gap_p99,
    "rss_kb": {"start": rss_start, "end": rss_end, "samples": len(rss)},
    "rss_growth_pct": round(growth, 2),
    "frames_processed": run["frames_processed"],
    "load_1min": {"mean": round(sum(load) / len(load), 2) if load else None, "max": max(load, default=None),
                  "samples": len(load)},
    "run_exit": int(run_rc),
    "ok": {"gap": gap_max <= 200.0 and gaps["pending"] <= 1, "rss": growth < 5.0, "counted": all_counted,
           "run": int(run_rc) == 0 and run["ended"] == "shutdown"},
}
print(json.dumps(summary))
sys.exit(0 if all(summary["ok"].values()) else 1)
EOF
