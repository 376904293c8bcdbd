#!/usr/bin/env bash
# The main job on the built-in simulated rig, as far as the project has come: for every shipped
# lens, its first-order report and its ghosts at a few light angles, written under out/lenses/.
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
cat "$out/lenses/heliar-tronnier.txt"
