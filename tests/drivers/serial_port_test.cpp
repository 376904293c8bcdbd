#include "drivers/serial_port.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <pty.h>
#include <sys/ioctl.h>
#include <termios.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>

#include "common/check.h"

namespace flarelab::drivers {
namespace {

namespace fs = std::filesystem;

// A pseudo-terminal pair: the test plays the device on the master.
struct Pty {
    int master = -1;
    int slave = -1;
    std::string path;
    Pty() {
        char name[256] = {};
        FLARELAB_CHECK(::openpty(&master, &slave, name, nullptr, nullptr) == 0);
        path = name;
    }
    ~Pty() {
        closeMaster();
        if (slave >= 0) ::close(slave);
    }
    void send(std::string_view bytes) const {
        FLARELAB_CHECK_EQ(::write(master, bytes.data(), bytes.size()),
                          static_cast<ssize_t>(bytes.size()));
    }
    // What the port sent, waiting up to a second for `n` bytes.
    std::string receive(size_t n) const {
        std::string out;
        const auto deadline = deadlineAfter(1.0);
        while (out.size() < n && SerialClock::now() < deadline) {
            char buffer[256];
            ::fcntl(master, F_SETFL, ::fcntl(master, F_GETFL) | O_NONBLOCK);
            const ssize_t got = ::read(master, buffer, sizeof(buffer));
            if (got > 0)
                out.append(buffer, static_cast<size_t>(got));
            else
                ::usleep(1000);
        }
        return out;
    }
    // Waits (up to a second) until the terminal holds n unread bytes: a pty moves bytes from
    // master to slave asynchronously.
    void awaitArrival(int n) const {
        const auto deadline = deadlineAfter(1.0);
        int queued = 0;
        while (SerialClock::now() < deadline && ::ioctl(slave, FIONREAD, &queued) == 0 &&
               queued < n)
            ::usleep(500);
    }
    void closeMaster() {
        if (master >= 0) ::close(master);
        master = -1;
    }
};

std::unique_ptr<SerialPort> openPort(const std::string& path, SerialOptions options = {}) {
    auto port = SerialPort::open(path, options);
    EXPECT_TRUE(port) << (port ? "" : port.error().message);
    return port ? std::move(*port) : nullptr;
}

TEST(SerialPort, ReadsLinesExactCountsAndWhatEverArrives) {
    Pty pty;
    auto port = openPort(pty.path);
    ASSERT_TRUE(port);
    pty.send("@01 1 OK IDLE -- 0\r\n@01 1 OK BUSY");
    auto line = port->readLine(deadlineAfter(1.0));
    ASSERT_TRUE(line) << line.error().message;
    EXPECT_EQ(*line, "@01 1 OK IDLE -- 0");
    pty.send(" -- 12\r\n");
    line = port->readLine(deadlineAfter(1.0));
    ASSERT_TRUE(line) << line.error().message;
    EXPECT_EQ(*line, "@01 1 OK BUSY -- 12");

    pty.send(std::string("\x64\x04\x0e\x00\x81\x50", 6));
    auto exact = port->readExact(4, deadlineAfter(1.0));
    ASSERT_TRUE(exact);
    EXPECT_EQ(*exact, (std::vector<uint8_t>{0x64, 0x04, 0x0e, 0x00}));
    std::array<uint8_t, 16> some{};
    auto n = port->readSome(some, deadlineAfter(1.0));
    ASSERT_TRUE(n);
    EXPECT_EQ(*n, 2u);
    EXPECT_EQ(some[0], 0x81);
    EXPECT_EQ(some[1], 0x50);
}

TEST(SerialPort, WritesEveryByte) {
    Pty pty;
    auto port = openPort(pty.path);
    ASSERT_TRUE(port);
    ASSERT_TRUE(port->writeAll(std::string_view("/1 1 get pos\n"), deadlineAfter(1.0)));
    EXPECT_EQ(pty.receive(13), "/1 1 get pos\n");
    EXPECT_TRUE(port->drainOutput());
}

TEST(SerialPort, TimesOutQuotingAPartialLine) {
    Pty pty;
    auto port = openPort(pty.path);
    ASSERT_TRUE(port);
    auto none = port->readLine(deadlineAfter(0.05));
    ASSERT_FALSE(none);
    EXPECT_EQ(deviceFaultOf(none.error()), DeviceFault::Timeout);
    EXPECT_NE(none.error().message.find(pty.path), std::string::npos);

    pty.send("@01 1 OK ID");
    auto cut = port->readLine(deadlineAfter(0.05));
    ASSERT_FALSE(cut);
    EXPECT_EQ(deviceFaultOf(cut.error()), DeviceFault::Timeout);
    EXPECT_NE(cut.error().message.find("'@01 1 OK ID'"), std::string::npos) << cut.error().message;

    auto short_read = port->readExact(6, deadlineAfter(0.05));
    ASSERT_FALSE(short_read);
    EXPECT_EQ(deviceFaultOf(short_read.error()), DeviceFault::Timeout);
    // A deadline already past still collects what has arrived, without waiting.
    pty.send("x\n");
    pty.awaitArrival(2);
    auto late = port->readLine(deadlineAfter(0.0));
    ASSERT_TRUE(late) << late.error().message;
    EXPECT_EQ(*late, "x");
}

TEST(SerialPort, RefusesALineWithoutEndAfterMaxBytes) {
    Pty pty;
    auto port = openPort(pty.path);
    ASSERT_TRUE(port);
    pty.send(std::string(300, 'A'));
    auto line = port->readLine(deadlineAfter(1.0), 100);
    ASSERT_FALSE(line);
    EXPECT_EQ(line.error().code, ErrorCode::IoError);
    EXPECT_NE(line.error().message.find("without a line end"), std::string::npos);
}

TEST(SerialPort, FlushDropsWhatWaited) {
    Pty pty;
    auto port = openPort(pty.path);
    ASSERT_TRUE(port);
    pty.send("stale reply\r\n");
    pty.awaitArrival(13);
    ASSERT_TRUE(port->flushInput());
    pty.send("fresh\r\n");
    auto line = port->readLine(deadlineAfter(1.0));
    ASSERT_TRUE(line);
    EXPECT_EQ(*line, "fresh");
}

TEST(SerialPort, HangUpIsDisconnected) {
    Pty pty;
    auto port = openPort(pty.path);
    ASSERT_TRUE(port);
    pty.closeMaster();
    auto line = port->readLine(deadlineAfter(1.0));
    ASSERT_FALSE(line);
    EXPECT_EQ(deviceFaultOf(line.error()), DeviceFault::Disconnected) << line.error().message;
    const Status wrote = port->writeAll(std::string_view("/\n"), deadlineAfter(1.0));
    ASSERT_FALSE(wrote);
    EXPECT_EQ(deviceFaultOf(wrote.error()), DeviceFault::Disconnected) << wrote.error().message;
}

TEST(SerialPort, ModemLinesOnAPtyAreNotAppliedButNoError) {
    Pty pty;
    SerialOptions options;
    options.flow = FlowControl::RtsCts;
    auto port = openPort(pty.path, options);
    ASSERT_TRUE(port);
    auto rts = port->setRts(true);
    ASSERT_TRUE(rts) << rts.error().message;
    EXPECT_FALSE(*rts);
    auto dtr = port->setDtr(false);
    ASSERT_TRUE(dtr);
    EXPECT_FALSE(*dtr);
}

TEST(SerialPort, OpenErrorsNameThePortAndTheCause) {
    auto missing = SerialPort::open("/dev/flarelab-no-such-port", {});
    ASSERT_FALSE(missing);
    EXPECT_EQ(deviceFaultOf(missing.error()), DeviceFault::Disconnected);
    EXPECT_NE(missing.error().message.find("/dev/flarelab-no-such-port"), std::string::npos);

    const fs::path file =
        fs::temp_directory_path() / ("flarelab_not_a_tty_" + std::to_string(::getpid()));
    std::ofstream(file) << "x";
    auto not_tty = SerialPort::open(file.string(), {});
    fs::remove(file);
    ASSERT_FALSE(not_tty);
    EXPECT_EQ(not_tty.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(not_tty.error().message.find("not a terminal"), std::string::npos);

    Pty pty;
    SerialOptions odd;
    odd.baud = 12345;
    auto baud = SerialPort::open(pty.path, odd);
    ASSERT_FALSE(baud);
    EXPECT_EQ(baud.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(baud.error().message.find("12345"), std::string::npos);
}

TEST(SerialPort, ExclusivityEndsWithThePort) {
    Pty pty;
    {
        auto first = openPort(pty.path);
        ASSERT_TRUE(first);
        if (::geteuid() != 0) {  // root may open an exclusive terminal anyway
            auto second = SerialPort::open(pty.path, {});
            ASSERT_FALSE(second);
            EXPECT_EQ(deviceFaultOf(second.error()), DeviceFault::Busy);
        }
    }
    auto again = SerialPort::open(pty.path, {});
    EXPECT_TRUE(again) << (again ? "" : again.error().message);
}

TEST(QuoteBytes, ShowsControlBytesAndCuts) {
    const std::vector<uint8_t> bytes{'@', '0', 0x01, '\r', '\n', 0xff};
    EXPECT_EQ(quoteBytes(bytes), "@0\\x01\\r\\n\\xff");
    EXPECT_EQ(quoteBytes(std::string_view("abcdef"), 3), "abc...");
}

// A fake sysfs laid out as the kernel does: class/tty entries are links into the device tree,
// each real port's "device" link points at its port or interface, the USB device sits above.
class FakeSysfs : public ::testing::Test {
protected:
    void SetUp() override {
        root_ = fs::temp_directory_path() /
                ("flarelab_sysfs_" + std::to_string(::getpid()) + "_" +
                 ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::remove_all(root_);
        sys_ = root_ / "sys";
        dev_ = root_ / "dev";
        fs::create_directories(sys_ / "class" / "tty");
        fs::create_directories(sys_ / "bus" / "usb-serial" / "drivers" / "ftdi_sio");
        fs::create_directories(sys_ / "bus" / "usb" / "drivers" / "cdc_acm");
        fs::create_directories(sys_ / "bus" / "platform");
        fs::create_directories(sys_ / "bus" / "pnp");
        fs::create_directories(dev_ / "serial" / "by-id");
    }
    void TearDown() override { fs::remove_all(root_); }

    static void write(const fs::path& file, const std::string& text) {
        fs::create_directories(file.parent_path());
        std::ofstream(file) << text << "\n";
    }
    // A link at `at` to `target`, given relative to sys_.
    void link(const fs::path& at, const fs::path& target) {
        fs::create_directories(at.parent_path());
        fs::create_symlink(fs::relative(sys_ / target, at.parent_path()), at);
    }
    void usbDevice(const std::string& dir,
                   const std::string& vendor,
                   const std::string& product,
                   const std::string& manufacturer,
                   const std::string& name,
                   const std::string& serial) {
        const fs::path d = sys_ / dir;
        write(d / "idVendor", vendor);
        write(d / "idProduct", product);
        if (!manufacturer.empty()) write(d / "manufacturer", manufacturer);
        if (!name.empty()) write(d / "product", name);
        if (!serial.empty()) write(d / "serial", serial);
    }
    // class/tty/NAME -> DEVICE_DIR/tty/NAME, whose "device" link points at DEVICE_DIR.
    void tty(const std::string& name,
             const std::string& device_dir,
             const std::string& subsystem,
             const std::string& driver) {
        const fs::path class_dev = fs::path(device_dir) / "tty" / name;
        fs::create_directories(sys_ / class_dev);
        link(sys_ / "class" / "tty" / name, class_dev);
        link(sys_ / class_dev / "device", device_dir);
        if (!subsystem.empty()) link(sys_ / device_dir / "subsystem", "bus/" + subsystem);
        if (!driver.empty()) link(sys_ / device_dir / "driver", driver);
    }

    fs::path root_, sys_, dev_;
};

TEST_F(FakeSysfs, ListsRealPortsWithTheirUsbIdentityAndSuggestsStageUris) {
    const std::string hub = "devices/pci0000:00/0000:00:14.0/usb1";
    usbDevice(hub + "/1-2", "0403", "faf0", "Thorlabs", "APT Stepper Motor Controller", "55000001");
    tty("ttyUSB0", hub + "/1-2/1-2:1.0/ttyUSB0", "usb-serial", "bus/usb-serial/drivers/ftdi_sio");
    usbDevice(hub + "/1-3", "2939", "495b", "Zaber Technologies Inc.", "X-MCC", "12345");
    tty("ttyACM0", hub + "/1-3/1-3:1.0", "usb", "bus/usb/drivers/cdc_acm");
    usbDevice(hub + "/1-4", "0403", "6001", "FTDI", "FT232R USB UART", "A10KZ");
    tty("ttyUSB1", hub + "/1-4/1-4:1.0/ttyUSB1", "usb-serial", "bus/usb-serial/drivers/ftdi_sio");
    // A motherboard COM port (pnp), the 8250 driver's placeholders (platform), a console.
    tty("ttyS4", "devices/pnp0/00:05", "pnp", "");
    tty("ttyS0", "devices/platform/serial8250", "platform", "");
    fs::create_directories(sys_ / "devices/virtual/tty/tty0");
    link(sys_ / "class/tty/tty0", "devices/virtual/tty/tty0");
    fs::create_symlink("../../ttyUSB0", dev_ / "serial/by-id/usb-Thorlabs_APT_55000001-if00");

    const auto ports = listSerialPorts(sys_.string(), dev_.string());
    ASSERT_EQ(ports.size(), 4u);
    const std::string d = dev_.string();

    EXPECT_EQ(ports[0].uri, "zaber:" + d + "/ttyACM0");
    EXPECT_EQ(ports[0].backend, "zaber");
    EXPECT_EQ(ports[0].kind, "serial-port");
    EXPECT_EQ(ports[0].model, "X-MCC");
    EXPECT_EQ(ports[0].serial, "12345");
    EXPECT_EQ(ports[0].details,
              (std::vector<std::string>{
                  "device: " + d + "/ttyACM0", "driver: cdc_acm",
                  "usb: 2939:495b Zaber Technologies Inc. X-MCC, serial 12345", "usb bus: 1-3"}));

    EXPECT_EQ(ports[1].uri, d + "/ttyS4");
    EXPECT_EQ(ports[1].backend, "");
    EXPECT_EQ(ports[1].model, "serial port");
    EXPECT_EQ(ports[1].details, (std::vector<std::string>{"device: " + d + "/ttyS4", "bus: pnp"}));

    EXPECT_EQ(ports[2].uri, "apt:" + d + "/ttyUSB0");
    EXPECT_EQ(ports[2].backend, "apt");
    EXPECT_EQ(ports[2].serial, "55000001");
    EXPECT_EQ(
        ports[2].details,
        (std::vector<std::string>{
            "device: " + d + "/ttyUSB0", "driver: ftdi_sio",
            "usb: 0403:faf0 Thorlabs APT Stepper Motor Controller, serial 55000001", "usb bus: 1-2",
            "by-id: " + (dev_ / "serial/by-id/usb-Thorlabs_APT_55000001-if00").string()}));

    EXPECT_EQ(ports[3].uri, d + "/ttyUSB1");
    EXPECT_EQ(ports[3].backend, "");
    EXPECT_EQ(ports[3].model, "FT232R USB UART");
}

TEST_F(FakeSysfs, LooksPastTheSerialBaseDevicesOfNewerKernels) {
    // Linux 6.5 and later: tty -> serial-base port -> serial-base controller -> the UART's holder.
    fs::create_directories(sys_ / "bus" / "serial-base");
    fs::create_directories(sys_ / "bus" / "pnp" / "drivers" / "serial");
    const std::string pnp = "devices/pnp0/00:00";
    link(sys_ / pnp / "subsystem", "bus/pnp");
    link(sys_ / pnp / "driver", "bus/pnp/drivers/serial");
    link(sys_ / pnp / "00:00:0" / "subsystem", "bus/serial-base");
    tty("ttyS0", pnp + "/00:00:0/00:00:0.0", "serial-base", "");
    const std::string legacy = "devices/platform/serial8250";
    link(sys_ / legacy / "subsystem", "bus/platform");
    link(sys_ / legacy / "serial8250:0" / "subsystem", "bus/serial-base");
    tty("ttyS1", legacy + "/serial8250:0/serial8250:0.1", "serial-base", "");

    const auto ports = listSerialPorts(sys_.string(), dev_.string());
    ASSERT_EQ(ports.size(), 1u);
    EXPECT_EQ(ports[0].uri, dev_.string() + "/ttyS0");
    EXPECT_EQ(ports[0].details, (std::vector<std::string>{"device: " + dev_.string() + "/ttyS0",
                                                          "driver: serial", "bus: pnp"}));
}

TEST_F(FakeSysfs, AMissingTreeListsNothing) {
    EXPECT_TRUE(listSerialPorts((root_ / "nowhere").string(), dev_.string()).empty());
    EXPECT_TRUE(listSerialPorts(sys_.string(), dev_.string()).empty());
}

TEST(SuggestedStageScheme, ByVendorProductOrManufacturer) {
    SerialUsbInfo usb;
    usb.vendor_id = 0x0403;
    usb.product_id = 0xfaf0;
    EXPECT_EQ(suggestedStageScheme(usb), "apt");
    usb.product_id = 0x6001;
    EXPECT_EQ(suggestedStageScheme(usb), "");
    usb.manufacturer = "Zaber Technologies Inc.";
    EXPECT_EQ(suggestedStageScheme(usb), "zaber");
    usb = SerialUsbInfo{};
    usb.vendor_id = 0x2939;
    EXPECT_EQ(suggestedStageScheme(usb), "zaber");
    usb = SerialUsbInfo{};
    usb.manufacturer = "THORLABS";
    EXPECT_EQ(suggestedStageScheme(usb), "apt");
}

}  // namespace
}  // namespace flarelab::drivers
