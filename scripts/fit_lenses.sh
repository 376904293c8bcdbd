#!/usr/bin/env bash
# Fits and scores every shipped lens on the simulated rig by the sparse protocol: a sweep 0 to 30
# deg in 0.2 deg steps at 640 x 427, with the brackets capture plans (so that no frame clips), is
# captured, one frame in every
# EVERY (default 5) is fitted (flarelab fit --every), and the model is scored against the
# simulator's noiseless ghosts at the frames the fit left out, at half-way and random angles, and
# at fitted ones (flarelab score --sweep). EVERY=1 fits every frame (then no frame is left out and
# the held-out angles are the half-way and random ones). Writes out/bench/fit-lenses.md (a
# Markdown table) and one JSON score per lens beside it. About 1 to 2 minutes per lens on 2
# cores with EVERY=5. BRACKETS (seconds, comma-separated) gives fixed brackets instead (the
# tables before 2026-12-03 used 0.25,1,4, which saturate much of the frames of the double Gauss,
# the Nikon 28-75 and, near the axis, the zooms). KEEP=DIR keeps each lens's sweep and model there.
# PATHS=1 fits with the prescription's ghost paths as seeds (flarelab fit --paths). FORMAT=bayer-rggb
# captures in colour (the simulated camera's Bayer mosaic; fitted and scored in colour), FORMAT=mono
# (the default) with the monochrome camera. The left-out frames are also scored against the
# captured frames themselves (flarelab score --measured, what a lab without the prescription has):
# the table's "measured" column, fit-LENS.measured.json.
#   [EVERY=5] [BRACKETS=0.25,1,4] [PATHS=1] [FORMAT=mono|bayer-rggb] [KEEP=DIR] \
#       scripts/fit_lenses.sh [BUILD_DIR] [LENS.csv ...]
set -euo pipefail
build=$(realpath -m "${1:-build/release}")
shift || true
cd "$(dirname "$0")/.."
out=${FLARELAB_OUT:-out}/bench
every=${EVERY:-5}
mkdir -p "$out"
lenses=("$@")
if ((${#lenses[@]} == 0)); then lenses=(data/lenses/*.csv); fi
table="$out/fit-lenses.md"
{
    echo "Fit one frame in every $every${PATHS:+, tracks seeded from the lens prescription (--paths)}; held out: the frames left out, half-way and random angles; brackets ${BRACKETS:-as capture plans them}; camera ${FORMAT:-mono}."
    echo
    echo "| lens | ghosts in model | fit time (s) | held-out rel L2 median | worst (angle) | held-out abs energy error median | held-out log rel L2 median | left-out rel L2 median | the same, measured | fitted angles median |"
    echo "|---|---|---|---|---|---|---|---|---|---|"
} >"$table"
for lens in "${lenses[@]}"; do
    name=$(basename "$lens" .csv)
    work=$(mktemp -d)
    brackets=()
    if [[ -n ${BRACKETS:-} ]]; then brackets=(--brackets "$BRACKETS"); fi
    "$build/apps/flarelab" capture --sim --fast --format "${FORMAT:-mono}" --lens "$lens" \
        --from 0 --to 30 --step 0.2 "${brackets[@]}" --width 640 --height 427 -o "$work/sweep" \
        >/dev/null
    start=$(date +%s.%N)
    paths=()
    if [[ -n ${PATHS:-} ]]; then paths=(--paths); fi
    "$build/apps/flarelab" fit "$work/sweep" --lens "$lens" --every "$every" "${paths[@]}" \
        -o "$work/model.flm" --quiet >"$work/fit.txt"
    end=$(date +%s.%N)
    "$build/apps/flarelab" score "$work/model.flm" --lens "$lens" --sweep "$work/sweep" --json \
        >"$out/fit-$name.json" 2>"$work/score.err" || { cat "$work/score.err" >&2; exit 1; }
    "$build/apps/flarelab" score "$work/model.flm" --measured --sweep "$work/sweep" --json \
        >"$out/fit-$name.measured.json" 2>"$work/score.err" || { cat "$work/score.err" >&2; exit 1; }
    ghosts=$(sed -n 's/^fit: \([0-9]*\) ghosts.*/\1/p' "$work/fit.txt")
    python3 - "$out/fit-$name.json" "$name" "$ghosts" "$start" "$end" "$out/fit-$name.measured.json" \
        >>"$table" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
h, f = s["heldout_rel_l2"], s["fit_rel_l2"]
left = s["by_kind"].get("left-out")
left = f"{left['median']:.3f}" if left else "-"
measured = json.load(open(sys.argv[6]))["by_kind"].get("left-out")
measured = f"{measured['median']:.3f}" if measured else "-"
t = float(sys.argv[5]) - float(sys.argv[4])
print(f"| {sys.argv[2]} | {sys.argv[3]} | {t:.0f} | {h['median']:.3f} | {h['worst']:.3f} ({h['worst_angle_deg']:.2f} deg) "
      f"| {100 * h['median_abs_energy_error']:.1f} % | {h['median_log_rel_l2']:.3f} | {left} | {measured} | {f['median']:.3f} |")
PY
    tail -1 "$table"
    if [[ -n ${KEEP:-} ]]; then
        mkdir -p "$KEEP/$name"
        mv "$work/sweep" "$work/model.flm" "$KEEP/$name/"
    fi
    rm -rf "$work"
done
echo "fit_lenses: $table"
