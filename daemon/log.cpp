#include "daemon/log.h"

#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>

#include <cstdio>
#include <memory>

namespace flarelab::daemon {
namespace {

std::shared_ptr<spdlog::logger>& logger() {
    static std::shared_ptr<spdlog::logger> instance = [] {
        auto made = std::make_shared<spdlog::logger>(
            "flarelabd", std::make_shared<spdlog::sinks::stderr_sink_mt>());
        made->set_pattern("ts=%Y-%m-%dT%H:%M:%S.%eZ level=%l %v", spdlog::pattern_time_type::utc);
        made->set_level(spdlog::level::info);
        made->flush_on(spdlog::level::debug);
        return made;
    }();
    return instance;
}

spdlog::level::level_enum toSpd(LogLevel level) {
    switch (level) {
        case LogLevel::Debug:
            return spdlog::level::debug;
        case LogLevel::Info:
            return spdlog::level::info;
        case LogLevel::Warn:
            return spdlog::level::warn;
        case LogLevel::Error:
            return spdlog::level::err;
    }
    return spdlog::level::info;
}

}  // namespace

std::string logValue(std::string_view value) {
    bool quote = value.empty();
    std::string body;
    for (const char ch : value) {
        const unsigned char c = static_cast<unsigned char>(ch);
        if (c == ' ' || c == '=' || c == '"') quote = true;
        if (c == '"' || c == '\\') {
            body += '\\';
            body += ch;
        } else if (c == '\n') {
            body += "\\n";
            quote = true;
        } else if (c == '\t') {
            body += "\\t";
            quote = true;
        } else if (c < 0x20 || c == 0x7f) {
            char hex[8];
            std::snprintf(hex, sizeof hex, "\\x%02x", c);
            body += hex;
            quote = true;
        } else {
            body += ch;
        }
    }
    return quote ? "\"" + body + "\"" : body;
}

void logEvent(LogLevel level, std::string_view event, std::initializer_list<LogField> fields) {
    logEvent(level, event, std::span<const LogField>(fields.begin(), fields.size()));
}

void logEvent(LogLevel level, std::string_view event, std::span<const LogField> fields) {
    auto& log = logger();
    if (!log->should_log(toSpd(level))) return;
    std::string line = "event=" + logValue(event);
    for (const auto& [key, value] : fields) {
        line += ' ';
        line += key;
        line += '=';
        line += logValue(value);
    }
    log->log(toSpd(level), "{}", line);
}

void setLogLevel(LogLevel level) { logger()->set_level(toSpd(level)); }

}  // namespace flarelab::daemon
