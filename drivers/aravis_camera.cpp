#include "drivers/aravis_camera.h"

#include <arv.h>

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <ctime>
#include <fstream>
#include <mutex>
#include <sstream>

namespace flarelab::drivers {
namespace {

using Clock = std::chrono::steady_clock;

// Aravis keeps one process-wide device list; its updates and opens are not thread-safe.
std::mutex& aravisLock() {
    static std::mutex lock;
    return lock;
}

std::string fmt(double x) {
    std::ostringstream out;
    out << x;
    return out.str();
}

int64_t realtimeNs() {
    timespec ts{};
    clock_gettime(CLOCK_REALTIME, &ts);
    return int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

std::string lower(std::string s) {
    for (char& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
    return s;
}

// A GError owned for the length of one call.
class GErr {
public:
    GErr() = default;
    GErr(const GErr&) = delete;
    GErr& operator=(const GErr&) = delete;
    ~GErr() { clear(); }
    GError** out() {
        clear();
        return &error_;
    }
    explicit operator bool() const { return error_ != nullptr; }
    std::string message() const { return error_ && error_->message ? error_->message : ""; }
    // Errors after which the control channel cannot be trusted: no reply within Aravis's GVCP
    // retries, control privilege gone, or a USB transfer that failed.
    bool lostControl() const {
        if (!error_ || error_->domain != arv_device_error_quark()) return false;
        return error_->code == ARV_DEVICE_ERROR_TIMEOUT ||
               error_->code == ARV_DEVICE_ERROR_NOT_CONTROLLER ||
               error_->code == ARV_DEVICE_ERROR_NOT_CONNECTED ||
               error_->code == ARV_DEVICE_ERROR_TRANSFER_ERROR ||
               error_->code == ARV_DEVICE_ERROR_PROTOCOL_ERROR_ACCESS_DENIED;
    }

private:
    void clear() {
        if (error_) g_error_free(error_);
        error_ = nullptr;
    }
    GError* error_ = nullptr;
};

// A counted array of strings Aravis hands over (the array is ours, the strings are not). Call
// Aravis first and pass the count after: as arguments of one call their order is unspecified.
std::vector<std::string> takeStrings(const char** strings, guint n) {
    std::vector<std::string> out;
    for (guint i = 0; strings && i < n; ++i)
        if (strings[i]) out.emplace_back(strings[i]);
    g_free(strings);
    return out;
}

std::string joined(const std::vector<std::string>& items) {
    std::string out;
    for (const std::string& s : items) out += (out.empty() ? "" : ", ") + s;
    return out.empty() ? "none" : out;
}

const char* bufferStatusWord(ArvBufferStatus status) {
    switch (status) {
        case ARV_BUFFER_STATUS_SUCCESS:
            return "success";
        case ARV_BUFFER_STATUS_CLEARED:
            return "cleared";
        case ARV_BUFFER_STATUS_TIMEOUT:
            return "timeout";
        case ARV_BUFFER_STATUS_MISSING_PACKETS:
            return "missing-packets";
        case ARV_BUFFER_STATUS_WRONG_PACKET_ID:
            return "wrong-packet-id";
        case ARV_BUFFER_STATUS_SIZE_MISMATCH:
            return "size-mismatch";
        case ARV_BUFFER_STATUS_FILLING:
            return "filling";
        case ARV_BUFFER_STATUS_ABORTED:
            return "aborted";
        default:
            return "unknown";
    }
}

const char* bufferStatusMeaning(ArvBufferStatus status) {
    switch (status) {
        case ARV_BUFFER_STATUS_TIMEOUT:
            return "packets stopped arriving before the frame was complete";
        case ARV_BUFFER_STATUS_MISSING_PACKETS:
            return "packets of the frame were lost";
        case ARV_BUFFER_STATUS_WRONG_PACKET_ID:
            return "a packet did not belong where it arrived";
        case ARV_BUFFER_STATUS_SIZE_MISMATCH:
            return "the frame is larger than the buffer";
        case ARV_BUFFER_STATUS_ABORTED:
            return "the stream was stopped while the frame was arriving";
        default:
            return "the frame is not usable";
    }
}

// The reopen back-off: 0.25, 0.5, 1, 2, then 4 s between tries.
std::chrono::milliseconds reopenDelay(int failures) {
    const int doublings = std::clamp(failures - 1, 0, 4);
    return std::chrono::milliseconds(250 << doublings);
}

Result<int64_t> integerParam(const DeviceUri& uri, const std::string& key, int64_t lo, int64_t hi) {
    const std::string& text = uri.params.at(key);
    int64_t value = 0;
    const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
    if (ec != std::errc() || end != text.data() + text.size() || value < lo || value > hi)
        return makeError(ErrorCode::InvalidArgument, "aravis uri '" + uri.text + "': " + key + "=" +
                                                         text + " is not an integer in [" +
                                                         std::to_string(lo) + ", " +
                                                         std::to_string(hi) + "]");
    return value;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// URI options

Result<AravisOptions> aravisOptions(const DeviceUri& uri) {
    if (Status known = uri.onlyParams({"roi", "pixel_format", "packet_size", "socket_buffer",
                                       "timeout_s", "retries", "trigger", "gain_db_per_raw"});
        !known)
        return known.error().withContext("aravis");
    AravisOptions o;
    o.device = uri.path;
    const auto bad = [&](const std::string& key, const std::string& why) {
        return makeError(ErrorCode::InvalidArgument, "aravis uri '" + uri.text + "': " + key + "=" +
                                                         uri.params.at(key) + " " + why);
    };
    if (uri.params.count("roi")) {
        const std::string& text = uri.params.at("roi");
        std::vector<int64_t> v;
        size_t start = 0;
        for (;;) {
            const size_t comma = text.find(',', start);
            const std::string part =
                text.substr(start, comma == std::string::npos ? std::string::npos : comma - start);
            int64_t x = 0;
            const auto [end, ec] = std::from_chars(part.data(), part.data() + part.size(), x);
            if (part.empty() || ec != std::errc() || end != part.data() + part.size())
                return bad("roi", "is not four integers X,Y,W,H");
            v.push_back(x);
            if (comma == std::string::npos) break;
            start = comma + 1;
        }
        if (v.size() != 4) return bad("roi", "is not four integers X,Y,W,H");
        constexpr int64_t kMax = 1 << 20;
        if (v[0] < 0 || v[1] < 0 || v[2] < 1 || v[3] < 1 || v[0] > kMax || v[1] > kMax ||
            v[2] > kMax || v[3] > kMax)
            return bad("roi", "needs X, Y >= 0 and W, H >= 1 (at most 2^20)");
        o.roi = AravisRoi{v[0], v[1], v[2], v[3]};
    }
    if (uri.params.count("pixel_format")) {
        o.pixel_format = uri.params.at("pixel_format");
        if (!genicamPixelFormat(o.pixel_format))
            return bad("pixel_format",
                       "is not a raw format flarelab takes (Mono8..Mono16, Bayer<RG|BG|GR|GB>"
                       "8..16, packed 10p/12p/10Packed/12Packed)");
    }
    if (uri.params.count("packet_size")) {
        auto v = integerParam(uri, "packet_size", 576, 65535);
        if (!v) return v.error();
        o.packet_size = *v;
    }
    if (uri.params.count("socket_buffer")) {
        auto v = integerParam(uri, "socket_buffer", 4096, (int64_t{1} << 31) - 1);
        if (!v) return v.error();
        o.socket_buffer = *v;
    }
    if (uri.params.count("retries")) {
        auto v = integerParam(uri, "retries", 0, 100);
        if (!v) return v.error();
        o.retries = static_cast<int>(*v);
    }
    auto timeout = uri.number("timeout_s", o.timeout_s);
    if (!timeout) return timeout.error().withContext("aravis");
    if (!(*timeout > 0.0 && *timeout <= 600.0)) return bad("timeout_s", "is not in (0, 600] s");
    o.timeout_s = *timeout;
    if (uri.params.count("gain_db_per_raw")) {
        auto step = uri.number("gain_db_per_raw", 0.0);
        if (!step) return step.error().withContext("aravis");
        if (!(*step > 0.0 && *step <= 10.0)) return bad("gain_db_per_raw", "is not in (0, 10] dB");
        o.gain_db_per_raw = *step;
    }
    if (uri.params.count("trigger")) {
        const std::string& t = uri.params.at("trigger");
        if (t == "software")
            o.trigger = AravisTrigger::Software;
        else if (t == "single-frame")
            o.trigger = AravisTrigger::SingleFrame;
        else
            return bad("trigger", "is neither software nor single-frame");
    }
    return o;
}

std::optional<int64_t> kernelReceiveBufferLimit() {
    std::ifstream in("/proc/sys/net/core/rmem_max");
    int64_t limit = 0;
    if (!(in >> limit) || limit <= 0) return std::nullopt;
    return limit;
}

Error socketBufferTooLarge(int64_t asked, int64_t limit) {
    return makeError(
        ErrorCode::InvalidArgument,
        "aravis: socket_buffer=" + std::to_string(asked) +
            " is above the kernel's limit net.core.rmem_max = " + std::to_string(limit) +
            " bytes, which would silently give a smaller buffer and lose packets: "
            "raise it as root with `sysctl -w net.core.rmem_max=" +
            std::to_string(asked) + "` (and a line net.core.rmem_max=" + std::to_string(asked) +
            " in /etc/sysctl.d/ to keep it), or ask for at most " + std::to_string(limit));
}

// ---------------------------------------------------------------------------------------------
// One connection

struct AravisCamera::Connection {
    ArvCamera* camera = nullptr;
    ArvStream* stream = nullptr;
    gulong lost_handler = 0;
    // Set by Aravis's heartbeat thread when the camera says we no longer control it (or stopped
    // answering the heartbeat for its retry time).
    std::atomic<bool> control_lost{false};
    guint payload = 0;
    ArvPixelFormat pixel_format = 0;
    bool need_new_buffers = false;

    Connection() = default;
    Connection(const Connection&) = delete;
    Connection& operator=(const Connection&) = delete;
    // The stream first (it holds the device too), then the camera: the last unref joins the
    // heartbeat thread, so no control-lost callback can reach this object afterwards. For a
    // camera that stopped answering this takes Aravis's GVCP timeouts (~5 s), which is why lost
    // connections are released on a thread of their own.
    ~Connection() {
        if (stream) {
            arv_stream_set_emit_signals(stream, FALSE);
            g_object_unref(stream);
        }
        if (camera) g_object_unref(camera);
    }

    static void onControlLost(ArvDevice*, gpointer self) {
        static_cast<Connection*>(self)->control_lost.store(true);
    }

    // Stream counters Aravis keeps (names without their "n_").
    std::map<std::string, int64_t> counters() const {
        std::map<std::string, int64_t> out;
        if (!stream) return out;
        for (guint i = 0; i < arv_stream_get_n_infos(stream); ++i) {
            if (arv_stream_get_info_type(stream, i) != G_TYPE_UINT64) continue;
            std::string name = arv_stream_get_info_name(stream, i);
            if (name.rfind("n_", 0) == 0) name = name.substr(2);
            out[name] = static_cast<int64_t>(arv_stream_get_info_uint64(stream, i));
        }
        return out;
    }
};

// ---------------------------------------------------------------------------------------------
// AravisCamera

AravisCamera::AravisCamera(Key, AravisOptions options, std::string uri)
    : options_(std::move(options)), uri_(std::move(uri)) {
    if (!options_.pixel_format.empty()) pixel_format_ = *genicamPixelFormat(options_.pixel_format);
}

AravisCamera::~AravisCamera() {
    if (connection_ && connection_->camera && !connection_->control_lost.load()) {
        GErr e;
        arv_camera_stop_acquisition(connection_->camera, e.out());
    }
    connection_.reset();
    reapers_.clear();  // joins the releases still running
}

Result<std::unique_ptr<AravisCamera>> AravisCamera::open(const DeviceUri& uri) {
    auto options = aravisOptions(uri);
    if (!options) return options.error();
    return open(*options, uri.text);
}

Result<std::unique_ptr<AravisCamera>> AravisCamera::open(const AravisOptions& options,
                                                         const std::string& uri) {
    if (options.socket_buffer > 0)
        if (const auto limit = kernelReceiveBufferLimit(); limit && options.socket_buffer > *limit)
            return socketBufferTooLarge(options.socket_buffer, *limit);
    auto camera = std::make_unique<AravisCamera>(Key{}, options,
                                                 uri.empty() ? "aravis:" + options.device : uri);
    if (Status ok = camera->connect(options.timeout_s); !ok) return ok.error();
    if (Status ok = camera->configure(); !ok) return ok.error();
    if (Status ok = camera->startStream(); !ok) return ok.error();
    return camera;
}

std::string AravisCamera::name() const {
    if (!serial_.empty()) return "aravis " + vendor_ + " " + model_ + " " + serial_;
    return "aravis '" + (options_.device.empty() ? std::string("first camera") : options_.device) +
           "'";
}

void AravisCamera::note(std::string text) {
    if (std::find(notes_.begin(), notes_.end(), text) == notes_.end())
        notes_.push_back(std::move(text));
}

bool AravisCamera::connected() const { return connection_ && !connection_->control_lost.load(); }

// Finds and opens the camera (trying again for search_s), checks it is the one opened before,
// and takes its control channel.
Status AravisCamera::connect(double search_s) {
    auto connection = std::make_unique<Connection>();
    const auto deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                             std::chrono::duration<double>(search_s));
    std::string last_error;
    {
        std::lock_guard<std::mutex> hold(aravisLock());
        for (;;) {
            GErr e;
            connection->camera = arv_camera_new(
                options_.device.empty() ? nullptr : options_.device.c_str(), e.out());
            if (connection->camera) break;
            last_error = e ? e.message() : "no camera";
            if (Clock::now() >= deadline)
                return makeError(
                    ErrorCode::NotFound,
                    "aravis: camera '" +
                        (options_.device.empty() ? std::string("(first found)") : options_.device) +
                        "' not found within " + fmt(search_s) + " s: " + last_error +
                        " (`arv-tool-0.8` lists the cameras Aravis sees)");
            std::this_thread::sleep_for(std::chrono::milliseconds(100));
        }
    }
    ArvCamera* cam = connection->camera;
    const auto text = [](const char* s) { return std::string(s ? s : ""); };
    GErr e;
    const std::string vendor = text(arv_camera_get_vendor_name(cam, e.out()));
    const std::string model = text(arv_camera_get_model_name(cam, e.out()));
    const std::string serial = text(arv_camera_get_device_serial_number(cam, e.out()));
    const std::string device_id = text(arv_camera_get_device_id(cam, e.out()));
    if (!serial_.empty() && serial != serial_) {
        retire(std::move(connection));
        return deviceError(DeviceFault::Disconnected, name(),
                           "'" + options_.device + "' now answers as " + vendor + " " + model +
                               " " + serial + ", a different camera; not taking it");
    }
    vendor_ = vendor;
    model_ = model;
    serial_ = serial;
    device_id_ = device_id;
    fake_ = vendor == "Aravis" && model == "Fake";
    gige_ = arv_camera_is_gv_device(cam);
    if (gige_ && !arv_gv_device_is_controller(ARV_GV_DEVICE(arv_camera_get_device(cam)))) {
        // Released in the background: leaving control of a camera we do not control waits out
        // the GVCP timeouts.
        retire(std::move(connection));
        return deviceError(DeviceFault::Busy, name(),
                           "another application controls the camera (GigE Vision control "
                           "channel privilege); close it (arv-viewer, a vendor tool) and retry");
    }
    connection->lost_handler =
        g_signal_connect(arv_camera_get_device(cam), "control-lost",
                         G_CALLBACK(&Connection::onControlLost), connection.get());
    connection_ = std::move(connection);
    return Ok{};
}

// An error of a call to the camera: a lost control channel becomes [disconnected] (and the
// connection is dropped), anything else an I/O error naming what was being done.
Error AravisCamera::controlError(const std::string& doing, const std::string& detail) {
    return makeError(ErrorCode::IoError, name() + ": " + doing + ": " + detail);
}

// Drops the connection. A loss found while reopening only fails that attempt (ensureConnected
// keeps the first reason and the back-off).
Error AravisCamera::lose(const std::string& why) {
    if (connection_) retire(std::move(connection_));
    if (reopening_) return deviceError(DeviceFault::Disconnected, name(), why);
    ++disconnects_;
    lost_reason_ = why;
    reopen_failures_ = 0;
    next_reopen_ = Clock::now();
    return deviceError(DeviceFault::Disconnected, name(),
                       why + "; the next call reopens the camera and applies its settings again");
}

void AravisCamera::retire(std::unique_ptr<Connection> connection) {
    for (const auto& [key, value] : connection->counters()) stream_totals_[key] += value;
    // Keep a few releases in flight; the oldest has long finished when a ninth comes.
    constexpr size_t kMaxReapers = 8;
    if (reapers_.size() >= kMaxReapers) reapers_.erase(reapers_.begin());
    reapers_.emplace_back([c = std::move(connection)]() mutable { c.reset(); });
}

// Everything a reopened camera must be told again, in the order cameras lock them: stop,
// binning, pixel format, region, trigger, exposure, gain, packet size.
Status AravisCamera::configure() {
    ArvCamera* cam = connection_->camera;
    GErr e;
    const auto check = [&](const std::string& doing) -> Status {
        if (!e) return Ok{};
        if (e.lostControl()) return lose("no answer while " + doing + ": " + e.message());
        return controlError(doing, e.message());
    };
    const auto has = [&](const char* feature) {
        GErr probe;
        return arv_camera_is_feature_available(cam, feature, probe.out()) && !probe;
    };
    const auto hasEntry = [&](const char* feature, const char* entry) {
        GErr probe;
        return arv_camera_is_enumeration_entry_available(cam, feature, entry, probe.out()) &&
               !probe;
    };

    arv_camera_stop_acquisition(cam, e.out());
    if (Status s = check("stopping the acquisition"); !s) return s;
    // A trigger left on by another application would hold back the format changes below.
    if (has("TriggerMode")) {
        arv_camera_set_string(cam, "TriggerMode", "Off", e.out());
        if (Status s = check("switching TriggerMode off"); !s) return s;
    }
    if (arv_camera_is_binning_available(cam, nullptr)) {
        arv_camera_set_binning(cam, 1, 1, e.out());
        if (Status s = check("setting binning 1 x 1"); !s) return s;
    }

    // Pixel format: the pinned or chosen one, else the best offered.
    guint n = 0;
    const char** offered = arv_camera_dup_available_pixel_formats_as_strings(cam, &n, e.out());
    offered_formats_ = takeStrings(offered, n);
    if (Status s = check("listing pixel formats"); !s) return s;
    const auto ranked = rankGenicamPixelFormats(offered_formats_);
    if (ranked.empty())
        return makeError(ErrorCode::Unsupported,
                         name() + ": offers no raw pixel format flarelab takes (it offers " +
                             joined(offered_formats_) + ")");
    if (pixel_format_.name.empty()) pixel_format_ = ranked.front();
    if (std::find(offered_formats_.begin(), offered_formats_.end(), pixel_format_.name) ==
        offered_formats_.end())
        return makeError(ErrorCode::InvalidArgument,
                         name() + ": pixel_format=" + pixel_format_.name +
                             " is not offered by the camera (it offers " +
                             joined(offered_formats_) + ")");
    if (Status s = applyFormat(pixel_format_); !s) return s;

    // Region: asked for, or the whole sensor.
    gint sensor_w = 0, sensor_h = 0, wmin = 0, wmax = 0, hmin = 0, hmax = 0;
    arv_camera_get_sensor_size(cam, &sensor_w, &sensor_h, e.out());
    if (Status s = check("reading the sensor size"); !s) return s;
    arv_camera_get_width_bounds(cam, &wmin, &wmax, e.out());
    if (Status s = check("reading the width bounds"); !s) return s;
    arv_camera_get_height_bounds(cam, &hmin, &hmax, e.out());
    if (Status s = check("reading the height bounds"); !s) return s;
    AravisRoi roi{0, 0, wmax, hmax};
    if (options_.roi) {
        roi = *options_.roi;
        if (roi.x + roi.width > sensor_w || roi.y + roi.height > sensor_h || roi.width < wmin ||
            roi.width > wmax || roi.height < hmin || roi.height > hmax)
            return makeError(ErrorCode::InvalidArgument,
                             name() + ": roi=" + std::to_string(roi.x) + "," +
                                 std::to_string(roi.y) + "," + std::to_string(roi.width) + "," +
                                 std::to_string(roi.height) + " does not fit the sensor of " +
                                 std::to_string(sensor_w) + " x " + std::to_string(sensor_h) +
                                 " (width " + std::to_string(wmin) + ".." + std::to_string(wmax) +
                                 ", height " + std::to_string(hmin) + ".." + std::to_string(hmax) +
                                 ")");
    }
    arv_camera_set_region(cam, static_cast<gint>(roi.x), static_cast<gint>(roi.y),
                          static_cast<gint>(roi.width), static_cast<gint>(roi.height), e.out());
    if (Status s = check("setting the region"); !s) return s;
    gint rx = 0, ry = 0, rw = 0, rh = 0;
    arv_camera_get_region(cam, &rx, &ry, &rw, &rh, e.out());
    if (Status s = check("reading the region back"); !s) return s;
    if (options_.roi && (rx != roi.x || ry != roi.y || rw != roi.width || rh != roi.height)) {
        GErr ignored;
        const gint wstep = arv_camera_get_width_increment(cam, ignored.out());
        const gint hstep = arv_camera_get_height_increment(cam, ignored.out());
        return makeError(ErrorCode::InvalidArgument,
                         name() + ": roi=" + std::to_string(roi.x) + "," + std::to_string(roi.y) +
                             "," + std::to_string(roi.width) + "," + std::to_string(roi.height) +
                             " is off the camera's steps: it took " + std::to_string(rx) + "," +
                             std::to_string(ry) + "," + std::to_string(rw) + "," +
                             std::to_string(rh) + " (width step " + std::to_string(wstep) +
                             ", height step " + std::to_string(hstep) + ")");
    }
    width_ = rw;
    height_ = rh;

    // Packet size (GigE Vision).
    if (options_.packet_size > 0) {
        if (!gige_)
            return makeError(ErrorCode::InvalidArgument,
                             name() + ": packet_size applies to GigE Vision cameras only");
        arv_camera_gv_set_packet_size(cam, static_cast<gint>(options_.packet_size), e.out());
        if (Status s = check("setting packet_size=" + std::to_string(options_.packet_size)); !s)
            return s;
    }

    // Trigger: one frame per exposure.
    const bool software =
        has("TriggerMode") && has("TriggerSoftware") && hasEntry("TriggerSource", "Software");
    const bool single = hasEntry("AcquisitionMode", "SingleFrame");
    if (options_.trigger == AravisTrigger::Software && !software)
        return makeError(ErrorCode::InvalidArgument,
                         name() +
                             ": trigger=software: the camera has no software trigger "
                             "(TriggerMode, TriggerSource=Software, TriggerSoftware)");
    if (options_.trigger == AravisTrigger::SingleFrame && !single)
        return makeError(ErrorCode::InvalidArgument,
                         name() +
                             ": trigger=single-frame: the camera's AcquisitionMode has no "
                             "SingleFrame");
    if (options_.trigger == AravisTrigger::Auto && !software && !single)
        return makeError(ErrorCode::Unsupported,
                         name() +
                             ": can take neither a software trigger nor a single-frame "
                             "acquisition, so it cannot take one frame per exposure");
    trigger_ = options_.trigger != AravisTrigger::Auto
                   ? options_.trigger
                   : (software ? AravisTrigger::Software : AravisTrigger::SingleFrame);
    if (has("TriggerSelector")) {
        // Only FrameStart may wait for a trigger: an AcquisitionStart trigger left on would hold
        // every frame.
        guint n_selectors = 0;
        const char** listed = arv_camera_dup_available_enumerations_as_strings(
            cam, "TriggerSelector", &n_selectors, e.out());
        const auto selectors = takeStrings(listed, n_selectors);
        if (Status s = check("listing TriggerSelector"); !s) return s;
        for (const std::string& selector : selectors) {
            GErr ignored;  // a selector that is not writable (the fake's) is simply skipped
            arv_camera_set_string(cam, "TriggerSelector", selector.c_str(), ignored.out());
            if (!ignored) arv_camera_set_string(cam, "TriggerMode", "Off", ignored.out());
            if (ignored.lostControl()) return lose("no answer while setting TriggerSelector");
        }
        if (trigger_ == AravisTrigger::Software && hasEntry("TriggerSelector", "FrameStart")) {
            GErr ignored;
            arv_camera_set_string(cam, "TriggerSelector", "FrameStart", ignored.out());
            if (ignored.lostControl()) return lose("no answer while setting TriggerSelector");
        }
    }
    if (trigger_ == AravisTrigger::Software) {
        arv_camera_set_string(cam, "AcquisitionMode", "Continuous", e.out());
        if (Status s = check("setting AcquisitionMode Continuous"); !s) return s;
        arv_camera_set_string(cam, "TriggerSource", "Software", e.out());
        if (Status s = check("setting TriggerSource Software"); !s) return s;
        arv_camera_set_string(cam, "TriggerMode", "On", e.out());
        if (Status s = check("setting TriggerMode On"); !s) return s;
    } else {
        arv_camera_set_string(cam, "AcquisitionMode", "SingleFrame", e.out());
        if (Status s = check("setting AcquisitionMode SingleFrame"); !s) return s;
    }

    // Exposure and gain: manual, then the wanted values (the camera's own on the first open).
    if (Status s = readRanges(); !s) return s;
    if (wanted_exposure_s_ <= 0.0) {
        const double us = arv_camera_get_float(cam, exposure_feature_.c_str(), e.out());
        if (Status s = check("reading " + exposure_feature_); !s) return s;
        wanted_exposure_s_ = std::clamp(us * 1e-6, min_exposure_s_, max_exposure_s_);
    }
    if (Status s = applyExposure(wanted_exposure_s_); !s) return s;
    if (!(wanted_gain_ >= min_gain_ && wanted_gain_ <= max_gain_)) wanted_gain_ = min_gain_;
    if (Status s = applyGain(wanted_gain_); !s) return s;
    return Ok{};
}

// The exposure and gain features and their ranges, and manual control of both.
Status AravisCamera::readRanges() {
    ArvCamera* cam = connection_->camera;
    GErr e;
    const auto check = [&](const std::string& doing) -> Status {
        if (!e) return Ok{};
        if (e.lostControl()) return lose("no answer while " + doing + ": " + e.message());
        return controlError(doing, e.message());
    };
    const auto has = [&](const char* feature) {
        GErr probe;
        return arv_camera_is_feature_available(cam, feature, probe.out()) && !probe;
    };
    if (has("ExposureAuto")) {
        arv_camera_set_string(cam, "ExposureAuto", "Off", e.out());
        if (Status s = check("setting ExposureAuto Off"); !s) return s;
    }
    if (has("ExposureTime"))
        exposure_feature_ = "ExposureTime";
    else if (has("ExposureTimeAbs"))
        exposure_feature_ = "ExposureTimeAbs";
    else
        return makeError(ErrorCode::Unsupported,
                         name() + ": has neither ExposureTime nor ExposureTimeAbs");
    double lo = 0.0, hi = 0.0;
    arv_camera_get_float_bounds(cam, exposure_feature_.c_str(), &lo, &hi, e.out());
    if (Status s = check("reading the bounds of " + exposure_feature_); !s) return s;
    min_exposure_s_ = lo * 1e-6;
    max_exposure_s_ = hi * 1e-6;

    if (has("GainAuto")) {
        arv_camera_set_string(cam, "GainAuto", "Off", e.out());
        if (Status s = check("setting GainAuto Off"); !s) return s;
    }
    if (has("Gain")) {
        gain_feature_ = "Gain";
        ArvGcNode* node = arv_device_get_feature(arv_camera_get_device(cam), "Gain");
        const char* unit =
            ARV_IS_GC_FLOAT(node) ? arv_gc_float_get_unit(ARV_GC_FLOAT(node)) : nullptr;
        const std::string u = lower(unit ? unit : "");
        gain_in_db_ = !(u == "x" || u == "times");
        if (u.empty())
            note("Gain has no unit: read as dB, the unit GenICam's SFNC gives it");
        else if (gain_in_db_ && u.find("db") == std::string::npos)
            note("Gain's unit '" + std::string(unit) + "' is not dB: read as dB all the same");
        arv_camera_get_float_bounds(cam, "Gain", &lo, &hi, e.out());
        if (Status s = check("reading the bounds of Gain"); !s) return s;
        min_gain_ = gain_in_db_ ? std::pow(10.0, lo / 20.0) : lo;
        max_gain_ = gain_in_db_ ? std::pow(10.0, hi / 20.0) : hi;
    } else if (has("GainRaw")) {
        gain_feature_ = "GainRaw";
        gint64 rlo = 0, rhi = 0;
        arv_camera_get_integer_bounds(cam, "GainRaw", &rlo, &rhi, e.out());
        if (Status s = check("reading the bounds of GainRaw"); !s) return s;
        min_gain_raw_ = static_cast<double>(rlo);
        max_gain_raw_ = static_cast<double>(rhi);
        if (options_.gain_db_per_raw > 0.0) {
            min_gain_ = std::pow(10.0, min_gain_raw_ * options_.gain_db_per_raw / 20.0);
            max_gain_ = std::pow(10.0, max_gain_raw_ * options_.gain_db_per_raw / 20.0);
        } else {
            min_gain_ = max_gain_ = 1.0;
            note(
                "the camera has only GainRaw, of no known scale: it is held at its lowest raw "
                "gain, reported as gain 1 (give gain_db_per_raw=DB from its manual to use it)");
        }
    } else {
        gain_feature_.clear();
        min_gain_ = max_gain_ = 1.0;
        note("the camera has no Gain or GainRaw feature: gain is 1");
    }
    return Ok{};
}

Status AravisCamera::applyFormat(const GenicamPixelFormat& format) {
    ArvCamera* cam = connection_->camera;
    GErr e;
    arv_camera_set_pixel_format_from_string(cam, format.name.c_str(), e.out());
    if (e) {
        if (e.lostControl()) return lose("no answer while setting PixelFormat: " + e.message());
        return controlError("setting PixelFormat " + format.name, e.message());
    }
    const char* now = arv_camera_get_pixel_format_as_string(cam, e.out());
    if (e.lostControl()) return lose("no answer while reading PixelFormat: " + e.message());
    if (!now || format.name != now)
        return controlError("setting PixelFormat " + format.name,
                            std::string("the camera kept ") + (now ? now : "(none)"));
    connection_->pixel_format = arv_camera_get_pixel_format(cam, e.out());
    pixel_format_ = format;
    if (format.bits <= 8)
        note("warning: pixel format " + format.name +
             " has 8 bits, too few for the range of a flare measurement (the camera offers " +
             joined(offered_formats_) + ")");
    return Ok{};
}

Status AravisCamera::applyExposure(double exposure_s) {
    ArvCamera* cam = connection_->camera;
    GErr e;
    arv_camera_set_float(cam, exposure_feature_.c_str(), exposure_s * 1e6, e.out());
    if (e) {
        if (e.lostControl())
            return lose("no answer while setting " + exposure_feature_ + ": " + e.message());
        // In range (setExposure checked): the camera refused for its own reasons (a feature
        // locked while acquiring, ...).
        return controlError("setting " + exposure_feature_ + " to " + fmt(exposure_s * 1e6) + " us",
                            e.message());
    }
    const double us = arv_camera_get_float(cam, exposure_feature_.c_str(), e.out());
    if (e) {
        if (e.lostControl())
            return lose("no answer while reading " + exposure_feature_ + ": " + e.message());
        return controlError("reading " + exposure_feature_ + " back", e.message());
    }
    if (!(us > 0.0) || !std::isfinite(us))
        return controlError("reading " + exposure_feature_ + " back",
                            "the camera says " + fmt(us) + " us");
    exposure_s_ = us * 1e-6;
    return Ok{};
}

Status AravisCamera::applyGain(double gain) {
    ArvCamera* cam = connection_->camera;
    GErr e;
    const auto failed = [&](const std::string& doing) -> Status {
        if (e.lostControl()) return lose("no answer while " + doing + ": " + e.message());
        return controlError(doing, e.message());
    };
    if (gain_feature_ == "Gain") {
        const double value = gain_in_db_ ? 20.0 * std::log10(gain) : gain;
        double lo = 0.0, hi = 0.0;
        arv_camera_get_float_bounds(cam, "Gain", &lo, &hi, e.out());
        if (e) return failed("reading the bounds of Gain");
        arv_camera_set_float(cam, "Gain", std::clamp(value, lo, hi), e.out());
        if (e) return failed("setting Gain");
        const double now = arv_camera_get_float(cam, "Gain", e.out());
        if (e) return failed("reading Gain back");
        gain_ = gain_in_db_ ? std::pow(10.0, now / 20.0) : now;
    } else if (gain_feature_ == "GainRaw") {
        const double k = options_.gain_db_per_raw;
        const double raw = k > 0.0 ? std::round(20.0 * std::log10(gain) / k) : min_gain_raw_;
        arv_camera_set_integer(cam, "GainRaw",
                               static_cast<gint64>(std::clamp(raw, min_gain_raw_, max_gain_raw_)),
                               e.out());
        if (e) return failed("setting GainRaw");
        const gint64 now = arv_camera_get_integer(cam, "GainRaw", e.out());
        if (e) return failed("reading GainRaw back");
        gain_ = k > 0.0 ? std::pow(10.0, static_cast<double>(now) * k / 20.0) : 1.0;
    } else {
        gain_ = 1.0;
    }
    if (!(gain_ > 0.0) || !std::isfinite(gain_))
        return controlError("reading the gain back", "the camera says " + fmt(gain_));
    return Ok{};
}

// A stream with a pool of buffers of the camera's payload size; the acquisition runs from here
// on in software-trigger mode.
Status AravisCamera::startStream() {
    ArvCamera* cam = connection_->camera;
    GErr e;
    if (connection_->stream) {
        // A new pool (another format, or buffers too small): stop the frames first.
        arv_camera_stop_acquisition(cam, e.out());
        if (e.lostControl()) return lose("no answer while stopping the acquisition");
        g_object_unref(connection_->stream);
        connection_->stream = nullptr;
    }
    connection_->payload = arv_camera_get_payload(cam, e.out());
    if (e) {
        if (e.lostControl()) return lose("no answer while reading PayloadSize: " + e.message());
        return controlError("reading PayloadSize", e.message());
    }
    // Aravis reads GVSP through a packet-socket ring when it may (root, CAP_NET_RAW), where no
    // socket buffer applies; a socket buffer asked for means the UDP socket that has one.
    if (gige_ && options_.socket_buffer > 0)
        arv_camera_gv_set_stream_options(cam, ARV_GV_STREAM_OPTION_PACKET_SOCKET_DISABLED);
    connection_->stream = arv_camera_create_stream(cam, nullptr, nullptr, e.out());
    if (!connection_->stream) {
        if (e.lostControl()) return lose("no answer while creating the stream: " + e.message());
        return controlError("creating the stream", e ? e.message() : "no stream");
    }
    constexpr int kBuffers = 4;  // one frame at a time; spares hold stale or damaged frames
    for (int i = 0; i < kBuffers; ++i)
        arv_stream_push_buffer(connection_->stream, arv_buffer_new_allocate(connection_->payload));
    connection_->need_new_buffers = false;

    if (gige_ && ARV_IS_GV_STREAM(connection_->stream)) {
        if (options_.socket_buffer > 0) {
            g_object_set(connection_->stream, "socket-buffer", ARV_GV_STREAM_SOCKET_BUFFER_FIXED,
                         "socket-buffer-size", static_cast<gint>(options_.socket_buffer), nullptr);
        } else {
            // As large as a frame; the kernel caps it at net.core.rmem_max without a word.
            g_object_set(connection_->stream, "socket-buffer", ARV_GV_STREAM_SOCKET_BUFFER_AUTO,
                         "socket-buffer-size", 0, nullptr);
            if (const auto limit = kernelReceiveBufferLimit();
                limit && static_cast<int64_t>(connection_->payload) > *limit)
                note("frames of " + std::to_string(connection_->payload) +
                     " bytes exceed the socket buffer the kernel allows (net.core.rmem_max = " +
                     std::to_string(*limit) +
                     "): packets may be lost; as root: sysctl -w net.core.rmem_max=" +
                     std::to_string(connection_->payload));
        }
        packet_size_ = arv_camera_gv_get_packet_size(cam, e.out());
        if (e) {
            if (e.lostControl()) return lose("no answer while reading the packet size");
            return controlError("reading the packet size", e.message());
        }
        if (options_.packet_size > 0 && packet_size_ != options_.packet_size)
            note("packet_size=" + std::to_string(options_.packet_size) +
                 " asked, the camera uses " + std::to_string(packet_size_) +
                 " (check the MTU of the interface: ip link)");
    }
    if (trigger_ == AravisTrigger::Software) {
        arv_camera_start_acquisition(cam, e.out());
        if (e) {
            if (e.lostControl()) return lose("no answer while starting the acquisition");
            return controlError("starting the acquisition", e.message());
        }
    }
    return Ok{};
}

Status AravisCamera::ensureConnected() {
    if (connection_ && connection_->control_lost.load())
        return lose(
            "Aravis's heartbeat reported control-lost (the camera stopped answering or "
            "was restarted)");
    if (connection_) return Ok{};
    const auto now = Clock::now();
    if (now < next_reopen_) {
        const double wait_s = std::chrono::duration<double>(next_reopen_ - now).count();
        return deviceError(DeviceFault::Disconnected, name(),
                           lost_reason_ + "; next reopen attempt in " +
                               fmt(std::round(wait_s * 100) / 100) + " s");
    }
    // One search per attempt (Aravis's own: ~1 s by id, 2.5 s by address): the back-off, not
    // this call, spreads the attempts out.
    reopening_ = true;
    Status reopened = connect(0.0);
    if (reopened) reopened = configure();
    if (reopened) reopened = startStream();
    reopening_ = false;
    if (reopened) {
        ++reopens_;
        reopen_failures_ = 0;
        lost_reason_.clear();
        return Ok{};
    }
    if (connection_) retire(std::move(connection_));
    ++reopen_failures_;
    next_reopen_ = Clock::now() + reopenDelay(reopen_failures_);
    const Error& why = reopened.error();
    if (deviceFaultOf(why) == DeviceFault::Busy) return why;
    return deviceError(
        DeviceFault::Disconnected, name(),
        lost_reason_ + "; reopening failed (attempt " + std::to_string(reopen_failures_) +
            "): " + why.message + "; next attempt in " +
            fmt(std::chrono::duration<double>(reopenDelay(reopen_failures_)).count()) + " s");
}

DeviceIdentity AravisCamera::identity() const {
    return {"aravis", vendor_ + " " + model_, serial_, uri_};
}

CameraCapabilities AravisCamera::capabilities() const {
    CameraCapabilities c;
    c.width_px = width_;
    c.height_px = height_;
    if (!options_.pixel_format.empty()) {
        c.formats.push_back(pixel_format_.layout);
    } else {
        for (const GenicamPixelFormat& f : rankGenicamPixelFormats(offered_formats_))
            if (std::find(c.formats.begin(), c.formats.end(), f.layout) == c.formats.end())
                c.formats.push_back(f.layout);
    }
    c.bit_depth = pixel_format_.bits;
    c.min_exposure_s = min_exposure_s_;
    c.max_exposure_s = max_exposure_s_;
    c.min_gain = min_gain_;
    c.max_gain = max_gain_;
    c.black_level_dn = 0.0;
    c.white_level_dn = std::ldexp(1.0, pixel_format_.bits) - 1.0;
    if (fake_) {
        c.response = CameraResponse::NonLinear;
        c.response_note =
            "Aravis's fake camera draws a diagonal ramp scaled by 1 + GainRaw + log10(exposure / "
            "10 ms) and clipped (arv_fake_camera_diagonal_ramp, src/arvfakecamera.c): its "
            "brightness grows with the logarithm of the exposure and is 0 at 1 ms and below";
    } else {
        c.response = CameraResponse::Linear;
        c.response_note = "raw GenICam output, taken as linear; `flarelab calibrate` measures it";
    }
    return c;
}

double AravisCamera::exposure_s() const { return exposure_s_; }
double AravisCamera::gain() const { return gain_; }
hdr::RawFormat AravisCamera::format() const { return pixel_format_.layout; }

Status AravisCamera::setExposure(double exposure_s) {
    // Relative slack for ranges read in microseconds.
    const double slack = 1e-9 * std::max(1.0, std::abs(exposure_s));
    if (!std::isfinite(exposure_s) || exposure_s < min_exposure_s_ - slack ||
        exposure_s > max_exposure_s_ + slack)
        return deviceError(DeviceFault::OutOfRange, name(),
                           "exposure_s " + fmt(exposure_s) + " is outside [" +
                               fmt(min_exposure_s_) + ", " + fmt(max_exposure_s_) + "] s");
    if (Status s = ensureConnected(); !s) return s;
    const double before = exposure_s_;
    if (Status s = applyExposure(std::clamp(exposure_s, min_exposure_s_, max_exposure_s_)); !s) {
        exposure_s_ = before;
        return s;
    }
    wanted_exposure_s_ = exposure_s;
    return Ok{};
}

Status AravisCamera::setGain(double gain) {
    const double slack = 1e-9 * std::max(1.0, std::abs(gain));
    if (!std::isfinite(gain) || gain < min_gain_ - slack || gain > max_gain_ + slack)
        return deviceError(DeviceFault::OutOfRange, name(),
                           "gain " + fmt(gain) + " is outside [" + fmt(min_gain_) + ", " +
                               fmt(max_gain_) + "]" +
                               (gain_feature_ == "GainRaw" && options_.gain_db_per_raw <= 0.0
                                    ? " (GainRaw of unknown scale: give gain_db_per_raw)"
                                    : ""));
    if (Status s = ensureConnected(); !s) return s;
    const double before = gain_;
    if (Status s = applyGain(std::clamp(gain, min_gain_, max_gain_)); !s) {
        gain_ = before;
        return s;
    }
    wanted_gain_ = gain;
    return Ok{};
}

Status AravisCamera::setFormat(hdr::RawFormat format) {
    if (format == pixel_format_.layout) return Ok{};
    if (!options_.pixel_format.empty())
        return deviceError(DeviceFault::OutOfRange, name(),
                           "format: the URI pins pixel_format=" + options_.pixel_format);
    const auto chosen = chooseGenicamPixelFormat(offered_formats_, format);
    if (!chosen)
        return deviceError(DeviceFault::OutOfRange, name(),
                           "format: the camera offers no such raw format (it offers " +
                               joined(offered_formats_) + ")");
    if (Status s = ensureConnected(); !s) return s;
    ArvCamera* cam = connection_->camera;
    GErr e;
    arv_camera_stop_acquisition(cam, e.out());
    if (e.lostControl()) return lose("no answer while stopping the acquisition");
    if (trigger_ == AravisTrigger::Software) {
        // Formats are locked while a trigger waits on some cameras.
        arv_camera_set_string(cam, "TriggerMode", "Off", e.out());
        if (e.lostControl()) return lose("no answer while switching TriggerMode off");
    }
    const GenicamPixelFormat before = pixel_format_;
    Status applied = applyFormat(*chosen);
    if (!applied && connection_) {
        GErr ignored;
        arv_camera_set_pixel_format_from_string(cam, before.name.c_str(), ignored.out());
        pixel_format_ = before;
    }
    if (!connection_) return applied;
    if (trigger_ == AravisTrigger::Software) {
        arv_camera_set_string(cam, "TriggerMode", "On", e.out());
        if (e.lostControl()) return lose("no answer while switching TriggerMode on");
    }
    if (Status s = startStream(); !s) return s;
    return applied;
}

// Puts back every buffer the stream holds: frames left from a failed take.
void AravisCamera::drainStream() {
    while (ArvBuffer* b = arv_stream_try_pop_buffer(connection_->stream))
        arv_stream_push_buffer(connection_->stream, b);
}

Result<hdr::RawFrame> AravisCamera::takeOnce(double timeout_s) {
    Connection& c = *connection_;
    if (c.need_new_buffers)
        if (Status s = startStream(); !s) return s.error();
    drainStream();
    GErr e;
    const int64_t fired_ns = realtimeNs();
    if (trigger_ == AravisTrigger::Software)
        arv_camera_software_trigger(c.camera, e.out());
    else
        arv_camera_start_acquisition(c.camera, e.out());
    if (e) {
        if (e.lostControl()) return lose("no answer to the trigger: " + e.message());
        return controlError("triggering", e.message());
    }

    const auto deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                             std::chrono::duration<double>(timeout_s));
    ArvBuffer* buffer = nullptr;
    // Aravis's heartbeat needs ~7 s to report a camera that stopped answering; a read of our own
    // each second of a long wait finds it after Aravis's GVCP retries (2.5 s).
    auto next_probe = Clock::now() + std::chrono::seconds(1);
    for (;;) {
        if (aborted_) {
            // A software-triggered exposure runs out on the camera; its frame, if it comes, is
            // an earlier take's to the next one (dated before its trigger) and is dropped.
            if (trigger_ == AravisTrigger::SingleFrame) {
                GErr ignored;
                arv_camera_stop_acquisition(c.camera, ignored.out());
            }
            return deviceError(DeviceFault::Stopped, name(), "the capture was aborted");
        }
        if (c.control_lost.load())
            return lose("Aravis's heartbeat reported control-lost while waiting for a frame");
        if (Clock::now() >= next_probe) {
            arv_camera_get_float(c.camera, exposure_feature_.c_str(), e.out());
            if (e.lostControl())
                return lose("no answer on the control channel while waiting for a frame: " +
                            e.message());
            next_probe = Clock::now() + std::chrono::seconds(1);
        }
        const auto left = deadline - Clock::now();
        if (left <= Clock::duration::zero()) break;
        // Short slices so that a lost control channel ends the wait early.
        const auto slice = std::min<Clock::duration>(left, std::chrono::milliseconds(50));
        buffer = arv_stream_timeout_pop_buffer(
            c.stream,
            static_cast<guint64>(std::max<int64_t>(
                1, std::chrono::duration_cast<std::chrono::microseconds>(slice).count())));
        if (!buffer) continue;
        // A complete frame whose leader came before the trigger belongs to an earlier take.
        if (arv_buffer_get_status(buffer) == ARV_BUFFER_STATUS_SUCCESS &&
            static_cast<int64_t>(arv_buffer_get_system_timestamp(buffer)) < fired_ns) {
            arv_stream_push_buffer(c.stream, buffer);
            buffer = nullptr;
            continue;
        }
        break;
    }
    const int64_t host_ns = realtimeNs();
    if (trigger_ == AravisTrigger::SingleFrame) {
        arv_camera_stop_acquisition(c.camera, e.out());
        if (e.lostControl()) {
            if (buffer) arv_stream_push_buffer(c.stream, buffer);
            return lose("no answer while stopping the acquisition: " + e.message());
        }
    }
    if (!buffer) {
        // Is the camera still there? A read of the exposure goes over the control channel.
        arv_camera_get_float(c.camera, exposure_feature_.c_str(), e.out());
        if (e.lostControl())
            return lose("no frame within " + fmt(timeout_s) +
                        " s and no answer on the control channel: " + e.message());
        return deviceError(
            DeviceFault::Timeout, name(),
            "no frame within " + fmt(timeout_s) + " s of the " +
                (trigger_ == AravisTrigger::Software ? "software trigger" : "acquisition start") +
                " (exposure " + fmt(exposure_s_) + " s)");
    }

    // From here on the buffer goes back to the pool whatever happens.
    struct Requeue {
        ArvStream* stream;
        ArvBuffer* buffer;
        ~Requeue() { arv_stream_push_buffer(stream, buffer); }
    } requeue{c.stream, buffer};
    const ArvBufferStatus status = arv_buffer_get_status(buffer);
    const int64_t frame_id = static_cast<int64_t>(arv_buffer_get_frame_id(buffer));
    if (status != ARV_BUFFER_STATUS_SUCCESS) {
        if (status == ARV_BUFFER_STATUS_SIZE_MISMATCH) c.need_new_buffers = true;
        return deviceError(DeviceFault::BadFrame, name(),
                           std::string("frame ") + std::to_string(frame_id) + ": buffer status " +
                               bufferStatusWord(status) + ": " + bufferStatusMeaning(status));
    }
    const ArvBufferPayloadType type = arv_buffer_get_payload_type(buffer);
    if (type != ARV_BUFFER_PAYLOAD_TYPE_IMAGE &&
        type != ARV_BUFFER_PAYLOAD_TYPE_EXTENDED_CHUNK_DATA)
        return deviceError(DeviceFault::BadFrame, name(),
                           "frame " + std::to_string(frame_id) + ": payload type " +
                               std::to_string(static_cast<int>(type)) + " is not an image");
    if (arv_buffer_get_image_pixel_format(buffer) != c.pixel_format)
        return deviceError(
            DeviceFault::BadFrame, name(),
            "frame " + std::to_string(frame_id) + ": pixel format 0x" +
                [](ArvPixelFormat f) {
                    std::ostringstream out;
                    out << std::hex << f;
                    return out.str();
                }(arv_buffer_get_image_pixel_format(buffer)) +
                " is not the " + pixel_format_.name + " that was set");
    gint x_padding = 0, y_padding = 0;
    arv_buffer_get_image_padding(buffer, &x_padding, &y_padding);
    const int64_t width = arv_buffer_get_image_width(buffer);
    const int64_t height = arv_buffer_get_image_height(buffer);
    size_t size = 0;
    const auto* data = static_cast<const uint8_t*>(arv_buffer_get_image_data(buffer, &size));
    auto samples = unpackGenicamPixels(pixel_format_, std::span<const uint8_t>(data, size), width,
                                       height, x_padding);
    if (!samples)
        return deviceError(DeviceFault::BadFrame, name(),
                           "frame " + std::to_string(frame_id) + ": " + samples.error().message);

    hdr::RawFrame frame;
    frame.width = width;
    frame.height = height;
    frame.format = pixel_format_.layout;
    frame.samples = std::move(*samples);
    frame.exposure_s = exposure_s_;
    frame.gain = gain_;
    frame.bit_depth = pixel_format_.bits;
    frame.black_level_dn = 0.0;
    frame.white_level_dn = std::ldexp(1.0, pixel_format_.bits) - 1.0;
    frame.timestamp_ns = static_cast<int64_t>(arv_buffer_get_timestamp(buffer));
    frame.timestamp_marks = hdr::TimestampMark::ExposureStart;
    frame.host_timestamp_ns = host_ns;
    // Unwrapped: when the id goes back (the 16-bit wrap, a restarted camera) the sequence goes
    // on from the last one.
    int64_t sequence = sequence_base_ + frame_id;
    if (sequence <= last_sequence_) {
        sequence_base_ = last_sequence_ + 1 - frame_id;
        sequence = last_sequence_ + 1;
    }
    last_sequence_ = sequence;
    last_frame_id_ = frame_id;
    frame.sequence = sequence;
    frame.camera = vendor_ + " " + model_ + " " + serial_;
    return frame;
}

Result<hdr::RawFrame> AravisCamera::capture(double timeout_s) {
    if (!std::isfinite(timeout_s) || !(timeout_s > 0.0))
        return deviceError(DeviceFault::OutOfRange, name(),
                           "timeout_s " + fmt(timeout_s) + " is not a positive number");
    if (aborted_) return deviceError(DeviceFault::Stopped, name(), "the capture was aborted");
    if (Status s = ensureConnected(); !s) return s.error();
    for (int take = 0;; ++take) {
        auto frame = takeOnce(timeout_s);
        if (frame) return frame;
        if (deviceFaultOf(frame.error()) != DeviceFault::BadFrame) return frame.error();
        if (take >= options_.retries)
            return Error{frame.error().code,
                         frame.error().message + " (" + std::to_string(take + 1) +
                             " takes, retries=" + std::to_string(options_.retries) + ")"};
        ++retaken_frames_;
    }
}

std::vector<std::pair<std::string, int64_t>> AravisCamera::statistics() const {
    std::map<std::string, int64_t> all = stream_totals_;
    if (connection_)
        for (const auto& [key, value] : connection_->counters()) all[key] += value;
    all["retaken_frames"] = retaken_frames_;
    all["disconnects"] = disconnects_;
    all["reopens"] = reopens_;
    return {all.begin(), all.end()};
}

// ---------------------------------------------------------------------------------------------
// Listing and registration

std::vector<DeviceListing> listAravisCameras() {
    std::vector<DeviceListing> found;
    std::lock_guard<std::mutex> hold(aravisLock());
    arv_update_device_list();
    const auto text = [](const char* s) { return std::string(s ? s : ""); };
    for (unsigned i = 0; i < arv_get_n_devices(); ++i) {
        DeviceListing d;
        const std::string id = text(arv_get_device_id(i));
        const std::string vendor = text(arv_get_device_vendor(i));
        const std::string model = text(arv_get_device_model(i));
        d.uri = "aravis:" + id;
        d.kind = "camera";
        d.backend = "aravis";
        d.model = vendor + " " + model;
        d.serial = text(arv_get_device_serial_nbr(i));
        d.details.push_back("vendor: " + vendor);
        d.details.push_back("model: " + model);
        d.details.push_back("address: " + text(arv_get_device_address(i)));
        d.details.push_back("physical id: " + text(arv_get_device_physical_id(i)));
        d.details.push_back("protocol: " + text(arv_get_device_protocol(i)));
        GErr e;
        ArvCamera* cam = arv_camera_new(id.c_str(), e.out());
        if (!cam) {
            d.details.push_back("pixel formats: unknown (cannot open it: " + e.message() + ")");
        } else {
            guint n = 0;
            const char** listed =
                arv_camera_dup_available_pixel_formats_as_strings(cam, &n, e.out());
            const auto formats = takeStrings(listed, n);
            std::vector<std::string> taken;
            for (const GenicamPixelFormat& f : rankGenicamPixelFormats(formats))
                taken.push_back(f.name);
            d.details.push_back("pixel formats: " + joined(formats));
            d.details.push_back("raw formats flarelab takes, best first: " + joined(taken));
            g_object_unref(cam);
        }
        found.push_back(std::move(d));
    }
    return found;
}

Status addAravisCameraBackend(CameraRegistry& registry) {
    return registry.addBackend(
        "aravis", "GigE Vision and USB3 Vision cameras through Aravis " ARAVIS_VERSION,
        [](const DeviceUri& uri) -> Result<std::unique_ptr<Camera>> {
            auto camera = AravisCamera::open(uri);
            if (!camera) return camera.error();
            return std::unique_ptr<Camera>(std::move(*camera));
        },
        [] { return listAravisCameras(); });
}

}  // namespace flarelab::drivers
