// A daemon in the test process: a JobManager and its gRPC server on a Unix socket in a fresh
// temporary state directory, a stub to call it, and sweep configurations for the simulated rig.
#pragma once

#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>
#include <thread>

#include "daemon/job_manager.h"
#include "daemon/service.h"
#include "hdr/sweep.h"
#include "proto/daemon.grpc.pb.h"
#include "tests/test_paths.h"

namespace flarelab::daemon::testing {

namespace fs = std::filesystem;

inline std::string readText(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    std::stringstream s;
    s << in.rdbuf();
    return s.str();
}

// A fresh directory under /tmp (short, for the socket path), removed at the end.
struct TempDir {
    TempDir() {
        char name[] = "/tmp/flarelabd-test-XXXXXX";
        path = ::mkdtemp(name);
    }
    ~TempDir() {
        std::error_code ec;
        fs::remove_all(path, ec);
    }
    std::string path;
};

// readSweep that refuses EXR files the manifest does not list.
inline hdr::ReadSweepOptions strictRead() {
    hdr::ReadSweepOptions options;
    options.extra_exr_files_are_errors = true;
    return options;
}

// A config for the simulated rig: the Heliar, small frames, short brackets.
inline v1::SweepConfig simConfig(const std::string& output_dir,
                                 double from_deg,
                                 double to_deg,
                                 double step_deg,
                                 bool fast = true) {
    v1::SweepConfig c;
    auto* sim = c.mutable_sim();
    sim->set_fast(fast);
    sim->set_seed(7);
    sim->mutable_lens()->set_prescription_csv(
        readText(flarelab::testing::lensPath("heliar-tronnier.csv")));
    sim->mutable_lens()->set_name("heliar-tronnier.csv");
    c.set_from_deg(from_deg);
    c.set_to_deg(to_deg);
    c.set_step_deg(step_deg);
    for (const double t : {0.01, 0.04}) c.add_exposure_times_s(t);
    c.set_width_px(64);
    c.set_height_px(43);
    c.set_output_dir(output_dir);
    return c;
}

// A sweep from 0 to `to_deg` in 0.2 degree steps, fitted, on frames large enough to hold ghosts
// (160 x 107): a fit of a few seconds.
inline v1::SweepConfig fitConfig(const std::string& output_dir, double to_deg) {
    v1::SweepConfig c = simConfig(output_dir, 0.0, to_deg, 0.2);
    c.set_width_px(160);
    c.set_height_px(107);
    c.set_fit(true);
    return c;
}

inline bool ended(const v1::Job& j) {
    return j.state() == v1::SUCCEEDED || j.state() == v1::FAILED || j.state() == v1::CANCELLED;
}

inline bool fittingOrEnded(const v1::Job& j) { return j.phase() == v1::FITTING || ended(j); }

class Daemon {
public:
    explicit Daemon(const std::string& state_dir,
                    ManagerOptions manager = {},
                    ServerOptions server = {}) {
        fs::create_directories(state_dir + "/output");
        manager.runner.state_dir = state_dir;
        manager.runner.output_root = fs::canonical(state_dir + "/output").string();
        if (manager.runner.software_version == "flarelabd")
            manager.runner.software_version = "flarelabd-test";
        auto made = JobManager::open(manager, &journal_warnings);
        EXPECT_TRUE(made) << made.error().message;
        manager_ = std::move(*made);
        server.socket_path = state_dir + "/flarelabd.sock";
        auto started = DaemonServer::start(*manager_, server);
        EXPECT_TRUE(started) << started.error().message;
        server_ = std::move(*started);
        socket = server.socket_path;
        output_root = manager.runner.output_root;
    }

    ~Daemon() { stop(); }

    void stop() {
        if (server_) server_->shutdown();
        server_.reset();
        manager_.reset();
    }

    std::unique_ptr<v1::FlareLab::Stub> stub(const std::string& target = "") const {
        return v1::FlareLab::NewStub(grpc::CreateChannel(target.empty() ? "unix:" + socket : target,
                                                         grpc::InsecureChannelCredentials()));
    }

    JobManager& manager() { return *manager_; }
    DaemonServer& server() { return *server_; }

    std::string socket;
    std::string output_root;
    std::vector<std::string> journal_warnings;

private:
    std::unique_ptr<JobManager> manager_;
    std::unique_ptr<DaemonServer> server_;
};

// The token every context() shows, when a test's daemon asks for one.
inline std::string& testToken() {
    static std::string token;
    return token;
}

inline std::unique_ptr<grpc::ClientContext> context(const std::string& client = "test",
                                                    double deadline_s = 60.0) {
    auto ctx = std::make_unique<grpc::ClientContext>();
    ctx->AddMetadata("flarelab-client", client);
    if (!testToken().empty()) ctx->AddMetadata("authorization", "Bearer " + testToken());
    ctx->set_deadline(std::chrono::system_clock::now() +
                      std::chrono::milliseconds(static_cast<int64_t>(deadline_s * 1e3)));
    return ctx;
}

inline grpc::Status startSweep(v1::FlareLab::Stub& stub,
                               const v1::SweepConfig& config,
                               v1::Job* job,
                               const std::string& client = "test",
                               const std::string& request_id = "") {
    v1::StartSweepRequest request;
    *request.mutable_config() = config;
    request.set_request_id(request_id);
    auto ctx = context(client);
    return stub.StartSweep(ctx.get(), request, job);
}

// Watches a job to its end; the events seen.
inline std::vector<v1::JobEvent> watchToEnd(v1::FlareLab::Stub& stub,
                                            const std::string& id,
                                            const std::string& client = "test",
                                            double deadline_s = 300.0) {
    auto ctx = context(client, deadline_s);
    v1::WatchJobRequest request;
    request.set_job_id(id);
    auto reader = stub.WatchJob(ctx.get(), request);
    std::vector<v1::JobEvent> events;
    v1::JobEvent e;
    while (reader->Read(&e)) events.push_back(e);
    const grpc::Status status = reader->Finish();
    EXPECT_TRUE(status.ok()) << status.error_message();
    return events;
}

// Polls the job until `done(job)` or the deadline; the last job seen.
template <typename Pred>
v1::Job waitFor(v1::FlareLab::Stub& stub,
                const std::string& id,
                Pred done,
                double deadline_s = 120) {
    const auto end = std::chrono::steady_clock::now() +
                     std::chrono::milliseconds(static_cast<int64_t>(deadline_s * 1e3));
    v1::Job last;
    while (std::chrono::steady_clock::now() < end) {
        v1::ListJobsResponse list;
        auto ctx = context("poller");
        if (stub.ListJobs(ctx.get(), {}, &list).ok())
            for (const v1::Job& j : list.jobs())
                if (j.id() == id) last = j;
        if (done(last)) return last;
        std::this_thread::sleep_for(std::chrono::milliseconds(40));
    }
    ADD_FAILURE() << "job " << id << " did not get there; last state "
                  << v1::JobState_Name(last.state()) << " reason " << last.reason();
    return last;
}

}  // namespace flarelab::daemon::testing
