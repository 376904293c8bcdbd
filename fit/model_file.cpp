#include "fit/model_file.h"

#include <fcntl.h>
#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/time_util.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <limits>
#include <set>
#include <sstream>
#include <system_error>
#include <utility>

#include "common/check.h"
#include "common/file_descriptor.h"
#include "common/utf8.h"
#include "hdr/raw_frame.h"
#include "proto/model.pb.h"

namespace flarelab::fit {
namespace {

namespace fs = std::filesystem;
namespace pb = google::protobuf;
namespace v1 = flarelab::v1;

constexpr int64_t kMaxUint32 = std::numeric_limits<uint32_t>::max();

// Shortest decimal that reads back to the same double.
std::string formatDouble(double value) {
    std::array<char, 32> buffer{};
    const auto result = std::to_chars(buffer.data(), buffer.data() + buffer.size(), value);
    return std::string(buffer.data(), result.ptr);
}

std::string indexed(const std::string& field, size_t index) {
    return field + "[" + std::to_string(index) + "]";
}

// For messages: control characters escaped, long text shortened, in single quotes.
std::string quotedText(std::string_view text) {
    std::string out = "'";
    for (const char c : text.substr(0, 200)) {
        const auto u = static_cast<unsigned char>(c);
        if (u < 0x20 || u == 0x7F) {
            char escape[8];
            std::snprintf(escape, sizeof(escape), "\\x%02x", u);
            out += escape;
        } else {
            out += c;
        }
    }
    if (text.size() > 200) out += "...";
    return out + "'";
}

// ---------------------------------------------------------------------------------------------
// The rules of the format (model_file.h), on the plain structs. Reading reports a broken
// rule as ParseError, writing as InvalidArgument; `name` is the file or a stand-in.

class Checker {
public:
    Checker(ErrorCode code, std::string name) : code_(code), name_(std::move(name)) {}

