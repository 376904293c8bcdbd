#include "drivers/v4l2_playback.h"

#include <linux/videodev2.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <deque>
#include <limits>
#include <vector>

#include "drivers/v4l2_formats.h"

namespace flarelab::drivers {
namespace {

constexpr int64_t kNsPerS = 1'000'000'000;

uint32_t controlType(const std::string& type) {
    if (type == "int") return V4L2_CTRL_TYPE_INTEGER;
    if (type == "bool") return V4L2_CTRL_TYPE_BOOLEAN;
    if (type == "menu") return V4L2_CTRL_TYPE_MENU;
    if (type == "intmenu") return V4L2_CTRL_TYPE_INTEGER_MENU;
    if (type == "int64") return V4L2_CTRL_TYPE_INTEGER64;
    if (type == "button") return V4L2_CTRL_TYPE_BUTTON;
    if (type == "bitmask") return V4L2_CTRL_TYPE_BITMASK;
    if (type == "str") return V4L2_CTRL_TYPE_STRING;
    if (type == "u8") return V4L2_CTRL_TYPE_U8;
    if (type == "u16") return V4L2_CTRL_TYPE_U16;
    if (type == "u32") return V4L2_CTRL_TYPE_U32;
    if (type == "area") return V4L2_CTRL_TYPE_AREA;
    return V4L2_CTRL_TYPE_U32;  // some compound type; the camera uses none
}

uint32_t controlFlags(const V4l2DumpControl& c) {
    static const std::pair<const char*, uint32_t> names[] = {
        {"disabled", V4L2_CTRL_FLAG_DISABLED},
        {"grabbed", V4L2_CTRL_FLAG_GRABBED},
        {"read-only", V4L2_CTRL_FLAG_READ_ONLY},
        {"update", V4L2_CTRL_FLAG_UPDATE},
        {"inactive", V4L2_CTRL_FLAG_INACTIVE},
        {"slider", V4L2_CTRL_FLAG_SLIDER},
        {"write-only", V4L2_CTRL_FLAG_WRITE_ONLY},
        {"volatile", V4L2_CTRL_FLAG_VOLATILE},
        {"has-payload", V4L2_CTRL_FLAG_HAS_PAYLOAD},
        {"execute-on-write", V4L2_CTRL_FLAG_EXECUTE_ON_WRITE},
        {"modify-layout", V4L2_CTRL_FLAG_MODIFY_LAYOUT},
    };
    uint32_t flags = 0;
    for (const std::string& f : c.flags)
        for (const auto& [name, bit] : names)
            if (f == name) flags |= bit;
    return flags;
}

template <size_t N>
void copyText(uint8_t (&to)[N], const std::string& from) {
    std::memset(to, 0, N);
    std::memcpy(to, from.data(), std::min(from.size(), N - 1));
}
template <size_t N>
void copyText(char (&to)[N], const std::string& from) {
    std::memset(to, 0, N);
    std::memcpy(to, from.data(), std::min(from.size(), N - 1));
}

struct Buffer {
    std::vector<uint8_t> storage;
    uint32_t offset = 0;
    bool queued = false;
    bool done = false;
    v4l2_buffer filled{};
};

struct Control {
    V4l2DumpControl dump;
    int64_t value = 0;
    // (time the value was set, value), oldest first; the dump's value at time -infinity.
    std::vector<std::pair<int64_t, int64_t>> history;
};

class Playback final : public V4l2Playback {
public:
    Playback(V4l2DeviceDump dump, V4l2PlaybackOptions options)
        : dump_(std::move(dump)), options_(std::move(options)), now_ns_(options_.start_ns) {
        for (const V4l2DumpControl& c : dump_.controls) {
            Control control{c, c.value.value_or(c.default_value), {}};
            control.history.emplace_back(std::numeric_limits<int64_t>::min(), control.value);
            controls_.push_back(std::move(control));
        }
        std::sort(controls_.begin(), controls_.end(),
                  [](const Control& a, const Control& b) { return a.dump.id < b.dump.id; });
        if (dump_.format) {
            format_.width = dump_.format->width;
            format_.height = dump_.format->height;
            format_.pixelformat = dump_.format->fourcc;
        } else if (!dump_.formats.empty()) {
            format_.pixelformat = dump_.formats.front().fourcc;
        }
        adjust(format_);
        if (dump_.time_per_frame)
            time_per_frame_ = {dump_.time_per_frame->first, dump_.time_per_frame->second};
        name_ = dump_.source;
    }

