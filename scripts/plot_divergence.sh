#!/usr/bin/env bash
# Plots how far paraxial ghost centres stray from the exact ones: the median and the maximum
# over each lens's ghosts, in % of the sensor half-diagonal, against the light angle.
#   scripts/plot_divergence.sh CSV PNG
# CSV is what `ghost_divergence --csv` writes. Log-log axes: a third-order aberration is then a
# straight line of slope 3, drawn for reference, and the 0.5 % tolerance a horizontal one.
set -euo pipefail
if (($# != 2)); then
    echo "usage: $0 CSV PNG" >&2
    exit 2
fi
csv=$1
png=$2
[[ -r $csv ]] || { echo "plot_divergence: cannot read $csv" >&2; exit 1; }
command -v gnuplot >/dev/null || { echo "plot_divergence: gnuplot is not installed" >&2; exit 1; }

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# One file per lens: theta, median, max. Column 8 is the centre divergence; it is empty where a
# model could not trace the ghost, and zero on the axis, where a log axis has no place for it.
tail -n +2 "$csv" | awk -F, '$8 != "" && $5 > 0 { print $1, $5, $8 }' |
    sort -k1,1 -k2,2g -k3,3g |
    awk -v dir="$work" '
        function flush() {
            if (n == 0) return
            median = n % 2 ? v[(n + 1) / 2] : (v[n / 2] + v[n / 2 + 1]) / 2
            print theta, median, v[n] >> (dir "/" lens ".dat")
            close(dir "/" lens ".dat")
            n = 0
        }
        $1 != lens || $2 != theta { flush(); lens = $1; theta = $2 }
        { v[++n] = $3 }
        END { flush() }'

lenses=()
for f in "$work"/*.dat; do
    [[ -e $f ]] || { echo "plot_divergence: no traced ghosts in $csv" >&2; exit 1; }
    lenses+=("$(basename "$f" .dat)")
done

# Pick the first terminal this gnuplot has: pngcairo draws smoother lines, png is always there.
terminal="pngcairo size 1400,1000 font 'DejaVu Sans,12'"
if ! gnuplot -e "set terminal pngcairo" 2>/dev/null; then
    terminal="png size 1400,1000 font 'DejaVuSans,11'"
fi

series() {  # series COLUMN: one plot clause per lens
    local column=$1 i=0 out=""
    for lens in "${lenses[@]}"; do
        out+="'$work/$lens.dat' using 1:$column with linespoints ls $((i % 9 + 1)) title '$lens', "
        i=$((i + 1))
    done
    echo "$out"
}

gnuplot <<EOF
set terminal $terminal
set output '$png.tmp'
set multiplot layout 1,2 title 'Paraxial vs exact ghost centre, 550 nm, phi = 0 (ghost\_divergence --csv)' font ',15'
set logscale xy
set xrange [0.2:35]
set yrange [1e-6:1e4]
set format y '10^{%L}'
set xtics (0.25, 0.5, 1, 2, 3, 5, 10, 20, 30)
set grid xtics ytics mytics lc rgb '#dddddd'
set xlabel 'light angle theta (deg)'
set ylabel 'centre divergence (% of sensor half-diagonal)'
set key top left font ',10' spacing 1.1
set style line 1 lc rgb '#1f77b4' lw 2 pt 7 ps 0.8
set style line 2 lc rgb '#ff7f0e' lw 2 pt 5 ps 0.8
set style line 3 lc rgb '#2ca02c' lw 2 pt 9 ps 0.9
set style line 4 lc rgb '#d62728' lw 2 pt 11 ps 0.9
set style line 5 lc rgb '#9467bd' lw 2 pt 13 ps 0.9
set style line 6 lc rgb '#8c564b' lw 2 pt 7 ps 0.8
set style line 7 lc rgb '#e377c2' lw 2 pt 5 ps 0.8
set style line 8 lc rgb '#7f7f7f' lw 2 pt 9 ps 0.9
set style line 9 lc rgb '#17becf' lw 2 pt 11 ps 0.9
set style line 20 lc rgb '#000000' lw 1.5 dt 2
set style line 21 lc rgb '#000000' lw 1 dt 3
tolerance(x) = 0.5
cubic(x) = 1e-3 * x**3
set title 'median over ghosts'
plot $(series 2) tolerance(x) ls 20 title '0.5 % tolerance', cubic(x) ls 21 title 'slope 3 (theta^3)'
set title 'maximum over ghosts'
unset key
plot $(series 3) tolerance(x) ls 20 notitle, cubic(x) ls 21 notitle
unset multiplot
EOF
mv "$png.tmp" "$png"
echo "plot_divergence: wrote $png"
