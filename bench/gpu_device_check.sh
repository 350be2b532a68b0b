#!/bin/sh
# GPU device check (docs/gpu.md "Measurements"): parity tests, the 720p benchmark of the GPU
# engine (default grid and dense) with per-pass GPU times and the host's split of a waiting
# `compute`, and `flownav flow --repeat` on the reference pairs, from prebuilt binaries, on a
# machine without a Rust toolchain or network (x86-64 Linux with a Vulkan driver). Optionally the
# same benchmark and `flownav flow` from a baseline build in the same run, so that before and
# after are measured on the same card. Takes about 2–4 minutes on an H100/H200; every step is
# capped by `timeout`.
#
# Build the binaries HERE (the build machine), from the repository root. One release build of
# the library serves the three binaries (`--benches` builds the criterion benchmark with the
# release profile; run with `--bench` it benchmarks as `cargo bench` does):
#
#   exe() { sed -n 's/.*"executable":"\([^"]*\/deps\/flow_gpu-[^"]*\)".*/\1/p'; }
#   cargo build --release --bin flownav
#   cargo test --release --test flow_gpu --benches --no-run --message-format=json | exe > /tmp/exes
#   mkdir -p .devbin && cp target/release/flownav .devbin/flownav
#   for f in $(cat /tmp/exes); do
#       if "$f" --list 2>/dev/null | grep -q ': benchmark'; then cp "$f" .devbin/flow_gpu_bench;
#       else cp "$f" .devbin/flow_gpu_test; fi
#   done
#   strip .devbin/*        # ~100 MB each with line tables, ~8–10 MB stripped
#
# For a baseline, the same from another checkout (e.g. `git worktree add ../base COMMIT`) into
# .devbin/base (flow_gpu_bench and flownav are enough). .devbin/ must be ignored by git (list
# /.devbin/ in .git/info/exclude); it does not travel with the working tree by itself: name it in
# the device tool's `carry` (~30–50 MB stripped with a baseline, under the 64 MiB limit). Do not
# commit it. data/graf_shift_512 and data/motorcycle_stereo (tracked) are the inputs. The lent
# NVIDIA machines have the driver's ICD but no Vulkan loader: carry the .debs of libvulkan1 and
# of glvnd (libglvnd0 libegl1 libgl1 libglx0 libopengl0 libgles2: the ICD, libGLX_nvidia.so.0,
# fails to load without them, and wgpu then finds no adapter) and `dpkg -x` each into / and run
# `ldconfig` before this script. Then on the device machine, from the repository root:
#
#   bench/gpu_device_check.sh [BINDIR [BASEDIR]]   # BINDIR defaults to .devbin; results in $OUT if set
#
# To try it here on lavapipe: WGPU_BACKEND=vulkan bench/gpu_device_check.sh (the benchmark skips
# gpu/dense on a software adapter).
#
# What it runs:
#   1. the flow_gpu test binary, --test-threads 8 (parity of both GPU paths with the CPU engine,
#      bit-identical; it prints the adapter the tests ran on), once as built and once under each
#      setting in $CHECK_ENVS (environment assignments, several separated by spaces, settings by
#      ';'; default: the per-block kernel at 256 and 1024 invocations per workgroup, the cost
#      volume with its rows summed unpacked, FLOWNAV_GPU_CV_SWAR=0, and with one dx per walk,
#      FLOWNAV_GPU_CV_DQ=0).
#      `cli_gpu_backend_runs_or_names_what_to_install` is skipped: it runs the `flownav` binary at
#      the absolute path baked in at build time, which does not exist there.
#   2. the benchmark (criterion, short: warm-up 1 s, measurement 2 s), groups
#      gpu/{default,dense}, gpu_stream_wait/… and gpu_stream/…: the baseline's first (if given),
#      then this build's. The benchmark first checks that the GPU field equals the CPU engine's
#      exactly on its 720p frames (it panics otherwise). After each gpu/… benchmark it prints
#      the mean GPU time of each compute pass over 50 more pairs ("pass times") and, in builds
#      that have it, the host's split of a waiting `compute` ("host split": submission, then the
#      wait and readback).
#   3. this build's default grid again under each setting in $VARIANTS (as $CHECK_ENVS;
#      default: the blocking wait, and 256 and 1024 invocations per workgroup of the per-block
#      kernel, docs/gpu.md), to see what each part is worth on this card; VARIANTS= skips them.
#      $VARIANT_FILTER picks other benchmarks for them (a criterion filter, e.g.
#      'flow_gpu_720p/gpu/dense$' with the cost-volume setting FLOWNAV_GPU_CV_SWAR=0,
#      docs/gpu.md).
#   4. `flownav flow A B --repeat 300 --flow-backend gpu --json` on data/graf_shift_512 and
#      data/motorcycle_stereo, baseline first: the `timing` object (wall time per pair of a
#      waiting `compute`, min/median/p90 ms).
set -u
cd "$(dirname "$0")/.."
BIN=${1:-.devbin}
BASE=${2:-}
OUTDIR=${OUT:-$PWD/.devout}
mkdir -p "$OUTDIR"
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-/tmp/xdg-$(id -u)}
mkdir -p "$XDG_RUNTIME_DIR" && chmod 700 "$XDG_RUNTIME_DIR"
export FLOWNAV_DATA=${FLOWNAV_DATA:-$PWD/data}
export RUST_BACKTRACE=1
export CRITERION_HOME=${CRITERION_HOME:-/tmp/flownav-criterion}
CHECK_ENVS=${CHECK_ENVS-"FLOWNAV_GPU_MATCH_WG=256;FLOWNAV_GPU_MATCH_WG=1024;FLOWNAV_GPU_CV_SWAR=0;FLOWNAV_GPU_CV_DQ=0"}
VARIANTS=${VARIANTS-"FLOWNAV_GPU_WAIT=block;FLOWNAV_GPU_MATCH_WG=256;FLOWNAV_GPU_MATCH_WG=1024"}
VARIANT_FILTER=${VARIANT_FILTER-'flow_gpu_720p/gpu(_stream_wait|_stream)?/default$'}
status=0

