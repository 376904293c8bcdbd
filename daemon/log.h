// ============================================================================
//  flarelab daemon: logEvent, LogField
// ============================================================================
//
// The daemon's structured log: one line per event on standard error, in logfmt, through spdlog,
//
//     ts=2026-11-29T21:40:03.120Z level=info event=job.state job=job-000003 state=RUNNING
//
// so that people can read it and programs (journald, a log shipper) can split it into fields.
// Values holding spaces, quotes or '=' are quoted, with '"' and '\' escaped; control
// characters are written as \n, \t or \xHH, so a value from a request can never forge a line.
#pragma once

#include <initializer_list>
#include <span>
#include <string>
#include <string_view>
#include <utility>

namespace flarelab::daemon {

enum class LogLevel { Debug, Info, Warn, Error };

using LogField = std::pair<std::string_view, std::string>;

void logEvent(LogLevel level, std::string_view event, std::initializer_list<LogField> fields = {});
// The same with fields only known at run time (a camera's statistics).
void logEvent(LogLevel level, std::string_view event, std::span<const LogField> fields);
// Messages below `level` are dropped (Info by default).
void setLogLevel(LogLevel level);
// The logfmt text of one value (quoted and escaped where needed).
std::string logValue(std::string_view value);

}  // namespace flarelab::daemon
