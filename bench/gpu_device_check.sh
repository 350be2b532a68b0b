#!/bin/sh
# GPU device check for the dense fast path (cost volume, docs/gpu.md "Dense mode"): parity tests
# and a short benchmark of both GPU paths, from prebuilt binaries, on a machine without a Rust
# toolchain or network (x86-64 Linux with a Vulkan driver). Takes about 1.5–2 minutes on an
# H100/H200; everything is capped by `timeout` so the whole run stays under 3 minutes.
#
# Build the binaries HERE (the build machine), from the repository root:
#
#   exe() { sed -n 's/.*"executable":"\([^"]*\/deps\/flow_gpu-[^"]*\)".*/\1/p'; }
#   T=$(cargo test --release --test flow_gpu --no-run --message-format=json | exe)
#   B=$(cargo bench --bench flow_gpu --no-run --message-format=json | exe)
#   mkdir -p .devbin && cp "$T" .devbin/flow_gpu_test && cp "$B" .devbin/flow_gpu_bench
#   strip .devbin/flow_gpu_test .devbin/flow_gpu_bench   # ~95 MB each with line tables, ~8 MB stripped
#
# (Both JSON streams also name target/release/flownav; `exe` keeps only the flow_gpu binary.)
# To try the script here on lavapipe: WGPU_BACKEND=vulkan bench/gpu_device_check.sh (the bench
# skips gpu/dense on a software adapter).
# .devbin/ is ignored (this repository's .git/info/exclude lists /.devbin/), so it does not
# travel with the working tree by itself: name it in the device tool's `carry` ([".devbin"],
# ~17 MB stripped, under the 64 MiB limit). Do not commit it. data/graf_shift_512 (tracked) is
# the benchmark's input. Then on the device machine, from the repository root:
#
#   bench/gpu_device_check.sh [BINDIR]      # BINDIR defaults to .devbin; results in $OUT if set
#
# What it runs:
#   1. the flow_gpu test binary, --test-threads 4 (parity of both GPU paths with the CPU engine,
#      bit-identical). `cli_gpu_backend_runs_or_names_what_to_install` is skipped: it runs the
#      `flownav` binary at the absolute path baked in at build time, which does not exist there.
#   2. the flow_gpu benchmark (criterion, short: warm-up 1 s, measurement 2 s), groups
#      gpu/{default,dense} and gpu_stream_wait/{default,dense}, once with the cost volume on
#      where it applies (the default) and once with FLOWNAV_GPU_COST_VOLUME=0 (the per-block
#      kernel only). The benchmark first checks that the GPU field equals the CPU engine's field
#      exactly on its 720p frames (it panics otherwise: that is how a parity failure shows).
#      After each gpu/… benchmark it prints the mean GPU time of each compute pass over 50 more
#      pairs (timestamp queries: "pass times (ms, mean of 50): prep …, costvol …, reduce …,
#      total …"; "match L0" for the per-block kernel), also for each forced tile shape
#      (FLOWNAV_BENCH_CV_TILES: the planner's 16x16 g6 forced, 16x16 g5 (the old fastest),
#      16x8 g6, 8x8 g11 (the old planner's choice), 8x4 g33).
set -u
cd "$(dirname "$0")/.."
BIN=${1:-.devbin}
OUTDIR=${OUT:-$PWD/.devout}
mkdir -p "$OUTDIR"
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-/tmp/xdg-$(id -u)}
mkdir -p "$XDG_RUNTIME_DIR" && chmod 700 "$XDG_RUNTIME_DIR"
export FLOWNAV_DATA=${FLOWNAV_DATA:-$PWD/data}
export RUST_BACKTRACE=1
export CRITERION_HOME=${CRITERION_HOME:-/tmp/flownav-criterion}
status=0

log() { echo "== $*" | tee -a "$OUTDIR/summary.txt"; }

log "$(date -u +%FT%TZ) device check in $PWD, binaries in $BIN"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader \
    | tee -a "$OUTDIR/summary.txt"

# 1. parity tests
timeout 50 "$BIN/flow_gpu_test" --test-threads 4 --skip cli_gpu_backend_runs_or_names_what_to_install \
    >"$OUTDIR/tests.txt" 2>&1
rc=$?
log "flow_gpu tests: exit $rc ($(grep -E '^test result' "$OUTDIR/tests.txt" | tail -1))"
grep -E '^GPU flow tests on|FAILED|panicked' "$OUTDIR/tests.txt" | head -40 | tee -a "$OUTDIR/summary.txt"
[ "$rc" = 0 ] || status=1

# 2. benchmarks, new path (default) then old path
# (the new path also times forced tile shapes of the cost volume: FLOWNAV_BENCH_CV_TILES)
FILTER='flow_gpu_720p/gpu(_stream_wait)?/(default|dense)(_tile_.*)?$'
TILES=${FLOWNAV_BENCH_CV_TILES-'16,8,6;16,16,6;16,16,5;8,8,11;8,4,33'}  # the planner's 720p choice first
for mode in new old; do
    if [ "$mode" = old ]; then sw="FLOWNAV_GPU_COST_VOLUME=0"; lim=40; else sw="-u FLOWNAV_GPU_COST_VOLUME FLOWNAV_BENCH_CV_TILES=$TILES"; lim=90; fi
    # shellcheck disable=SC2086
    env $sw timeout $lim "$BIN/flow_gpu_bench" --bench --warm-up-time 1 --measurement-time 2 \
        --noplot "$FILTER" >"$OUTDIR/bench_$mode.txt" 2>&1
    rc=$?
    log "bench ($mode path: env $sw): exit $rc"
    grep -E '^GPU:|cost volume|identical|differ|panicked|tile|pass times|^flow_gpu_720p/|time:' "$OUTDIR/bench_$mode.txt" \
        | tee -a "$OUTDIR/summary.txt"
    [ "$rc" = 0 ] || status=1
done
log "done, status $status"
exit $status