    int ioctl(unsigned long request, void* argument) override {
        if (gone_) return ENODEV;
        switch (request) {
            case VIDIOC_QUERYCAP:
                return querycap(*static_cast<v4l2_capability*>(argument));
            case VIDIOC_ENUM_FMT:
                return enumFormat(*static_cast<v4l2_fmtdesc*>(argument));
            case VIDIOC_ENUM_FRAMESIZES:
                return enumSizes(*static_cast<v4l2_frmsizeenum*>(argument));
            case VIDIOC_G_FMT:
                return getFormat(*static_cast<v4l2_format*>(argument));
            case VIDIOC_S_FMT:
            case VIDIOC_TRY_FMT:
                return setFormat(*static_cast<v4l2_format*>(argument), request == VIDIOC_S_FMT);
            case VIDIOC_G_PARM:
            case VIDIOC_S_PARM:
                return parm(*static_cast<v4l2_streamparm*>(argument), request == VIDIOC_S_PARM);
            case VIDIOC_QUERYCTRL:
                return queryControl(*static_cast<v4l2_queryctrl*>(argument));
            case VIDIOC_QUERY_EXT_CTRL:
                return queryExtControl(*static_cast<v4l2_query_ext_ctrl*>(argument));
            case VIDIOC_QUERYMENU:
                return queryMenu(*static_cast<v4l2_querymenu*>(argument));
            case VIDIOC_G_CTRL:
                return getControl(*static_cast<v4l2_control*>(argument));
            case VIDIOC_S_CTRL:
                return setControl(*static_cast<v4l2_control*>(argument));
            case VIDIOC_G_EXT_CTRLS:
            case VIDIOC_S_EXT_CTRLS:
            case VIDIOC_TRY_EXT_CTRLS:
                return extControls(*static_cast<v4l2_ext_controls*>(argument), request);
            case VIDIOC_REQBUFS:
                return requestBuffers(*static_cast<v4l2_requestbuffers*>(argument));
            case VIDIOC_QUERYBUF:
                return queryBuffer(*static_cast<v4l2_buffer*>(argument));
            case VIDIOC_QBUF:
                return queueBuffer(*static_cast<v4l2_buffer*>(argument));
            case VIDIOC_DQBUF:
                return dequeueBuffer(*static_cast<v4l2_buffer*>(argument));
            case VIDIOC_STREAMON:
                return streamOn(*static_cast<int*>(argument));
            case VIDIOC_STREAMOFF:
                return streamOff(*static_cast<int*>(argument));
            default:
                return ENOTTY;
        }
    }

    Result<std::span<const uint8_t>> map(uint32_t length, uint32_t offset) override {
        for (Buffer& b : buffers_)
            if (b.offset == offset && length <= b.storage.size())
                return std::span<const uint8_t>(b.storage.data(), length);
        return makeError(ErrorCode::IoError, name_ + ": mmap of " + std::to_string(length) +
                                                 " bytes at " + std::to_string(offset) +
                                                 " matches no buffer: Invalid argument");
    }

    void unmap(std::span<const uint8_t>) override {}

    int waitForFrame(int timeout_ms) override {
        if (gone_) return -EPIPE;
        advanceTo(now_ns_);
        if (gone_) return -EPIPE;
        if (!done_.empty()) return 1;
        const bool any_queued =
            std::any_of(buffers_.begin(), buffers_.end(), [](const Buffer& b) { return b.queued; });
        if (!streaming_ || !any_queued) return -EPIPE;
        const int64_t deadline = now_ns_ + int64_t{std::max(timeout_ms, 0)} * 1'000'000;
        // Run frame by frame (each may be dropped or fill a buffer) until one lands or time is up.
        while (done_.empty()) {
            const int64_t due = frameDone(next_start_ns_);
            if (due > deadline) {
                now_ns_ = deadline;
                return 0;
            }
            advanceTo(due);
            if (gone_) return -EPIPE;
        }
        return 1;
    }

