#!/usr/bin/env bash
# A sweep through flarelabd from a GigE Vision camera, over the real protocol:
#
#     scripts/aravis_demo.sh BUILD_DIR [OUT_DIR]
#
# Aravis's fake GigE Vision camera (arv-fake-gv-camera-0.8, package aravis-tools) listens on
# 127.0.0.1 inside a network namespace of this script's own (`unshare -n`: root, or a user
# allowed to make namespaces), so that GigE Vision's discovery broadcasts stay off the real
# network. Then, as a lab would with a real camera:
#   1. flarelab rig devices lists it;
#   2. flarelab calibrate measures it: its response is not linear (its test pattern grows with
#      the logarithm of the exposure), so its curve is recovered and written to a file;
#   3. flarelabd drives it (--camera aravis:127.0.0.1 with a region of interest, the simulated
#      head) with that calibration; flarelab sweep start takes a bracketed sweep, kept raw and
#      merged to HDR OpenEXR; flarelab sweep info reads it back.
# The fake camera draws a moving test pattern, not flare, so no fit is asked of it.
#
# Results under OUT_DIR (default out/aravis): fake.cal.json, flarelabd.log, state/ and the sweep
# in state/output/fake-sweep/. Exits 0 when every step succeeded.
set -euo pipefail

if (($# < 1 || $# > 2)); then
    echo "usage: $0 BUILD_DIR [OUT_DIR]" >&2
    exit 2
fi
build=$(cd "$1" && pwd)
out=$(mkdir -p "${2:-out/aravis}" && cd "${2:-out/aravis}" && pwd)
flarelab=$build/apps/flarelab
flarelabd=$build/apps/flarelabd
for tool in "$flarelab" "$flarelabd"; do
    [[ -x $tool ]] || { echo "aravis_demo: $tool is missing: build first" >&2; exit 1; }
done
command -v arv-fake-gv-camera-0.8 >/dev/null ||
    { echo "aravis_demo: arv-fake-gv-camera-0.8 is missing (Debian: aravis-tools)" >&2; exit 1; }

if [[ ${FLARELAB_IN_NETNS:-} != 1 ]]; then
    if ! unshare -n true 2>/dev/null; then
        echo "aravis_demo: cannot make a network namespace (unshare -n needs root or" \
            "CAP_SYS_ADMIN)" >&2
        exit 1
    fi
    exec env FLARELAB_IN_NETNS=1 unshare -n "$0" "$@"
fi

# Inside the namespace: only lo, brought up here.
ip link set lo up 2>/dev/null || { echo "aravis_demo: cannot bring lo up" >&2; exit 1; }
rm -rf "$out/state" "$out/fake.cal.json"
pids=()
cleanup() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; }
trap cleanup EXIT

arv-fake-gv-camera-0.8 -i 127.0.0.1 >/dev/null 2>&1 &
pids+=($!)
for _ in $(seq 50); do grep -q ':0F74 ' /proc/net/udp 2>/dev/null && break; sleep 0.1; done

camera="aravis:127.0.0.1?roi=0,0,512,384"
echo "== 1. the devices"
"$flarelab" rig devices | sed -n '/^cameras:/,/^heads:/p' | grep -v '^heads:' | head -n 12

echo "== 2. calibrate the camera (below 1 ms the fake reads black: the dark frames)"
"$flarelab" calibrate --camera "$camera" --yes --dark-exposure 0.0005 -o "$out/fake.cal.json" |
    grep -E '^(camera|black level|response|saturation|wrote)'

echo "== 3. a bracketed sweep through flarelabd"
mkdir -p "$out/state"
"$flarelabd" --state-dir "$out/state" --camera "$camera" --head "sim:?time=fast&settle_s=0" \
    --calibration "$out/fake.cal.json" >"$out/flarelabd.log" 2>&1 &
pids+=($!)
export FLARELAB_SOCKET=$out/state/flarelabd.sock
for _ in $(seq 100); do [[ -S $FLARELAB_SOCKET ]] && break; sleep 0.1; done
"$flarelab" rig status | grep -E '^(rig|cameras|heads)'
"$flarelab" sweep start --from 0 --to 2 --step 0.5 --brackets 0.002,0.004,0.008 --keep-raw \
    --pixel-um 5.86 --lens-description "none (test pattern)" --watch -o "$out/state/output/fake-sweep"
"$flarelab" sweep info "$out/state/output/fake-sweep" | head -n 12
grep -E 'event=sweep.camera_statistics' "$out/flarelabd.log" | tail -n 1 || true
echo "aravis_demo: done; the sweep is in $out/state/output/fake-sweep"
