#include "daemon/service.h"

#include <fcntl.h>
#include <grpcpp/grpcpp.h>
#include <grpcpp/resource_quota.h>
#include <grpcpp/server_posix.h>
#include <poll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <map>
#include <mutex>
#include <thread>

#include "common/file_descriptor.h"
#include "daemon/access.h"
#include "daemon/log.h"
#include "drivers/device.h"
#include "proto/daemon.grpc.pb.h"

namespace flarelab::daemon {
namespace {

namespace fs = std::filesystem;
using grpc::ServerContext;
using grpc::Status;
using grpc::StatusCode;

// The Unix socket, accepted by a thread of ours so that each connection's credentials are read
// before gRPC takes it (AddInsecureChannelFromFd; gRPC then names its peer "fd:N").
class UnixListener {
public:
    // Binds `path` as described in service.h; IoError naming the path when it cannot.
    static Result<std::unique_ptr<UnixListener>> open(const std::string& path) {
        if (path.size() >= sizeof(sockaddr_un::sun_path))
            return makeError(ErrorCode::IoError,
                             path + ": longer than the " +
                                 std::to_string(sizeof(sockaddr_un::sun_path) - 1) +
                                 " bytes a Unix socket path may have; use a shorter --state-dir");
        const fs::path parent = fs::path(path).parent_path();
        std::string private_dir = (parent / ".s-XXXXXX").string();
        if (!::mkdtemp(private_dir.data()))  // mode 0700
            return makeError(ErrorCode::IoError, "cannot make a private directory in " +
                                                     parent.string() + ": " + osMessage(errno));
        const std::string bound = private_dir + "/s";
        const auto cleanup = [&] {
            ::unlink(bound.c_str());
            ::rmdir(private_dir.c_str());
        };
        FileDescriptor fd(::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0));
        sockaddr_un address{};
        address.sun_family = AF_UNIX;
        std::strncpy(address.sun_path, bound.c_str(), sizeof address.sun_path - 1);
        if (!fd.valid() ||
            ::bind(fd.get(), reinterpret_cast<sockaddr*>(&address), sizeof address) ||
            ::chmod(bound.c_str(), 0660) || ::listen(fd.get(), 64) ||
            ::rename(bound.c_str(), path.c_str())) {
            const int error = errno;
            cleanup();
            return makeError(ErrorCode::IoError,
                             "cannot listen on unix:" + path + ": " + osMessage(error));
        }
        ::rmdir(private_dir.c_str());
        std::unique_ptr<UnixListener> out(new UnixListener(std::move(fd)));
        if (!out->wake_.valid())
            return makeError(ErrorCode::IoError, "eventfd: " + osMessage(errno));
        return out;
    }

    ~UnixListener() { stop(); }

    // Accepts connections for `server` until stop().
    void serve(grpc::Server* server) {
        thread_ = std::thread([this, server] { acceptLoop(server); });
    }

    void stop() {
        if (!thread_.joinable()) return;
        const uint64_t one = 1;
        (void)::write(wake_.get(), &one, sizeof one);
        thread_.join();
    }

    // "uid N" of the connection gRPC names "fd:N"; empty when it is not one of ours.
    std::string peerOf(const std::string& grpc_peer) const {
        if (grpc_peer.rfind("fd:", 0) != 0) return "";
        const int fd = std::atoi(grpc_peer.c_str() + 3);
        std::lock_guard lock(mutex_);
        const auto it = peers_.find(fd);
        return it == peers_.end() ? "" : it->second;
    }

private:
    explicit UnixListener(FileDescriptor fd)
        : fd_(std::move(fd)), wake_(::eventfd(0, EFD_CLOEXEC)) {}

