#!/usr/bin/env bash
# Plots the renderer's speed against its accuracy: total time against PSNR for each base grid
# size, one line per merge level, from the "trade" array of `flarelab bench render --json`.
#   scripts/plot_render_trade.sh JSON PNG
set -euo pipefail
if (($# != 2)); then
    echo "usage: $0 JSON PNG" >&2
    exit 2
fi
json=$1
png=$2
[[ -r $json ]] || { echo "plot_render_trade: cannot read $json" >&2; exit 1; }
command -v gnuplot >/dev/null || { echo "plot_render_trade: gnuplot is not installed" >&2; exit 1; }

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
python3 - "$json" "$work" <<'PY'
import json, sys
doc = json.load(open(sys.argv[1]))
rows = doc.get("trade", [])
if not rows:
    sys.exit("plot_render_trade: the document has no trade table (run without --quick/--no-trade)")
for merge in ("none", "light", "heavy"):
    with open(f"{sys.argv[2]}/{merge}.dat", "w") as f:
        for r in rows:
            if r["merge"] == merge and r["psnr_db"] is not None:
                f.write(f'{r["total_ms"]} {r["psnr_db"]} {r["grid"]}\n')
PY
gnuplot <<GP
set terminal pngcairo size 900,560 font ",11"
set output "$png.tmp"
set title "Tiled renderer, Nikon tele 5 deg, 960x540: time against PSNR (against base grid 1024, no merge)"
set xlabel "total time (ms, log scale)"
set ylabel "PSNR (dB)"
set logscale x
set grid
set key bottom right
plot "$work/none.dat" using 1:2 with linespoints lw 2 pt 7 title "no merge", \
     "$work/light.dat" using 1:2 with linespoints lw 2 pt 5 title "light merge (4 steps, sine 0.001)", \
     "$work/heavy.dat" using 1:2 with linespoints lw 2 pt 9 title "heavy merge (4 steps, sine 0.1)", \
     "$work/none.dat" using 1:2:(sprintf("grid %d", \$3)) with labels offset 0,1 notitle
GP
mv "$png.tmp" "$png"
echo "plot_render_trade: wrote $png"