    void advance(int64_t ns) override {
        if (gone_ || ns <= 0) return;
        advanceTo(now_ns_ + ns);
    }

    int64_t monotonicNs() const override { return now_ns_; }
    int64_t realtimeNs() const override { return now_ns_ + options_.realtime_offset_ns; }
    const std::string& path() const override { return name_; }

private:
    // The playback's idea of a format: sizes from the dump, bytes from the format table.
    void adjust(v4l2_pix_format& f) const {
        const V4l2DumpFormat* listed = dump_.findFormat(f.pixelformat);
        if (!listed && !dump_.formats.empty()) {
            listed = &dump_.formats.front();
            f.pixelformat = listed->fourcc;
        }
        if (listed && !listed->sizes.empty()) {
            const V4l2DumpFrameSize& first = listed->sizes.front();
            if (first.kind == V4l2DumpFrameSize::Kind::Discrete) {
                // The nearest listed size, as drivers with discrete sizes pick it.
                const V4l2DumpFrameSize* best = &first;
                int64_t best_distance = std::numeric_limits<int64_t>::max();
                for (const V4l2DumpFrameSize& s : listed->sizes) {
                    const int64_t d = std::abs(int64_t{s.width} - f.width) +
                                      std::abs(int64_t{s.height} - f.height);
                    if (d < best_distance) {
                        best_distance = d;
                        best = &s;
                    }
                }
                f.width = best->width;
                f.height = best->height;
            } else {
                const auto snap = [](uint32_t v, uint32_t lo, uint32_t hi, uint32_t step) {
                    v = std::clamp(v, lo, std::max(lo, hi));
                    if (step > 1) v = lo + (v - lo) / step * step;
                    return v;
                };
                f.width = snap(f.width, first.min_width, first.max_width, first.step_width);
                f.height = snap(f.height, first.min_height, first.max_height, first.step_height);
            }
        }
        f.width = std::clamp<uint32_t>(f.width, 1, 1u << 14);
        f.height = std::clamp<uint32_t>(f.height, 1, 1u << 14);
        f.field = V4L2_FIELD_NONE;
        const V4l2FormatInfo* info = findV4l2Format(f.pixelformat);
        const int64_t line = info ? minBytesPerLine(*info, f.width) : 4 * int64_t{f.width};
        f.bytesperline = static_cast<uint32_t>(line);
        f.sizeimage =
            static_cast<uint32_t>(info ? imageBytes(*info, line, f.height) : line * f.height);
        f.colorspace = info && info->raw ? V4L2_COLORSPACE_RAW : V4L2_COLORSPACE_SRGB;
    }

    int querycap(v4l2_capability& cap) const {
        std::memset(&cap, 0, sizeof cap);
        copyText(cap.driver, dump_.driver);
        copyText(cap.card, dump_.card);
        copyText(cap.bus_info, dump_.bus_info);
        cap.version = dump_.driver_version;
        cap.capabilities = dump_.capabilities;
        cap.device_caps = dump_.device_caps;
        return 0;
    }

    int enumFormat(v4l2_fmtdesc& d) const {
        const uint32_t listed = dump_.format_list_type == "Video Capture Multiplanar"
                                    ? V4L2_BUF_TYPE_VIDEO_CAPTURE_MPLANE
                                    : V4L2_BUF_TYPE_VIDEO_CAPTURE;
        if (d.type != listed || d.index >= dump_.formats.size()) return EINVAL;
        const V4l2DumpFormat& f = dump_.formats[d.index];
        const uint32_t index = d.index;
        std::memset(&d, 0, sizeof d);
        d.index = index;
        d.type = listed;
        d.pixelformat = f.fourcc;
        copyText(d.description, f.description);
        if (f.hasFlag("compressed")) d.flags |= V4L2_FMT_FLAG_COMPRESSED;
        if (f.hasFlag("emulated")) d.flags |= V4L2_FMT_FLAG_EMULATED;
        return 0;
    }