    void acceptLoop(grpc::Server* server) {
        for (;;) {
            pollfd p[2] = {{fd_.get(), POLLIN, 0}, {wake_.get(), POLLIN, 0}};
            if (::poll(p, 2, -1) < 0 && errno != EINTR) return;
            if (p[1].revents) return;
            if (!(p[0].revents & POLLIN)) continue;
            const int client = ::accept4(fd_.get(), nullptr, nullptr, SOCK_CLOEXEC | SOCK_NONBLOCK);
            if (client < 0) {
                // Out of descriptors: wait a little rather than spin.
                if (errno == EMFILE || errno == ENFILE || errno == ENOBUFS || errno == ENOMEM)
                    std::this_thread::sleep_for(std::chrono::milliseconds(100));
                continue;
            }
            ucred credentials{};
            socklen_t size = sizeof credentials;
            if (::getsockopt(client, SOL_SOCKET, SO_PEERCRED, &credentials, &size) != 0) {
                ::close(client);
                continue;
            }
            {
                // gRPC closes the descriptor when the connection ends; the next connection that
                // gets its number is recorded here before gRPC sees it.
                std::lock_guard lock(mutex_);
                peers_[client] = "uid " + std::to_string(credentials.uid);
            }
            logEvent(LogLevel::Debug, "server.connection",
                     {{"uid", std::to_string(credentials.uid)},
                      {"pid", std::to_string(credentials.pid)}});
            grpc::AddInsecureChannelFromFd(server, client);
        }
    }

    FileDescriptor fd_;
    FileDescriptor wake_;
    mutable std::mutex mutex_;
    std::map<int, std::string> peers_;
    std::thread thread_;
};

// Calls a second per peer, as a token bucket.
class RateLimiter {
public:
    RateLimiter(double per_s, double burst) : per_s_(per_s), burst_(burst) {}

