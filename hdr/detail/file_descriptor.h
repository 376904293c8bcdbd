// ============================================================================
//  flarelab hdr (private): FileDescriptor
// ============================================================================
//
// An owned POSIX file descriptor for the writers that flush files to disk before renaming them
// into place (exr.cpp, sweep.cpp). close() reports the error a destructor would have to drop.
#pragma once

#include <unistd.h>

#include <cerrno>

namespace flarelab::hdr::detail {

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

private:
    int fd_ = -1;
};

}  // namespace flarelab::hdr::detail
