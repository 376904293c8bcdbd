// libFuzzer target for the lens prescription parser and the first things a parsed lens meets.
//
// Any byte string goes to parsePrescription. A rejection must carry a "source:line:col: " prefix
// that points inside the input; an acceptance must hold the invariants the rest of optics/ relies
// on (finite fields, one stop, positive apertures). An accepted lens is then made into a Lens
// with the default camera, and its paraxial properties, ghost enumeration and two small ray grids
// (the imaging path and the first ghost) must come out finite. Every violation is a trap, so
// libFuzzer records the input.
#include <cctype>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "common/units.h"
#include "optics/ghosts.h"
#include "optics/lens.h"
#include "optics/paraxial.h"
#include "optics/prescription.h"
#include "optics/ray_grid.h"

namespace {

using namespace flarelab;
using namespace flarelab::optics;

constexpr char kSource[] = "fuzz-input";
// Ray grids cost time per surface; past this the lens is only parsed, made and enumerated.
constexpr size_t kMaxTracedSurfaces = 64;
constexpr int kGridN = 4;
constexpr double kGridTheta_deg = 5.0;

void require(bool condition) {
    if (!condition) __builtin_trap();
}

void requireFinite(double value) { require(std::isfinite(value)); }

// The decimal number at `pos` (at most 12 digits, so it cannot overflow); -1 when there is none.
long readNumber(std::string_view text, size_t& pos) {
    const size_t start = pos;
    long value = 0;
    while (pos < text.size() && std::isdigit(static_cast<unsigned char>(text[pos])) &&
           pos - start < 12)
        value = value * 10 + (text[pos++] - '0');
    return pos == start ? -1 : value;
}

// "fuzz-input:LINE:COL: message", with LINE within the input's lines and COL within the line
// (one past its end at most, for faults at the end of a line).
void checkErrorLocation(std::string_view input, const std::string& message) {
    const std::string_view prefix = std::string_view(kSource);
    require(message.size() > prefix.size() + 1 && message.compare(0, prefix.size(), prefix) == 0 &&
            message[prefix.size()] == ':');
    size_t pos = prefix.size() + 1;
    const long line = readNumber(message, pos);
    require(line >= 1 && pos < message.size() && message[pos] == ':');
    ++pos;
    const long column = readNumber(message, pos);
    require(column >= 1 && message.compare(pos, 2, ": ") == 0 && message.size() > pos + 2);

    long lines = 1;
    size_t line_start = 0;
    for (size_t i = 0; i < input.size(); ++i) {
        if (input[i] != '\n') continue;
        if (lines == line) break;
        ++lines;
        line_start = i + 1;
    }
    require(line <= lines);
    if (line < lines || line_start < input.size()) {
        const size_t eol = input.find('\n', line_start);
        const size_t length = (eol == std::string_view::npos ? input.size() : eol) - line_start;
        require(static_cast<size_t>(column) <= length + 1);
    } else {
        require(column == 1);
    }
}

void checkPrescription(const Prescription& p) {
    require(!p.surfaces.empty() && p.surfaces.size() <= 512);
    require(p.stop_index >= 0 && static_cast<size_t>(p.stop_index) < p.surfaces.size());
    int stops = 0;
    for (const Surface& s : p.surfaces) {
        requireFinite(s.radius_mm);
        requireFinite(s.thickness_mm);
        requireFinite(s.ior_d);
        requireFinite(s.abbe);
        requireFinite(s.semi_aperture_mm);
        requireFinite(s.coating_wavelength_nm);
        require(s.thickness_mm >= 0.0 && s.thickness_mm <= 1e6);
        require(s.ior_d >= 1.0 && s.ior_d <= 4.0);
        require(s.semi_aperture_mm >= 1e-6 && s.semi_aperture_mm <= 1e6);
        require(s.radius_mm == 0.0 || s.semi_aperture_mm <= std::abs(s.radius_mm));
        require(s.line >= 1);
        if (s.kind == SurfaceKind::Stop) {
            require(s.radius_mm == 0.0);
            ++stops;
        }
    }
    require(stops == 1 && p.surfaces[p.stop_index].kind == SurfaceKind::Stop);
    require(p.surfaces.back().thickness_mm > 0.0);
}

// What Lens::make promises about a lens it returns: a finite geometry, an open stop and a
// resolved camera.
void checkLens(const Lens& lens) {
    for (const LensSurface& s : lens.surfaces()) {
        requireFinite(s.z_mm);
        requireFinite(s.curvature);
        requireFinite(s.semi_aperture_mm);
        require(s.semi_aperture_mm > 0.0);
    }
    requireFinite(lens.sensorZ_mm());
    const CameraDescription& camera = lens.camera();
    requireFinite(camera.focal_length_mm);
    requireFinite(camera.f_number);
    require(camera.focal_length_mm > 0.0 && camera.f_number > 0.0);
}

void checkGrid(const Result<RayGrid>& grid) {
    // The arguments are inside traceRayGrid's documented ranges, so it may not refuse them.
    require(grid.has_value());
    require(grid->samples.size() == static_cast<size_t>(kGridN) * kGridN);
    for (const GridSample& s : grid->samples) {
        if (!s.valid) continue;
        requireFinite(s.sensor_x_mm);
        requireFinite(s.sensor_y_mm);
        requireFinite(s.throughput);
        requireFinite(s.stop_u);
        requireFinite(s.stop_v);
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
    const std::string_view text(reinterpret_cast<const char*>(data), size);
    const Result<Prescription> prescription = parsePrescription(text, kSource);
    if (!prescription) {
        checkErrorLocation(text, prescription.error().message);
        return 0;
    }
    checkPrescription(*prescription);

    const Result<Lens> lens = Lens::make(*prescription, CameraDescription{});
    if (!lens) return 0;  // afocal, or a stop no paraxial ray reaches: a reported refusal
    checkLens(*lens);

    const auto paraxial = paraxialProperties(*lens, kLambdaD_nm);
    // Lens::make has just succeeded on the same paraxial computation.
    require(paraxial.has_value());
    requireFinite(paraxial->efl_mm);
    requireFinite(paraxial->bfl_mm);
    requireFinite(paraxial->entrance_pupil_z_mm);
    requireFinite(paraxial->entrance_pupil_radius_mm);

    const Result<GhostEnumeration> ghosts = enumerateGhosts(*lens);
    require(ghosts.has_value());
    if (ghosts->ghosts.empty() || lens->surfaces().size() > kMaxTracedSurfaces) return 0;

    const double theta = degToRad(kGridTheta_deg);
    checkGrid(traceRayGrid(*lens, ghosts->ghosts.front(), theta, 0.0, kLambdaGreen_nm, kGridN));
    checkGrid(traceRayGrid(*lens, GhostPath{}, theta, 0.0, kLambdaGreen_nm, kGridN));
    return 0;
}
