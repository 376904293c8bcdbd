#include "daemon/service.h"

#include <grpcpp/grpcpp.h>
#include <grpcpp/resource_quota.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <map>
#include <mutex>

#include "daemon/log.h"
#include "drivers/device.h"
#include "proto/daemon.grpc.pb.h"

namespace flarelab::daemon {
namespace {

using grpc::ServerContext;
using grpc::Status;
using grpc::StatusCode;

// Calls a second per client, as a token bucket.
class RateLimiter {
public:
    RateLimiter(double per_s, double burst) : per_s_(per_s), burst_(burst) {}

    bool admit(const std::string& client) {
        const auto now = std::chrono::steady_clock::now();
        std::lock_guard lock(mutex_);
        if (buckets_.size() > 4096) buckets_.clear();  // many names: start afresh, still bounded
        auto [it, fresh] = buckets_.try_emplace(client, Bucket{burst_, now});
        Bucket& b = it->second;
        if (!fresh) {
            const double dt = std::chrono::duration<double>(now - b.last).count();
            b.tokens = std::min(burst_, b.tokens + dt * per_s_);
            b.last = now;
        }
        if (b.tokens < 1.0) return false;
        b.tokens -= 1.0;
        return true;
    }

private:
    struct Bucket {
        double tokens;
        std::chrono::steady_clock::time_point last;
    };
    const double per_s_, burst_;
    std::mutex mutex_;
    std::map<std::string, Bucket> buckets_;
};

class Service final : public v1::FlareLab::Service {
public:
    Service(JobManager& manager, ServiceOptions options)
        : manager_(manager),
          options_(std::move(options)),
          limiter_(options_.calls_per_s, options_.burst) {}

    Status DescribeRig(ServerContext* ctx,
                       const v1::DescribeRigRequest*,
                       v1::RigDescription* out) override {
        std::string client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        const SweepLimits& l = manager_.options().runner.limits;
        out->set_daemon_version(options_.daemon_version);
        out->set_api_version(1);
        out->set_rig(options_.rig);
        auto* camera = out->mutable_camera();
        camera->set_backend(options_.rig);
        camera->set_model(options_.camera_model);
        camera->set_serial(options_.camera_serial);
        camera->set_uri(options_.device_uri);
        auto* head = out->mutable_head();
        head->set_backend(options_.rig);
        head->set_model(options_.head_model);
        head->set_serial(options_.head_serial);
        head->set_uri(options_.device_uri);
        for (const auto& [uris, list] : {std::pair{&options_.cameras, out->mutable_cameras()},
                                         std::pair{&options_.heads, out->mutable_heads()}})
            for (const std::string& uri : *uris) {
                auto* d = list->Add();
                d->set_uri(uri);
                if (auto parsed = drivers::parseDeviceUri(uri)) d->set_backend(parsed->scheme);
                const auto seen = manager_.deviceIdentity(uri);
                d->set_model(seen.first);
                d->set_serial(seen.second);
            }
        if (!options_.cameras.empty()) *out->mutable_camera() = out->cameras(0);
        if (!options_.heads.empty()) *out->mutable_head() = out->heads(0);
        out->set_head_min_deg(l.head_min_deg);
        out->set_head_max_deg(l.head_max_deg);
        out->set_head_speed_deg_s(l.head_speed_deg_s);
        out->set_min_exposure_s(l.min_exposure_s);
        out->set_max_exposure_s(l.max_exposure_s);
        out->set_bit_depth(static_cast<uint32_t>(options_.bit_depth));
        out->set_running_job_id(manager_.runningJob());
        out->set_queued_jobs(static_cast<uint32_t>(manager_.queuedJobs()));
        out->set_output_root(manager_.options().runner.output_root);
        out->set_max_request_bytes(options_.max_request_bytes);
        return Status::OK;
    }

    Status CheckSweep(ServerContext* ctx,
                      const v1::CheckSweepRequest* request,
                      v1::SweepPlan* plan) override {
        std::string client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        return manager_.check(request->config(), plan);
    }

