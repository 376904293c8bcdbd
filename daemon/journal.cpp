#include "daemon/journal.h"

#include <fcntl.h>
#include <google/protobuf/util/json_util.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "common/file_descriptor.h"

namespace flarelab::daemon {
namespace {

namespace fs = std::filesystem;
using google::protobuf::util::JsonParseOptions;
using google::protobuf::util::JsonPrintOptions;

constexpr int64_t kMaxRecordBytes = 4 << 20;  // a record holds a lens file of at most 1 MiB

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
    fs::create_directories(dir, ec);
    if (ec) return makeError(ErrorCode::IoError, dir.string() + ": cannot create: " + ec.message());
    return Journal(dir.string());
}

Status Journal::save(const v1::Job& job) const {
    if (jobNumber(job.id()) == 0)
        return makeError(ErrorCode::InvalidArgument, "journal: '" + job.id() + "' is not a job id");
    std::string json;
    JsonPrintOptions print;
    print.add_whitespace = true;
    print.preserve_proto_field_names = true;
    if (auto s = google::protobuf::util::MessageToJsonString(job, &json, print); !s.ok())
        return makeError(ErrorCode::Internal, "journal: " + job.id() + ": " + s.ToString());
    FileDescriptor dir_fd(::open(directory_.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
    if (!dir_fd.valid())
        return makeError(ErrorCode::IoError, directory_ + ": cannot open: " + osMessage(errno));
    return replaceFile(directory_, dir_fd.get(), job.id() + ".json", json, {});
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
    for (fs::directory_iterator it(directory_, ec), end; !ec && it != end; it.increment(ec))
        if (it->path().extension() == ".json" && it->is_regular_file(ec))
            files.push_back(it->path());
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
        const auto size = fs::file_size(file, ec);
        if (ec || size > static_cast<uintmax_t>(kMaxRecordBytes)) {
            setAside(file.string() + ": unreadable or over " + std::to_string(kMaxRecordBytes) +
                     " bytes");
            ec.clear();
            continue;
        }
        std::ifstream in(file, std::ios::binary);
        std::stringstream text;
        text << in.rdbuf();
        auto job = parse(text.str(), file.string());
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
