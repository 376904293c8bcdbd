// Helpers the serial stage drivers (zaber_head, apt_head) and their simulators share: URI
// parameters with ranges, numbers in messages, error text without its tag.
#pragma once

#include <cmath>
#include <optional>
#include <sstream>
#include <string>

#include "common/result.h"
#include "drivers/device.h"

namespace flarelab::drivers::detail {

inline std::string fmt(double x) {
    std::ostringstream out;
    out << x;
    return out.str();
}

// An error's message without its "[tag] device: " prefix, to quote inside another error without
// carrying its tag (and so its kind) along.
inline std::string untagged(const Error& e) {
    if (e.message.empty() || e.message[0] != '[') return e.message;
    const size_t colon = e.message.find(": ");
    return colon == std::string::npos ? e.message : e.message.substr(colon + 2);
}

inline Error badUriParam(const DeviceUri& uri, const std::string& key, const std::string& rule) {
    return makeError(ErrorCode::InvalidArgument,
                     "device uri '" + uri.text + "': " + key + " must be " + rule);
}

inline Result<double> uriPositive(const DeviceUri& uri, const std::string& key, double fallback) {
    auto value = uri.number(key, fallback);
    if (!value) return value.error();
    if (!(*value > 0.0)) return badUriParam(uri, key, "positive");
    return *value;
}

inline Result<long long> uriWhole(
    const DeviceUri& uri, const std::string& key, long long fallback, long long lo, long long hi) {
    auto value = uri.number(key, static_cast<double>(fallback));
    if (!value) return value.error();
    if (*value != std::floor(*value) || *value < static_cast<double>(lo) ||
        *value > static_cast<double>(hi))
        return badUriParam(
            uri, key, "a whole number in [" + std::to_string(lo) + ", " + std::to_string(hi) + "]");
    return static_cast<long long>(*value);
}

// nullopt when the URI does not give the parameter.
inline Result<std::optional<double>> uriOptional(const DeviceUri& uri, const std::string& key) {
    if (!uri.params.count(key)) return std::optional<double>{};
    auto value = uri.number(key, 0.0);
    if (!value) return value.error();
    return std::optional<double>(*value);
}

}  // namespace flarelab::drivers::detail
