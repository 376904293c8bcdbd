// flarelabd as a systemd service: the unit passes `systemd-analyze verify`, the sysusers.d and
// tmpfiles.d files make the user and the state directory flarelabd accepts (in a scratch root),
// and the notification protocol runs against a datagram socket standing in for systemd: READY=1
// once the daemon answers, WATCHDOG=1 at the interval WATCHDOG_USEC asks, STOPPING=1 at the end.
#include <gtest/gtest.h>
#include <sys/socket.h>
#include <sys/un.h>

#include <condition_variable>
#include <cstdio>
#include <mutex>

#include "daemon/notify.h"
#include "tests/daemon/daemon_process.h"

namespace flarelab::daemon {
namespace {

using namespace testing;
using Clock = std::chrono::steady_clock;

// The exit status and output (stdout and stderr) of a shell command.
std::pair<int, std::string> shell(const std::string& command) {
    std::string output;
    FILE* pipe = ::popen((command + " 2>&1").c_str(), "r");
    if (!pipe) return {-1, ""};
    char buffer[4096];
    while (size_t n = std::fread(buffer, 1, sizeof buffer, pipe)) output.append(buffer, n);
    const int status = ::pclose(pipe);
    return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, output};
}

bool have(const std::string& tool) { return shell("command -v " + tool).first == 0; }

std::string dist(const std::string& name) {
    return std::string(FLARELAB_SOURCE_DIR) + "/dist/" + name;
}

TEST(Systemd, TheUnitPassesSystemdAnalyzeVerify) {
    if (!have("systemd-analyze")) GTEST_SKIP() << "systemd-analyze is not installed (systemd)";
    const std::string unit = std::string(FLARELAB_BINARY_DIR) + "/dist/flarelabd-test.service";
    ASSERT_TRUE(fs::exists(unit)) << unit;
    const auto [code, output] = shell("systemd-analyze verify " + unit);
    if (output.find("System has not been booted with systemd") != std::string::npos ||
        output.find("Failed to initialize manager") != std::string::npos)
        GTEST_SKIP() << "systemd-analyze cannot run in this container: " << output;
    EXPECT_EQ(code, 0) << output;
    // Warnings (an unknown key, a bad value) leave the status 0: none is allowed either.
    EXPECT_EQ(output, "");
    const std::string text = readText(unit);
    EXPECT_NE(text.find("Type=notify"), std::string::npos);
    EXPECT_NE(text.find("ExecStart=" + std::string(FLARELAB_BINARY_DIR) +
                        "/apps/flarelabd --state-dir /var/lib/flarelab"),
              std::string::npos);
}

TEST(Systemd, SysusersAndTmpfilesMakeTheUserAndAStateDirectoryFlarelabdAccepts) {
    if (!have("systemd-sysusers") || !have("systemd-tmpfiles"))
        GTEST_SKIP() << "systemd-sysusers or systemd-tmpfiles is not installed (systemd)";
    TempDir root;
    fs::create_directories(root.path + "/etc");
    // The groups Debian has, so that the memberships have somewhere to go.
    std::ofstream(root.path + "/etc/group") << "video:x:44:\ndialout:x:20:\n";
    const auto users =
        shell("systemd-sysusers --root=" + root.path + " " + dist("flarelab.sysusers"));
    ASSERT_EQ(users.first, 0) << users.second;
    const std::string passwd = readText(root.path + "/etc/passwd");
    EXPECT_NE(passwd.find("flarelab:x:"), std::string::npos) << passwd;
    EXPECT_NE(passwd.find(":/var/lib/flarelab:/usr/sbin/nologin"), std::string::npos) << passwd;
    const std::string group = readText(root.path + "/etc/group");
    EXPECT_NE(group.find("video:x:44:flarelab"), std::string::npos) << group;
    EXPECT_NE(group.find("dialout:x:20:flarelab"), std::string::npos) << group;
    const auto dirs =
        shell("systemd-tmpfiles --root=" + root.path + " --create " + dist("flarelab.tmpfiles"));
    ASSERT_EQ(dirs.first, 0) << dirs.second;
    const std::string state = root.path + "/var/lib/flarelab";
    ASSERT_TRUE(fs::is_directory(state + "/output"));
    EXPECT_EQ(fs::status(state).permissions() & fs::perms::all,
              fs::perms::owner_all | fs::perms::group_read | fs::perms::group_exec);
}

// A datagram socket standing in for systemd's notification socket, read all along by a thread
// of its own (as systemd does: a sender blocks once the queue is full).
class NotifySocket {
public:
    explicit NotifySocket(const std::string& path) {
        fd_ = ::socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
        sockaddr_un address{};
        address.sun_family = AF_UNIX;
        std::strncpy(address.sun_path, path.c_str(), sizeof address.sun_path - 1);
        EXPECT_EQ(::bind(fd_, reinterpret_cast<sockaddr*>(&address), sizeof address), 0);
        timeval t{0, 100'000};
        ::setsockopt(fd_, SOL_SOCKET, SO_RCVTIMEO, &t, sizeof t);
        reader_ = std::thread([this] {
            char buffer[4096];
            while (!done_) {
                const ssize_t n = ::recv(fd_, buffer, sizeof buffer, 0);
                if (n <= 0) continue;
                std::lock_guard lock(mutex_);
                messages_.push_back({Clock::now(), std::string(buffer, static_cast<size_t>(n))});
                cv_.notify_all();
            }
        });
    }
    ~NotifySocket() {
        done_ = true;
        reader_.join();
        ::close(fd_);
    }
    // The time of the first message holding `text`, waiting up to deadline_s for it.
    std::optional<Clock::time_point> first(const std::string& text, double deadline_s) {
        std::unique_lock lock(mutex_);
        std::optional<Clock::time_point> found;
        cv_.wait_for(lock, std::chrono::milliseconds(static_cast<int64_t>(deadline_s * 1e3)), [&] {
            for (const auto& [at, message] : messages_)
                if (message.find(text) != std::string::npos) return (found = at).has_value();
            return false;
        });
        return found;
    }
    // The times of the messages holding `text`, from `from` on.
    std::vector<Clock::time_point> all(const std::string& text, Clock::time_point from) {
        std::lock_guard lock(mutex_);
        std::vector<Clock::time_point> out;
        for (const auto& [at, message] : messages_)
            if (at >= from && message.find(text) != std::string::npos) out.push_back(at);
        return out;
    }

private:
    int fd_ = -1;
    std::atomic<bool> done_{false};
    std::mutex mutex_;
    std::condition_variable cv_;
    std::vector<std::pair<Clock::time_point, std::string>> messages_;
    std::thread reader_;
};

TEST(Systemd, NotifiesReadyOnceListeningThenTheWatchdogAtItsIntervalThenStopping) {
    if (!systemdNotifyBuiltIn()) GTEST_SKIP() << "built without libsystemd (libsystemd-dev)";
    TempDir dir;
    const std::string state = privateStateDir(dir.path), log = dir.path + "/log";
    NotifySocket notify(dir.path + "/notify");
    // 300 ms asked: pings every 150 ms.
    FlarelabdProcess daemon({"--state-dir", state}, log,
                            {"NOTIFY_SOCKET=" + dir.path + "/notify", "WATCHDOG_USEC=300000"});
    const auto ready = notify.first("READY=1", 30.0);
    ASSERT_TRUE(ready) << readText(log);
    // READY=1 means the socket answers now, not soon.
    {
        auto stub = v1::FlareLab::NewStub(grpc::CreateChannel("unix:" + state + "/flarelabd.sock",
                                                              grpc::InsecureChannelCredentials()));
        v1::RigDescription rig;
        auto ctx = context("test", 5.0);
        EXPECT_TRUE(stub->DescribeRig(ctx.get(), {}, &rig).ok());
    }
    // The watchdog: over two seconds at least half the pings asked for (every 150 ms).
    std::this_thread::sleep_for(std::chrono::seconds(2));
    const auto pings = notify.all("WATCHDOG=1", *ready);
    double longest_gap_s = 0.0;
    for (size_t i = 1; i < pings.size(); ++i)
        longest_gap_s =
            std::max(longest_gap_s, std::chrono::duration<double>(pings[i] - pings[i - 1]).count());
    std::printf("%zu pings in 2 s, longest gap %.3f s\n", pings.size(), longest_gap_s);
    EXPECT_GE(pings.size(), 6u);
    ::kill(daemon.pid, SIGTERM);
    EXPECT_TRUE(notify.first("STOPPING=1", 30.0)) << readText(log);
    EXPECT_TRUE(exitedWith(daemon.waitExit(30.0), 0)) << readText(log);
}

}  // namespace
}  // namespace flarelab::daemon
