#include "drivers/genicam_pixels.h"

#include <algorithm>
#include <array>
#include <limits>
#include <utility>

namespace flarelab::drivers {
namespace {

struct BayerOrder {
    std::string_view word;
    hdr::RawFormat layout;
};
constexpr std::array<BayerOrder, 4> kBayerOrders = {{
    {"RG", hdr::RawFormat::BayerRGGB},
    {"BG", hdr::RawFormat::BayerBGGR},
    {"GR", hdr::RawFormat::BayerGRBG},
    {"GB", hdr::RawFormat::BayerGBRG},
}};

// The depth suffixes after "Mono" or "Bayer<order>".
struct Depth {
    std::string_view suffix;
    int bits;
    PixelPacking packing;
};
constexpr std::array<Depth, 10> kDepths = {{
    {"8", 8, PixelPacking::None},
    {"10", 10, PixelPacking::None},
    {"10p", 10, PixelPacking::Lsb},
    {"10Packed", 10, PixelPacking::GigEPacked},
    {"12", 12, PixelPacking::None},
    {"12p", 12, PixelPacking::Lsb},
    {"12Packed", 12, PixelPacking::GigEPacked},
    {"14", 14, PixelPacking::None},
    {"14p", 14, PixelPacking::Lsb},
    {"16", 16, PixelPacking::None},
}};

std::optional<Depth> depthOf(std::string_view suffix) {
    for (const Depth& d : kDepths)
        if (d.suffix == suffix) return d;
    return std::nullopt;
}

// A tuple compared lexicographically, larger is better (see the header).
std::array<int, 4> rank(const GenicamPixelFormat& f) {
    return {f.bits > 8 ? 1 : 0, f.layout == hdr::RawFormat::Mono ? 1 : 0, f.bits,
            f.packing == PixelPacking::None ? 1 : 0};
}

Error badPayload(const GenicamPixelFormat& format, const std::string& what) {
    return makeError(ErrorCode::InvalidArgument, "pixel data in " + format.name + ": " + what);
}

}  // namespace

std::optional<GenicamPixelFormat> genicamPixelFormat(std::string_view name) {
    GenicamPixelFormat f;
    f.name = std::string(name);
    std::string_view rest;
    if (name.substr(0, 4) == "Mono") {
        f.layout = hdr::RawFormat::Mono;
        rest = name.substr(4);
    } else if (name.substr(0, 5) == "Bayer" && name.size() >= 7) {
        const std::string_view order = name.substr(5, 2);
        const auto found = std::find_if(kBayerOrders.begin(), kBayerOrders.end(),
                                        [&](const BayerOrder& b) { return b.word == order; });
        if (found == kBayerOrders.end()) return std::nullopt;
        f.layout = found->layout;
        rest = name.substr(7);
    } else {
        return std::nullopt;
    }
    const auto depth = depthOf(rest);
    if (!depth) return std::nullopt;
    f.bits = depth->bits;
    f.packing = depth->packing;
    return f;
}

std::vector<GenicamPixelFormat> rankGenicamPixelFormats(const std::vector<std::string>& names) {
    std::vector<GenicamPixelFormat> taken;
    for (const std::string& n : names)
        if (auto f = genicamPixelFormat(n)) taken.push_back(std::move(*f));
    std::stable_sort(taken.begin(), taken.end(),
                     [](const auto& a, const auto& b) { return rank(a) > rank(b); });
    return taken;
}

std::optional<GenicamPixelFormat> chooseGenicamPixelFormat(const std::vector<std::string>& names,
                                                           hdr::RawFormat layout) {
    for (GenicamPixelFormat& f : rankGenicamPixelFormats(names))
        if (f.layout == layout) return std::move(f);
    return std::nullopt;
}

std::string_view bayerOrderName(hdr::RawFormat layout) {
    for (const BayerOrder& b : kBayerOrders)
        if (b.layout == layout) return b.word;
    return "";
}

int64_t genicamPayloadBytes(const GenicamPixelFormat& format, int64_t count) {
    switch (format.packing) {
        case PixelPacking::None:
            return count * (format.bits > 8 ? 2 : 1);
        case PixelPacking::GigEPacked:  // 12 bits a sample whatever the depth; an odd last
            return 3 * (count / 2) + (count % 2 == 1 ? 2 : 0);  // sample takes two bytes
        case PixelPacking::Lsb:
            return (count * format.bits + 7) / 8;
    }
    return 0;
}

Result<std::vector<uint16_t>> unpackGenicamPixels(const GenicamPixelFormat& format,
                                                  std::span<const uint8_t> data,
                                                  int64_t width,
                                                  int64_t height,
                                                  int64_t row_padding_bytes) {
    // 2^28 samples (512 MiB of output) is far beyond any camera and keeps every product below
    // in int64_t.
    constexpr int64_t kMaxSamples = int64_t{1} << 28;
    if (width <= 0 || height <= 0 || width > kMaxSamples / height)
        return badPayload(format, "image of " + std::to_string(width) + " x " +
                                      std::to_string(height) + " samples is empty or too large");
    if (row_padding_bytes < 0 || row_padding_bytes > (int64_t{1} << 20))
        return badPayload(format, "row padding of " + std::to_string(row_padding_bytes) +
                                      " bytes is out of range");
    // Rows either run on as one stream (no padding) or each start on a byte.
    const bool rows_aligned = row_padding_bytes > 0;
    const int64_t row_bytes = genicamPayloadBytes(format, width);
    const int64_t needed = rows_aligned ? (row_bytes + row_padding_bytes) * height
                                        : genicamPayloadBytes(format, width * height);
    if (static_cast<int64_t>(data.size()) < needed)
        return badPayload(format, std::to_string(data.size()) + " bytes for a " +
                                      std::to_string(width) + " x " + std::to_string(height) +
                                      " image that needs " + std::to_string(needed));

    std::vector<uint16_t> samples(static_cast<size_t>(width * height));
    const uint32_t mask = (uint32_t{1} << format.bits) - 1;
    const int64_t rows = rows_aligned ? height : 1;
    const int64_t per_row = rows_aligned ? width : width * height;
    for (int64_t r = 0; r < rows; ++r) {
        const uint8_t* in = data.data() + r * (row_bytes + row_padding_bytes);
        uint16_t* out = samples.data() + r * per_row;
        switch (format.packing) {
            case PixelPacking::None:
                if (format.bits <= 8) {
                    std::copy(in, in + per_row, out);
                } else {
                    for (int64_t i = 0; i < per_row; ++i) {
                        const uint32_t v = in[2 * i] | (uint32_t{in[2 * i + 1]} << 8);
                        if (v > mask)
                            return badPayload(
                                format, "sample " + std::to_string(v) + " at index " +
                                            std::to_string(r * per_row + i) + " exceeds " +
                                            std::to_string(format.bits) +
                                            " bits (is the camera sending left-aligned samples?)");
                        out[i] = static_cast<uint16_t>(v);
                    }
                }
                break;
            case PixelPacking::GigEPacked: {
                const int low_bits = format.bits - 8;  // 2 or 4 low bits per sample in byte 1
                const uint32_t low_mask = (uint32_t{1} << low_bits) - 1;
                for (int64_t i = 0; i < per_row; ++i) {
                    const uint8_t* group = in + 3 * (i / 2);
                    const uint32_t high = (i % 2 == 0) ? group[0] : group[2];
                    const uint32_t low =
                        (i % 2 == 0) ? (group[1] & low_mask) : ((group[1] >> 4) & low_mask);
                    out[i] = static_cast<uint16_t>((high << low_bits) | low);
                }
                break;
            }
            case PixelPacking::Lsb: {
                uint64_t bit = 0;
                for (int64_t i = 0; i < per_row; ++i, bit += format.bits) {
                    // A sample of at most 16 bits spans at most three bytes; read only those
                    // the image holds.
                    const uint64_t first = bit / 8;
                    const uint64_t last = (bit + format.bits - 1) / 8;
                    uint32_t window = 0;
                    for (uint64_t b = first; b <= last; ++b)
                        window |= uint32_t{in[b]} << (8 * (b - first));
                    out[i] = static_cast<uint16_t>((window >> (bit % 8)) & mask);
                }
                break;
            }
        }
    }
    return samples;
}

}  // namespace flarelab::drivers
