// ============================================================================
//  flarelab common: FileFaults, ScopedFileFaults, writeAll, syncFile, syncDirectory
// ============================================================================
//
// The calls that hand bytes to the disk and make them durable, behind one seam: the sweep writer
// (hdr/sweep.h, hdr/exr.h, hdr/raw_io.h), the daemon's journal (daemon/journal.h) and
// replaceFile (common/file_descriptor.h) write and flush through these functions, so that a
// test can make them fail exactly as a full or failing disk does (ENOSPC from write, EIO from
// fsync) without root, a special file system or luck.
//
// The discipline they serve, learnt from PostgreSQL's fsync bug (2018): a failed fsync may have
// dropped the dirty pages it failed to write while marking them clean, so a second fsync that
// succeeds proves nothing. Callers therefore treat an fsync error as final for whatever they were
// writing (the sweep writer closes the sweep, the daemon fails the job), and never retry it. A
// directory is flushed after a file is created or renamed in it, or the new name may vanish in a
// crash although the file's bytes are safe.
#pragma once

#include <fcntl.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <system_error>
#include <utility>

#include "common/result.h"

namespace flarelab {

// Faults a test injects. Each hook is called with the path of the file (for a directory's flush,
// the directory) before the real call and returns 0 to let it through, or the errno to fail it
// with (the real call is then not made). A hook may be empty.
struct FileFaults {
    std::function<int(const std::string& path)> write;
    std::function<int(const std::string& path)> fsync;
};

namespace detail {

struct FileFaultState {
    std::atomic<bool> armed{false};
    std::mutex mutex;
    std::shared_ptr<const FileFaults> faults;
};

inline FileFaultState& fileFaultState() {
    static FileFaultState state;
    return state;
}

// The errno a hook injects for `path`, or 0.
inline int injectedFault(bool fsync, const std::string& path) {
    FileFaultState& state = fileFaultState();
    if (!state.armed.load(std::memory_order_acquire)) return 0;
    std::shared_ptr<const FileFaults> faults;
    {
        std::lock_guard lock(state.mutex);
        faults = state.faults;
    }
    if (!faults) return 0;
    const auto& hook = fsync ? faults->fsync : faults->write;
    return hook ? hook(path) : 0;
}

}  // namespace detail

// Installs `faults` for the whole process (nullptr removes them). For tests only.
inline void setFileFaults(std::shared_ptr<const FileFaults> faults) {
    detail::FileFaultState& state = detail::fileFaultState();
    std::lock_guard lock(state.mutex);
    state.armed.store(faults != nullptr, std::memory_order_release);
    state.faults = std::move(faults);
}

// Faults installed for a scope.
class ScopedFileFaults {
public:
    explicit ScopedFileFaults(FileFaults faults) {
        setFileFaults(std::make_shared<const FileFaults>(std::move(faults)));
    }
    ~ScopedFileFaults() { setFileFaults(nullptr); }
    ScopedFileFaults(const ScopedFileFaults&) = delete;
    ScopedFileFaults& operator=(const ScopedFileFaults&) = delete;
};

// Writes all `size` bytes at `data` to `fd` (the file `path`), going on after short writes and
// EINTR. 0, or the errno of the write that failed (ENOSPC for a write that made no progress on a
// full disk; EIO when write returned 0).
inline int writeAll(int fd, const std::string& path, const void* data, size_t size) {
    if (const int injected = detail::injectedFault(false, path); injected != 0) return injected;
    const char* bytes = static_cast<const char*>(data);
    size_t done = 0;
    while (done < size) {
        const ssize_t wrote = ::write(fd, bytes + done, size - done);
        if (wrote < 0 && errno == EINTR) continue;
        if (wrote < 0) return errno;
        if (wrote == 0) return EIO;
        done += static_cast<size_t>(wrote);
    }
    return 0;
}

// fsyncs that failed on this thread so far: a caller that hands a whole write to another
// function (writeExr, replaceFile) compares it before and after to tell a failed flush, which is
// final, from a failed write, which may be retried once space is freed.
inline uint64_t& syncFailureCount() {
    thread_local uint64_t count = 0;
    return count;
}

// fsync(fd) of the file `path`: 0 or the errno. Never call it again on the same data after an
// error (see the top of this file).
inline int syncFile(int fd, const std::string& path) {
    int error = detail::injectedFault(true, path);
    while (error == 0 && ::fsync(fd) != 0) {
        if (errno != EINTR) error = errno;
    }
    if (error != 0) ++syncFailureCount();
    return error;
}

// Flushes the directory `directory` (its entries: names created, renamed or removed in it).
// IoError naming it when it cannot be opened or flushed.
inline Status syncDirectory(const std::string& directory) {
    const std::string shown = directory.empty() ? "." : directory;
    const int fd = ::open(shown.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (fd < 0) {
        const int error = errno;
        return makeError(ErrorCode::IoError,
                         shown + ": cannot open the directory to flush it: " +
                             std::error_code(error, std::generic_category()).message());
    }
    const int error = syncFile(fd, shown);
    ::close(fd);
    if (error != 0)
        return makeError(ErrorCode::IoError,
                         shown + ": cannot flush the directory to disk (fsync): " +
                             std::error_code(error, std::generic_category()).message());
    return Ok{};
}

}  // namespace flarelab
