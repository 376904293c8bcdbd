#include "render/preview.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <png.h>

namespace flarelab::render {
namespace {

// The sRGB transfer function (IEC 61966-2-1) from linear [0, 1] to encoded [0, 1].
double encodeSrgb(double linear) {
    if (linear <= 0.0031308) return 12.92 * linear;
    return 1.055 * std::pow(linear, 1.0 / 2.4) - 0.055;
}

uint8_t quantize(double display) {
    return static_cast<uint8_t>(std::lround(std::clamp(display, 0.0, 1.0) * 255.0));
}

Error ioError(const std::string& path, const std::string& what, int error_number) {
    return makeError(ErrorCode::IoError,
                     "cannot write " + path + ": " + what + ": " + std::strerror(error_number));
}

// Writes all of `bytes` to a fresh temporary next to `path`, flushes it and renames it into place.
// On failure the temporary is removed and the error names `path`.
Status writeAtomically(const std::string& path, const std::vector<uint8_t>& bytes) {
    std::string temp = path + ".tmp.XXXXXX";
    const int fd = ::mkstemp(temp.data());
    if (fd < 0) return ioError(path, "creating a temporary file", errno);
    const auto fail = [&](const char* what) {
        const int saved = errno;
        ::close(fd);
        ::unlink(temp.c_str());
        return ioError(path, what, saved);
    };
    // mkstemp makes the file private (0600); a preview is for everyone to read.
    if (::fchmod(fd, 0644) != 0) return fail("setting permissions");
    size_t done = 0;
    while (done < bytes.size()) {
        const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
        if (n < 0 && errno == EINTR) continue;
        if (n <= 0) return fail("writing");
        done += static_cast<size_t>(n);
    }
    if (::fsync(fd) != 0) return fail("flushing");
    if (::close(fd) != 0) {
        const int saved = errno;
        ::unlink(temp.c_str());
        return ioError(path, "closing", saved);
    }
    if (::rename(temp.c_str(), path.c_str()) != 0) {
        const int saved = errno;
        ::unlink(temp.c_str());
        return ioError(path, "renaming the temporary file into place", saved);
    }
    return Ok{};
}

}  // namespace

Status validateToneMapOptions(const ToneMapOptions& options) {
    if (!(options.exposure_stops >= -64.0 && options.exposure_stops <= 64.0))
        return makeError(ErrorCode::InvalidArgument,
                         "tone map option exposure_stops must be in -64..64, got " +
                             std::to_string(options.exposure_stops));
    if (!(options.log_range_stops >= 1.0 && options.log_range_stops <= 64.0))
        return makeError(ErrorCode::InvalidArgument,
                         "tone map option log_range_stops must be in 1..64, got " +
                             std::to_string(options.log_range_stops));
    if (options.curve != ToneCurve::Reinhard && options.curve != ToneCurve::Log)
        return makeError(ErrorCode::InvalidArgument, "tone map option curve is not a known curve");
    return Ok{};
}

double toneCurve(double linear, const ToneMapOptions& options) {
    // A float times at most 2^64 stays far inside double's range: no overflow to infinity.
    const double x = linear * std::exp2(options.exposure_stops);
    if (!(x > 0.0)) return 0.0;
    if (options.curve == ToneCurve::Log)
        return std::clamp(1.0 + std::log2(x) / options.log_range_stops, 0.0, 1.0);
    return encodeSrgb(x / (1.0 + x));
}

Result<PreviewImage> toneMap(const ImageRGB& image, const ToneMapOptions& options) {
    if (Status valid = validateToneMapOptions(options); !valid) return valid.error();
    FLARELAB_CHECK_EQ(image.pixels.size(), static_cast<size_t>(image.width * image.height * 3));
    int64_t bad = 0, first = -1;
    for (size_t i = 0; i < image.pixels.size(); ++i) {
        if (std::isfinite(image.pixels[i])) continue;
        if (bad++ == 0) first = static_cast<int64_t>(i);
    }
    if (bad > 0) {
        const int64_t pixel = first / 3;
        return makeError(ErrorCode::InvalidArgument,
                         "image has " + std::to_string(bad) +
                             " non-finite values (NaN or infinity), the first at x=" +
                             std::to_string(pixel % image.width) +
                             " y=" + std::to_string(pixel / image.width) + " channel " +
                             std::to_string(first % 3));
    }
    PreviewImage out{image.width, image.height, std::vector<uint8_t>(image.pixels.size())};
    for (size_t i = 0; i < image.pixels.size(); ++i)
        out.pixels[i] = quantize(toneCurve(image.pixels[i], options));
    return out;
}

Status writePng(const ImageRGB& image, const std::string& path, const ToneMapOptions& options) {
    if (path.empty()) return makeError(ErrorCode::InvalidArgument, "cannot write PNG: empty path");
    if (image.empty())
        return makeError(ErrorCode::InvalidArgument, "cannot write " + path + ": image is empty");
    constexpr int64_t kMaxSide = 65535;
    if (image.width > kMaxSide || image.height > kMaxSide)
        return makeError(ErrorCode::InvalidArgument,
                         "cannot write " + path + ": image is " + std::to_string(image.width) +
                             " x " + std::to_string(image.height) + ", more than " +
                             std::to_string(kMaxSide) + " pixels a side");
    Result<PreviewImage> preview = toneMap(image, options);
    if (!preview) return preview.error().withContext("cannot write " + path);

    // libpng's simplified API encodes to memory, which keeps the file writing, and its errno,
    // in our hands. Its errors come back in image.message, never as a longjmp through our frames.
    png_image png;
    std::memset(&png, 0, sizeof(png));
    png.version = PNG_IMAGE_VERSION;
    png.width = static_cast<png_uint_32>(image.width);
    png.height = static_cast<png_uint_32>(image.height);
    png.format = PNG_FORMAT_RGB;
    const auto stride = static_cast<png_int_32>(image.width * 3);
    png_alloc_size_t size = 0;
    if (!png_image_write_get_memory_size(png, size, 0, preview->pixels.data(), stride, nullptr))
        return makeError(ErrorCode::Internal,
                         "cannot write " + path + ": PNG encoding failed: " + png.message);
    std::vector<uint8_t> bytes(size);
    if (!png_image_write_to_memory(&png, bytes.data(), &size, 0, preview->pixels.data(), stride,
                                   nullptr))
        return makeError(ErrorCode::Internal,
                         "cannot write " + path + ": PNG encoding failed: " + png.message);
    bytes.resize(size);
    return writeAtomically(path, bytes);
}

Result<PreviewImage> readPng(const std::string& path) {
    std::error_code ec;
    if (!std::filesystem::exists(path, ec))
        return makeError(ErrorCode::NotFound, "cannot read " + path + ": no such file");
    png_image png;
    std::memset(&png, 0, sizeof(png));
    png.version = PNG_IMAGE_VERSION;
    if (!png_image_begin_read_from_file(&png, path.c_str()))
        return makeError(ErrorCode::ParseError, "cannot read " + path + ": " + png.message);
    // A header claiming more than 2^28 pixels (768 MiB of RGB, a 16K x 16K image) is refused
    // before anything is allocated.
    constexpr uint64_t kMaxPixels = uint64_t{1} << 28;
    if (png.width == 0 || png.height == 0 ||
        uint64_t{png.width} * uint64_t{png.height} > kMaxPixels) {
        const std::string what = std::to_string(png.width) + " x " + std::to_string(png.height);
        png_image_free(&png);
        return makeError(ErrorCode::ParseError, "cannot read " + path + ": image is " + what +
                                                    " pixels, more than 2^28 or none");
    }
    // 8-bit sRGB; an alpha channel, if any, is composited onto black (the zeroed buffer).
    png.format = PNG_FORMAT_RGB;
    PreviewImage out{static_cast<int64_t>(png.width), static_cast<int64_t>(png.height),
                     std::vector<uint8_t>(PNG_IMAGE_SIZE(png), 0)};
    if (!png_image_finish_read(&png, nullptr, out.pixels.data(), 0, nullptr))
        return makeError(ErrorCode::ParseError, "cannot read " + path + ": " + png.message);
    return out;
}

double autoExposureStops(const ImageRGB& image, double percentile) {
    std::vector<float> lit;
    lit.reserve(image.pixels.size() / 3);
    for (size_t i = 0; i + 2 < image.pixels.size(); i += 3) {
        float peak = 0.0f;
        for (size_t c = 0; c < 3; ++c)
            if (std::isfinite(image.pixels[i + c])) peak = std::max(peak, image.pixels[i + c]);
        if (peak > 0.0f) lit.push_back(peak);
    }
    if (lit.empty()) return 0.0;
    const double p = std::clamp(std::isfinite(percentile) ? percentile : 0.99, 0.0, 1.0);
    const auto k = static_cast<size_t>(std::llround(p * static_cast<double>(lit.size() - 1)));
    std::nth_element(lit.begin(), lit.begin() + static_cast<std::ptrdiff_t>(k), lit.end());
    return std::clamp(-std::log2(static_cast<double>(lit[k])), -64.0, 64.0);
}

}  // namespace flarelab::render
