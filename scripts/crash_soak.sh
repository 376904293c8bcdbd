#!/usr/bin/env bash
# The daemon killed with SIGKILL at random points of real-time sweeps, many times in a row
# (issue 18): after every kill a new flarelabd resumes where the sweeps on disk end. Once the
# kills are done and every sweep has finished, each is checked against the same sweep taken
# uninterrupted (simulated time, same seed): every angle present exactly once, every frame's EXR
# byte for byte the same, the sweep read back whole (flarelab sweep info --check --strict).
#
#   scripts/crash_soak.sh BUILD_DIR [KILLS]      (KILLS: 100 by default; ctest runs 4)
#
# The kill points are drawn from a seeded generator (FLARELAB_SOAK_SEED, default 1) between 0 and
# 1.5 s after the daemon answers, so some land in its start, some in a head move, an exposure, a
# merge, a write or a flush. Each sweep is 16 frames (0 to 3 degrees in 0.2 degree steps) of 64 x 43
# pixels with a two-exposure bracket, about 5 s uninterrupted; a new one starts whenever none is
# left. Quarantine is off (--quarantine-after 0): a kill before a job writes a frame is what this
# soak does on purpose, not a job that crashes the daemon. Prints the result and its timing; exits 1
# when a frame is missing, doubled or different, or a job did not succeed.
set -euo pipefail
if (($# < 1 || $# > 2)); then
    echo "usage: $0 BUILD_DIR [KILLS]" >&2
    exit 2
fi
build=$(realpath "$1")
kills=${2:-100}
source_dir=$(cd "$(dirname "$0")/.." && pwd)
flarelabd=$build/apps/flarelabd
flarelab=$build/apps/flarelab
for binary in "$flarelabd" "$flarelab"; do
    [[ -x $binary ]] || { echo "crash_soak: $binary is not built" >&2; exit 2; }
done
RANDOM=${FLARELAB_SOAK_SEED:-1}
work=$(mktemp -d "${TMPDIR:-/tmp}/flarelab-soak-XXXXXX")
state=$work/state
socket=$state/flarelabd.sock
log=$work/flarelabd.log
pid=
cleanup() {
    [[ -n $pid ]] && kill -9 "$pid" 2>/dev/null && wait "$pid" 2>/dev/null
    if [[ ${status:-1} == 0 && -z ${FLARELAB_SOAK_KEEP:-} ]]; then rm -rf "$work"; else echo "crash_soak: kept $work" >&2; fi
}
trap cleanup EXIT
sweep=(--sim --lens "$source_dir/data/lenses/heliar-tronnier.csv" --from 0 --to 3 --step 0.2
       --brackets 0.01,0.04 --width 64 --height 43 --seed 7)
frames_per_sweep=16

start_daemon() {
    "$flarelabd" --state-dir "$state" --quarantine-after 0 --log-level warn 2>>"$log" &
    pid=$!
    for _ in $(seq 1 500); do
        if "$flarelab" rig status --socket "$socket" >/dev/null 2>&1; then return 0; fi
        kill -0 "$pid" 2>/dev/null || { echo "crash_soak: flarelabd exited; its log:" >&2; tail -20 "$log" >&2; exit 1; }
        sleep 0.02
    done
    echo "crash_soak: flarelabd does not answer on $socket" >&2
    exit 1
}

# "id state" per job.
job_states() {
    "$flarelab" job list --json --socket "$socket" |
        python3 -c 'import json,sys
for j in json.load(sys.stdin).get("jobs", []): print(j["id"], j.get("state", "?"))'
}

sweeps=0
start_sweep() {
    sweeps=$((sweeps + 1))
    "$flarelab" sweep start --socket "$socket" "${sweep[@]}" -o "$state/output/soak/s$sweeps" >/dev/null
}

started=$(date +%s.%N)
start_daemon
start_sweep
for ((k = 1; k <= kills; k++)); do
    sleep "$(printf '0.%03d' $((RANDOM % 1000)))" "$(printf '0.%03d' $((RANDOM % 500)))"
    kill -9 "$pid"
    wait "$pid" 2>/dev/null || true
    start_daemon
    if ! grep -qv ' SUCCEEDED$' <<<"$(job_states)"; then start_sweep; fi
done
killed=$(date +%s.%N)

# Every sweep to its end, uninterrupted now.
deadline=$((SECONDS + 300))
while grep -qE ' (QUEUED|RUNNING)$' <<<"$(job_states)"; do
    ((SECONDS < deadline)) || { echo "crash_soak: the sweeps did not finish" >&2; exit 1; }
    sleep 0.2
done
if grep -qv ' SUCCEEDED$' <<<"$(job_states)"; then
    echo "crash_soak: FAILED: not every job succeeded:" >&2
    job_states >&2
    exit 1
fi
# The same sweeps, uninterrupted, in simulated time.
for ((n = 1; n <= sweeps; n++)); do
    "$flarelab" sweep start --socket "$socket" "${sweep[@]}" --fast -o "$state/output/reference/s$n" >/dev/null
done
while grep -qE ' (QUEUED|RUNNING)$' <<<"$(job_states)"; do sleep 0.1; done
kill "$pid"
wait "$pid" || true
pid=

frames=0
problems=0
for ((n = 1; n <= sweeps; n++)); do
    soaked=$state/output/soak/s$n
    reference=$state/output/reference/s$n
    info=$("$flarelab" sweep info "$soaked" --check --strict --json) || {
        echo "crash_soak: $soaked does not read back whole" >&2
        problems=$((problems + 1))
        continue
    }
    # Every angle exactly once, all of them, in order.
    if ! python3 -c 'import json,sys
a = json.loads(sys.argv[1])["angles_deg"]
want = [round(0.2 * i, 9) for i in range(int(sys.argv[2]))]
sys.exit(0 if [round(x, 9) for x in a] == want else 1)' "$info" "$frames_per_sweep"; then
        echo "crash_soak: $soaked: angles missing, doubled or out of place" >&2
        problems=$((problems + 1))
    fi
    # Byte for byte the uninterrupted run's frames (and no other EXR file).
    mapfile -t exrs < <(cd "$reference" && ls ./*.exr)
    mapfile -t soaked_exrs < <(cd "$soaked" && ls ./*.exr)
    if [[ "${exrs[*]}" != "${soaked_exrs[*]}" ]]; then
        echo "crash_soak: $soaked: other frame files than the uninterrupted sweep" >&2
        problems=$((problems + 1))
    fi
    for exr in "${exrs[@]}"; do
        frames=$((frames + 1))
        cmp -s "$reference/$exr" "$soaked/$exr" || {
            echo "crash_soak: $soaked/$exr differs from the uninterrupted sweep's" >&2
            problems=$((problems + 1))
        }
    done
done
finished=$(date +%s.%N)
set_aside=0
[[ -d $state/recovered ]] && set_aside=$(find "$state/recovered" -type f | wc -l)
python3 - "$kills" "$sweeps" "$frames" "$problems" "$started" "$killed" "$finished" "$set_aside" <<'EOF'
import sys
kills, sweeps, frames, problems = map(int, sys.argv[1:5])
started, killed, finished = map(float, sys.argv[5:8])
print(f"crash_soak: {kills} kill -9, {sweeps} sweeps, {frames} frames compared with an "
      f"uninterrupted run: {frames - problems if problems <= frames else 0} identical, "
      f"{problems} problem(s); {sys.argv[8]} unlisted file(s) set aside; "
      f"kills {killed - started:.1f} s, total {finished - started:.1f} s")
EOF
if ((problems > 0)); then
    echo "crash_soak: FAILED" >&2
    exit 1
fi
status=0
echo "crash_soak: passed"