    int enumSizes(v4l2_frmsizeenum& e) const {
        const V4l2DumpFormat* f = dump_.findFormat(e.pixel_format);
        if (!f || e.index >= f->sizes.size()) return EINVAL;
        const V4l2DumpFrameSize& s = f->sizes[e.index];
        if (s.kind == V4l2DumpFrameSize::Kind::Discrete) {
            e.type = V4L2_FRMSIZE_TYPE_DISCRETE;
            e.discrete = {s.width, s.height};
        } else {
            if (e.index != 0) return EINVAL;
            e.type = s.kind == V4l2DumpFrameSize::Kind::Stepwise ? V4L2_FRMSIZE_TYPE_STEPWISE
                                                                 : V4L2_FRMSIZE_TYPE_CONTINUOUS;
            e.stepwise = {s.min_width,  s.max_width,  s.step_width,
                          s.min_height, s.max_height, s.step_height};
        }
        return 0;
    }

    int getFormat(v4l2_format& f) const {
        if (f.type != V4L2_BUF_TYPE_VIDEO_CAPTURE) return EINVAL;
        f.fmt.pix = format_;
        return 0;
    }

    int setFormat(v4l2_format& f, bool set) {
        if (f.type != V4L2_BUF_TYPE_VIDEO_CAPTURE) return EINVAL;
        if (set && !buffers_.empty()) return EBUSY;
        v4l2_pix_format wanted = f.fmt.pix;
        adjust(wanted);
        f.fmt.pix = wanted;
        if (set) format_ = wanted;
        return 0;
    }

    const V4l2DumpFrameSize* currentSize() const {
        const V4l2DumpFormat* f = dump_.findFormat(format_.pixelformat);
        if (!f) return nullptr;
        for (const V4l2DumpFrameSize& s : f->sizes)
            if (s.kind == V4l2DumpFrameSize::Kind::Discrete && s.width == format_.width &&
                s.height == format_.height)
                return &s;
        return nullptr;
    }

    int parm(v4l2_streamparm& p, bool set) {
        if (p.type != V4L2_BUF_TYPE_VIDEO_CAPTURE) return EINVAL;
        if (!time_per_frame_.numerator) return set ? ENOTTY : (p.parm.capture = {}, 0);
        if (set && p.parm.capture.timeperframe.numerator &&
            p.parm.capture.timeperframe.denominator) {
            double wanted = static_cast<double>(p.parm.capture.timeperframe.numerator) /
                            p.parm.capture.timeperframe.denominator;
            const V4l2DumpFrameSize* size = currentSize();
            if (size && !size->intervals_s.empty()) {
                double best = size->intervals_s.front();
                for (double t : size->intervals_s)
                    if (std::abs(t - wanted) < std::abs(best - wanted)) best = t;
                wanted = best;
            }
            // A fraction in microseconds: the dump prints intervals to 1 ms.
            wanted = std::clamp(wanted, 1e-6, 4000.0);
            time_per_frame_ = {static_cast<uint32_t>(std::llround(wanted * 1e6)), 1'000'000};
        }
        std::memset(&p.parm.capture, 0, sizeof p.parm.capture);
        p.parm.capture.capability = V4L2_CAP_TIMEPERFRAME;
        p.parm.capture.timeperframe = time_per_frame_;
        return 0;
    }

    Control* find(uint32_t id) {
        for (Control& c : controls_)
            if (c.dump.id == id) return &c;
        return nullptr;
    }

    // The control of `id`, or with V4L2_CTRL_FLAG_NEXT_CTRL the next one after it.
    Control* lookup(uint32_t id) {
        if (!(id & V4L2_CTRL_FLAG_NEXT_CTRL)) return find(id);
        const uint32_t after = id & ~(V4L2_CTRL_FLAG_NEXT_CTRL | V4L2_CTRL_FLAG_NEXT_COMPOUND);
        for (Control& c : controls_)
            if (c.dump.id > after) return &c;
        return nullptr;
    }

