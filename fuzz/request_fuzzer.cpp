// libFuzzer target for what clients hand the daemon (daemon/sweep_config.h, daemon/journal.h).
//
// The bytes are read four ways: as a StartSweepRequest on the wire (what gRPC hands the service
// after its size limit), whose config then goes through prepareSweep, the check every request
// passes before the daemon acts on it; as a PredictRequest, through checkPredictRequest, the
// check that runs before a prediction writes anything (daemon/predict_call.h); as a journal
// record (protobuf JSON, what a restarted daemon reads back); and as a requested output
// directory. A refused prediction must be INVALID_ARGUMENT or RESOURCE_EXHAUSTED with a message. A refusal must be InvalidArgument
// (ParseError for a record) and start with the field it names; an accepted config must have its
// defaults filled, angles that increase inside [from, to], a bracket of positive times and an
// output directory below the root. Every violation is a trap, so libFuzzer records the input.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <string>

#include "daemon/journal.h"
#include "daemon/predict_call.h"
#include "daemon/sweep_config.h"

namespace {

using namespace flarelab;
using namespace flarelab::daemon;

void require(bool condition) {
    if (!condition) __builtin_trap();
}

const std::string& root() {
    static const std::string path = [] {
        const auto dir = std::filesystem::temp_directory_path() / "flarelab-request-fuzz-root";
        std::filesystem::create_directories(dir);
        return std::filesystem::canonical(dir).string();
    }();
    return path;
}

bool below(const std::string& path, const std::string& dir) {
    return path.size() > dir.size() + 1 && path.compare(0, dir.size(), dir) == 0 &&
           path[dir.size()] == '/';
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    const std::string bytes(reinterpret_cast<const char*>(data), size);
    flarelab::v1::StartSweepRequest request;
    if (request.ParseFromString(bytes)) {
        auto prepared = prepareSweep(request.config(), root());
        if (!prepared) {
            require(prepared.error().code == ErrorCode::InvalidArgument);
            require(prepared.error().message.rfind("config.", 0) == 0);
        } else {
            const auto& p = *prepared;
            require(!p.angles_deg.empty() && p.lens.has_value());
            for (size_t i = 0; i < p.angles_deg.size(); ++i) {
                require(std::isfinite(p.angles_deg[i]));
                require(p.angles_deg[i] >= p.config.from_deg() - 1e-6 &&
                        p.angles_deg[i] <= p.config.to_deg() + 1e-6);
                if (i > 0) require(p.angles_deg[i] > p.angles_deg[i - 1]);
            }
            require(!p.exposure_times_s.empty());
            for (const double t : p.exposure_times_s) require(t > 0.0 && std::isfinite(t));
            require(p.config.width_px() > 0 && p.config.height_px() > 0);
            require(p.config.sim().seed() != 0 && p.config.gain() > 0.0);
            require(below(p.output_dir, root()));
            require(std::isfinite(p.rig_time_s) && p.rig_time_s >= 0.0);
        }
    }
    flarelab::v1::PredictRequest predict;
    if (predict.ParseFromString(bytes)) {
        const grpc::Status checked = checkPredictRequest(predict, PredictLimits{});
        if (!checked.ok()) {
            require(checked.error_code() == grpc::StatusCode::INVALID_ARGUMENT ||
                    checked.error_code() == grpc::StatusCode::RESOURCE_EXHAUSTED);
            require(!checked.error_message().empty());
        }
    }
    auto record = Journal::parse(bytes, "fuzz-input");
    if (!record) {
        require(record.error().code == ErrorCode::ParseError);
        require(record.error().message.rfind("fuzz-input: ", 0) == 0);
    } else {
        require(jobNumber(record->id()) > 0);
    }
    auto dir = resolveOutputDir(bytes, root(), "output_dir");
    if (dir) {
        require(below(*dir, root()));
    } else {
        require(dir.error().message.rfind("output_dir: ", 0) == 0);
    }
    return 0;
}