    bool admit(const std::string& key) {
        const auto now = std::chrono::steady_clock::now();
        std::lock_guard lock(mutex_);
        if (buckets_.size() > 4096) buckets_.clear();  // many names: start afresh, still bounded
        auto [it, fresh] = buckets_.try_emplace(key, Bucket{burst_, now});
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
    Service(JobManager& manager, ServiceOptions options, const UnixListener* unix_listener)
        : manager_(manager),
          options_(std::move(options)),
          limiter_(options_.calls_per_s, options_.burst),
          unix_listener_(unix_listener),
          predict_root_((fs::path(manager.options().runner.state_dir) / "predict").string()) {
        clearPredictWork(predict_root_);
    }

    Status DescribeRig(ServerContext* ctx,
                       const v1::DescribeRigRequest*,
                       v1::RigDescription* out) override {
        Caller client;
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
        Caller client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        return manager_.check(request->config(), plan);
    }

    Status StartSweep(ServerContext* ctx,
                      const v1::StartSweepRequest* request,
                      v1::Job* job) override {
        Caller client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        Status status = manager_.start(*request, client, job);
        if (!status.ok())
            logEvent(LogLevel::Info, "request.refused",
                     {{"rpc", "StartSweep"},
                      {"client", client.name},
                      {"peer", client.peer},
                      {"code", std::to_string(status.error_code())},
                      {"message", status.error_message()}});
        return status;
    }

    Status WatchJob(ServerContext* ctx,
                    const v1::WatchJobRequest* request,
                    grpc::ServerWriter<v1::JobEvent>* writer) override {
        Caller client;
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
        Caller client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        return manager_.pause(*request, client, job);
    }

    Status ResumeJob(ServerContext* ctx,
                     const v1::JobControlRequest* request,
                     v1::Job* job) override {
        Caller client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        return manager_.resume(*request, client, job);
    }

    Status CancelJob(ServerContext* ctx,
                     const v1::JobControlRequest* request,
                     v1::Job* job) override {
        Caller client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        return manager_.cancel(*request, client, job);
    }

    Status ListJobs(ServerContext* ctx,
                    const v1::ListJobsRequest*,
                    v1::ListJobsResponse* out) override {
        Caller client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        for (v1::Job& job : manager_.list()) *out->add_jobs() = std::move(job);
        return Status::OK;
    }

    Status GetJobResult(ServerContext* ctx,
                        const v1::GetJobResultRequest* request,
                        v1::JobResult* out) override {
        Caller client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        return manager_.result(request->job_id(), out);
    }

    // Any client the daemon admits may predict: it does not touch the rig. One at a time, as a
    // prediction takes the machine's cores (its tables are drawn in parallel); a second is
    // refused at once rather than queued, so that no call waits without a word.
    Status Predict(ServerContext* ctx,
                   const v1::PredictRequest* request,
                   v1::PredictResponse* out) override {
        Caller client;
        if (Status ok = admit(ctx, &client); !ok.ok()) return ok;
        Status status = checkPredictRequest(*request, options_.predict);
        std::unique_lock slot(predict_mutex_, std::defer_lock);
        if (status.ok() && !slot.try_lock())
            status = Status(StatusCode::RESOURCE_EXHAUSTED,
                            "another prediction is running; the daemon runs one at a time: "
                            "retry when it ends");
        if (status.ok()) {
            const auto start = std::chrono::steady_clock::now();
            status = runPredict(
                *request, options_.predict, predict_root_,
                [this, ctx] { return stopping_.load() || ctx->IsCancelled(); }, out);
            if (status.ok())
                logEvent(LogLevel::Info, "predict.done",
                         {{"client", client.name},
                          {"peer", client.peer},
                          {"cameras", std::to_string(out->cameras_size())},
                          {"outputs", std::to_string(out->outputs_size())},
                          {"ms", std::to_string(static_cast<int64_t>(
                                     std::chrono::duration<double, std::milli>(
                                         std::chrono::steady_clock::now() - start)
                                         .count()))}});
        }
        if (!status.ok()) {
            out->Clear();
            logEvent(LogLevel::Info, "request.refused",
                     {{"rpc", "Predict"},
                      {"client", client.name},
                      {"peer", client.peer},
                      {"code", std::to_string(status.error_code())},
                      {"message", status.error_message()}});
        }
        return status;
    }

    // Predictions under way stop at their next step (the daemon is stopping).
    void stopPredictions() { stopping_ = true; }

private:
    Status admit(ServerContext* ctx, Caller* client) {
        const std::string grpc_peer = ctx->peer();
        client->peer = unix_listener_ ? unix_listener_->peerOf(grpc_peer) : "";
        if (client->peer.empty()) client->peer = tcpPeerKey(grpc_peer);
        // The connection that was looked up must still be the call's: gRPC cancels the calls of
        // a connection that ends before its descriptor (and so its number) can be reused.
        if (ctx->IsCancelled()) return Status(StatusCode::CANCELLED, "the client went away");
        const auto& metadata = ctx->client_metadata();
        if (!options_.token.empty()) {
            auto it = metadata.find("authorization");
            const std::string given = it == metadata.end()
                                          ? std::string()
                                          : std::string(it->second.data(), it->second.size());
            if (!sameSecret(given, "Bearer " + options_.token)) {
                logEvent(LogLevel::Warn, "request.unauthenticated", {{"peer", client->peer}});
                return Status(StatusCode::UNAUTHENTICATED,
                              "metadata authorization: missing or wrong token");
            }
        }
        client->name = "anonymous";
        if (auto it = metadata.find("flarelab-client"); it != metadata.end()) {
            const std::string name(it->second.data(), it->second.size());
            bool ok = !name.empty() && name.size() <= 64;
            for (const char c : name) ok = ok && c > 0x20 && c < 0x7f;
            if (!ok)
                return Status(StatusCode::INVALID_ARGUMENT,
                              "metadata flarelab-client: must be 1..64 printable ASCII "
                              "characters without spaces");
            client->name = name;
        }
        // Per peer: a client that renames itself is still the same peer.
        if (!limiter_.admit(client->peer))
            return Status(
                StatusCode::RESOURCE_EXHAUSTED,
                "peer " + client->peer + " (client '" + client->name + "') calls more than " +
                    std::to_string(static_cast<int>(options_.calls_per_s)) + " times a second");
        return Status::OK;
    }

    JobManager& manager_;
    const ServiceOptions options_;
    RateLimiter limiter_;
    const UnixListener* unix_listener_;
    std::atomic<size_t> watchers_{0};
    const std::string predict_root_;  // the daemon's own: STATE/predict
    std::mutex predict_mutex_;        // held by the prediction under way
    std::atomic<bool> stopping_{false};
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
    std::unique_ptr<UnixListener> unix_listener;
    std::unique_ptr<Service> service;
    std::unique_ptr<grpc::Server> server;
    std::string socket_path;
    std::once_flag stopped;
};

Result<std::unique_ptr<DaemonServer>> DaemonServer::start(JobManager& manager,
                                                          const ServerOptions& options) {
    // The server is whole only at the end: a failed start leaves the manager alone.
    auto made = std::make_unique<Impl>();
    Impl& impl = *made;
    impl.manager = &manager;
    std::shared_ptr<grpc::ServerCredentials> tcp_credentials = grpc::InsecureServerCredentials();
    if (!options.tcp_address.empty()) {
        if (options.service.token.empty())
            return makeError(ErrorCode::InvalidArgument,
                             "listen " + options.tcp_address +
                                 ": TCP needs a token (--token-file): every local user can "
                                 "reach a TCP port");
        if (options.allow_remote && (options.tls_cert_file.empty() || options.tls_key_file.empty()))
            return makeError(ErrorCode::InvalidArgument,
                             "listen " + options.tcp_address +
                                 ": beyond loopback (--allow-remote) the daemon needs TLS "
                                 "(--tls-cert and --tls-key): the token would cross the network "
                                 "in clear");
        if (!options.allow_remote)
            if (auto ok = checkLoopbackAddress(options.tcp_address); !ok)
                return makeError(ErrorCode::InvalidArgument,
                                 "listen " + ok.error().message +
                                     "; add --allow-remote (with TLS) to expose the rig");
        if (options.tls_cert_file.empty() != options.tls_key_file.empty())
            return makeError(ErrorCode::InvalidArgument,
                             "TLS needs both a certificate (--tls-cert) and its key (--tls-key)");
        if (!options.tls_cert_file.empty()) {
            auto cert = readPemFile(options.tls_cert_file, "--tls-cert");
            if (!cert) return cert.error();
            auto key = readSecretFile(options.tls_key_file, "--tls-key");
            if (!key) return key.error();
            grpc::SslServerCredentialsOptions ssl;
            ssl.pem_key_cert_pairs.push_back({*key, *cert});
            tcp_credentials = grpc::SslServerCredentials(ssl);
        }
    }
    if (!options.socket_path.empty()) {
        auto listener = UnixListener::open(options.socket_path);
        if (!listener) return listener.error();
        impl.unix_listener = std::move(*listener);
        impl.socket_path = options.socket_path;
    }
    impl.service = std::make_unique<Service>(manager, options.service, impl.unix_listener.get());
    grpc::ServerBuilder builder;
    int port = 0;
    if (!options.tcp_address.empty())
        builder.AddListeningPort(options.tcp_address, tcp_credentials, &port);
    builder.RegisterService(impl.service.get());
    builder.SetMaxReceiveMessageSize(static_cast<int>(options.service.max_request_bytes));
    grpc::ResourceQuota quota("flarelabd");
    quota.SetMaxThreads(static_cast<int>(options.service.max_watchers) + 64);
    builder.SetResourceQuota(quota);
    impl.server = builder.BuildAndStart();
    if (!impl.server) {
        if (!impl.socket_path.empty()) ::unlink(impl.socket_path.c_str());
        return makeError(ErrorCode::IoError, "cannot listen on " + options.tcp_address);
    }
    if (!options.tcp_address.empty() && port == 0) {
        impl.server->Shutdown();
        if (!impl.socket_path.empty()) ::unlink(impl.socket_path.c_str());
        return makeError(ErrorCode::IoError, "cannot listen on " + options.tcp_address);
    }
    if (impl.unix_listener) impl.unix_listener->serve(impl.server.get());
    std::unique_ptr<DaemonServer> out(new DaemonServer());
    out->impl_ = std::move(made);
    out->tcp_port_ = port;
    logEvent(LogLevel::Info, "server.listening",
             {{"socket", options.socket_path},
              {"tcp", options.tcp_address.empty() ? "" : options.tcp_address},
              {"tcp_port", std::to_string(port)},
              {"tls", options.tls_cert_file.empty() ? "off" : "on"},
              {"token", options.service.token.empty() ? "none" : "required"}});
    return out;
}

void DaemonServer::shutdown(double deadline_s) {
    if (!impl_) return;
    std::call_once(impl_->stopped, [&] {
        if (impl_->unix_listener) impl_->unix_listener->stop();
        impl_->service->stopPredictions();
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
