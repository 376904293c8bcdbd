#!/bin/bash
# Whole simulated frames of several flarelab builds, side by side: each lens is rendered by every
# build in turn, ROUNDS times over, and the best total (the render's own time, from the summary
# line `simulate` prints) is kept per build. Running the builds alternately in one go is what
# makes their figures comparable on a shared, noisy machine.
#
#   bench/simulate_side_by_side.sh [--rounds N] [--adaptive] BUILD... -- LENS.csv...
#
# BUILD is a flarelab binary (for example build/release/apps/flarelab, and one built from an
# older commit in a git worktree). Renders 1920x1080 at 5 deg, roll 30 deg, no starburst, light
# merge (the README's "Renderer: measured" command); --adaptive adds --adaptive-grid for builds
# that have it. Prints one line per run and a table of the best totals in ms.
set -euo pipefail
rounds=3
extra=()
builds=()
while [[ $# -gt 0 && "$1" != "--" ]]; do
    case "$1" in
        --rounds) rounds="$2"; shift 2 ;;
        --adaptive) extra+=(--adaptive-grid); shift ;;
        *) builds+=("$1"); shift ;;
    esac
done
[[ "${1:-}" == "--" ]] && shift
lenses=("$@")
if [[ ${#builds[@]} -eq 0 || ${#lenses[@]} -eq 0 ]]; then
    echo "usage: $0 [--rounds N] [--adaptive] BUILD... -- LENS.csv..." >&2
    exit 2
fi
for b in "${builds[@]}"; do
    [[ -x "$b" ]] || { echo "$0: $b is not an executable flarelab" >&2; exit 2; }
done
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
declare -A best
for ((r = 1; r <= rounds; ++r)); do
    for lens in "${lenses[@]}"; do
        for i in "${!builds[@]}"; do
            line=$("${builds[$i]}" simulate --lens "$lens" --angle 5 --roll 30 --no-starburst \
                       --merge light "${extra[@]}" -o "$out/frame.exr" 2>&1 | tail -1)
            total_s=$(sed -n 's/.*total \([0-9.]*\) s.*/\1/p' <<<"$line")
            if [[ -z "$total_s" ]]; then
                echo "$0: no timing from ${builds[$i]} on $lens: $line" >&2
                exit 1
            fi
            ms=$(awk -v s="$total_s" 'BEGIN { printf "%.1f", s * 1000 }')
            echo "round $r  $(basename "$lens" .csv)  build $i  $(grep -o 'trace.*s ->' <<<"$line" | sed 's/ ->//')"
            key="$lens|$i"
            if [[ -z "${best[$key]:-}" ]] || awk -v a="$ms" -v b="${best[$key]}" 'BEGIN { exit !(a < b) }'; then
                best[$key]=$ms
            fi
        done
    done
done
echo
printf '| lens |'; for i in "${!builds[@]}"; do printf ' build %s ms |' "$i"; done; echo
printf '|---|'; for i in "${!builds[@]}"; do printf -- '---:|'; done; echo
for lens in "${lenses[@]}"; do
    printf '| %s |' "$(basename "$lens" .csv)"
    for i in "${!builds[@]}"; do printf ' %s |' "${best[$lens|$i]}"; done
    echo
done
for i in "${!builds[@]}"; do echo "build $i: ${builds[$i]}"; done