    int queryExtControl(v4l2_query_ext_ctrl& q) {
        Control* c = lookup(q.id);
        if (!c) return EINVAL;
        std::memset(&q, 0, sizeof q);
        q.id = c->dump.id;
        q.type = controlType(c->dump.type);
        copyText(q.name, c->dump.name);
        q.minimum = c->dump.minimum;
        q.maximum = c->dump.maximum;
        q.step = static_cast<uint64_t>(std::max<int64_t>(c->dump.step, 0));
        q.default_value = c->dump.default_value;
        q.flags = controlFlags(c->dump);
        q.elem_size = 4;
        q.elems = 1;
        return 0;
    }

    int queryControl(v4l2_queryctrl& q) {
        v4l2_query_ext_ctrl e{};
        e.id = q.id;
        if (const int error = queryExtControl(e); error) return error;
        std::memset(&q, 0, sizeof q);
        q.id = e.id;
        q.type = e.type;
        std::memcpy(q.name, e.name, sizeof q.name);
        q.name[sizeof q.name - 1] = 0;
        // The 32-bit query cannot carry 64-bit ranges; the kernel reports them as 0.
        const auto fits = [](int64_t v) {
            return v >= std::numeric_limits<int32_t>::min() &&
                   v <= std::numeric_limits<int32_t>::max();
        };
        const bool narrow = fits(e.minimum) && fits(e.maximum) && fits(e.default_value) &&
                            e.step <= static_cast<uint64_t>(std::numeric_limits<int32_t>::max());
        q.minimum = narrow ? static_cast<int32_t>(e.minimum) : 0;
        q.maximum = narrow ? static_cast<int32_t>(e.maximum) : 0;
        q.step = narrow ? static_cast<int32_t>(e.step) : 0;
        q.default_value = narrow ? static_cast<int32_t>(e.default_value) : 0;
        q.flags = e.flags;
        return 0;
    }

    int queryMenu(v4l2_querymenu& m) {
        Control* c = find(m.id);
        if (!c || (c->dump.type != "menu" && c->dump.type != "intmenu")) return EINVAL;
        for (const auto& [index, item] : c->dump.menu) {
            if (index != m.index) continue;
            if (c->dump.type == "menu") {
                // v4l2_querymenu is packed: no reference to its fields.
                char name[sizeof m.name] = {};
                std::memcpy(name, item.data(), std::min(item.size(), sizeof name - 1));
                std::memcpy(m.name, name, sizeof name);
            } else {
                // "5 (0x5)": the value comes first.
                m.value = std::strtoll(item.c_str(), nullptr, 10);
            }
            return 0;
        }
        return EINVAL;
    }

    // Validates and, when `apply`, sets one control as the V4L2 core would.
    int writeControl(uint32_t id, int64_t& value, bool apply) {
        Control* c = find(id);
        if (!c) return EINVAL;
        const uint32_t flags = controlFlags(c->dump);
        if (flags & (V4L2_CTRL_FLAG_READ_ONLY | V4L2_CTRL_FLAG_DISABLED)) return EACCES;
        const std::string& type = c->dump.type;
        if (type == "menu" || type == "intmenu") {
            const bool listed = std::any_of(c->dump.menu.begin(), c->dump.menu.end(),
                                            [&](const auto& item) { return item.first == value; });
            if (!listed) return EINVAL;
        } else if (type == "bool") {
            value = value != 0;
        } else if (type == "int" || type == "int64" || type == "u8" || type == "u16" ||
                   type == "u32") {
            const int64_t lo = c->dump.minimum, hi = std::max(c->dump.minimum, c->dump.maximum);
            value = std::clamp(value, lo, hi);
            const int64_t step = c->dump.step;
            if (step > 1) {
                // The core rounds to the nearest step counted from the minimum (in 128 bits:
                // a dump's range may span all of int64).
                const __int128 offset = static_cast<__int128>(value) - lo;
                __int128 rounded = lo + (offset + step / 2) / step * step;
                if (rounded > hi) rounded -= step;
                value = static_cast<int64_t>(rounded);
            }
        } else if (type != "button" && type != "bitmask") {
            return EINVAL;  // strings and compound controls: the camera sets none
        }
        if (apply) {
            c->value = value;
            c->history.emplace_back(now_ns_, value);
        }
        return 0;
    }

