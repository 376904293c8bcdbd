// ============================================================================
//  flarelab daemon: ServiceOptions, ServerOptions, DaemonServer
// ============================================================================
//
// The gRPC face of the daemon (proto/daemon.proto) over a JobManager: admission of every call
// (the shared token when one is set, the client's name, a rate limit per peer), the RPCs, and
// the server that listens on a Unix domain socket (mode 0660) and, when configured, on TCP.
//
// Peers. The Unix socket is accepted here, not by gRPC, so that each connection's credentials
// (SO_PEERCRED: the kernel's word for the client's uid and pid) are known; the connection is then
// handed to gRPC. A call's peer is "uid N" there, and the address without its port on TCP
// ("ipv4:10.0.0.7"). Rate limits are per peer, whatever names its clients give themselves, and
// control of a job needs the same name from the same peer (job_manager.h). The socket is bound in
// a private directory (mode 0700), given mode 0660 there and only then renamed into place: it is
// never reachable with another mode, and the process's umask is never touched.
//
// TCP. A TCP listener needs the token (every local user can reach a loopback port), and one
// beyond loopback (allow_remote) needs TLS too: the token would cross the network in clear.
//
// Bounds, so that no client can exhaust the daemon: a request of more than max_request_bytes
// is refused by gRPC (RESOURCE_EXHAUSTED) before it is parsed; a peer gets calls_per_s calls a
// second on average with bursts of `burst` (RESOURCE_EXHAUSTED beyond); at most max_watchers
// streams watch at once. Predictions (daemon/predict_call.h) run one at a time, within
// ServiceOptions::predict; a second while one runs is refused (RESOURCE_EXHAUSTED).
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "common/result.h"
#include "daemon/job_manager.h"
#include "daemon/predict_call.h"

namespace flarelab::daemon {

struct ServiceOptions {
    std::string token;  // empty: no token is asked for
    double calls_per_s = 50.0;
    double burst = 200.0;
    size_t max_watchers = 256;
    size_t max_request_bytes = size_t{2} << 20;  // a 1 MiB lens file and the rest
    std::string daemon_version = "flarelabd";
    std::string rig = "sim";  // "sim" or "replay"
    // What DescribeRig names; the simulated rig's by default.
    std::string camera_model = "flarelab simulated camera", camera_serial = "SIMCAM-0";
    std::string head_model = "flarelab simulated head", head_serial = "SIMHEAD-0";
    std::string device_uri = "sim:";
    int bit_depth = 12;
    // The rig's devices (rig "devices"), by URI, as flarelabd was given them.
    std::vector<std::string> cameras;
    std::vector<std::string> heads;
    // What one Predict call may take, write and hand back.
    PredictLimits predict;
};

struct ServerOptions {
    std::string socket_path;  // empty: none
    // "host:port" to listen on TCP as well; empty: none. Loopback only (checkLoopbackAddress)
    // unless allow_remote, which needs TLS.
    std::string tcp_address;
    bool allow_remote = false;
    // PEM files of the TLS certificate chain and its private key for TCP; both or neither. The
    // key must be readable by its owner only.
    std::string tls_cert_file;
    std::string tls_key_file;
    ServiceOptions service;
};

class DaemonServer {
public:
    // Listens and serves on gRPC's threads. IoError when the socket cannot be made (path too
    // long for a Unix socket, directory not writable, port taken); InvalidArgument when TCP is
    // asked without a token, beyond loopback without allow_remote, or with allow_remote without
    // TLS, or when a TLS file cannot be used.
    static Result<std::unique_ptr<DaemonServer>> start(JobManager& manager,
                                                       const ServerOptions& options);
    ~DaemonServer();
    // Stops the job manager (a running job is interrupted at once, watchers are told),
    // then the server, waiting at most `deadline_s` for calls in flight. Idempotent.
    void shutdown(double deadline_s = 5.0);
    // The TCP port when listening on TCP (the one chosen when the address asked for port 0).
    int tcpPort() const { return tcp_port_; }

private:
    DaemonServer() = default;
    struct Impl;
    std::unique_ptr<Impl> impl_;
    int tcp_port_ = 0;
};

// The constant-time comparison a token check needs.
bool sameSecret(const std::string& a, const std::string& b);

}  // namespace flarelab::daemon
