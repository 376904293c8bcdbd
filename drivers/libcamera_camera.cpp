#include "drivers/libcamera_camera.h"

#include <libcamera/camera.h>
#include <libcamera/camera_manager.h>
#include <libcamera/control_ids.h>
#include <libcamera/controls.h>
#include <libcamera/formats.h>
#include <libcamera/framebuffer.h>
#include <libcamera/framebuffer_allocator.h>
#include <libcamera/logging.h>
#include <libcamera/property_ids.h>
#include <libcamera/request.h>
#include <libcamera/stream.h>
#include <linux/dma-buf.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <limits>
#include <mutex>
#include <optional>
#include <ostream>
#include <sstream>
#include <streambuf>

namespace flarelab::drivers {
namespace {

namespace lc = libcamera;

// The format table of libcamera_mapping.h is flarelab's own (so that it builds without
// libcamera); here it is held against libcamera's.
constexpr bool sameFormat(std::string_view name, const lc::PixelFormat& format) {
    for (const LibcameraRawFormat& f : kLibcameraRawFormats)
        if (f.name == name) return f.fourcc == format.fourcc() && f.modifier == format.modifier();
    return false;
}
#define FLARELAB_SAME_FORMAT(NAME) \
    static_assert(sameFormat(#NAME, lc::formats::NAME), #NAME " differs from libcamera's")
FLARELAB_SAME_FORMAT(R8);
FLARELAB_SAME_FORMAT(R10);
FLARELAB_SAME_FORMAT(R12);
FLARELAB_SAME_FORMAT(R10_CSI2P);
FLARELAB_SAME_FORMAT(SRGGB8);
FLARELAB_SAME_FORMAT(SGRBG8);
FLARELAB_SAME_FORMAT(SGBRG8);
FLARELAB_SAME_FORMAT(SBGGR8);
FLARELAB_SAME_FORMAT(SRGGB10);
FLARELAB_SAME_FORMAT(SGRBG10);
FLARELAB_SAME_FORMAT(SGBRG10);
FLARELAB_SAME_FORMAT(SBGGR10);
FLARELAB_SAME_FORMAT(SRGGB12);
FLARELAB_SAME_FORMAT(SGRBG12);
FLARELAB_SAME_FORMAT(SGBRG12);
FLARELAB_SAME_FORMAT(SBGGR12);
FLARELAB_SAME_FORMAT(SRGGB16);
FLARELAB_SAME_FORMAT(SGRBG16);
FLARELAB_SAME_FORMAT(SGBRG16);
FLARELAB_SAME_FORMAT(SBGGR16);
FLARELAB_SAME_FORMAT(SRGGB10_CSI2P);
FLARELAB_SAME_FORMAT(SGRBG10_CSI2P);
FLARELAB_SAME_FORMAT(SGBRG10_CSI2P);
FLARELAB_SAME_FORMAT(SBGGR10_CSI2P);
FLARELAB_SAME_FORMAT(SRGGB12_CSI2P);
FLARELAB_SAME_FORMAT(SGRBG12_CSI2P);
FLARELAB_SAME_FORMAT(SGBRG12_CSI2P);
FLARELAB_SAME_FORMAT(SBGGR12_CSI2P);
FLARELAB_SAME_FORMAT(SRGGB10_IPU3);
FLARELAB_SAME_FORMAT(SGRBG10_IPU3);
FLARELAB_SAME_FORMAT(SGBRG10_IPU3);
FLARELAB_SAME_FORMAT(SBGGR10_IPU3);
#undef FLARELAB_SAME_FORMAT
static_assert(kLibcameraRawFormats.size() == 32, "every format above is checked");

// ---------------------------------------------------------------------------------------------
// libcamera's log. Its Logger writes every message to one std::ostream from whichever thread
// logs (the caller's, the CameraManager's, a pipeline's), so the buffer below takes a lock. Lines
// of WARN and above are kept (the last few) to explain a failure in this backend's errors.

class LogSink final : public std::streambuf {
public:
    std::string tail() {
        std::lock_guard lock(mutex_);
        std::string text;
        for (const std::string& line : tail_) text += (text.empty() ? "" : "; ") + line;
        return text;
    }
    void clear() {
        std::lock_guard lock(mutex_);
        tail_.clear();
    }

protected:
    int overflow(int c) override {
        std::lock_guard lock(mutex_);
        if (c != traits_type::eof()) put(static_cast<char>(c));
        return traits_type::not_eof(c);
    }
    std::streamsize xsputn(const char* s, std::streamsize n) override {
        std::lock_guard lock(mutex_);
        for (std::streamsize i = 0; i < n; ++i) put(s[i]);
        return n;
    }

private:
    static constexpr size_t kLines = 6;
    static constexpr size_t kLineLength = 400;

    void put(char c) {
        if (c != '\n') {
            if (line_.size() < kLineLength) line_ += c;
            return;
        }
        // "[time] [thread]  WARN Category file.cpp:154 message": kept from the severity on.
        for (const char* severity : {" WARN ", " ERROR ", " FATAL ", "WARN ", "ERROR ", "FATAL "})
            if (const size_t at = line_.find(severity); at != std::string::npos) {
                tail_.push_back(line_.substr(at + (severity[0] == ' ' ? 1 : 0)));
                if (tail_.size() > kLines) tail_.pop_front();
                break;
            }
        line_.clear();
    }

    std::mutex mutex_;
    std::string line_;
    std::deque<std::string> tail_;
};

LogSink& logSink() {
    static LogSink sink;
    return sink;
}

void quietLibcameraLog() {
    static std::once_flag once;
    std::call_once(once, [] {
        // A lab debugging libcamera sets these; then its log goes where they say.
        if (std::getenv("LIBCAMERA_LOG_FILE") || std::getenv("LIBCAMERA_LOG_LEVELS")) return;
        static std::ostream stream(&logSink());
        lc::logSetStream(&stream, false);
        // The stream dies with the other statics at exit, libcamera's Logger perhaps later:
        // nothing may be written to it after exit() has begun.
        std::atexit([] { lc::logSetTarget(lc::LoggingTargetNone); });
    });
}

std::string withLog(std::string message) {
    const std::string tail = logSink().tail();
    if (!tail.empty()) message += " (libcamera logged: " + tail + ")";
    return message;
}

std::string errnoText(int negative_errno) { return std::strerror(-negative_errno); }

std::string fmt(double x) {
    std::ostringstream out;
    out << x;
    return out.str();
}

// ---------------------------------------------------------------------------------------------
// The process's CameraManager. libcamera 0.0.3 aborts the process ("Multiple IPAManager objects
// are not allowed") when a second one is made while one lives, so every user shares this one;
// the mutex also keeps a new one from being made while the last is being destroyed.

std::mutex& managerMutex() {
    static std::mutex mutex;
    return mutex;
}

Result<std::shared_ptr<lc::CameraManager>> sharedManager() {
    quietLibcameraLog();
    static std::weak_ptr<lc::CameraManager> shared;
    std::lock_guard lock(managerMutex());
    if (auto manager = shared.lock()) return manager;
    logSink().clear();
    auto owned = std::make_unique<lc::CameraManager>();
    if (const int ret = owned->start(); ret < 0)
        return makeError(ErrorCode::IoError,
                         withLog("libcamera " + lc::CameraManager::version() +
                                 ": CameraManager::start failed: " + errnoText(ret)));
    std::shared_ptr<lc::CameraManager> manager(owned.release(), [](lc::CameraManager* raw) {
        std::lock_guard lock(managerMutex());
        std::unique_ptr<lc::CameraManager> gone(raw);
        gone->stop();
    });
    shared = manager;
    return manager;
}

// ---------------------------------------------------------------------------------------------
// Controls. ControlValue::get<T>() only asserts its type (compiled out in release builds), so
// every value a camera hands over is checked before it is read.

std::optional<double> scalarOf(const lc::ControlValue& value) {
    if (value.isNone() || value.isArray()) return std::nullopt;
    switch (value.type()) {
        case lc::ControlTypeByte:
            return static_cast<double>(value.get<uint8_t>());
        case lc::ControlTypeInteger32:
            return static_cast<double>(value.get<int32_t>());
        case lc::ControlTypeInteger64:
            return static_cast<double>(value.get<int64_t>());
        case lc::ControlTypeFloat:
            return static_cast<double>(value.get<float>());
        default:
            return std::nullopt;
    }
}

std::optional<LibcameraControlRange> rangeOf(const lc::ControlInfoMap& info,
                                             const lc::ControlId& id) {
    const auto it = info.find(&id);
    if (it == info.end()) return std::nullopt;
    // A range of another type than a number reads as NaN, which libcameraLimits refuses.
    constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
    return LibcameraControlRange{scalarOf(it->second.min()).value_or(kNaN),
                                 scalarOf(it->second.max()).value_or(kNaN)};
}

const lc::ControlValue* findControl(const lc::ControlList& list, const lc::ControlId& id) {
    return list.contains(id.id()) ? &list.get(id.id()) : nullptr;
}

LibcameraFrameMetadata readMetadata(const lc::ControlList& controls,
                                    const lc::FrameMetadata& buffer,
                                    int64_t host_timestamp_ns) {
    LibcameraFrameMetadata m;
    if (const auto* v = findControl(controls, lc::controls::ExposureTime))
        if (const auto us = scalarOf(*v)) m.exposure_us = std::llround(*us);
    if (const auto* v = findControl(controls, lc::controls::AnalogueGain))
        m.analogue_gain = scalarOf(*v);
    if (const auto* v = findControl(controls, lc::controls::SensorTimestamp))
        if (!v->isArray() && v->type() == lc::ControlTypeInteger64)
            m.sensor_timestamp_ns = v->get<int64_t>();
    if (const auto* v = findControl(controls, lc::controls::SensorBlackLevels))
        if (v->isArray() && v->type() == lc::ControlTypeInteger32 && v->numElements() == 4) {
            const auto levels = v->get<lc::Span<const int32_t>>();
            m.black_levels = std::array<int64_t, 4>{levels[0], levels[1], levels[2], levels[3]};
        }
    m.sequence = buffer.sequence;
    m.host_timestamp_ns = host_timestamp_ns;
    return m;
}

std::vector<LibcameraFormatOffer> offersOf(const lc::StreamConfiguration& stream) {
    std::vector<LibcameraFormatOffer> offers;
    const lc::StreamFormats& formats = stream.formats();
    for (const lc::PixelFormat& format : formats.pixelformats()) {
        LibcameraFormatOffer offer;
        offer.name = format.toString();
        offer.fourcc = format.fourcc();
        offer.modifier = format.modifier();
        for (const lc::Size& size : formats.sizes(format))
            offer.sizes.push_back(PixelSize{size.width, size.height});
        // A stream that gives a range instead of discrete sizes: its largest.
        if (offer.sizes.empty()) {
            const lc::Size largest = formats.range(format).max;
            if (largest.width > 0 && largest.height > 0)
                offer.sizes.push_back(PixelSize{largest.width, largest.height});
        }
        offers.push_back(std::move(offer));
    }
    return offers;
}

std::string modelOf(const lc::Camera& camera) {
    const auto model = camera.properties().get(lc::properties::Model);
    return model && !model->empty() ? *model : std::string("libcamera camera");
}

int64_t realtimeNowNs() {
    return std::chrono::duration_cast<std::chrono::nanoseconds>(
               std::chrono::system_clock::now().time_since_epoch())
        .count();
}

// DMA-BUF cache coherency around CPU reads (linux/dma-buf.h); buffers that are not dma-bufs
// answer ENOTTY, which is fine: they need nothing.
void syncDmaBuf(int fd, uint64_t flags) {
    dma_buf_sync sync{};
    sync.flags = flags;
    while (::ioctl(fd, DMA_BUF_IOCTL_SYNC, &sync) < 0 && errno == EINTR) {
    }
}

}  // namespace

// ---------------------------------------------------------------------------------------------

struct LibcameraCamera::State {
    std::shared_ptr<lc::CameraManager> manager;  // outlives the camera (declared first)
    std::shared_ptr<lc::Camera> camera;
    std::string id;
    std::string model;
    std::string uri;
    std::string name;  // for messages: "libcamera camera <id>"
    bool acquired = false;
    bool connected = false;  // signals connected
    bool started = false;

    std::unique_ptr<lc::CameraConfiguration> config;
    lc::Stream* stream = nullptr;
    std::unique_ptr<lc::FrameBufferAllocator> allocator;
    lc::FrameBuffer* buffer = nullptr;
    std::unique_ptr<lc::Request> request;
    // The buffer's plane, memory-mapped: map_base .. map_base + map_length; the plane starts at
    // map_base + map_skip.
    void* map_base = MAP_FAILED;
    size_t map_length = 0;
    size_t map_skip = 0;
    size_t plane_length = 0;
    int plane_fd = -1;

    LibcameraFormatChoice format;
    int64_t stride_bytes = 0;
    LibcameraLimits limits;
    bool has_ae_enable = false;
    LibcameraSettings settings;
    double exposure_s = 0.0;  // as set; settings.exposure_us is it rounded
    double gain = 1.0;
    LibcameraSettleTracker tracker;
    bool in_flight = false;  // the request is queued and has not been seen complete
    double last_black_level_dn = 0.0;

    // Written by libcamera's threads (the signal handlers below), read by the capture.
    std::mutex mutex;
    std::condition_variable wake;
    bool completed = false;
    bool disconnected = false;
    bool aborted = false;  // abort(): set from any thread
    int64_t completed_host_ns = 0;

    int64_t frames_completed = 0;
    int64_t frames_failed = 0;
    int64_t frames_discarded = 0;
    int64_t requests_cancelled = 0;

    // Runs in the thread that completes the request; takes no time.
    void onRequestCompleted(lc::Request*) {
        const int64_t now = realtimeNowNs();
        std::lock_guard lock(mutex);
        completed = true;
        completed_host_ns = now;
        wake.notify_all();
    }
    void onDisconnected() {
        std::lock_guard lock(mutex);
        disconnected = true;
        wake.notify_all();
    }
    bool isDisconnected() {
        std::lock_guard lock(mutex);
        return disconnected;
    }
    Error gone() const {
        return deviceError(DeviceFault::Disconnected, name,
                           "the camera was unplugged or its pipeline went away "
                           "(Camera::disconnected)");
    }

    // Teardown in the order libcamera needs: stop (which completes every queued request, so that
    // no handler runs afterwards), the request before the buffers it holds, the buffers before the
    // release, the camera before the manager.
    ~State() {
        if (started) camera->stop();
        if (connected) {
            camera->requestCompleted.disconnect(this);
            camera->disconnected.disconnect(this);
        }
        request.reset();
        if (map_base != MAP_FAILED) ::munmap(map_base, map_length);
        if (allocator && stream) allocator->free(stream);
        allocator.reset();
        config.reset();
        if (acquired) camera->release();
        camera.reset();
        manager.reset();
    }

    Status queue() {
        request->reuse(lc::Request::ReuseBuffers);
        lc::ControlList& controls = request->controls();
        if (has_ae_enable) controls.set(lc::controls::AeEnable, false);
        controls.set(lc::controls::ExposureTime, settings.exposure_us);
        controls.set(lc::controls::AnalogueGain, settings.gain);
        {
            std::lock_guard lock(mutex);
            completed = false;
        }
        if (const int ret = camera->queueRequest(request.get()); ret < 0) {
            if (ret == -ENODEV) return gone();
            return makeError(ErrorCode::IoError,
                             withLog(name + ": queueRequest failed: " + errnoText(ret)));
        }
        in_flight = true;
        return Ok{};
    }
};

LibcameraCamera::LibcameraCamera(std::unique_ptr<State> state) : state_(std::move(state)) {}
LibcameraCamera::~LibcameraCamera() = default;

Result<std::unique_ptr<LibcameraCamera>> LibcameraCamera::open(const DeviceUri& uri) {
    auto options = libcameraOptionsFromUri(uri);
    if (!options) return options.error();
    auto manager = sharedManager();
    if (!manager) return manager.error();

    auto state = std::make_unique<State>();
    state->manager = *manager;
    state->uri = uri.text;
    std::vector<std::string> ids;
    for (const std::shared_ptr<lc::Camera>& camera : state->manager->cameras())
        ids.push_back(camera->id());
    auto id = pickLibcameraCamera(ids, options->name);
    if (!id) return id.error();
    state->id = *id;
    state->name = "libcamera camera " + state->id;
    state->camera = state->manager->get(state->id);
    if (!state->camera)
        return makeError(ErrorCode::NotFound, state->name + ": gone before it could be opened");
    state->model = modelOf(*state->camera);
    const std::string& name = state->name;
    logSink().clear();

    if (const int ret = state->camera->acquire(); ret < 0) {
        if (ret == -EBUSY)
            return deviceError(DeviceFault::Busy, name,
                               "another program (or another flarelab camera) holds it");
        return makeError(ErrorCode::IoError, withLog(name + ": acquire failed: " + errnoText(ret)));
    }
    state->acquired = true;

    // The raw stream, its format and size.
    state->config = state->camera->generateConfiguration({lc::StreamRole::Raw});
    if (!state->config || state->config->size() != 1)
        return makeError(ErrorCode::Unsupported,
                         withLog(name + ": the camera has no raw stream (StreamRole::Raw)"));
    lc::StreamConfiguration& stream_config = state->config->at(0);
    const std::vector<LibcameraFormatOffer> offers = offersOf(stream_config);
    auto chosen = chooseLibcameraFormat(offers, options->format, name);
    if (!chosen) return chosen.error();
    stream_config.pixelFormat = lc::PixelFormat(chosen->format.fourcc, chosen->format.modifier);
    stream_config.size = lc::Size(static_cast<unsigned int>(chosen->size.width),
                                  static_cast<unsigned int>(chosen->size.height));
    switch (state->config->validate()) {
        case lc::CameraConfiguration::Invalid:
            return makeError(ErrorCode::Unsupported,
                             withLog(name + ": the camera refuses a raw stream of " +
                                     std::string(chosen->format.name) + " " +
                                     std::to_string(chosen->size.width) + "x" +
                                     std::to_string(chosen->size.height)));
        case lc::CameraConfiguration::Adjusted: {
            // The stream the camera will give, taken if it is still readable and keeps what the
            // URI asked for.
            auto adjusted = acceptValidatedFormat(
                stream_config.pixelFormat.fourcc(), stream_config.pixelFormat.modifier(),
                stream_config.pixelFormat.toString(),
                PixelSize{stream_config.size.width, stream_config.size.height}, options->format,
                name);
            if (!adjusted) return adjusted.error();
            chosen = std::move(adjusted);
            break;
        }
        case lc::CameraConfiguration::Valid:
            break;
    }
    state->format = *chosen;
    if (const int ret = state->camera->configure(state->config.get()); ret < 0)
        return makeError(ErrorCode::IoError,
                         withLog(name + ": configure failed: " + errnoText(ret)));
    // The stride as configured (validate() and configure() set it).
    state->stride_bytes = stream_config.stride;
    if (state->stride_bytes < libcameraLineBytes(state->format.format, state->format.size.width))
        return makeError(ErrorCode::IoError,
                         name + ": the camera's stride of " + std::to_string(stream_config.stride) +
                             " bytes is shorter than a line of " +
                             std::to_string(state->format.size.width) + " samples of " +
                             std::string(state->format.format.name));
    state->stream = stream_config.stream();
    if (!state->stream)
        return makeError(ErrorCode::IoError, name + ": configure gave the raw stream no Stream");

    // Manual exposure: the ranges of the configured sensor mode.
    const lc::ControlInfoMap& controls = state->camera->controls();
    auto limits = libcameraLimits(rangeOf(controls, lc::controls::ExposureTime),
                                  rangeOf(controls, lc::controls::AnalogueGain), name);
    if (!limits) return limits.error();
    state->limits = *limits;
    state->has_ae_enable = controls.find(&lc::controls::AeEnable) != controls.end();
    state->tracker = LibcameraSettleTracker(state->limits.min_exposure_us);
    // 10 ms at the lowest gain: a start that neither clips a lit lab nor takes long.
    state->exposure_s = std::clamp(0.01, state->limits.min_exposure_us * 1e-6,
                                   state->limits.max_exposure_us * 1e-6);
    state->gain = std::clamp(1.0, state->limits.min_gain, state->limits.max_gain);
    auto us = exposureToMicroseconds(state->exposure_s, state->limits, name);
    if (!us) return us.error();
    state->settings = LibcameraSettings{*us, static_cast<float>(state->gain)};

    // One buffer, memory-mapped, carried by the one request.
    state->allocator = std::make_unique<lc::FrameBufferAllocator>(state->camera);
    if (const int ret = state->allocator->allocate(state->stream); ret <= 0)
        return makeError(ErrorCode::IoError,
                         withLog(name + ": no buffers for the raw stream: " +
                                 (ret < 0 ? errnoText(ret) : std::string("none allocated"))));
    state->buffer = state->allocator->buffers(state->stream).front().get();
    if (state->buffer->planes().empty())
        return makeError(ErrorCode::IoError, name + ": the raw buffer has no plane");
    const lc::FrameBuffer::Plane& plane = state->buffer->planes().front();
    if (plane.offset == lc::FrameBuffer::Plane::kInvalidOffset || !plane.fd.isValid())
        return makeError(ErrorCode::IoError, name + ": the raw buffer's plane has no memory");
    const auto page = static_cast<size_t>(::sysconf(_SC_PAGESIZE));
    const size_t base = plane.offset / page * page;
    state->map_skip = plane.offset - base;
    state->map_length = state->map_skip + plane.length;
    state->plane_length = plane.length;
    state->plane_fd = plane.fd.get();
    state->map_base = ::mmap(nullptr, state->map_length, PROT_READ, MAP_SHARED, state->plane_fd,
                             static_cast<off_t>(base));
    if (state->map_base == MAP_FAILED)
        return makeError(ErrorCode::IoError,
                         name + ": mapping the raw buffer failed: " + std::strerror(errno));
    state->request = state->camera->createRequest();
    if (!state->request)
        return makeError(ErrorCode::IoError, withLog(name + ": createRequest failed"));
    if (const int ret = state->request->addBuffer(state->stream, state->buffer); ret < 0)
        return makeError(
            ErrorCode::IoError,
            withLog(name + ": adding the buffer to the request failed: " + errnoText(ret)));

    state->camera->requestCompleted.connect(state.get(), &State::onRequestCompleted);
    state->camera->disconnected.connect(state.get(), &State::onDisconnected);
    state->connected = true;

    lc::ControlList start_controls(controls);
    if (state->has_ae_enable) start_controls.set(lc::controls::AeEnable, false);
    start_controls.set(lc::controls::ExposureTime, state->settings.exposure_us);
    start_controls.set(lc::controls::AnalogueGain, state->settings.gain);
    if (const int ret = state->camera->start(&start_controls); ret < 0)
        return makeError(ErrorCode::IoError, withLog(name + ": start failed: " + errnoText(ret)));
    state->started = true;
    return std::make_unique<LibcameraCamera>(std::move(state));
}

DeviceIdentity LibcameraCamera::identity() const {
    return DeviceIdentity{"libcamera", state_->model, state_->id, state_->uri};
}

CameraCapabilities LibcameraCamera::capabilities() const {
    const State& s = *state_;
    CameraCapabilities c;
    c.width_px = s.format.size.width;
    c.height_px = s.format.size.height;
    c.formats = {s.format.format.layout};
    c.bit_depth = s.format.format.bit_depth;
    c.min_exposure_s = s.limits.min_exposure_us * 1e-6;
    c.max_exposure_s = s.limits.max_exposure_us * 1e-6;
    c.min_gain = s.limits.min_gain;
    c.max_gain = s.limits.max_gain;
    c.black_level_dn = s.last_black_level_dn;
    c.white_level_dn = std::ldexp(1.0, c.bit_depth) - 1.0;
    c.response = CameraResponse::Linear;
    c.response_note = "raw sensor samples (libcamera raw stream " +
                      std::string(s.format.format.name) + "), before any image processing";
    return c;
}

Status LibcameraCamera::setExposure(double exposure_s) {
    State& s = *state_;
    if (s.isDisconnected()) return s.gone();
    auto us = exposureToMicroseconds(exposure_s, s.limits, s.name);
    if (!us) return us.error();
    s.settings.exposure_us = *us;
    s.exposure_s = exposure_s;
    return Ok{};
}

double LibcameraCamera::exposure_s() const { return state_->exposure_s; }

Status LibcameraCamera::setGain(double gain) {
    State& s = *state_;
    if (s.isDisconnected()) return s.gone();
    auto value = gainToControl(gain, s.limits, s.name);
    if (!value) return value.error();
    s.settings.gain = *value;
    s.gain = gain;
    return Ok{};
}

double LibcameraCamera::gain() const { return state_->gain; }

Status LibcameraCamera::setFormat(hdr::RawFormat format) {
    State& s = *state_;
    if (s.isDisconnected()) return s.gone();
    if (format != s.format.format.layout)
        return deviceError(DeviceFault::OutOfRange, s.name,
                           "format: the raw stream is " + std::string(s.format.format.name) +
                               "; another is chosen when opening (format= in the URI)");
    return Ok{};
}

hdr::RawFormat LibcameraCamera::format() const { return state_->format.format.layout; }

void LibcameraCamera::abort() {
    State& s = *state_;
    {
        std::lock_guard lock(s.mutex);
        s.aborted = true;
    }
    s.wake.notify_all();
}

Result<hdr::RawFrame> LibcameraCamera::capture(double timeout_s) {
    State& s = *state_;
    if (!std::isfinite(timeout_s) || !(timeout_s > 0.0))
        return deviceError(DeviceFault::OutOfRange, s.name, "timeout_s must be positive");
    if (s.isDisconnected()) return s.gone();
    const auto stopped = [&] {
        return deviceError(DeviceFault::Stopped, s.name, "the capture was aborted");
    };
    {
        std::lock_guard lock(s.mutex);
        if (s.aborted) return stopped();
    }
    using Clock = std::chrono::steady_clock;
    // A week bounds the wait so that the deadline cannot overflow the clock.
    const auto deadline =
        Clock::now() + std::chrono::duration_cast<Clock::duration>(
                           std::chrono::duration<double>(std::min(timeout_s, 7 * 86400.0)));
    s.tracker.request(s.settings);
    for (;;) {
        if (!s.in_flight) {
            if (Clock::now() >= deadline) break;
            if (Status queued = s.queue(); !queued) return queued.error();
        }
        int64_t host_ns = 0;
        {
            std::unique_lock lock(s.mutex);
            const bool woke = s.wake.wait_until(
                lock, deadline, [&] { return s.completed || s.disconnected || s.aborted; });
            if (s.aborted) return stopped();
            if (s.disconnected) return s.gone();
            if (!woke) break;
            s.completed = false;
            host_ns = s.completed_host_ns;
        }
        s.in_flight = false;
        if (s.request->status() == lc::Request::RequestCancelled) {
            ++s.requests_cancelled;
            if (s.isDisconnected()) return s.gone();
            return makeError(ErrorCode::IoError,
                             withLog(s.name + ": the request was cancelled (the camera stopped)"));
        }
        const lc::FrameMetadata& buffer_metadata = s.buffer->metadata();
        if (buffer_metadata.status != lc::FrameMetadata::FrameSuccess) {
            ++s.frames_failed;
            continue;
        }
        ++s.frames_completed;
        const LibcameraFrameMetadata metadata =
            readMetadata(s.request->metadata(), buffer_metadata, host_ns);
        const LibcameraSettleTracker::Decision decision = s.tracker.judge(metadata, s.name);
        if (decision.verdict == LibcameraSettleTracker::Verdict::Refuse) return *decision.error;
        if (decision.verdict == LibcameraSettleTracker::Verdict::Discard) {
            ++s.frames_discarded;
            continue;
        }

        size_t used = s.plane_length;
        if (!buffer_metadata.planes().empty())
            used = std::min<size_t>(used, buffer_metadata.planes()[0].bytesused);
        const auto* bytes = static_cast<const uint8_t*>(s.map_base) + s.map_skip;
        syncDmaBuf(s.plane_fd, DMA_BUF_SYNC_START | DMA_BUF_SYNC_READ);
        auto samples =
            unpackLibcameraRaw(std::span<const uint8_t>(bytes, used), s.format.format,
                               s.format.size.width, s.format.size.height, s.stride_bytes);
        syncDmaBuf(s.plane_fd, DMA_BUF_SYNC_END | DMA_BUF_SYNC_READ);
        if (!samples) return makeError(ErrorCode::IoError, s.name + ": " + samples.error().message);
        auto frame = rawFrameFromLibcamera(metadata, s.settings, s.format, std::move(*samples),
                                           identity().describe());
        if (frame) s.last_black_level_dn = frame->black_level_dn;
        return frame;
    }
    return deviceError(DeviceFault::Timeout, s.name,
                       "no frame within timeout_s = " + fmt(timeout_s) + " (" +
                           std::to_string(s.tracker.framesSinceChange()) +
                           " frames since the settings changed, " +
                           std::to_string(s.frames_failed) + " failed frames so far)");
}

std::vector<std::pair<std::string, int64_t>> LibcameraCamera::statistics() const {
    const State& s = *state_;
    return {{"completed", s.frames_completed},
            {"failed", s.frames_failed},
            {"discarded", s.frames_discarded},
            {"cancelled", s.requests_cancelled}};
}

std::vector<DeviceListing> listLibcameraCameras() {
    auto manager = sharedManager();
    if (!manager) {
        DeviceListing d;
        d.uri = "libcamera:";
        d.kind = "camera";
        d.backend = "libcamera";
        d.model = "libcamera " + lc::CameraManager::version() + " (not started)";
        d.details = {"error: " + manager.error().message};
        return {d};
    }
    std::vector<DeviceListing> found;
    for (const std::shared_ptr<lc::Camera>& camera : (*manager)->cameras()) {
        DeviceListing d;
        d.uri = "libcamera:" + camera->id();
        d.kind = "camera";
        d.backend = "libcamera";
        d.model = modelOf(*camera);
        d.serial = camera->id();
        d.details.push_back("libcamera: " + lc::CameraManager::version());
        if (const auto location = camera->properties().get(lc::properties::Location)) {
            const char* where[] = {"front", "back", "external"};
            d.details.push_back(std::string("location: ") +
                                (*location >= 0 && *location < 3 ? where[*location] : "unknown"));
        }
        const auto config = camera->generateConfiguration({lc::StreamRole::Raw});
        if (!config || config->size() != 1) {
            d.details.push_back("raw stream: none (flarelab cannot use this camera)");
        } else {
            std::string readable, other;
            for (const LibcameraFormatOffer& offer : offersOf(config->at(0))) {
                std::string text = offer.name;
                for (const PixelSize& size : offer.sizes)
                    text += ' ' + std::to_string(size.width) + 'x' + std::to_string(size.height);
                std::string& list =
                    findLibcameraRawFormat(offer.fourcc, offer.modifier) ? readable : other;
                list += (list.empty() ? "" : ", ") + text;
            }
            d.details.push_back("raw formats: " +
                                (readable.empty() ? "none flarelab reads" : readable));
            if (!other.empty()) d.details.push_back("other formats: " + other);
        }
        const lc::ControlInfoMap& controls = camera->controls();
        for (const lc::ControlId* id :
             {static_cast<const lc::ControlId*>(&lc::controls::ExposureTime),
              static_cast<const lc::ControlId*>(&lc::controls::AnalogueGain)})
            if (controls.find(id) == controls.end())
                d.details.push_back("no " + id->name() +
                                    " control: flarelab cannot expose it by hand");
        found.push_back(std::move(d));
    }
    return found;
}

Status addLibcameraCameraBackend(CameraRegistry& registry) {
    auto open = [](const DeviceUri& uri) -> Result<std::unique_ptr<Camera>> {
        auto camera = LibcameraCamera::open(uri);
        if (!camera) return camera.error();
        return std::unique_ptr<Camera>(std::move(*camera));
    };
    return registry.addBackend("libcamera",
                               "libcamera cameras (libcamera " + lc::CameraManager::version() +
                                   "; raw stream, manual exposure)",
                               std::move(open), listLibcameraCameras);
}

std::string libcameraVersion() { return lc::CameraManager::version(); }

std::string libcameraFormatName(uint32_t fourcc, uint64_t modifier) {
    return lc::PixelFormat(fourcc, modifier).toString();
}

}  // namespace flarelab::drivers
