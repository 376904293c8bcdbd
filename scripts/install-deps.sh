#!/usr/bin/env bash
# Installs every Debian 12 package flarelab builds, tests, fuzzes and benchmarks with.
# Idempotent and non-interactive: when everything is present it changes nothing and asks no
# network. Run as root, or as a user with password-less sudo.
set -euo pipefail

packages=(
    # toolchain
    build-essential cmake ninja-build pkg-config git
    clang clang-format libclang-rt-14-dev libfuzzer-14-dev valgrind
    # numerics, images, optimization
    libeigen3-dev libceres-dev libopencv-dev libopenexr-dev libfftw3-dev libtbb-dev libssl-dev
    libpng-dev
    # glTF import of venues: cameras and KHR_lights_punctual lights (predict/gltf_import.h)
    libtinygltf-dev
    # control API and model files
    libprotobuf-dev protobuf-compiler libgrpc++-dev protobuf-compiler-grpc
    python3 python3-grpcio python3-protobuf python3-grpc-tools
    # devices
    # (V4L2 needs only the kernel headers; the serial stages need no libusb: drivers/serial_port.h)
    libaravis-dev libcamera-dev
    # flarelabd as a service: sd_notify (Type=notify, the watchdog); systemd-analyze, sysusers
    # and tmpfiles check the unit and its files in the tests
    libsystemd-dev systemd
    # Aravis's fake GigE Vision camera (tests/aravis) and arv-tool-0.8 (docs: the lab procedure)
    aravis-tools aravis-tools-cli
    # the V4L2 test in a VM (scripts/vivid_test.sh): qemu, a static busybox for its initramfs,
    # v4l2-ctl for the dumps
    qemu-system-x86 busybox-static v4l-utils
    # command line, logs, JSON
    libcli11-dev libspdlog-dev libfmt-dev nlohmann-json3-dev
    # tests and benchmarks
    libgtest-dev libgmock-dev libbenchmark-dev gnuplot-nox
    # the report test opens flarelab predict's report in headless Chromium
    # (tests/predict/report_in_chromium.sh)
    chromium
)

missing=()
for p in "${packages[@]}"; do
    if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
        missing+=("$p")
    fi
done

if ((${#missing[@]} == 0)); then
    exit 0
fi

echo "install-deps: installing ${#missing[@]} Debian packages: ${missing[*]}"
sudo=""
if [[ $(id -u) -ne 0 ]]; then
    sudo="sudo"
fi
export DEBIAN_FRONTEND=noninteractive
$sudo apt-get update -qq
$sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
echo "install-deps: done"
