#include "daemon/notify.h"

#if FLARELAB_HAVE_SYSTEMD
#include <systemd/sd-daemon.h>
#endif

namespace flarelab::daemon {
namespace {

void send(const std::string& state) {
#if FLARELAB_HAVE_SYSTEMD
    // 0: the environment is left as it is, so a child could notify too (it has none).
    (void)sd_notify(0, state.c_str());
#else
    (void)state;
#endif
}

// A STATUS= value on one line: the protocol separates assignments by newlines.
std::string oneLine(std::string text) {
    for (char& c : text)
        if (c == '\n' || c == '\r') c = ' ';
    return text;
}

}  // namespace

bool systemdNotifyBuiltIn() { return FLARELAB_HAVE_SYSTEMD != 0; }

void notifyReady(const std::string& status) { send("READY=1\nSTATUS=" + oneLine(status)); }

void notifyStopping(const std::string& status) { send("STOPPING=1\nSTATUS=" + oneLine(status)); }

void notifyWatchdog() { send("WATCHDOG=1"); }

void notifyStatus(const std::string& status) { send("STATUS=" + oneLine(status)); }

std::chrono::microseconds watchdogInterval() {
#if FLARELAB_HAVE_SYSTEMD
    uint64_t usec = 0;
    if (sd_watchdog_enabled(0, &usec) > 0) return std::chrono::microseconds(usec);
#endif
    return std::chrono::microseconds(0);
}

}  // namespace flarelab::daemon