    int readControl(uint32_t id, int64_t& value) {
        Control* c = find(id);
        if (!c) return EINVAL;
        if (controlFlags(c->dump) & V4L2_CTRL_FLAG_WRITE_ONLY) return EACCES;
        if (c->dump.array || !c->dump.value) return EINVAL;
        value = c->value;
        return 0;
    }

    int getControl(v4l2_control& c) {
        int64_t value = 0;
        if (const int error = readControl(c.id, value); error) return error;
        c.value = static_cast<int32_t>(value);
        return 0;
    }

    int setControl(v4l2_control& c) {
        int64_t value = c.value;
        if (const int error = writeControl(c.id, value, true); error) return error;
        c.value = static_cast<int32_t>(value);
        return 0;
    }

    int extControls(v4l2_ext_controls& list, unsigned long request) {
        if (list.count > 64 || (list.count && !list.controls)) return EINVAL;
        const bool write = request != VIDIOC_G_EXT_CTRLS;
        // All or nothing: every control is checked before any is applied.
        for (uint32_t i = 0; i < list.count; ++i) {
            v4l2_ext_control& c = list.controls[i];
            int64_t value = find(c.id) && find(c.id)->dump.type == "int64" ? c.value64 : c.value;
            const int error = write ? writeControl(c.id, value, false) : readControl(c.id, value);
            if (error) {
                list.error_idx = i;
                return error;
            }
        }
        for (uint32_t i = 0; i < list.count; ++i) {
            v4l2_ext_control& c = list.controls[i];
            const bool wide = find(c.id)->dump.type == "int64";
            int64_t value = wide ? c.value64 : c.value;
            if (request == VIDIOC_S_EXT_CTRLS)
                writeControl(c.id, value, true);
            else if (request == VIDIOC_TRY_EXT_CTRLS)
                writeControl(c.id, value, false);
            else
                readControl(c.id, value);
            if (wide)
                c.value64 = value;
            else
                c.value = static_cast<int32_t>(value);
        }
        return 0;
    }

    int requestBuffers(v4l2_requestbuffers& r) {
        if (r.type != V4L2_BUF_TYPE_VIDEO_CAPTURE || r.memory != V4L2_MEMORY_MMAP) return EINVAL;
        if (streaming_) return EBUSY;
        buffers_.clear();
        done_.clear();
        const uint32_t count = std::min<uint32_t>(r.count, VIDEO_MAX_FRAME);
        const uint32_t page = 4096;
        const uint32_t length = (format_.sizeimage + page - 1) / page * page;
        for (uint32_t i = 0; i < count; ++i) {
            Buffer b;
            b.storage.assign(length, 0);
            b.offset = i * length;
            buffers_.push_back(std::move(b));
        }
        r.count = count;
        return 0;
    }

    int queryBuffer(v4l2_buffer& b) {
        if (b.type != V4L2_BUF_TYPE_VIDEO_CAPTURE || b.index >= buffers_.size()) return EINVAL;
        const Buffer& buffer = buffers_[b.index];
        const uint32_t index = b.index;
        std::memset(&b, 0, sizeof b);
        b.index = index;
        b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        b.memory = V4L2_MEMORY_MMAP;
        b.length = static_cast<uint32_t>(buffer.storage.size());
        b.m.offset = buffer.offset;
        b.flags =
            (buffer.queued ? V4L2_BUF_FLAG_QUEUED : 0) | (buffer.done ? V4L2_BUF_FLAG_DONE : 0);
        return 0;
    }

