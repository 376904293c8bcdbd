#include "optics/prescription.h"

#include <array>
#include <charconv>
#include <cmath>
#include <fstream>
#include <sstream>

namespace flarelab::optics {
namespace {

constexpr size_t kMaxSurfaces = 512;

// Lengths beyond any lens ever built, by many orders of magnitude either way. They keep each
// value the optics derives from one row finite: the vertex positions sum at most 512 gaps of 1e6,
// and since semi_aperture_mm <= |radius_mm|, no curvature exceeds 1e6 per mm, nor does a stop
// underflow to zero. Radii get no upper bound: a huge radius (often written for "flat") is
// harmless.
constexpr double kMinLength_mm = 1e-6;
constexpr double kMaxLength_mm = 1e6;

constexpr std::array<std::string_view, 7> kColumns = {
    "kind", "radius_mm",        "thickness_mm",         "ior_d",
    "abbe", "semi_aperture_mm", "coating_wavelength_nm"};

std::string_view trim(std::string_view s) {
    const auto is_space = [](char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\n'; };
    while (!s.empty() && is_space(s.front())) s.remove_prefix(1);
    while (!s.empty() && is_space(s.back())) s.remove_suffix(1);
    return s;
}

struct Field {
    std::string_view text;  // trimmed
    int column = 1;         // 1-based column of the field's first character in the line
};

std::vector<Field> splitFields(std::string_view line) {
    std::vector<Field> fields;
    size_t start = 0;
    while (true) {
        const size_t comma = line.find(',', start);
        const std::string_view raw = line.substr(
            start, comma == std::string_view::npos ? std::string_view::npos : comma - start);
        size_t lead = 0;
        while (lead < raw.size() && (raw[lead] == ' ' || raw[lead] == '\t')) ++lead;
        fields.push_back(Field{trim(raw), static_cast<int>(start + lead) + 1});
        if (comma == std::string_view::npos) break;
        start = comma + 1;
    }
    return fields;
}

Error parseError(const std::string& source, int line, int column, const std::string& message) {
    std::ostringstream out;
    out << source << ":" << line << ":" << column << ": " << message;
    return makeError(ErrorCode::ParseError, out.str());
}

enum class NumberFault { None, NotANumber, OutOfRange };

struct ParsedNumber {
    double value = 0.0;
    NumberFault fault = NumberFault::None;
};

// A finite decimal number and nothing else ("1e3", "+2" and "-0.5" pass; "nan", "1.2mm", "+-1",
// "" do not). from_chars takes no '+', so one is stripped here, and only one: after it a second
// sign would be read by from_chars as the number's own.
ParsedNumber parseNumber(std::string_view text) {
    if (!text.empty() && text.front() == '+') {
        text.remove_prefix(1);
        if (!text.empty() && (text.front() == '-' || text.front() == '+'))
            return {0.0, NumberFault::NotANumber};
    }
    if (text.empty()) return {0.0, NumberFault::NotANumber};
    double value = 0.0;
    const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
    if (end != text.data() + text.size()) return {0.0, NumberFault::NotANumber};
    if (ec == std::errc::result_out_of_range) return {0.0, NumberFault::OutOfRange};
    if (ec != std::errc() || !std::isfinite(value)) return {0.0, NumberFault::NotANumber};
    return {value, NumberFault::None};
}

// The identifier before the first colon of `part`, or empty when `part` does not start "key:".
std::string_view leadingKey(std::string_view part) {
    const size_t colon = part.find(':');
    if (colon == std::string_view::npos || colon == 0) return {};
    const std::string_view key = trim(part.substr(0, colon));
    for (char c : key)
        if (!std::isalnum(static_cast<unsigned char>(c)) && c != '_') return {};
    return key;
}

void parseMetadataComment(std::string_view comment, std::map<std::string, std::string>& metadata) {
    // "# key: value" or "# key1: value1 ; key2: value2". Keys are identifiers; anything else in
    // a comment is prose and ignored. A ';' separates pairs only where another "key:" follows,
    // so a value may hold semicolons of its own ("name: a toy; not a patent").
    comment = trim(comment);
    const std::string_view first = leadingKey(comment);
    if (first.empty()) return;
    size_t value_start = comment.find(':') + 1;
    std::string key(first);
    size_t search = value_start;
    while (true) {
        size_t semi = comment.find(';', search);
        while (semi != std::string_view::npos && leadingKey(trim(comment.substr(semi + 1))).empty())
            semi = comment.find(';', semi + 1);
        const std::string_view value =
            trim(comment.substr(value_start, semi == std::string_view::npos ? std::string_view::npos
                                                                            : semi - value_start));
        if (!metadata.count(key)) metadata[key] = std::string(value);
        if (semi == std::string_view::npos) break;
        const std::string_view rest = trim(comment.substr(semi + 1));
        key = std::string(leadingKey(rest));
        value_start = comment.size() - rest.size() + rest.find(':') + 1;
        search = value_start;
    }
}

}  // namespace

std::optional<double> Prescription::metadataNumber(const std::string& key) const {
    const auto it = metadata.find(key);
    if (it == metadata.end()) return std::nullopt;
    std::string_view value = trim(it->second);
    if (!value.empty() && value.front() == '+') value.remove_prefix(1);
    // from_chars stops where the number ends, which is what "leading" asks for: "28-75" gives 28
    // and "1e" gives 1, where scanning number-like characters first would give nothing.
    double number = 0.0;
    const auto [end, ec] = std::from_chars(value.data(), value.data() + value.size(), number);
    if (ec != std::errc() || end == value.data() || !std::isfinite(number)) return std::nullopt;
    return number;
}

std::optional<std::string> CameraDescription::invalidReason() const {
    const auto bad = [](double v) { return !std::isfinite(v) || v < 0.0; };
    if (bad(focal_length_mm) || focal_length_mm > 1e6 ||
        (focal_length_mm > 0.0 && focal_length_mm < 0.01))
        return "focal_length_mm must lie in 0.01..1e6 (0: from the lens)";
    if (bad(f_number) || f_number > 1e4) return "f_number must lie in 0.5..1e4 (0: from the lens)";
    if (f_number > 0.0 && f_number < 0.5) return "f_number below 0.5 is not a real lens";
    if (!std::isfinite(sensor_width_mm) || sensor_width_mm <= 0.0)
        return "sensor_width_mm must be positive";
    if (!std::isfinite(sensor_height_mm) || sensor_height_mm <= 0.0)
        return "sensor_height_mm must be positive";
    if (aperture_blades != 0 && (aperture_blades < 3 || aperture_blades > 64))
        return "aperture_blades must be 0 (circle) or 3..64";
    if (!std::isfinite(aperture_rotation_deg)) return "aperture_rotation_deg must be finite";
    if (!std::isfinite(default_coating_wavelength_nm) || default_coating_wavelength_nm < 100.0 ||
        default_coating_wavelength_nm > 5000.0)
        return "default_coating_wavelength_nm must lie in 100..5000 nm";
    return std::nullopt;
}

Result<Prescription> parsePrescription(std::string_view text, const std::string& source) {
    Prescription lens;
    lens.source = source;
    if (text.size() >= 3 && static_cast<unsigned char>(text[0]) == 0xEF &&
        static_cast<unsigned char>(text[1]) == 0xBB && static_cast<unsigned char>(text[2]) == 0xBF)
        text.remove_prefix(3);  // UTF-8 byte order mark

    std::array<int, kColumns.size()> column_of{};  // header position of each known column
    bool have_header = false;
    int header_line = 0;
    size_t header_width = 0;
    int line_number = 0;
    int first_stop_line = 0;
    int last_thickness_column = 1;  // where the last row's thickness_mm stands, for its check
    size_t pos = 0;
    while (pos < text.size()) {
        size_t eol = text.find('\n', pos);
        if (eol == std::string_view::npos) eol = text.size();
        const std::string_view raw_line = text.substr(pos, eol - pos);
        pos = eol + 1;
        ++line_number;
        if (const size_t nul = raw_line.find('\0'); nul != std::string_view::npos)
            return parseError(source, line_number, static_cast<int>(nul) + 1,
                              "NUL byte: not a text file");
        const std::string_view line = trim(raw_line);
        if (line.empty()) continue;
        if (line.front() == '#') {
            parseMetadataComment(line.substr(1), lens.metadata);
            continue;
        }
        const std::vector<Field> fields = splitFields(raw_line);
        if (!have_header) {
            column_of.fill(-1);
            for (size_t f = 0; f < fields.size(); ++f) {
                size_t known = 0;
                while (known < kColumns.size() && kColumns[known] != fields[f].text) ++known;
                if (known == kColumns.size())
                    return parseError(source, line_number, fields[f].column,
                                      "unknown column '" + std::string(fields[f].text) +
                                          "' in header (expected kind,radius_mm,thickness_mm,"
                                          "ior_d,abbe,semi_aperture_mm,coating_wavelength_nm)");
                if (column_of[known] >= 0)
                    return parseError(
                        source, line_number, fields[f].column,
                        "column '" + std::string(fields[f].text) + "' appears twice in header");
                column_of[known] = static_cast<int>(f);
            }
            for (size_t k = 0; k < kColumns.size(); ++k)
                if (column_of[k] < 0)
                    return parseError(source, line_number, 1,
                                      "header lacks column '" + std::string(kColumns[k]) + "'");
            have_header = true;
            header_line = line_number;
            header_width = fields.size();
            continue;
        }
        if (fields.size() != header_width) {
            std::ostringstream msg;
            msg << "row has " << fields.size() << " fields, header (line " << header_line
                << ") has " << header_width;
            // Point at the first field too many, or just past the last one when fields are
            // missing.
            const int column =
                fields.size() > header_width
                    ? fields[header_width].column
                    : fields.back().column + static_cast<int>(fields.back().text.size());
            return parseError(source, line_number, column, msg.str());
        }
        const auto field = [&](size_t k) -> const Field& { return fields[column_of[k]]; };
        Surface surface;
        surface.line = line_number;

        const Field& kind = field(0);
        if (kind.text == "surface") {
            surface.kind = SurfaceKind::Refracting;
        } else if (kind.text == "stop") {
            surface.kind = SurfaceKind::Stop;
        } else {
            return parseError(
                source, line_number, kind.column,
                "kind must be 'surface' or 'stop', not '" + std::string(kind.text) + "'");
        }

        // Numeric fields: name, where to store, whether it may be empty.
        struct NumericColumn {
            size_t index;
            double* target;
            bool optional;
        };
        const std::array<NumericColumn, 6> numeric = {{
            {1, &surface.radius_mm, false},
            {2, &surface.thickness_mm, false},
            {3, &surface.ior_d, false},
            {4, &surface.abbe, true},
            {5, &surface.semi_aperture_mm, false},
            {6, &surface.coating_wavelength_nm, true},
        }};
        for (const NumericColumn& col : numeric) {
            const Field& f = field(col.index);
            if (f.text.empty()) {
                if (col.optional) {
                    *col.target = 0.0;
                    continue;
                }
                return parseError(source, line_number, f.column,
                                  std::string(kColumns[col.index]) + " is empty");
            }
            const ParsedNumber number = parseNumber(f.text);
            if (number.fault != NumberFault::None)
                return parseError(
                    source, line_number, f.column,
                    std::string(kColumns[col.index]) + " '" + std::string(f.text) +
                        (number.fault == NumberFault::OutOfRange ? "' is out of the range of double"
                                                                 : "' is not a finite number"));
            *col.target = number.value;
        }
        const auto at = [&](size_t k) { return field(k).column; };
        if (surface.thickness_mm < 0.0)
            return parseError(source, line_number, at(2), "negative thickness_mm");
        if (surface.thickness_mm > kMaxLength_mm)
            return parseError(source, line_number, at(2),
                              "thickness_mm above 1e6 (a kilometre) is not a lens");
        if (surface.ior_d < 1.0) return parseError(source, line_number, at(3), "ior_d below 1");
        if (surface.ior_d > 4.0)
            return parseError(source, line_number, at(3), "ior_d above 4 is not an optical glass");
        if (surface.semi_aperture_mm <= 0.0)
            return parseError(source, line_number, at(5), "semi_aperture_mm must be positive");
        if (surface.semi_aperture_mm < kMinLength_mm || surface.semi_aperture_mm > kMaxLength_mm)
            return parseError(source, line_number, at(5),
                              "semi_aperture_mm must lie in 1e-6..1e6 (a nanometre to a "
                              "kilometre)");
        if (surface.radius_mm != 0.0 && surface.semi_aperture_mm > std::abs(surface.radius_mm))
            return parseError(source, line_number, at(5),
                              "semi_aperture_mm exceeds |radius_mm|: no spherical cap is that "
                              "wide");
        if (surface.ior_d == 1.0) {
            surface.abbe = 0.0;  // air does not disperse, whatever the column says
        } else if (surface.abbe < 0.0 || (surface.abbe > 0.0 && surface.abbe < 5.0)) {
            return parseError(source, line_number, at(4),
                              "abbe must be empty (no dispersion) or at least 5");
        }
        if (surface.coating_wavelength_nm < 0.0 ||
            (surface.coating_wavelength_nm > 0.0 &&
             (surface.coating_wavelength_nm < 100.0 || surface.coating_wavelength_nm > 5000.0)))
            return parseError(source, line_number, at(6),
                              "coating_wavelength_nm must be empty or in 100..5000");
        if (surface.kind == SurfaceKind::Stop) {
            if (first_stop_line != 0) {
                std::ostringstream msg;
                msg << "second aperture stop (the first is on line " << first_stop_line
                    << "); a lens has exactly one";
                return parseError(source, line_number, kind.column, msg.str());
            }
            if (surface.radius_mm != 0.0)
                return parseError(source, line_number, at(1), "the stop must be flat (radius 0)");
            // The tracers do not refract at the stop, so a different glass after it would bend
            // no ray at the d line and still disperse differently at every other wavelength.
            const Surface air;
            const Surface& before = lens.surfaces.empty() ? air : lens.surfaces.back();
            if (surface.ior_d != before.ior_d)
                return parseError(source, line_number, at(3),
                                  "the stop cannot change the medium: ior_d must equal the "
                                  "medium before it");
            if (surface.abbe != before.abbe)
                return parseError(source, line_number, at(4),
                                  "the stop cannot change the medium: abbe must equal the "
                                  "medium before it");
            first_stop_line = line_number;
            lens.stop_index = static_cast<int>(lens.surfaces.size());
        }
        // Checked per row, not after the loop, so a huge input is refused before it is held.
        if (lens.surfaces.size() == kMaxSurfaces) {
            std::ostringstream msg;
            msg << "more than " << kMaxSurfaces << " surfaces";
            return parseError(source, line_number, kind.column, msg.str());
        }
        lens.surfaces.push_back(surface);
        last_thickness_column = at(2);
    }
    if (!have_header)
        return parseError(source, std::max(line_number, 1), 1,
                          "no header line: empty file, or only comments");
    if (lens.surfaces.empty())
        return parseError(source, line_number, 1, "no surface rows after the header");
    if (lens.stop_index < 0)
        return parseError(source, line_number, 1,
                          "no aperture stop: exactly one row must have kind 'stop'");
    if (lens.surfaces.back().thickness_mm <= 0.0)
        return parseError(source, lens.surfaces.back().line, last_thickness_column,
                          "the last row's thickness_mm (distance to the image plane) must be "
                          "positive");
    const auto name = lens.metadata.find("name");
    if (name != lens.metadata.end() && !name->second.empty()) {
        lens.name = name->second;
    } else {
        const size_t slash = source.find_last_of('/');
        std::string stem = source.substr(slash == std::string::npos ? 0 : slash + 1);
        const size_t dot = stem.rfind('.');
        lens.name = dot == std::string::npos ? stem : stem.substr(0, dot);
    }
    return lens;
}

Result<Prescription> loadPrescription(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    if (!in) return makeError(ErrorCode::NotFound, path + ": cannot open lens file");
    std::ostringstream buffer;
    buffer << in.rdbuf();
    if (in.bad()) return makeError(ErrorCode::IoError, path + ": read failed");
    const std::string text = buffer.str();
    if (text.size() > (16u << 20))
        return makeError(ErrorCode::ParseError, path + ": larger than 16 MiB, not a lens file");
    return parsePrescription(text, path);
}

}  // namespace flarelab::optics