    Status StartSweep(ServerContext* ctx,
                      const v1::StartSweepRequest* request,
                      v1::Job* job) override {
        std::string client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        Status status = manager_.start(*request, client, job);
        if (!status.ok())
            logEvent(LogLevel::Info, "request.refused",
                     {{"rpc", "StartSweep"},
                      {"client", client},
                      {"code", std::to_string(status.error_code())},
                      {"message", status.error_message()}});
        return status;
    }

    Status WatchJob(ServerContext* ctx,
                    const v1::WatchJobRequest* request,
                    grpc::ServerWriter<v1::JobEvent>* writer) override {
        std::string client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        if (watchers_.fetch_add(1) >= options_.max_watchers) {
            watchers_.fetch_sub(1);
            return Status(StatusCode::RESOURCE_EXHAUSTED,
                          std::to_string(options_.max_watchers) +
                              " watchers already, the most this daemon serves");
        }
        struct Release {
            std::atomic<size_t>& n;
            ~Release() { n.fetch_sub(1); }
        } release{watchers_};
        v1::JobEvent first;
        uint64_t sequence = 0;
        if (Status ok = manager_.watchStart(request->job_id(), &first, &sequence); !ok.ok())
            return ok;
        if (!writer->Write(first)) return Status::OK;  // the client went away
        WatchBatch batch;
        for (;;) {
            if (ctx->IsCancelled()) return Status::OK;
            Status ok = manager_.watchNext(request->job_id(), &sequence,
                                           std::chrono::milliseconds(250), &batch);
            if (!ok.ok()) return ok;
            for (const v1::JobEvent& event : batch.events)
                if (!writer->Write(event)) return Status::OK;
            if (batch.ended) return Status::OK;
        }
    }

    Status PauseJob(ServerContext* ctx,
                    const v1::JobControlRequest* request,
                    v1::Job* job) override {
        std::string client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        return manager_.pause(*request, client, job);
    }

    Status ResumeJob(ServerContext* ctx,
                     const v1::JobControlRequest* request,
                     v1::Job* job) override {
        std::string client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        return manager_.resume(*request, client, job);
    }

    Status CancelJob(ServerContext* ctx,
                     const v1::JobControlRequest* request,
                     v1::Job* job) override {
        std::string client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        return manager_.cancel(*request, client, job);
    }

    Status ListJobs(ServerContext* ctx,
                    const v1::ListJobsRequest*,
                    v1::ListJobsResponse* out) override {
        std::string client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        for (v1::Job& job : manager_.list()) *out->add_jobs() = std::move(job);
        return Status::OK;
    }

    Status GetJobResult(ServerContext* ctx,
                        const v1::GetJobResultRequest* request,
                        v1::JobResult* out) override {
        std::string client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        return manager_.result(request->job_id(), out);
    }

private:
    Status admit(ServerContext* ctx, std::string* client) {
        const auto& metadata = ctx->client_metadata();
        if (!options_.token.empty()) {
            auto it = metadata.find("authorization");
            const std::string given = it == metadata.end()
                                          ? std::string()
                                          : std::string(it->second.data(), it->second.size());
            if (!sameSecret(given, "Bearer " + options_.token)) {
                logEvent(LogLevel::Warn, "request.unauthenticated", {{"peer", ctx->peer()}});
                return Status(StatusCode::UNAUTHENTICATED,
                              "metadata authorization: missing or wrong token");
            }
        }
        *client = "anonymous";
        if (auto it = metadata.find("flarelab-client"); it != metadata.end()) {
            const std::string name(it->second.data(), it->second.size());
            bool ok = !name.empty() && name.size() <= 64;
            for (const char c : name) ok = ok && c > 0x20 && c < 0x7f;
            if (!ok)
                return Status(StatusCode::INVALID_ARGUMENT,
                              "metadata flarelab-client: must be 1..64 printable ASCII "
                              "characters without spaces");
            *client = name;
        }
        if (!limiter_.admit(*client))
            return Status(StatusCode::RESOURCE_EXHAUSTED,
                          "client '" + *client + "' calls more than " +
                              std::to_string(static_cast<int>(options_.calls_per_s)) +
                              " times a second");
        return Status::OK;
    }

