// ============================================================================
//  flarelab predict (detail): number, utf8SequenceLength, controlAt, quotedText, indexed,
//                             typeOf, readSmallFile, JsonDocumentBuilder
// ============================================================================
//
// What the readers of planners' JSON (scene.cpp, gltf_import.cpp) share: text for error messages
// that a hostile file cannot abuse, and a JSON document built from nlohmann's SAX events.
#pragma once

#include <cstddef>
#include <cstdint>
#include <nlohmann/json.hpp>
#include <string>
#include <string_view>
#include <vector>

#include "common/result.h"

namespace flarelab::predict::detail {

// The shortest of 15 or 17 significant digits that reads back to `value`: "0.1", not
// "0.10000000000000001"; "0.0009", not to_chars' "9e-04".
std::string number(double value);

// The length of the UTF-8 sequence starting with `lead`; 1 for a byte that cannot start one.
size_t utf8SequenceLength(unsigned char lead);

// A C0 or C1 control character or DEL starts at text[i].
bool controlAt(std::string_view text, size_t i);

// `text` in quotes for a message: control characters and bytes that are not UTF-8 escaped, quotes
// and backslashes escaped, and cut after `max_characters`, so a hostile file cannot put a terminal
// sequence or a megabyte into a log line (or invalid UTF-8 into a protobuf reply).
std::string quotedText(std::string_view text, size_t max_characters = 64);

// "path[i]".
std::string indexed(const std::string& path, size_t i);

// What a JSON value is, for "must be ..., got X": "an object", "a string", "true", and for a
// number "a number" or, with `show_numbers`, the number itself.
std::string typeOf(const nlohmann::json& value, bool show_numbers);

// The bytes of the regular file at `path` (common/file_descriptor.h's openRegularFile: no link
// followed, nothing but a regular file read). ParseError when it holds more than `max_bytes`
// ("PATH: N bytes, more than WHAT may hold (MAX)"), IoError when it cannot be read or grows while
// it is read, NotFound when it does not exist.
Result<std::string> readSmallFile(const std::string& path,
                                  int64_t max_bytes,
                                  const std::string& what);

// Builds the document from nlohmann's SAX events rather than json::parse, for what json::parse
// does not give: a key given twice is refused (json::parse keeps the last, so one of two
// "exposure_s" would vanish silently), nesting is bounded, and bad input throws nothing: the
// error, with its position, comes back as data. Use: json::sax_parse(begin, end, &builder), then
// `error` (empty for a well-formed text) at `error_path` ("" for the whole document).
class JsonDocumentBuilder final : public nlohmann::json::json_sax_t {
public:
    // `max_depth`: containers open at once; `depth_hint` follows the error ("; a scene is ...").
    explicit JsonDocumentBuilder(size_t max_depth, std::string depth_hint = "")
        : max_depth_(max_depth), depth_hint_(std::move(depth_hint)) {}

    nlohmann::json document;
    std::string error_path;
    std::string error;

    bool null() override;
    bool boolean(bool value) override;
    bool number_integer(number_integer_t value) override;
    bool number_unsigned(number_unsigned_t value) override;
    bool number_float(number_float_t value, const string_t&) override;
    bool string(string_t& value) override;
    bool binary(binary_t&) override;
    bool start_object(std::size_t) override;
    bool key(string_t& key) override;
    bool end_object() override;
    bool start_array(std::size_t) override;
    bool end_array() override;
    bool parse_error(std::size_t position,
                     const std::string&,
                     const nlohmann::json::exception& e) override;

private:
    // An open container and how its path goes on from its parent's: ".key" or "[index]". Each
    // keeps its own part only, and whole paths are put together for an error: a copy of the
    // parent's path in every container would cost time and memory quadratic in a long key.
    struct Open {
        nlohmann::json* value;
        std::string segment;
    };

    std::string childSegment() const;
    std::string pathOf(size_t depth) const;
    nlohmann::json* put(nlohmann::json&& value);
    bool add(nlohmann::json&& value);
    bool open(nlohmann::json&& container);

    size_t max_depth_;
    std::string depth_hint_;
    std::vector<Open> open_;
    std::string key_;
};

}  // namespace flarelab::predict::detail