log() { echo "== $*" | tee -a "$OUTDIR/summary.txt"; }
keep() { grep -E '^GPU:|cost volume|identical|differ|panicked|pass times|host split|^flow_gpu_720p/|time:' "$1" \
    | grep -v -E 'change:|Performance|No change' | tee -a "$OUTDIR/summary.txt"; }

log "$(date -u +%FT%TZ) device check in $PWD, binaries in $BIN${BASE:+, baseline in $BASE}"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader \
    | tee -a "$OUTDIR/summary.txt"

# 1. parity tests, as built and under each setting of CHECK_ENVS
parity() { # NAME [ASSIGNMENT...]
    name=$1
    shift
    env -u FLOWNAV_GPU_MATCH_WG -u FLOWNAV_GPU_CV_SWAR "$@" timeout 60 \
        "$BIN/flow_gpu_test" --test-threads 8 --nocapture --skip cli_gpu_backend_runs_or_names_what_to_install \
        >"$OUTDIR/tests_$name.txt" 2>&1
    rc=$?
    log "flow_gpu tests (env $*): exit $rc ($(grep -E '^test result' "$OUTDIR/tests_$name.txt" | tail -1))"
    grep -E '^GPU flow tests on|SKIPPED|FAILED|panicked' "$OUTDIR/tests_$name.txt" | sort | uniq -c | head -20 \
        | tee -a "$OUTDIR/summary.txt"
    [ "$rc" = 0 ] || status=1
}
parity default
i=0
oldifs=$IFS
IFS=';'
for v in $CHECK_ENVS; do
    IFS=$oldifs
    i=$((i + 1))
    # shellcheck disable=SC2086 # several assignments in one setting
    [ -n "$v" ] && parity "env$i" $v
done
IFS=$oldifs

# 2. benchmarks: baseline, then this build
FILTER='flow_gpu_720p/gpu(_stream_wait|_stream)?/(default|dense)$'
bench() { # NAME BINARY FILTER [ENV...]
    name=$1 exe=$2 filter=$3
    shift 3
    env "$@" timeout "$limit" "$exe" --bench --warm-up-time 1 --measurement-time 2 --noplot "$filter" \
        >"$OUTDIR/bench_$name.txt" 2>&1
    rc=$?
    log "bench $name (env $*): exit $rc"
    keep "$OUTDIR/bench_$name.txt"
    [ "$rc" = 0 ] || status=1
}
limit=90
[ -n "$BASE" ] && bench base "$BASE/flow_gpu_bench" "$FILTER" -u FLOWNAV_GPU_COST_VOLUME
bench new "$BIN/flow_gpu_bench" "$FILTER" -u FLOWNAV_GPU_COST_VOLUME

# 3. this build's default grid under each variant
i=0
limit=45
oldifs=$IFS
IFS=';'
for v in $VARIANTS; do
    IFS=$oldifs
    [ -n "$v" ] || continue
    i=$((i + 1))
    # shellcheck disable=SC2086 # several assignments in one setting
    bench "variant$i" "$BIN/flow_gpu_bench" "$VARIANT_FILTER" $v
done
IFS=$oldifs

# 4. flownav flow --repeat on the reference pairs
for pair in graf_shift_512 motorcycle_stereo; do
    for build in ${BASE:+base} new; do
        if [ "$build" = base ]; then exe=$BASE/flownav; else exe=$BIN/flownav; fi
        [ -x "$exe" ] || continue
        timeout 30 "$exe" flow "data/$pair/0000.png" "data/$pair/0001.png" --repeat 300 --flow-backend gpu --json \
            >"$OUTDIR/flow_${pair}_$build.json" 2>"$OUTDIR/flow_${pair}_$build.err"
        rc=$?
        log "flownav flow $pair ($build): exit $rc $(grep -o '"timing":{[^}]*}' "$OUTDIR/flow_${pair}_$build.json")"
        [ "$rc" = 0 ] || { status=1; tail -3 "$OUTDIR/flow_${pair}_$build.err" | tee -a "$OUTDIR/summary.txt"; }
    done
done
log "done, status $status"
exit $status
