#include "daemon/access.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cstring>

#include "common/file_descriptor.h"

namespace flarelab::daemon {
namespace {

std::string octal(mode_t mode) {
    char text[8];
    std::snprintf(text, sizeof text, "%04o", static_cast<unsigned>(mode & 07777));
    return text;
}

bool loopback(const sockaddr* address) {
    if (address->sa_family == AF_INET) {
        const auto* v4 = reinterpret_cast<const sockaddr_in*>(address);
        return (ntohl(v4->sin_addr.s_addr) >> 24) == 127;
    }
    if (address->sa_family == AF_INET6) {
        const in6_addr& a = reinterpret_cast<const sockaddr_in6*>(address)->sin6_addr;
        if (IN6_IS_ADDR_LOOPBACK(&a)) return true;
        return IN6_IS_ADDR_V4MAPPED(&a) && a.s6_addr[12] == 127;
    }
    return false;
}

// Reads a regular file of at most max_bytes through an open descriptor, checking `check` on its
// status first.
template <typename Check>
Result<std::string> readChecked(const std::string& path,
                                const std::string& what,
                                int64_t max_bytes,
                                Check check) {
    FileDescriptor fd(::open(path.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC));
    if (!fd.valid())
        return makeError(ErrorCode::IoError,
                         what + " " + path + ": cannot open: " + osMessage(errno));
    struct stat info {};
    if (::fstat(fd.get(), &info) != 0)
        return makeError(ErrorCode::IoError,
                         what + " " + path + ": cannot stat: " + osMessage(errno));
    if (!S_ISREG(info.st_mode))
        return makeError(ErrorCode::InvalidArgument, what + " " + path + ": not a regular file");
    if (Status ok = check(info); !ok) return ok.error();
    if (info.st_size > max_bytes)
        return makeError(ErrorCode::InvalidArgument, what + " " + path + ": larger than " +
                                                         std::to_string(max_bytes) + " bytes");
    std::string text(static_cast<size_t>(info.st_size), '\0');
    size_t done = 0;
    while (done < text.size()) {
        const ssize_t got = ::read(fd.get(), text.data() + done, text.size() - done);
        if (got < 0 && errno == EINTR) continue;
        if (got < 0)
            return makeError(ErrorCode::IoError,
                             what + " " + path + ": cannot read: " + osMessage(errno));
        if (got == 0) break;
        done += static_cast<size_t>(got);
    }
    text.resize(done);
    return text;
}

}  // namespace

Status checkLoopbackAddress(const std::string& address) {
    const auto colon = address.rfind(':');
    if (colon == std::string::npos || colon + 1 == address.size())
        return makeError(ErrorCode::InvalidArgument, address + ": not HOST:PORT");
    std::string host = address.substr(0, colon);
    if (host.size() >= 2 && host.front() == '[' && host.back() == ']')
        host = host.substr(1, host.size() - 2);
    if (host.empty())
        return makeError(ErrorCode::InvalidArgument,
                         address + ": no host: it would listen on every address");
    addrinfo hints{};
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    addrinfo* found = nullptr;
    if (const int error = ::getaddrinfo(host.c_str(), nullptr, &hints, &found); error != 0)
        return makeError(ErrorCode::InvalidArgument,
                         address + ": '" + host + "' does not resolve (" + ::gai_strerror(error) +
                             "), so it is not loopback");
    std::string outside;
    for (const addrinfo* a = found; a; a = a->ai_next)
        if (!loopback(a->ai_addr)) {
            char text[INET6_ADDRSTRLEN] = "?";
            const void* raw =
                a->ai_family == AF_INET
                    ? static_cast<const void*>(
                          &reinterpret_cast<const sockaddr_in*>(a->ai_addr)->sin_addr)
                    : static_cast<const void*>(
                          &reinterpret_cast<const sockaddr_in6*>(a->ai_addr)->sin6_addr);
            ::inet_ntop(a->ai_family, raw, text, sizeof text);
            outside = text;
            break;
        }
    ::freeaddrinfo(found);
    if (!outside.empty())
        return makeError(ErrorCode::InvalidArgument,
                         address + ": '" + host + "' resolves to " + outside + ", not loopback");
    return Ok{};
}

Status checkPrivateDirectory(const std::string& path, const std::string& what) {
    struct stat info {};
    if (::stat(path.c_str(), &info) != 0)
        return makeError(ErrorCode::IoError, what + " " + path + ": " + osMessage(errno));
    if (!S_ISDIR(info.st_mode))
        return makeError(ErrorCode::InvalidArgument, what + " " + path + ": not a directory");
    if (info.st_uid != ::geteuid())
        return makeError(ErrorCode::InvalidArgument,
                         what + " " + path + ": owned by uid " + std::to_string(info.st_uid) +
                             ", not by this user (uid " + std::to_string(::geteuid()) +
                             "): another user could replace the daemon's journal, lock or socket");
    if (info.st_mode & (S_IWGRP | S_IWOTH))
        return makeError(ErrorCode::InvalidArgument,
                         what + " " + path + ": mode " + octal(info.st_mode) +
                             " lets other users write in it; chmod go-w " + path +
                             " (group members reach the socket through g+x)");
    return Ok{};
}

Result<std::string> readSecretFile(const std::string& path, const std::string& what) {
    return readChecked(path, what, 64 << 10, [&](const struct stat& info) -> Status {
        if (info.st_mode & (S_IRWXG | S_IRWXO))
            return makeError(ErrorCode::InvalidArgument,
                             what + " " + path + ": mode " + octal(info.st_mode) +
                                 " lets other users read or change it; chmod 600 " + path);
        return Ok{};
    });
}

Result<std::string> readPemFile(const std::string& path, const std::string& what) {
    return readChecked(path, what, 1 << 20, [](const struct stat&) -> Status { return Ok{}; });
}

std::string tcpPeerKey(const std::string& grpc_peer) {
    if (grpc_peer.rfind("ipv4:", 0) != 0 && grpc_peer.rfind("ipv6:", 0) != 0) return grpc_peer;
    const auto colon = grpc_peer.rfind(':');
    return colon > 4 ? grpc_peer.substr(0, colon) : grpc_peer;
}

}  // namespace flarelab::daemon