    int queueBuffer(v4l2_buffer& b) {
        if (b.type != V4L2_BUF_TYPE_VIDEO_CAPTURE || b.memory != V4L2_MEMORY_MMAP ||
            b.index >= buffers_.size())
            return EINVAL;
        Buffer& buffer = buffers_[b.index];
        if (buffer.queued || buffer.done) return EINVAL;
        buffer.queued = true;
        queue_.push_back(b.index);
        // As the kernel does, the structure comes back describing the queued buffer: no
        // timestamp, sequence or payload any more.
        const uint32_t index = b.index;
        std::memset(&b, 0, sizeof b);
        b.index = index;
        b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        b.memory = V4L2_MEMORY_MMAP;
        b.length = static_cast<uint32_t>(buffer.storage.size());
        b.m.offset = buffer.offset;
        b.flags = V4L2_BUF_FLAG_QUEUED | options_.timestamp_type;
        return 0;
    }

    int dequeueBuffer(v4l2_buffer& b) {
        if (b.type != V4L2_BUF_TYPE_VIDEO_CAPTURE || b.memory != V4L2_MEMORY_MMAP) return EINVAL;
        if (!streaming_) return EINVAL;
        advanceTo(now_ns_);
        if (gone_) return ENODEV;
        if (done_.empty()) return EAGAIN;
        Buffer& buffer = buffers_[done_.front()];
        done_.pop_front();
        buffer.done = false;
        b = buffer.filled;
        return 0;
    }

    int streamOn(int type) {
        if (type != V4L2_BUF_TYPE_VIDEO_CAPTURE || buffers_.empty()) return EINVAL;
        if (!streaming_) {
            streaming_ = true;
            next_start_ns_ = now_ns_;
        }
        return 0;
    }

    int streamOff(int type) {
        if (type != V4L2_BUF_TYPE_VIDEO_CAPTURE) return EINVAL;
        streaming_ = false;
        for (Buffer& b : buffers_) b.queued = b.done = false;
        queue_.clear();
        done_.clear();
        return 0;
    }

    int64_t periodNs() const {
        if (!time_per_frame_.denominator || !time_per_frame_.numerator) return kNsPerS / 30;
        return static_cast<int64_t>(time_per_frame_.numerator) * kNsPerS /
               time_per_frame_.denominator;
    }

    // The controls a frame starting its exposure at `start` is exposed with.
    V4l2PlaybackFrame frameAt(int64_t start) const {
        V4l2PlaybackFrame frame;
        frame.sequence = sequence_;
        frame.exposure_start_ns = start;
        const int64_t latency = options_.control_latency_frames * periodNs();
        for (const Control& c : controls_) {
            int64_t value = c.history.front().second;
            for (const auto& [time, v] : c.history)
                if (time == std::numeric_limits<int64_t>::min() || time + latency <= start)
                    value = v;
            frame.controls[c.dump.id] = value;
        }
        const V4l2FormatInfo* info = findV4l2Format(format_.pixelformat);
        frame.bits = info ? info->bits : 8;
        return frame;
    }

    // Seconds, in [0, 1e6] whatever the controls say, so that times stay within int64 ns.
    double exposureOf(const V4l2PlaybackFrame& frame) const {
        double exposure = 0.0;
        if (options_.exposure_s) {
            exposure = options_.exposure_s(frame);
        } else if (const auto it = frame.controls.find(V4L2_CID_EXPOSURE_ABSOLUTE);
                   it != frame.controls.end()) {
            exposure = static_cast<double>(it->second) * 1e-4;
        }
        return std::isfinite(exposure) ? std::clamp(exposure, 0.0, 1e6) : 0.0;
    }

    int64_t frameDone(int64_t start) const {
        const double exposure = exposureOf(frameAt(start));
        const double readout = std::clamp(options_.readout_s, 0.0, 1e6);
        return start + static_cast<int64_t>(std::llround((exposure + readout) * 1e9));
    }

    // Completes every frame done by `time` and moves the clock there.
    void advanceTo(int64_t time) {
        if (!streaming_) {
            now_ns_ = std::max(now_ns_, time);
            return;
        }
        for (;;) {
            const int64_t start = next_start_ns_;
            const V4l2PlaybackFrame frame = frameAt(start);
            const double exposure = exposureOf(frame);
            const int64_t exposure_ns = static_cast<int64_t>(std::llround(exposure * 1e9));
            const int64_t done = frameDone(start);
            if (done > time) break;
            if (options_.disconnect_after_frames >= 0 &&
                sequence_ >= options_.disconnect_after_frames) {
                gone_ = true;
                break;
            }
            next_start_ns_ = start + std::max(periodNs(), exposure_ns);
            if (!queue_.empty()) fill(queue_.front(), frame, done);
            if (!queue_.empty()) queue_.pop_front();
            ++sequence_;
        }
        now_ns_ = std::max(now_ns_, time);
    }

