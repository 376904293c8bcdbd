// The V4L2 backend against the kernel's vivid driver: scripts/vivid_test.sh runs it inside a
// virtual machine (Debian's kernel, `modprobe vivid`), where it opens every vivid capture node
// through the "v4l2" camera backend and captures frames in every raw format that the backend
// reads and vivid offers. Not a ctest test: it needs vivid's nodes, which only the VM has.
//
// Per node and format it checks: the negotiated format, size and bit depth; frames by mmap
// streaming with monotonic timestamps marked as vivid marks them (end of frame by default, start
// of exposure after vivid's timestamp_source control is switched), rising sequence numbers and
// a host timestamp; that the samples' means follow vivid's test patterns (100% white and 100%
// black, normalized by the bit depth, agree across formats, which catches a wrong alignment;
// under 100% red the red sites of a Bayer mosaic are the bright ones, which catches a wrong
// order); the gain control (vivid has gain and gain_automatic, no exposure control): automatic
// gain is turned off, a gain set is read back by the backend into the frame and by a second file
// descriptor from the driver, and the frame returned after a change was exposed after it; the
// exposure is the frame interval, and another exposure is refused as out-of-range; a frame
// waited for after the node sat idle was exposed after the call. Per node, once: a buffer vivid
// flags as an error is skipped and counted. A multi-planar node must be refused with its
// reason. Last, vivid's disconnect control must turn a capture into [disconnected].
//
//   v4l2_vivid_check [--dev-dir /dev] [--width 320] [--height 180] [--fps 30]
//   v4l2_vivid_check --lab "v4l2:/dev/video0?format=Y16&gain_unity=16"
//
// --lab runs the checks for a real camera (docs/lab.md, "V4L2 cameras"): frames, timestamps, and
// with an exposure control the first frame after a change against the third, and linearity over
// exposures t, 2t, 4t of a steady scene.
//
// Prints one line per check ("PASS ..." / "FAIL ...") and a summary; exits 0 only when every
// check passed and at least one format was captured.
#include <linux/videodev2.h>
#include <time.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "drivers/rig.h"
#include "drivers/v4l2_camera.h"
#include "drivers/v4l2_device.h"
#include "drivers/v4l2_formats.h"

