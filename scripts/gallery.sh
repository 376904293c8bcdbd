#!/usr/bin/env bash
# Flare images of every shipped lens at a few light angles, for people to look at: one white
# light at roll -30 deg, 480x320 (the 36x24 mm sensor), base grid 128, light merge, with the
# starburst, tone-mapped at +14 stops.
#   scripts/gallery.sh BUILD_DIR OUT_DIR
set -euo pipefail
if (($# != 2)); then
    echo "usage: $0 BUILD_DIR OUT_DIR" >&2
    exit 2
fi
build=$(realpath -m "$1")
out=$(realpath -m "$2")
cd "$(dirname "$0")/.."
mkdir -p "$out"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
for lens in data/lenses/*.csv; do
    name=$(basename "$lens" .csv)
    for angle in 2 10 25; do
        "$build/apps/flarelab" simulate --lens "$lens" --angle "$angle" --roll -30 \
            --width 480 --height 320 --grid 128 --merge light --exposure-stops 14 \
            -o "$work/$name-$angle.exr" --png "$out/$name-$angle.png" >/dev/null
    done
    echo "gallery: $name"
done
