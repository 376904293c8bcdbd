#include "daemon/log.h"

#include <poll.h>
#include <spdlog/pattern_formatter.h>
#include <spdlog/sinks/base_sink.h>
#include <spdlog/spdlog.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <deque>
#include <memory>
#include <mutex>
#include <optional>
#include <stop_token>
#include <thread>

namespace flarelab::daemon {
namespace {

using Clock = std::chrono::steady_clock;

constexpr size_t kMaxQueuedBytes = size_t{1} << 20;
constexpr size_t kMaxBatchBytes = size_t{64} << 10;
// A pipe with room for one more buffer takes a write of up to PIPE_BUF bytes without blocking;
// writing no more at a time after poll() said POLLOUT keeps the writer from blocking on it.
constexpr size_t kWriteChunk = 4096;

std::atomic<LogTarget> g_target{LogTarget::Terminal};

char syslogPriority(spdlog::level::level_enum level) {
    switch (level) {
        case spdlog::level::trace:
        case spdlog::level::debug:
            return '7';
        case spdlog::level::info:
            return '6';
        case spdlog::level::warn:
            return '4';
        case spdlog::level::err:
            return '3';
        default:
            return '2';
    }
}

// A line for the writer's own report, formatted as spdlog formats the others.
std::string ownLine(const std::string& body) {
    if (g_target.load() == LogTarget::Journal) return "<4>level=warning " + body + "\n";
    const auto now = std::chrono::system_clock::now();
    const std::time_t seconds = std::chrono::system_clock::to_time_t(now);
    const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch());
    std::tm tm{};
    gmtime_r(&seconds, &tm);
    char stamp[40];
    std::strftime(stamp, sizeof stamp, "%Y-%m-%dT%H:%M:%S", &tm);
    char line[64];
    std::snprintf(line, sizeof line, "ts=%s.%03dZ", stamp, static_cast<int>(ms.count() % 1000));
    return std::string(line) + " level=warning " + body + "\n";
}

// Standard error's writer: a thread of its own, so that no thread of the daemon waits on it.
class StderrWriter {
public:
    static StderrWriter& instance() {
        static StderrWriter writer;
        return writer;
    }

    void push(std::string line) {
        {
            std::lock_guard lock(mutex_);
            if (queued_bytes_ + line.size() > kMaxQueuedBytes) {
                ++dropped_;
                ++unreported_;
                return;
            }
            queued_bytes_ += line.size();
            lines_.push_back(std::move(line));
        }
        wake_.notify_one();
    }

    bool flush(double wait_s) {
        std::unique_lock lock(mutex_);
        return idle_.wait_for(lock, std::chrono::duration<double>(std::max(0.0, wait_s)),
                              [&] { return lines_.empty() && unreported_ == 0 && !writing_; });
    }

    uint64_t dropped() const {
        std::lock_guard lock(mutex_);
        return dropped_;
    }

private:
    StderrWriter() : thread_([this](std::stop_token stop) { run(stop); }) {}

    void run(std::stop_token stop) {
        std::unique_lock lock(mutex_);
        for (;;) {
            wake_.wait(lock, stop, [&] { return !lines_.empty() || unreported_ > 0; });
            if (lines_.empty() && unreported_ == 0) return;  // stopped with nothing left
            std::string text;
            if (unreported_ > 0) {
                text = ownLine("event=log.dropped lines=" + std::to_string(unreported_));
                unreported_ = 0;
            }
            while (!lines_.empty() && text.size() < kMaxBatchBytes) {
                queued_bytes_ -= lines_.front().size();
                text += lines_.front();
                lines_.pop_front();
            }
            writing_ = true;
            lock.unlock();
            const bool written = writeOut(text, stop);
            lock.lock();
            writing_ = false;
            idle_.notify_all();
            if (!written && stop.stop_requested()) return;  // exiting; standard error is stuck
        }
    }

