#include "optics/prescription.h"

#include <array>
#include <charconv>
#include <cmath>
#include <fstream>
#include <sstream>

namespace flarelab::optics {
namespace {

constexpr std::array<std::string_view, 7> kColumns = {
    "kind", "radius_mm", "thickness_mm", "ior_d", "abbe", "semi_aperture_mm",
    "coating_wavelength_nm"};

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
        const std::string_view raw =
            line.substr(start, comma == std::string_view::npos ? std::string_view::npos
                                                               : comma - start);
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

// A finite decimal number and nothing else ("1e3" and "-0.5" pass; "nan", "1.2mm", "" do not).
std::optional<double> parseNumber(std::string_view text) {
    if (text.empty()) return std::nullopt;
    if (text.front() == '+') text.remove_prefix(1);
    double value = 0.0;
    const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
    if (ec != std::errc() || end != text.data() + text.size() || !std::isfinite(value))
        return std::nullopt;
    return value;
}

void parseMetadataComment(std::string_view comment, std::map<std::string, std::string>& metadata) {
    // "# key: value" or "# key1: value1 ; key2: value2". Keys are identifiers; anything else in
    // a comment is prose and ignored.
    size_t start = 0;
    while (start <= comment.size()) {
        size_t semi = comment.find(';', start);
        const std::string_view part =
            trim(comment.substr(start, semi == std::string_view::npos ? std::string_view::npos
                                                                      : semi - start));
        const size_t colon = part.find(':');
        if (colon != std::string_view::npos && colon > 0) {
            const std::string_view key = trim(part.substr(0, colon));
            bool identifier = !key.empty();
            for (char c : key)
                identifier = identifier && (std::isalnum(static_cast<unsigned char>(c)) ||
                                            c == '_');
            if (identifier && !metadata.count(std::string(key)))
                metadata[std::string(key)] = std::string(trim(part.substr(colon + 1)));
        }
        if (semi == std::string_view::npos) break;
        start = semi + 1;
    }
}

}  // namespace

std::optional<double> Prescription::metadataNumber(const std::string& key) const {
    const auto it = metadata.find(key);
    if (it == metadata.end()) return std::nullopt;
    const std::string_view value = trim(it->second);
    size_t end = 0;
    while (end < value.size() &&
           (std::isdigit(static_cast<unsigned char>(value[end])) || value[end] == '.' ||
            value[end] == '-' || value[end] == '+' || value[end] == 'e' || value[end] == 'E'))
        ++end;
    return parseNumber(value.substr(0, end));
}

std::optional<std::string> CameraDescription::invalidReason() const {
    const auto bad = [](double v) { return !std::isfinite(v) || v < 0.0; };
    if (bad(focal_length_mm)) return "focal_length_mm must be finite and >= 0 (0: from the lens)";
    if (bad(f_number)) return "f_number must be finite and >= 0 (0: from the lens)";
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
    size_t pos = 0;
    while (pos < text.size()) {
        size_t eol = text.find('\n', pos);
        if (eol == std::string_view::npos) eol = text.size();
        const std::string_view raw_line = text.substr(pos, eol - pos);
        pos = eol + 1;
        ++line_number;
        for (char c : raw_line)
            if (c == '\0')
                return parseError(source, line_number, 1, "NUL byte: not a text file");
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
                    return parseError(source, line_number, fields[f].column,
                                      "column '" + std::string(fields[f].text) +
                                          "' appears twice in header");
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
            return parseError(source, line_number, 1, msg.str());
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
            return parseError(source, line_number, kind.column,
                              "kind must be 'surface' or 'stop', not '" + std::string(kind.text) +
                                  "'");
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
            const std::optional<double> value = parseNumber(f.text);
            if (!value)
                return parseError(source, line_number, f.column,
                                  std::string(kColumns[col.index]) + " '" + std::string(f.text) +
                                      "' is not a finite number");
            *col.target = *value;
        }
        const auto at = [&](size_t k) { return field(k).column; };
        if (surface.thickness_mm < 0.0)
            return parseError(source, line_number, at(2), "negative thickness_mm");
        if (surface.ior_d < 1.0)
            return parseError(source, line_number, at(3), "ior_d below 1");
        if (surface.ior_d > 4.0)
            return parseError(source, line_number, at(3),
                              "ior_d above 4 is not an optical glass");
        if (surface.semi_aperture_mm <= 0.0)
            return parseError(source, line_number, at(5), "semi_aperture_mm must be positive");
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
            const double before =
                lens.surfaces.empty() ? 1.0 : lens.surfaces.back().ior_d;
            if (surface.ior_d != before)
                return parseError(source, line_number, at(3),
                                  "the stop cannot change the medium: ior_d must equal the "
                                  "medium before it");
            first_stop_line = line_number;
            lens.stop_index = static_cast<int>(lens.surfaces.size());
        }
        lens.surfaces.push_back(surface);
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
        return parseError(source, lens.surfaces.back().line, 1,
                          "the last row's thickness_mm (distance to the image plane) must be "
                          "positive");
    if (lens.surfaces.size() > 512)
        return parseError(source, line_number, 1, "more than 512 surfaces");
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
