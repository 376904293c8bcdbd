#include "predict/gltf_import.h"

#include <sys/stat.h>
#include <tiny_gltf.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <new>
#include <nlohmann/json.hpp>
#include <numbers>
#include <optional>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "common/file_descriptor.h"
#include "common/utf8.h"
#include "predict/detail/json_document.h"

namespace flarelab::predict {
namespace {

using detail::indexed;
using detail::number;
using nlohmann::json;

constexpr double kDegree = std::numbers::pi / 180.0;
constexpr const char* kLightsExtension = "KHR_lights_punctual";
constexpr size_t kMaxQuotedCharacters = 64;
constexpr size_t kMaxLibraryMessageCharacters = 400;
// Exporters write float32 noise: a matrix's last row of 1e-17 or a quaternion off unit length
// by 1e-7 is the file's intent, not an error.
constexpr double kAffineTolerance = 1e-9;
constexpr double kUnitQuaternionTolerance = 1e-3;
// Below this length an axis has collapsed (a scale of 0): it has no direction.
constexpr double kMinAxisLength = 1e-12;
// A camera whose axes differ in length or angle by more than this (relative) is noted.
constexpr double kUniformScaleTolerance = 1e-6;

// ---------------------------------------------------------------------------------------------
// Text for messages.

// `text` made safe for a message: control characters and bytes that are not UTF-8 escaped, cut
// after `max_characters`, so that a hostile file cannot put a terminal sequence, a megabyte or
// invalid UTF-8 (which a protobuf reply would refuse) into a log line.
std::string printable(std::string_view text, size_t max_characters) {
    std::string out;
    size_t characters = 0;
    for (size_t i = 0; i < text.size(); ++characters) {
        if (characters == max_characters) {
            out += "...";
            break;
        }
        const auto c = static_cast<unsigned char>(text[i]);
        const size_t length = detail::utf8SequenceLength(c);
        char escaped[16];
        if (c < 0x20 || c == 0x7F) {
            std::snprintf(escaped, sizeof escaped, "\\u%04X", c);
            out += escaped;
            ++i;
        } else if (c < 0x80) {
            out += static_cast<char>(c);
            ++i;
        } else if (length > 1 && i + length <= text.size() && validUtf8(text.substr(i, length))) {
            const auto next = static_cast<unsigned char>(text[i + 1]);
            if (c == 0xC2 && next <= 0x9F) {  // a C1 control character
                std::snprintf(escaped, sizeof escaped, "\\u%04X", next);
                out += escaped;
            } else {
                out.append(text.substr(i, length));
            }
            i += length;
        } else {
            std::snprintf(escaped, sizeof escaped, "\\x%02X", c);
            out += escaped;
            ++i;
        }
    }
    return out;
}

std::string quotedText(std::string_view text) {
    return detail::quotedText(text, kMaxQuotedCharacters);
}

// tinygltf's error text: lines joined with "; ", without a trailing newline, made printable.
std::string libraryMessage(const std::string& text) {
    std::string joined;
    for (const char c : text) {
        if (c == '\n' || c == '\r') {
            if (!joined.empty() && joined.back() != ' ') joined += "; ";
        } else {
            joined += c;
        }
    }
    while (!joined.empty() && (joined.back() == ' ' || joined.back() == ';')) joined.pop_back();
    if (joined.empty()) return "tinygltf refused it without saying why";
    return "tinygltf: " + printable(joined, kMaxLibraryMessageCharacters);
}

std::string typeOf(const json& value) { return detail::typeOf(value, true); }

std::string plural(size_t count, const std::string& what) {
    return std::to_string(count) + " " + what + (count == 1 ? "" : "s");
}

// ---------------------------------------------------------------------------------------------
// The JSON document, read once before tinygltf reads it: tinygltf silently drops what has the
// wrong type ("camera": "1" becomes no camera; "light": 4294967296 becomes light 0), keeps the
// last of two equal keys, and recurses without bound on deeply nested extras. The checks below
// look at the document itself, so that what tinygltf then gives is what the file says.

// ---------------------------------------------------------------------------------------------
// GLB (glTF 2.0, section 4.4): a 12-byte header, then chunks of an 8-byte header and data.

uint32_t readU32(std::string_view bytes, size_t offset) {
    const auto b = [&](size_t i) { return static_cast<uint32_t>(static_cast<uint8_t>(bytes[i])); };
    return b(offset) | b(offset + 1) << 8 | b(offset + 2) << 16 | b(offset + 3) << 24;
}

constexpr uint32_t kGlbVersion = 2;
constexpr uint32_t kChunkJson = 0x4E4F534A;  // "JSON"

// The JSON chunk of a GLB whose layout is sound. tinygltf 2.7 checks a binary chunk's length
// against the file without its 8-byte header, so a chunk that claims those 8 bytes would have it
// read past the end: every length is checked here first.
Result<std::string_view> glbJson(std::string_view bytes, const std::string& name) {
    const auto fail = [&](const std::string& what) {
        return makeError(ErrorCode::ParseError, name + ": not a GLB file: " + what);
    };
    if (bytes.size() < 20)
        return fail(std::to_string(bytes.size()) +
                    " bytes, shorter than a header and a chunk header (20)");
    if (bytes.substr(0, 4) != "glTF") return fail("it does not start with \"glTF\"");
    const uint32_t version = readU32(bytes, 4);
    if (version != kGlbVersion)
        return makeError(ErrorCode::Unsupported, name + ": GLB version " + std::to_string(version) +
                                                     "; flarelab reads version 2");
    const uint64_t length = readU32(bytes, 8);
    if (length != bytes.size())
        return fail("the header gives a length of " + std::to_string(length) +
                    " bytes, the file has " + std::to_string(bytes.size()));
    const uint64_t json_length = readU32(bytes, 12);
    if (readU32(bytes, 16) != kChunkJson) return fail("the first chunk is not JSON");
    if (20 + json_length > length)
        return fail("the JSON chunk of " + std::to_string(json_length) +
                    " bytes runs past the end of the file");
    const uint64_t rest = length - 20 - json_length;
    if (rest > 0) {
        if (rest < 8) return fail("a chunk header is cut short at the end of the file");
        const uint64_t binary_length = readU32(bytes, 20 + json_length);
        if (8 + binary_length > rest)
            return fail("the chunk after the JSON, of " + std::to_string(binary_length) +
                        " bytes, runs past the end of the file");
    }
    return bytes.substr(20, json_length);
}

// ---------------------------------------------------------------------------------------------
// Buffers in files: which may be read, and reading them through tinygltf's file callbacks.

// A buffer's URI as tinygltf 2.7 decodes it (dlib's urldecode): "+" is a space, "%XY" a byte.
std::string urlDecoded(const std::string& uri) {
    const auto hex = [](unsigned char c) -> unsigned {
        if (c >= '0' && c <= '9') return c - '0';
        if (c >= 'a' && c <= 'f') return c - 'a' + 10;
        if (c >= 'A' && c <= 'F') return c - 'A' + 10;
        return 0;
    };
    std::string out;
    for (size_t i = 0; i < uri.size(); ++i) {
        if (uri[i] == '+') {
            out += ' ';
        } else if (uri[i] == '%' && uri.size() > i + 2) {
            out += static_cast<char>(hex(static_cast<unsigned char>(uri[i + 1])) << 4 |
                                     hex(static_cast<unsigned char>(uri[i + 2])));
            i += 2;
        } else {
            out += uri[i];
        }
    }
    return out;
}

bool isAsciiAlpha(char c) { return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z'); }

// Why a buffer's URI may not be read, or "" when it may: a base64 data: URI tinygltf decodes,
// or a relative file name in the glTF's folder or below it.
std::string uriProblem(const std::string& uri, bool from_memory) {
    if (tinygltf::IsDataURI(uri)) return "";
    if (uri.rfind("data:", 0) == 0)
        return "a data: URI that is not base64 of a type tinygltf reads (such as "
               "application/octet-stream)";
    // RFC 3986: scheme = ALPHA *( ALPHA / DIGIT / "+" / "-" / "." ) ":"
    const size_t colon = uri.find(':');
    if (colon != std::string::npos && colon > 0 && isAsciiAlpha(uri[0]) &&
        std::all_of(uri.begin() + 1, uri.begin() + static_cast<std::ptrdiff_t>(colon), [](char c) {
            return isAsciiAlpha(c) || (c >= '0' && c <= '9') || c == '+' || c == '-' || c == '.';
        }))
        return "a URI with a scheme; only file names relative to the glTF and base64 data: URIs "
               "are read";
    if (from_memory) return "a file name; an import from memory reads no file";
    const std::string path = urlDecoded(uri);
    if (path.empty()) return "empty";
    if (path.front() == '/') return "an absolute path; buffers are read from the glTF's folder";
    for (const char c : path) {
        const auto u = static_cast<unsigned char>(c);
        if (u < 0x20 || u == 0x7F) return "a control character in a file name";
        if (c == '\\') return "a backslash; a URI separates folders with \"/\"";
    }
    size_t start = 0;
    while (start <= path.size()) {
        size_t end = path.find('/', start);
        if (end == std::string::npos) end = path.size();
        if (path.compare(start, end - start, "..") == 0)
            return "\"..\" leaves the glTF's folder; buffers are read from it and below it only";
        start = end + 1;
    }
    return "";
}

// What tinygltf may read through the callbacks below: only the buffers the document names,
// in the glTF's folder, together with the glTF at most kGltfMaxBytes. Images are never read (the
// callbacks say they do not exist), nor anything tinygltf looks for in the working directory.
struct FileAccess {
    std::string name;               // the glTF, for messages
    std::string prefix;             // its folder with a trailing "/"; empty: no file is read
    std::set<std::string> buffers;  // decoded URIs of the buffers in files
    int64_t bytes_left = 0;
    std::optional<Error> error;  // why a buffer was not read, in our words
};

bool fileExists(const std::string& path, void* user_data) {
    auto& access = *static_cast<FileAccess*>(user_data);
    try {
        if (access.prefix.empty() || path.compare(0, access.prefix.size(), access.prefix) != 0)
            return false;
        const std::string relative = path.substr(access.prefix.size());
        if (access.buffers.count(relative) == 0) return false;
        struct stat info {};
        if (::stat(path.c_str(), &info) != 0) {
            const int error = errno;
            if (!access.error)
                access.error =
                    makeError(error == ENOENT ? ErrorCode::NotFound : ErrorCode::IoError,
                              access.name + ": buffer " + quotedText(relative) + ": cannot open " +
                                  printable(path, 256) + ": " + osMessage(error));
            return false;
        }
        return true;
    } catch (const std::exception&) {
        return false;
    }
}

std::string expandFilePath(const std::string& path, void*) {
    return path;  // tinygltf's own would expand "~" and environment variables (wordexp)
}

bool readWholeFile(std::vector<unsigned char>* out,
                   std::string* err,
                   const std::string& path,
                   void* user_data) {
    auto& access = *static_cast<FileAccess*>(user_data);
    const auto refuse = [&](Error error) {
        if (!access.error) access.error = std::move(error);
        if (err) *err = "refused";
        return false;
    };
    try {
        auto file = openRegularFile(path);
        if (!file) return refuse(file.error().withContext(access.name + ": buffer"));
        if (file->size > access.bytes_left)
            return refuse(makeError(ErrorCode::ParseError,
                                    access.name + ": buffer " + printable(path, 256) + ": " +
                                        std::to_string(file->size) +
                                        " bytes; a glTF and its buffers may hold " +
                                        std::to_string(kGltfMaxBytes) + " bytes together"));
        // One byte more than the size: a file that grew while being read is refused.
        out->resize(static_cast<size_t>(file->size) + 1);
        size_t done = 0;
        while (done < out->size()) {
            const ssize_t got = ::read(file->fd.get(), out->data() + done, out->size() - done);
            if (got < 0 && errno == EINTR) continue;
            if (got < 0)
                return refuse(
                    makeError(ErrorCode::IoError, access.name + ": buffer " + printable(path, 256) +
                                                      ": cannot read: " + osMessage(errno)));
            if (got == 0) break;
            done += static_cast<size_t>(got);
        }
        if (done > static_cast<size_t>(file->size))
            return refuse(makeError(
                ErrorCode::IoError,
                access.name + ": buffer " + printable(path, 256) + ": grew while it was read"));
        out->resize(done);
        access.bytes_left -= static_cast<int64_t>(done);
        return true;
    } catch (const std::bad_alloc&) {
        return refuse(
            makeError(ErrorCode::IoError,
                      access.name + ": out of memory reading buffer " + printable(path, 256)));
    } catch (const std::exception& e) {
        return refuse(makeError(ErrorCode::IoError, access.name + ": buffer " +
                                                        printable(path, 256) + ": " + e.what()));
    }
}

bool writeWholeFile(std::string* err,
                    const std::string&,
                    const std::vector<unsigned char>&,
                    void*) {
    if (err) *err = "flarelab's glTF import writes no file";
    return false;
}

// Images are neither decoded nor kept: a venue's textures say nothing about its lights.
bool skipImage(tinygltf::Image*,
               const int,
               std::string*,
               std::string*,
               int,
               int,
               const unsigned char*,
               int,
               void*) {
    return true;
}

// ---------------------------------------------------------------------------------------------
// Checks of the document, before tinygltf reads it.

struct Counts {
    size_t nodes = 0;
    size_t cameras = 0;
    size_t scenes = 0;
    size_t lights = 0;
};

class DocumentCheck {
public:
    DocumentCheck(const std::string& name, bool binary, bool from_memory, FileAccess& access)
        : name_(name), binary_(binary), from_memory_(from_memory), access_(access) {}

    Status check(const json& root) {
        if (!root.is_object())
            return fail("", "the top level must be an object, got " + typeOf(root));
        if (auto s = checkAsset(root); !s) return s;
        if (auto s = countArrays(root); !s) return s;
        if (auto s = checkBuffers(root); !s) return s;
        if (auto s = checkCameras(root); !s) return s;
        if (auto s = checkLights(root); !s) return s;
        if (auto s = checkNodes(root); !s) return s;
        return checkScenes(root);
    }

    const Counts& counts() const { return counts_; }

private:
    Error fail(const std::string& path, const std::string& what) const {
        return makeError(ErrorCode::ParseError,
                         name_ + ": " + (path.empty() ? "" : path + ": ") + what);
    }

    static const json* member(const json& object, const char* key) {
        const auto it = object.find(key);
        return it == object.end() ? nullptr : &*it;
    }

    // An array of objects, or absent (nullptr).
    Result<const json*> objects(const json& object, const char* key, const std::string& path) {
        const json* array = member(object, key);
        if (!array) return static_cast<const json*>(nullptr);
        if (!array->is_array()) return fail(path, "must be an array, got " + typeOf(*array));
        for (size_t i = 0; i < array->size(); ++i)
            if (!(*array)[i].is_object())
                return fail(indexed(path, i), "must be an object, got " + typeOf((*array)[i]));
        return array;
    }

    Result<const json*> object(const json& parent, const char* key, const std::string& path) {
        const json* value = member(parent, key);
        if (value && !value->is_object())
            return fail(path, "must be an object, got " + typeOf(*value));
        return value;
    }

    Status checkString(const json& parent, const char* key, const std::string& path) {
        const json* value = member(parent, key);
        if (value && !value->is_string())
            return fail(path, "must be a string, got " + typeOf(*value));
        return Ok{};
    }

    // A JSON integer (not 1.0: tinygltf drops that silently) in [0, count).
    Status checkIndex(const json& value,
                      size_t count,
                      const std::string& path,
                      const std::string& what) {
        if (!value.is_number_integer())
            return fail(path, "must be a " + what + " index (an integer), got " + typeOf(value));
        const bool in_range =
            value.is_number_unsigned()
                ? value.get<uint64_t>() < count
                : value.get<int64_t>() >= 0 && static_cast<uint64_t>(value.get<int64_t>()) < count;
        if (!in_range)
            return fail(path, what + " index " + value.dump() + " out of range (" +
                                  plural(count, what) + ")");
        return Ok{};
    }

    Status checkIndexArray(const json& parent,
                           const char* key,
                           size_t count,
                           const std::string& path,
                           const std::string& what) {
        const json* array = member(parent, key);
        if (!array) return Ok{};
        if (!array->is_array()) return fail(path, "must be an array, got " + typeOf(*array));
        for (size_t i = 0; i < array->size(); ++i)
            if (auto s = checkIndex((*array)[i], count, indexed(path, i), what); !s) return s;
        return Ok{};
    }

    // `length` numbers, each >= `low` where `low` is given.
    Status checkNumbers(const json& parent,
                        const char* key,
                        size_t length,
                        const std::string& path,
                        std::optional<double> low = std::nullopt) {
        const json* array = member(parent, key);
        if (!array) return Ok{};
        if (!array->is_array() || array->size() != length)
            return fail(
                path, "must be an array of " + std::to_string(length) + " numbers, got " +
                          (array->is_array() ? plural(array->size(), "element") : typeOf(*array)));
        for (size_t i = 0; i < length; ++i) {
            const json& x = (*array)[i];
            if (!x.is_number()) return fail(indexed(path, i), "must be a number, got " + typeOf(x));
            if (low && !(x.get<double>() >= *low))
                return fail(indexed(path, i), "must be >= " + number(*low) + ", got " + typeOf(x));
        }
        return Ok{};
    }

    Status checkNumber(
        const json& parent, const char* key, const std::string& path, double low, bool low_open) {
        const json* value = member(parent, key);
        if (!value) return Ok{};
        if (!value->is_number()) return fail(path, "must be a number, got " + typeOf(*value));
        const double x = value->get<double>();
        if (!(low_open ? x > low : x >= low))
            return fail(path, std::string("must be ") + (low_open ? "> " : ">= ") + number(low) +
                                  ", got " + number(x));
        return Ok{};
    }

    Status checkAsset(const json& root) {
        auto asset = object(root, "asset", "asset");
        if (!asset) return asset.error();
        if (!*asset) return fail("asset", "missing; every glTF names its version there");
        const json* version = member(**asset, "version");
        if (!version || !version->is_string())
            return fail("asset.version", "must be a string such as \"2.0\"");
        const std::string text = version->get<std::string>();
        if (text.rfind("2.", 0) != 0)
            return makeError(
                ErrorCode::Unsupported,
                name_ + ": asset.version: glTF " + quotedText(text) + "; flarelab reads glTF 2.x");
        if (const json* min_version = member(**asset, "minVersion")) {
            if (!min_version->is_string())
                return fail("asset.minVersion", "must be a string, got " + typeOf(*min_version));
            if (min_version->get<std::string>() != "2.0")
                return makeError(ErrorCode::Unsupported,
                                 name_ + ": asset.minVersion: the file needs glTF " +
                                     quotedText(min_version->get<std::string>()) +
                                     "; flarelab reads glTF 2.0");
        }
        return Ok{};
    }

    Status countArrays(const json& root) {
        for (const auto& [key, count] :
             {std::pair{"nodes", &counts_.nodes}, std::pair{"cameras", &counts_.cameras},
              std::pair{"scenes", &counts_.scenes}}) {
            auto array = objects(root, key, key);
            if (!array) return array.error();
            *count = *array ? (*array)->size() : 0;
        }
        auto extensions = object(root, "extensions", "extensions");
        if (!extensions) return extensions.error();
        if (!*extensions) return Ok{};
        const std::string path = std::string("extensions.") + kLightsExtension;
        auto lights_extension = object(**extensions, kLightsExtension, path);
        if (!lights_extension) return lights_extension.error();
        if (!*lights_extension) return Ok{};
        auto lights = objects(**lights_extension, "lights", path + ".lights");
        if (!lights) return lights.error();
        lights_ = *lights;
        counts_.lights = lights_ ? lights_->size() : 0;
        return Ok{};
    }

    Status checkBuffers(const json& root) {
        auto buffers = objects(root, "buffers", "buffers");
        if (!buffers) return buffers.error();
        if (!*buffers) return Ok{};
        for (size_t i = 0; i < (*buffers)->size(); ++i) {
            const json& buffer = (**buffers)[i];
            const std::string path = indexed("buffers", i);
            const json* byte_length = member(buffer, "byteLength");
            if (!byte_length || !byte_length->is_number_unsigned() ||
                byte_length->get<uint64_t>() < 1)
                return fail(path + ".byteLength",
                            "must be an integer >= 1, got " +
                                (byte_length ? typeOf(*byte_length) : std::string("nothing")));
            const json* uri = member(buffer, "uri");
            if (!uri) {
                if (!binary_)
                    return fail(path, "has no uri; only a GLB's buffer may go without one");
                continue;
            }
            if (!uri->is_string())
                return fail(path + ".uri", "must be a string, got " + typeOf(*uri));
            const std::string text = uri->get<std::string>();
            if (const std::string problem = uriProblem(text, from_memory_); !problem.empty())
                return fail(path + ".uri", quotedText(text) + ": " + problem);
            if (!tinygltf::IsDataURI(text)) access_.buffers.insert(urlDecoded(text));
        }
        return Ok{};
    }

    Status checkCameras(const json& root) {
        const json* cameras = member(root, "cameras");
        for (size_t i = 0; i < counts_.cameras; ++i)
            if (auto s = checkString((*cameras)[i], "name", indexed("cameras", i) + ".name"); !s)
                return s;
        return Ok{};
    }

    Status checkLights(const json&) {
        const std::string base = std::string("extensions.") + kLightsExtension + ".lights";
        for (size_t i = 0; i < counts_.lights; ++i) {
            const json& light = (*lights_)[i];
            const std::string path = indexed(base, i);
            const json* type = member(light, "type");
            if (!type || !type->is_string())
                return fail(path + ".type", "must be a string such as \"point\", got " +
                                                (type ? typeOf(*type) : std::string("nothing")));
            if (auto s = checkString(light, "name", path + ".name"); !s) return s;
            if (auto s = checkNumbers(light, "color", 3, path + ".color", 0.0); !s) return s;
            if (auto s = checkNumber(light, "intensity", path + ".intensity", 0.0, false); !s)
                return s;
            if (auto s = checkNumber(light, "range", path + ".range", 0.0, true); !s) return s;
            if (type->get<std::string>() == "spot") {
                auto spot = object(light, "spot", path + ".spot");
                if (!spot) return spot.error();
                if (!*spot) return fail(path, "a spot light must have \"spot\"");
                for (const char* angle : {"innerConeAngle", "outerConeAngle"}) {
                    const json* value = member(**spot, angle);
                    if (value && !value->is_number())
                        return fail(path + ".spot." + angle,
                                    "must be a number, got " + typeOf(*value));
                }
            }
        }
        return Ok{};
    }

    Status checkNodes(const json& root) {
        const json* nodes = member(root, "nodes");
        for (size_t i = 0; i < counts_.nodes; ++i) {
            const json& node = (*nodes)[i];
            const std::string path = indexed("nodes", i);
            if (auto s = checkString(node, "name", path + ".name"); !s) return s;
            if (const json* camera = member(node, "camera"))
                if (auto s = checkIndex(*camera, counts_.cameras, path + ".camera", "camera"); !s)
                    return s;
            if (auto s =
                    checkIndexArray(node, "children", counts_.nodes, path + ".children", "node");
                !s)
                return s;
            if (auto s = checkNumbers(node, "matrix", 16, path + ".matrix"); !s) return s;
            if (auto s = checkNumbers(node, "translation", 3, path + ".translation"); !s) return s;
            if (auto s = checkNumbers(node, "rotation", 4, path + ".rotation"); !s) return s;
            if (auto s = checkNumbers(node, "scale", 3, path + ".scale"); !s) return s;
            if (member(node, "matrix") &&
                (member(node, "translation") || member(node, "rotation") || member(node, "scale")))
                return fail(path, "has both a matrix and translation, rotation or scale");
            auto extensions = object(node, "extensions", path + ".extensions");
            if (!extensions) return extensions.error();
            if (!*extensions) continue;
            const std::string light_path = path + ".extensions." + kLightsExtension;
            auto light = object(**extensions, kLightsExtension, light_path);
            if (!light) return light.error();
            if (!*light) continue;
            const json* index = member(**light, "light");
            if (!index) return fail(light_path, "must name its \"light\"");
            if (auto s = checkIndex(*index, counts_.lights, light_path + ".light", "light"); !s)
                return s;
        }
        return Ok{};
    }

    Status checkScenes(const json& root) {
        const json* scenes = member(root, "scenes");
        for (size_t i = 0; i < counts_.scenes; ++i) {
            const std::string path = indexed("scenes", i);
            if (auto s =
                    checkIndexArray((*scenes)[i], "nodes", counts_.nodes, path + ".nodes", "node");
                !s)
                return s;
        }
        if (const json* scene = member(root, "scene"))
            return checkIndex(*scene, counts_.scenes, "scene", "scene");
        return Ok{};
    }

    const std::string& name_;
    const bool binary_;
    const bool from_memory_;
    FileAccess& access_;
    Counts counts_;
    const json* lights_ = nullptr;
};

// ---------------------------------------------------------------------------------------------
// Transforms.

// x' = a x + t, with `a` row-major.
struct Affine {
    std::array<double, 9> a = {1, 0, 0, 0, 1, 0, 0, 0, 1};
    Vec3 t = {0.0, 0.0, 0.0};

    Vec3 column(int c) const { return {a[c], a[3 + c], a[6 + c]}; }
};

Affine compose(const Affine& parent, const Affine& local) {
    Affine out;
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c)
            out.a[r * 3 + c] = parent.a[r * 3] * local.a[c] + parent.a[r * 3 + 1] * local.a[3 + c] +
                               parent.a[r * 3 + 2] * local.a[6 + c];
        out.t[r] = parent.a[r * 3] * local.t[0] + parent.a[r * 3 + 1] * local.t[1] +
                   parent.a[r * 3 + 2] * local.t[2] + parent.t[r];
    }
    return out;
}

bool finite(const Affine& x) {
    return std::all_of(x.a.begin(), x.a.end(), [](double v) { return std::isfinite(v); }) &&
           std::all_of(x.t.begin(), x.t.end(), [](double v) { return std::isfinite(v); });
}

double dot(const Vec3& a, const Vec3& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
double length(const Vec3& v) { return std::sqrt(dot(v, v)); }
Vec3 scaled(const Vec3& v, double s) { return {v[0] * s, v[1] * s, v[2] * s}; }

// x, or +0 for -0: a planner reading "-0" in an exported scene would wonder what it means.
double withoutNegativeZero(double x) { return x + 0.0; }

// glTF's frame (Y up, -Z north) to flarelab's world (x east, y north, z up): a rotation.
Vec3 toWorld(const Vec3& v) {
    return {withoutNegativeZero(v[0]), withoutNegativeZero(-v[2]), withoutNegativeZero(v[1])};
}

// The pose whose cameraFrame() has `forward` and `up` (unit, perpendicular, world frame).
CameraPose poseFromAxes(const Vec3& position_m, const Vec3& forward, const Vec3& up) {
    CameraPose pose;
    pose.position_m = position_m;
    const auto normalisePan = [&pose] {
        if (pose.pan_deg < 0.0) pose.pan_deg += 360.0;
        if (pose.pan_deg >= 360.0) pose.pan_deg -= 360.0;
    };
    const double horizontal = std::hypot(forward[0], forward[1]);
    if (!(horizontal > kMinAxisLength)) {
        // Straight up or down: cameraFrame's unrolled up is -sin(tilt) (sin pan, cos pan, 0),
        // so the pan alone puts `up` in place, and the roll is 0 (not the 1e-14 that a roll
        // measured against cos(90 degrees) = 6e-17 would give).
        const double s = forward[2] > 0.0 ? 1.0 : -1.0;
        pose.tilt_deg = 90.0 * s;
        pose.pan_deg = std::atan2(-s * up[0], -s * up[1]) / kDegree;
        normalisePan();
        pose.pan_deg = withoutNegativeZero(pose.pan_deg);
        return pose;
    }
    pose.tilt_deg = std::atan2(forward[2], horizontal) / kDegree;
    pose.pan_deg = std::atan2(forward[0], forward[1]) / kDegree;
    normalisePan();
    // cameraFrame rolls its unrolled right and up by the roll: up = sin r right0 + cos r up0.
    const CameraFrame unrolled = cameraFrame(pose);
    pose.roll_deg = std::atan2(dot(up, unrolled.right), dot(up, unrolled.up)) / kDegree;
    if (pose.roll_deg <= -180.0) pose.roll_deg = 180.0;
    pose.pan_deg = withoutNegativeZero(pose.pan_deg);
    pose.tilt_deg = withoutNegativeZero(pose.tilt_deg);
    pose.roll_deg = withoutNegativeZero(pose.roll_deg);
    return pose;
}

// ---------------------------------------------------------------------------------------------
// The import.

class Importer {
public:
    Importer(const std::string& name, const tinygltf::Model& model) : name_(name), model_(model) {}

    Result<GltfImport> run() {
        if (auto s = checkCameras(); !s) return s.error();
        if (auto s = checkHierarchy(); !s) return s.error();
        auto roots = sceneRoots();
        if (!roots) return roots.error();
        if (auto s = walk(*roots); !s) return s.error();
        noteUnused();
        noteRequiredExtensions();
        if (out_.cameras.empty()) out_.notes.push_back("no cameras in the imported scene");
        if (out_.lights.empty()) out_.notes.push_back("no lights in the imported scene");
        return std::move(out_);
    }

private:
    Error fail(const std::string& path, const std::string& what) const {
        return makeError(ErrorCode::ParseError, name_ + ": " + path + ": " + what);
    }

    std::string nodeLabel(size_t i) const {
        const std::string& name = model_.nodes[i].name;
        return indexed("nodes", i) + (name.empty() ? "" : " " + quotedText(name));
    }

    std::string lightLabel(size_t i) const {
        const std::string& name = model_.lights[i].name;
        return indexed("lights", i) + (name.empty() ? "" : " " + quotedText(name));
    }

    std::string cameraLabel(size_t i) const {
        const std::string& name = model_.cameras[i].name;
        return indexed("cameras", i) + (name.empty() ? "" : " " + quotedText(name));
    }

    std::string instanceName(size_t node, const std::string& object_name) const {
        if (!model_.nodes[node].name.empty()) return model_.nodes[node].name;
        if (!object_name.empty()) return object_name;
        return "node " + std::to_string(node);
    }

    Status checkCameras() const {
        for (size_t i = 0; i < model_.cameras.size(); ++i) {
            const tinygltf::Camera& camera = model_.cameras[i];
            if (camera.type != "perspective") continue;
            const double yfov = camera.perspective.yfov;
            if (!(yfov > 0.0 && yfov < std::numbers::pi))
                return fail(indexed("cameras", i) + ".perspective.yfov",
                            "must be in (0, pi) radians, got " + number(yfov));
        }
        return Ok{};
    }

    // glTF 2.0, section 3.5.3: the nodes form disjoint strict trees. Each node's parent, refusing
    // a second parent, a cycle and depth beyond kGltfMaxNodeDepth.
    Status checkHierarchy() {
        const size_t n = model_.nodes.size();
        parent_.assign(n, -1);
        for (size_t i = 0; i < n; ++i) {
            const auto& children = model_.nodes[i].children;
            for (size_t k = 0; k < children.size(); ++k) {
                const auto child = static_cast<size_t>(children[k]);
                const std::string path = indexed(indexed("nodes", i) + ".children", k);
                if (child == i) return fail(path, "the node is its own child");
                if (parent_[child] >= 0)
                    return fail(path,
                                "node " + std::to_string(child) + " is already a child of node " +
                                    std::to_string(parent_[child]) + "; a node has one parent");
                parent_[child] = static_cast<int64_t>(i);
            }
        }
        // Depths by walking up from each node until a node of known depth or a root; a walk
        // longer than the node count has gone round a cycle.
        std::vector<int> depth(n, 0);
        std::vector<size_t> path;
        for (size_t i = 0; i < n; ++i) {
            path.clear();
            size_t at = i;
            while (depth[at] == 0) {
                path.push_back(at);
                if (path.size() > n)
                    return fail(indexed("nodes", i), "its ancestors form a cycle (node " +
                                                         std::to_string(at) +
                                                         " is its own ancestor)");
                if (parent_[at] < 0) break;
                at = static_cast<size_t>(parent_[at]);
            }
            int d = depth[at];  // 0 when the walk ended at a root not yet given a depth
            for (auto it = path.rbegin(); it != path.rend(); ++it) {
                depth[*it] = ++d;
                if (d > kGltfMaxNodeDepth)
                    return fail(
                        indexed("nodes", *it),
                        "nested more than " + std::to_string(kGltfMaxNodeDepth) + " levels deep");
            }
        }
        return Ok{};
    }

    Result<std::vector<size_t>> sceneRoots() {
        std::vector<size_t> roots;
        const size_t scenes = model_.scenes.size();
        if (scenes == 0) {
            for (size_t i = 0; i < model_.nodes.size(); ++i)
                if (parent_[i] < 0) roots.push_back(i);
            if (!model_.nodes.empty())
                out_.notes.push_back("no scenes in the file; every root node imported");
            return roots;
        }
        size_t chosen = 0;
        if (model_.defaultScene >= 0) {
            chosen = static_cast<size_t>(model_.defaultScene);
            if (scenes > 1)
                out_.notes.push_back(plural(scenes, "scene") + "; scene " + std::to_string(chosen) +
                                     " (the default) imported");
        } else if (scenes > 1) {
            out_.notes.push_back("no default scene; scene 0 of " + std::to_string(scenes) +
                                 " imported");
        }
        std::vector<bool> listed(model_.nodes.size(), false);
        const auto& nodes = model_.scenes[chosen].nodes;
        for (size_t k = 0; k < nodes.size(); ++k) {
            const auto node = static_cast<size_t>(nodes[k]);
            const std::string path = indexed(indexed("scenes", chosen) + ".nodes", k);
            if (parent_[node] >= 0)
                return fail(path, "node " + std::to_string(node) + " is a child of node " +
                                      std::to_string(parent_[node]) +
                                      "; a scene lists root nodes only");
            if (listed[node])
                return fail(path, "node " + std::to_string(node) + " is listed twice");
            listed[node] = true;
            roots.push_back(node);
        }
        return roots;
    }

    Result<Affine> localTransform(size_t i) {
        const tinygltf::Node& node = model_.nodes[i];
        const std::string path = indexed("nodes", i);
        Affine local;
        if (!node.matrix.empty()) {
            const auto& m = node.matrix;  // column-major
            if (std::abs(m[3]) > kAffineTolerance || std::abs(m[7]) > kAffineTolerance ||
                std::abs(m[11]) > kAffineTolerance || std::abs(m[15] - 1.0) > kAffineTolerance)
                return fail(path + ".matrix",
                            "its last row must be 0, 0, 0, 1 (an affine "
                            "transform), got " +
                                number(m[3]) + ", " + number(m[7]) + ", " + number(m[11]) + ", " +
                                number(m[15]));
            for (int r = 0; r < 3; ++r) {
                for (int c = 0; c < 3; ++c) local.a[r * 3 + c] = m[c * 4 + r];
                local.t[r] = m[12 + r];
            }
            return local;
        }
        double x = 0.0, y = 0.0, z = 0.0, w = 1.0;
        if (!node.rotation.empty()) {
            const auto& q = node.rotation;
            const double norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
            if (!(norm > kMinAxisLength && std::isfinite(norm)))
                return fail(path + ".rotation",
                            "not a rotation: a quaternion of length " + number(norm));
            if (std::abs(norm - 1.0) > kUnitQuaternionTolerance)
                out_.notes.push_back(path + ".rotation: a quaternion of length " + number(norm) +
                                     ", not 1; normalised");
            x = q[0] / norm;
            y = q[1] / norm;
            z = q[2] / norm;
            w = q[3] / norm;
        }
        const std::array<double, 9> rotation = {
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w),     2 * (x * z + y * w),
            2 * (x * y + z * w),     1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w),     2 * (y * z + x * w),     1 - 2 * (x * x + y * y)};
        const Vec3 scale = node.scale.empty() ? Vec3{1.0, 1.0, 1.0}
                                              : Vec3{node.scale[0], node.scale[1], node.scale[2]};
        for (int r = 0; r < 3; ++r)
            for (int c = 0; c < 3; ++c) local.a[r * 3 + c] = rotation[r * 3 + c] * scale[c];
        if (!node.translation.empty())
            local.t = {node.translation[0], node.translation[1], node.translation[2]};
        return local;
    }

