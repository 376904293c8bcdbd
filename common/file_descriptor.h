// ============================================================================
//  flarelab common: FileDescriptor, osMessage, RegularFile, openRegularFile, replaceFile
// ============================================================================
//
// POSIX file handling shared by the EXR, sweep and model readers and writers: an
// owned descriptor whose close() reports the error a destructor would have to drop, the text of
// an errno, opening a file for reading that must be a regular file, and replacing a file's
// contents atomically (replaceFile). Writes and flushes go through common/durable_io.h, where
// tests inject disk faults.
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

#include "common/durable_io.h"
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
    FileDescriptor& operator=(FileDescriptor&& other) noexcept {
        if (this != &other) {
            if (fd_ >= 0) ::close(fd_);
            fd_ = std::exchange(other.fd_, -1);
        }
        return *this;
    }

private:
    int fd_ = -1;
};

inline std::string osMessage(int error_number) {
    return std::error_code(error_number, std::generic_category()).message();
}

// "a FIFO", "a directory", ...: what a file of mode `mode` (st_mode) is, for messages.
inline const char* fileTypeName(mode_t mode) {
    if (S_ISREG(mode)) return "a regular file";
    if (S_ISDIR(mode)) return "a directory";
    if (S_ISLNK(mode)) return "a symbolic link";
    if (S_ISFIFO(mode)) return "a FIFO";
    if (S_ISCHR(mode)) return "a character device";
    if (S_ISBLK(mode)) return "a block device";
    if (S_ISSOCK(mode)) return "a socket";
    return "of an unknown type";
}

struct RegularFile {
    FileDescriptor fd;
    int64_t size = 0;
};

// Opens `path` for reading. NotFound when it does not exist; IoError naming the path when it
// cannot be opened or examined, is a symbolic link (not followed), or is not a regular file.
// Whatever stands at `path` (a FIFO without a writer, a device that never answers), the open
// does not wait: it is made with O_NONBLOCK, and the type is checked before anything is read.
inline Result<RegularFile> openRegularFile(const std::string& path) {
    // Opening some devices acts (a tape rewinds): look before opening, and check again after.
    struct stat seen {};
    if (::lstat(path.c_str(), &seen) == 0 && !S_ISREG(seen.st_mode)) {
        if (S_ISLNK(seen.st_mode))
            return makeError(ErrorCode::IoError,
                             path + ": is a symbolic link; refusing to follow it");
        return makeError(ErrorCode::IoError,
                         path + ": not a regular file (it is " + fileTypeName(seen.st_mode) + ")");
    }
    FileDescriptor fd(::open(path.c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW | O_NONBLOCK));
    if (!fd.valid()) {
        const int error = errno;
        if (error == ELOOP)
            return makeError(ErrorCode::IoError,
                             path + ": is a symbolic link; refusing to follow it");
        return makeError(error == ENOENT ? ErrorCode::NotFound : ErrorCode::IoError,
                         path + ": cannot open: " + osMessage(error));
    }
    struct stat info {};
    if (::fstat(fd.get(), &info) != 0)
        return makeError(ErrorCode::IoError, path + ": cannot stat: " + osMessage(errno));
    if (!S_ISREG(info.st_mode))
        return makeError(ErrorCode::IoError,
                         path + ": not a regular file (it is " + fileTypeName(info.st_mode) + ")");
    // Reads of a regular file do not block anyway; clear the flag for whoever reads it.
    ::fcntl(fd.get(), F_SETFL, ::fcntl(fd.get(), F_GETFL) & ~O_NONBLOCK);
    return RegularFile{std::move(fd), static_cast<int64_t>(info.st_size)};
}

// Writes `text` to `directory`/`file_name` so that the file holds either its old or its new
// contents whatever happens: a temporary file beside it, flushed to disk, renamed over it, and
// the rename itself flushed through `directory_fd`. An error after the rename (the directory's
// flush failed) says so: the file then holds the new contents, but they may not survive a crash.
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
    if (const int error = writeAll(fd.get(), temporary, text.data(), text.size()); error != 0)
        return fail("cannot write " + temporary, error);
    if (const int error = syncFile(fd.get(), temporary); error != 0)
        return fail("cannot flush " + temporary + " to disk (fsync)", error);
    if (const int error = fd.close(); error != 0) return fail("cannot close " + temporary, error);
    if (before_rename) before_rename();
    if (::rename(temporary.c_str(), path.c_str()) != 0)
        return fail("cannot rename " + temporary + " into place", errno);
    if (const int error = syncFile(directory_fd, directory); error != 0)
        return makeError(ErrorCode::IoError,
                         path + ": renamed into place, but the directory " + directory +
                             " cannot be flushed to disk (fsync): " + osMessage(error) +
                             "; the new contents may not survive a crash");
    return Ok{};
}

}  // namespace flarelab