    // Writes all of `text` to standard error unless it fails, or stays full for half a second
    // after a stop was requested. Never blocks for longer than a poll slice.
    bool writeOut(const std::string& text, const std::stop_token& stop) {
        struct stat info {};
        const bool socket = ::fstat(STDERR_FILENO, &info) == 0 && S_ISSOCK(info.st_mode);
        std::optional<Clock::time_point> give_up;
        size_t done = 0;
        while (done < text.size()) {
            if (stop.stop_requested()) {
                if (!give_up) give_up = Clock::now() + std::chrono::milliseconds(500);
                if (Clock::now() > *give_up) return false;
            }
            pollfd p{STDERR_FILENO, POLLOUT, 0};
            const int ready = ::poll(&p, 1, 100);
            if (ready < 0 && errno != EINTR) return false;
            if (ready <= 0) continue;
            if (p.revents & (POLLERR | POLLNVAL)) return false;
            const size_t n = std::min(kWriteChunk, text.size() - done);
            const ssize_t wrote =
                socket ? ::send(STDERR_FILENO, text.data() + done, n, MSG_DONTWAIT | MSG_NOSIGNAL)
                       : ::write(STDERR_FILENO, text.data() + done, n);
            if (wrote < 0 && (errno == EINTR || errno == EAGAIN)) continue;
            if (wrote <= 0) return false;  // closed or broken: nobody to tell
            done += static_cast<size_t>(wrote);
        }
        return true;
    }

    mutable std::mutex mutex_;
    std::condition_variable_any wake_;
    std::condition_variable idle_;
    std::deque<std::string> lines_;
    size_t queued_bytes_ = 0;
    uint64_t dropped_ = 0, unreported_ = 0;
    bool writing_ = false;
    std::jthread thread_;  // last: it uses the members above
};

// spdlog's end: the formatted line goes to the writer.
class WriterSink final : public spdlog::sinks::base_sink<std::mutex> {
protected:
    void sink_it_(const spdlog::details::log_msg& msg) override {
        spdlog::memory_buf_t text;
        formatter_->format(msg, text);
        StderrWriter::instance().push(std::string(text.data(), text.size()));
    }
    void flush_() override {}
};

// "<6>" for an info line: the priority journald reads from the start of a line.
class SyslogPriorityFlag final : public spdlog::custom_flag_formatter {
public:
    void format(const spdlog::details::log_msg& msg,
                const std::tm&,
                spdlog::memory_buf_t& dest) override {
        const char text[3] = {'<', syslogPriority(msg.level), '>'};
        dest.append(text, text + 3);
    }
    std::unique_ptr<custom_flag_formatter> clone() const override {
        return std::make_unique<SyslogPriorityFlag>();
    }
};

std::unique_ptr<spdlog::formatter> formatterFor(LogTarget target) {
    if (target == LogTarget::Journal) {
        auto f = std::make_unique<spdlog::pattern_formatter>();
        f->add_flag<SyslogPriorityFlag>('*').set_pattern("%*level=%l %v");
        return f;
    }
    return std::make_unique<spdlog::pattern_formatter>("ts=%Y-%m-%dT%H:%M:%S.%eZ level=%l %v",
                                                       spdlog::pattern_time_type::utc);
}

std::shared_ptr<spdlog::logger>& logger() {
    static std::shared_ptr<spdlog::logger> instance = [] {
        StderrWriter::instance();  // made first, so that it outlives the logger
        auto made = std::make_shared<spdlog::logger>("flarelabd", std::make_shared<WriterSink>());
        made->set_formatter(formatterFor(LogTarget::Terminal));
        made->set_level(spdlog::level::info);
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

LogTarget detectLogTarget() {
    const char* stream = std::getenv("JOURNAL_STREAM");
    if (!stream) return LogTarget::Terminal;
    unsigned long long device = 0, inode = 0;
    char end = 0;
    if (std::sscanf(stream, "%llu:%llu%c", &device, &inode, &end) != 2) return LogTarget::Terminal;
    struct stat info {};
    if (::fstat(STDERR_FILENO, &info) != 0) return LogTarget::Terminal;
    return static_cast<unsigned long long>(info.st_dev) == device &&
                   static_cast<unsigned long long>(info.st_ino) == inode
               ? LogTarget::Journal
               : LogTarget::Terminal;
}

void setLogTarget(LogTarget target) {
    g_target = target;
    logger()->set_formatter(formatterFor(target));
}

bool flushLog(double wait_s) {
    logger();
    return StderrWriter::instance().flush(wait_s);
}

uint64_t droppedLogLines() { return StderrWriter::instance().dropped(); }

}  // namespace flarelab::daemon
