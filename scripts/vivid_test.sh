#!/usr/bin/env bash
# The V4L2 backend against a real kernel driver: scripts/vivid_test.sh BUILD_DIR
#
# Boots Debian 12's own kernel (linux-image-amd64, fetched with `apt-get download` and cached)
# in qemu-system-x86_64, headless, with a small busybox initramfs. Inside the VM it loads vivid
# (the kernel's virtual video test driver: three instances, two single-planar capture nodes and
# one multi-planar), records `v4l2-ctl --all --list-formats-ext` of every node, creates a USB
# serial gadget through dummy_hcd and configfs (an ACM function posing as 0403:faf0, the USB id
# of a Thorlabs APT controller) so that a real /dev/ttyACM0 with USB descriptors appears, and
# runs BUILD_DIR/tests/v4l2_vivid_check (build it with `cmake --build --preset release --target
# v4l2_vivid_check`), which captures every raw format vivid offers through flarelab's v4l2
# backend. It then checks `flarelab rig devices --json` (the gadget's port must be listed as an
# APT head with its USB identity, vivid's nodes as cameras), and drives the APT driver over the
# gadget's USB line against flarelab-stage-sim serving the device side (/dev/ttyGS0): home, a
# move, the position read back. The VM sees the host's file system read-only over 9p (virtio) and chroots into it, so
# the test binary runs with the host's libraries; results come back through a second, writable
# 9p share.
#
# Exits 0 only when every check passed; 77 when Debian's kernel package cannot be downloaded or
# the VM never gets as far as the check (nothing was tested); 1 on any failure. Prints what each
# part took. Never hangs: qemu runs under `timeout` (VIVID_TIMEOUT_S, default 900 s).
#
# Environment:
#   VIVID_ACCEL       auto (default: kvm when /dev/kvm is usable and the CPU offers vmx or svm,
#                     else tcg), kvm or tcg
#   VIVID_CACHE       where the kernel packages and the extracted kernel are kept (default
#                     build/vm of this repository, ignored by git): reruns need no network
#   VIVID_RECORD_DIR  copy the recorded v4l2-ctl dumps there (e.g. tests/data/v4l2)
#   VIVID_TIMEOUT_S   wall-clock limit of the VM (default 900)
#
# Needs: qemu-system-x86 busybox-static apt (scripts/install-deps.sh installs them), and
# v4l-utils on the host for the dumps (optional: without it the dumps are skipped).
set -euo pipefail

if (($# != 1)); then
    echo "usage: $0 BUILD_DIR" >&2
    exit 2
fi
repo=$(cd "$(dirname "$0")/.." && pwd)
build=$(cd "$1" && pwd)
check=$build/tests/v4l2_vivid_check
cache=${VIVID_CACHE:-$repo/build/vm}
accel=${VIVID_ACCEL:-auto}
limit=${VIVID_TIMEOUT_S:-900}
record=${VIVID_RECORD_DIR:-}

now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }
fail() {
    echo "vivid_test: $*" >&2
    exit 1
}

t_total=$(now)
[[ -x $check ]] || fail "$check is missing: cmake --build $1 --target v4l2_vivid_check"
[[ $build != *" "* && $repo != *" "* ]] || fail "paths with spaces are not supported"
command -v qemu-system-x86_64 >/dev/null || fail "qemu-system-x86_64 is missing (Debian: qemu-system-x86)"
busybox=""
for b in /bin/busybox /usr/bin/busybox; do
    if [[ -x $b ]] && ! ldd "$b" >/dev/null 2>&1; then busybox=$b && break; fi
done
[[ -n $busybox ]] || fail "a static busybox is missing (Debian: busybox-static)"

case $accel in
auto)
    if [[ -r /dev/kvm && -w /dev/kvm ]] && grep -qwE 'vmx|svm' /proc/cpuinfo; then
        accel=kvm
    else
        accel=tcg
    fi
    ;;
kvm | tcg) ;;
*) fail "VIVID_ACCEL must be auto, kvm or tcg, not '$accel'" ;;
esac

