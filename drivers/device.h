// ============================================================================
//  flarelab drivers: DeviceIdentity, DeviceListing, DeviceFault, DeviceUri, DeviceRegistry
// ============================================================================
//
// What every device backend (cameras, heads; simulated or real) shares: how it names itself,
// how its failures are told apart, and how a program opens one by URI ("sim:",
// "v4l2:/dev/video0", "aravis:Basler-40012345?packet_size=9000") or by an alias a lab gives it.
//
// Device failures are ordinary Errors (common/result.h) whose message carries a tag in brackets,
// "[timeout] sim-head SIMHEAD-0: move to 12 deg did not arrive within 0.5 s", so that a daemon
// can react to the kind (retry a timeout, re-home after lost position, give up on a device that
// is gone) while the message stays readable and survives Error::withContext. ErrorCode has no
// codes for these kinds yet; deviceFaultOf reads the tag back.
#pragma once

#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "common/result.h"

namespace flarelab::drivers {

struct DeviceIdentity {
    std::string backend;  // URI scheme of the backend: "sim", "v4l2", ...
    std::string model;
    std::string serial;
    std::string uri;  // the URI it was opened with, if any

    std::string describe() const { return model + " " + serial; }
};

// One device a backend can see now, for `flarelab rig devices`: how to open it and what a lab
// needs to recognise it (a camera's formats, a serial port's USB vendor, product and serial).
struct DeviceListing {
    std::string uri;      // opens it: "v4l2:/dev/video0", "aravis:Fake_1", "zaber:/dev/ttyUSB0"
    std::string kind;     // "camera", "head" or "serial-port" (a port that may hold a stage)
    std::string backend;  // URI scheme
    std::string model;
    std::string serial;
    // "key: value" lines: formats, sizes, USB ids, driver, bus; free text, one fact a line.
    std::vector<std::string> details;
    bool operator==(const DeviceListing&) const = default;
};

enum class DeviceFault {
    OutOfRange,    // a setting or target outside the device's range (ErrorCode::InvalidArgument)
    Timeout,       // the device did not answer or arrive in time (IoError)
    Stalled,       // a motor stopped against resistance (IoError)
    NotHomed,      // the head does not know its position: home it first (Unsupported)
    LostPosition,  // the head noticed it lost steps during a move; it is no longer homed (IoError)
    Stopped,       // a move was interrupted by stop(), a capture by abort() (IoError)
    Busy,          // another command is still running (Unsupported)
    Disconnected,  // the device is gone (unplugged, powered off) (NotFound)
    BadFrame,      // a frame arrived damaged: packets lost, wrong size (IoError); retaking may help
};

// The tag written in brackets: "out-of-range", "timeout", "stalled", "not-homed",
// "lost-position", "stopped", "busy", "disconnected", "bad-frame".
const char* deviceFaultName(DeviceFault fault);

// An Error "[tag] <device>: <detail>" with the ErrorCode noted above.
Error deviceError(DeviceFault fault, std::string_view device, std::string_view detail);

// The fault tagged in an error's message (with or without context prepended); nullopt when the
// error is not a tagged device error.
std::optional<DeviceFault> deviceFaultOf(const Error& error);

// scheme ":" path ["?" key "=" value ("&" key "=" value)*]. The scheme is lower-case letters,
// digits, '+', '-', '.'; the path may be empty ("sim:").
struct DeviceUri {
    std::string text;  // as given
    std::string scheme;
    std::string path;
    std::map<std::string, std::string> params;

    // A parameter as a number, `fallback` when absent; InvalidArgument naming the key when the
    // value is not a finite number.
    Result<double> number(const std::string& key, double fallback) const;
    // InvalidArgument naming the first parameter not in `known`.
    Status onlyParams(const std::vector<std::string>& known) const;
};

// InvalidArgument naming the URI when it does not follow the grammar above. A bare scheme
// ("sim") is read as "sim:".
Result<DeviceUri> parseDeviceUri(std::string_view text);

// Opens devices of one kind (Camera, Head) by URI through the backends added to it. Backends
// register an opener per scheme and, optionally, a lister that names the URIs of the devices it
// can see now (enumeration). Not thread-safe: fill it at start-up, then only open.
template <typename Device>
class DeviceRegistry {
public:
    using Opener = std::function<Result<std::unique_ptr<Device>>(const DeviceUri&)>;
    using Lister = std::function<std::vector<DeviceListing>()>;

    // InvalidArgument when the scheme is malformed or already taken.
    Status addBackend(const std::string& scheme,
                      const std::string& description,
                      Opener open,
                      Lister list = {}) {
        auto parsed = parseDeviceUri(scheme + ":");
        if (!parsed || parsed->scheme != scheme)
            return makeError(ErrorCode::InvalidArgument,
                             "device registry: bad scheme '" + scheme + "'");
        if (backends_.count(scheme))
            return makeError(ErrorCode::InvalidArgument,
                             "device registry: scheme '" + scheme + "' is registered twice");
        backends_[scheme] = Backend{description, std::move(open), std::move(list)};
        return Ok{};
    }

    // A name a lab uses for a URI ("bench-cam" -> "v4l2:/dev/video2"). InvalidArgument when the
    // name contains ':' or is taken.
    Status addAlias(const std::string& name, const std::string& uri) {
        if (name.empty() || name.find(':') != std::string::npos || aliases_.count(name))
            return makeError(ErrorCode::InvalidArgument,
                             "device registry: alias '" + name + "' is empty, has ':' or is taken");
        aliases_[name] = uri;
        return Ok{};
    }

    // Opens by alias or URI. NotFound when no backend serves the scheme (the message lists the
    // ones that do); otherwise whatever the backend's opener returns.
    Result<std::unique_ptr<Device>> open(std::string_view name_or_uri) const {
        std::string text(name_or_uri);
        if (auto alias = aliases_.find(text); alias != aliases_.end()) text = alias->second;
        auto uri = parseDeviceUri(text);
        if (!uri) return uri.error();
        auto backend = backends_.find(uri->scheme);
        if (backend == backends_.end()) {
            std::string known;
            for (const auto& [scheme, b] : backends_) known += (known.empty() ? "" : ", ") + scheme;
            return makeError(ErrorCode::NotFound, "device registry: no backend for '" + text +
                                                      "' (known schemes: " + known + ")");
        }
        return backend->second.open(*uri);
    }

    // The devices every backend with a lister sees now, in scheme order.
    std::vector<DeviceListing> enumerate() const {
        std::vector<DeviceListing> found;
        for (const auto& [scheme, backend] : backends_)
            if (backend.list)
                for (DeviceListing& d : backend.list()) found.push_back(std::move(d));
        return found;
    }

    // (scheme, description) of every backend.
    std::vector<std::pair<std::string, std::string>> backends() const {
        std::vector<std::pair<std::string, std::string>> out;
        for (const auto& [scheme, backend] : backends_)
            out.emplace_back(scheme, backend.description);
        return out;
    }

private:
    struct Backend {
        std::string description;
        Opener open;
        Lister list;
    };
    std::map<std::string, Backend> backends_;
    std::map<std::string, std::string> aliases_;
};

}  // namespace flarelab::drivers
