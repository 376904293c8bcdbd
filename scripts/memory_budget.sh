#!/usr/bin/env bash
# The daemon's memory against its budget: scripts/memory_budget.sh BUILD_DIR [BUDGET_MB ...]
#
# For each budget (default 512 and 1024 MiB) it starts flarelabd with --memory-budget-mb BUDGET,
# finds the largest 3:2 frame the daemon accepts for a bracket of three exposures (larger ones are
# refused up front, naming the figure: each request of the search is accepted and cancelled, or
# refused), then runs a job of 4 frames of that size on the simulated rig in simulated time and
# reads the daemon's peak resident memory (VmHWM) when the job has ended. Prints one line a budget
# and exits 1 when a peak exceeds its budget.
set -euo pipefail

if (($# < 1)); then
    echo "usage: $0 BUILD_DIR [BUDGET_MB ...]" >&2
    exit 2
fi
repo=$(cd "$(dirname "$0")/.." && pwd)
build=$(cd "$1" && pwd)
shift
budgets=("$@")
((${#budgets[@]})) || budgets=(512 1024)
flarelab=$build/apps/flarelab
flarelabd=$build/apps/flarelabd
lens=$repo/data/lenses/heliar-tronnier.csv
work=$(mktemp -d /tmp/flarelab-memory.XXXXXX)
daemon=""
cleanup() {
    [[ -n $daemon ]] && kill "$daemon" 2>/dev/null && wait "$daemon" 2>/dev/null
    rm -rf "$work"
}
trap cleanup EXIT

failed=0
for budget in "${budgets[@]}"; do
    state=$work/state-$budget
    mkdir -p "$state"
    chmod 700 "$state"
    "$flarelabd" --state-dir "$state" --memory-budget-mb "$budget" --no-resume \
        >"$work/flarelabd-$budget.log" 2>&1 &
    daemon=$!
    export FLARELAB_SOCKET=$state/flarelabd.sock
    for _ in $(seq 100); do [[ -S $FLARELAB_SOCKET ]] && break; sleep 0.1; done
    [[ -S $FLARELAB_SOCKET ]] || { echo "memory_budget: flarelabd did not start" >&2; exit 1; }

    # The largest width (height = 2/3 of it) that the daemon accepts: binary search.
    lo=64 hi=8192 n=0
    while ((hi - lo > 8)); do
        mid=$(((lo + hi) / 2))
        n=$((n + 1))
        if out=$("$flarelab" sweep start --sim --lens "$lens" --from 0 --to 0.2 --step 0.2 --fast \
            --brackets 0.25,1,4 --width "$mid" --height $((mid * 2 / 3)) \
            -o "$state/output/probe-$n" 2>&1); then
            job=$(grep -o 'job-[0-9]*' <<<"$out" | head -n 1)
            "$flarelab" job cancel "$job" >/dev/null 2>&1 || true
            lo=$mid
        else
            grep -q 'memory' <<<"$out" ||
                { echo "memory_budget: a probe was refused for another reason: $out" >&2; exit 1; }
            hi=$mid
        fi
    done
    width=$lo height=$((lo * 2 / 3))
    refused=$("$flarelab" sweep start --sim --lens "$lens" --from 0 --to 0.2 --step 0.2 --fast \
        --brackets 0.25,1,4 --width "$hi" --height $((hi * 2 / 3)) -o "$state/output/refused" 2>&1 ||
        true)
    # Let the cancelled probes end before the measured job.
    sleep 1
    "$flarelab" sweep start --sim --lens "$lens" --from 0 --to 0.6 --step 0.2 --fast \
        --brackets 0.25,1,4 --width "$width" --height "$height" --watch \
        -o "$state/output/largest" >/dev/null
    peak_kib=$(awk '/^VmHWM:/ { print $2 }' "/proc/$daemon/status")
    kill "$daemon"
    wait "$daemon" 2>/dev/null || true
    daemon=""
    peak_mib=$(awk -v k="$peak_kib" 'BEGIN { printf "%.1f", k / 1024 }')
    verdict=within
    if ((peak_kib > budget * 1024)); then verdict=OVER && failed=1; fi
    echo "budget $budget MiB: largest accepted frame ${width}x${height} (3 exposures), 4 frames;" \
        "peak resident $peak_mib MiB: $verdict the budget"
    echo "    the next size refused: ${refused//$'\n'/ }"
done
exit $failed
