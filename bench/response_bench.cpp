#include "bench/response_bench.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <iomanip>
#include <opencv2/core.hpp>
#include <opencv2/photo.hpp>
#include <sstream>

#include "drivers/calibration_measure.h"
#include "drivers/sim_camera.h"
#include "optics/prescription.h"

namespace flarelab::bench {
namespace {

using drivers::SimCameraOptions;
using drivers::SimResponse;

double msSince(std::chrono::steady_clock::time_point start) {
    return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
        .count();
}

Result<SimCameraOptions> curveOptions(const std::string& curve, const ResponseBenchOptions& o) {
    SimCameraOptions s;
    s.width_px = o.width;
    s.height_px = o.height;
    s.fixed_angle_deg = o.angle_deg;
    s.hot_pixel_fraction = 1e-4;
    const auto colon = curve.find(':');
    const std::string kind = curve.substr(0, colon);
    double parameter = 0.0;
    if (colon != std::string::npos) {
        try {
            size_t used = 0;
            parameter = std::stod(curve.substr(colon + 1), &used);
            if (used != curve.size() - colon - 1) parameter = 0.0;
        } catch (const std::exception&) {
            parameter = 0.0;
        }
    }
    if (kind == "linear" && colon == std::string::npos) {
        s.response = SimResponse::Linear;
    } else if (kind == "gamma" && parameter > 0.0) {
        s.response = SimResponse::Gamma;
        s.response_gamma = parameter;
    } else if (kind == "log" && parameter > 0.0) {
        s.response = SimResponse::Log;
        s.response_log_range = parameter;
    } else {
        return makeError(
            ErrorCode::InvalidArgument,
            "bench response: curve '" + curve + "' is not linear, gamma:G or log:A with G, A > 0");
    }
    return s;
}

// The frame reduced to 8 bits as an 8-bit camera would give it.
hdr::RawFrame eightBit(const hdr::RawFrame& f) {
    hdr::RawFrame out = f;
    const double scale = 255.0 / (std::ldexp(1.0, f.bit_depth) - 1.0);
    for (uint16_t& s : out.samples)
        s = static_cast<uint16_t>(std::clamp(std::round(s * scale), 0.0, 255.0));
    out.bit_depth = 8;
    out.black_level_dn = f.black_level_dn * scale;
    out.white_level_dn = 255.0;
    return out;
}

cv::Mat toMat(const hdr::RawFrame& eight) {
    cv::Mat m(static_cast<int>(eight.height), static_cast<int>(eight.width), CV_8UC3);
    for (int64_t y = 0; y < eight.height; ++y) {
        auto* row = m.ptr<cv::Vec3b>(static_cast<int>(y));
        for (int64_t x = 0; x < eight.width; ++x)
            row[x] = cv::Vec3b::all(
                static_cast<uint8_t>(eight.samples[static_cast<size_t>(y * eight.width + x)]));
    }
    return m;
}

struct Score {
    double rms = 0.0, max = 0.0;
    int64_t levels = 0;
};

// Scores X_recovered(z) against the simulated camera's curve over 12-bit DN z.
template <typename Recovered>
Score score(const SimCameraOptions& camera, double stops, Recovered recovered) {
    const double full = std::ldexp(1.0, camera.bit_depth) - 1.0;
    const double range = full - camera.black_level_dn;
    const double lowest = std::exp2(-stops);
    std::vector<double> errors;
    for (double z = std::ceil(camera.black_level_dn) + 1.0; z < full; z += 1.0) {
        const double truth =
            drivers::simResponseInverse(camera, (z - camera.black_level_dn) / range);
        if (!(truth >= lowest)) continue;
        const double x = recovered(z);
        errors.push_back(x > 0.0 && std::isfinite(x) ? std::log2(x / truth) : -64.0);
    }
    Score s;
    s.levels = static_cast<int64_t>(errors.size());
    if (errors.empty()) return s;
    std::vector<double> sorted = errors;
    std::nth_element(sorted.begin(),
                     sorted.begin() + static_cast<std::ptrdiff_t>(sorted.size() / 2), sorted.end());
    const double offset = sorted[sorted.size() / 2];
    double sum2 = 0.0;
    for (const double e : errors) {
        sum2 += (e - offset) * (e - offset);
        s.max = std::max(s.max, std::abs(e - offset));
    }
    s.rms = std::sqrt(sum2 / static_cast<double>(errors.size()));
    return s;
}

// Channel 0 of an OpenCV response (256 codes), with the codes it left undefined (Robertson's
// NaN where no sample had that code; anything not positive) filled in linearly from their
// defined neighbours, as a user of it would have to.
std::vector<double> filledResponse(const cv::Mat& response) {
    std::vector<double> x(256);
    std::vector<int> defined;
    for (int c = 0; c < 256; ++c) {
        x[c] = response.at<cv::Vec3f>(c)[0];
        if (std::isfinite(x[c]) && x[c] > 0.0) defined.push_back(c);
    }
    if (defined.empty()) return x;
    for (int c = 0; c < 256; ++c) {
        if (std::isfinite(x[c]) && x[c] > 0.0) continue;
        const auto hi = std::lower_bound(defined.begin(), defined.end(), c);
        if (hi == defined.begin()) {
            x[c] = x[*hi];
        } else if (hi == defined.end()) {
            x[c] = x[defined.back()];
        } else {
            const int a = *(hi - 1), b = *hi;
            x[c] = x[a] + (x[b] - x[a]) * (c - a) / static_cast<double>(b - a);
        }
    }
    return x;
}

// X of a filled OpenCV response at 12-bit DN z, linear between codes.
double openCvAt(const std::vector<double>& response, double z, double full) {
    const double c = std::clamp(z * 255.0 / full, 0.0, 255.0);
    const int lo = std::min(254, static_cast<int>(c));
    const double f = c - lo;
    return (1.0 - f) * response[lo] + f * response[lo + 1];
}

}  // namespace

Result<std::vector<ResponseBenchRow>> runResponseBench(const ResponseBenchOptions& o,
                                                       std::ostream& log) {
    if (o.width < 32 || o.height < 32 || o.width > 8192 || o.height > 8192)
        return makeError(ErrorCode::InvalidArgument, "bench response: width and height: 32..8192");
    if (!(o.stops > 1.0 && o.stops <= 24.0))
        return makeError(ErrorCode::InvalidArgument, "bench response: stops must lie in (1, 24]");
    if (o.curves.empty() || o.seeds.empty())
        return makeError(ErrorCode::InvalidArgument, "bench response: give curves and seeds");
    auto prescription = optics::loadPrescription(o.lens_file);
    if (!prescription) return prescription.error();
    auto lens = optics::Lens::make(*prescription, optics::CameraDescription{});
    if (!lens) return lens.error();

    std::vector<ResponseBenchRow> rows;
    for (const std::string& curve : o.curves) {
        auto base = curveOptions(curve, o);
        if (!base) return base.error();
        for (const uint64_t seed : o.seeds) {
            SimCameraOptions camera_options = *base;
            camera_options.seed = seed;
            auto camera = drivers::SimCamera::make(*lens, camera_options);
            if (!camera) return camera.error();
            drivers::SimCamera& camera_ref = **camera;
            log << "bench response: " << curve << " seed " << seed << ": capturing\n";
            const drivers::CalibrationCapture capture;
            camera_ref.setLensCapped(true);
            auto dark = drivers::captureDarkFrames(camera_ref, capture);
            if (!dark) return dark.error();
            camera_ref.setLensCapped(false);
            auto measured_dark = drivers::measureDark(*dark);
            if (!measured_dark) return measured_dark.error();
            auto exposures =
                drivers::planSeriesExposures(camera_ref, measured_dark->black_level_dn, capture);
            if (!exposures) return exposures.error();
            auto series = drivers::captureSeries(camera_ref, *exposures, capture);
            if (!series) return series.error();
            const double full = std::ldexp(1.0, camera_options.bit_depth) - 1.0;

            const auto row = [&](const std::string& method, int bits) {
                ResponseBenchRow r;
                r.curve = curve;
                r.seed = seed;
                r.method = method;
                r.bits = bits;
                return r;
            };
            // flarelab on the series as captured, and on 8-bit single frames.
            for (const int bits : {12, 8}) {
                drivers::DarkFrames d = *dark;
                std::vector<drivers::ExposureLevel> s = *series;
                double scale = 1.0;
                if (bits == 8) {
                    scale = 255.0 / full;
                    for (auto* frames : {&d.bias, &d.long_dark})
                        for (hdr::RawFrame& f : *frames) f = eightBit(f);
                    for (drivers::ExposureLevel& level : s) {
                        level.frames.resize(1);
                        level.frames[0] = eightBit(level.frames[0]);
                    }
                }
                ResponseBenchRow r = row(bits == 12 ? "flarelab" : "flarelab 8-bit", bits);
                const auto start = std::chrono::steady_clock::now();
                auto md = drivers::measureDark(d);
                if (!md) return md.error().withContext("bench response: " + r.method);
                auto measured = drivers::measureResponse(s, md->black_level_dn, md->noise_floor_dn,
                                                         md->hot_pixels);
                r.ms = msSince(start);
                if (!measured) {
                    r.note = measured.error().message;
                    r.rms_stops = r.max_stops = std::nan("");
                    rows.push_back(r);
                    continue;
                }
                r.linear_verdict = measured->linear;
                const double black = md->black_level_dn;
                const double saturation = measured->saturation_dn;
                const Score sc = score(camera_options, o.stops, [&](double z) {
                    const double code = z * scale;
                    if (measured->curve)
                        return drivers::relativeExposure(*measured->curve, black, code);
                    return std::max(0.0, (code - black) / (saturation - black));
                });
                r.rms_stops = sc.rms;
                r.max_stops = sc.max;
                r.levels = sc.levels;
                if (measured->curve) r.note = measured->curve->method;
                rows.push_back(r);
            }
            if (!o.opencv) continue;
            try {
                std::vector<cv::Mat> images;
                std::vector<float> times;
                for (const drivers::ExposureLevel& level : *series) {
                    images.push_back(toMat(eightBit(level.frames.front())));
                    times.push_back(static_cast<float>(level.exposure_s));
                }
                for (const bool debevec : {true, false}) {
                    ResponseBenchRow r =
                        row(debevec ? "OpenCV CalibrateDebevec" : "OpenCV CalibrateRobertson", 8);
                    cv::Mat response;
                    const auto start = std::chrono::steady_clock::now();
                    if (debevec)
                        cv::createCalibrateDebevec()->process(images, response, times);
                    else
                        cv::createCalibrateRobertson()->process(images, response, times);
                    r.ms = msSince(start);
                    const std::vector<double> filled = filledResponse(response);
                    const Score sc = score(camera_options, o.stops,
                                           [&](double z) { return openCvAt(filled, z, full); });
                    r.rms_stops = sc.rms;
                    r.max_stops = sc.max;
                    r.levels = sc.levels;
                    rows.push_back(r);
                }
            } catch (const cv::Exception& e) {
                return makeError(ErrorCode::Internal,
                                 std::string("bench response: OpenCV: ") + e.what());
            }
        }
    }
    return rows;
}

void printResponseBench(const std::vector<ResponseBenchRow>& rows, std::ostream& out) {
    out << "| curve | seed | method | bits | verdict | RMS error (stops) | max error (stops) | "
           "DN levels | time (ms) |\n";
    out << "| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n";
    for (const ResponseBenchRow& r : rows) {
        std::ostringstream line;
        line << std::fixed << std::setprecision(3);
        line << "| " << r.curve << " | " << r.seed << " | " << r.method << " | " << r.bits << " | "
             << (r.method.rfind("flarelab", 0) == 0 ? (r.linear_verdict ? "linear" : "not linear")
                                                    : "-")
             << " | " << r.rms_stops << " | " << r.max_stops << " | " << r.levels << " | "
             << std::setprecision(1) << r.ms << " |";
        out << line.str() << "\n";
    }
}

nlohmann::json responseBenchJson(const std::vector<ResponseBenchRow>& rows) {
    nlohmann::json doc = nlohmann::json::array();
    for (const ResponseBenchRow& r : rows)
        doc.push_back({{"curve", r.curve},
                       {"seed", r.seed},
                       {"method", r.method},
                       {"bits", r.bits},
                       {"linear_verdict", r.linear_verdict},
                       {"rms_error_stops", std::isfinite(r.rms_stops) ? nlohmann::json(r.rms_stops)
                                                                      : nlohmann::json()},
                       {"max_error_stops", std::isfinite(r.max_stops) ? nlohmann::json(r.max_stops)
                                                                      : nlohmann::json()},
                       {"levels", r.levels},
                       {"ms", r.ms},
                       {"note", r.note}});
    return doc;
}

}  // namespace flarelab::bench