    Error fail(const std::string& field, const std::string& what) const {
        return makeError(code_, name_ + ": " + field + ": " + what);
    }
    Status finite(const std::string& field, double value) const {
        if (!std::isfinite(value)) return fail(field, formatDouble(value) + " is not finite");
        return Ok{};
    }
    Status positive(const std::string& field, double value) const {
        if (!(std::isfinite(value) && value > 0.0))
            return fail(field, formatDouble(value) + " is not a finite number > 0");
        return Ok{};
    }
    Status positive(const std::string& field, const std::optional<double>& value) const {
        return value ? positive(field, *value) : Status(Ok{});
    }
    Status nonNegative(const std::string& field, double value) const {
        if (!(std::isfinite(value) && value >= 0.0))
            return fail(field, formatDouble(value) + " is not a finite number >= 0");
        return Ok{};
    }
    Status text(const std::string& field, const std::string& value) const {
        if (value.size() > kModelMaxStringBytes)
            return fail(field, std::to_string(value.size()) + " bytes, more than the limit of " +
                                   std::to_string(kModelMaxStringBytes));
        if (value.find('\0') != std::string::npos) return fail(field, "holds a NUL character");
        if (!validUtf8(value)) return fail(field, "is not valid UTF-8");
        return Ok{};
    }
    Status count(const std::string& field, size_t n, size_t low, size_t high) const {
        if (n < low || n > high)
            return fail(field, std::to_string(n) + " entries; " + std::to_string(low) + ".." +
                                   std::to_string(high) + " allowed");
        return Ok{};
    }

private:
    ErrorCode code_;
    std::string name_;
};

bool isLowerHexDigest(std::string_view text) {
    if (text.size() != 64) return false;
    return std::all_of(text.begin(), text.end(),
                       [](char c) { return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'); });
}

Status checkHeader(const FlareModel& m, const Checker& check) {
    if (m.format_version < kModelOldestFormatVersion || m.format_version > kModelFormatVersion)
        return check.fail("format_version", std::to_string(m.format_version) +
                                                " is not a version this program knows (" +
                                                std::to_string(kModelOldestFormatVersion) + ".." +
                                                std::to_string(kModelFormatVersion) + ")");
    if (auto ok = check.text("software_version", m.software_version); !ok) return ok;
    if (!m.created_utc.empty()) {
        pb::Timestamp stamp;
        if (m.created_utc.size() > 64 || !pb::util::TimeUtil::FromString(m.created_utc, &stamp))
            return check.fail("created", quotedText(m.created_utc) +
                                             " is not an RFC 3339 time (2026-11-29T07:04:02Z)");
    }
    const ModelLens& lens = m.lens;
    if (auto ok = check.text("lens.description", lens.description); !ok) return ok;
    if (auto ok = check.text("lens.prescription_file", lens.prescription_file); !ok) return ok;
    if (!lens.prescription_sha256.empty() && !isLowerHexDigest(lens.prescription_sha256))
        return check.fail(
            "lens.prescription_sha256",
            quotedText(lens.prescription_sha256) + " is not 64 lowercase hex digits (a SHA-256)");
    if (auto ok = check.positive("lens.f_number", lens.f_number); !ok) return ok;
    if (auto ok = check.positive("lens.focal_length_mm", lens.focal_length_mm); !ok) return ok;
    if (auto ok = check.positive("lens.sensor_width_mm", lens.sensor_width_mm); !ok) return ok;
    if (auto ok = check.positive("lens.sensor_height_mm", lens.sensor_height_mm); !ok) return ok;
    if (m.format_version < 2) {
        const std::pair<const char*, bool> newer[] = {
            {"lens.aperture_blades", lens.aperture_blades.has_value()},
            {"lens.blade_rotation_deg", lens.blade_rotation_deg.has_value()},
            {"lens.stop_semi_aperture_mm", lens.stop_semi_aperture_mm.has_value()},
            {"lens.coat_unspecified_surfaces", lens.coat_unspecified_surfaces.has_value()}};
        for (const auto& [field, present] : newer)
            if (present)
                return check.fail(field, "is a field of format version 2, not of version " +
                                             std::to_string(m.format_version));
    }
    if (lens.aperture_blades && *lens.aperture_blades != 0 &&
        (*lens.aperture_blades < 3 || *lens.aperture_blades > kModelMaxApertureBlades))
        return check.fail("lens.aperture_blades", std::to_string(*lens.aperture_blades) +
                                                      " is neither 0 (a circular stop) nor 3.." +
                                                      std::to_string(kModelMaxApertureBlades));
    if (lens.blade_rotation_deg)
        if (auto ok = check.finite("lens.blade_rotation_deg", *lens.blade_rotation_deg); !ok)
            return ok;
    if (auto ok = check.positive("lens.stop_semi_aperture_mm", lens.stop_semi_aperture_mm); !ok)
        return ok;

    const ModelCapture& c = m.capture;
    if (auto ok = check.finite("capture.from_deg", c.from_deg); !ok) return ok;
    if (auto ok = check.finite("capture.to_deg", c.to_deg); !ok) return ok;
    if (auto ok = check.finite("capture.roll_deg", c.roll_deg); !ok) return ok;
    if (auto ok = check.positive("capture.step_deg", c.step_deg); !ok) return ok;
    if (c.from_deg > c.to_deg)
        return check.fail("capture.to_deg", formatDouble(c.to_deg) + " is below capture.from_deg " +
                                                formatDouble(c.from_deg));
    for (size_t i = 0; i < c.exposure_times_s.size(); ++i)
        if (auto ok = check.positive(indexed("capture.exposure_times_s", i), c.exposure_times_s[i]);
            !ok)
            return ok;
    const std::pair<const char*, int64_t> sides[] = {{"capture.width_px", c.width_px},
                                                     {"capture.height_px", c.height_px}};
    for (const auto& [field, side] : sides)
        if (side < 1 || side > kModelMaxSide)
            return check.fail(field, std::to_string(side) + " is outside 1.." +
                                         std::to_string(kModelMaxSide) + " pixels");
    if (auto ok = check.text("capture.camera", c.camera); !ok) return ok;
    if (!c.raw_format.empty()) {
        if (m.format_version < 3)
            return check.fail("capture.raw_format",
                              "is a field of format version 3, not of version " +
                                  std::to_string(m.format_version));
        if (!hdr::parseRawFormat(c.raw_format))
            return check.fail("capture.raw_format",
                              quotedText(c.raw_format) +
                                  " is not mono, bayer-rggb, bayer-bggr, bayer-grbg or bayer-gbrg");
    }
    if (c.light_power_dn_s) {
        if (m.format_version < 4)
            return check.fail("capture.light_power_dn_s",
                              "is a field of format version 4, not of version " +
                                  std::to_string(m.format_version));
        if (auto ok = check.positive("capture.light_power_dn_s", c.light_power_dn_s); !ok)
            return ok;
    }
    if (!c.light_discs.empty()) {
        if (m.format_version < 5)
            return check.fail("capture.light_discs",
                              "is a field of format version 5, not of version " +
                                  std::to_string(m.format_version));
        if (auto ok =
                check.count("capture.light_discs", c.light_discs.size(), 0, kModelMaxSamples);
            !ok)
            return ok;
        const double diagonal =
            std::hypot(static_cast<double>(c.width_px), static_cast<double>(c.height_px));
        for (size_t i = 0; i < c.light_discs.size(); ++i) {
            const ModelLightDisc& d = c.light_discs[i];
            const std::string at = indexed("capture.light_discs", i);
            if (auto ok = check.finite(at + ".angle_deg", d.angle_deg); !ok) return ok;
            if (d.angle_deg < c.from_deg || d.angle_deg > c.to_deg ||
                (i > 0 && !(d.angle_deg > c.light_discs[i - 1].angle_deg)))
                return check.fail(at + ".angle_deg",
                                  formatDouble(d.angle_deg) +
                                      " is not increasing inside capture.from_deg..to_deg (" +
                                      formatDouble(c.from_deg) + ".." + formatDouble(c.to_deg) +
                                      ")");
            if (auto ok = check.nonNegative(at + ".radius_px", d.radius_px); !ok) return ok;
            if (d.radius_px > diagonal)
                return check.fail(at + ".radius_px", formatDouble(d.radius_px) +
                                                         " px is more than the frame's diagonal " +
                                                         formatDouble(diagonal));
        }
    }

    if (auto ok = check.finite("valid_range.from_deg", m.valid_from_deg); !ok) return ok;
    if (auto ok = check.finite("valid_range.to_deg", m.valid_to_deg); !ok) return ok;
    if (!(m.valid_from_deg < m.valid_to_deg))
        return check.fail("valid_range.to_deg", formatDouble(m.valid_to_deg) +
                                                    " is not above valid_range.from_deg " +
                                                    formatDouble(m.valid_from_deg));
    if (m.valid_from_deg < c.from_deg || m.valid_to_deg > c.to_deg)
        return check.fail("valid_range",
                          formatDouble(m.valid_from_deg) + ".." + formatDouble(m.valid_to_deg) +
                              " reaches outside capture.from_deg..capture.to_deg (" +
                              formatDouble(c.from_deg) + ".." + formatDouble(c.to_deg) + ")");
    return Ok{};
}

// `sole`: the parameter's only piece, which may cover a single angle.
Status checkPiece(const ModelPiece& p, const std::string& at, bool sole, const Checker& check) {
    if (auto ok = check.finite(at + ".angle_from_deg", p.angle_from_deg); !ok) return ok;
    if (auto ok = check.finite(at + ".angle_to_deg", p.angle_to_deg); !ok) return ok;
    if (!(p.angle_from_deg < p.angle_to_deg || (sole && p.angle_from_deg == p.angle_to_deg)))
        return check.fail(at + ".angle_to_deg",
                          formatDouble(p.angle_to_deg) + " is not above angle_from_deg " +
                              formatDouble(p.angle_from_deg) +
                              (sole ? "" : " (only a parameter's sole piece may cover one angle)"));
    if (auto ok =
            check.count(at + ".coefficients", p.coefficients.size(), 1, kModelMaxCoefficients);
        !ok)
        return ok;
    for (size_t k = 0; k < p.coefficients.size(); ++k)
        if (auto ok = check.finite(indexed(at + ".coefficients", k), p.coefficients[k]); !ok)
            return ok;
    if (auto ok = check.nonNegative(at + ".residual_rms", p.residual_rms); !ok) return ok;
    if (auto ok = check.nonNegative(at + ".residual_max", p.residual_max); !ok) return ok;
    if (p.samples < 1 || p.samples > kMaxUint32)
        return check.fail(at + ".samples", std::to_string(p.samples) + " is outside 1.." +
                                               std::to_string(kMaxUint32));
    return Ok{};
}

Status checkParameter(const FlareModel& m,
                      const ModelParameter& p,
                      const std::string& at,
                      const Checker& check) {
    if (auto ok = check.text(at + ".name", p.name); !ok) return ok;
    if (p.name.empty()) return check.fail(at + ".name", "is empty");
    if (auto ok = check.text(at + ".unit", p.unit); !ok) return ok;
    if (p.lower_bound)
        if (auto ok = check.finite(at + ".lower_bound", *p.lower_bound); !ok) return ok;
    if (p.upper_bound)
        if (auto ok = check.finite(at + ".upper_bound", *p.upper_bound); !ok) return ok;
    if (p.lower_bound && p.upper_bound && *p.lower_bound > *p.upper_bound)
        return check.fail(
            at + ".upper_bound",
            formatDouble(*p.upper_bound) + " is below lower_bound " + formatDouble(*p.lower_bound));
    if (auto ok = check.count(at + ".pieces", p.pieces.size(), 1, kModelMaxPieces); !ok) return ok;
    for (size_t i = 0; i < p.pieces.size(); ++i) {
        const std::string piece_at = indexed(at + ".pieces", i);
        if (auto ok = checkPiece(p.pieces[i], piece_at, p.pieces.size() == 1, check); !ok)
            return ok;
        if (i > 0 && p.pieces[i].angle_from_deg != p.pieces[i - 1].angle_to_deg)
            return check.fail(piece_at + ".angle_from_deg",
                              formatDouble(p.pieces[i].angle_from_deg) + " is not " +
                                  indexed(at + ".pieces", i - 1) + ".angle_to_deg " +
                                  formatDouble(p.pieces[i - 1].angle_to_deg) +
                                  "; pieces must be ordered and contiguous");
    }
    const double from = p.pieces.front().angle_from_deg;
    const double to = p.pieces.back().angle_to_deg;
    if (!p.sample_angles_deg.empty() || !p.sample_values.empty()) {
        if (m.format_version < 4)
            return check.fail(at + ".sample_angles_deg",
                              "is a field of format version 4, not of version " +
                                  std::to_string(m.format_version));
        if (p.sample_angles_deg.size() != p.sample_values.size())
            return check.fail(at + ".sample_values",
                              std::to_string(p.sample_values.size()) + " values for " +
                                  std::to_string(p.sample_angles_deg.size()) + " angles");
        if (auto ok = check.count(at + ".sample_angles_deg", p.sample_angles_deg.size(), 0,
                                  kModelMaxSamples);
            !ok)
            return ok;
        for (size_t i = 0; i < p.sample_angles_deg.size(); ++i) {
            const double a = p.sample_angles_deg[i];
            if (auto ok = check.finite(indexed(at + ".sample_angles_deg", i), a); !ok) return ok;
            if (auto ok = check.finite(indexed(at + ".sample_values", i), p.sample_values[i]); !ok)
                return ok;
            if (a < from || a > to || (i > 0 && !(a > p.sample_angles_deg[i - 1])))
                return check.fail(indexed(at + ".sample_angles_deg", i),
                                  formatDouble(a) +
                                      " is not increasing inside the pieces' span " +
                                      formatDouble(from) + ".." + formatDouble(to));
        }
    }
    if (from < m.valid_from_deg || to > m.valid_to_deg)
        return check.fail(at + ".pieces", "cover " + formatDouble(from) + ".." + formatDouble(to) +
                                              ", outside valid_range (" +
                                              formatDouble(m.valid_from_deg) + ".." +
                                              formatDouble(m.valid_to_deg) + ")");
    return Ok{};
}

Status checkGhost(const FlareModel& m,
                  const ModelGhost& g,
                  const std::string& at,
                  const Checker& check) {
    if (g.id < 0 || g.id > kMaxUint32)
        return check.fail(at + ".id",
                          std::to_string(g.id) + " is outside 0.." + std::to_string(kMaxUint32));
    if (auto ok = check.text(at + ".name", g.name); !ok) return ok;
    if (auto ok = check.count(at + ".parameters", g.parameters.size(), 1, kModelMaxParameters); !ok)
        return ok;
    std::set<std::string_view> names;
    for (size_t i = 0; i < g.parameters.size(); ++i) {
        const ModelParameter& p = g.parameters[i];
        const std::string param_at = indexed(at + ".parameters", i);
        if (auto ok = checkParameter(m, p, param_at, check); !ok) return ok;
        if (!names.insert(p.name).second)
            return check.fail(param_at + ".name",
                              quotedText(p.name) + " names two parameters of the ghost");
        const ModelParameter& first = g.parameters.front();
        if (p.pieces.front().angle_from_deg != first.pieces.front().angle_from_deg ||
            p.pieces.back().angle_to_deg != first.pieces.back().angle_to_deg)
            return check.fail(param_at + ".pieces",
                              "cover " + formatDouble(p.pieces.front().angle_from_deg) + ".." +
                                  formatDouble(p.pieces.back().angle_to_deg) + ", but " + at +
                                  ".parameters[0].pieces cover " +
                                  formatDouble(first.pieces.front().angle_from_deg) + ".." +
                                  formatDouble(first.pieces.back().angle_to_deg) +
                                  "; a ghost's parameters share one span");
    }
    const ModelGhostFit& f = g.fit;
    if (f.frames_fitted < 1 || f.frames_fitted > kMaxUint32)
        return check.fail(
            at + ".fit.frames_fitted",
            std::to_string(f.frames_fitted) + " is outside 1.." + std::to_string(kMaxUint32));
    if (auto ok = check.finite(at + ".fit.first_angle_deg", f.first_angle_deg); !ok) return ok;
    if (auto ok = check.finite(at + ".fit.last_angle_deg", f.last_angle_deg); !ok) return ok;
    if (f.first_angle_deg > f.last_angle_deg)
        return check.fail(at + ".fit.last_angle_deg", formatDouble(f.last_angle_deg) +
                                                          " is below fit.first_angle_deg " +
                                                          formatDouble(f.first_angle_deg));
    return Ok{};
}

Status checkModel(const FlareModel& m, const Checker& check) {
    if (auto ok = checkHeader(m, check); !ok) return ok;
    if (auto ok = check.count("ghosts", m.ghosts.size(), 0, kModelMaxGhosts); !ok) return ok;
    std::set<int64_t> ids;
    for (size_t i = 0; i < m.ghosts.size(); ++i) {
        const std::string at = indexed("ghosts", i);
        if (auto ok = checkGhost(m, m.ghosts[i], at, check); !ok) return ok;
        if (!ids.insert(m.ghosts[i].id).second)
            return check.fail(at + ".id",
                              std::to_string(m.ghosts[i].id) + " is the id of an earlier ghost");
    }
    return Ok{};
}

// ---------------------------------------------------------------------------------------------
// Between the structs and flarelab.v1.FlareModel.

template <typename T>
std::vector<T> toVector(const pb::RepeatedField<T>& values) {
    return std::vector<T>(values.begin(), values.end());
}

// Unvalidated; every proto value fits its struct field. Counts were limited before (limitCounts).
FlareModel fromProto(const v1::FlareModel& m) {
    FlareModel model;
    // format_version was checked before; keeps the uint32 from wrapping.
    model.format_version = static_cast<int>(std::min<uint32_t>(m.format_version(), 1u << 30));
    model.software_version = m.software_version();
    if (m.has_created()) model.created_utc = pb::util::TimeUtil::ToString(m.created());
    const v1::ModelLens& l = m.lens();
    model.lens.description = l.description();
    model.lens.prescription_file = l.prescription_file();
    model.lens.prescription_sha256 = l.prescription_sha256();
    if (l.has_f_number()) model.lens.f_number = l.f_number();
    if (l.has_focal_length_mm()) model.lens.focal_length_mm = l.focal_length_mm();
    model.lens.sensor_width_mm = l.sensor_width_mm();
    model.lens.sensor_height_mm = l.sensor_height_mm();
    // Kept from wrapping into a valid count; the rules refuse it.
    if (l.has_aperture_blades())
        model.lens.aperture_blades =
            static_cast<int>(std::min<uint32_t>(l.aperture_blades(), 1u << 30));
    if (l.has_blade_rotation_deg()) model.lens.blade_rotation_deg = l.blade_rotation_deg();
    if (l.has_stop_semi_aperture_mm()) model.lens.stop_semi_aperture_mm = l.stop_semi_aperture_mm();
    if (l.has_coat_unspecified_surfaces())
        model.lens.coat_unspecified_surfaces = l.coat_unspecified_surfaces();
    const v1::ModelCapture& c = m.capture();
    model.capture.from_deg = c.from_deg();
    model.capture.to_deg = c.to_deg();
    model.capture.step_deg = c.step_deg();
    model.capture.roll_deg = c.roll_deg();
    model.capture.exposure_times_s = toVector(c.exposure_times_s());
    model.capture.width_px = c.width_px();
    model.capture.height_px = c.height_px();
    model.capture.camera = c.camera();
    if (c.has_raw_format()) model.capture.raw_format = c.raw_format();
    if (c.has_light_power_dn_s()) model.capture.light_power_dn_s = c.light_power_dn_s();
    model.capture.light_discs.reserve(static_cast<size_t>(c.light_discs_size()));
    for (const v1::ModelLightDisc& d : c.light_discs())
        model.capture.light_discs.push_back({d.angle_deg(), d.radius_px()});
    model.valid_from_deg = m.valid_range().from_deg();
    model.valid_to_deg = m.valid_range().to_deg();
    model.ghosts.reserve(static_cast<size_t>(m.ghosts_size()));
    for (const v1::ModelGhost& g : m.ghosts()) {
        ModelGhost ghost;
        ghost.id = g.id();
        ghost.name = g.name();
        ghost.parameters.reserve(static_cast<size_t>(g.parameters_size()));
        for (const v1::ModelParameter& p : g.parameters()) {
            ModelParameter parameter;
            parameter.name = p.name();
            parameter.unit = p.unit();
            if (p.has_lower_bound()) parameter.lower_bound = p.lower_bound();
            if (p.has_upper_bound()) parameter.upper_bound = p.upper_bound();
            parameter.pieces.reserve(static_cast<size_t>(p.pieces_size()));
            for (const v1::ModelPiece& q : p.pieces())
                parameter.pieces.push_back({q.angle_from_deg(), q.angle_to_deg(),
                                            toVector(q.coefficients()), q.residual_rms(),
                                            q.residual_max(), q.samples()});
            parameter.sample_angles_deg = toVector(p.sample_angles_deg());
            parameter.sample_values = toVector(p.sample_values());
            ghost.parameters.push_back(std::move(parameter));
        }
        ghost.fit = {g.fit().frames_fitted(), g.fit().first_angle_deg(), g.fit().last_angle_deg()};
        model.ghosts.push_back(std::move(ghost));
    }
    return model;
}

// `model` must have passed checkModel.
v1::FlareModel toProto(const FlareModel& model) {
    v1::FlareModel m;
    m.set_format_version(static_cast<uint32_t>(model.format_version));
    m.set_software_version(model.software_version);
    if (!model.created_utc.empty()) {
        const bool parsed = pb::util::TimeUtil::FromString(model.created_utc, m.mutable_created());
        FLARELAB_CHECK(parsed);
    }
    v1::ModelLens* l = m.mutable_lens();
    l->set_description(model.lens.description);
    l->set_prescription_file(model.lens.prescription_file);
    l->set_prescription_sha256(model.lens.prescription_sha256);
    if (model.lens.f_number) l->set_f_number(*model.lens.f_number);
    if (model.lens.focal_length_mm) l->set_focal_length_mm(*model.lens.focal_length_mm);
    l->set_sensor_width_mm(model.lens.sensor_width_mm);
    l->set_sensor_height_mm(model.lens.sensor_height_mm);
    if (model.lens.aperture_blades)
        l->set_aperture_blades(static_cast<uint32_t>(*model.lens.aperture_blades));
    if (model.lens.blade_rotation_deg) l->set_blade_rotation_deg(*model.lens.blade_rotation_deg);
    if (model.lens.stop_semi_aperture_mm)
        l->set_stop_semi_aperture_mm(*model.lens.stop_semi_aperture_mm);
    if (model.lens.coat_unspecified_surfaces)
        l->set_coat_unspecified_surfaces(*model.lens.coat_unspecified_surfaces);
    v1::ModelCapture* c = m.mutable_capture();
    c->set_from_deg(model.capture.from_deg);
    c->set_to_deg(model.capture.to_deg);
    c->set_step_deg(model.capture.step_deg);
    c->set_roll_deg(model.capture.roll_deg);
    for (const double t : model.capture.exposure_times_s) c->add_exposure_times_s(t);
    c->set_width_px(static_cast<uint32_t>(model.capture.width_px));
    c->set_height_px(static_cast<uint32_t>(model.capture.height_px));
    c->set_camera(model.capture.camera);
    if (!model.capture.raw_format.empty()) c->set_raw_format(model.capture.raw_format);
    if (model.capture.light_power_dn_s) c->set_light_power_dn_s(*model.capture.light_power_dn_s);
    for (const ModelLightDisc& d : model.capture.light_discs) {
        v1::ModelLightDisc* disc = c->add_light_discs();
        disc->set_angle_deg(d.angle_deg);
        disc->set_radius_px(d.radius_px);
    }
    m.mutable_valid_range()->set_from_deg(model.valid_from_deg);
    m.mutable_valid_range()->set_to_deg(model.valid_to_deg);
    for (const ModelGhost& ghost : model.ghosts) {
        v1::ModelGhost* g = m.add_ghosts();
        g->set_id(static_cast<uint32_t>(ghost.id));
        g->set_name(ghost.name);
        for (const ModelParameter& parameter : ghost.parameters) {
            v1::ModelParameter* p = g->add_parameters();
            p->set_name(parameter.name);
            p->set_unit(parameter.unit);
            if (parameter.lower_bound) p->set_lower_bound(*parameter.lower_bound);
            if (parameter.upper_bound) p->set_upper_bound(*parameter.upper_bound);
            for (const ModelPiece& piece : parameter.pieces) {
                v1::ModelPiece* q = p->add_pieces();
                q->set_angle_from_deg(piece.angle_from_deg);
                q->set_angle_to_deg(piece.angle_to_deg);
                for (const double k : piece.coefficients) q->add_coefficients(k);
                q->set_residual_rms(piece.residual_rms);
                q->set_residual_max(piece.residual_max);
                q->set_samples(static_cast<uint32_t>(piece.samples));
            }
            for (const double a : parameter.sample_angles_deg) p->add_sample_angles_deg(a);
            for (const double v : parameter.sample_values) p->add_sample_values(v);
        }
        v1::ModelGhostFit* f = g->mutable_fit();
        f->set_frames_fitted(static_cast<uint32_t>(ghost.fit.frames_fitted));
        f->set_first_angle_deg(ghost.fit.first_angle_deg);
        f->set_last_angle_deg(ghost.fit.last_angle_deg);
    }
    return m;
}

// Where in `message` (recursively) protobuf kept fields it does not know, as a field path
// ("ghosts[0].fit"); nullopt when nowhere. A binary file from a newer writer carries them.
std::optional<std::string> findUnknownFields(const pb::Message& message, const std::string& at) {
    const pb::Reflection* reflection = message.GetReflection();
    if (!reflection->GetUnknownFields(message).empty()) {
        const int number = reflection->GetUnknownFields(message).field(0).number();
        return (at.empty() ? std::string() : at + ".") + "field number " + std::to_string(number);
    }
    std::vector<const pb::FieldDescriptor*> fields;
    reflection->ListFields(message, &fields);
    for (const pb::FieldDescriptor* field : fields) {
        if (field->cpp_type() != pb::FieldDescriptor::CPPTYPE_MESSAGE) continue;
        const std::string name = (at.empty() ? std::string() : at + ".") + field->name();
        if (field->is_repeated()) {
            const int n = reflection->FieldSize(message, field);
            for (int i = 0; i < n; ++i)
                if (auto found =
                        findUnknownFields(reflection->GetRepeatedMessage(message, field, i),
                                          indexed(name, static_cast<size_t>(i))))
                    return found;
        } else if (auto found = findUnknownFields(reflection->GetMessage(message, field), name)) {
            return found;
        }
    }
    return std::nullopt;
}

// The counts limited before the structs are built, so a hostile file cannot make fromProto
// allocate more than the message already holds, and errors name the field.
Status limitCounts(const v1::FlareModel& m, const Checker& check) {
    if (auto ok = check.count("ghosts", static_cast<size_t>(m.ghosts_size()), 0, kModelMaxGhosts);
        !ok)
        return ok;
    for (int i = 0; i < m.ghosts_size(); ++i) {
        const std::string at = indexed("ghosts", static_cast<size_t>(i));
        const v1::ModelGhost& g = m.ghosts(i);
        if (auto ok = check.count(at + ".parameters", static_cast<size_t>(g.parameters_size()), 1,
                                  kModelMaxParameters);
            !ok)
            return ok;
        for (int j = 0; j < g.parameters_size(); ++j) {
            const std::string param_at = indexed(at + ".parameters", static_cast<size_t>(j));
            if (auto ok = check.count(param_at + ".pieces",
                                      static_cast<size_t>(g.parameters(j).pieces_size()), 1,
                                      kModelMaxPieces);
                !ok)
                return ok;
            if (auto ok = check.count(param_at + ".sample_angles_deg",
                                      static_cast<size_t>(g.parameters(j).sample_angles_deg_size()),
                                      0, kModelMaxSamples);
                !ok)
                return ok;
            if (auto ok = check.count(param_at + ".sample_values",
                                      static_cast<size_t>(g.parameters(j).sample_values_size()), 0,
                                      kModelMaxSamples);
                !ok)
                return ok;
        }
    }
    return Ok{};
}

Error unsupportedVersion(const std::string& name, const std::string& shown) {
    return makeError(ErrorCode::Unsupported, name + ": format_version: " + shown +
                                                 " is not a version this reader knows (" +
                                                 std::to_string(kModelOldestFormatVersion) + ".." +
                                                 std::to_string(kModelFormatVersion) + ")");
}

bool knownVersion(uint32_t version) {
    return version >= static_cast<uint32_t>(kModelOldestFormatVersion) &&
           version <= static_cast<uint32_t>(kModelFormatVersion);
}

Result<FlareModel> fromCheckedProto(const v1::FlareModel& m, const std::string& name) {
    const Checker check(ErrorCode::ParseError, name);
    if (auto ok = limitCounts(m, check); !ok) return ok.error();
    FlareModel model = fromProto(m);
    if (auto ok = checkModel(model, check); !ok) return ok.error();
    return model;
}

// protobuf's JSON syntax errors run over three lines: the complaint, an excerpt and a caret. One
// line here: the complaint and the text from the caret.
std::string statusText(const pb::util::Status& status) {
    const std::string text(status.message());
    const size_t first = text.find('\n');
    if (first == std::string::npos) return text;
    const size_t second = text.find('\n', first + 1);
    const std::string excerpt = text.substr(
        first + 1, second == std::string::npos ? std::string::npos : second - first - 1);
    const std::string caret_line = second == std::string::npos ? "" : text.substr(second + 1);
    const size_t caret = caret_line.find('^');
    std::string line = text.substr(0, first);
    if (caret == std::string::npos) return line;
    const std::string near = caret < excerpt.size() ? excerpt.substr(caret, 40) : "";
    line += near.empty() ? " (at the end of the text)" : " (at " + quotedText(near) + ")";
    return line;
}

// protobuf says "(ghosts[1]) idd: Cannot find field."; this says "ghosts[1].idd: unknown field".
std::string describeStrictFailure(const pb::util::Status& status) {
    const std::string text = statusText(status);
    constexpr std::string_view kUnknown = ": Cannot find field.";
    if (text.size() < kUnknown.size() || text.substr(text.size() - kUnknown.size()) != kUnknown) {
        // "(ghosts[1].fit.frames_fitted): invalid value ..." reads "ghosts[1].fit...: invalid ...".
        if (text.rfind("(", 0) == 0) {
            const size_t close = text.find("):");
            if (close != std::string::npos)
                return text.substr(1, close - 1) + text.substr(close + 1);
        }
        return text;
    }
    std::string field = text.substr(0, text.size() - kUnknown.size());
    if (!field.empty() && field.front() == '(') {
        const size_t close = field.find(") ");
        if (close != std::string::npos)
            field = field.substr(1, close - 1) + "." + field.substr(close + 2);
    }
    return field + ": unknown field (a version " + std::to_string(kModelFormatVersion) +
           " model has no such field; new fields come with a new format_version)";
}

// ---------------------------------------------------------------------------------------------
// Files.

Result<std::string> readWholeFile(const std::string& path, int64_t max_bytes) {
    auto file = openRegularFile(path);
    if (!file) return file.error();
    const FileDescriptor& fd = file->fd;
    if (file->size > max_bytes)
        return makeError(ErrorCode::IoError, path + ": " + std::to_string(file->size) +
                                                 " bytes, more than the limit of " +
                                                 std::to_string(max_bytes));
    std::string bytes(static_cast<size_t>(file->size), '\0');
    size_t done = 0;
    while (done < bytes.size()) {
        const ssize_t got = ::read(fd.get(), bytes.data() + done, bytes.size() - done);
        if (got < 0 && errno == EINTR) continue;
        if (got < 0)
            return makeError(ErrorCode::IoError, path + ": read failed: " + osMessage(errno));
        if (got == 0) break;  // shrank while being read
        done += static_cast<size_t>(got);
    }
    bytes.resize(done);
    return bytes;
}

// Writes `bytes` to `path` so that it holds either its old or its new contents whatever happens.
Status replaceFile(const std::string& path, const std::string& bytes) {
    const std::string temporary = path + ".tmp-" + std::to_string(::getpid());
    const auto fail = [&](const std::string& what, int error) -> Status {
        ::unlink(temporary.c_str());
        return makeError(ErrorCode::IoError, path + ": " + what + ": " + osMessage(error));
    };
    FileDescriptor fd(
        ::open(temporary.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC | O_NOFOLLOW, 0666));
    if (!fd.valid()) {
        // Nothing was created: unlinking `temporary` here could remove another writer's file.
        const int error = errno;
        return makeError(ErrorCode::IoError,
                         path + ": cannot create " + temporary + ": " + osMessage(error));
    }
    size_t done = 0;
    while (done < bytes.size()) {
        const ssize_t wrote = ::write(fd.get(), bytes.data() + done, bytes.size() - done);
        if (wrote < 0 && errno == EINTR) continue;
        if (wrote <= 0) return fail("cannot write " + temporary, wrote < 0 ? errno : EIO);
        done += static_cast<size_t>(wrote);
    }
    if (::fsync(fd.get()) != 0) return fail("cannot flush " + temporary + " to disk", errno);
    if (const int error = fd.close(); error != 0) return fail("cannot close " + temporary, error);
    if (::rename(temporary.c_str(), path.c_str()) != 0)
        return fail("cannot rename " + temporary + " into place", errno);
    // The rename has happened; a failed flush of the directory is not a failed write.
    const fs::path parent = fs::path(path).parent_path();
    FileDescriptor directory(
        ::open(parent.empty() ? "." : parent.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
    if (directory.valid()) ::fsync(directory.get());
    return Ok{};
}

}  // namespace

Status validateModel(const FlareModel& model) {
    return checkModel(model, Checker(ErrorCode::InvalidArgument, "model"));
}

Status writeModel(const std::string& path, const FlareModel& model) {
    if (auto ok = checkModel(model, Checker(ErrorCode::InvalidArgument, path)); !ok) return ok;
    std::string bytes;
    if (!toProto(model).SerializeToString(&bytes))
        return makeError(ErrorCode::Internal, path + ": cannot serialize the model");
    return replaceFile(path, bytes);
}

Result<FlareModel> readModelFromMemory(std::string_view bytes, const std::string& name) {
    if (bytes.size() > static_cast<uint64_t>(kModelMaxFileBytes))
        return makeError(ErrorCode::IoError, name + ": " + std::to_string(bytes.size()) +
                                                 " bytes, more than the limit of " +
                                                 std::to_string(kModelMaxFileBytes));
    v1::FlareModel m;
    if (!m.ParseFromArray(bytes.data(), static_cast<int>(bytes.size())))
        return makeError(ErrorCode::ParseError,
                         name +
                             ": not a flare model (binary protobuf that does not parse as "
                             "flarelab.v1.FlareModel; truncated or another kind of file?)");
    // The version first: a newer writer's fields should read as "unsupported version", not as
    // "unknown field".
    if (!knownVersion(m.format_version()))
        return unsupportedVersion(name, std::to_string(m.format_version()));
    if (auto unknown = findUnknownFields(m, ""))
        return makeError(ErrorCode::ParseError,
                         name + ": " + *unknown + ": unknown field (a version " +
                             std::to_string(kModelFormatVersion) +
                             " model has no such field; new fields come with a new "
                             "format_version)");
    return fromCheckedProto(m, name);
}

Result<FlareModel> readModel(const std::string& path) {
    auto bytes = readWholeFile(path, kModelMaxFileBytes);
    if (!bytes) return bytes.error();
    return readModelFromMemory(*bytes, path);
}

Result<std::string> modelToJson(const FlareModel& model) {
    if (auto ok = validateModel(model); !ok) return ok.error();
    pb::util::JsonPrintOptions options;
    options.add_whitespace = true;
    options.always_print_primitive_fields = true;
    options.preserve_proto_field_names = true;
    std::string json;
    if (auto status = pb::util::MessageToJsonString(toProto(model), &json, options); !status.ok())
        return makeError(ErrorCode::Internal, "cannot print the model: " + statusText(status));
    return json;
}

Result<FlareModel> modelFromJson(std::string_view json, const std::string& name) {
    if (json.size() > static_cast<uint64_t>(kModelMaxFileBytes))
        return makeError(ErrorCode::IoError, name + ": " + std::to_string(json.size()) +
                                                 " bytes, more than the limit of " +
                                                 std::to_string(kModelMaxFileBytes));
    // format_version before the strict parse, as for binary files.
    pb::Struct loose;
    pb::util::JsonParseOptions options;
    options.ignore_unknown_fields = false;
    const pb::StringPiece text(json.data(), json.size());
    if (auto status = pb::util::JsonStringToMessage(text, &loose, options); !status.ok())
        return makeError(ErrorCode::ParseError,
                         name + ": not a valid JSON object: " + statusText(status));
    const auto& fields = loose.fields();
    auto version = fields.find("format_version");
    if (version == fields.end()) version = fields.find("formatVersion");
    if (version == fields.end())
        return makeError(ErrorCode::ParseError, name + ": format_version: missing");
    const pb::Value& value = version->second;
    // protobuf JSON allows integers as numbers or as strings ("1").
    bool known = false;
    for (int v = kModelOldestFormatVersion; v <= kModelFormatVersion; ++v)
        known = known ||
                (value.kind_case() == pb::Value::kNumberValue && value.number_value() == v) ||
                (value.kind_case() == pb::Value::kStringValue &&
                 value.string_value() == std::to_string(v));
    if (!known) {
        std::string shown = "a value that is not a number";
        if (value.kind_case() == pb::Value::kNumberValue)
            shown = formatDouble(value.number_value());
        if (value.kind_case() == pb::Value::kStringValue) shown = quotedText(value.string_value());
        return unsupportedVersion(name, shown);
    }
    v1::FlareModel m;
    if (auto status = pb::util::JsonStringToMessage(text, &m, options); !status.ok())
        return makeError(ErrorCode::ParseError, name + ": " + describeStrictFailure(status));
    return fromCheckedProto(m, name);
}

namespace {

// "0.001 0.01 0.1"
std::string joined(const std::vector<double>& values) {
    std::ostringstream out;
    for (size_t i = 0; i < values.size(); ++i) out << (i ? " " : "") << values[i];
    return out.str();
}

std::string orNotDescribed(const std::string& text) {
    return text.empty() ? "(not described)" : text;
}

// "mm, bounds -18..18, 2 pieces over -2..3 deg, degrees 1 3, residual rms <= 0.5, max 1.5"
void printParameter(const ModelParameter& p, std::ostringstream& out) {
    out << "    " << p.name << " [" << (p.unit.empty() ? "-" : p.unit) << "]";
    if (p.lower_bound || p.upper_bound) {
        out << ", bounds ";
        if (p.lower_bound)
            out << *p.lower_bound;
        else
            out << "-inf";
        out << "..";
        if (p.upper_bound)
            out << *p.upper_bound;
        else
            out << "inf";
    }
    out << ": " << p.pieces.size() << (p.pieces.size() == 1 ? " piece" : " pieces") << ", degree"
        << (p.pieces.size() == 1 ? " " : "s ");
    double rms = 0.0;
    double max = 0.0;
    for (size_t i = 0; i < p.pieces.size(); ++i) {
        const ModelPiece& piece = p.pieces[i];
        out << (i ? " " : "") << piece.coefficients.size() - 1;
        rms = std::max(rms, piece.residual_rms);
        max = std::max(max, piece.residual_max);
    }
    out << ", residual rms " << (p.pieces.size() == 1 ? "" : "<= ") << rms << ", max " << max
        << "\n";
}

}  // namespace

std::string describeModel(const FlareModel& m, const std::string& path) {
    std::ostringstream out;
    out << "model " << path << " (format " << m.format_version;
    if (!m.software_version.empty()) out << ", written by " << m.software_version;
    if (!m.created_utc.empty()) out << ", created " << m.created_utc;
    out << ")\n";

    const ModelLens& lens = m.lens;
    out << "lens: " << orNotDescribed(lens.description);
    if (lens.focal_length_mm) out << ", " << *lens.focal_length_mm << " mm";
    if (lens.f_number) out << ", f/" << *lens.f_number;
    out << ", sensor " << lens.sensor_width_mm << " x " << lens.sensor_height_mm << " mm\n";
    out << "prescription: "
        << (lens.prescription_file.empty() ? std::string("none") : lens.prescription_file);
    if (!lens.prescription_sha256.empty()) out << " (sha256 " << lens.prescription_sha256 << ")";
    out << "\n";
    // Version 2's settings, those the model records.
    std::vector<std::string> settings;
    if (lens.aperture_blades)
        settings.push_back(*lens.aperture_blades == 0
                               ? std::string("circular stop")
                               : std::to_string(*lens.aperture_blades) + " blades");
    std::ostringstream number;
    if (lens.blade_rotation_deg) {
        number << "blades rotated " << *lens.blade_rotation_deg << " deg";
        settings.push_back(number.str());
    }
    if (lens.stop_semi_aperture_mm) {
        number.str("");
        number << "stop semi-aperture " << *lens.stop_semi_aperture_mm << " mm";
        settings.push_back(number.str());
    }
    if (lens.coat_unspecified_surfaces)
        settings.push_back(*lens.coat_unspecified_surfaces ? "unspecified surfaces coated"
                                                           : "unspecified surfaces bare");
    for (size_t i = 0; i < settings.size(); ++i)
        out << (i ? ", " : "aperture: ") << settings[i] << (i + 1 == settings.size() ? "\n" : "");

    const ModelCapture& c = m.capture;
    out << "capture: " << c.from_deg << " to " << c.to_deg << " deg in steps of " << c.step_deg
        << " deg, roll " << c.roll_deg << " deg, " << c.width_px << "x" << c.height_px
        << " pixels, camera " << orNotDescribed(c.camera) << ", "
        << (c.raw_format.empty() ? std::string("raw format not recorded")
                                 : "raw format " + c.raw_format)
        << "\n";
    out << "light power: "
        << (c.light_power_dn_s ? formatDouble(*c.light_power_dn_s) + " DN/s"
                               : std::string("not measured"))
        << "\n";
    out << "light's disc: ";
    if (c.light_discs.empty()) {
        out << "not recorded";
    } else {
        double lo = std::numeric_limits<double>::infinity(), hi = 0.0;
        size_t lit = 0;
        for (const ModelLightDisc& d : c.light_discs) {
            if (!(d.radius_px > 0.0)) continue;
            ++lit;
            lo = std::min(lo, d.radius_px);
            hi = std::max(hi, d.radius_px);
        }
        out << "left out in " << lit << " of " << c.light_discs.size() << " fitted frames";
        if (lit > 0) out << ", radius " << formatDouble(lo) << " to " << formatDouble(hi) << " px";
    }
    out << "\n";
    out << "brackets: ";
    if (c.exposure_times_s.empty())
        out << "none";
    else
        out << c.exposure_times_s.size() << " exposures of " << joined(c.exposure_times_s) << " s";
    out << "\n";
    out << "valid range: " << m.valid_from_deg << " to " << m.valid_to_deg << " deg\n";

    out << "ghosts: " << m.ghosts.size() << "\n";
    for (const ModelGhost& g : m.ghosts) {
        out << "  ghost " << g.id;
        if (!g.name.empty()) out << " (" << g.name << ")";
        const ModelPiece& first = g.parameters.front().pieces.front();
        const ModelPiece& last = g.parameters.front().pieces.back();
        out << ": " << first.angle_from_deg << " to " << last.angle_to_deg << " deg, "
            << g.fit.frames_fitted << " frames fitted (" << g.fit.first_angle_deg << " to "
            << g.fit.last_angle_deg << " deg), " << g.parameters.size()
            << (g.parameters.size() == 1 ? " parameter" : " parameters") << "\n";
        for (const ModelParameter& p : g.parameters) printParameter(p, out);
    }
    return out.str();
}

}  // namespace flarelab::fit
