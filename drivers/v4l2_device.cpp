#include "drivers/v4l2_device.h"

#include <fcntl.h>
#include <grp.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include <cerrno>

#include "common/file_descriptor.h"

namespace flarelab::drivers {
namespace {

int64_t clockNs(clockid_t clock) {
    timespec t{};
    ::clock_gettime(clock, &t);
    return static_cast<int64_t>(t.tv_sec) * 1'000'000'000 + t.tv_nsec;
}

class V4l2Node final : public V4l2Device {
public:
    V4l2Node(FileDescriptor fd, std::string path) : fd_(std::move(fd)), path_(std::move(path)) {}

    int ioctl(unsigned long request, void* argument) override {
        for (;;) {
            if (::ioctl(fd_.get(), request, argument) == 0) return 0;
            if (errno != EINTR) return errno;
        }
    }

    Result<std::span<const uint8_t>> map(uint32_t length, uint32_t offset) override {
        void* address =
            ::mmap(nullptr, length, PROT_READ | PROT_WRITE, MAP_SHARED, fd_.get(), offset);
        if (address == MAP_FAILED)
            return makeError(ErrorCode::IoError, path_ + ": mmap of a " + std::to_string(length) +
                                                     "-byte buffer failed: " + osMessage(errno));
        return std::span<const uint8_t>(static_cast<const uint8_t*>(address), length);
    }

    void unmap(std::span<const uint8_t> mapping) override {
        ::munmap(const_cast<uint8_t*>(mapping.data()), mapping.size());
    }

    int waitForFrame(int timeout_ms) override {
        pollfd p{fd_.get(), POLLIN, 0};
        for (;;) {
            const int n = ::poll(&p, 1, timeout_ms < 0 ? 0 : timeout_ms);
            if (n < 0 && errno == EINTR) continue;  // the caller's deadline bounds the retries
            if (n < 0) return -errno;
            if (n == 0) return 0;
            if (p.revents & POLLIN) return 1;
            return -EPIPE;
        }
    }

    int64_t monotonicNs() const override { return clockNs(CLOCK_MONOTONIC); }
    int64_t realtimeNs() const override { return clockNs(CLOCK_REALTIME); }
    const std::string& path() const override { return path_; }

private:
    FileDescriptor fd_;
    std::string path_;
};

}  // namespace

Result<std::unique_ptr<V4l2Device>> openV4l2Node(const std::string& path) {
    struct stat info {};
    if (::stat(path.c_str(), &info) != 0) {
        const int error = errno;
        return makeError(error == ENOENT ? ErrorCode::NotFound : ErrorCode::IoError,
                         path + ": " + osMessage(error));
    }
    if (!S_ISCHR(info.st_mode))
        return makeError(ErrorCode::IoError, path + ": not a character device (a V4L2 node is)");
    FileDescriptor fd(::open(path.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC));
    if (!fd.valid()) {
        const int error = errno;
        std::string message = path + ": cannot open: " + osMessage(error);
        if (error == EACCES) {
            group entry{};
            group* owner = nullptr;
            char buffer[1024];
            ::getgrgid_r(info.st_gid, &entry, buffer, sizeof buffer, &owner);
            message += " (the node belongs to group '" +
                       std::string(owner ? owner->gr_name : std::to_string(info.st_gid)) +
                       "': add the user to it, or install a udev rule; docs/lab.md)";
        }
        return makeError(error == ENOENT ? ErrorCode::NotFound : ErrorCode::IoError, message);
    }
    return std::unique_ptr<V4l2Device>(std::make_unique<V4l2Node>(std::move(fd), path));
}

}  // namespace flarelab::drivers
