// ============================================================================
//  flarelab daemon: logEvent, LogField, LogTarget, flushLog
// ============================================================================
//
// The daemon's structured log: one line per event on standard error, in logfmt, through spdlog,
//
//     ts=2026-11-29T21:40:03.120Z level=info event=job.state job=job-000003 state=RUNNING
//
// so that people can read it and programs (journald, a log shipper) can split it into fields.
// Values holding spaces, quotes or '=' are quoted, with '"' and '\' escaped; control
// characters are written as \n, \t or \xHH, so a value from a request can never forge a line.
//
// Under systemd (LogTarget::Journal: standard error is the journal's stream) a line starts with
// its syslog priority instead of the time, "<6>level=info event=job.state ...", which journald
// takes as the entry's priority (sd-daemon(3)); the journal stamps the time itself.
//
// Nothing waits on standard error: logEvent formats the line and hands it to a writer thread. A
// reader that stops reading (a stalled pipe, a paused terminal) must not stop the rig, so lines
// wait for it up to 1 MiB; beyond, new lines are dropped and counted, and once standard error
// takes lines again the writer says so first: "event=log.dropped lines=N".
#pragma once

#include <cstdint>
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

enum class LogTarget { Terminal, Journal };
// Journal when JOURNAL_STREAM (set by systemd: "DEVICE:INODE" of the stream it gave the service)
// names the file standard error is now; Terminal otherwise (also when standard error was
// redirected since, as the variable is inherited).
LogTarget detectLogTarget();
void setLogTarget(LogTarget target);  // Terminal until set

// Waits up to wait_s for the lines logged so far to be written; false when standard error did
// not take them in time (they stay queued).
bool flushLog(double wait_s);
// Lines dropped so far because standard error did not take them.
uint64_t droppedLogLines();

}  // namespace flarelab::daemon
