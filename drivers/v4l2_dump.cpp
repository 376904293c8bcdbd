#include "drivers/v4l2_dump.h"

#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <limits>

#include "common/file_descriptor.h"
#include "drivers/v4l2_formats.h"

namespace flarelab::drivers {
namespace {

std::string_view trim(std::string_view s) {
    while (!s.empty() && (s.front() == ' ' || s.front() == '\t')) s.remove_prefix(1);
    while (!s.empty() && (s.back() == ' ' || s.back() == '\t')) s.remove_suffix(1);
    return s;
}

bool startsWith(std::string_view s, std::string_view prefix) {
    return s.substr(0, prefix.size()) == prefix;
}

bool endsWith(std::string_view s, std::string_view suffix) {
    return s.size() >= suffix.size() && s.substr(s.size() - suffix.size()) == suffix;
}

std::vector<std::string> splitList(std::string_view s) {
    std::vector<std::string> out;
    while (!s.empty()) {
        const size_t comma = s.find(',');
        const std::string_view item = trim(s.substr(0, comma));
        if (!item.empty()) out.emplace_back(item);
        if (comma == std::string_view::npos) break;
        s.remove_prefix(comma + 1);
    }
    return out;
}

// A whole decimal or 0x-hexadecimal int64; nullopt for anything else.
std::optional<int64_t> parseInt(std::string_view s) {
    if (s.empty()) return std::nullopt;
    if (startsWith(s, "0x") || startsWith(s, "0X")) {
        uint64_t u = 0;
        const std::string_view digits = s.substr(2);
        const auto [end, ec] = std::from_chars(digits.data(), digits.data() + digits.size(), u, 16);
        if (digits.empty() || ec != std::errc{} || end != digits.data() + digits.size())
            return std::nullopt;
        return static_cast<int64_t>(u);
    }
    int64_t v = 0;
    const auto [end, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
    if (ec != std::errc{} || end != s.data() + s.size()) return std::nullopt;
    return v;
}

std::optional<uint32_t> parseU32(std::string_view s, int base = 10) {
    uint32_t v = 0;
    if (base == 16 && (startsWith(s, "0x") || startsWith(s, "0X"))) s.remove_prefix(2);
    const auto [end, ec] = std::from_chars(s.data(), s.data() + s.size(), v, base);
    if (s.empty() || ec != std::errc{} || end != s.data() + s.size()) return std::nullopt;
    return v;
}

// "640x480" -> (640, 480).
std::optional<std::pair<uint32_t, uint32_t>> parseSize(std::string_view s, char separator = 'x') {
    const size_t x = s.find(separator);
    if (x == std::string_view::npos) return std::nullopt;
    const auto w = parseU32(s.substr(0, x));
    const auto h = parseU32(s.substr(x + 1));
    if (!w || !h) return std::nullopt;
    return std::make_pair(*w, *h);
}

// Types whose "value=" is one integer.
bool numericType(std::string_view type) {
    for (const char* t :
         {"int", "int64", "bool", "menu", "intmenu", "bitmask", "button", "u8", "u16", "u32"})
        if (type == t) return true;
    return false;
}

enum class Section { None, DriverInfo, Format, Streaming, Controls, FormatList, Other };

class Parser {
public:
    Parser(std::string_view text, std::string_view source) : text_(text) {
        dump_.source = std::string(source);
    }

    Result<V4l2DeviceDump> run() {
        size_t start = 0;
        while (start < text_.size()) {
            size_t end = text_.find('\n', start);
            if (end == std::string_view::npos) end = text_.size();
            std::string_view line = text_.substr(start, end - start);
            if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
            ++line_number_;
            if (Status ok = parseLine(line); !ok) return ok.error();
            start = end + 1;
        }
        return std::move(dump_);
    }

private:
    Error bad(const std::string& what) const {
        return makeError(ErrorCode::ParseError,
                         dump_.source + ":" + std::to_string(line_number_) + ": " + what);
    }

    Status parseLine(std::string_view line) {
        if (trim(line).empty()) return Ok{};
        if (line.find('\0') != std::string_view::npos) return bad("holds a NUL byte");
        const bool indented = line.front() == ' ' || line.front() == '\t';
        // Names of 31 characters or more reach column 0 (v4l2-ctl right-aligns them in 31).
        if (section_ == Section::Controls && looksLikeControl(line)) return control(line);
        if (!indented) return heading(line);
        switch (section_) {
            case Section::None:
                return bad("an indented line before any section");
            case Section::Other:
                return Ok{};
            case Section::DriverInfo:
                return driverInfo(line);
            case Section::Format:
                return format(line);
            case Section::Streaming:
                return streaming(line);
            case Section::Controls:
                return menuItem(line);
            case Section::FormatList:
                return formatList(line);
        }
        return Ok{};
    }

    Status heading(std::string_view line) {
        const std::string_view t = trim(line);
        if (startsWith(t, "ioctl: VIDIOC_ENUM_FMT")) {
            section_ = Section::FormatList;
            dump_.has_format_list = true;
            dump_.formats.clear();
            return Ok{};
        }
        const size_t colon = t.find(':');
        if (colon == std::string_view::npos) {
            if (endsWith(t, "Controls")) {
                section_ = Section::Controls;
                class_ = std::string(t);
                return Ok{};
            }
            return bad("'" + std::string(t.substr(0, 60)) +
                       "' is neither a section, a control class nor a control");
        }
        const std::string_view key = trim(t.substr(0, colon));
        const std::string_view rest = trim(t.substr(colon + 1));
        if (!rest.empty()) {
            section_ = Section::Other;  // a one-line entry: "Priority: 2"
            return Ok{};
        }
        if (key == "Driver Info") {
            section_ = Section::DriverInfo;
            dump_.has_driver_info = true;
        } else if (key == "Format Video Capture") {
            section_ = Section::Format;
            dump_.format = V4l2DumpPixFormat{};
        } else if (key == "Streaming Parameters Video Capture") {
            section_ = Section::Streaming;
        } else {
            section_ = Section::Other;
        }
        return Ok{};
    }

    // "\tKey   : value" -> (key, value); nullopt when the line has no colon.
    static std::optional<std::pair<std::string_view, std::string_view>> keyValue(
        std::string_view line) {
        const size_t colon = line.find(':');
        if (colon == std::string_view::npos) return std::nullopt;
        return std::make_pair(trim(line.substr(0, colon)), trim(line.substr(colon + 1)));
    }

    Status driverInfo(std::string_view line) {
        if (startsWith(line, "\t\t")) return Ok{};  // the names of capability bits
        const auto kv = keyValue(line);
        if (!kv) return bad("expected 'key : value' in Driver Info");
        const auto [key, value] = *kv;
        if (key == "Driver name") {
            dump_.driver = std::string(value);
        } else if (key == "Card type") {
            dump_.card = std::string(value);
        } else if (key == "Bus info") {
            dump_.bus_info = std::string(value);
        } else if (key == "Driver version") {
            uint32_t parts[3] = {0, 0, 0};
            std::string_view rest = value;
            for (int i = 0; i < 3; ++i) {
                const size_t dot = rest.find('.');
                const auto part = parseU32(rest.substr(0, dot));
                if (!part || *part > 255 || (i < 2 && dot == std::string_view::npos) ||
                    (i == 2 && dot != std::string_view::npos))
                    return bad("Driver version '" + std::string(value) + "' is not a.b.c");
                parts[i] = *part;
                rest = dot == std::string_view::npos ? std::string_view{} : rest.substr(dot + 1);
            }
            dump_.driver_version = (parts[0] << 16) | (parts[1] << 8) | parts[2];
        } else if (key == "Capabilities" || key == "Device Caps") {
            const auto caps = parseU32(value, 16);
            if (!caps || !startsWith(value, "0x"))
                return bad(std::string(key) + " '" + std::string(value) + "' is not 0x........");
            (key == "Capabilities" ? dump_.capabilities : dump_.device_caps) = *caps;
        }
        return Ok{};
    }

    // "'YUYV' (YUYV 4:2:2)" or "'Y16 -BE' (...)": the fourcc, nullopt when malformed.
    static std::optional<uint32_t> quotedFourcc(std::string_view s, size_t* end) {
        if (s.size() < 6 || s.front() != '\'') return std::nullopt;
        const size_t close = s.find('\'', 5);
        if (close == std::string_view::npos) return std::nullopt;
        const std::string_view inside = s.substr(1, close - 1);
        std::string_view tail = inside.substr(4);
        if (!tail.empty() && tail != "-BE") return std::nullopt;
        uint32_t fourcc = 0;
        for (int i = 0; i < 4; ++i)
            fourcc |= static_cast<uint32_t>(static_cast<unsigned char>(inside[i])) << (8 * i);
        if (!tail.empty()) fourcc |= 1u << 31;
        *end = close + 1;
        return fourcc;
    }

    Status format(std::string_view line) {
        const auto kv = keyValue(line);
        if (!kv) return bad("expected 'key : value' in Format Video Capture");
        const auto [key, value] = *kv;
        V4l2DumpPixFormat& f = *dump_.format;
        if (key == "Width/Height") {
            const auto size = parseSize(value, '/');
            if (!size) return bad("Width/Height '" + std::string(value) + "' is not W/H");
            f.width = size->first;
            f.height = size->second;
        } else if (key == "Pixel Format") {
            size_t end = 0;
            const auto fourcc = quotedFourcc(value, &end);
            if (!fourcc) return bad("Pixel Format '" + std::string(value) + "' has no 'FCC '");
            f.fourcc = *fourcc;
        } else if (key == "Field") {
            f.field = std::string(value);
        } else if (key == "Bytes per Line" || key == "Size Image") {
            const auto n = parseU32(value);
            if (!n) return bad(std::string(key) + " '" + std::string(value) + "' is not a number");
            (key == "Size Image" ? f.size_image : f.bytes_per_line) = *n;
        } else if (key == "Colorspace") {
            f.colorspace = std::string(value);
        }
        return Ok{};
    }

    Status streaming(std::string_view line) {
        const auto kv = keyValue(line);
        if (!kv) return bad("expected 'key : value' in Streaming Parameters");
        const auto [key, value] = *kv;
        if (key != "Frames per second") return Ok{};
        const size_t open = value.find('(');
        const size_t close = value.rfind(')');
        if (open == std::string_view::npos || close == std::string_view::npos || close < open)
            return bad("Frames per second '" + std::string(value) + "' has no (num/den)");
        const auto fraction = parseSize(value.substr(open + 1, close - open - 1), '/');
        if (!fraction) return bad("Frames per second '" + std::string(value) + "' has no num/den");
        // v4l2-ctl prints the frame rate, the inverse of the time per frame.
        if (fraction->first != 0 && fraction->second != 0)
            dump_.time_per_frame = std::make_pair(fraction->second, fraction->first);
        return Ok{};
    }

    static bool looksLikeControl(std::string_view line) {
        const std::string_view t = trim(line);
        const size_t space = t.find(' ');
        if (space == std::string_view::npos || space == 0) return false;
        const std::string_view rest = trim(t.substr(space));
        const size_t id_end = rest.find(' ');
        if (id_end == std::string_view::npos) return false;
        const std::string_view after = trim(rest.substr(id_end));
        // v4l2-ctl prints ids with "%#8.8x": "0x00980900", or "00000000" for 0.
        std::string_view id = rest.substr(0, id_end);
        if (startsWith(id, "0x")) id.remove_prefix(2);
        const bool hex = id.size() == 8 && std::all_of(id.begin(), id.end(), [](char c) {
                             return std::isxdigit(static_cast<unsigned char>(c)) != 0;
                         });
        return hex && !after.empty() && after.front() == '(';
    }

    Status control(std::string_view line) {
        V4l2DumpControl c;
        c.control_class = class_;
        c.line = line_number_;
        std::string_view s = trim(line);
        const size_t space = s.find(' ');
        c.name = std::string(s.substr(0, space));
        s = trim(s.substr(space));
        const size_t id_end = s.find(' ');
        const auto id = parseU32(s.substr(0, id_end), 16);
        if (!id)
            return bad("control '" + c.name + "': id '" + std::string(s.substr(0, id_end)) +
                       "' is not hexadecimal");
        c.id = *id;
        s = trim(s.substr(id_end));
        const size_t type_end = s.find(')');
        if (type_end == std::string_view::npos)
            return bad("control '" + c.name + "': no ')' after its type");
        c.type = std::string(trim(s.substr(1, type_end - 1)));
        s = trim(s.substr(type_end + 1));
        if (s.empty() || s.front() != ':')
            return bad("control '" + c.name + "': no ':' after (type)");
        s = trim(s.substr(1));
        while (!s.empty()) {
            const size_t eq = s.find('=');
            if (eq == std::string_view::npos || eq == 0 || s.substr(0, eq).find(' ') != s.npos)
                return bad("control '" + c.name + "': '" + std::string(s.substr(0, 40)) +
                           "' is not key=value");
            const std::string_view key = s.substr(0, eq);
            s = s.substr(eq + 1);
            if (key == "flags") {
                c.flags = splitList(s);
                break;
            }
            std::string_view value;
            if (!s.empty() && s.front() == '\'') {
                // A string value, quoted; it may hold spaces and quotes, so it ends at the last
                // quote before " flags=" or the end of the line.
                const size_t flags = s.find(" flags=");
                const std::string_view quoted = s.substr(0, flags);
                const size_t close = quoted.rfind('\'');
                if (close == 0) return bad("control '" + c.name + "': unterminated string value");
                value = s.substr(1, close - 1);
                s = s.substr(close + 1);
            } else {
                const size_t end = s.find(' ');
                value = s.substr(0, end);
                s = end == std::string_view::npos ? std::string_view{} : s.substr(end);
            }
            s = trim(s);
            if (!s.empty() && s.front() == '(') {
                // The value's meaning: "(Menu Item 3)", "(5 0x5)"; may nest parentheses.
                int depth = 0;
                size_t i = 0;
                for (; i < s.size(); ++i) {
                    if (s[i] == '(') ++depth;
                    if (s[i] == ')' && --depth == 0) break;
                }
                if (depth != 0) return bad("control '" + c.name + "': unbalanced '('");
                s = trim(s.substr(i + 1));
            }
            if (Status ok = controlField(c, key, value); !ok) return ok;
        }
        dump_.controls.push_back(std::move(c));
        return Ok{};
    }

    Status controlField(V4l2DumpControl& c, std::string_view key, std::string_view value) {
        if (key == "dims") {
            c.array = true;
            c.value.reset();
            return Ok{};
        }
        int64_t* field = nullptr;
        if (key == "min") field = &c.minimum;
        if (key == "max") field = &c.maximum;
        if (key == "step") field = &c.step;
        if (key == "default") field = &c.default_value;
        const bool is_value = key == "value";
        if (!field && !is_value) return Ok{};  // a field of a newer v4l2-ctl
        if (is_value && (!numericType(c.type) || c.array)) return Ok{};
        const auto n = parseInt(value);
        if (!n)
            return bad("control '" + c.name + "': " + std::string(key) + "='" +
                       std::string(value.substr(0, 40)) + "' is not an integer");
        if (field)
            *field = *n;
        else
            c.value = *n;
        return Ok{};
    }

    Status menuItem(std::string_view line) {
        const std::string_view t = trim(line);
        const size_t colon = t.find(':');
        const auto index =
            colon == std::string_view::npos ? std::nullopt : parseInt(t.substr(0, colon));
        if (!index)
            return bad("'" + std::string(t.substr(0, 60)) +
                       "' is neither a control nor a menu item");
        if (dump_.controls.empty() ||
            (dump_.controls.back().type != "menu" && dump_.controls.back().type != "intmenu"))
            return bad("menu item " + std::to_string(*index) + " without a menu control above it");
        dump_.controls.back().menu.emplace_back(*index, std::string(trim(t.substr(colon + 1))));
        return Ok{};
    }

    Status formatList(std::string_view line) {
        const std::string_view t = trim(line);
        if (startsWith(t, "[")) {
            const size_t close = t.find("]:");
            const auto index =
                close == std::string_view::npos ? std::nullopt : parseU32(t.substr(1, close - 1));
            if (!index)
                return bad("format line '" + std::string(t.substr(0, 40)) + "' has no [index]:");
            if (*index != dump_.formats.size())
                return bad("format [" + std::to_string(*index) + "] where [" +
                           std::to_string(dump_.formats.size()) + "] was due");
            V4l2DumpFormat f;
            f.line = line_number_;
            const std::string_view rest = trim(t.substr(close + 2));
            size_t end = 0;
            const auto fourcc = quotedFourcc(rest, &end);
            if (!fourcc) return bad("format [" + std::to_string(*index) + "] has no 'FCC '");
            f.fourcc = *fourcc;
            std::string_view described = trim(rest.substr(end));
            if (!described.empty()) {
                if (described.front() != '(' || described.back() != ')')
                    return bad("format [" + std::to_string(*index) +
                               "]: description not in parentheses");
                std::vector<std::string> parts =
                    splitList(described.substr(1, described.size() - 2));
                if (!parts.empty()) {
                    f.description = parts.front();
                    f.flags.assign(parts.begin() + 1, parts.end());
                }
            }
            dump_.formats.push_back(std::move(f));
            return Ok{};
        }
        if (startsWith(t, "Size:")) {
            if (dump_.formats.empty()) return bad("a Size line before any format");
            return frameSize(trim(t.substr(5)));
        }
        if (startsWith(t, "Interval:")) {
            if (dump_.formats.empty() || dump_.formats.back().sizes.empty())
                return bad("an Interval line before any Size line");
            const std::string_view rest = trim(t.substr(9));
            if (startsWith(rest, "Discrete ")) {
                std::string_view number = rest.substr(9);
                number = number.substr(0, number.find('s'));
                double seconds = 0.0;
                const auto [end, ec] =
                    std::from_chars(number.data(), number.data() + number.size(), seconds);
                if (ec != std::errc{} || end != number.data() + number.size() ||
                    !std::isfinite(seconds) || seconds < 0.0)
                    return bad("Interval '" + std::string(rest.substr(0, 40)) +
                               "' is not 'Discrete N.NNNs'");
                dump_.formats.back().sizes.back().intervals_s.push_back(seconds);
                return Ok{};
            }
            if (startsWith(rest, "Stepwise ") || startsWith(rest, "Continuous ")) return Ok{};
            return bad("Interval '" + std::string(rest.substr(0, 40)) + "' of an unknown kind");
        }
        if (startsWith(t, "Type:")) dump_.format_list_type = std::string(trim(t.substr(5)));
        return Ok{};
    }

    Status frameSize(std::string_view s) {
        V4l2DumpFrameSize size;
        const auto range = [&](std::string_view r) -> Status {
            const size_t dash = r.find(" - ");
            if (dash == std::string_view::npos)
                return bad("Size range '" + std::string(r) + "' has no ' - '");
            const auto lo = parseSize(trim(r.substr(0, dash)));
            std::string_view hi_text = trim(r.substr(dash + 3));
            const size_t with = hi_text.find(" with step ");
            const auto hi = parseSize(trim(hi_text.substr(0, with)));
            if (!lo || !hi) return bad("Size range '" + std::string(r) + "' is not WxH - WxH");
            size.min_width = lo->first;
            size.min_height = lo->second;
            size.max_width = hi->first;
            size.max_height = hi->second;
            if (with != std::string_view::npos) {
                const auto step = parseSize(trim(hi_text.substr(with + 11)), '/');
                if (!step) return bad("Size step in '" + std::string(r) + "' is not W/H");
                size.step_width = step->first;
                size.step_height = step->second;
            }
            return Ok{};
        };
        if (startsWith(s, "Discrete ")) {
            const auto wh = parseSize(trim(s.substr(9)));
            if (!wh) return bad("Size '" + std::string(s) + "' is not 'Discrete WxH'");
            size.width = wh->first;
            size.height = wh->second;
        } else if (startsWith(s, "Stepwise ")) {
            size.kind = V4l2DumpFrameSize::Kind::Stepwise;
            if (Status ok = range(s.substr(9)); !ok) return ok;
        } else if (startsWith(s, "Continuous ")) {
            size.kind = V4l2DumpFrameSize::Kind::Continuous;
            if (Status ok = range(s.substr(11)); !ok) return ok;
        } else {
            return bad("Size '" + std::string(s.substr(0, 40)) + "' of an unknown kind");
        }
        dump_.formats.back().sizes.push_back(std::move(size));
        return Ok{};
    }

    std::string_view text_;
    V4l2DeviceDump dump_;
    Section section_ = Section::None;
    std::string class_;
    int line_number_ = 0;
};

}  // namespace

bool V4l2DumpControl::hasFlag(std::string_view flag) const {
    return std::find(flags.begin(), flags.end(), flag) != flags.end();
}

bool V4l2DumpFormat::hasFlag(std::string_view flag) const {
    return std::find(flags.begin(), flags.end(), flag) != flags.end();
}

const V4l2DumpControl* V4l2DeviceDump::control(uint32_t id) const {
    for (const V4l2DumpControl& c : controls)
        if (c.id == id) return &c;
    return nullptr;
}

const V4l2DumpFormat* V4l2DeviceDump::findFormat(uint32_t fourcc) const {
    for (const V4l2DumpFormat& f : formats)
        if (f.fourcc == fourcc) return &f;
    return nullptr;
}

Result<V4l2DeviceDump> parseV4l2Dump(std::string_view text, std::string_view source) {
    return Parser(text, source).run();
}

Result<V4l2DeviceDump> loadV4l2Dump(const std::string& path) {
    constexpr int64_t kMaxBytes = int64_t{16} << 20;
    auto file = openRegularFile(path);
    if (!file) return file.error();
    if (file->size > kMaxBytes)
        return makeError(ErrorCode::IoError, path + ": larger than 16 MiB; not a v4l2-ctl dump");
    std::string text(static_cast<size_t>(file->size), '\0');
    size_t done = 0;
    while (done < text.size()) {
        const ssize_t got = ::read(file->fd.get(), text.data() + done, text.size() - done);
        if (got < 0 && errno == EINTR) continue;
        if (got < 0)
            return makeError(ErrorCode::IoError, path + ": cannot read: " + osMessage(errno));
        if (got == 0) break;
        done += static_cast<size_t>(got);
    }
    text.resize(done);
    return parseV4l2Dump(text, path);
}

}  // namespace flarelab::drivers