    JobManager& manager_;
    const ServiceOptions options_;
    RateLimiter limiter_;
    std::atomic<size_t> watchers_{0};
};

}  // namespace

bool sameSecret(const std::string& a, const std::string& b) {
    unsigned char diff = a.size() == b.size() ? 0 : 1;
    const size_t n = std::max(a.size(), b.size());
    for (size_t i = 0; i < n; ++i)
        diff |= static_cast<unsigned char>((i < a.size() ? a[i] : 0) ^ (i < b.size() ? b[i] : 0));
    return diff == 0;
}

struct DaemonServer::Impl {
    JobManager* manager = nullptr;
    std::unique_ptr<Service> service;
    std::unique_ptr<grpc::Server> server;
    std::string socket_path;
    std::once_flag stopped;
};

Result<std::unique_ptr<DaemonServer>> DaemonServer::start(JobManager& manager,
                                                          const ServerOptions& options) {
    std::unique_ptr<DaemonServer> out(new DaemonServer());
    out->impl_ = std::make_unique<Impl>();
    Impl& impl = *out->impl_;
    impl.manager = &manager;
    impl.service = std::make_unique<Service>(manager, options.service);
    grpc::ServerBuilder builder;
    if (!options.socket_path.empty()) {
        if (options.socket_path.size() >= sizeof(sockaddr_un::sun_path))
            return makeError(ErrorCode::IoError,
                             options.socket_path + ": longer than the " +
                                 std::to_string(sizeof(sockaddr_un::sun_path) - 1) +
                                 " bytes a Unix socket path may have; use a shorter --state-dir");
        ::unlink(options.socket_path.c_str());  // a stale one (the state lock is ours)
        builder.AddListeningPort("unix:" + options.socket_path, grpc::InsecureServerCredentials());
        impl.socket_path = options.socket_path;
    }
    int port = 0;
    if (!options.tcp_address.empty())
        builder.AddListeningPort(options.tcp_address, grpc::InsecureServerCredentials(), &port);
    builder.RegisterService(impl.service.get());
    builder.SetMaxReceiveMessageSize(static_cast<int>(options.service.max_request_bytes));
    grpc::ResourceQuota quota("flarelabd");
    quota.SetMaxThreads(static_cast<int>(options.service.max_watchers) + 64);
    builder.SetResourceQuota(quota);
    // The socket gets mode 0660: created under this umask.
    const mode_t old_mask = ::umask(0117);
    impl.server = builder.BuildAndStart();
    ::umask(old_mask);
    if (!impl.server)
        return makeError(ErrorCode::IoError,
                         "cannot listen on " +
                             (options.socket_path.empty() ? std::string()
                                                          : "unix:" + options.socket_path + " ") +
                             options.tcp_address);
    if (!options.socket_path.empty()) ::chmod(options.socket_path.c_str(), 0660);
    if (!options.tcp_address.empty() && port == 0)
        return makeError(ErrorCode::IoError, "cannot listen on " + options.tcp_address);
    out->tcp_port_ = port;
    logEvent(LogLevel::Info, "server.listening",
             {{"socket", options.socket_path},
              {"tcp", options.tcp_address.empty() ? "" : options.tcp_address},
              {"tcp_port", std::to_string(port)},
              {"token", options.service.token.empty() ? "none" : "required"}});
    return out;
}

void DaemonServer::shutdown(double deadline_s) {
    if (!impl_) return;
    std::call_once(impl_->stopped, [&] {
        impl_->manager->shutdown();
        impl_->server->Shutdown(std::chrono::system_clock::now() +
                                std::chrono::milliseconds(static_cast<int64_t>(deadline_s * 1e3)));
        impl_->server->Wait();
        if (!impl_->socket_path.empty()) ::unlink(impl_->socket_path.c_str());
        logEvent(LogLevel::Info, "server.stopped");
    });
}

DaemonServer::~DaemonServer() { shutdown(); }

}  // namespace flarelab::daemon
