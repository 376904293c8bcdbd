// ============================================================================
//  flarelab tests: isolateLoopback, FakeGvCamera, FakeGvCameraProcess, fakePatternMatches
// ============================================================================
//
// Aravis's fake GigE Vision camera for tests (tests/aravis, and tests/daemon for sweeps through
// flarelabd), speaking the real GVCP and GVSP protocols on 127.0.0.1:
//
//   FakeGvCamera         in this process (arv_gv_fake_camera_new, public in Aravis 0.8); its
//                        GVSP lost-packet ratio can change while it runs; stop() ends it as a
//                        camera that lost power ends (no more replies), start() brings up a fresh
//                        one with power-on registers.
//   FakeGvCameraProcess  the arv-fake-gv-camera-0.8 tool (Debian: aravis-tools) as a child
//                        process; kill() sends SIGKILL, start() runs it again.
//
// Both listen on 127.0.0.1, port 3956, so only one runs at a time in a network namespace. Tests
// run each in a namespace of its own (tests/aravis/in_netns.sh: `unshare -n`), where discovery
// broadcasts cannot reach a real network; isolateLoopback() checks that (no interface but lo)
// and brings lo up.
//
// fakePatternMatches() checks a frame against the fake's test pattern (Aravis's
// src/arvfakecamera.c, arv_fake_camera_diagonal_ramp): with frame id f, sample (x, y) is
//   Mono8:  clip(((x + y + f) mod 255) * s, 0, 255)
//   Mono16: clip(((256 (x + y + f)) mod 65535) * s, 0, 65535)
// truncated to an integer, with s = 1 + GainRaw + log10(ExposureTimeAbs_us / 10000): brightness
// grows with the logarithm of the exposure and is 0 below 1 ms at GainRaw 0.
#pragma once

#include <arv.h>
#include <fcntl.h>
#include <ifaddrs.h>
#include <net/if.h>
#include <signal.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <set>
#include <string>
#include <thread>

#include "hdr/raw_frame.h"

namespace flarelab::testing {

inline constexpr const char* kFakeAddress = "127.0.0.1";
inline constexpr const char* kFakeSerial = "GV01";
inline constexpr const char* kFakeId = "Aravis-Fake-GV01";  // Aravis's id: vendor-model-serial

// "" when this process sees no network interface but lo, and lo is up (brought up here);
// otherwise why not. Run the tests through tests/aravis/in_netns.sh.
inline std::string isolateLoopback() {
    ifaddrs* list = nullptr;
    if (getifaddrs(&list) != 0) return std::string("getifaddrs: ") + std::strerror(errno);
    std::set<std::string> names;
    for (ifaddrs* i = list; i; i = i->ifa_next)
        if (i->ifa_name) names.insert(i->ifa_name);
    freeifaddrs(list);
    for (const std::string& n : names)
        if (n != "lo")
            return "network interface '" + n +
                   "' is visible: these tests broadcast GigE Vision discovery and must run in a "
                   "network namespace of their own (ctest runs them through "
                   "tests/aravis/in_netns.sh, `unshare -n`)";
    const int fd = socket(AF_INET, SOCK_DGRAM, 0);
    if (fd < 0) return std::string("socket: ") + std::strerror(errno);
    ifreq request{};
    std::strncpy(request.ifr_name, "lo", IFNAMSIZ - 1);
    std::string why;
    if (ioctl(fd, SIOCGIFFLAGS, &request) != 0) {
        why = std::string("SIOCGIFFLAGS lo: ") + std::strerror(errno);
    } else if (!(request.ifr_flags & IFF_UP)) {
        request.ifr_flags = static_cast<short>(request.ifr_flags | IFF_UP | IFF_RUNNING);
        if (ioctl(fd, SIOCSIFFLAGS, &request) != 0)
            why = std::string("bringing lo up: ") + std::strerror(errno);
    }
    close(fd);
    return why;
}

// Whether a UDP socket is bound to port 3956 (GVCP) in this namespace: the fake is listening.
inline bool gvcpPortBound() {
    std::ifstream udp("/proc/net/udp");
    std::string line;
    std::getline(udp, line);  // header
    while (std::getline(udp, line)) {
        // "  sl  local_address rem_address ...": local is HEXIP:HEXPORT
        const size_t colon = line.find(':', line.find(':') + 1);
        if (colon != std::string::npos && line.compare(colon + 1, 4, "0F74") == 0) return true;
    }
    return false;
}

inline bool waitFor(const auto& condition, double timeout_s) {
    const auto deadline = std::chrono::steady_clock::now() +
                          std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                              std::chrono::duration<double>(timeout_s));
    while (!condition()) {
        if (std::chrono::steady_clock::now() >= deadline) return false;
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return true;
}

class FakeGvCamera {
public:
    explicit FakeGvCamera(std::string serial = kFakeSerial) : serial_(std::move(serial)) {
        start();
    }
    FakeGvCamera(const FakeGvCamera&) = delete;
    FakeGvCamera& operator=(const FakeGvCamera&) = delete;
    ~FakeGvCamera() { stop(); }

