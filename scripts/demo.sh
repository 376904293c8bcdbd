#!/usr/bin/env bash
# The main job on the built-in simulated rig, as far as the project has come: for every shipped
# lens, its first-order report and its ghosts at a few light angles (out/lenses/), and flare
# images of two lenses drawn by the reference renderer (out/images/, OpenEXR and PNG).
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
cat "$out/lenses/heliar-tronnier.txt"
