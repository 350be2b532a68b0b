#!/bin/bash
# Frame → set-point latency of `flownav run` (README "Measured figures", docs/deploy.md
# "Latency"): a 720p frame folder rendered from the simulated office played at its 30 fps, the
# simulated FNP/1 base on a pty, no log. Prints one JSON line per run: the latency and its parts
# (capture stamp → step start, the step, step end → set-point sent), the step's CPU time, frames
# dropped, and the 0.5 ms latency histogram; then `flownav flow --repeat` on one pair of the
# folder with 1 and 2 CPU threads.
#
#   bench/latency_check.sh BIN [BASE]
#
# BIN, BASE: flownav binaries (BASE, e.g. an older build, is measured first, the same way).
# Environment:
#   CPUS=0,1        the cores `run` and `flow` are pinned to (taskset), e.g. two cores of a
#                   larger machine to stand for a 2-core robot computer; empty: no pinning
#   BASE_CPU=2      the core the simulated base runs on (it stands for the base's own MCU);
#                   empty: no pinning
#   BACKENDS="cpu"  flow backends to run (`gpu` needs a GPU)
#   RUNS=3          runs per binary and backend
#   FRAMES=DIR      the frame folder (rendered with BIN when it does not exist; default
#                   /tmp/flownav_latency_frames)
#   FLOWNAV_ARGS    global flownav options for every `run` of BIN, e.g. "--config F"
# Results also go to $OUT/latency.jsonl when OUT is set.
set -u
BIN=$(realpath "$1")
BASE=${2:+$(realpath "$2")}
CPUS=${CPUS-0,1}
BASE_CPU=${BASE_CPU-2}
BACKENDS=${BACKENDS-cpu}
RUNS=${RUNS-3}
FRAMES=${FRAMES-/tmp/flownav_latency_frames}
RESULTS=${OUT:+$OUT/latency.jsonl}
read -r -a EXTRA <<<"${FLOWNAV_ARGS-}"
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-/tmp/xdg-$(id -u)}
mkdir -p "$XDG_RUNTIME_DIR" && chmod 700 "$XDG_RUNTIME_DIR"

pin() { # pin CPULIST CMD...: runs CMD on those cores (or unpinned for an empty list)
    local cpus=$1
    shift
    if [ -n "$cpus" ]; then taskset -c "$cpus" "$@"; else "$@"; fi
}

emit() {
    echo "$1"
    if [ -n "$RESULTS" ]; then echo "$1" >>"$RESULTS"; fi
}

if [ ! -d "$FRAMES" ]; then
    "$BIN" render --out "$FRAMES" --frames 90 --velocity 0.3 --size 1280x720 >/dev/null 2>&1 ||
        { echo "cannot render the frame folder $FRAMES" >&2; exit 1; }
fi

one_run() { # one_run LABEL BINARY BACKEND [GLOBAL OPTIONS...]
    local label=$1 bin=$2 backend=$3 dir pty sb
    shift 3
    dir=$(mktemp -d)
    # started directly (not through `pin`, a function, whose background subshell `kill` would
    # end while leaving the base running)
    if [ -n "$BASE_CPU" ]; then
        taskset -c "$BASE_CPU" "$bin" sim-base >"$dir/sb.out" 2>"$dir/sb.err" &
    else
        "$bin" sim-base >"$dir/sb.out" 2>"$dir/sb.err" &
    fi
    sb=$!
    for _ in $(seq 100); do
        [ -s "$dir/sb.out" ] && break
        sleep 0.05
    done
    pty=$(grep -o '/dev/pts/[0-9]*' "$dir/sb.out" | head -1)
    if [ -z "$pty" ]; then
        echo "sim-base did not start: $(cat "$dir/sb.err")" >&2
        kill "$sb" 2>/dev/null
        return 1
    fi
    pin "$CPUS" timeout 60 "$bin" "$@" --flow-backend "$backend" run --camera "frames:$FRAMES" --base "fnp:$pty" \
        --no-log >"$dir/run.out" 2>"$dir/run.err"
    kill "$sb" 2>/dev/null
    wait "$sb" 2>/dev/null
    python3 - "$label" "$backend" "$dir/run.out" <<'EOF'
import json, sys
label, backend, path = sys.argv[1:4]
lines = [l for l in open(path) if l.startswith("{")]
if not lines:
    print(json.dumps({"build": label, "backend": backend, "error": "no report"}))
    sys.exit()
r = json.loads(lines[-1])
pick = lambda k: {q: r[k][q] for q in ("median_ms", "p90_ms", "max_ms")} if k in r else None
print(json.dumps({
    "build": label, "backend": backend,
    "latency": pick("latency"), "wait": pick("latency_wait"), "step_wall": pick("step_wall"),
    "deliver": pick("latency_deliver"), "step_cpu": pick("step_cpu"),
    "frames": r.get("frames_processed"), "dropped": r.get("frames_dropped"),
    "histogram": r.get("latency_histogram"),
}))
EOF
    rm -rf "$dir"
}

for backend in $BACKENDS; do
    for i in $(seq "$RUNS"); do
        if [ -n "$BASE" ]; then emit "$(one_run base "$BASE" "$backend")"; fi
        emit "$(one_run new "$BIN" "$backend" "${EXTRA[@]}")"
    done
done

a="$FRAMES/0010.png"
b="$FRAMES/0014.png"
flow_timing() { # flow_timing LABEL BINARY [ARGS...]
    local label=$1 bin=$2
    shift 2
    pin "$CPUS" "$bin" --flow-backend cpu flow "$a" "$b" --json --repeat 200 "$@" 2>/dev/null |
        python3 -c "import json,sys; t=json.load(sys.stdin)['timing']; t['build']='$label'; print(json.dumps(t))"
}
if [ -n "$BASE" ]; then emit "$(flow_timing base "$BASE")"; fi
emit "$(flow_timing new "$BIN" --threads 1)"
emit "$(flow_timing new "$BIN" --threads 2)"