    // Depth first from the roots, children in their order; the hierarchy is known to be a forest
    // of bounded depth.
    Status walk(const std::vector<size_t>& roots) {
        used_cameras_.assign(model_.cameras.size(), false);
        used_lights_.assign(model_.lights.size(), false);
        struct Pending {
            size_t node;
            Affine parent;
        };
        std::vector<Pending> stack;
        for (auto it = roots.rbegin(); it != roots.rend(); ++it) stack.push_back({*it, Affine{}});
        while (!stack.empty()) {
            const Pending pending = stack.back();
            stack.pop_back();
            auto local = localTransform(pending.node);
            if (!local) return local.error();
            const Affine world = compose(pending.parent, *local);
            if (!finite(world))
                return fail(indexed("nodes", pending.node),
                            "its world transform overflows (a number is not finite)");
            addCamera(pending.node, world);
            addLight(pending.node, world);
            const auto& children = model_.nodes[pending.node].children;
            for (auto it = children.rbegin(); it != children.rend(); ++it)
                stack.push_back({static_cast<size_t>(*it), world});
        }
        return Ok{};
    }

    void addCamera(size_t node, const Affine& world) {
        const int index = model_.nodes[node].camera;
        if (index < 0) return;
        const tinygltf::Camera& camera = model_.cameras[static_cast<size_t>(index)];
        used_cameras_[static_cast<size_t>(index)] = true;
        const std::string label =
            nodeLabel(node) + " (" + cameraLabel(static_cast<size_t>(index)) + ")";
        // The camera looks along -Z with +Y up (glTF 2.0, section 3.10.2).
        const Vec3 x_axis = world.column(0), y_axis = world.column(1), z_axis = world.column(2);
        const double z_length = length(z_axis), y_length = length(y_axis);
        if (!(z_length > kMinAxisLength && y_length > kMinAxisLength)) {
            out_.notes.push_back(label +
                                 ": its transform collapses the camera's axes (a scale "
                                 "of 0); skipped");
            return;
        }
        const Vec3 forward = scaled(z_axis, -1.0 / z_length);
        const double along = dot(y_axis, forward);
        Vec3 up = {y_axis[0] - along * forward[0], y_axis[1] - along * forward[1],
                   y_axis[2] - along * forward[2]};
        const double up_length = length(up);
        if (!(up_length > kMinAxisLength * y_length)) {
            out_.notes.push_back(label +
                                 ": its transform turns the camera's up onto its optical "
                                 "axis; skipped");
            return;
        }
        up = scaled(up, 1.0 / up_length);
        // A similarity has columns of one length, at right angles.
        const double xx = dot(x_axis, x_axis), yy = y_length * y_length, zz = z_length * z_length;
        const double s2 = (xx + yy + zz) / 3.0;
        const double deviation = std::max(
            {std::abs(xx - s2), std::abs(yy - s2), std::abs(zz - s2), std::abs(dot(x_axis, y_axis)),
             std::abs(dot(y_axis, z_axis)), std::abs(dot(z_axis, x_axis))});
        if (deviation > kUniformScaleTolerance * s2)
            out_.notes.push_back(label +
                                 ": its transform scales unevenly or shears; the optical "
                                 "axis is kept and the up direction squared to it");
        const Vec3 y_cross_z = {y_axis[1] * z_axis[2] - y_axis[2] * z_axis[1],
                                y_axis[2] * z_axis[0] - y_axis[0] * z_axis[2],
                                y_axis[0] * z_axis[1] - y_axis[1] * z_axis[0]};
        if (dot(x_axis, y_cross_z) < 0.0)
            out_.notes.push_back(label +
                                 ": its transform mirrors the image; a pose cannot, and "
                                 "the mirror is ignored");
        GltfCamera out;
        out.name = instanceName(node, camera.name);
        out.type = camera.type;
        out.pose = poseFromAxes(toWorld(world.t), toWorld(forward), toWorld(up));
        if (camera.type == "perspective") out.yfov_deg = camera.perspective.yfov / kDegree;
        out_.cameras.push_back(std::move(out));
    }

