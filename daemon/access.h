// ============================================================================
//  flarelab daemon: checkLoopbackAddress, checkPrivateDirectory, readSecretFile, readPemFile,
//                   peerKey
// ============================================================================
//
// Who may reach the daemon, and what it trusts on disk. The daemon's state directory holds its
// journal, its lock and its socket: another user who could write there could replace any of them,
// so it must belong to the daemon's user and be writable by no one else. A secret (the token, a
// TLS key) must be readable by no one else either: a token that every local user can read guards
// nothing. A TCP listener without TLS is for loopback only, and an address is loopback only when
// every address its name resolves to is (127.0.0.0/8, ::1, or ::ffff:127.0.0.0/104): not because
// its text starts with "127.".
#pragma once

#include <string>

#include "common/result.h"

namespace flarelab::daemon {

// OK when `address` ("HOST:PORT", "[V6]:PORT") names loopback only; InvalidArgument naming the
// address and why otherwise (an address that does not resolve is not loopback).
Status checkLoopbackAddress(const std::string& address);

// OK when `path` is a directory owned by this process's effective user, not writable by group or
// others; InvalidArgument naming the directory and the command that fixes it otherwise.
Status checkPrivateDirectory(const std::string& path, const std::string& what);

// The contents (at most 64 KiB) of a secret's file: a regular file readable by its owner only.
// InvalidArgument naming `what` and the file, saying "chmod 600", when group or others may read
// or write it; IoError when it cannot be read.
Result<std::string> readSecretFile(const std::string& path, const std::string& what);

// The contents (at most 1 MiB) of a PEM file that need not be secret (a certificate).
Result<std::string> readPemFile(const std::string& path, const std::string& what);

// The identity a rate limit and control are keyed on, from gRPC's peer string: for TCP the
// address without the port ("ipv4:10.0.0.7"), so that a client reconnecting from another port is
// the same client. Other peers are returned as they are.
std::string tcpPeerKey(const std::string& grpc_peer);

}  // namespace flarelab::daemon