namespace {

using namespace flarelab;
using namespace flarelab::drivers;

// vivid's own controls (drivers/media/test-drivers/vivid/vivid-ctrls.c).
constexpr uint32_t kVividClassBase = 0x00f00000 | 0xf000;
constexpr uint32_t kTestPattern = kVividClassBase + 0;
constexpr uint32_t kOsdTextMode = kVividClassBase + 1;
constexpr uint32_t kTimestampSource = kVividClassBase + 0x18;
constexpr uint32_t kDisconnect = kVividClassBase + 0x41;
constexpr uint32_t kInjectBufferError = kVividClassBase + 0x42;
constexpr int kPatternWhite = 6, kPatternBlack = 5, kPatternRed = 7;

int failures = 0, passes = 0;

void report(bool ok, const std::string& what) {
    std::printf("%s %s\n", ok ? "PASS" : "FAIL", what.c_str());
    std::fflush(stdout);
    (ok ? passes : failures)++;
}

int64_t monotonicNs() {
    timespec t{};
    clock_gettime(CLOCK_MONOTONIC, &t);
    return static_cast<int64_t>(t.tv_sec) * 1'000'000'000 + t.tv_nsec;
}
int64_t realtimeNs() {
    timespec t{};
    clock_gettime(CLOCK_REALTIME, &t);
    return static_cast<int64_t>(t.tv_sec) * 1'000'000'000 + t.tv_nsec;
}

std::string num(double x) {
    char b[64];
    std::snprintf(b, sizeof b, "%.4g", x);
    return b;
}

// A second descriptor on the node, to drive vivid's controls and read back what the driver
// holds, independently of the camera under test.
struct SideChannel {
    std::unique_ptr<V4l2Device> device;
    bool set(uint32_t id, int32_t value) {
        v4l2_control c{id, value};
        return device->ioctl(VIDIOC_S_CTRL, &c) == 0;
    }
    std::optional<int32_t> get(uint32_t id) {
        v4l2_control c{id, 0};
        if (device->ioctl(VIDIOC_G_CTRL, &c) != 0) return std::nullopt;
        return c.value;
    }
};

double meanOf(const hdr::RawFrame& f, int dx = -1, int dy = -1) {
    double sum = 0.0;
    int64_t n = 0;
    for (int64_t y = 0; y < f.height; ++y)
        for (int64_t x = 0; x < f.width; ++x) {
            if (dx >= 0 && ((x & 1) != dx || (y & 1) != dy)) continue;
            sum += f.samples[static_cast<size_t>(y * f.width + x)];
            ++n;
        }
    return n ? sum / static_cast<double>(n) : 0.0;
}

// Where red sits in a 2x2 mosaic of each order.
std::pair<int, int> redSite(hdr::RawFormat f) {
    switch (f) {
        case hdr::RawFormat::BayerRGGB:
            return {0, 0};
        case hdr::RawFormat::BayerGRBG:
            return {1, 0};
        case hdr::RawFormat::BayerGBRG:
            return {0, 1};
        case hdr::RawFormat::BayerBGGR:
            return {1, 1};
        case hdr::RawFormat::Mono:
            break;
    }
    return {-1, -1};
}

struct Options {
    std::string dev_dir = "/dev";
    int width = 320, height = 180;
    double fps = 30.0;
    std::string lab_uri;  // --lab URI: the checks for a real camera instead
};

struct FormatResult {
    double white = 0.0, black = 0.0;  // normalized means
};

std::optional<hdr::RawFrame> shoot(Camera& camera,
                                   const std::string& what,
                                   double timeout_s = 5.0) {
    auto frame = camera.capture(timeout_s);
    if (!frame) {
        report(false, what + ": capture failed: " + frame.error().message);
        return std::nullopt;
    }
    return std::move(*frame);
}

void checkFormat(const Options& o,
                 const std::string& node,
                 const V4l2FormatInfo& info,
                 SideChannel& side,
                 std::map<std::string, FormatResult>& results) {
    const auto started = std::chrono::steady_clock::now();
    const std::string uri =
        "v4l2:" + node + "?format=" + info.name + "&width=" + std::to_string(o.width) +
        "&height=" + std::to_string(o.height) + "&fps=" + num(o.fps) + "&gain_unity=100";
    const std::string tag = node + " " + info.name;
    auto registries = makeRigRegistries(RigOptions{});
    if (!registries) {
        report(false, tag + ": registries: " + registries.error().message);
        return;
    }
    auto opened = registries->cameras.open(uri);
    if (!opened) {
        report(false, tag + ": open " + uri + ": " + opened.error().message);
        return;
    }
    Camera& camera = **opened;
    auto* v4l2 = dynamic_cast<V4l2Camera*>(&camera);
    const CameraCapabilities caps = camera.capabilities();
    bool ok = v4l2 && std::string(v4l2->pixelFormat().name) == info.name &&
              caps.width_px == o.width && caps.height_px == o.height &&
              caps.bit_depth == info.bits && camera.format() == info.raw_format &&
              caps.response == CameraResponse::Linear;
    report(ok, tag + ": negotiated " + (v4l2 ? v4l2->pixelFormat().name : "?") + " " +
                   std::to_string(caps.width_px) + "x" + std::to_string(caps.height_px) + ", " +
                   std::to_string(caps.bit_depth) + " bit, response linear");

    // Exposure: vivid has no exposure control; the frame interval stands in for it.
    const double interval = v4l2 ? v4l2->frameInterval_s() : 0.0;
    ok = v4l2 && v4l2->exposureMode() == V4l2ExposureMode::FrameInterval &&
         std::abs(interval - 1.0 / o.fps) < 0.1 / o.fps && caps.min_exposure_s == interval &&
         caps.max_exposure_s == interval;
    const Status other = camera.setExposure(interval * 2.0 + 0.01);
    ok = ok && !other && deviceFaultOf(other.error()) == DeviceFault::OutOfRange &&
         other.error().message.find("exposure_s") != std::string::npos &&
         camera.setExposure(interval).has_value();
    report(ok, tag + ": no exposure control: exposure is the frame interval " + num(interval) +
                   " s; another exposure is [out-of-range]");

    // Gain: automatic off, the value set read back by the camera and by the driver. The stream
    // runs first (at gain 1), so that the change falls in the middle of it.
    if (!camera.setGain(1.0)) report(false, tag + ": setGain(1)");
    if (!shoot(camera, tag + " first frame")) return;
    const int64_t before_change = monotonicNs();
    const Status gain_set = camera.setGain(2.0);
    const int64_t after_change = monotonicNs();
    const auto driver_gain = side.get(V4L2_CID_GAIN);
    const auto driver_auto = side.get(V4L2_CID_AUTOGAIN);
    side.set(kTestPattern, kPatternWhite);
    auto white = shoot(camera, tag + " white");
    if (!white) return;
    ok = gain_set.has_value() && driver_gain == 200 && driver_auto == 0 &&
         std::abs(white->gain - 2.0) < 1e-9 && std::abs(camera.gain() - 2.0) < 1e-9;
    report(ok, tag + ": gain 2 with gain_unity 100: driver holds gain " +
                   (driver_gain ? std::to_string(*driver_gain) : "?") + ", gain_automatic " +
                   (driver_auto ? std::to_string(*driver_auto) : "?") + ", frame says " +
                   num(white->gain));
    // The frame after a change was exposed after it: its end-of-frame timestamp, less one
    // frame interval of exposure and one of readout, is past the change.
    const double start_ns = static_cast<double>(white->timestamp_ns) - 2e9 * interval;
    report(start_ns >= static_cast<double>(before_change),
           tag + ": frame after the gain change starts " +
               num((start_ns - static_cast<double>(after_change)) * 1e-6) +
               " ms after it (end-of-frame stamp less 2 frame intervals)");

    // Frame metadata.
    const double white_level = std::ldexp(1.0, info.bits) - 1.0;
    uint16_t largest = 0;
    for (uint16_t v : white->samples) largest = std::max(largest, v);
    const int64_t host_age_ms = (realtimeNs() - white->host_timestamp_ns) / 1'000'000;
    ok = white->width == o.width && white->height == o.height &&
         white->samples.size() == static_cast<size_t>(o.width * o.height) &&
         white->bit_depth == info.bits && white->white_level_dn == white_level &&
         largest <= white_level && white->format == info.raw_format &&
         white->timestamp_marks == hdr::TimestampMark::FrameArrival && white->timestamp_ns > 0 &&
         white->host_timestamp_ns > 0 && host_age_ms >= 0 && host_age_ms < 5000 &&
         std::abs(white->exposure_s - interval) < 1e-9;
    report(ok, tag + ": frame " + std::to_string(white->width) + "x" +
                   std::to_string(white->height) + " bit_depth " +
                   std::to_string(white->bit_depth) + ", max sample " + std::to_string(largest) +
                   ", timestamp marks frame arrival (EOF), host time " +
                   std::to_string(host_age_ms) + " ms old");

    // An idle node fills its buffers with frames that are stale by the time capture is called.
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    const int64_t called = monotonicNs();
    auto black_stale_test = (side.set(kTestPattern, kPatternBlack), shoot(camera, tag + " black"));
    if (!black_stale_test) return;
    const hdr::RawFrame& black = *black_stale_test;
    const double black_start = static_cast<double>(black.timestamp_ns) - 2e9 * interval;
    ok = black_start >= static_cast<double>(called) && black.sequence > white->sequence &&
         black.timestamp_ns > white->timestamp_ns;
    int64_t stale = 0;
    for (const auto& [name, value] : camera.statistics())
        if (name == "dropped-stale") stale = value;
    report(ok && stale > 0, tag + ": after 300 ms idle, " + std::to_string(stale) +
                                " stale frames dropped so far; the frame returned starts " +
                                num((black_start - static_cast<double>(called)) * 1e-6) +
                                " ms after the call; sequence " + std::to_string(white->sequence) +
                                " -> " + std::to_string(black.sequence));

    const double w = meanOf(*white) / white_level, b = meanOf(black) / white_level;
    results[info.name] = {w, b};
    report(w > 0.8 && b < 0.1,
           tag + ": 100% white mean " + num(w) + ", 100% black mean " + num(b) + " of full scale");

    if (info.raw_format != hdr::RawFormat::Mono) {
        side.set(kTestPattern, kPatternRed);
        auto red = shoot(camera, tag + " red");
        if (!red) return;
        const auto [rx, ry] = redSite(info.raw_format);
        const double r = meanOf(*red, rx, ry) / white_level;
        double brightest_other = 0.0;
        for (int dy = 0; dy < 2; ++dy)
            for (int dx = 0; dx < 2; ++dx)
                if (dx != rx || dy != ry)
                    brightest_other = std::max(brightest_other, meanOf(*red, dx, dy) / white_level);
        report(r > 0.8 && brightest_other < 0.2, tag + ": 100% red: red sites " + num(r) +
                                                     ", other sites at most " +
                                                     num(brightest_other) + " of full scale");
    }
    side.set(kTestPattern, 0);
    const double seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
    std::printf("TIME %s %s %.2f s\n", node.c_str(), info.name, seconds);
}

void checkNode(const Options& o,
               const std::string& node,
               std::map<std::string, FormatResult>& all) {
    auto opened = openV4l2Node(node);
    if (!opened) {
        report(false, node + ": " + opened.error().message);
        return;
    }
    SideChannel side{std::move(*opened)};
    v4l2_capability cap{};
    side.device->ioctl(VIDIOC_QUERYCAP, &cap);
    const uint32_t caps =
        (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
    if (std::string(reinterpret_cast<const char*>(cap.driver)) != "vivid") {
        std::printf("SKIP %s: driver %s is not vivid\n", node.c_str(), cap.driver);
        return;
    }
    auto registries = makeRigRegistries(RigOptions{});
    if (!(caps & V4L2_CAP_VIDEO_CAPTURE)) {
        auto refused = registries->cameras.open("v4l2:" + node);
        report(!refused && refused.error().code == ErrorCode::Unsupported &&
                   refused.error().message.find("multi-planar") != std::string::npos,
               node + ": multi-planar node refused: " +
                   (refused ? std::string("opened!") : refused.error().message));
        return;
    }
    side.set(kOsdTextMode, 2);  // no text over the pattern
    side.set(kTestPattern, 0);

    // The default: the preferred format at the largest size (opening only: no frames).
    {
        auto camera = registries->cameras.open("v4l2:" + node);
        auto* v4l2 = camera ? dynamic_cast<V4l2Camera*>(camera->get()) : nullptr;
        report(v4l2 && std::string(v4l2->pixelFormat().name) == "Y16" &&
                   (*camera)->capabilities().width_px == 3840,
               node + ": opens by default as " + (v4l2 ? v4l2->pixelFormat().name : "?") + " " +
                   (camera ? std::to_string((*camera)->capabilities().width_px) + "x" +
                                 std::to_string((*camera)->capabilities().height_px)
                           : camera.error().message) +
                   " (Y16 at the largest size expected)");
        auto unknown = registries->cameras.open("v4l2:" + node + "?exposure=1");
        report(!unknown && unknown.error().message.find("'exposure'") != std::string::npos,
               node + ": unknown URI parameter refused by name");
        auto absent = registries->cameras.open("v4l2:" + node + "?format=pRAA");
        report(!absent && deviceFaultOf(absent.error()) == DeviceFault::OutOfRange,
               node + ": a format vivid does not offer is [out-of-range]: " +
                   (absent ? std::string("opened!") : absent.error().message));
    }

    std::set<uint32_t> offered;
    for (uint32_t i = 0;; ++i) {
        v4l2_fmtdesc d{};
        d.index = i;
        d.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        if (side.device->ioctl(VIDIOC_ENUM_FMT, &d) != 0) break;
        offered.insert(d.pixelformat);
    }
    int tested = 0;
    for (const V4l2FormatInfo& info : v4l2Formats()) {
        if (!info.raw || !offered.count(info.fourcc)) continue;
        checkFormat(o, node, info, side, all);
        ++tested;
    }
    report(tested >= 1, node + ": " + std::to_string(tested) + " raw formats captured");

    // Start-of-exposure timestamps, and a buffer flagged as an error, on the first raw format.
    {
        auto camera = registries->cameras.open(
            "v4l2:" + node + "?format=Y16&width=" + std::to_string(o.width) +
            "&height=" + std::to_string(o.height) + "&fps=" + num(o.fps));
        if (!camera) {
            report(false, node + ": reopen: " + camera.error().message);
            return;
        }
        side.set(kTimestampSource, 1);
        auto soe = shoot(**camera, node + " SOE");
        report(soe && soe->timestamp_marks == hdr::TimestampMark::ExposureStart,
               node + ": with vivid's timestamp_source at Start of Exposure frames say so");
        side.set(kTimestampSource, 0);
        side.set(kInjectBufferError, 1);
        auto after = shoot(**camera, node + " after an error buffer");
        auto again = shoot(**camera, node + " after an error buffer");
        int64_t errors = 0;
        for (const auto& [name, value] : (*camera)->statistics())
            if (name == "buffer-errors") errors = value;
        report(after && again && errors == 1,
               node + ": a buffer vivid flags as an error is skipped and counted (" +
                   std::to_string(errors) + ")");
    }
}

// A real camera in the lab, pointed at a steady, evenly lit scene (a diffuser, a grey card):
// frames arrive with the negotiated size and depth and rising timestamps; with an exposure
// control, doubling the exposure about doubles the signal above the darkest exposure's, and
// the first frame after a change is as bright as the third (settle_frames is enough).
int labCheck(const std::string& uri) {
    auto registries = makeRigRegistries(RigOptions{});
    if (!registries) return 1;
    auto opened = registries->cameras.open(uri);
    if (!opened) {
        report(false, uri + ": " + opened.error().message);
        return 1;
    }
    Camera& camera = **opened;
    auto* v4l2 = dynamic_cast<V4l2Camera*>(&camera);
    const CameraCapabilities caps = camera.capabilities();
    const char* modes[] = {"exposure_time_absolute (100 us)", "exposure (lines)",
                           "none (frame interval)"};
    std::printf(
        "CAMERA %s: %s %lldx%lld, %d bit, exposure %s %g..%g s, line time %g us, "
        "frame interval %g s, settle %d frames, gain %g..%g, response %s\n",
        uri.c_str(), v4l2 ? v4l2->pixelFormat().name : "?", static_cast<long long>(caps.width_px),
        static_cast<long long>(caps.height_px), caps.bit_depth,
        v4l2 ? modes[static_cast<int>(v4l2->exposureMode())] : "?", caps.min_exposure_s,
        caps.max_exposure_s, v4l2 ? v4l2->lineTime_s() * 1e6 : 0.0,
        v4l2 ? v4l2->frameInterval_s() : 0.0, v4l2 ? v4l2->settleFrames() : 0, caps.min_gain,
        caps.max_gain, caps.response_note.c_str());
    if (v4l2)
        for (const std::string& w : v4l2->warnings()) std::printf("WARNING %s\n", w.c_str());

    std::optional<hdr::RawFrame> previous;
    for (int i = 0; i < 3; ++i) {
        auto frame =
            shoot(camera, uri + " frame " + std::to_string(i), 10.0 + 3.0 * caps.max_exposure_s);
        if (!frame) return 1;
        const bool ok = frame->width == caps.width_px && frame->height == caps.height_px &&
                        frame->bit_depth == caps.bit_depth &&
                        (!previous || (frame->timestamp_ns > previous->timestamp_ns &&
                                       frame->sequence > previous->sequence));
        const char* marks[] = {"unknown", "exposure start", "exposure end", "frame arrival"};
        report(ok, uri + ": frame " + std::to_string(frame->sequence) + " " +
                       std::to_string(frame->width) + "x" + std::to_string(frame->height) +
                       ", timestamp marks " + marks[static_cast<int>(frame->timestamp_marks)] +
                       ", mean " + num(meanOf(*frame)) + ", exposure " + num(frame->exposure_s) +
                       " s, gain " + num(frame->gain));
        previous = std::move(frame);
    }
    if (!v4l2 || v4l2->exposureMode() == V4l2ExposureMode::FrameInterval) {
        std::printf("SUMMARY %d passed, %d failed (no exposure control to step)\n", passes,
                    failures);
        return failures == 0 ? 0 : 1;
    }
    // Exposures t, 2t, 4t from a short one, each with the first and third frame after the change.
    const double white = caps.white_level_dn;
    const double t0 =
        std::max(caps.min_exposure_s * 4.0, std::min(0.005, caps.max_exposure_s / 8.0));
    std::vector<double> means;
    for (double t : {t0, 2.0 * t0, 4.0 * t0}) {
        if (!camera.setExposure(t)) {
            report(false, uri + ": setExposure(" + num(t) + ")");
            return 1;
        }
        auto first = shoot(camera, uri + " first after change", 10.0 + 8.0 * t);
        shoot(camera, uri + " second after change", 10.0 + 4.0 * t);
        auto third = shoot(camera, uri + " third after change", 10.0 + 4.0 * t);
        if (!first || !third) return 1;
        const double m1 = meanOf(*first), m3 = meanOf(*third);
        report(std::abs(m1 - m3) <= 0.03 * std::max(m3, 1.0) + 2.0,
               uri + ": exposure " + num(first->exposure_s) + " s: first frame after the change " +
                   num(m1) + ", third " + num(m3) +
                   " (equal within 3% when settle_frames suffices)");
        means.push_back(m3);
    }
    if (means.back() > 0.8 * white) {
        std::printf("NOTE the longest exposure is near white (%g of %g): dim the scene\n",
                    means.back(), white);
    } else {
        const double ratio = (means[2] - means[1]) / std::max(means[1] - means[0], 1e-9);
        report(ratio > 1.6 && ratio < 2.4,
               uri + ": signal gained from 2t to 4t over that from t to 2t: " + num(ratio) +
                   " (2 for a linear sensor with a steady scene)");
    }
    std::printf("SUMMARY %d passed, %d failed\n", passes, failures);
    return failures == 0 ? 0 : 1;
}

}  // namespace

int main(int argc, char** argv) {
    Options o;
    for (int i = 1; i + 1 < argc; i += 2) {
        const std::string flag = argv[i], value = argv[i + 1];
        if (flag == "--dev-dir")
            o.dev_dir = value;
        else if (flag == "--width")
            o.width = std::atoi(value.c_str());
        else if (flag == "--height")
            o.height = std::atoi(value.c_str());
        else if (flag == "--fps")
            o.fps = std::atof(value.c_str());
        else if (flag == "--lab")
            o.lab_uri = value;
        else {
            std::fprintf(stderr,
                         "usage: %s [--dev-dir D] [--width W] [--height H] [--fps F]\n"
                         "       %s --lab v4l2:/dev/videoN?...   (a real camera)\n",
                         argv[0], argv[0]);
            return 2;
        }
    }
    if (!o.lab_uri.empty()) return labCheck(o.lab_uri);
    const auto started = std::chrono::steady_clock::now();

    // What `flarelab rig devices` shows: every backend's listing.
    auto registries = makeRigRegistries(RigOptions{});
    if (!registries) {
        std::printf("FAIL registries: %s\n", registries.error().message.c_str());
        return 1;
    }
    std::vector<std::string> nodes;
    for (const DeviceListing& d : listDevices(*registries)) {
        std::printf("DEVICE %s kind=%s model=%s serial=%s\n", d.uri.c_str(), d.kind.c_str(),
                    d.model.c_str(), d.serial.c_str());
        for (const std::string& line : d.details) std::printf("    %s\n", line.c_str());
        if (d.backend == "v4l2" && d.uri.rfind("v4l2:" + o.dev_dir + "/video", 0) == 0)
            nodes.push_back(d.uri.substr(5));
    }
    report(!nodes.empty(),
           "the v4l2 lister sees " + std::to_string(nodes.size()) + " capture nodes");

    std::map<std::string, FormatResult> results;
    for (const std::string& node : nodes) checkNode(o, node, results);

    // The same scene in every format: means normalized by the bit depth must agree.
    if (results.count("GREY")) {
        const FormatResult ref = results.at("GREY");
        for (const auto& [name, r] : results) {
            report(std::abs(r.white - ref.white) < 0.02 && std::abs(r.black - ref.black) < 0.02,
                   std::string(name) + ": normalized white " + num(r.white) + ", black " +
                       num(r.black) + " agree with GREY (" + num(ref.white) + ", " +
                       num(ref.black) + ") within 0.02");
        }
    }

    // Last: vivid's disconnect control unregisters the first node, as an unplugged USB camera.
    if (!nodes.empty()) {
        const std::string node = nodes.front();
        auto camera =
            registries->cameras.open("v4l2:" + node + "?width=" + std::to_string(o.width) +
                                     "&height=" + std::to_string(o.height) + "&fps=" + num(o.fps));
        auto side = openV4l2Node(node);
        if (camera && side) {
            auto first = (*camera)->capture(5.0);
            v4l2_control c{kDisconnect, 1};
            (*side)->ioctl(VIDIOC_S_CTRL, &c);
            auto gone = (*camera)->capture(2.0);
            report(first && !gone && deviceFaultOf(gone.error()) == DeviceFault::Disconnected,
                   node + ": after vivid's disconnect a capture is [disconnected]: " +
                       (gone ? std::string("frame!") : gone.error().message));
        } else {
            report(false, node + ": cannot reopen for the disconnect check");
        }
    }

    const double seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
    std::printf("SUMMARY %d passed, %d failed, %zu formats, %.1f s\n", passes, failures,
                results.size(), seconds);
    return failures == 0 && !results.empty() ? 0 : 1;
}