# ---- the kernel: Debian's package, downloaded once ------------------------------------------
t_kernel=$(now)
mkdir -p "$cache/debs"
image=$(ls "$cache"/debs/linux-image-[0-9]*-amd64_*.deb 2>/dev/null | sort -V | tail -n 1 || true)
if [[ -z $image ]]; then
    echo "vivid_test: fetching Debian's kernel package into $cache/debs"
    if ! (cd "$cache/debs" && apt-get download -q linux-image-amd64 >/dev/null 2>&1); then
        # A machine whose packages were all installed may have no package lists (Debian's
        # container images delete them): fetch them once, then try again.
        sudo=""
        [[ $(id -u) -eq 0 ]] || sudo="sudo -n"
        $sudo apt-get update -qq >/dev/null 2>&1 || true
        if ! (cd "$cache/debs" && apt-get download -q linux-image-amd64 >/dev/null 2>&1); then
            echo "vivid_test: cannot download Debian's kernel package (linux-image-amd64): no" \
                "network or no package lists; nothing was tested" >&2
            exit 77
        fi
    fi
    meta=$(ls "$cache"/debs/linux-image-amd64_*.deb | sort -V | tail -n 1)
    real=$(dpkg-deb -f "$meta" Depends | tr ',' '\n' | grep -o 'linux-image-[0-9][^ ]*-amd64' | head -n 1)
    [[ -n $real ]] || fail "$meta names no linux-image-N-amd64"
    (cd "$cache/debs" && apt-get download -q "$real" >/dev/null 2>&1) || fail "apt-get download $real failed"
    image=$(ls "$cache"/debs/"$real"_*.deb | sort -V | tail -n 1)
fi
version=$(basename "$image" | sed -E 's/^linux-image-([^_]+)_.*/\1/')
kdir=$cache/kernel-$version
if [[ ! -f $kdir/.extracted ]]; then
    rm -rf "$kdir"
    mkdir -p "$kdir"
    dpkg-deb -x "$image" "$kdir"
    "$busybox" depmod -b "$kdir" "$version"
    touch "$kdir/.extracted"
fi
vmlinuz=$kdir/boot/vmlinuz-$version
[[ -f $vmlinuz ]] || fail "$vmlinuz missing from $image"
kernel_s=$(since "$t_kernel")

# ---- the initramfs: busybox, the modules and their dependencies, our init --------------------
t_initramfs=$(now)
run=$cache/run
rm -rf "$run"
mkdir -p "$run/root"/{bin,dev,proc,sys,mnt/host,out,lib/modules} "$run/out"
cp "$busybox" "$run/root/bin/busybox"
moddir=$kdir/lib/modules/$version
modules=""
for m in virtio_pci 9pnet_virtio 9p vivid dummy_hcd libcomposite usb_f_acm usb_f_serial cdc-acm configfs; do
    line=$(grep -E "(^|/)$m\.ko(\.[a-z]+)?:" "$moddir/modules.dep" || true)
    [[ -n $line ]] || fail "module $m is not in $image"
    modules="$modules ${line%%:*} ${line#*:}"
done
for f in $(echo "$modules" | tr ' ' '\n' | sort -u); do
    mkdir -p "$run/root/lib/modules/$version/$(dirname "$f")"
    cp "$moddir/$f" "$run/root/lib/modules/$version/$f"
