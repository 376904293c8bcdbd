#include "drivers/device.h"

#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdlib>

namespace flarelab::drivers {
namespace {

constexpr DeviceFault kFaults[] = {
    DeviceFault::OutOfRange, DeviceFault::Timeout,      DeviceFault::Stalled,
    DeviceFault::NotHomed,   DeviceFault::LostPosition, DeviceFault::Stopped,
    DeviceFault::Busy,       DeviceFault::Disconnected, DeviceFault::BadFrame,
};

ErrorCode codeOf(DeviceFault fault) {
    switch (fault) {
        case DeviceFault::OutOfRange:
            return ErrorCode::InvalidArgument;
        case DeviceFault::NotHomed:
        case DeviceFault::Busy:
            return ErrorCode::Unsupported;
        case DeviceFault::Disconnected:
            return ErrorCode::NotFound;
        case DeviceFault::Timeout:
        case DeviceFault::Stalled:
        case DeviceFault::LostPosition:
        case DeviceFault::Stopped:
        case DeviceFault::BadFrame:
            return ErrorCode::IoError;
    }
    return ErrorCode::Internal;
}

bool isSchemeChar(char c) {
    return (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '+' || c == '-' || c == '.';
}

}  // namespace

const char* deviceFaultName(DeviceFault fault) {
    switch (fault) {
        case DeviceFault::OutOfRange:
            return "out-of-range";
        case DeviceFault::Timeout:
            return "timeout";
        case DeviceFault::Stalled:
            return "stalled";
        case DeviceFault::NotHomed:
            return "not-homed";
        case DeviceFault::LostPosition:
            return "lost-position";
        case DeviceFault::Stopped:
            return "stopped";
        case DeviceFault::Busy:
            return "busy";
        case DeviceFault::Disconnected:
            return "disconnected";
        case DeviceFault::BadFrame:
            return "bad-frame";
    }
    return "unknown";
}

Error deviceError(DeviceFault fault, std::string_view device, std::string_view detail) {
    std::string message = "[";
    message += deviceFaultName(fault);
    message += "] ";
    message += device;
    message += ": ";
    message += detail;
    return Error{codeOf(fault), std::move(message)};
}

std::optional<DeviceFault> deviceFaultOf(const Error& error) {
    for (DeviceFault fault : kFaults) {
        const std::string tag = std::string("[") + deviceFaultName(fault) + "]";
        if (error.message.find(tag) != std::string::npos) return fault;
    }
    return std::nullopt;
}

Result<double> DeviceUri::number(const std::string& key, double fallback) const {
    auto it = params.find(key);
    if (it == params.end()) return fallback;
    const std::string& value = it->second;
    char* end = nullptr;
    const double x = std::strtod(value.c_str(), &end);
    if (value.empty() || end != value.c_str() + value.size() || !std::isfinite(x))
        return makeError(ErrorCode::InvalidArgument,
                         "device uri '" + text + "': " + key + "='" + value + "' is not a number");
    return x;
}

Status DeviceUri::onlyParams(const std::vector<std::string>& known) const {
    for (const auto& [key, value] : params) {
        bool found = false;
        for (const std::string& k : known) found = found || k == key;
        if (!found) {
            std::string list;
            for (const std::string& k : known) list += (list.empty() ? "" : ", ") + k;
            return makeError(
                ErrorCode::InvalidArgument,
                "device uri '" + text + "': unknown parameter '" + key + "' (known: " + list + ")");
        }
    }
    return Ok{};
}

Result<DeviceUri> parseDeviceUri(std::string_view text) {
    DeviceUri uri;
    uri.text = std::string(text);
    const auto bad = [&](const std::string& why) -> Error {
        return makeError(ErrorCode::InvalidArgument, "device uri '" + uri.text + "': " + why);
    };
    size_t colon = text.find(':');
    std::string_view scheme = colon == std::string_view::npos ? text : text.substr(0, colon);
    std::string_view rest =
        colon == std::string_view::npos ? std::string_view{} : text.substr(colon + 1);
    if (scheme.empty()) return bad("no scheme before ':' (e.g. 'sim:')");
    for (char c : scheme)
        if (!isSchemeChar(c)) return bad("scheme may hold only a-z, 0-9, '+', '-', '.'");
    uri.scheme = std::string(scheme);
    const size_t question = rest.find('?');
    uri.path = std::string(rest.substr(0, question));
    if (question == std::string_view::npos) return uri;
    std::string_view query = rest.substr(question + 1);
    while (!query.empty()) {
        const size_t amp = query.find('&');
        const std::string_view pair = query.substr(0, amp);
        const size_t eq = pair.find('=');
        if (eq == std::string_view::npos || eq == 0)
            return bad("parameter '" + std::string(pair) + "' is not key=value");
        const std::string key(pair.substr(0, eq));
        if (uri.params.count(key)) return bad("parameter '" + key + "' given twice");
        uri.params[key] = std::string(pair.substr(eq + 1));
        if (amp == std::string_view::npos) break;
        query = query.substr(amp + 1);
    }
    return uri;
}

}  // namespace flarelab::drivers
