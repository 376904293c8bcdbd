#include "drivers/serial_port.h"

#include <fcntl.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <optional>
#include <system_error>

namespace flarelab::drivers {
namespace {

namespace fs = std::filesystem;

// Caps a timeout so that the time point stays representable.
constexpr double kMaxTimeout_s = 86400.0;

Result<speed_t> baudConstant(int baud) {
    switch (baud) {
        case 1200:
            return speed_t{B1200};
        case 2400:
            return speed_t{B2400};
        case 4800:
            return speed_t{B4800};
        case 9600:
            return speed_t{B9600};
        case 19200:
            return speed_t{B19200};
        case 38400:
            return speed_t{B38400};
        case 57600:
            return speed_t{B57600};
        case 115200:
            return speed_t{B115200};
        case 230400:
            return speed_t{B230400};
        case 460800:
            return speed_t{B460800};
        case 921600:
            return speed_t{B921600};
        default:
            return makeError(ErrorCode::InvalidArgument,
                             "serial port: baud rate " + std::to_string(baud) +
                                 " is not one of 1200 ... 921600 (the standard rates)");
    }
}

// Errors of a device that went away: the USB adapter unplugged, the pty master closed.
bool isHangup(int error_number) {
    return error_number == EIO || error_number == ENXIO || error_number == ENODEV ||
           error_number == EPIPE;
}

// Milliseconds to wait in poll() for a deadline, rounded up so we never wake early and spin.
int pollMilliseconds(SerialClock::time_point deadline) {
    const auto left = deadline - SerialClock::now();
    if (left <= SerialClock::duration::zero()) return 0;
    const auto ms = std::chrono::ceil<std::chrono::milliseconds>(left).count();
    return static_cast<int>(std::min<int64_t>(ms, 1000 * 60));
}

std::string trimmed(std::string s) {
    while (!s.empty() && (s.back() == '\n' || s.back() == '\r' || s.back() == ' ')) s.pop_back();
    size_t start = 0;
    while (start < s.size() && s[start] == ' ') ++start;
    return s.substr(start);
}

// The first line of a small sysfs attribute file, "" when absent.
std::string readAttribute(const fs::path& file) {
    std::ifstream in(file);
    if (!in) return "";
    std::string line;
    std::getline(in, line);
    return trimmed(line);
}

std::optional<uint16_t> parseHex16(const std::string& text) {
    if (text.empty() || text.size() > 4) return std::nullopt;
    unsigned value = 0;
    for (char c : text) {
        value <<= 4;
        if (c >= '0' && c <= '9')
            value |= static_cast<unsigned>(c - '0');
        else if (c >= 'a' && c <= 'f')
            value |= static_cast<unsigned>(c - 'a' + 10);
        else if (c >= 'A' && c <= 'F')
            value |= static_cast<unsigned>(c - 'A' + 10);
        else
            return std::nullopt;
    }
    return static_cast<uint16_t>(value);
}

std::string hex4(uint16_t value) {
    char text[8];
    std::snprintf(text, sizeof(text), "%04x", static_cast<unsigned>(value));
    return text;
}

bool containsNoCase(std::string_view haystack, std::string_view needle) {
    if (needle.empty() || haystack.size() < needle.size()) return false;
    for (size_t i = 0; i + needle.size() <= haystack.size(); ++i) {
        bool match = true;
        for (size_t j = 0; j < needle.size() && match; ++j)
            match = std::tolower(static_cast<unsigned char>(haystack[i + j])) ==
                    std::tolower(static_cast<unsigned char>(needle[j]));
        if (match) return true;
    }
    return false;
}

// The USB device above a tty's device directory: the nearest ancestor with an idVendor file,
// searched no higher than sysfs_root/devices.
std::optional<fs::path> usbDeviceAbove(const fs::path& device_dir, const fs::path& devices_root) {
    std::error_code ec;
    for (fs::path dir = device_dir; !dir.empty(); dir = dir.parent_path()) {
        if (fs::exists(dir / "idVendor", ec)) return dir;
        if (dir == devices_root || dir == dir.parent_path()) break;
    }
    return std::nullopt;
}

}  // namespace

SerialClock::time_point deadlineAfter(double timeout_s) {
    const double s = std::isfinite(timeout_s) ? std::clamp(timeout_s, 0.0, kMaxTimeout_s) : 0.0;
    return SerialClock::now() +
           std::chrono::duration_cast<SerialClock::duration>(std::chrono::duration<double>(s));
}

std::string quoteBytes(std::span<const uint8_t> bytes, size_t max_chars) {
    std::string out;
    for (const uint8_t b : bytes) {
        if (out.size() >= max_chars) {
            out += "...";
            break;
        }
        if (b == '\r') {
            out += "\\r";
        } else if (b == '\n') {
            out += "\\n";
        } else if (b == '\\') {
            out += "\\\\";
        } else if (b >= 32 && b < 127) {
            out += static_cast<char>(b);
        } else {
            char hex[8];
            std::snprintf(hex, sizeof(hex), "\\x%02x", static_cast<unsigned>(b));
            out += hex;
        }
    }
    return out;
}

std::string quoteBytes(std::string_view text, size_t max_chars) {
    return quoteBytes(
        std::span<const uint8_t>(reinterpret_cast<const uint8_t*>(text.data()), text.size()),
        max_chars);
}

SerialPort::SerialPort(Key, std::string path, int fd) : path_(std::move(path)), fd_(fd) {}

SerialPort::~SerialPort() {
    if (fd_ >= 0) {
        // Exclusivity belongs to the terminal, not to our descriptor: release it, or the next
        // program (another head, a pty simulator's next client) could not open the port.
        ::ioctl(fd_, TIOCNXCL);
        ::close(fd_);
    }
}

Error SerialPort::ioError(const char* what, int error_number) const {
    if (isHangup(error_number))
        return deviceError(DeviceFault::Disconnected, name(),
                           std::string(what) + ": " + std::strerror(error_number) +
                               " (device unplugged or powered off?)");
    return makeError(ErrorCode::IoError, name() + ": " + what + ": " + std::strerror(error_number));
}

Result<std::unique_ptr<SerialPort>> SerialPort::open(const std::string& path,
                                                     const SerialOptions& options) {
    const std::string name = "serial port " + path;
    auto speed = baudConstant(options.baud);
    if (!speed) return speed.error().withContext(name);
    const int fd = ::open(path.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
    if (fd < 0) {
        const int e = errno;
        if (e == ENOENT || e == ENODEV || e == ENXIO)
            return deviceError(DeviceFault::Disconnected, name,
                               std::string("cannot open: ") + std::strerror(e) +
                                   " (is the device plugged in and powered? `flarelab rig "
                                   "devices` lists the serial ports)");
        if (e == EACCES || e == EPERM)
            return makeError(ErrorCode::IoError,
                             name + ": permission denied: add your user to the group owning " +
                                 "the port (Debian: dialout; `sudo usermod -aG dialout $USER`, "
                                 "then log in again) or install the udev rule of docs/lab.md");
        if (e == EBUSY)
            return deviceError(DeviceFault::Busy, name,
                               "another program holds the port open exclusively");
        return makeError(ErrorCode::IoError, name + ": cannot open: " + std::strerror(e));
    }
    auto port = std::make_unique<SerialPort>(Key{}, path, fd);
    if (!::isatty(fd))
        return makeError(ErrorCode::InvalidArgument, name + ": not a terminal device");
    if (options.exclusive && ::ioctl(fd, TIOCEXCL) != 0 && errno != ENOTTY && errno != EINVAL)
        return port->ioError("TIOCEXCL", errno);

    termios tio{};
    if (::tcgetattr(fd, &tio) != 0) return port->ioError("tcgetattr", errno);
    ::cfmakeraw(&tio);
    tio.c_cflag &= ~static_cast<tcflag_t>(CSIZE | PARENB | CSTOPB | CRTSCTS);
    tio.c_cflag |= CS8 | CLOCAL | CREAD;
    if (options.flow == FlowControl::RtsCts) tio.c_cflag |= CRTSCTS;
    tio.c_iflag &= ~static_cast<tcflag_t>(IXON | IXOFF | IXANY);
    // Reads never block in the kernel: poll() does the waiting, against our deadlines.
    tio.c_cc[VMIN] = 0;
    tio.c_cc[VTIME] = 0;
    if (::cfsetispeed(&tio, *speed) != 0 || ::cfsetospeed(&tio, *speed) != 0)
        return port->ioError("cfsetspeed", errno);
    if (::tcsetattr(fd, TCSANOW, &tio) != 0) return port->ioError("tcsetattr", errno);
    if (Status ok = port->flushInput(); !ok) return ok.error();
    return port;
}

Status SerialPort::writeAll(std::span<const uint8_t> bytes, SerialClock::time_point deadline) {
    size_t done = 0;
    while (done < bytes.size()) {
        const ssize_t n = ::write(fd_, bytes.data() + done, bytes.size() - done);
        if (n > 0) {
            done += static_cast<size_t>(n);
            continue;
        }
        if (n < 0 && errno == EINTR) continue;
        if (n < 0 && errno != EAGAIN && errno != EWOULDBLOCK) return ioError("write", errno);
        // The kernel buffer is full (flow control holds us back): wait for room.
        pollfd p{fd_, POLLOUT, 0};
        const int ms = pollMilliseconds(deadline);
        if (ms <= 0)
            return deviceError(DeviceFault::Timeout, name(),
                               "could not send " + std::to_string(bytes.size() - done) + " of " +
                                   std::to_string(bytes.size()) +
                                   " bytes in time (flow control held back? is CTS wired?)");
        const int r = ::poll(&p, 1, ms);
        if (r < 0 && errno != EINTR) return ioError("poll", errno);
        if (r > 0 && (p.revents & (POLLHUP | POLLERR | POLLNVAL)))
            return deviceError(DeviceFault::Disconnected, name(),
                               "hung up while sending (device unplugged or powered off?)");
    }
    return Ok{};
}

Status SerialPort::writeAll(std::string_view text, SerialClock::time_point deadline) {
    return writeAll(
        std::span<const uint8_t>(reinterpret_cast<const uint8_t*>(text.data()), text.size()),
        deadline);
}

Status SerialPort::drainOutput() {
    while (::tcdrain(fd_) != 0) {
        if (errno == EINTR) continue;
        if (errno == ENOTTY || errno == EINVAL) return Ok{};
        return ioError("tcdrain", errno);
    }
    return Ok{};
}

Status SerialPort::fill(SerialClock::time_point deadline, const char* waiting_for) {
    uint8_t chunk[512];
    bool poll_said_readable = false;
    for (;;) {
        const ssize_t n = ::read(fd_, chunk, sizeof(chunk));
        if (n > 0) {
            pending_.insert(pending_.end(), chunk, chunk + n);
            return Ok{};
        }
        if (n == 0) {
            // A terminal in non-canonical mode with VMIN = 0 reads 0 both when nothing is there
            // and at end of file; after poll() called it readable, it is the end: hang-up.
            if (poll_said_readable)
                return deviceError(DeviceFault::Disconnected, name(),
                                   "the line hung up (device unplugged or powered off?)");
        } else if (errno == EINTR) {
            continue;
        } else if (errno != EAGAIN && errno != EWOULDBLOCK) {
            return ioError("read", errno);
        }
        const int ms = pollMilliseconds(deadline);
        if (ms <= 0)
            return deviceError(DeviceFault::Timeout, name(),
                               std::string("no ") + waiting_for + " in time");
        pollfd p{fd_, POLLIN, 0};
        const int r = ::poll(&p, 1, ms);
        if (r < 0) {
            if (errno == EINTR) continue;
            return ioError("poll", errno);
        }
        if (r == 0) continue;  // the loop re-checks the deadline
        if ((p.revents & (POLLHUP | POLLERR | POLLNVAL)) && !(p.revents & POLLIN))
            return deviceError(DeviceFault::Disconnected, name(),
                               "the line hung up (device unplugged or powered off?)");
        // Readable, or hung up with bytes still to read: the next read() tells.
        poll_said_readable = true;
    }
}

Result<size_t> SerialPort::readSome(std::span<uint8_t> buffer, SerialClock::time_point deadline) {
    if (buffer.empty()) return size_t{0};
    if (pending_.empty())
        if (Status ok = fill(deadline, "bytes"); !ok) return ok.error();
    const size_t n = std::min(buffer.size(), pending_.size());
    std::copy_n(pending_.begin(), n, buffer.begin());
    pending_.erase(pending_.begin(), pending_.begin() + static_cast<std::ptrdiff_t>(n));
    return n;
}

Result<std::vector<uint8_t>> SerialPort::readExact(size_t n, SerialClock::time_point deadline) {
    while (pending_.size() < n) {
        if (Status ok = fill(deadline, "bytes"); !ok) {
            const Error e = ok.error();
            const size_t got = pending_.size();
            pending_.clear();
            if (deviceFaultOf(e) == DeviceFault::Timeout)
                return deviceError(
                    DeviceFault::Timeout, name(),
                    "got " + std::to_string(got) + " of " + std::to_string(n) + " bytes in time");
            return e;
        }
    }
    std::vector<uint8_t> out(pending_.begin(), pending_.begin() + static_cast<std::ptrdiff_t>(n));
    pending_.erase(pending_.begin(), pending_.begin() + static_cast<std::ptrdiff_t>(n));
    return out;
}

Result<std::string> SerialPort::readLine(SerialClock::time_point deadline, size_t max_bytes) {
    size_t searched = 0;
    for (;;) {
        const auto newline = std::find(pending_.begin() + static_cast<std::ptrdiff_t>(searched),
                                       pending_.end(), uint8_t{'\n'});
        if (newline != pending_.end()) {
            std::string line(pending_.begin(), newline);
            pending_.erase(pending_.begin(), newline + 1);
            if (!line.empty() && line.back() == '\r') line.pop_back();
            return line;
        }
        searched = pending_.size();
        if (pending_.size() > max_bytes) {
            const std::string head = quoteBytes(std::span<const uint8_t>(pending_), 40);
            pending_.clear();
            return makeError(ErrorCode::IoError, name() + ": more than " +
                                                     std::to_string(max_bytes) +
                                                     " bytes without a line end ('" + head +
                                                     "'): wrong baud rate or protocol?");
        }
        if (Status ok = fill(deadline, "reply line"); !ok) {
            if (deviceFaultOf(ok.error()) == DeviceFault::Timeout && !pending_.empty()) {
                const std::string partial = quoteBytes(std::span<const uint8_t>(pending_));
                pending_.clear();
                return deviceError(DeviceFault::Timeout, name(),
                                   "reply line cut short: '" + partial + "' and no line end");
            }
            return ok.error();
        }
    }
}

Status SerialPort::flushInput() {
    pending_.clear();
    if (::tcflush(fd_, TCIFLUSH) != 0 && errno != ENOTTY && errno != EINVAL)
        return ioError("tcflush", errno);
    // Bytes may sit between the pty master's write and our tcflush; read them out as well.
    uint8_t chunk[256];
    for (;;) {
        const ssize_t n = ::read(fd_, chunk, sizeof(chunk));
        if (n > 0) continue;
        if (n < 0 && errno == EINTR) continue;
        if (n < 0 && errno != EAGAIN && errno != EWOULDBLOCK) return ioError("read", errno);
        return Ok{};
    }
}

Result<bool> SerialPort::setModemLine(int line, bool on, const char* what) {
    int bits = line;
    if (::ioctl(fd_, on ? TIOCMBIS : TIOCMBIC, &bits) == 0) return true;
    if (errno == ENOTTY || errno == EINVAL) return false;
    return ioError(what, errno);
}

Result<bool> SerialPort::setRts(bool on) {
    return setModemLine(TIOCM_RTS, on, on ? "raise RTS" : "lower RTS");
}

Result<bool> SerialPort::setDtr(bool on) {
    return setModemLine(TIOCM_DTR, on, on ? "raise DTR" : "lower DTR");
}

std::string suggestedStageScheme(const SerialUsbInfo& usb) {
    // Zaber Technologies' USB vendor id; older X-series carry an FTDI chip with Zaber's strings.
    constexpr uint16_t kZaberVendor = 0x2939;
    // FTDI's vendor id with the product id FTDI assigned to Thorlabs' APT/Kinesis controllers
    // (Linux ftdi_sio: FTDI_THORLABS_PID).
    constexpr uint16_t kFtdiVendor = 0x0403, kThorlabsProduct = 0xfaf0;
    if (usb.vendor_id == kZaberVendor || containsNoCase(usb.manufacturer, "zaber") ||
        containsNoCase(usb.product, "zaber"))
        return "zaber";
    if ((usb.vendor_id == kFtdiVendor && usb.product_id == kThorlabsProduct) ||
        containsNoCase(usb.manufacturer, "thorlabs"))
        return "apt";
    return "";
}

std::vector<DeviceListing> listSerialPorts(const std::string& sysfs_root,
                                           const std::string& dev_root) {
    std::vector<DeviceListing> found;
    std::error_code ec;
    const fs::path class_dir = fs::path(sysfs_root) / "class" / "tty";
    const fs::path devices_root = fs::weakly_canonical(fs::path(sysfs_root) / "devices", ec);
    fs::directory_iterator it(class_dir, ec);
    if (ec) return found;

    // /dev/serial/by-id links, resolved: the stable names udev gives USB serial ports.
    std::vector<std::pair<fs::path, fs::path>> by_id;
    const fs::path by_id_dir = fs::path(dev_root) / "serial" / "by-id";
    for (fs::directory_iterator link(by_id_dir, ec); !ec && link != fs::directory_iterator();
         link.increment(ec)) {
        std::error_code link_ec;
        const fs::path target = fs::read_symlink(link->path(), link_ec);
        if (link_ec) continue;
        const fs::path resolved =
            target.is_absolute() ? target : (by_id_dir / target).lexically_normal();
        by_id.emplace_back(resolved, link->path());
    }
    ec.clear();

    for (; it != fs::directory_iterator(); it.increment(ec)) {
        if (ec) break;
        const std::string tty = it->path().filename().string();
        const fs::path device_link = it->path() / "device";
        std::error_code dev_ec;
        if (!fs::exists(device_link, dev_ec)) continue;  // virtual consoles, ptys, console
        const fs::path device_dir = fs::canonical(device_link, dev_ec);
        if (dev_ec) continue;
        // Kernels since 6.5 put "serial-base" port and controller devices between a UART's tty
        // and the device that holds it: look past them.
        fs::path holder = device_dir;
        fs::path subsystem = fs::read_symlink(holder / "subsystem", dev_ec);
        while (!dev_ec && subsystem.filename() == "serial-base" && holder.has_parent_path() &&
               holder != devices_root) {
            holder = holder.parent_path();
            subsystem = fs::read_symlink(holder / "subsystem", dev_ec);
        }
        // The 8250 driver registers ttyS0..ttyS31 whether or not a UART exists; those hang off
        // the platform bus, while real ports sit on pnp, pci or usb.
        if (!dev_ec && subsystem.filename() == "platform") continue;

        DeviceListing listing;
        listing.kind = "serial-port";
        const std::string dev_path = (fs::path(dev_root) / tty).string();
        listing.details.push_back("device: " + dev_path);
        std::error_code driver_ec;
        const fs::path driver = fs::read_symlink(holder / "driver", driver_ec);
        if (!driver_ec) listing.details.push_back("driver: " + driver.filename().string());

        SerialUsbInfo usb;
        bool has_usb = false;
        if (auto usb_dir = usbDeviceAbove(device_dir, devices_root)) {
            const auto vendor = parseHex16(readAttribute(*usb_dir / "idVendor"));
            const auto product = parseHex16(readAttribute(*usb_dir / "idProduct"));
            if (vendor && product) {
                has_usb = true;
                usb.vendor_id = *vendor;
                usb.product_id = *product;
                usb.manufacturer = readAttribute(*usb_dir / "manufacturer");
                usb.product = readAttribute(*usb_dir / "product");
                usb.serial = readAttribute(*usb_dir / "serial");
                usb.bus_path = usb_dir->filename().string();
            }
        }
        std::string scheme;
        if (has_usb) {
            std::string line = "usb: " + hex4(usb.vendor_id) + ":" + hex4(usb.product_id);
            if (!usb.manufacturer.empty()) line += " " + usb.manufacturer;
            if (!usb.product.empty()) line += " " + usb.product;
            if (!usb.serial.empty()) line += ", serial " + usb.serial;
            listing.details.push_back(line);
            listing.details.push_back("usb bus: " + usb.bus_path);
            listing.model = usb.product.empty() ? "USB serial adapter" : usb.product;
            listing.serial = usb.serial;
            scheme = suggestedStageScheme(usb);
        } else {
            listing.model = "serial port";
            listing.details.push_back("bus: " + subsystem.filename().string());
        }
        for (const auto& [target, link] : by_id)
            if (target == fs::path(dev_path)) listing.details.push_back("by-id: " + link.string());
        listing.backend = scheme;
        listing.uri = scheme.empty() ? dev_path : scheme + ":" + dev_path;
        found.push_back(std::move(listing));
    }
    std::sort(found.begin(), found.end(), [](const DeviceListing& a, const DeviceListing& b) {
        return a.details.front() < b.details.front();
    });
    return found;
}

}  // namespace flarelab::drivers