done
cp "$moddir"/modules.{order,builtin} "$run/root/lib/modules/$version/" 2>/dev/null || true
"$busybox" depmod -b "$run/root" "$version"
have_flarelab=0
[[ -x $build/apps/flarelab && -x $build/apps/flarelab-stage-sim ]] && have_flarelab=1
# The VM gives the chroot a /tmp of its own; the repository and the build directory stay
# visible there when they lie under the host's /tmp (a clean clone in /tmp, as CI may make).
under_tmp=""
for p in "$repo" "$build"; do
    if [[ $p == /tmp/* ]]; then
        rel=${p#/tmp/}
        under_tmp="$under_tmp ${rel%%/*}"
    fi
done
cat >"$run/root/init" <<EOF
#!/bin/busybox sh
/bin/busybox --install -s /bin
export PATH=/bin
mount -t proc proc /proc
mount -t sysfs sys /sys
mount -t devtmpfs dev /dev
mark() { echo "VIVID-TIME \$1 \$(cut -d' ' -f1 /proc/uptime)"; }
mark boot
for m in virtio_pci 9pnet_virtio 9p; do modprobe \$m || echo "VIVID-ERROR modprobe \$m"; done
mount -t 9p -o trans=virtio,version=9p2000.L,ro,msize=262144 hostroot /mnt/host || echo "VIVID-ERROR host share"
mount -t 9p -o trans=virtio,version=9p2000.L,msize=262144 out /out || echo "VIVID-ERROR out share"
mark shares
# Two single-planar capture nodes and one multi-planar one.
modprobe vivid n_devs=3 node_types=0x1,0x1,0x1 multiplanar=1,1,2 || echo "VIVID-ERROR modprobe vivid"
mark vivid
ls -l /dev/video* > /out/video-nodes.txt 2>&1

# A USB serial port with real descriptors: an ACM gadget on dummy_hcd, posing as a Thorlabs
# APT controller's USB id (0403:faf0); the host side binds cdc_acm and makes /dev/ttyACM0.
modprobe dummy_hcd && modprobe libcomposite && modprobe usb_f_acm && modprobe cdc-acm || echo "VIVID-ERROR gadget modules"
mount -t configfs none /sys/kernel/config 2>/dev/null
g=/sys/kernel/config/usb_gadget/flarelab
mkdir -p \$g/strings/0x409 \$g/configs/c.1/strings/0x409 \$g/functions/acm.usb0
echo 0x0403 > \$g/idVendor
echo 0xfaf0 > \$g/idProduct
echo 55000001 > \$g/strings/0x409/serialnumber
echo "flarelab VM" > \$g/strings/0x409/manufacturer
echo "ACM gadget with a Thorlabs APT USB id" > \$g/strings/0x409/product
echo "acm" > \$g/configs/c.1/strings/0x409/configuration
ln -s \$g/functions/acm.usb0 \$g/configs/c.1/
ls /sys/class/udc > \$g/UDC
i=0; while [ ! -e /dev/ttyACM0 ] && [ \$i -lt 100 ]; do sleep 0.1; i=\$((i + 1)); done
mark gadget
{
    ls -l /dev/ttyACM0
    echo "/sys/class/tty/ttyACM0/device -> \$(readlink -f /sys/class/tty/ttyACM0/device)"
    ls -l /sys/class/tty/ttyACM0/device/
    u=\$(readlink -f /sys/class/tty/ttyACM0/device/..)
    for f in idVendor idProduct serial manufacturer product bcdDevice busnum devnum speed; do
        echo "\$u/\$f: \$(cat \$u/\$f 2>/dev/null)"
    done
    echo "interface class: \$(cat /sys/class/tty/ttyACM0/device/bInterfaceClass 2>/dev/null), driver: \$(basename \$(readlink /sys/class/tty/ttyACM0/device/driver) 2>/dev/null)"
} > /out/acm-sysfs.txt 2>&1

# Into the host's file system, read-only, with this VM's /dev, /proc, /sys.
for d in dev proc sys; do mount --bind /\$d /mnt/host/\$d; done
mkdir -p /hosttmp
mount --bind /mnt/host/tmp /hosttmp
mount -t tmpfs tmp /mnt/host/tmp
for p in $under_tmp; do mkdir -p /mnt/host/tmp/\$p && mount --bind /hosttmp/\$p /mnt/host/tmp/\$p; done
mkdir -p /mnt/host/tmp/out
mount --bind /out /mnt/host/tmp/out
host() { chroot /mnt/host /usr/bin/env -i PATH=/usr/bin:/bin HOME=/tmp "\$@"; }
if [ -x /mnt/host/usr/bin/v4l2-ctl ]; then
    for n in /dev/video*; do
        b=\$(basename \$n)
        { host v4l2-ctl -d \$n --all; host v4l2-ctl -d \$n --list-formats-ext; } > /out/dump-\$b.txt 2>&1
    done
    # vivid's first node after a raw format is chosen and automatic gain is off.
    host v4l2-ctl -d /dev/video0 --set-fmt-video=width=320,height=180,pixelformat='Y16 ' --set-ctrl=gain_automatic=0,gain=64
    { host v4l2-ctl -d /dev/video0 --all; host v4l2-ctl -d /dev/video0 --list-formats-ext; } > /out/dump-video0-y16.txt 2>&1
    host v4l2-ctl -d /dev/video0 --set-fmt-video=width=640,height=360,pixelformat=YUYV --set-ctrl=gain_automatic=1
fi
mark dumps
if [ $have_flarelab = 1 ]; then
    host $build/apps/flarelab rig devices --json > /out/rig-devices.json 2> /out/rig-devices.err
    echo \$? > /out/rig-devices.rc
    # The APT driver through the kernel's USB stack: the simulator serves the gadget's side of the
    # line (/dev/ttyGS0), the driver opens the host's (/dev/ttyACM0, cdc_acm).
    host $build/apps/flarelab-stage-sim apt --tty /dev/ttyGS0 > /out/stage-sim.log 2>&1 &
    i=0; while ! grep -q ttyGS0 /out/stage-sim.log 2>/dev/null && [ \$i -lt 50 ]; do sleep 0.1; i=\$((i + 1)); done
    {
        host $build/apps/flarelab rig head apt:/dev/ttyACM0 home --timeout 60 --json &&
        host $build/apps/flarelab rig head apt:/dev/ttyACM0 move 12.4 --timeout 60 --json &&
        host $build/apps/flarelab rig head apt:/dev/ttyACM0 position --json
    } > /out/apt-usb.json 2> /out/apt-usb.err
    echo \$? > /out/apt-usb.rc
    killall flarelab-stage-sim 2>/dev/null
fi
mark check-start
host $check --dev-dir /dev --width 320 --height 180 --fps 30 > /out/check.log 2>&1
rc=\$?
# The lab mode of the same program, on the second node (the first is disconnected by now).
host $check --lab "v4l2:/dev/video1?width=320&height=180&fps=30" > /out/lab.log 2>&1 || rc=1
echo \$rc > /out/check.rc
mark check
cat /out/check.log | grep -E "^(FAIL|SUMMARY)"
sync
poweroff -f
EOF
chmod +x "$run/root/init"
(cd "$run/root" && find . | "$busybox" cpio -o -H newc 2>/dev/null | gzip -1 >"$run/initramfs.gz")
initramfs_s=$(since "$t_initramfs")

# ---- the VM -----------------------------------------------------------------------------------
t_vm=$(now)
cpu=()
[[ $accel == kvm ]] && cpu=(-cpu host)
echo "vivid_test: booting Debian's kernel $version with $accel (limit ${limit} s)"
set +e
timeout --kill-after=10 "$limit" qemu-system-x86_64 -accel "$accel" "${cpu[@]}" -m 1536 -smp 1 \
    -nographic -no-reboot -kernel "$vmlinuz" -initrd "$run/initramfs.gz" \
    -append "console=ttyS0 quiet panic=-1 loglevel=3" \
    -virtfs local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap \
    -virtfs local,path="$run/out",mount_tag=out,security_model=none \
    </dev/null >"$run/console.log" 2>&1
qemu_rc=$?
set -e
vm_s=$(since "$t_vm")

# ---- results -----------------------------------------------------------------------------------
# (-o: the firmware's escape sequences may share the first line.)
guest() { { grep -ao "VIVID-TIME $1 [0-9.]*" "$run/console.log" || true; } | awk '{print $3}' | tail -n 1; }
boot=$(guest boot)
vivid=$(guest vivid)
gadget=$(guest gadget)
start=$(guest check-start)
done_=$(guest check)
span() { [[ -n $1 && -n $2 ]] && awk -v a="$1" -v b="$2" 'BEGIN { printf "%.1f", b - a }' || echo "?"; }

if [[ -n $record ]]; then
    mkdir -p "$record"
    for f in "$run"/out/dump-*.txt; do
        [[ -f $f ]] && cp "$f" "$record/vivid-$(basename "$f" .txt | sed 's/^dump-//').txt"
    done
fi

echo
for log in "$run/out/check.log" "$run/out/lab.log"; do
    [[ -f $log ]] && { grep -E "^(PASS|FAIL|TIME|SUMMARY|SKIP|CAMERA|WARNING)" "$log" || true; }
done
echo
echo "USB gadget (sysfs as the VM saw it):"
sed 's/^/    /' "$run/out/acm-sysfs.txt" 2>/dev/null || echo "    (none)"
if [[ -f $run/out/rig-devices.rc ]]; then
    echo "flarelab rig devices --json: exit $(cat "$run/out/rig-devices.rc")"
    python3 -c 'import json, sys
for d in json.load(open(sys.argv[1]))["devices"]:
    print("    %-22s %-12s %s %s" % (d["uri"], d["kind"], d["model"], d["serial"]))' \
        "$run/out/rig-devices.json" 2>&1 || true
    sed 's/^/    /' "$run/out/rig-devices.err" 2>/dev/null || true
fi
grep -a "VIVID-ERROR" "$run/console.log" || true
echo
echo "vivid_test summary ($accel, kernel $version):"
echo "    kernel package and extraction  ${kernel_s} s"
echo "    initramfs                      ${initramfs_s} s"
echo "    VM wall time                   ${vm_s} s (qemu exit $qemu_rc)"
echo "    guest: kernel boot to init     ${boot:-?} s"
echo "    guest: modules and vivid       $(span "$boot" "$vivid") s"
echo "    guest: USB gadget              $(span "$vivid" "$gadget") s"
echo "    guest: v4l2_vivid_check        $(span "$start" "$done_") s"
echo "    total                          $(since "$t_total") s"
echo "    console log: $run/console.log"

rc=$(cat "$run/out/check.rc" 2>/dev/null || echo none)
if [[ $rc == none ]] && ! grep -aq "VIVID-TIME check-start" "$run/console.log" 2>/dev/null; then
    # The VM never got as far as flarelab's code (qemu could not start, the guest could not boot
    # or mount the host's files): this machine cannot run the test, which says nothing of V4L2.
    echo "vivid_test: the VM did not get as far as the check (qemu exit $qemu_rc); nothing was" \
        "tested; see $run/console.log" >&2
    exit 77
fi
if [[ $qemu_rc -ne 0 ]]; then
    echo "vivid_test: FAILED: qemu exited $qemu_rc (124: it ran past ${limit} s); see $run/console.log" >&2
    exit 1
fi
if [[ $rc != 0 ]]; then
    echo "vivid_test: FAILED: v4l2_vivid_check exit status $rc; see $run/out/check.log" >&2
    exit 1
fi
# The device listing, as a lab would run it: the gadget's port as an APT head with its USB
# identity, and vivid's single-planar nodes as cameras.
if [[ -f $run/out/rig-devices.json ]]; then
    if ! python3 - "$run/out/rig-devices.json" <<'PY'
import json, sys
devices = json.load(open(sys.argv[1]))["devices"]
by_uri = {d["uri"]: d for d in devices}
problems = []
acm = by_uri.get("apt:/dev/ttyACM0")
if not acm or acm["kind"] != "head" or acm["serial"] != "55000001" or \
        not any("0403:faf0" in line for line in acm["details"]):
    problems.append("apt:/dev/ttyACM0 is not listed as a head with USB id 0403:faf0, serial 55000001")
for node in ("v4l2:/dev/video0", "v4l2:/dev/video1"):
    d = by_uri.get(node)
    if not d or d["kind"] != "camera" or not any(l.startswith("opens as: Y16") for l in d["details"]):
        problems.append(node + " is not listed as a camera that opens as Y16")
for p in problems:
    print("vivid_test: rig devices: " + p, file=sys.stderr)
sys.exit(1 if problems else 0)
PY
    then
        echo "vivid_test: FAILED: the device listing; see $run/out/rig-devices.json" >&2
        exit 1
    fi
    echo "vivid_test: rig devices lists apt:/dev/ttyACM0 (0403:faf0, serial 55000001) and vivid's nodes"
    # The last answer is the position read back: 12.4 deg to one count of the K10CR1's
    # 409600/3 per degree.
    if [[ $(cat "$run/out/apt-usb.rc" 2>/dev/null) != 0 ]] ||
        ! python3 -c 'import json, re, sys
docs = re.findall(r"\{.*?\n\}", open(sys.argv[1]).read(), re.S)
sys.exit(0 if docs and abs(json.loads(docs[-1])["position_deg"] - 12.4) <= 3 / 409600 else 1)' \
            "$run/out/apt-usb.json"; then
        echo "vivid_test: FAILED: the APT driver over USB (apt:/dev/ttyACM0 to the simulator on" \
            "/dev/ttyGS0):" >&2
        sed 's/^/    /' "$run/out/apt-usb.json" "$run/out/apt-usb.err" "$run/out/stage-sim.log" >&2
        exit 1
    fi
    echo "vivid_test: the APT driver homed and moved the simulated K10CR1 over USB (cdc_acm):" \
        "at $(grep -o '"position_deg": [0-9.]*' "$run/out/apt-usb.json" | tail -1 | cut -d' ' -f2) deg"
else
    echo "vivid_test: FAILED: flarelab rig devices did not run in the VM" >&2
    exit 1
fi
echo "vivid_test: PASSED"
