// flarelabd as a process of its own, for the tests of what only a process shows: its flags and
// refusals, signals, its standard error, and systemd's notification. Every wait is bounded.
#pragma once

#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "tests/daemon/daemon_fixture.h"

extern char** environ;

namespace flarelab::daemon::testing {

// This build's flarelabd; FLARELABD_UNDER_TEST names another (to run these tests against an
// older daemon, and see them fail).
inline std::string flarelabdPath() {
    if (const char* other = std::getenv("FLARELABD_UNDER_TEST"); other && *other) return other;
    return std::string(FLARELAB_BINARY_DIR) + "/apps/flarelabd";
}

struct FlarelabdProcess {
    pid_t pid = -1;

    // Starts flarelabd with `args`, its standard error into `log` (a file, appended) or, when
    // stderr_fd >= 0, that descriptor; `env` is added to the test's environment.
    FlarelabdProcess(const std::vector<std::string>& args,
                     const std::string& log,
                     const std::vector<std::string>& env = {},
                     int stderr_fd = -1) {
        posix_spawn_file_actions_t actions;
        posix_spawn_file_actions_init(&actions);
        if (stderr_fd >= 0)
            posix_spawn_file_actions_adddup2(&actions, stderr_fd, 2);
        else
            posix_spawn_file_actions_addopen(&actions, 2, log.c_str(),
                                             O_WRONLY | O_CREAT | O_APPEND, 0644);
        std::vector<std::string> argv = {flarelabdPath()};
        argv.insert(argv.end(), args.begin(), args.end());
        std::vector<char*> argp;
        for (auto& a : argv) argp.push_back(a.data());
        argp.push_back(nullptr);
        std::vector<std::string> environment = env;
        for (char** e = environ; *e; ++e) environment.emplace_back(*e);
        std::vector<char*> envp;
        for (auto& e : environment) envp.push_back(e.data());
        envp.push_back(nullptr);
        EXPECT_EQ(posix_spawn(&pid, argp[0], &actions, nullptr, argp.data(), envp.data()), 0);
        posix_spawn_file_actions_destroy(&actions);
    }

    // The exit status once it exits within `deadline_s`; nothing when it is still running.
    std::optional<int> waitExit(double deadline_s) {
        const auto end = std::chrono::steady_clock::now() +
                         std::chrono::milliseconds(static_cast<int64_t>(deadline_s * 1e3));
        for (;;) {
            int status = 0;
            const pid_t done = ::waitpid(pid, &status, WNOHANG);
            if (done == pid) {
                pid = -1;
                return status;
            }
            if (std::chrono::steady_clock::now() > end) return std::nullopt;
            std::this_thread::sleep_for(std::chrono::milliseconds(20));
        }
    }

    ~FlarelabdProcess() {
        if (pid > 0) {
            ::kill(pid, SIGKILL);
            int status = 0;
            ::waitpid(pid, &status, 0);
        }
    }
};

inline bool exitedWith(const std::optional<int>& status, int code) {
    return status && WIFEXITED(*status) && WEXITSTATUS(*status) == code;
}

// A stub on `socket` once a daemon answers there (within deadline_s); nullptr otherwise.
inline std::unique_ptr<v1::FlareLab::Stub> connectWhenUp(const std::string& socket,
                                                         double deadline_s = 30.0) {
    auto stub = v1::FlareLab::NewStub(
        grpc::CreateChannel("unix:" + socket, grpc::InsecureChannelCredentials()));
    const auto end = std::chrono::steady_clock::now() +
                     std::chrono::milliseconds(static_cast<int64_t>(deadline_s * 1e3));
    while (std::chrono::steady_clock::now() < end) {
        if (fs::exists(socket)) {
            v1::RigDescription rig;
            auto ctx = context("test", 2.0);
            if (stub->DescribeRig(ctx.get(), {}, &rig).ok()) return stub;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    return nullptr;
}

// A state directory flarelabd accepts: made by the test's user, mode 0700.
inline std::string privateStateDir(const std::string& parent, const std::string& name = "state") {
    const std::string path = parent + "/" + name;
    fs::create_directories(path);
    fs::permissions(path, fs::perms::owner_all, fs::perm_options::replace);
    return path;
}

}  // namespace flarelab::daemon::testing
