#include "daemon/journal.h"

#include <fcntl.h>
#include <google/protobuf/util/json_util.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "common/durable_io.h"
#include "common/file_descriptor.h"

namespace flarelab::daemon {
namespace {

namespace fs = std::filesystem;
using google::protobuf::util::JsonParseOptions;
using google::protobuf::util::JsonPrintOptions;

Result<std::string> recordText(const v1::Job& job) {
    std::string json;
    JsonPrintOptions print;
    print.add_whitespace = true;
    print.preserve_proto_field_names = true;
    if (auto s = google::protobuf::util::MessageToJsonString(job, &json, print); !s.ok())
        return makeError(ErrorCode::Internal, "journal: " + job.id() + ": " + s.ToString());
    return json;
}

}  // namespace

std::string jobId(uint64_t number) {
    char text[32];
    std::snprintf(text, sizeof text, "job-%06llu", static_cast<unsigned long long>(number));
    return text;
}

uint64_t jobNumber(const std::string& id) {
    if (id.size() < 5 || id.size() > 24 || id.compare(0, 4, "job-") != 0) return 0;
    uint64_t n = 0;
    for (size_t i = 4; i < id.size(); ++i) {
        if (id[i] < '0' || id[i] > '9') return 0;
        n = n * 10 + static_cast<uint64_t>(id[i] - '0');
    }
    return n;
}

Result<Journal> Journal::open(const std::string& state_dir) {
    const fs::path dir = fs::path(state_dir) / "jobs";
    std::error_code ec;
    const bool existed = fs::exists(fs::symlink_status(dir, ec));
    fs::create_directories(dir, ec);
    if (ec) return makeError(ErrorCode::IoError, dir.string() + ": cannot create: " + ec.message());
    // The folder's name must survive a crash as much as the records in it.
    if (!existed)
        if (Status synced = syncDirectory(state_dir); !synced) return synced.error();
    return Journal(dir.string());
}

Result<int64_t> Journal::recordBytes(const v1::Job& job) {
    auto json = recordText(job);
    if (!json) return json.error();
    return static_cast<int64_t>(json->size());
}

Status Journal::save(const v1::Job& job) const {
    if (jobNumber(job.id()) == 0)
        return makeError(ErrorCode::InvalidArgument, "journal: '" + job.id() + "' is not a job id");
    auto json = recordText(job);
    if (!json) return json.error();
    // A record the next start could not read would lose the job: refused, not written.
    if (static_cast<int64_t>(json->size()) > kJournalMaxRecordBytes)
        return makeError(ErrorCode::InvalidArgument,
                         "journal: " + job.id() + ": the record would take " +
                             std::to_string(json->size()) + " bytes, more than the " +
                             std::to_string(kJournalMaxRecordBytes) + " a record may have");
    FileDescriptor dir_fd(::open(directory_.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
    if (!dir_fd.valid())
        return makeError(ErrorCode::IoError, directory_ + ": cannot open: " + osMessage(errno));
    return replaceFile(directory_, dir_fd.get(), job.id() + ".json", *json, {});
}

Status Journal::remove(const std::string& id) const {
    if (jobNumber(id) == 0)
        return makeError(ErrorCode::InvalidArgument, "journal: '" + id + "' is not a job id");
    const std::string path = (fs::path(directory_) / (id + ".json")).string();
    if (::unlink(path.c_str()) != 0 && errno != ENOENT)
        return makeError(ErrorCode::IoError, path + ": cannot delete: " + osMessage(errno));
    FileDescriptor dir_fd(::open(directory_.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
    if (dir_fd.valid()) ::fsync(dir_fd.get());
    return Ok{};
}

Result<v1::Job> Journal::parse(const std::string& json, const std::string& name) {
    v1::Job job;
    JsonParseOptions options;
    options.ignore_unknown_fields = false;
    if (auto s = google::protobuf::util::JsonStringToMessage(json, &job, options); !s.ok())
        return makeError(ErrorCode::ParseError, name + ": " + std::string(s.message()));
    if (jobNumber(job.id()) == 0)
        return makeError(ErrorCode::ParseError, name + ": id '" + job.id() + "' is not a job id");
    if (job.state() == v1::JOB_STATE_UNSPECIFIED || !v1::JobState_IsValid(job.state()))
        return makeError(ErrorCode::ParseError, name + ": state is missing or unknown");
    return job;
}

Result<JournalLoad> Journal::load() const {
    JournalLoad out;
    std::error_code ec;
    std::vector<fs::path> files;
    // Every entry named *.json, whatever it is: one that is not a regular file is set aside and
    // reported, not skipped in silence (nor opened: a FIFO would block the start).
    for (fs::directory_iterator it(directory_, ec), end; !ec && it != end; it.increment(ec))
        if (it->path().extension() == ".json") files.push_back(it->path());
    if (ec) return makeError(ErrorCode::IoError, directory_ + ": cannot list: " + ec.message());
    std::sort(files.begin(), files.end());
    for (const fs::path& file : files) {
        const auto setAside = [&](const std::string& why) {
            const std::string to = file.string() + ".corrupt";
            std::error_code rename_ec;
            fs::rename(file, to, rename_ec);
            out.warnings.push_back(
                why + (rename_ec ? " (could not set it aside: " + rename_ec.message() + ")"
                                 : "; set aside as " + to));
        };
        auto opened = openRegularFile(file.string());
        if (!opened) {
            setAside(opened.error().message);
            continue;
        }
        if (opened->size > kJournalMaxRecordBytes) {
            setAside(file.string() + ": " + std::to_string(opened->size) +
                     " bytes, more than a record may have (" +
                     std::to_string(kJournalMaxRecordBytes) + ")");
            continue;
        }
        std::string text(static_cast<size_t>(opened->size), '\0');
        size_t done = 0;
        bool read_failed = false;
        while (done < text.size()) {
            const ssize_t got = ::read(opened->fd.get(), text.data() + done, text.size() - done);
            if (got < 0 && errno == EINTR) continue;
            if (got <= 0) {
                read_failed = got < 0;
                break;
            }
            done += static_cast<size_t>(got);
        }
        if (read_failed) {
            setAside(file.string() + ": cannot read: " + osMessage(errno));
            continue;
        }
        text.resize(done);
        auto job = parse(text, file.string());
        if (!job) {
            setAside(job.error().message);
            continue;
        }
        if (file.stem().string() != job->id()) {
            setAside(file.string() + ": holds job " + job->id() + ", not " + file.stem().string());
            continue;
        }
        out.jobs.push_back(std::move(*job));
    }
    std::sort(out.jobs.begin(), out.jobs.end(), [](const v1::Job& a, const v1::Job& b) {
        return jobNumber(a.id()) < jobNumber(b.id());
    });
    return out;
}

}  // namespace flarelab::daemon
