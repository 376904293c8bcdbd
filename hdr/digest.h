// ============================================================================
//  flarelab hdr: Sha256, sha256Hex, sha256File (digests of recorded inputs)
// ============================================================================
//
// A sweep and a model record the SHA-256 of the lens prescription they were made with
// (SweepLens::prescription_sha256), so that `flarelab fit --lens` and `score --lens` can refuse
// another file under the same name. `flarelab capture` hashes the file it reads; the daemon
// hashes the text a client sent, which is the file's bytes. OpenSSL's libcrypto does the hashing.
// Digests are 64 lowercase hex digits.
#pragma once

#include <memory>
#include <string>
#include <string_view>

#include "common/result.h"

namespace flarelab::hdr {

// An incremental SHA-256.
class Sha256 {
public:
    Sha256();
    ~Sha256();
    Sha256(const Sha256&) = delete;
    Sha256& operator=(const Sha256&) = delete;
    Status update(std::string_view bytes);
    // The digest of everything updated so far; the hash may not be updated after it.
    Result<std::string> finishHex();

private:
    struct State;
    std::unique_ptr<State> state_;
};

// The SHA-256 of `bytes`.
Result<std::string> sha256Hex(std::string_view bytes);
// The SHA-256 of a file's bytes. Errors name the file: missing, unreadable.
Result<std::string> sha256File(const std::string& path);

}  // namespace flarelab::hdr
