#include "predict/detail/json_document.h"

#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <new>
#include <utility>

#include "common/file_descriptor.h"
#include "common/utf8.h"

namespace flarelab::predict::detail {

using nlohmann::json;

std::string number(double value) {
    char text[32];
    std::snprintf(text, sizeof text, "%.15g", value);
    if (std::strtod(text, nullptr) != value) std::snprintf(text, sizeof text, "%.17g", value);
    return text;
}

size_t utf8SequenceLength(unsigned char lead) {
    if (lead >= 0xF0 && lead < 0xF8) return 4;
    if (lead >= 0xE0) return lead < 0xF0 ? 3 : 1;
    if (lead >= 0xC0) return 2;
    return 1;
}

bool controlAt(std::string_view text, size_t i) {
    const auto c = static_cast<unsigned char>(text[i]);
    if (c < 0x20 || c == 0x7F) return true;
    return c == 0xC2 && i + 1 < text.size() && static_cast<unsigned char>(text[i + 1]) >= 0x80 &&
           static_cast<unsigned char>(text[i + 1]) <= 0x9F;
}

std::string quotedText(std::string_view text, size_t max_characters) {
    std::string out = "\"";
    size_t characters = 0;
    for (size_t i = 0; i < text.size(); ++characters) {
        if (characters == max_characters) {
            out += "...";
            break;
        }
        const auto c = static_cast<unsigned char>(text[i]);
        const size_t length = utf8SequenceLength(c);
        char escaped[16];
        if (controlAt(text, i)) {
            const unsigned code = c < 0x80 ? c : static_cast<unsigned char>(text[i + 1]);
            std::snprintf(escaped, sizeof escaped, "\\u%04X", code);
            out += escaped;
            i += c < 0x80 ? 1 : 2;
        } else if (c == '"' || c == '\\') {
            out += '\\';
            out += static_cast<char>(c);
            ++i;
        } else if (c < 0x80) {
            out += static_cast<char>(c);
            ++i;
        } else if (length > 1 && i + length <= text.size() && validUtf8(text.substr(i, length))) {
            out.append(text.substr(i, length));
            i += length;
        } else {
            std::snprintf(escaped, sizeof escaped, "\\x%02X", c);
            out += escaped;
            ++i;
        }
    }
    out += '"';
    return out;
}

std::string indexed(const std::string& path, size_t i) {
    return path + "[" + std::to_string(i) + "]";
}

std::string typeOf(const json& value, bool show_numbers) {
    switch (value.type()) {
        case json::value_t::null:
            return "null";
        case json::value_t::object:
            return "an object";
        case json::value_t::array:
            return "an array";
        case json::value_t::string:
            return "a string";
        case json::value_t::boolean:
            return value.get<bool>() ? "true" : "false";
        case json::value_t::number_integer:
        case json::value_t::number_unsigned:
            return show_numbers ? value.dump() : "a number";
        case json::value_t::number_float:
            return show_numbers ? number(value.get<double>()) : "a number";
        default:
            return "a value of no JSON type";
    }
}

Result<std::string> readSmallFile(const std::string& path,
                                  int64_t max_bytes,
                                  const std::string& what) {
    auto file = openRegularFile(path);
    if (!file) return file.error();
    if (file->size > max_bytes)
        return makeError(ErrorCode::ParseError, path + ": " + std::to_string(file->size) +
                                                    " bytes, more than " + what + " may hold (" +
                                                    std::to_string(max_bytes) + ")");
    std::string text;
    try {
        // One byte more than the size: a file that grew while being read is read to the limit
        // and refused rather than cut short.
        text.resize(static_cast<size_t>(file->size) + 1);
    } catch (const std::bad_alloc&) {
        return makeError(ErrorCode::IoError, path + ": out of memory reading it");
    }
    size_t done = 0;
    while (done < text.size()) {
        const ssize_t got = ::read(file->fd.get(), text.data() + done, text.size() - done);
        if (got < 0 && errno == EINTR) continue;
        if (got < 0)
            return makeError(ErrorCode::IoError, path + ": cannot read: " + osMessage(errno));
        if (got == 0) break;
        done += static_cast<size_t>(got);
    }
    if (done > static_cast<size_t>(file->size))
        return makeError(ErrorCode::IoError, path + ": grew while it was read");
    text.resize(done);
    return text;
}

bool JsonDocumentBuilder::null() { return add(json(nullptr)); }
bool JsonDocumentBuilder::boolean(bool value) { return add(json(value)); }
bool JsonDocumentBuilder::number_integer(number_integer_t value) { return add(json(value)); }
bool JsonDocumentBuilder::number_unsigned(number_unsigned_t value) { return add(json(value)); }
bool JsonDocumentBuilder::number_float(number_float_t value, const string_t&) {
    return add(json(value));
}
bool JsonDocumentBuilder::string(string_t& value) { return add(json(std::move(value))); }
bool JsonDocumentBuilder::binary(binary_t&) {
    error = "not valid JSON: binary data";  // only the binary formats produce this
    return false;
}
bool JsonDocumentBuilder::start_object(std::size_t) { return open(json::object()); }
bool JsonDocumentBuilder::key(string_t& key) {
    if (open_.back().value->contains(key)) {
        error_path = pathOf(open_.size());
        error = "the field " + quotedText(key) + " is given twice";
        return false;
    }
    key_ = std::move(key);
    return true;
}
bool JsonDocumentBuilder::end_object() {
    open_.pop_back();
    return true;
}
bool JsonDocumentBuilder::start_array(std::size_t) { return open(json::array()); }
bool JsonDocumentBuilder::end_array() {
    open_.pop_back();
    return true;
}
bool JsonDocumentBuilder::parse_error(std::size_t position,
                                      const std::string&,
                                      const nlohmann::json::exception& e) {
    std::string what = e.what();
    // "[json.exception.parse_error.101] parse error at line 1, column 3: ...": the bracket
    // names nlohmann's exception class, which means nothing to whoever wrote the file.
    if (!what.empty() && what.front() == '[') {
        const size_t end = what.find("] ");
        if (end != std::string::npos) what.erase(0, end + 2);
    }
    // The number overflow ("1e999") comes without a position.
    if (what.find("line ") == std::string::npos) what += " at byte " + std::to_string(position);
    // The token nlohmann quotes may hold bytes that are not UTF-8.
    if (!validUtf8(what))
        for (char& c : what)
            if (static_cast<unsigned char>(c) >= 0x80) c = '?';
    error_path.clear();
    error = "not valid JSON: " + what;
    return false;
}

// The part of a path that leads to the next value of the innermost open container.
std::string JsonDocumentBuilder::childSegment() const {
    if (open_.empty()) return "";
    const json& parent = *open_.back().value;
    if (parent.is_array()) return "[" + std::to_string(parent.size()) + "]";
    // A key shown as it is unless it is long or strange.
    bool plain = !key_.empty() && key_.size() <= 64;
    for (size_t i = 0; plain && i < key_.size(); ++i)
        plain = !controlAt(key_, i) && key_[i] != '"' && key_[i] != '.' && key_[i] != '[';
    return "." + (plain ? key_ : quotedText(key_));
}

// The path of the `depth` outermost open containers.
std::string JsonDocumentBuilder::pathOf(size_t depth) const {
    std::string path;
    for (size_t i = 0; i < depth; ++i) path += open_[i].segment;
    return path.empty() || path.front() != '.' ? path : path.substr(1);
}

// Where the value went, which stays put until its container is closed: an array's elements only
// move when the array grows, and an open container's parent does not grow.
json* JsonDocumentBuilder::put(json&& value) {
    if (open_.empty()) {
        document = std::move(value);
        return &document;
    }
    json& parent = *open_.back().value;
    if (parent.is_array()) {
        auto& elements = *parent.get_ptr<json::array_t*>();
        elements.push_back(std::move(value));
        return &elements.back();
    }
    auto& members = *parent.get_ptr<json::object_t*>();
    return &members.emplace(key_, std::move(value)).first->second;
}

bool JsonDocumentBuilder::add(json&& value) {
    put(std::move(value));
    return true;
}

bool JsonDocumentBuilder::open(json&& container) {
    if (open_.size() >= max_depth_) {
        error_path = pathOf(open_.size()) + childSegment();
        if (!error_path.empty() && error_path.front() == '.') error_path.erase(0, 1);
        error = "nested more than " + std::to_string(max_depth_) + " levels deep" + depth_hint_;
        return false;
    }
    std::string segment = childSegment();
    json* value = put(std::move(container));
    open_.push_back(Open{value, std::move(segment)});
    return true;
}

}  // namespace flarelab::predict::detail
