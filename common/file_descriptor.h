// ============================================================================
//  flarelab common: FileDescriptor, osMessage, RegularFile, openRegularFile
// ============================================================================
//
// POSIX file handling shared by the EXR, sweep and model readers and writers: an
// owned descriptor whose close() reports the error a destructor would have to drop, the text of
// an errno, and opening a file for reading that must be a regular file.
#pragma once

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdint>
#include <string>
#include <system_error>
#include <utility>

#include "common/result.h"

namespace flarelab {

class FileDescriptor {
public:
    explicit FileDescriptor(int fd) : fd_(fd) {}
    ~FileDescriptor() {
        if (fd_ >= 0) ::close(fd_);
    }
    FileDescriptor(const FileDescriptor&) = delete;
    FileDescriptor& operator=(const FileDescriptor&) = delete;
    int get() const { return fd_; }
    bool valid() const { return fd_ >= 0; }
    // 0 or the errno of close().
    int close() {
        const int result = ::close(fd_);
        fd_ = -1;
        return result == 0 ? 0 : errno;
    }

    FileDescriptor(FileDescriptor&& other) noexcept : fd_(std::exchange(other.fd_, -1)) {}

private:
    int fd_ = -1;
};

inline std::string osMessage(int error_number) {
    return std::error_code(error_number, std::generic_category()).message();
}

struct RegularFile {
    FileDescriptor fd;
    int64_t size = 0;
};

// Opens `path` for reading. NotFound when it does not exist; IoError naming the path when it
// cannot be opened or examined or is not a regular file.
inline Result<RegularFile> openRegularFile(const std::string& path) {
    FileDescriptor fd(::open(path.c_str(), O_RDONLY | O_CLOEXEC));
    if (!fd.valid()) {
        const int error = errno;
        return makeError(error == ENOENT ? ErrorCode::NotFound : ErrorCode::IoError,
                         path + ": cannot open: " + osMessage(error));
    }
    struct stat info {};
    if (::fstat(fd.get(), &info) != 0)
        return makeError(ErrorCode::IoError, path + ": cannot stat: " + osMessage(errno));
    if (!S_ISREG(info.st_mode)) return makeError(ErrorCode::IoError, path + ": not a regular file");
    return RegularFile{std::move(fd), static_cast<int64_t>(info.st_size)};
}

}  // namespace flarelab