    // A fresh camera (power-on registers: Mono8, 512 x 512, GainRaw 0); false when it could not
    // bind its sockets.
    bool start() {
        stop();
        fake_ = arv_gv_fake_camera_new(kFakeAddress, serial_.c_str());
        return running();
    }
    // Gone at once: its thread ends and its sockets close, as if it lost power.
    void stop() {
        if (fake_) g_object_unref(fake_);
        fake_ = nullptr;
    }
    bool running() const { return fake_ && arv_gv_fake_camera_is_running(fake_); }
    // The fraction of GVSP packets (leader, data, trailer) it drops, drawn per packet.
    void setLostPacketRatio(double ratio) {
        g_object_set(fake_, "gvsp-lost-ratio", ratio, nullptr);
    }
    uint32_t reg(uint32_t address) const {
        guint32 value = 0;
        arv_fake_camera_read_register(arv_gv_fake_camera_get_fake_camera(fake_), address, &value);
        return value;
    }

private:
    std::string serial_;
    ArvGvFakeCamera* fake_ = nullptr;
};

class FakeGvCameraProcess {
public:
    static constexpr const char* kTool = "arv-fake-gv-camera-0.8";
    explicit FakeGvCameraProcess(std::string serial = kFakeSerial, int lost_per_thousand = 0)
        : serial_(std::move(serial)), lost_per_thousand_(lost_per_thousand) {}
    FakeGvCameraProcess(const FakeGvCameraProcess&) = delete;
    FakeGvCameraProcess& operator=(const FakeGvCameraProcess&) = delete;
    ~FakeGvCameraProcess() { kill(); }

    // Runs the tool and waits (up to timeout_s) until it listens; "" on success, else why not.
    std::string start(double timeout_s = 10.0) {
        kill();
        const std::string lost = std::to_string(lost_per_thousand_);
        pid_ = fork();
        if (pid_ < 0) return std::string("fork: ") + std::strerror(errno);
        if (pid_ == 0) {
            const int null = ::open("/dev/null", O_WRONLY);
            if (null >= 0) dup2(null, STDOUT_FILENO);
            execlp(kTool, kTool, "-i", kFakeAddress, "-s", serial_.c_str(), "-r", lost.c_str(),
                   static_cast<char*>(nullptr));
            _exit(127);
        }
        if (!waitFor([&] { return gvcpPortBound() || exited(); }, timeout_s) || exited()) {
            kill();
            return std::string(kTool) +
                   " did not start listening on 127.0.0.1:3956 (is aravis-tools installed? "
                   "scripts/install-deps.sh)";
        }
        return "";
    }
    // SIGKILL: the camera vanishes mid-whatever, as when its cable is pulled.
    void kill() {
        if (pid_ <= 0) return;
        ::kill(pid_, SIGKILL);
        waitpid(pid_, nullptr, 0);
        pid_ = -1;
    }
    pid_t pid() const { return pid_; }

private:
    bool exited() {
        int status = 0;
        if (pid_ > 0 && waitpid(pid_, &status, WNOHANG) == pid_) {
            pid_ = -1;
            return true;
        }
        return pid_ <= 0;
    }
    std::string serial_;
    int lost_per_thousand_;
    pid_t pid_ = -1;
};

// The fake's pattern value of sample (x, y) for frame id f (see the top of this file).
inline uint16_t fakePatternSample(
    int64_t x, int64_t y, int64_t frame_id, int bits, uint32_t exposure_us, uint32_t gain_raw) {
    const double scale =
        1.0 + static_cast<double>(gain_raw) + std::log10(static_cast<double>(exposure_us) / 1e4);
    double v = 0.0;
    double top = 0.0;
    if (bits == 8) {
        v = static_cast<double>((x + frame_id + y) % 255);
        top = 255.0;
    } else {
        v = static_cast<double>((256 * x + 256 * frame_id + 256 * y) % 65535);
        top = 65535.0;
    }
    v *= scale;
    return static_cast<uint16_t>(v < 0.0 ? 0.0 : (v > top ? top : v));
}

// Whether a Mono8 or Mono16 frame is exactly the fake's pattern for some frame id (the fake's ids
// run 1..65535) with this exposure and GainRaw; the frame id found goes to *frame_id.
inline bool fakePatternMatches(const hdr::RawFrame& frame,
                               uint32_t exposure_us,
                               uint32_t gain_raw,
                               int64_t* frame_id = nullptr) {
    if (frame.format != hdr::RawFormat::Mono || frame.samples.empty()) return false;
    for (int64_t f = 1; f <= 65535; ++f) {
        bool all = true;
        for (int64_t y = 0; y < frame.height && all; ++y)
            for (int64_t x = 0; x < frame.width && all; ++x)
                all = frame.samples[static_cast<size_t>(y * frame.width + x)] ==
                      fakePatternSample(x, y, f, frame.bit_depth, exposure_us, gain_raw);
        if (all) {
            if (frame_id) *frame_id = f;
            return true;
        }
    }
    return false;
}

}  // namespace flarelab::testing
