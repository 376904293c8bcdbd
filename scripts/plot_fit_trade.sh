#!/usr/bin/env bash
# Plots the fitting backend's speed against its accuracy: fit time against the held-out relative
# L2 median, one point per setting of each knob (the defaults marked), from the "trade" array of
# `flarelab bench fit --json`.
#   scripts/plot_fit_trade.sh JSON PNG
set -euo pipefail
if (($# != 2)); then
    echo "usage: $0 JSON PNG" >&2
    exit 2
fi
json=$1
png=$2
[[ -r $json ]] || { echo "plot_fit_trade: cannot read $json" >&2; exit 1; }
command -v gnuplot >/dev/null || { echo "plot_fit_trade: gnuplot is not installed" >&2; exit 1; }

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
python3 - "$json" "$work" <<'PY'
import json, re, sys
doc = json.load(open(sys.argv[1]))
rows = doc.get("trade", [])
if not rows:
    sys.exit("plot_fit_trade: the document has no trade table (run without --no-trade)")
knobs = []
for r in rows:
    if r["knob"] not in knobs:
        knobs.append(r["knob"])
with open(f"{sys.argv[2]}/knobs.txt", "w") as k:
    for i, knob in enumerate(knobs):
        with open(f"{sys.argv[2]}/{i}.dat", "w") as f:
            for r in rows:
                if r["knob"] == knob:
                    label = "defaults" if knob == "baseline" else r["setting"]
                    f.write(f'{r["fit_s"]} {r["heldout_median"]} "{label}"\n')
        k.write(f"{i}\t{knob}\n")
PY
plots=""
while IFS=$'\t' read -r i knob; do
    [[ -n $plots ]] && plots+=", "
    plots+="\"$work/$i.dat\" using 1:2 with linespoints lw 2 pt 7 ps 1.3 title \"$knob\""
    plots+=", \"$work/$i.dat\" using 1:2:3 with labels offset 0,0.9 font \",9\" notitle"
done <"$work/knobs.txt"
gnuplot <<GP
set terminal pngcairo size 960,600 font ",11"
set output "$png.tmp"
set title "flarelab fit, Heliar Tronnier 0-30 deg, 640x427: fit time against held-out error"
set xlabel "fit time (s)"
set ylabel "held-out relative L2, median of 20 angles"
set grid
set key outside right
plot $plots
GP
mv "$png.tmp" "$png"
echo "plot_fit_trade: wrote $png"
