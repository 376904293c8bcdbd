#!/usr/bin/env bash
# Records the small sweeps the tests replay (tests/data/sweeps/), with the simulated rig:
#   heliar-raw:  Heliar, 0 to 2 deg in 0.5 deg steps, brackets 0.25/1/4 s, 160x107, raw kept
#   nikon-hdr:   Nikon tele, 0 to 1 deg in 0.5 deg steps, the same brackets, 160x107, HDR only
# Run it again (and commit the result) when the sweep, raw or EXR format changes.
#   scripts/make_test_sweeps.sh BUILD_DIR
set -euo pipefail
if (($# != 1)); then
    echo "usage: $0 BUILD_DIR" >&2
    exit 2
fi
build=$(realpath -m "$1")
cd "$(dirname "$0")/.."
out=tests/data/sweeps
rm -rf "$out/heliar-raw" "$out/nikon-hdr"
mkdir -p "$out"
"$build/apps/flarelab" capture --sim --fast --lens data/lenses/heliar-tronnier.csv \
    --from 0 --to 2 --step 0.5 --width 160 --height 107 --seed 7 --keep-raw -o "$out/heliar-raw"
"$build/apps/flarelab" capture --sim --fast --lens data/lenses/nikon-tele-zoom.csv \
    --from 0 --to 1 --step 0.5 --width 160 --height 107 --seed 8 -o "$out/nikon-hdr"
du -sh "$out"
