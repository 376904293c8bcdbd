// ============================================================================
//  flarelab drivers: SerialPort, SerialOptions, FlowControl, listSerialPorts
// ============================================================================
//
// A serial line through the kernel's termios interface, for the rotation stages (zaber_head.h,
// apt_head.h): raw 8N1 at a chosen baud rate, with or without RTS/CTS flow control. The port is
// opened non-blocking and every read waits with poll() against a deadline, so no call blocks past
// the time it was given: a device that says nothing gives [timeout], one that vanished (USB
// unplugged, pseudo-terminal master closed) gives [disconnected] (device.h). Errors name the port.
//
// Modem lines (RTS, DTR) are set through TIOCMBIS/TIOCMBIC. FTDI-based Thorlabs controllers want
// RTS raised; a pseudo-terminal has no modem lines and answers ENOTTY or EINVAL, which setRts
// reports as "not applied" instead of failing, so the drivers run unchanged against the
// simulators (stage_sim.h).
//
// listSerialPorts reads sysfs the way udev does: every tty with a real device behind it, and for
// USB adapters the vendor and product ids, strings and serial number of the USB device above it,
// so that a lab can tell its Zaber stage from its Thorlabs mount from its GPS receiver.
//
// A SerialPort is not thread-safe: the heads serialise their exchanges with a mutex.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.h"
#include "drivers/device.h"

namespace flarelab::drivers {

using SerialClock = std::chrono::steady_clock;

// The time point timeout_s (>= 0, finite; larger values are capped at a day) from now.
SerialClock::time_point deadlineAfter(double timeout_s);

enum class FlowControl {
    None,
    RtsCts,  // hardware handshake (CRTSCTS)
};

struct SerialOptions {
    // One of 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600.
    int baud = 115200;
    FlowControl flow = FlowControl::None;
    // Refuse a second opener while we hold the port (TIOCEXCL; ignored where unsupported).
    bool exclusive = true;
};

class SerialPort {
public:
    // Opens `path` (O_NOCTTY, non-blocking) as raw 8N1 with `options`, and discards whatever the
    // line held. Errors: [disconnected] when the path does not exist; [busy] when another program
    // holds it exclusively; IoError for permission denied (naming the dialout group) and other
    // refusals; InvalidArgument for an unsupported baud rate or a path that is not a terminal.
    static Result<std::unique_ptr<SerialPort>> open(const std::string& path,
                                                    const SerialOptions& options);
    ~SerialPort();
    SerialPort(const SerialPort&) = delete;
    SerialPort& operator=(const SerialPort&) = delete;

    const std::string& path() const { return path_; }
    // "serial port /dev/ttyUSB0", the prefix of this port's errors.
    std::string name() const { return "serial port " + path_; }

    // Writes every byte before the deadline: [timeout] when the line would not take them (flow
    // control held back), [disconnected] when the device is gone.
    Status writeAll(std::span<const uint8_t> bytes, SerialClock::time_point deadline);
    Status writeAll(std::string_view text, SerialClock::time_point deadline);
    // Waits until the kernel has sent everything written (tcdrain).
    Status drainOutput();

    // Reads at least one byte (at most buffer.size()), waiting until the deadline: the number
    // read, [timeout] when nothing came, [disconnected] on hang-up.
    Result<size_t> readSome(std::span<uint8_t> buffer, SerialClock::time_point deadline);
    // Exactly n bytes, or [timeout] saying how many came (those are then discarded).
    Result<std::vector<uint8_t>> readExact(size_t n, SerialClock::time_point deadline);
    // Bytes up to the next '\n', without it and without a '\r' before it. [timeout] quotes the
    // partial line; a line longer than max_bytes is an IoError (a device talking garbage or at
    // another baud rate), its bytes discarded.
    Result<std::string> readLine(SerialClock::time_point deadline, size_t max_bytes = 1024);

    // Discards unread input: the kernel's buffer (tcflush) and this port's own.
    Status flushInput();
    // Bytes already received and held by this port (read past the end of a line).
    size_t buffered() const { return pending_.size(); }

    // Raises or lowers a modem line. true when applied, false when the port has no modem lines
    // (ENOTTY, EINVAL: pseudo-terminals); [disconnected] or IoError otherwise.
    Result<bool> setRts(bool on);
    Result<bool> setDtr(bool on);

    // For open() only (a passkey keeps the constructor out of reach); takes ownership of fd.
    struct Key {
        explicit Key() = default;
    };
    SerialPort(Key, std::string path, int fd);

private:
    Result<bool> setModemLine(int line, bool on, const char* what);
    // Waits for input until the deadline and appends what came to pending_.
    Status fill(SerialClock::time_point deadline, const char* waiting_for);
    Error ioError(const char* what, int error_number) const;

    std::string path_;
    int fd_ = -1;
    std::vector<uint8_t> pending_;
};

// Device bytes as readable text for error messages: printable ASCII as is, the rest as \xNN (\r
// and \n as such), cut after max_chars with "...".
std::string quoteBytes(std::span<const uint8_t> bytes, size_t max_chars = 80);
std::string quoteBytes(std::string_view text, size_t max_chars = 80);

// The USB identity of a serial port's adapter, when it has one.
struct SerialUsbInfo {
    uint16_t vendor_id = 0;
    uint16_t product_id = 0;
    std::string manufacturer;
    std::string product;
    std::string serial;
    std::string bus_path;  // the USB device's sysfs name, e.g. "1-2" (bus 1, port 2)
    bool operator==(const SerialUsbInfo&) const = default;
};

// Which stage protocol a USB adapter suggests: "zaber" for Zaber's vendor id 0x2939 or a
// manufacturer string naming Zaber, "apt" for Thorlabs' FTDI product id 0403:faf0 or a
// manufacturer string naming Thorlabs, "" otherwise.
std::string suggestedStageScheme(const SerialUsbInfo& usb);

// Every serial port with a device behind it (sysfs_root/class/tty/*/device), skipping the
// placeholder ports of the legacy 8250 driver (their device is on the "platform" bus, directly or,
// since Linux 6.5, behind "serial-base" port and controller devices): kind
// "serial-port", uri "zaber:DEV" / "apt:DEV" when the USB identity suggests a stage (backend
// then that scheme), else the device path itself (backend ""). Details: "device: /dev/ttyUSB0",
// "driver: ftdi_sio", "usb: 0403:faf0 Thorlabs APT Stepper Motor Controller, serial 55000001",
// "usb bus: 1-2", "by-id: /dev/serial/by-id/..." where dev_root/serial/by-id has a link to it.
// Sorted by device path; an unreadable tree gives an empty list.
std::vector<DeviceListing> listSerialPorts(const std::string& sysfs_root = "/sys",
                                           const std::string& dev_root = "/dev");

}  // namespace flarelab::drivers
