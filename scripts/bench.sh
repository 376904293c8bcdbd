#!/usr/bin/env bash
# The optics benchmarks, the paraxial-versus-exact ghost report, adaptive grids against whole ones,
# the renderer benchmark (flarelab bench render) and the bracket merge benchmark (flarelab bench
# merge), written under out/bench/.
#   scripts/bench.sh BUILD_DIR [--quick]
# The renderer benchmark takes about an hour on 2 cores and the adaptive-grid one about 20 minutes;
# --quick runs their smoke versions.
# optics_bench runs every benchmark five times and the summary keeps the fastest repetition of
# each: on a shared machine noise only ever slows a run down, so the best one is the closest to
# what the code costs. Ratios are to the textbook sphere intersection of the same run.
# --quick: two repetitions of 0.05 s each, to check that everything runs.
set -euo pipefail
if (($# < 1 || $# > 2)) || { (($# == 2)) && [[ $2 != --quick ]]; }; then
    echo "usage: $0 BUILD_DIR [--quick]" >&2
    exit 2
fi
build=$(realpath -m "$1")  # before the cd below, so a relative BUILD_DIR keeps its meaning
repetitions=5
min_time=0.5
if [[ ${2:-} == --quick ]]; then
    repetitions=2
    min_time=0.05
fi
cd "$(dirname "$0")/.."
out=${FLARELAB_OUT:-out}/bench
mkdir -p "$out"
for tool in bench/optics_bench bench/quad_bench bench/model_ghost_bench bench/ghost_divergence \
    bench/adaptive_grid_bench bench/sun_bench apps/flarelab; do
    if [[ ! -x $build/$tool ]]; then
        echo "bench: $build/$tool is missing (a sanitizer build has no benchmarks)" >&2
        exit 1
    fi
done

echo "bench: optics_bench, $repetitions repetitions of at least $min_time s each"
"$build/bench/optics_bench" \
    --benchmark_repetitions="$repetitions" \
    --benchmark_report_aggregates_only=false \
    --benchmark_min_time="$min_time" \
    --benchmark_out="$out/optics_bench.json.tmp" \
    --benchmark_out_format=json
mv "$out/optics_bench.json.tmp" "$out/optics_bench.json"

# The renderer's kernels (issue 19): quads and the area integration, model playback; the sun's
# position and timelines (issue 21).
for kernels in quad_bench model_ghost_bench sun_bench; do
    echo "bench: $kernels, $repetitions repetitions of at least $min_time s each"
    "$build/bench/$kernels" \
        --benchmark_repetitions="$repetitions" \
        --benchmark_min_time="$min_time" \
        --benchmark_out="$out/$kernels.json.tmp" \
        --benchmark_out_format=json
    mv "$out/$kernels.json.tmp" "$out/$kernels.json"
done

python3 - "$out/optics_bench.json" "$out/optics_bench.md" <<'EOF'
import json, os, sys

with open(sys.argv[1]) as f:
    doc = json.load(f)
best = {}
for b in doc["benchmarks"]:
    if b.get("run_type") != "iteration":
        continue
    name = b["run_name"]
    if name not in best or b["items_per_second"] > best[name]["items_per_second"]:
        best[name] = b
baseline = best.get("BM_IntersectSphereTextbook", {}).get("items_per_second")
ctx = doc["context"]
lines = [
    f"Fastest of each benchmark's repetitions; {ctx['host_name']}, {ctx['num_cpus']} CPUs at "
    f"{ctx['mhz_per_cpu']} MHz, {ctx['date']}, Google Benchmark library built as "
    f"{ctx.get('library_build_type', '?')} (its timing loop only; flarelab is built as the "
    "build directory says)",
    "",
    "| benchmark | intersections/s | vs textbook | rays/s | per ray | path |",
    "| --- | ---: | ---: | ---: | ---: | --- |",
]
for name, b in best.items():
    ratio = f"{b['items_per_second'] / baseline:.3f}" if baseline else "-"
    per_ray = f"{b['per_ray']:.0f}" if "per_ray" in b else "-"
    lines.append(
        f"| {name} | {b['items_per_second'] / 1e6:.2f} M | {ratio} | "
        f"{b['rays_per_s'] / 1e6:.3f} M | {per_ray} | {b.get('label', '')} |"
    )
text = "\n".join(lines) + "\n"
with open(sys.argv[2] + ".tmp", "w") as f:
    f.write(text)
os.replace(sys.argv[2] + ".tmp", sys.argv[2])
print()
print(text, end="")
EOF

echo
echo "bench: ghost_divergence (every shipped lens, 13 angles)"
"$build/bench/ghost_divergence" --csv "$out/ghost_divergence.csv" \
    --json "$out/ghost_divergence.json" >"$out/ghost_divergence.md.tmp"
mv "$out/ghost_divergence.md.tmp" "$out/ghost_divergence.md"
sed -n '/^## Acceptance/,/^\(PASS\|FAIL\)/p' "$out/ghost_divergence.md"

scripts/plot_divergence.sh "$out/ghost_divergence.csv" "$out/ghost_divergence.png"
echo "bench: wrote $out/optics_bench.{json,md} and $out/ghost_divergence.{md,csv,json,png}"

# Adaptive ray grids against the whole grid, every shipped lens (about 20 minutes on 2 cores;
# --quick: two lenses at 640x360, one run each).
echo "bench: adaptive_grid_bench"
if [[ ${2:-} == --quick ]]; then
    adaptive_args=(--width 640 --height 360 --repeat 1 data/lenses/heliar-tronnier.csv
        data/lenses/lensbaby-toy.csv)
else
    adaptive_args=(--repeat 3)
fi
"$build/bench/adaptive_grid_bench" "${adaptive_args[@]}" --json "$out/adaptive_grid.json.tmp" \
    >"$out/adaptive_grid.md.tmp"
mv "$out/adaptive_grid.json.tmp" "$out/adaptive_grid.json"
mv "$out/adaptive_grid.md.tmp" "$out/adaptive_grid.md"
echo "bench: wrote $out/adaptive_grid.{md,json}"

echo
echo "bench: flarelab bench render${2:+ $2} (progress on stderr)"
"$build/apps/flarelab" bench render ${2:+"$2"} --json "$out/render.json.tmp" >"$out/render.md.tmp"
mv "$out/render.json.tmp" "$out/render.json"
mv "$out/render.md.tmp" "$out/render.md"
cat "$out/render.md"
if [[ ${2:-} != --quick ]]; then
    scripts/plot_render_trade.sh "$out/render.json" "$out/render_trade.png"
fi
echo "bench: wrote $out/render.{md,json}"

echo
echo "bench: flarelab bench merge${2:+ $2}"
"$build/apps/flarelab" bench merge ${2:+"$2"} --json "$out/merge.json.tmp" >"$out/merge.md.tmp"
mv "$out/merge.json.tmp" "$out/merge.json"
mv "$out/merge.md.tmp" "$out/merge.md"
cat "$out/merge.md"
echo "bench: wrote $out/merge.{md,json}"