    void addLight(size_t node, const Affine& world) {
        const auto extension = model_.nodes[node].extensions.find(kLightsExtension);
        if (extension == model_.nodes[node].extensions.end()) return;
        // The document check made it an object whose "light" is an index in range.
        const auto index = static_cast<size_t>(extension->second.Get("light").GetNumberAsInt());
        const tinygltf::Light& light = model_.lights[index];
        used_lights_[index] = true;
        const std::string label = nodeLabel(node) + " (" + lightLabel(index) + ")";
        if (light.type != "point" && light.type != "spot" && light.type != "directional") {
            out_.notes.push_back(label + ": a light of type " + quotedText(light.type) +
                                 ", which flarelab does not read (point, spot and directional "
                                 "lights); skipped");
            return;
        }
        GltfLight out;
        out.name = instanceName(node, light.name);
        out.type = light.type;
        out.intensity = light.intensity;
        if (light.color.size() == 3) out.colour = {light.color[0], light.color[1], light.color[2]};
        if (light.range > 0.0) out.range_m = light.range;
        if (out.intensity == 0.0) {
            out_.notes.push_back(label + ": intensity 0; skipped");
            return;
        }
        if (out.colour == std::array<double, 3>{0.0, 0.0, 0.0}) {
            out_.notes.push_back(label + ": colour black; skipped");
            return;
        }
        if (light.type == "directional") {
            // It shines along the node's -Z: the light is towards +Z.
            const Vec3 z_axis = world.column(2);
            const double z_length = length(z_axis);
            if (!(z_length > kMinAxisLength)) {
                out_.notes.push_back(label +
                                     ": its transform collapses the light's direction (a "
                                     "scale of 0); skipped");
                return;
            }
            out.direction = toWorld(scaled(z_axis, 1.0 / z_length));
        } else {
            out.position_m = toWorld(world.t);
            if (light.type == "spot")
                out_.notes.push_back(label +
                                     ": a spot light; its cone is not modelled, so it is "
                                     "imported as a point light");
        }
        out_.lights.push_back(std::move(out));
    }

