// ============================================================================
//  flarelab daemon: notifyReady, notifyStopping, notifyWatchdog, watchdogInterval
// ============================================================================
//
// systemd's service notification (sd_notify(3)), for a unit of Type=notify: READY=1 once the
// daemon answers on its socket, WATCHDOG=1 at half the interval the unit asks (WatchdogSec=, seen
// as WATCHDOG_USEC), STOPPING=1 when it begins to stop, and STATUS= lines for `systemctl status`.
// Every call does nothing when the daemon was not started by systemd (no NOTIFY_SOCKET), and
// when flarelab was built without libsystemd (systemdNotifyBuiltIn() says which).
#pragma once

#include <chrono>
#include <string>

namespace flarelab::daemon {

bool systemdNotifyBuiltIn();
void notifyReady(const std::string& status);
void notifyStopping(const std::string& status);
void notifyWatchdog();
void notifyStatus(const std::string& status);
// The watchdog interval systemd asks of this process; zero when none.
std::chrono::microseconds watchdogInterval();

}  // namespace flarelab::daemon
