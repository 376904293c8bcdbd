#!/usr/bin/env bash
# The main job on the built-in simulated rig, as far as the project has come: for every shipped
# lens, its first-order report and its ghosts at a few light angles (out/lenses/), flare images of
# two lenses (out/images/, OpenEXR and PNG), and a sweep of the simulated rig: the Heliar from 0
# to 30 degrees in 0.2 degree steps, three brackets per step merged to HDR (out/sweeps/heliar/,
# with a PNG preview of every frame), then that sweep fitted into a flare model (out/models/:
# the model file, its description, its score against the simulator's noiseless ghosts, and the
# model drawn at a few angles, captured and in between).
set -euo pipefail
build=${1:-build/release}
out=${FLARELAB_OUT:-out}
mkdir -p "$out/lenses"
for lens in data/lenses/*.csv; do
    name=$(basename "$lens" .csv)
    "$build/apps/flarelab" lens show "$lens" >"$out/lenses/$name.txt"
    "$build/apps/flarelab" lens show "$lens" --json >"$out/lenses/$name.json"
    for angle in 0 5 15; do
        "$build/apps/flarelab" lens ghosts "$lens" --angle "$angle" \
            >"$out/lenses/$name.ghosts-$angle.txt"
        "$build/apps/flarelab" lens ghosts "$lens" --angle "$angle" --json \
            >"$out/lenses/$name.ghosts-$angle.json"
    done
    echo "demo: $name -> $out/lenses/$name.{txt,json}, ghosts at 0/5/15 deg"
done
mkdir -p "$out/images"
for shot in heliar-tronnier:5:20 itoh-wide-zoom:8:-30; do
    IFS=: read -r name angle roll <<<"$shot"
    "$build/apps/flarelab" simulate --lens "data/lenses/$name.csv" --angle "$angle" --roll "$roll" \
        --width 960 --height 640 --grid 128 --exposure-stops 14 \
        -o "$out/images/$name-$angle.exr" --png "$out/images/$name-$angle.png"
done
rm -rf "$out/sweeps/heliar" "$out/sweeps/heliar-previews"
"$build/apps/flarelab" capture --sim --fast --lens data/lenses/heliar-tronnier.csv \
    --from 0 --to 30 --step 0.2 --brackets 0.25,1,4 --width 640 --height 427 \
    --previews "$out/sweeps/heliar-previews" --preview-stops -12 -o "$out/sweeps/heliar"
"$build/apps/flarelab" sweep info "$out/sweeps/heliar"
cat "$out/lenses/heliar-tronnier.txt"
mkdir -p "$out/models"
heliar=data/lenses/heliar-tronnier.csv
"$build/apps/flarelab" fit "$out/sweeps/heliar" --lens "$heliar" -o "$out/models/heliar.flm"
"$build/apps/flarelab" model show "$out/models/heliar.flm" >"$out/models/heliar.txt"
"$build/apps/flarelab" score "$out/models/heliar.flm" --lens "$heliar" --json \
    >"$out/models/heliar.score.json"
"$build/apps/flarelab" score "$out/models/heliar.flm" --lens "$heliar" |
    tee "$out/models/heliar.score.txt"
for angle in 5 12.3 20; do
    "$build/apps/flarelab" model render "$out/models/heliar.flm" --angle "$angle" \
        -o "$out/models/heliar-$angle.exr" --png "$out/models/heliar-$angle.png" --exposure-stops -12
done
echo "demo: model $out/models/heliar.flm (described in heliar.txt, scored in heliar.score.txt)"
