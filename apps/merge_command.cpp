#include "apps/merge_command.h"

#include <memory>
#include <optional>
#include <ostream>
#include <string>
#include <vector>

#include "apps/png_preview.h"
#include "hdr/exr.h"
#include "hdr/merge.h"
#include "hdr/raw_io.h"
#include "render/preview.h"

namespace flarelab::apps {
namespace {

struct MergeState {
    std::vector<std::string> brackets;
    std::string exr_path;
    std::string png_path;
    std::string lens;
    std::optional<double> exposure_stops;  // none: automatic (png_preview.h)
    bool half = false;
};

int run(const MergeState& s, std::ostream& out, std::ostream& err) {
    std::vector<hdr::RawFrame> frames;
    for (const std::string& path : s.brackets) {
        auto frame = hdr::readRaw(path);
        if (!frame) {
            err << "flarelab: " << frame.error().message << "\n";
            return 1;
        }
        frames.push_back(std::move(*frame));
    }
    auto merged = hdr::mergeBrackets(frames);
    if (!merged) {
        err << "flarelab: merging " << s.brackets.size()
            << " bracket(s): " << merged.error().message << "\n";
        return 1;
    }
    auto image = hdr::toImage(*merged);
    if (!image) {
        err << "flarelab: " << image.error().message << "\n";
        return 1;
    }
    hdr::ExrMetadata meta;
    meta.angle_deg = merged->angle_deg;
    meta.exposure_times_s = merged->exposure_times_s;
    meta.gain = merged->gain;
    meta.camera = merged->camera;
    meta.lens = s.lens;
    meta.merge_method = merged->method;
    meta.software_version = "flarelab merge";
    meta.extra["saturated_samples"] = std::to_string(merged->saturated_samples);
    meta.extra["dark_samples"] = std::to_string(merged->dark_samples);
    hdr::ExrWriteOptions options;
    options.pixel_type = s.half ? hdr::ExrPixelType::HalfWhereFits : hdr::ExrPixelType::Float;
    auto bounds = hdr::lowerBounds(*merged);
    if (!bounds) {
        err << "flarelab: " << bounds.error().message << "\n";
        return 1;
    }
    const auto written = hdr::writeExr(s.exr_path, *image, meta, options, *bounds);
    if (!written) {
        err << "flarelab: " << written.error().message << "\n";
        return 1;
    }
    if (!written->note.empty()) err << "flarelab: " << written->note << "\n";
    if (!writePngPreview(*image, s.png_path, s.exposure_stops, out, err)) return 1;
    out << "merge: " << frames.size() << " bracket(s), " << merged->width << "x" << merged->height
        << ", angle " << merged->angle_deg << " deg, " << merged->saturated_samples
        << " samples saturated in every bracket, " << merged->dark_samples
        << " dark in every bracket -> " << s.exr_path
        << (s.png_path.empty() ? "" : ", " + s.png_path) << "\n";
    return 0;
}

}  // namespace

void addMergeCommand(CLI::App& app, std::ostream& out, std::ostream& err, int& exit_code) {
    auto state = std::make_shared<MergeState>();
    CLI::App* cmd =
        app.add_subcommand("merge", "merge raw brackets (flarelab raw PGM files) into one HDR EXR");
    cmd->add_option("brackets", state->brackets, "the raw brackets of one angle, any order")
        ->required();
    cmd->add_option("-o,--output", state->exr_path, "output OpenEXR file")->required();
    cmd->add_option("--png", state->png_path, "also a tone-mapped PNG preview");
    cmd->add_option("--exposure-stops", state->exposure_stops,
                    "PNG exposure in stops (default: automatic, printed)");
    cmd->add_option("--lens", state->lens, "lens description for the EXR header");
    cmd->add_flag("--half", state->half, "half floats where every value fits half");
    cmd->callback([state, &out, &err, &exit_code] { exit_code = run(*state, out, err); });
}

}  // namespace flarelab::apps