    void noteUnused() {
        for (size_t i = 0; i < used_cameras_.size(); ++i)
            if (!used_cameras_[i])
                out_.notes.push_back(cameraLabel(i) + " is on no node of the imported scene");
        for (size_t i = 0; i < used_lights_.size(); ++i)
            if (!used_lights_[i])
                out_.notes.push_back(lightLabel(i) + " is on no node of the imported scene");
    }

    void noteRequiredExtensions() {
        std::string others;
        for (const std::string& extension : model_.extensionsRequired) {
            if (extension == kLightsExtension) continue;
            others += (others.empty() ? "" : ", ") + quotedText(extension);
        }
        if (!others.empty())
            out_.notes.push_back("the file requires " + others +
                                 ", which flarelab does not read: cameras and lights are read "
                                 "without them");
    }

    const std::string& name_;
    const tinygltf::Model& model_;
    std::vector<int64_t> parent_;
    std::vector<bool> used_cameras_;
    std::vector<bool> used_lights_;
    GltfImport out_;
};

// `base_dir` is the glTF's folder; nullopt for bytes from memory, which read no file.
Result<GltfImport> importBytes(std::string_view bytes,
                               const std::string& name,
                               bool binary,
                               const std::optional<std::string>& base_dir) {
    if (static_cast<uint64_t>(bytes.size()) > static_cast<uint64_t>(kGltfMaxBytes))
        return makeError(ErrorCode::ParseError, name + ": " + std::to_string(bytes.size()) +
                                                    " bytes, more than a glTF may hold here (" +
                                                    std::to_string(kGltfMaxBytes) + ")");
    std::string_view json_text = bytes;
    if (binary) {
        auto chunk = glbJson(bytes, name);
        if (!chunk) return chunk.error();
        json_text = *chunk;
    } else if (bytes.substr(0, 4) == "glTF") {
        return makeError(ErrorCode::ParseError,
                         name + ": starts with \"glTF\", the mark of a binary GLB, not JSON");
    }

    FileAccess access;
    access.name = name;
    access.bytes_left = kGltfMaxBytes - static_cast<int64_t>(bytes.size());
    if (base_dir)
        access.prefix = base_dir->empty() || base_dir->back() == '/' ? *base_dir : *base_dir + "/";

    Counts counts;
    {
        detail::JsonDocumentBuilder builder(kGltfMaxJsonDepth);
        json::sax_parse(json_text.begin(), json_text.end(), &builder);
        if (!builder.error.empty())
            return makeError(ErrorCode::ParseError,
                             name + ": " +
                                 (builder.error_path.empty() ? "" : builder.error_path + ": ") +
                                 builder.error);
        DocumentCheck check(name, binary, !base_dir.has_value(), access);
        if (auto s = check.check(builder.document); !s) return s.error();
        counts = check.counts();
    }

    tinygltf::Model model;
    tinygltf::TinyGLTF loader;
    loader.SetImageLoader(&skipImage, nullptr);
    loader.SetFsCallbacks(tinygltf::FsCallbacks{&fileExists, &expandFilePath, &readWholeFile,
                                                &writeWholeFile, &access});
    std::string error, warning;
    const std::string library_dir = base_dir.value_or("");
    bool loaded = false;
    try {
        const auto* data = reinterpret_cast<const unsigned char*>(bytes.data());
        const auto size = static_cast<unsigned int>(bytes.size());
        loaded = binary ? loader.LoadBinaryFromMemory(&model, &error, &warning, data, size,
                                                      library_dir, tinygltf::REQUIRE_VERSION)
                        : loader.LoadASCIIFromString(&model, &error, &warning, bytes.data(), size,
                                                     library_dir, tinygltf::REQUIRE_VERSION);
    } catch (const std::bad_alloc&) {
        return makeError(ErrorCode::ParseError, name + ": too large to read");
    } catch (const std::exception& e) {
        return makeError(ErrorCode::ParseError, name + ": " + libraryMessage(e.what()));
    } catch (...) {
        return makeError(ErrorCode::ParseError,
                         name + ": tinygltf failed with an unknown exception");
    }
    if (access.error) return *access.error;
    if (!loaded) return makeError(ErrorCode::ParseError, name + ": " + libraryMessage(error));
    // tinygltf read the document checked above; a count that differs is a bug on either side.
    if (model.nodes.size() != counts.nodes || model.cameras.size() != counts.cameras ||
        model.scenes.size() != counts.scenes || model.lights.size() != counts.lights)
        return makeError(ErrorCode::Internal,
                         name + ": tinygltf read " + plural(model.nodes.size(), "node") + ", " +
                             plural(model.cameras.size(), "camera") + ", " +
                             plural(model.scenes.size(), "scene") + " and " +
                             plural(model.lights.size(), "light") + " where the document has " +
                             std::to_string(counts.nodes) + ", " + std::to_string(counts.cameras) +
                             ", " + std::to_string(counts.scenes) + " and " +
                             std::to_string(counts.lights));
    return Importer(name, model).run();
}

}  // namespace

Result<GltfImport> importGltfFromMemory(std::string_view bytes,
                                        const std::string& name,
                                        bool binary) {
    try {
        return importBytes(bytes, name, binary, std::nullopt);
    } catch (const std::bad_alloc&) {
        return makeError(ErrorCode::ParseError, name + ": too large to read");
    } catch (const std::exception& e) {
        // The checks come before every conversion: this is a bug, not bad input.
        return makeError(ErrorCode::Internal, name + ": " + e.what());
    }
}

Result<GltfImport> importGltf(const std::string& path) {
    try {
        auto read = detail::readSmallFile(path, kGltfMaxBytes, "a glTF file");
        if (!read) return read.error();
        const std::string& bytes = *read;
        std::string base_dir = std::filesystem::path(path).parent_path().string();
        if (base_dir.empty()) base_dir = ".";
        const bool binary = bytes.size() >= 4 && std::string_view(bytes).substr(0, 4) == "glTF";
        return importBytes(bytes, path, binary, base_dir);
    } catch (const std::bad_alloc&) {
        return makeError(ErrorCode::IoError, path + ": out of memory reading it");
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal, path + ": " + e.what());
    }
}

}  // namespace flarelab::predict
