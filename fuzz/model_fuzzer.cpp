// libFuzzer target for the flare model reader (fit/model_file.h).
//
// The same bytes go to both readers: readModelFromMemory (binary protobuf) and modelFromJson (the
// JSON mapping). A rejection must name the input and be a parse error or an unsupported version
// (or, for the binary reader, the size limit). An acceptance must pass validateModel and survive
// round trips: through the JSON text and back to the same model, and through the binary file
// format (written and read back) to the same model. Every violation is a trap, so libFuzzer
// records the input.
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>

#include "fit/model_file.h"

namespace {

using namespace flarelab;
using namespace flarelab::fit;

constexpr char kSource[] = "fuzz-input";

void require(bool condition) {
    if (!condition) __builtin_trap();
}

void requireNamedRefusal(const Error& error) {
    require(error.message.rfind(std::string(kSource) + ": ", 0) == 0);
    require(error.code == ErrorCode::ParseError || error.code == ErrorCode::Unsupported);
}

// The binary form of `model`, through the one writer there is (a file).
void requireBinaryRoundTrip(const FlareModel& model) {
    static const std::string path =
        (std::filesystem::temp_directory_path() /
         ("flarelab-model-fuzzer-" + std::to_string(::getpid()) + ".flaremodel"))
            .string();
    require(writeModel(path, model).has_value());
    const Result<FlareModel> again = readModel(path);
    std::filesystem::remove(path);
    require(again.has_value() && *again == model);
}

void requireAccepted(const FlareModel& model) {
    require(validateModel(model).has_value());
    const Result<std::string> json = modelToJson(model);
    require(json.has_value());
    const Result<FlareModel> again = modelFromJson(*json, kSource);
    require(again.has_value() && *again == model);
    const Result<std::string> json_again = modelToJson(*again);
    require(json_again.has_value() && *json_again == *json);
    requireBinaryRoundTrip(model);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    if (size > static_cast<size_t>(kModelMaxFileBytes)) return 0;  // the readers' own limit
    const std::string_view bytes(reinterpret_cast<const char*>(data), size);

    const Result<FlareModel> binary = readModelFromMemory(bytes, kSource);
    if (binary)
        requireAccepted(*binary);
    else
        requireNamedRefusal(binary.error());

    const Result<FlareModel> json = modelFromJson(bytes, kSource);
    if (json)
        requireAccepted(*json);
    else
        requireNamedRefusal(json.error());
    return 0;
}
