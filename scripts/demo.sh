#!/usr/bin/env bash
# The main job on the built-in simulated rig, as far as the project has come: for every shipped
# lens, its first-order report and its ghosts at a few light angles (out/lenses/), flare images of
# two lenses (out/images/, OpenEXR and PNG), and a sweep of the simulated rig: the Heliar from 0
# to 30 degrees in 0.2 degree steps, three brackets per step merged to HDR and fitted into a
# flare model, run as one job of the rig daemon flarelabd (out/sweeps/heliar/: the frames, a PNG
# preview of each in previews/, model.flm and its description model.txt), then the model's score
# against the simulator's noiseless ghosts and the model drawn at a few angles, captured and in
# between (out/models/).
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
# The rig daemon runs the sweep and its fit as one job: flarelabd on the simulated rig, driven
# through its socket by the flarelab client, then stopped with SIGTERM.
heliar=data/lenses/heliar-tronnier.csv
state=$(realpath -m "$out/flarelabd")
if ((${#state} > 80)); then  # a Unix socket path holds at most 107 bytes
    state=$(mktemp -d /tmp/flarelabd-demo-XXXXXX)
fi
export FLARELAB_SOCKET=$state/flarelabd.sock
export FLARELAB_CLIENT=demo
rm -rf "$out/sweeps/heliar" "$out/sweeps/heliar-previews"
mkdir -p "$out/sweeps"
"$build/apps/flarelabd" --state-dir "$state" --output-root "$out" 2>"$out/flarelabd.log" &
daemon=$!
trap 'kill $daemon 2>/dev/null || true' EXIT
for _ in $(seq 200); do
    [[ -S $FLARELAB_SOCKET ]] && break
    kill -0 $daemon 2>/dev/null || { cat "$out/flarelabd.log" >&2; exit 1; }
    sleep 0.05
done
"$build/apps/flarelab" rig status
"$build/apps/flarelab" sweep start --sim --fast --lens "$heliar" \
    --from 0 --to 30 --step 0.2 --brackets 0.25,1,4 --width 640 --height 427 \
    --previews --preview-stops -12 --fit --watch -o "$out/sweeps/heliar"
"$build/apps/flarelab" job list
kill -TERM $daemon
wait $daemon
trap - EXIT
echo "demo: flarelabd stopped; its log is $out/flarelabd.log, its journal $state/jobs/"
"$build/apps/flarelab" sweep info "$out/sweeps/heliar"
cat "$out/lenses/heliar-tronnier.txt"
mkdir -p "$out/models"
model=$out/sweeps/heliar/model.flm
cp "$out/sweeps/heliar/model.txt" "$out/models/heliar.txt"
"$build/apps/flarelab" score "$model" --lens "$heliar" --json \
    >"$out/models/heliar.score.json"
"$build/apps/flarelab" score "$model" --lens "$heliar" |
    tee "$out/models/heliar.score.txt"
for angle in 5 12.3 20; do
    "$build/apps/flarelab" model render "$model" --angle "$angle" \
        -o "$out/models/heliar-$angle.exr" --png "$out/models/heliar-$angle.png" --exposure-stops -12
done
echo "demo: model $model (described in model.txt beside it and $out/models/heliar.txt, scored in $out/models/heliar.score.txt)"
# A planner's question of the same model: a stadium's cameras, a floodlight and the evening sun
# (data/scenes/stadium.json, its model path relative to it), answered with figures, the sun's
# timeline, a switching plan and frames in a report that opens in a browser.
mkdir -p "$out/predict"
cp data/scenes/stadium.json "$out/predict/stadium.json"
cp "$model" "$out/predict/heliar.flm"
"$build/apps/flarelab" predict "$out/predict/stadium.json" -o "$out/predict/report"
echo "demo: prediction report $out/predict/report/report.html"
