// libFuzzer target for the sweep manifest parser (hdr/sweep.h).
//
// Any byte string goes to parseSweepManifest, the code readSweepManifest runs on manifest.json. A
// rejection must name the input and be a parse error or an unsupported version. An acceptance
// must keep the rules of its format version (rechecked here independently of the parser), and
// must survive a round trip: formatSweepManifest accepts it, and its text parses back to the same
// sweep and formats to the same text. Every violation is a trap, so libFuzzer records the input.
#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <set>
#include <string>
#include <string_view>

#include "hdr/sweep.h"

namespace {

using namespace flarelab;
using namespace flarelab::hdr;

constexpr char kSource[] = "fuzz-input";

void require(bool condition) {
    if (!condition) __builtin_trap();
}

// The path rules of sweep.h, written again: relative, '/'-separated, no empty, "." or ".."
// component, no backslash or control character.
bool insideDirectory(std::string_view path) {
    if (path.empty() || path.front() == '/' || path.back() == '/') return false;
    for (const char c : path) {
        const auto u = static_cast<unsigned char>(c);
        if (u < 0x20 || u == 0x7F || c == '\\') return false;
    }
    size_t start = 0;
    while (start <= path.size()) {
        const size_t slash = std::min(path.find('/', start), path.size());
        const std::string_view part = path.substr(start, slash - start);
        if (part.empty() || part == "." || part == "..") return false;
        start = slash + 1;
    }
    return true;
}

void requireValid(const Sweep& s) {
    require(s.directory.empty() && s.warnings.empty());
    const SweepHeader& h = s.header;
    require(h.format_version >= kSweepOldestFormatVersion &&
            h.format_version <= kSweepFormatVersion);
    const SweepCapture& c = h.capture;
    require(std::isfinite(c.from_deg) && std::isfinite(c.to_deg) && std::isfinite(c.roll_deg));
    require(c.from_deg <= c.to_deg);
    require(std::isfinite(c.step_deg) && c.step_deg > 0.0);
    require(c.width_px >= 1 && c.width_px <= kSweepMaxSide);
    require(c.height_px >= 1 && c.height_px <= kSweepMaxSide);
    for (const double t : c.exposure_times_s) require(std::isfinite(t) && t > 0.0);
    require(!c.gain || (std::isfinite(*c.gain) && *c.gain > 0.0));
    require(!h.camera.bit_depth || (*h.camera.bit_depth >= 1 && *h.camera.bit_depth <= 32));
    const SweepLens& l = h.lens;
    const auto positive = [](const std::optional<double>& v) {
        return !v || (std::isfinite(*v) && *v > 0.0);
    };
    require(positive(l.focal_length_mm) && positive(l.f_number));
    require(positive(l.stop_semi_aperture_mm) && positive(l.sensor_width_mm) &&
            positive(l.sensor_height_mm));
    require(!l.aperture_blades || *l.aperture_blades == 0 ||
            (*l.aperture_blades >= 3 && *l.aperture_blades <= kSweepMaxApertureBlades));
    require(!l.blade_rotation_deg || std::isfinite(*l.blade_rotation_deg));
    require(l.prescription_sha256.empty() || l.prescription_sha256.size() == 64);
    // Version 3's lens fields only in version 3.
    if (h.format_version < 3)
        require(!l.aperture_blades && !l.blade_rotation_deg && !l.stop_semi_aperture_mm &&
                !l.coat_unspecified_surfaces && !l.sensor_width_mm && !l.sensor_height_mm &&
                l.prescription_file.empty() && l.prescription_sha256.empty());
    std::set<std::string> files;
    for (size_t i = 0; i < s.frames.size(); ++i) {
        const SweepFrame& f = s.frames[i];
        require(std::isfinite(f.angle_deg));
        require(f.angle_deg >= c.from_deg - kSweepAngleSlackDeg);
        require(f.angle_deg <= c.to_deg + kSweepAngleSlackDeg);
        if (i > 0) require(f.angle_deg > s.frames[i - 1].angle_deg);
        require(insideDirectory(f.exr_file));
        require(f.exr_file.size() > 4 && f.exr_file.substr(f.exr_file.size() - 4) == ".exr");
        require(files.insert(f.exr_file).second);
        for (const double t : f.exposure_times_s) require(std::isfinite(t) && t > 0.0);
        require(f.raw_files.empty() || f.raw_files.size() == f.exposure_times_s.size());
        for (const std::string& raw : f.raw_files) {
            require(insideDirectory(raw) && raw != kSweepManifestFile);
            require(files.insert(raw).second);
        }
        require(f.brackets.empty() || f.brackets.size() == f.exposure_times_s.size());
        for (size_t b = 0; b < f.brackets.size(); ++b)
            require(f.brackets[b].exposure_s == f.exposure_times_s[b]);
        require(f.merge_method.find('\0') == std::string::npos);
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    if (size > static_cast<size_t>(kSweepMaxManifestBytes)) return 0;  // the reader's own limit
    const std::string_view text(reinterpret_cast<const char*>(data), size);
    const Result<Sweep> sweep = parseSweepManifest(text, kSource);
    if (!sweep) {
        require(sweep.error().message.rfind(std::string(kSource) + ": ", 0) == 0);
        require(sweep.error().code == ErrorCode::ParseError ||
                sweep.error().code == ErrorCode::Unsupported);
        return 0;
    }
    requireValid(*sweep);

    const Result<std::string> json = formatSweepManifest(*sweep);
    require(json.has_value());
    const Result<Sweep> again = parseSweepManifest(*json, kSource);
    require(again.has_value());
    require(*again == *sweep);
    const Result<std::string> json_again = formatSweepManifest(*again);
    require(json_again.has_value() && *json_again == *json);
    return 0;
}
