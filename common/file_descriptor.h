// ============================================================================
//  flarelab common: FileDescriptor, osMessage, RegularFile, openRegularFile, replaceFile
// ============================================================================
//
// POSIX file handling shared by the EXR, sweep and model readers and writers: an
// owned descriptor whose close() reports the error a destructor would have to drop, the text of
// an errno, opening a file for reading that must be a regular file, and replacing a file's
// contents atomically (replaceFile).
#pragma once

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdint>
#include <filesystem>
#include <functional>
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

// Writes `text` to `directory`/`file_name` so that the file holds either its old or its new
// contents whatever happens: a temporary file beside it, flushed to disk, renamed over it, and
// the rename itself flushed through `directory_fd`.
inline Status replaceFile(const std::string& directory,
                          int directory_fd,
                          const std::string& file_name,
                          const std::string& text,
                          const std::function<void()>& before_rename) {
    const std::string path = (std::filesystem::path(directory) / file_name).string();
    const std::string temporary = path + ".tmp-" + std::to_string(::getpid());
    const auto fail = [&](const std::string& what, int error) -> Status {
        ::unlink(temporary.c_str());
        return makeError(ErrorCode::IoError, path + ": " + what + ": " + osMessage(error));
    };
    FileDescriptor fd(
        ::open(temporary.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC | O_NOFOLLOW, 0666));
    if (!fd.valid()) return fail("cannot create " + temporary, errno);
    size_t done = 0;
    while (done < text.size()) {
        const ssize_t wrote = ::write(fd.get(), text.data() + done, text.size() - done);
        if (wrote < 0 && errno == EINTR) continue;
        if (wrote <= 0) return fail("cannot write " + temporary, wrote < 0 ? errno : EIO);
        done += static_cast<size_t>(wrote);
    }
    if (::fsync(fd.get()) != 0) return fail("cannot flush " + temporary + " to disk", errno);
    if (const int error = fd.close(); error != 0) return fail("cannot close " + temporary, error);
    if (before_rename) before_rename();
    if (::rename(temporary.c_str(), path.c_str()) != 0)
        return fail("cannot rename " + temporary + " into place", errno);
    // The rename has happened; a failed flush of the directory is not a failed write.
    ::fsync(directory_fd);
    return Ok{};
}

}  // namespace flarelab
