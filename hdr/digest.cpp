#include "hdr/digest.h"

#include <openssl/evp.h>

#include <fstream>
#include <vector>

namespace flarelab::hdr {

struct Sha256::State {
    EVP_MD_CTX* ctx = nullptr;
    bool ok = false;
    bool finished = false;
};

Sha256::Sha256() : state_(std::make_unique<State>()) {
    state_->ctx = EVP_MD_CTX_new();
    state_->ok = state_->ctx && EVP_DigestInit_ex(state_->ctx, EVP_sha256(), nullptr) == 1;
}

Sha256::~Sha256() { EVP_MD_CTX_free(state_->ctx); }

Status Sha256::update(std::string_view bytes) {
    if (!state_->ok) return makeError(ErrorCode::Internal, "sha256: OpenSSL refused to start");
    if (state_->finished)
        return makeError(ErrorCode::Internal, "sha256: updated after the digest was taken");
    if (!bytes.empty() && EVP_DigestUpdate(state_->ctx, bytes.data(), bytes.size()) != 1)
        return makeError(ErrorCode::Internal, "sha256: OpenSSL refused the data");
    return Ok{};
}

Result<std::string> Sha256::finishHex() {
    if (!state_->ok) return makeError(ErrorCode::Internal, "sha256: OpenSSL refused to start");
    if (state_->finished) return makeError(ErrorCode::Internal, "sha256: digest taken twice");
    state_->finished = true;
    unsigned char digest[EVP_MAX_MD_SIZE];
    unsigned int length = 0;
    if (EVP_DigestFinal_ex(state_->ctx, digest, &length) != 1)
        return makeError(ErrorCode::Internal, "sha256: OpenSSL refused to finish the digest");
    static constexpr char kHex[] = "0123456789abcdef";
    std::string hex;
    hex.reserve(2 * length);
    for (unsigned int i = 0; i < length; ++i) {
        hex.push_back(kHex[digest[i] >> 4]);
        hex.push_back(kHex[digest[i] & 15]);
    }
    return hex;
}

Result<std::string> sha256Hex(std::string_view bytes) {
    Sha256 hash;
    if (Status ok = hash.update(bytes); !ok) return ok.error();
    return hash.finishHex();
}

Result<std::string> sha256File(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    if (!in) return makeError(ErrorCode::NotFound, path + ": cannot open it to hash");
    Sha256 hash;
    std::vector<char> buffer(1 << 16);
    while (in) {
        in.read(buffer.data(), static_cast<std::streamsize>(buffer.size()));
        const std::streamsize got = in.gcount();
        if (got > 0)
            if (Status ok = hash.update({buffer.data(), static_cast<size_t>(got)}); !ok)
                return ok.error();
    }
    if (in.bad()) return makeError(ErrorCode::IoError, path + ": read failed while hashing");
    return hash.finishHex();
}

}  // namespace flarelab::hdr
