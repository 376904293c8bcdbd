#!/usr/bin/env bash
# The daemon's pipeline measured (bench/daemon_bench.cpp), written to out/bench/daemon.json:
#   - overhead: 10 frames at 640x427 with the default brackets (0.25, 1, 4 s) in real time, the
#     rig alone against the daemon's job, best of 3 runs (about 6 minutes);
#   - memory: jobs of 10 and of 1000 frames at 640x427 in simulated time, resident memory along
#     the way and at the peak, and the same sweeps through the rig alone (about 7 minutes);
#   - idle: flarelabd's CPU time over 60 s with nothing to do.
#   scripts/bench_daemon.sh BUILD_DIR [--quick]    (--quick: 3 frames of short brackets, 100
#   frames, 5 s idle; checks that it runs)
# Run it on a quiet machine: the real-time runs compete with anything else for the CPU.
set -euo pipefail
if (($# < 1 || $# > 2)) || { (($# == 2)) && [[ $2 != --quick ]]; }; then
    echo "usage: $0 BUILD_DIR [--quick]" >&2
    exit 2
fi
build=$(realpath -m "$1")
cd "$(dirname "$0")/.."
out=${FLARELAB_OUT:-out}/bench
mkdir -p "$out"
bench=$build/bench/daemon_bench
if [[ ! -x $bench || ! -x $build/apps/flarelabd ]]; then
    echo "bench_daemon: $bench or $build/apps/flarelabd is missing (a sanitizer build has no benchmarks)" >&2
    exit 1
fi
if [[ ${2:-} == --quick ]]; then
    overhead=(--frames 3 --brackets 0.05,0.2 --runs 1)
    long=100
    idle=5
else
    overhead=(--frames 10 --brackets 0.25,1,4 --runs 3)
    long=1000
    idle=60
fi
{
    "$bench" overhead "${overhead[@]}"
    "$bench" memory --frames 10
    "$bench" memory --frames "$long"
    "$bench" rigmem --frames 10
    "$bench" rigmem --frames "$long"
    "$bench" idle --flarelabd "$build/apps/flarelabd" --seconds "$idle"
} >"$out/daemon.jsonl.tmp"
mv "$out/daemon.jsonl.tmp" "$out/daemon.jsonl"
echo "bench_daemon: $out/daemon.jsonl"
