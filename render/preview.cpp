#include "render/preview.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <exception>
#include <filesystem>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

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

    // OpenCV stores BGR; encoding to memory (rather than imwrite) keeps the file writing, and
    // its errno, in our hands.
    std::vector<uint8_t> bytes;
    try {
        cv::Mat bgr(static_cast<int>(image.height), static_cast<int>(image.width), CV_8UC3);
        for (int64_t y = 0; y < image.height; ++y) {
            uint8_t* row = bgr.ptr<uint8_t>(static_cast<int>(y));
            const uint8_t* src = preview->pixels.data() + y * image.width * 3;
            for (int64_t x = 0; x < image.width; ++x) {
                row[x * 3 + 0] = src[x * 3 + 2];
                row[x * 3 + 1] = src[x * 3 + 1];
                row[x * 3 + 2] = src[x * 3 + 0];
            }
        }
        if (!cv::imencode(".png", bgr, bytes))
            return makeError(ErrorCode::Internal, "cannot write " + path + ": PNG encoding failed");
    } catch (const std::exception& e) {  // cv::Exception, or bad_alloc from the Mat
        return makeError(ErrorCode::Internal,
                         "cannot write " + path + ": PNG encoding failed: " + e.what());
    }
    return writeAtomically(path, bytes);
}

Result<PreviewImage> readPng(const std::string& path) {
    std::error_code ec;
    if (!std::filesystem::exists(path, ec))
        return makeError(ErrorCode::NotFound, "cannot read " + path + ": no such file");
    try {
        const cv::Mat bgr = cv::imread(path, cv::IMREAD_COLOR);
        if (bgr.empty() || bgr.type() != CV_8UC3)
            return makeError(ErrorCode::ParseError, "cannot read " + path + ": not an 8-bit image");
        PreviewImage out{bgr.cols, bgr.rows, std::vector<uint8_t>(bgr.total() * 3)};
        for (int y = 0; y < bgr.rows; ++y) {
            const uint8_t* row = bgr.ptr<uint8_t>(y);
            uint8_t* dst = out.pixels.data() + static_cast<size_t>(y) * bgr.cols * 3;
            for (int x = 0; x < bgr.cols; ++x) {
                dst[x * 3 + 0] = row[x * 3 + 2];
                dst[x * 3 + 1] = row[x * 3 + 1];
                dst[x * 3 + 2] = row[x * 3 + 0];
            }
        }
        return out;
    } catch (const std::exception& e) {
        return makeError(ErrorCode::ParseError, "cannot read " + path + ": " + e.what());
    }
}

}  // namespace flarelab::render