    void fill(uint32_t index, const V4l2PlaybackFrame& frame, int64_t done_ns) {
        Buffer& b = buffers_[index];
        const int64_t w = format_.width, h = format_.height;
        const V4l2FormatInfo* info = findV4l2Format(format_.pixelformat);
        if (info) {
            std::vector<uint16_t> samples(static_cast<size_t>(w * h));
            const uint32_t white = (1u << info->bits) - 1;
            for (int64_t y = 0; y < h; ++y)
                for (int64_t x = 0; x < w; ++x) {
                    const uint32_t v = options_.scene ? options_.scene(x, y, frame)
                                                      : static_cast<uint32_t>(x + 2 * y) & white;
                    samples[static_cast<size_t>(y * w + x)] =
                        static_cast<uint16_t>(std::min(v, white));
                }
            const std::vector<uint8_t> bytes =
                packV4l2Samples(*info, samples, w, h, format_.bytesperline);
            std::copy(bytes.begin(),
                      bytes.begin() +
                          static_cast<std::ptrdiff_t>(std::min(bytes.size(), b.storage.size())),
                      b.storage.begin());
        }
        v4l2_buffer& out = b.filled;
        std::memset(&out, 0, sizeof out);
        out.index = index;
        out.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        out.memory = V4L2_MEMORY_MMAP;
        out.bytesused = std::min<uint32_t>(format_.sizeimage, b.storage.size());
        out.length = static_cast<uint32_t>(b.storage.size());
        out.m.offset = b.offset;
        out.field = V4L2_FIELD_NONE;
        out.sequence = static_cast<uint32_t>(frame.sequence);
        const int64_t stamp = options_.start_of_exposure ? frame.exposure_start_ns : done_ns;
        out.timestamp.tv_sec = stamp / kNsPerS;
        out.timestamp.tv_usec = stamp % kNsPerS / 1000;
        out.flags = options_.timestamp_type |
                    (options_.start_of_exposure ? V4L2_BUF_FLAG_TSTAMP_SRC_SOE
                                                : V4L2_BUF_FLAG_TSTAMP_SRC_EOF) |
                    V4L2_BUF_FLAG_DONE;
        if (options_.error_every > 0 && (frame.sequence + 1) % options_.error_every == 0)
            out.flags |= V4L2_BUF_FLAG_ERROR;
        b.queued = false;
        b.done = true;
        done_.push_back(index);
    }

    V4l2DeviceDump dump_;
    V4l2PlaybackOptions options_;
    std::string name_;
    std::vector<Control> controls_;
    v4l2_pix_format format_{};
    v4l2_fract time_per_frame_{0, 0};
    std::vector<Buffer> buffers_;
    std::deque<uint32_t> queue_;  // queued buffers in the order they fill
    std::deque<uint32_t> done_;   // filled buffers in the order they dequeue
    bool streaming_ = false;
    bool gone_ = false;
    int64_t now_ns_ = 0;
    int64_t next_start_ns_ = 0;
    int64_t sequence_ = 0;
};

}  // namespace

Result<std::unique_ptr<V4l2Playback>> makeV4l2Playback(V4l2DeviceDump dump,
                                                       V4l2PlaybackOptions options) {
    if (!dump.has_driver_info)
        return makeError(ErrorCode::NotFound,
                         dump.source + ": no 'Driver Info' section (record `v4l2-ctl --all`)");
    if (!dump.has_format_list)
        return makeError(
            ErrorCode::NotFound,
            dump.source + ": no format list (record `v4l2-ctl --list-formats-ext` after it)");
    return std::unique_ptr<V4l2Playback>(
        std::make_unique<Playback>(std::move(dump), std::move(options)));
}

}  // namespace flarelab::drivers
