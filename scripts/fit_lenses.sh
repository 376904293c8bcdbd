#!/usr/bin/env bash
# Fits and scores every shipped lens on the simulated rig: a sweep 0 to 30 deg in 0.2 deg steps at
# 640 x 427 with brackets 0.25 / 1 / 4 s is captured, fitted (flarelab fit) and scored against the
# simulator's noiseless ghosts (flarelab score). Writes out/bench/fit-lenses.md (a Markdown table)
# and one JSON score per lens beside it. About 4 minutes per lens on 2 cores. BRACKETS (seconds,
# comma-separated) replaces the brackets: the defaults saturate the whole frame of lenses whose
# ghosts are much brighter (the double Gauss and the Nikon 28-75 need 0.004,0.016,0.064).
#   [BRACKETS=...] scripts/fit_lenses.sh [BUILD_DIR] [LENS.csv ...]
set -euo pipefail
build=$(realpath -m "${1:-build/release}")
shift || true
cd "$(dirname "$0")/.."
out=${FLARELAB_OUT:-out}/bench
mkdir -p "$out"
lenses=("$@")
if ((${#lenses[@]} == 0)); then lenses=(data/lenses/*.csv); fi
table="$out/fit-lenses.md"
{
    echo "| lens | ghosts in model | fit time (s) | held-out rel L2 median | worst (angle) | fitted angles median |"
    echo "|---|---|---|---|---|---|"
} >"$table"
for lens in "${lenses[@]}"; do
    name=$(basename "$lens" .csv)
    work=$(mktemp -d)
    "$build/apps/flarelab" capture --sim --fast --lens "$lens" --from 0 --to 30 --step 0.2 \
        --brackets "${BRACKETS:-0.25,1,4}" --width 640 --height 427 -o "$work/sweep" >/dev/null
    start=$(date +%s.%N)
    "$build/apps/flarelab" fit "$work/sweep" --lens "$lens" -o "$work/model.flm" --quiet >"$work/fit.txt"
    end=$(date +%s.%N)
    "$build/apps/flarelab" score "$work/model.flm" --lens "$lens" --json >"$out/fit-$name.json"
    ghosts=$(sed -n 's/^fit: \([0-9]*\) ghosts.*/\1/p' "$work/fit.txt")
    python3 - "$out/fit-$name.json" "$name" "$ghosts" "$start" "$end" >>"$table" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
h, f = s["heldout_rel_l2"], s["fit_rel_l2"]
t = float(sys.argv[5]) - float(sys.argv[4])
print(f"| {sys.argv[2]} | {sys.argv[3]} | {t:.0f} | {h['median']:.3f} | {h['worst']:.3f} ({h['worst_angle_deg']:.2f} deg) | {f['median']:.3f} |")
PY
    tail -1 "$table"
    rm -rf "$work"
done
echo "fit_lenses: $table"
