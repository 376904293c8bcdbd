#include "fit/sweep_fit.h"

#include <Eigen/Dense>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <ctime>
#include <future>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <numeric>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <system_error>
#include <thread>
#include <utility>

#include "fit/model_eval.h"

namespace flarelab::fit {
namespace {

Error invalid(const std::string& message) {
    return makeError(ErrorCode::InvalidArgument, "sweep fit: " + message);
}

// Two ghosts that describe the same thing: centres and extents within 2% of the larger ghost's
// size, plus half a pixel.
bool sameGhost(const GhostState& a, const GhostState& b, double half_pixel_mm) {
    const double tolerance = 0.02 * std::max(ghostSize(a), ghostSize(b)) + half_pixel_mm;
    return std::abs(a.shape.centre_x_mm - b.shape.centre_x_mm) <= tolerance &&
           std::abs(a.shape.centre_y_mm - b.shape.centre_y_mm) <= tolerance &&
           std::abs(a.shape.half_height_mm - b.shape.half_height_mm) <= tolerance &&
           std::abs(a.shape.left_mm - b.shape.left_mm) <= tolerance &&
           std::abs(a.shape.right_mm - b.shape.right_mm) <= tolerance;
}

// A ghost whose border and inner intensities are all below this many noise sigmas has faded.
constexpr double kFadedSigmas = 2.0;

// A frame's "light" whose peak is under this share of the brightest light of the probed frames
// is a ghost: the light itself is out of view there and the brightest blob is a small bright
// ghost, which the detection would leave out as the light's disc. On the shipped lenses'
// simulated sweeps (planned brackets) the light peaks at 1.3e10 to 1e12 DN/s wherever it is in
// view, and what the detection took for it elsewhere at 4e-10 to 9e-4 of the sweep's brightest
// (docs/fit-scoring.md). Where the merge clips the light (fixed brackets), its peak is the
// merge's ceiling, and ghosts above a hundredth of it are still taken for it, as before.
constexpr double kLightPeakShare = 1e-2;

// Whether a fitted state is a plausible outcome of a fit started at `from`: the centre moved by
// at most `move` of from's radius, each extent changed by at most a factor `factor` (both plus
// `slack_mm`). A fit that runs off (a diverged optimizer, a ghost pulled onto a neighbour) is not
// taken as a sample.
bool plausibleFit(
    const GhostState& from, const GhostState& fitted, double move, double factor, double slack_mm) {
    const auto& a = from.shape;
    const auto& b = fitted.shape;
    if (std::hypot(b.centre_x_mm - a.centre_x_mm, b.centre_y_mm - a.centre_y_mm) >
        move * ghostSize(from) + slack_mm)
        return false;
    const auto within = [&](double x, double y) {
        return y <= factor * x + slack_mm && x <= factor * y + slack_mm;
    };
    return within(a.half_height_mm, b.half_height_mm) && within(a.left_mm, b.left_mm) &&
           within(a.right_mm, b.right_mm);
}

struct Track {
    int64_t id = 0;
    int64_t path = -1;                 // PathSeed::path, -1 when born from a detection
    std::vector<TrackSample> samples;  // in the order fitted; sorted at the end
    int missed = 0;
    bool live = false;
    int born_frame = 0;
    int born_direction = 0;  // +1 in the forward pass, -1 in the backward pass, 0 at the start
};

// A track's sample in a frame.
struct FrameEntry {
    size_t track = 0;
    size_t sample = 0;
};

// The state a track predicts at `angle_deg`: per parameter, the least-squares polynomial of
// degree min(degree, n - 1) through its `history` samples nearest the angle (all on one side: a
// track is followed away from what it has), evaluated there.
// Guards against wild extrapolation from noisy samples: ln intensities are floored at
// ln_floor (a channel fitted to 0 has ln -80, which would swing the polynomial), and each predicted
// parameter stays within the history's range widened by that range on either side (a smooth
// parameter moves on by about one step of the history's span).
GhostState predictState(
    const Track& track, double angle_deg, int history, int degree, double ln_floor) {
    const auto& samples = track.samples;
    std::vector<size_t> order(samples.size());
    std::iota(order.begin(), order.end(), size_t{0});
    std::sort(order.begin(), order.end(), [&](size_t a, size_t b) {
        return std::abs(samples[a].angle_deg - angle_deg) <
               std::abs(samples[b].angle_deg - angle_deg);
    });
    const size_t m = std::min(order.size(), static_cast<size_t>(history));
    const GhostState& nearest = samples[order[0]].state;
    if (m <= 1) return nearest;
    const int d = std::min(degree, static_cast<int>(m) - 1);
    double scale = 0.0;
    for (size_t r = 0; r < m; ++r)
        scale = std::max(scale, std::abs(samples[order[r]].angle_deg - angle_deg));
    if (!(scale > 0.0)) return nearest;
    Eigen::MatrixXd a(static_cast<Eigen::Index>(m), d + 1);
    Eigen::MatrixXd b(static_cast<Eigen::Index>(m), kGhostParameterCount);
    for (size_t r = 0; r < m; ++r) {
        const auto& sample = samples[order[r]];
        const double t = (sample.angle_deg - angle_deg) / scale;
        double power = 1.0;
        for (int k = 0; k <= d; ++k, power *= t) a(static_cast<Eigen::Index>(r), k) = power;
        const GhostParameters values = ghostParameters(sample.state, ln_floor);
        for (int p = 0; p < kGhostParameterCount; ++p)
            b(static_cast<Eigen::Index>(r), p) = values[p];
    }
    const Eigen::MatrixXd x = a.colPivHouseholderQr().solve(b);
    GhostParameters predicted{};
    for (int p = 0; p < kGhostParameterCount; ++p) {
        const double lo = b.col(p).minCoeff(), hi = b.col(p).maxCoeff();
        predicted[p] = std::clamp(x(0, p), lo - (hi - lo), hi + (hi - lo));  // the value at t = 0
    }
    auto state = ghostStateFromParameters(predicted);
    return state ? *state : nearest;
}

using Clock = std::chrono::steady_clock;

// The median gap between neighbouring angles (in sorted order); 0 with fewer than two.
double medianStep(std::vector<double> angles) {
    std::sort(angles.begin(), angles.end());
    return medianSpacing(angles);
}

// A path seed's ghost as the frame shows it: the seed's outline with circle-like falloffs, its
// inner intensity the median of the frame over the sky inside half its extents, its border the
// 90th percentile between 0.6 and 1 of them (per channel; excluded pixels and pixels off the
// frame are not looked at). nullopt when too little of it is in the frame to say.
std::optional<GhostState> seedState(const FitFrame& frame,
                                    const FrameDetection& detection,
                                    const render::GhostShapeParams& shape,
                                    int channels) {
    const auto& m = frame.mapping;
    const int64_t w = frame.image.width, h = frame.image.height;
    const double x0 = m.centre_x_px + (shape.centre_x_mm - shape.left_mm) * m.px_per_mm_x;
    const double x1 = m.centre_x_px + (shape.centre_x_mm + shape.right_mm) * m.px_per_mm_x;
    const double y0 = m.centre_y_px + (shape.centre_y_mm - shape.half_height_mm) * m.px_per_mm_y;
    const double y1 = m.centre_y_px + (shape.centre_y_mm + shape.half_height_mm) * m.px_per_mm_y;
    const int64_t ix0 = std::max<int64_t>(0, static_cast<int64_t>(std::floor(x0)));
    const int64_t ix1 = std::min<int64_t>(w - 1, static_cast<int64_t>(std::ceil(x1)));
    const int64_t iy0 = std::max<int64_t>(0, static_cast<int64_t>(std::floor(y0)));
    const int64_t iy1 = std::min<int64_t>(h - 1, static_cast<int64_t>(std::ceil(y1)));
    if (ix1 < ix0 || iy1 < iy0) return std::nullopt;
    // About 4096 pixels looked at, whatever the ghost's size.
    const double area = static_cast<double>(ix1 - ix0 + 1) * static_cast<double>(iy1 - iy0 + 1);
    const int64_t stride = std::max<int64_t>(1, static_cast<int64_t>(std::sqrt(area / 4096.0)));
    std::array<std::vector<float>, 3> inner, border;
    for (int64_t y = iy0; y <= iy1; y += stride) {
        const double dy_mm =
            (static_cast<double>(y) + 0.5 - m.centre_y_px) / m.px_per_mm_y - shape.centre_y_mm;
        for (int64_t x = ix0; x <= ix1; x += stride) {
            const size_t i = static_cast<size_t>(y * w + x);
            if (detection.excluded[i]) continue;
            const double dx_mm =
                (static_cast<double>(x) + 0.5 - m.centre_x_px) / m.px_per_mm_x - shape.centre_x_mm;
            const double ex = dx_mm < 0.0 ? shape.left_mm : shape.right_mm;
            const double r = std::hypot(dx_mm / std::max(ex, 1e-9),
                                        dy_mm / std::max(shape.half_height_mm, 1e-9));
            for (int c = 0; c < channels; ++c) {
                const float v =
                    static_cast<float>(frame.image.pixels[3 * i + static_cast<size_t>(c)] -
                                       detection.background[static_cast<size_t>(c)]);
                if (!std::isfinite(v)) continue;
                if (r <= 0.5)
                    inner[static_cast<size_t>(c)].push_back(v);
                else if (r >= 0.6 && r <= 1.0)
                    border[static_cast<size_t>(c)].push_back(v);
            }
        }
    }
    if (inner[0].size() + border[0].size() < 8) return std::nullopt;
    const auto at = [](std::vector<float>& v, double q) -> double {
        if (v.empty()) return 0.0;
        const size_t k =
            std::min(v.size() - 1, static_cast<size_t>(q * static_cast<double>(v.size())));
        std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
        return std::max(0.0, static_cast<double>(v[k]));
    };
    GhostState state;
    state.shape = shape;
    for (int c = 0; c < 3; ++c) {
        const size_t k = static_cast<size_t>(std::min(c, channels - 1));
        state.shading.inner_rgb[static_cast<size_t>(c)] = at(inner[k], 0.5);
        state.shading.border_rgb[static_cast<size_t>(c)] =
            std::max(at(border[k], 0.9), state.shading.inner_rgb[static_cast<size_t>(c)]);
    }
    const double px_mm = 1.0 / std::max(m.px_per_mm_x, m.px_per_mm_y);
    const double extent = std::min({shape.left_mm + shape.right_mm, 2.0 * shape.half_height_mm});
    state.shading.inner_falloff_mm = std::max(0.15 * 0.5 * extent, px_mm);
    state.shading.outer_falloff_mm = 1.5 * px_mm;
    return state;
}

double msSince(Clock::time_point t0) {
    return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

// Frames read once and kept, with their detections, the least recently used let go beyond a
// byte budget. Not thread safe: the sweep fit's passes call their frame source under a lock.
class FrameCache {
public:
    FrameCache(std::function<Result<FitFrame>(size_t)> load, int64_t budget_bytes)
        : load_(std::move(load)), budget_(budget_bytes) {}

    Result<FitFrame> get(size_t index) {
        auto entry = find(index);
        if (!entry) return entry.error();
        if (*entry) return (*entry)->frame;
        return load_(index);  // too large to keep
    }

    Result<FrameDetection> detect(size_t index,
                                  const FitFrame& frame,
                                  const DetectOptions& options) {
        const auto found = entries_.find(index);
        if (found == entries_.end()) return detectGhosts(frame, options);
        Entry& entry = found->second;
        entry.used = ++clock_;
        if (entry.detection && entry.detect_options == options) return *entry.detection;
        auto detection = detectGhosts(frame, options);
        if (!detection) return detection;
        const int64_t bytes = static_cast<int64_t>(
            detection->excluded.size() + detection->candidates.size() * sizeof(GhostCandidate));
        release(entry.detection_bytes);
        entry.detection.reset();
        entry.detection_bytes = 0;
        if (!makeRoom(bytes, index)) return detection;
        entry.detection = *detection;
        entry.detect_options = options;
        entry.detection_bytes = bytes;
        used_ += bytes;
        return detection;
    }

    // Frame `index` and its detection with `options` read into memory, where they fit in it.
    void prefetch(size_t index, const DetectOptions& options) {
        auto entry = find(index);
        if (!entry || !*entry) return;  // unreadable (the load will say why) or too large
        (void)detect(index, (*entry)->frame, options);
    }

private:
    struct Entry {
        FitFrame frame;
        int64_t bytes = 0;  // the frame's
        std::optional<FrameDetection> detection;
        DetectOptions detect_options;
        int64_t detection_bytes = 0;
        uint64_t used = 0;
    };

    // The entry of frame `index`, read now if it is not kept; null when it cannot be kept.
    Result<Entry*> find(size_t index) {
        const auto found = entries_.find(index);
        if (found != entries_.end()) {
            found->second.used = ++clock_;
            return &found->second;
        }
        auto frame = load_(index);
        if (!frame) return frame.error();
        const int64_t bytes = static_cast<int64_t>(frame->image.pixels.size() * sizeof(float) +
                                                   frame->lower_bound.size() + sizeof(FitFrame));
        if (!makeRoom(bytes, index)) return static_cast<Entry*>(nullptr);
        Entry& entry = entries_[index];
        entry.frame = std::move(*frame);
        entry.bytes = bytes;
        entry.used = ++clock_;
        used_ += bytes;
        return &entry;
    }

    void release(int64_t bytes) { used_ -= bytes; }

    // Lets the least recently used entries (never `keep`) go until `bytes` more fit the budget;
    // false when they cannot.
    bool makeRoom(int64_t bytes, size_t keep) {
        if (bytes > budget_) return false;
        while (used_ + bytes > budget_) {
            auto oldest = entries_.end();
            for (auto it = entries_.begin(); it != entries_.end(); ++it)
                if (it->first != keep &&
                    (oldest == entries_.end() || it->second.used < oldest->second.used))
                    oldest = it;
            if (oldest == entries_.end()) return false;
            release(oldest->second.bytes + oldest->second.detection_bytes);
            entries_.erase(oldest);
        }
        return true;
    }

    std::function<Result<FitFrame>(size_t)> load_;
    int64_t budget_ = 0;
    int64_t used_ = 0;
    uint64_t clock_ = 0;
    std::map<size_t, Entry> entries_;
};

std::string nowUtc() {
    const std::time_t now = std::time(nullptr);
    std::tm tm{};
    gmtime_r(&now, &tm);
    char text[32];
    std::strftime(text, sizeof text, "%Y-%m-%dT%H:%M:%SZ", &tm);
    return text;
}

// What the forward and the backward pass share while they run side by side: the frame source
// (whose loader need not be thread safe), the progress callback, and a stop when one fails.
struct PassShare {
    std::mutex source;
    std::mutex progress;
    int64_t frames_fitted = 0;  // both passes', for progress
    std::atomic<bool> stop{false};
};

class SweepFitter {
public:
    SweepFitter(const FrameSource& frames,
                const SweepFitOptions& options,
                const std::function<void(const SweepFitProgress&)>& progress)
        : frames_(frames), options_(options), progress_(progress) {}

    Result<SweepFitResult> run();

private:
    Result<int> chooseStart();
    // The backward pass from the start frame s, on this fitter (a copy of the forward one's
    // state, see run).
    Status backwardPass(size_t s);
    // Takes the backward pass's tracks, samples and frame entries into this fitter, numbering the
    // tracks it started after every track of this one, as if it had run after the forward pass.
    // `snapshot` holds each track's sample count when the two passes parted.
    void mergeBackward(SweepFitter& backward, const std::vector<size_t>& snapshot, size_t s);
    // Fits frame j: the live tracks (predicted; updated to those still live afterwards), new
    // tracks from unexplained detections when allow_new, and with `extend` the ghosts stored at j
    // for the other tracks as context (fitted too, not ended).
    Status processFrame(
        size_t j, std::vector<size_t>& live, bool allow_new, int direction, bool extend);

    // The frame source's loader, refusing once options_.cancel is set (or the other pass failed).
    Result<FitFrame> load(size_t index) {
        if (options_.cancel && options_.cancel->load())
            return makeError(ErrorCode::Unsupported, "sweep fit: cancelled");
        if (share_->stop.load()) return makeError(ErrorCode::Unsupported, "sweep fit: stopped");
        const auto t0 = Clock::now();
        std::lock_guard<std::mutex> lock(share_->source);
        auto frame = frames_.load(index);
        result_.stages.load_ms += msSince(t0);
        return frame;
    }
    // The options frame j is detected with: circles (which only start tracks) in the start frame,
    // every detect_every frames from it and wherever no track is live; in between the
    // predictions carry the fit and the cheap blobs still match. None when following a track
    // back, nor with the paths as seeds (the seeds start the tracks).
    DetectOptions detectOptionsAt(size_t j, bool any_live, bool extend) const {
        DetectOptions detect = detect_;
        if (!fullDetectionAt(j, any_live, extend)) detect.circles = false;
        return detect;
    }
    // Whether frame j is detected in full (see detectOptionsAt).
    bool fullDetectionAt(size_t j, bool any_live, bool extend) const {
        const int64_t from_start = std::abs(static_cast<int64_t>(j) - static_cast<int64_t>(start_));
        if (any_live && from_start % options_.detect_every != 0) return false;
        return !extend && !options_.path_seeds;
    }
    // Frame `index` loaded and detected into the source's memory on another thread while this
    // pass fits the frame before it (FrameSource::prefetch), with the options the pass will
    // detect it with unless no track is live then. The last read-ahead is waited for first.
    void readAhead(size_t index, const DetectOptions& options) {
        settleReadAhead();
        if (!frames_.prefetch) return;
        try {
            ahead_ = std::async(std::launch::async, [this, index, options] {
                const auto t0 = Clock::now();
                if ((options_.cancel && options_.cancel->load()) || share_->stop.load()) return 0.0;
                try {
                    std::lock_guard<std::mutex> lock(share_->source);
                    frames_.prefetch(index, options);
                } catch (const std::exception&) {
                    // The pass reads the frame itself, and reports what went wrong.
                }
                return msSince(t0);
            });
        } catch (const std::system_error&) {
            // No thread to spare: the pass reads the frame itself when it gets there.
        }
    }
    void settleReadAhead() {
        if (ahead_.valid()) result_.stages.ahead_ms += ahead_.get();
    }
    Result<FrameDetection> detectIn(size_t index,
                                    const FitFrame& frame,
                                    const DetectOptions& options) {
        const auto t0 = Clock::now();
        Result<FrameDetection> detection = makeError(ErrorCode::Internal, "not detected");
        if (frames_.detect) {
            std::lock_guard<std::mutex> lock(share_->source);
            detection = frames_.detect(index, frame, options);
        } else {
            detection = detectGhosts(frame, options);
        }
        result_.stages.detect_ms += msSince(t0);
        return detection;
    }

    const FrameSource& frames_;
    const SweepFitOptions& options_;
    const std::function<void(const SweepFitProgress&)>& progress_;
    std::vector<Track> tracks_;
    std::vector<std::vector<FrameEntry>> at_frame_;
    // The light's disc the detection left out of each frame this fitter processed (the sweep's
    // frames, by index).
    std::vector<std::optional<LightSpot>> lights_;
    SweepFitResult result_;
    int64_t frames_total_ = 0;
    size_t start_ = 0;
    std::shared_ptr<PassShare> share_ = std::make_shared<PassShare>();
    // The sky: the lowest background of the probed frames. The camera and the sky do not change
    // along a sweep, the ghosts only add light, so a frame whose own background lies above it
    // holds a ghost larger than the frame (a veil with no edge in view).
    std::array<double, 3> sky_ = {std::numeric_limits<double>::infinity(),
                                  std::numeric_limits<double>::infinity(),
                                  std::numeric_limits<double>::infinity()};
    // options_.detect, with a floor under the light's peak once the probes have shown the light.
    DetectOptions detect_ = options_.detect;
    // The sweep's step: the median gap between neighbouring frame angles (0 for one frame).
    double step_deg_ = medianStep(frames_.angles_deg);
    // The read-ahead in flight (readAhead): its time, ms. Declared last, so that it is waited
    // for before anything it uses goes.
    std::future<double> ahead_;
};

Result<int> SweepFitter::chooseStart() {
    const int n = static_cast<int>(frames_.angles_deg.size());
    if (options_.start_frame >= 0) return options_.start_frame;
    const int probes = std::min(options_.start_probes, n);
    std::vector<int> indices;
    if (probes == 1) {
        indices.push_back((n - 1) / 2);
    } else {
        for (int i = 0; i < probes; ++i) {
            const int index =
                static_cast<int>(std::lround(static_cast<double>(i) * (n - 1) / (probes - 1)));
            if (indices.empty() || indices.back() != index) indices.push_back(index);
        }
    }
    std::vector<size_t> counts;
    double brightest_light = 0.0;
    for (const int index : indices) {
        auto frame = load(static_cast<size_t>(index));
        if (!frame) return frame.error().withContext("frame " + std::to_string(index));
        auto detection = detectIn(static_cast<size_t>(index), *frame, options_.detect);
        if (!detection) return detection.error();
        for (int c = 0; c < 3; ++c)
            sky_[c] = std::min(sky_[c], detection->background[static_cast<size_t>(c)]);
        if (detection->light.found)
            brightest_light = std::max(brightest_light, detection->light.peak);
        counts.push_back(detection->candidates.size());
    }
    if (counts.empty()) return 0;
    // Of the probes that show nearly as many ghosts as the most any shows, the one nearest the
    // middle: the two passes from it then take about as long, and they run side by side.
    const size_t most = *std::max_element(counts.begin(), counts.end());
    const auto off_middle = [&](int k) { return std::abs(2 * k - (n - 1)); };
    int best = -1;
    for (size_t i = 0; i < indices.size(); ++i) {
        if (static_cast<double>(counts[i]) < options_.start_min_share * static_cast<double>(most))
            continue;
        if (best < 0 || off_middle(indices[i]) < off_middle(best)) best = indices[i];
    }
    detect_.min_light_peak =
        std::max(options_.detect.min_light_peak, kLightPeakShare * brightest_light);
    return best;
}

Status SweepFitter::processFrame(
    size_t j, std::vector<size_t>& live, bool allow_new, int direction, bool extend) {
    auto frame = load(j);
    if (!frame) return frame.error().withContext("frame " + std::to_string(j));
    auto detection = detectIn(j, *frame, detectOptionsAt(j, !live.empty(), extend));
    if (!detection) return detection.error();
    if (!extend) {  // the start frame's pass (direction 0) goes on forward
        const int64_t next = static_cast<int64_t>(j) + (direction != 0 ? direction : +1);
        if (next >= 0 && next < static_cast<int64_t>(frames_.angles_deg.size()))
            readAhead(static_cast<size_t>(next),
                      detectOptionsAt(static_cast<size_t>(next), true, false));
    }
    lights_[j] = detection->light;
    const double angle = frames_.angles_deg[j];
    const auto& mapping = frame->mapping;
    // Fit above the sky; what this frame's background holds beyond it is a frame-filling ghost.
    std::array<double, 3> veil{};
    bool veiled = false;
    for (int c = 0; c < 3; ++c) {
        if (!std::isfinite(sky_[c])) continue;
        veil[c] = detection->background[c] - sky_[c];
        detection->background[c] = sky_[c];
        veiled = veiled || veil[c] > options_.detect.threshold_sigmas * detection->noise_sigma[c];
    }
    const double half_pixel_mm = 0.5 / std::max(mapping.px_per_mm_x, mapping.px_per_mm_y);
    const double pixel_mm = 2.0 * half_pixel_mm;
    const int channels = std::clamp(frame->channels, 1, 3);

    // Context: the other tracks' ghosts stored at this frame.
    std::vector<FrameEntry> context;
    if (extend) {
        for (const FrameEntry& entry : at_frame_[j])
            if (std::find(live.begin(), live.end(), entry.track) == live.end())
                context.push_back(entry);
    }
    double min_sigma = std::numeric_limits<double>::infinity();
    for (int c = 0; c < channels; ++c) min_sigma = std::min(min_sigma, detection->noise_sigma[c]);
    const double ln_floor = std::log(std::max(0.1 * min_sigma, 1e-30));
    std::vector<GhostState> predicted(live.size());
    for (size_t i = 0; i < live.size(); ++i)
        predicted[i] = predictState(tracks_[live[i]], angle, options_.history,
                                    options_.prediction_degree, ln_floor);
    std::vector<PathSeed> seeds;
    if (options_.path_seeds) {
        const auto t_seed = Clock::now();
        auto made = options_.path_seeds(angle);
        result_.stages.seed_ms += msSince(t_seed);
        if (!made)
            return made.error().withContext("path seeds at " + std::to_string(angle) + " deg");
        seeds = std::move(*made);
        // A path's ghost is where the optics core puts it: the seed's outline is the prior of
        // the track's shape, its history keeps the shading (the history's shape as prior scored
        // worse: docs/path-tracking.md).
        for (size_t i = 0; i < live.size(); ++i)
            for (const PathSeed& seed : seeds)
                if (seed.path == tracks_[live[i]].path) predicted[i].shape = seed.shape;
    }

    // Detections in mm.
    const auto& candidates = detection->candidates;
    const auto toMm = [&](const Eigen::Vector2d& px) -> Eigen::Vector2d {
        return {(px.x() - mapping.centre_x_px) / mapping.px_per_mm_x,
                (px.y() - mapping.centre_y_px) / mapping.px_per_mm_y};
    };
    std::vector<Eigen::Vector2d> centroid_mm(candidates.size());
    for (size_t c = 0; c < candidates.size(); ++c) centroid_mm[c] = toMm(candidates[c].centroid_px);
    // How far a detection is from a ghost: centre and radius differences over the radius.
    // Centres alone would call concentric discs of different sizes (every ghost at 0 degrees) one.
    const auto distanceTo = [&](const GhostState& state, const Eigen::Vector2d& centre_mm,
                                double candidate_radius) {
        const double radius = std::max(ghostSize(state), 2.0 * pixel_mm);
        // The box's centre: what a detection's centroid estimates.
        const double box_x =
            state.shape.centre_x_mm + 0.5 * (state.shape.right_mm - state.shape.left_mm);
        return (std::hypot(centre_mm.x() - box_x, centre_mm.y() - state.shape.centre_y_mm) +
                std::abs(candidate_radius - radius)) /
               radius;
    };
    const auto normalisedDistance = [&](const GhostState& state, size_t c) {
        return distanceTo(state, centroid_mm[c], ghostSize(candidates[c].initial));
    };

    // The brightest of the ghost's border and inner intensities, in noise sigmas.
    const auto peakSigmas = [&](const GhostState& s) {
        double peak = 0.0;
        for (int c = 0; c < channels; ++c) {
            const double sigma = std::max(detection->noise_sigma[c], 1e-30);
            peak =
                std::max(peak, std::max(s.shading.border_rgb[c], s.shading.inner_rgb[c]) / sigma);
        }
        return peak;
    };

    const double frame_diagonal_mm =
        std::hypot(static_cast<double>(frame->image.width) / mapping.px_per_mm_x,
                   static_cast<double>(frame->image.height) / mapping.px_per_mm_y);

    // Greedy matching by normalised distance.
    struct Pair {
        double distance;
        size_t track;
        size_t candidate;
    };
    std::vector<Pair> pairs;
    for (size_t i = 0; i < live.size(); ++i)
        for (size_t c = 0; c < candidates.size(); ++c) {
            const double d = normalisedDistance(predicted[i], c);
            if (d <= options_.match_radius) pairs.push_back({d, i, c});
        }
    std::sort(pairs.begin(), pairs.end(),
              [](const Pair& a, const Pair& b) { return a.distance < b.distance; });
    std::vector<bool> matched(live.size(), false), used(candidates.size(), false);
    std::vector<int64_t> match_of(live.size(), -1);
    for (const Pair& pair : pairs) {
        if (matched[pair.track] || used[pair.candidate]) continue;
        matched[pair.track] = true;
        used[pair.candidate] = true;
        match_of[pair.track] = static_cast<int64_t>(pair.candidate);
    }

    // The frame's extent in mm, for "left the frame".
    const double frame_x0 = -mapping.centre_x_px / mapping.px_per_mm_x;
    const double frame_x1 =
        (static_cast<double>(frame->image.width) - mapping.centre_x_px) / mapping.px_per_mm_x;
    const double frame_y0 = -mapping.centre_y_px / mapping.px_per_mm_y;
    const double frame_y1 =
        (static_cast<double>(frame->image.height) - mapping.centre_y_px) / mapping.px_per_mm_y;
    // Out of view: less than a tenth of the ghost's box lies in the frame (a ghost that is all
    // but gone cannot be fitted: the data no longer holds its size or intensity).
    const auto outside = [&](const GhostState& s) {
        const double x0 = s.shape.centre_x_mm - s.shape.left_mm;
        const double x1 = s.shape.centre_x_mm + s.shape.right_mm;
        const double y0 = s.shape.centre_y_mm - s.shape.half_height_mm;
        const double y1 = s.shape.centre_y_mm + s.shape.half_height_mm;
        const double w = std::max(0.0, std::min(frame_x1, x1) - std::max(frame_x0, x0));
        const double h = std::max(0.0, std::min(frame_y1, y1) - std::max(frame_y0, y0));
        const double in_view =
            std::min((x1 - x0) * (y1 - y0), (frame_x1 - frame_x0) * (frame_y1 - frame_y0));
        return !(w * h >= 0.1 * in_view);
    };

    // New tracks from detections that no ghost explains.
    std::vector<size_t> born;
    std::vector<GhostState> born_states;
    const auto startTrack = [&](const GhostState& state, int64_t path = -1) {
        Track track;
        track.id = static_cast<int64_t>(tracks_.size());
        track.path = path;
        track.live = true;
        track.born_frame = static_cast<int>(j);
        track.born_direction = direction;
        tracks_.push_back(std::move(track));
        born.push_back(tracks_.size() - 1);
        born_states.push_back(state);
    };
    // With the prescription's paths: which are in view here, and new tracks from those no track
    // follows.
    std::vector<int64_t> seen_paths;
    if (options_.path_seeds) {
        const auto t_seed = Clock::now();
        std::vector<int64_t> followed;
        for (const size_t t : live) followed.push_back(tracks_[t].path);
        for (const auto& entry : context) followed.push_back(tracks_[entry.track].path);
        for (const PathSeed& seed : seeds) {
            auto state = seedState(*frame, *detection, seed.shape, channels);
            if (!state || outside(*state) ||
                std::min(state->shape.left_mm + state->shape.right_mm,
                         2.0 * state->shape.half_height_mm) < 2.0 * pixel_mm ||
                peakSigmas(*state) < kFadedSigmas)
                continue;
            seen_paths.push_back(seed.path);
            if (!allow_new ||
                std::find(followed.begin(), followed.end(), seed.path) != followed.end())
                continue;
            if (static_cast<int>(live.size() + born.size()) >= options_.max_ghosts) continue;
            followed.push_back(seed.path);
            startTrack(*state, seed.path);
        }
        result_.stages.seed_ms += msSince(t_seed);
    }
    if (allow_new && !options_.path_seeds) {
        for (size_t c = 0; c < candidates.size(); ++c) {
            if (used[c]) continue;
            if (static_cast<int>(live.size() + born.size()) >= options_.max_ghosts) break;
            // A detection's ghost may be centred off the frame (a circle's visible arc), but it
            // must be in view, bright enough and of a plausible size.
            if (outside(candidates[c].initial)) continue;
            if (peakSigmas(candidates[c].initial) < kFadedSigmas) continue;
            if (ghostSize(candidates[c].initial) > 4.0 * frame_diagonal_mm) continue;
            bool explained = false;
            for (const auto& state : predicted)
                explained = explained || normalisedDistance(state, c) <= options_.duplicate_radius;
            for (const auto& entry : context)
                explained = explained ||
                            normalisedDistance(tracks_[entry.track].samples[entry.sample].state,
                                               c) <= options_.duplicate_radius;
            for (const auto& state : born_states)
                explained = explained || normalisedDistance(state, c) <= options_.duplicate_radius;
            if (explained) continue;
            startTrack(candidates[c].initial);
        }
        // A veil: light above the sky everywhere, from a ghost whose rim lies outside the frame.
        // It is followed as a ghost centred on the axis, larger than the frame, unless a ghost
        // already covers the whole frame.
        const auto covers = [&](const GhostState& g) {
            return g.shape.centre_x_mm - g.shape.left_mm <= frame_x0 &&
                   g.shape.centre_x_mm + g.shape.right_mm >= frame_x1 &&
                   g.shape.centre_y_mm - g.shape.half_height_mm <= frame_y0 &&
                   g.shape.centre_y_mm + g.shape.half_height_mm >= frame_y1;
        };
        bool covered = false;
        for (const auto& state : predicted) covered = covered || covers(state);
        for (const auto& state : born_states) covered = covered || covers(state);
        for (const auto& entry : context)
            covered = covered || covers(tracks_[entry.track].samples[entry.sample].state);
        if (veiled && !covered &&
            static_cast<int>(live.size() + born.size()) < options_.max_ghosts) {
            GhostState state;
            state.shape = render::circleGhostShape(0.0, 0.0, 1.5 * frame_diagonal_mm);
            for (int c = 0; c < 3; ++c) {
                const double level = std::max(0.0, veil[channels == 1 ? 0 : c]);
                state.shading.border_rgb[c] = level;
                state.shading.inner_rgb[c] = level;
            }
            state.shading.inner_falloff_mm = 0.1 * frame_diagonal_mm;
            state.shading.outer_falloff_mm = 4.0 * pixel_mm;
            startTrack(state);
        }
    }

    // Fit the live and new ghosts; the context (ghosts stored at this frame by other tracks) is
    // part of the model but stays as it was fitted.
    std::vector<GhostState> fixed;
    for (const auto& entry : context)
        fixed.push_back(tracks_[entry.track].samples[entry.sample].state);
    std::vector<GhostState> ghosts = predicted;
    ghosts.insert(ghosts.end(), born_states.begin(), born_states.end());
    FrameFitReport report;
    if (!ghosts.empty()) {
        // Priors: the live tracks' predictions; new ghosts have none (their detection or seed
        // is all there is; a seed's outline as a new ghost's prior kept ghosts whose seed the
        // frame does not bear out, docs/path-tracking.md).
        const std::span<const GhostState> priors(predicted);
        // The first frame after missing frames (more than a step and a half from the frame
        // before it in the pass): a track predicted across the gap may have moved from where
        // the prediction puts it, so its nearest sample as it was, and the detection it
        // matched, are tried as starts too. Sweeps without gaps are fitted as before.
        std::vector<std::vector<GhostState>> restarts(live.size());
        const int64_t before = static_cast<int64_t>(j) - direction;
        const bool after_gap =
            direction != 0 && step_deg_ > 0.0 && before >= 0 &&
            before < static_cast<int64_t>(frames_.angles_deg.size()) &&
            std::abs(frames_.angles_deg[static_cast<size_t>(before)] - angle) > 1.5 * step_deg_;
        if (after_gap) {
            for (size_t i = 0; i < live.size(); ++i) {
                const Track& track = tracks_[live[i]];
                if (track.samples.empty()) continue;
                const TrackSample* nearest = &track.samples.front();
                for (const TrackSample& sample : track.samples)
                    if (std::abs(sample.angle_deg - angle) < std::abs(nearest->angle_deg - angle))
                        nearest = &sample;
                if (std::abs(nearest->angle_deg - angle) <= 1.5 * step_deg_) continue;
                restarts[i].push_back(nearest->state);
                if (match_of[i] >= 0)
                    restarts[i].push_back(candidates[static_cast<size_t>(match_of[i])].initial);
            }
        }
        const auto t0 = Clock::now();
        auto fitted = fitFrame(*frame, *detection, ghosts, options_.frame, priors, fixed, restarts);
        (extend ? result_.stages.extend_ms : result_.stages.fit_ms) += msSince(t0);
        if (!fitted)
            return fitted.error().withContext("frame " + std::to_string(j) + " (" +
                                              std::to_string(angle) + " deg)");
        report = std::move(*fitted);
        ++result_.frames_fitted;
        result_.evaluations += report.evaluations;
        {
            std::lock_guard<std::mutex> lock(share_->progress);
            ++share_->frames_fitted;
        }
    }
    // Residual detection (SweepFitOptions::residual_detection): in a frame detected in full, what
    // the fitted ghosts leave unexplained (the frame less their model, above the sky) is detected
    // again, and each residual blob that no ghost stands for becomes a new track, fitted with
    // every other ghost held. A small bright ghost on top of broad ones is no component of its
    // own in the frame, and often no circle the detector keeps; in the residual it is.
    if (options_.residual_detection && allow_new && !ghosts.empty() &&
        fullDetectionAt(j, !live.empty(), extend) &&
        static_cast<int>(live.size() + born.size()) < options_.max_ghosts) {
        const auto t_residual = Clock::now();
        std::vector<GhostState> drawn = ghosts;
        drawn.insert(drawn.end(), fixed.begin(), fixed.end());
        const ImageRGB drawn_model =
            drawFrameModel(*frame, *detection, drawn, options_.frame.cost.distance);
        FitFrame residual;
        residual.image = ImageRGB(frame->image.width, frame->image.height);
        residual.angle_deg = frame->angle_deg;
        residual.mapping = frame->mapping;
        residual.channels = frame->channels;
        const int64_t pixel_count = frame->image.width * frame->image.height;
        for (int64_t i = 0; i < pixel_count; ++i) {
            const bool left_out = detection->excluded[static_cast<size_t>(i)] != 0;
            for (int c = 0; c < 3; ++c) {
                const size_t k = static_cast<size_t>(3 * i + c);
                const double v = static_cast<double>(frame->image.pixels[k]) -
                                 static_cast<double>(drawn_model.pixels[k]) +
                                 detection->background[static_cast<size_t>(c)];
                residual.image.pixels[k] = left_out ? std::numeric_limits<float>::quiet_NaN()
                                                    : static_cast<float>(std::max(0.0, v));
            }
        }
        DetectOptions residual_options = detectOptionsAt(j, !live.empty(), extend);
        residual_options.find_light = false;  // the light's disc is left out (NaN) above
        auto found = detectGhosts(residual, residual_options);
        if (!found) return found.error().withContext("frame " + std::to_string(j) + " residual");
        std::vector<GhostState> extra;
        for (const GhostCandidate& candidate : found->candidates) {
            if (static_cast<int>(live.size() + born.size() + extra.size()) >= options_.max_ghosts)
                break;
            const GhostState& initial = candidate.initial;
            if (outside(initial) || peakSigmas(initial) < kFadedSigmas ||
                ghostSize(initial) > 4.0 * frame_diagonal_mm)
                continue;
            const Eigen::Vector2d centre_mm = toMm(candidate.centroid_px);
            const double candidate_radius = ghostSize(initial);
            const auto near = [&](const GhostState& state) {
                return distanceTo(state, centre_mm, candidate_radius) <= options_.duplicate_radius;
            };
            bool explained = false;
            for (const GhostState& state : drawn) explained = explained || near(state);
            for (const GhostState& state : extra) explained = explained || near(state);
            if (!explained) extra.push_back(initial);
        }
        if (!extra.empty()) {
            std::vector<GhostState> starts = extra;
            auto more = fitFrame(*frame, *detection, extra, options_.frame, {}, drawn);
            if (!more)
                return more.error().withContext("frame " + std::to_string(j) + " (" +
                                                std::to_string(angle) + " deg), residual");
            result_.evaluations += more->evaluations;
            for (size_t k = 0; k < extra.size(); ++k) {
                startTrack(starts[k]);
                ghosts.push_back(extra[k]);
                report.ghosts.push_back(k < more->ghosts.size() ? more->ghosts[k]
                                                                : GhostFitReport{});
            }
        }
        result_.stages.fit_ms += msSince(t_residual);
    }

    const auto ghostCost = [&](size_t k) {
        return k < report.ghosts.size() ? report.ghosts[k].final_cost : 0.0;
    };
    const auto ghostFitted = [&](size_t k) {
        return k < report.ghosts.size() && report.ghosts[k].ok && report.ghosts[k].samples > 0;
    };

    // The brightest the frame is above the sky outside the excluded pixels: no ghost's own
    // intensity can exceed it by much (a fit that does has run off, usually on a ghost that is
    // mostly out of view, where the data cannot hold its intensity).
    double brightest_data = 0.0;
    for (int64_t i = 0; i < frame->image.width * frame->image.height; ++i) {
        if (detection->excluded[static_cast<size_t>(i)]) continue;
        for (int c = 0; c < channels; ++c)
            brightest_data =
                std::max(brightest_data, frame->image.pixels[static_cast<size_t>(3 * i + c)] -
                                             detection->background[c]);
    }
    const auto tooBright = [&](const GhostState& g) {
        for (int c = 0; c < channels; ++c)
            if (std::max(g.shading.border_rgb[c], g.shading.inner_rgb[c]) > 2.0 * brightest_data)
                return true;
        return false;
    };
    // A ghost's light in the frame, roughly: its mean intensity over the part of its box in view,
    // each intensity capped at the brightest the frame is (a border outside the frame is not held
    // by the data and may run off; uncapped, such a ghost's "energy" once outweighed every other
    // ghost's a thousandfold and ended them all by min_energy_fraction, leaving frames empty).
    const auto visibleEnergy = [&](const GhostState& g) {
        const double w =
            std::max(0.0, std::min(frame_x1, g.shape.centre_x_mm + g.shape.right_mm) -
                              std::max(frame_x0, g.shape.centre_x_mm - g.shape.left_mm));
        const double h =
            std::max(0.0, std::min(frame_y1, g.shape.centre_y_mm + g.shape.half_height_mm) -
                              std::max(frame_y0, g.shape.centre_y_mm - g.shape.half_height_mm));
        double level = 0.0;
        for (int c = 0; c < channels; ++c)
            level += 0.5 * (std::min(g.shading.border_rgb[c], brightest_data) +
                            std::min(g.shading.inner_rgb[c], brightest_data));
        return level * w * h;
    };
    // Over the ghosts whose fit is kept (a run-off fit is not taken as a sample below).
    double total_energy = 0.0;
    for (const GhostState& g : ghosts)
        if (!tooBright(g)) total_energy += visibleEnergy(g);
    for (const GhostState& g : fixed) total_energy += visibleEnergy(g);

    // The tracks fitted here (live, then born): their samples and their ends.
    std::vector<size_t> fitted_tracks = live;
    fitted_tracks.insert(fitted_tracks.end(), born.begin(), born.end());
    std::vector<bool> has_sample(fitted_tracks.size(), false);
    for (size_t i = 0; i < fitted_tracks.size(); ++i) {
        const size_t k = i;
        Track& track = tracks_[fitted_tracks[i]];
        const bool is_born = i >= live.size();
        const bool plausible =
            ghostFitted(k) &&
            (is_born ? plausibleFit(born_states[i - live.size()], ghosts[k], 1.0, 3.0, pixel_mm)
                     : plausibleFit(predicted[i], ghosts[k], std::max(0.5, options_.match_radius),
                                    2.0, pixel_mm)) &&
            ghostSize(ghosts[k]) <= 2.0 * frame_diagonal_mm && !tooBright(ghosts[k]);
        if (!plausible) {
            // Nothing to fit it to here: a miss, and a new track is dropped.
            if (is_born || ++track.missed > options_.max_missed) track.live = false;
            continue;
        }
        const GhostState& state = ghosts[k];
        const double peak = peakSigmas(state);
        // Faded, gone out of the frame, collapsed to a speck or sliver (under 2 pixels across) no
        // ghost is, or too faint to matter next to the others (culled: it changes nothing a user
        // would measure).
        if (peak < kFadedSigmas || outside(state) ||
            std::min(state.shape.left_mm + state.shape.right_mm, 2.0 * state.shape.half_height_mm) <
                2.0 * pixel_mm ||
            visibleEnergy(state) < options_.min_energy_fraction * total_energy) {
            track.live = false;
            continue;
        }
        track.samples.push_back({angle, state, ghostCost(k)});
        has_sample[i] = true;
        const bool seen = is_born || matched[i] || peak >= options_.detect.threshold_sigmas ||
                          (track.path >= 0 && std::find(seen_paths.begin(), seen_paths.end(),
                                                        track.path) != seen_paths.end());
        track.missed = seen ? 0 : track.missed + 1;
        if (track.missed > options_.max_missed) track.live = false;
    }

    // Duplicates: of two ghosts that converged to the same state, the younger ends (a context
    // ghost never does).
    struct Present {
        size_t track;
        size_t fitted_index;  // into fitted_tracks, or npos for context
    };
    constexpr size_t npos = std::numeric_limits<size_t>::max();
    std::vector<Present> present;
    for (const auto& entry : context) present.push_back({entry.track, npos});
    for (size_t i = 0; i < fitted_tracks.size(); ++i)
        if (has_sample[i]) present.push_back({fitted_tracks[i], i});
    const auto stateOf = [&](const Present& p) -> const GhostState& {
        const Track& track = tracks_[p.track];
        if (p.fitted_index == npos) {
            for (const auto& entry : context)
                if (entry.track == p.track) return track.samples[entry.sample].state;
        }
        return track.samples.back().state;
    };
    const auto gone = [&](const Present& p) {
        return p.fitted_index != npos && !has_sample[p.fitted_index];
    };
    for (size_t a = 0; a < present.size(); ++a) {
        for (size_t b = a + 1; b < present.size(); ++b) {
            if (gone(present[a])) break;
            if (gone(present[b])) continue;
            if (!sameGhost(stateOf(present[a]), stateOf(present[b]), half_pixel_mm)) continue;
            // Two paths' ghosts may coincide (concentric at 0 deg); both stay.
            const int64_t path_a = tracks_[present[a].track].path;
            const int64_t path_b = tracks_[present[b].track].path;
            if (path_a >= 0 && path_b >= 0 && path_a != path_b) continue;
            const bool a_endable = present[a].fitted_index != npos;
            const bool b_endable = present[b].fitted_index != npos;
            if (!a_endable && !b_endable) continue;
            size_t victim;
            if (a_endable && b_endable)
                victim = tracks_[present[a].track].id > tracks_[present[b].track].id ? a : b;
            else
                victim = a_endable ? a : b;
            Track& track = tracks_[present[victim].track];
            track.samples.pop_back();
            track.live = false;
            has_sample[present[victim].fitted_index] = false;
        }
    }

    // What this frame holds now, and who lives on.
    std::vector<FrameEntry> entries = context;
    std::vector<size_t> still_live;
    for (size_t i = 0; i < fitted_tracks.size(); ++i) {
        Track& track = tracks_[fitted_tracks[i]];
        if (has_sample[i]) entries.push_back({fitted_tracks[i], track.samples.size() - 1});
        if (track.live) still_live.push_back(fitted_tracks[i]);
    }
    at_frame_[j] = std::move(entries);
    live = std::move(still_live);

    if (progress_) {
        std::lock_guard<std::mutex> lock(share_->progress);
        SweepFitProgress p;
        p.frames_done = share_->frames_fitted;
        p.frames_total = std::max(frames_total_, share_->frames_fitted);
        p.angle_deg = angle;
        p.live_ghosts = static_cast<int>(live.size());
        progress_(p);
    }
    return Ok{};
}

Status SweepFitter::backwardPass(size_t s) {
    std::vector<size_t> live;
    for (const FrameEntry& entry : at_frame_[s]) {
        tracks_[entry.track].live = true;
        tracks_[entry.track].missed = 0;
        live.push_back(entry.track);
    }
    for (size_t j = s; j-- > 0;) {
        auto status = processFrame(j, live, true, -1, false);
        if (!status) return status;
    }
    settleReadAhead();
    return Ok{};
}

void SweepFitter::mergeBackward(SweepFitter& backward,
                                const std::vector<size_t>& snapshot,
                                size_t s) {
    // Where each of the backward pass's tracks and samples lands here.
    std::vector<size_t> track_at(backward.tracks_.size());
    std::vector<size_t> first_new(backward.tracks_.size(), 0);  // its first sample's index here
    for (size_t t = 0; t < backward.tracks_.size(); ++t) {
        Track& from = backward.tracks_[t];
        if (t < snapshot.size()) {
            track_at[t] = t;
            first_new[t] = tracks_[t].samples.size();
            tracks_[t].samples.insert(
                tracks_[t].samples.end(),
                from.samples.begin() + static_cast<std::ptrdiff_t>(snapshot[t]),
                from.samples.end());
        } else {
            track_at[t] = tracks_.size();
            from.id = static_cast<int64_t>(tracks_.size());
            tracks_.push_back(std::move(from));
        }
    }
    for (size_t j = 0; j < s; ++j) {
        if (backward.lights_[j]) lights_[j] = backward.lights_[j];
        at_frame_[j].clear();
        for (const FrameEntry& entry : backward.at_frame_[j]) {
            const size_t t = entry.track;
            const size_t sample =
                t < snapshot.size() ? first_new[t] + (entry.sample - snapshot[t]) : entry.sample;
            at_frame_[j].push_back({track_at[t], sample});
        }
    }
    result_.frames_fitted += backward.result_.frames_fitted;
    result_.evaluations += backward.result_.evaluations;
    SweepFitStages& st = result_.stages;
    const SweepFitStages& b = backward.result_.stages;
    st.load_ms += b.load_ms;
    st.detect_ms += b.detect_ms;
    st.ahead_ms += b.ahead_ms;
    st.fit_ms += b.fit_ms;
    st.seed_ms += b.seed_ms;
}

Result<SweepFitResult> SweepFitter::run() {
    const auto t0 = Clock::now();
    const size_t n = frames_.angles_deg.size();
    at_frame_.assign(n, {});
    lights_.assign(n, std::nullopt);
    frames_total_ = static_cast<int64_t>(n);
    auto start = chooseStart();
    if (!start) return start.error();
    const size_t s = static_cast<size_t>(*start);
    start_ = s;
    result_.start_frame = *start;
    result_.frame_count = static_cast<int64_t>(n);

    // Forward from the start, and backward from it with the tracks the start frame holds. The
    // backward pass predicts its first frames from the forward pass's first `history` frames
    // (the nearest samples), so those go first; then the two passes run side by side, the
    // backward one on a copy of the state, and are merged as if it had run after the forward
    // one (tracks it starts numbered after the forward pass's).
    std::vector<size_t> live;
    const size_t head = std::min(n, s + static_cast<size_t>(options_.history));
    for (size_t j = s; j < head; ++j) {
        auto status = processFrame(j, live, true, j == s ? 0 : +1, false);
        if (!status) return status.error();
    }
    SweepFitter backward(frames_, options_, progress_);
    backward.tracks_ = tracks_;
    backward.at_frame_ = at_frame_;
    backward.lights_ = lights_;
    backward.frames_total_ = frames_total_;
    backward.start_ = start_;
    backward.sky_ = sky_;
    backward.detect_ = detect_;
    backward.share_ = share_;
    std::vector<size_t> snapshot;
    for (const Track& track : tracks_) snapshot.push_back(track.samples.size());
    // The first pass to fail stops the other, and its error is the one reported.
    std::atomic<int> first_failure{0};  // 1 forward, 2 backward
    Status backward_status = Ok{};
    std::thread backward_thread([&] {
        // An exception must not end the process from this thread; it becomes the pass's error.
        try {
            backward_status = backward.backwardPass(s);
        } catch (const std::exception& e) {
            backward_status = makeError(ErrorCode::Internal,
                                        std::string("sweep fit: backward pass: ") + e.what());
        }
        int none = 0;
        if (!backward_status && first_failure.compare_exchange_strong(none, 2)) share_->stop = true;
    });
    Status forward_status = Ok{};
    for (size_t j = head; j < n && forward_status; ++j)
        forward_status = processFrame(j, live, true, +1, false);
    settleReadAhead();
    int none = 0;
    if (!forward_status && first_failure.compare_exchange_strong(none, 1)) share_->stop = true;
    backward_thread.join();
    if (first_failure == 1) return forward_status.error();
    if (first_failure == 2) return backward_status.error();
    mergeBackward(backward, snapshot, s);
    // Tracks born away from the start, followed back from where they were born.
    const size_t born_count = tracks_.size();
    for (size_t t = 0; t < born_count; ++t) {
        // A path's track starts where its ghost comes into view and rises above the noise.
        if (tracks_[t].born_direction == 0 || tracks_[t].samples.empty() || tracks_[t].path >= 0)
            continue;
        const int step = -tracks_[t].born_direction;
        tracks_[t].live = true;
        tracks_[t].missed = 0;
        std::vector<size_t> extended = {t};
        for (int64_t j = tracks_[t].born_frame + step, walked = 0;
             j >= 0 && j < static_cast<int64_t>(n) && !extended.empty() &&
             walked < options_.max_extension_frames;
             j += step, ++walked) {
            ++frames_total_;
            auto status = processFrame(static_cast<size_t>(j), extended, false, 0, true);
            if (!status) return status.error();
        }
    }

    // The pieces of one path (a track ended, and started again from the path's seed further on,
    // or in the other pass) become one track, the earliest's; where two hold the same frame, the
    // lower cost stays.
    for (size_t t = 0; t < tracks_.size(); ++t) {
        if (tracks_[t].path < 0) continue;
        for (size_t u = t + 1; u < tracks_.size(); ++u) {
            if (tracks_[u].path != tracks_[t].path) continue;
            mergeTrackSamples(tracks_[t].samples, tracks_[u].samples);
        }
    }
    for (Track& track : tracks_) {
        if (track.samples.empty()) continue;
        std::sort(
            track.samples.begin(), track.samples.end(),
            [](const TrackSample& a, const TrackSample& b) { return a.angle_deg < b.angle_deg; });
        result_.tracks.push_back({track.id, track.path, std::move(track.samples)});
    }
    // Fragments of one ghost (a track that ended and a new one that started a few frames later)
    // linked over the whole sweep at once (track_link.h); tracks from the lens's paths keep
    // theirs.
    const auto link_start = Clock::now();
    TrackLinkStats linked;
    result_.tracks =
        linkTracks(std::move(result_.tracks), frames_.angles_deg, options_.link, &linked);
    result_.fragments_linked = linked.links;
    result_.stages.link_ms = msSince(link_start);
    result_.sky = sky_;
    result_.detect = detect_;
    for (size_t j = 0; j < n; ++j)
        if (lights_[j])
            result_.light_discs.push_back(
                {frames_.angles_deg[j], lights_[j]->found ? lights_[j]->radius_px : 0.0});
    result_.time_ms = msSince(t0);
    SweepFitStages& st = result_.stages;
    st.track_ms = std::max(0.0, result_.time_ms - st.load_ms - st.detect_ms - st.fit_ms -
                                    st.extend_ms - st.seed_ms - st.link_ms);
    st.total_ms = result_.time_ms;
    return std::move(result_);
}

}  // namespace

Status checkSweepFitOptions(const SweepFitOptions& options) {
    if (options.history < 1) return invalid("history must be >= 1");
    if (options.prediction_degree < 0 || options.prediction_degree > 3)
        return invalid("prediction_degree must be in 0..3");
    if (!(options.match_radius > 0.0) || !std::isfinite(options.match_radius))
        return invalid("match_radius must be finite and > 0");
    if (options.max_missed < 0) return invalid("max_missed must be >= 0");
    if (!(options.duplicate_radius > 0.0) || !std::isfinite(options.duplicate_radius))
        return invalid("duplicate_radius must be finite and > 0");
    if (options.min_track_frames < 1) return invalid("min_track_frames must be >= 1");
    if (options.start_frame < -1) return invalid("start_frame must be -1 (automatic) or a frame");
    if (options.start_probes < 1) return invalid("start_probes must be >= 1");
    if (!(options.start_min_share > 0.0) || options.start_min_share > 1.0)
        return invalid("start_min_share must lie in (0, 1]");
    if (options.max_ghosts < 1) return invalid("max_ghosts must be >= 1");
    if (!(options.min_energy_fraction >= 0.0) || options.min_energy_fraction >= 1.0)
        return invalid("min_energy_fraction must lie in [0, 1)");
    if (options.detect_every < 1) return invalid("detect_every must be >= 1");
    if (auto link = checkTrackLinkOptions(options.link); !link) return link.error();
    if (options.max_extension_frames < 0) return invalid("max_extension_frames must be >= 0");
    if (options.frame_stride < 1) return invalid("frame_stride must be >= 1");
    if (options.frame_cache_bytes < 0) return invalid("frame_cache_bytes must be >= 0");
    if (auto status = checkFrameFitOptions(options.frame); !status)
        return status.error().withContext("sweep fit: frame");
    if (auto status = checkPolyFitOptions(options.poly); !status)
        return status.error().withContext("sweep fit: poly");
    if (auto status = checkShadingRefitOptions(options.shading); !status)
        return status.error().withContext("sweep fit");
    // The detection options, on a tiny black frame (detectGhosts refuses only options).
    FitFrame probe;
    probe.image = ImageRGB(8, 8);
    probe.mapping.px_per_mm_x = probe.mapping.px_per_mm_y = 1.0;
    probe.mapping.centre_x_px = probe.mapping.centre_y_px = 4.0;
    probe.channels = 1;
    if (auto detection = detectGhosts(probe, options.detect); !detection)
        return detection.error().withContext("sweep fit: detect");
    return Ok{};
}

Result<SweepFitResult> fitSweepFrames(
    const FrameSource& frames,
    const SweepFitOptions& options,
    const std::function<void(const SweepFitProgress&)>& progress) {
    if (auto status = checkSweepFitOptions(options); !status) return status.error();
    const size_t n = frames.angles_deg.size();
    if (n == 0) return invalid("the sweep has no frames");
    if (!frames.load) return invalid("the frame source has no loader");
    for (size_t i = 0; i < n; ++i) {
        if (!std::isfinite(frames.angles_deg[i]))
            return invalid("angles_deg[" + std::to_string(i) + "] is not finite");
        if (i > 0 && !(frames.angles_deg[i] > frames.angles_deg[i - 1]))
            return invalid("angles_deg[" + std::to_string(i) + "] is not above the one before");
    }
    if (options.start_frame >= static_cast<int64_t>(n))
        return invalid("start_frame " + std::to_string(options.start_frame) +
                       " is past the last of " + std::to_string(n) + " frames");
    SweepFitter fitter(frames, options, progress);
    return fitter.run();
}

namespace {

// ln intensities are floored at a thousandth of the track's brightest frame (its largest
// intensity): below that a ghost is invisible next to itself, and a black frame must not swing
// the series. The floor stays at least ten times below the track's median frame: a frame whose
// fit went astray must not lift it into the ghost's ordinary brightness. Without that bound one
// thin rim fitted 4000 times too bright at 0 deg (the Canon 200, --paths) floored every other
// frame of its track at five times what it held, and the model drew the ghost so at every angle.
// (The floor from a brightest frame chosen robustly, outliers left out, moved the floor of
// tracks that are legitimately bright at a few angles and changed the double Gauss's and the
// Canon 135's models for the worse; this bound leaves every track whose brightest frame is
// within a hundred times its median (frames fitted black left out) as it was.)
double lnFloor(const GhostTrack& track) {
    std::vector<double> brightest;
    for (const TrackSample& sample : track.samples) {
        double b = 0.0;
        for (int c = 0; c < 3; ++c)
            b = std::max(
                {b, sample.state.shading.border_rgb[c], sample.state.shading.inner_rgb[c]});
        if (b > 0.0) brightest.push_back(b);  // a black frame is no ghost's ordinary brightness
    }
    if (brightest.empty()) return kMinLnIntensity;
    const double most = *std::max_element(brightest.begin(), brightest.end());
    const auto mid = brightest.begin() + static_cast<std::ptrdiff_t>(brightest.size() / 2);
    std::nth_element(brightest.begin(), mid, brightest.end());
    const double floor = std::min(1e-3 * most, 0.1 * *mid);
    return floor > 0.0 ? std::log(floor) : kMinLnIntensity;
}

// The residual fields of every piece, from its series as it is now against the track's per-frame
// values (a value at a shared end belongs to the later piece, as in evaluation). After the
// shading refit the series no longer are the least-squares fits of those values, and the fields
// must say how far they now lie from them.
void refreshResiduals(FlareModel& model, const SweepFitResult& result) {
    std::map<int64_t, const GhostTrack*> tracks;
    for (const GhostTrack& track : result.tracks) tracks[track.id] = &track;
    for (ModelGhost& ghost : model.ghosts) {
        const auto found = tracks.find(ghost.id);
        if (found == tracks.end() || ghost.parameters.size() != kGhostParameterCount) continue;
        const GhostTrack& track = *found->second;
        const double ln_floor = lnFloor(track);
        std::vector<GhostParameters> values;
        for (const TrackSample& sample : track.samples)
            values.push_back(ghostParameters(sample.state, ln_floor));
        for (int p = 0; p < kGhostParameterCount; ++p) {
            auto& pieces = ghost.parameters[static_cast<size_t>(p)].pieces;
            std::vector<double> sum_sq(pieces.size(), 0.0), max_abs(pieces.size(), 0.0);
            std::vector<int64_t> count(pieces.size(), 0);
            for (size_t i = 0; i < track.samples.size(); ++i) {
                const double angle = track.samples[i].angle_deg;
                if (pieces.empty() || angle < pieces.front().angle_from_deg ||
                    angle > pieces.back().angle_to_deg)
                    continue;
                size_t k = 0;
                for (size_t j = 0; j < pieces.size(); ++j)
                    if (angle >= pieces[j].angle_from_deg) k = j;
                const ModelPiece& piece = pieces[k];
                const double span = piece.angle_to_deg - piece.angle_from_deg;
                const double x =
                    span > 0.0 ? 2.0 * (angle - piece.angle_from_deg) / span - 1.0 : 0.0;
                const double r = std::abs(chebyshevValue(piece.coefficients, x) - values[i][p]);
                sum_sq[k] += r * r;
                max_abs[k] = std::max(max_abs[k], r);
                ++count[k];
            }
            for (size_t k = 0; k < pieces.size(); ++k) {
                if (count[k] == 0) continue;  // no per-frame value inside: keep the fields
                pieces[k].residual_rms = std::sqrt(sum_sq[k] / static_cast<double>(count[k]));
                pieces[k].residual_max = max_abs[k];
            }
        }
    }
}

}  // namespace

Result<FlareModel> buildModel(const SweepFitResult& result,
                              FlareModel model,
                              const SweepFitOptions& options) {
    if (auto status = checkPolyFitOptions(options.poly); !status)
        return status.error().withContext("sweep fit: poly");
    if (options.min_track_frames < 1) return invalid("min_track_frames must be >= 1");
    int64_t min_frames = options.min_track_frames;
    if (result.frame_count > 0) min_frames = std::min(min_frames, result.frame_count);
    model.ghosts.clear();
    // The light's discs, those inside the capture's angles (a caller's metadata may name fewer).
    model.capture.light_discs.clear();
    for (const ModelLightDisc& disc : result.light_discs)
        if (disc.angle_deg >= model.capture.from_deg && disc.angle_deg <= model.capture.to_deg)
            model.capture.light_discs.push_back(disc);
    for (const GhostTrack& track : result.tracks) {
        const size_t n = track.samples.size();
        if (n == 0 || static_cast<int64_t>(n) < min_frames) continue;
        if (model.ghosts.size() >= kModelMaxGhosts) break;
        const double ln_floor = lnFloor(track);
        std::vector<double> angles(n);
        std::vector<GhostParameters> values(n);
        for (size_t i = 0; i < n; ++i) {
            angles[i] = track.samples[i].angle_deg;
            values[i] = ghostParameters(track.samples[i].state, ln_floor);
        }
        // A fixed degree above what the track's frames support is capped there (a short track
        // is interpolated rather than refused).
        PolyFitOptions poly = options.poly;
        if (poly.fixed_degree > static_cast<int>(n) - 1)
            poly.fixed_degree = static_cast<int>(n) - 1;
        ModelGhost ghost;
        ghost.id = track.id;
        ghost.name = "track " + std::to_string(track.id);
        ghost.fit.frames_fitted = static_cast<int64_t>(n);
        ghost.fit.first_angle_deg = angles.front();
        ghost.fit.last_angle_deg = angles.back();
        for (int p = 0; p < kGhostParameterCount; ++p) {
            const GhostParameterInfo& info = ghostParameterInfo(p);
            ModelParameter parameter;
            parameter.name = info.name;
            parameter.unit = info.unit;
            std::vector<double> series(n);
            for (size_t i = 0; i < n; ++i) series[i] = values[i][p];
            // Bounds: the range the track's frames span, widened by a quarter of it on each side
            // (and kept inside the parameter's own bounds). Evaluation clamps to them, so that no
            // series, however it swings between or beyond its samples, draws a ghost brighter or
            // larger than any seen.
            const auto [lo, hi] = std::minmax_element(series.begin(), series.end());
            const double spread = *hi - *lo;
            const double pad = 0.25 * spread + 1e-9 * (1.0 + std::abs(*hi));
            parameter.lower_bound = *lo - pad;
            parameter.upper_bound = *hi + pad;
            if (info.lower_bound)
                parameter.lower_bound = std::max(*parameter.lower_bound, *info.lower_bound);
            if (info.upper_bound)
                parameter.upper_bound = std::min(*parameter.upper_bound, *info.upper_bound);
            if (*parameter.lower_bound > *parameter.upper_bound)
                parameter.lower_bound = parameter.upper_bound;
            if (n == 1) {
                parameter.pieces.push_back({angles[0], angles[0], {series[0]}, 0.0, 0.0, 1});
            } else {
                auto fit = fitPolynomial(angles, series, poly);
                if (!fit)
                    return fit.error().withContext("sweep fit: track " + std::to_string(track.id) +
                                                   ", " + info.name);
                // One frame whose fit went astray must not bend the series: samples more than
                // four robust sigmas (1.4826 x the median absolute residual) off the first fit
                // are given a weight of 1e-6 and the series is fitted again.
                if (n >= 5) {
                    std::vector<double> residual(n);
                    for (size_t i = 0; i < n; ++i) {
                        auto v = evaluatePolyFit(*fit, angles[i]);
                        residual[i] = v ? std::abs(series[i] - *v) : 0.0;
                    }
                    std::vector<double> sorted = residual;
                    std::nth_element(sorted.begin(),
                                     sorted.begin() + static_cast<std::ptrdiff_t>(n / 2),
                                     sorted.end());
                    const double sigma = 1.4826 * sorted[n / 2];
                    std::vector<double> weights(n, 1.0);
                    bool any = false;
                    for (size_t i = 0; i < n; ++i)
                        if (residual[i] > 4.0 * sigma + 1e-12 * (1.0 + std::abs(series[i]))) {
                            weights[i] = 1e-6;
                            any = true;
                        }
                    if (any) {
                        auto refit = fitPolynomial(angles, series, poly, weights);
                        if (refit) fit = std::move(refit);
                    }
                }
                for (const PolyPiece& piece : fit->pieces)
                    parameter.pieces.push_back({piece.angle_min_deg, piece.angle_max_deg,
                                                piece.coefficients, piece.rms_residual,
                                                piece.max_abs_residual, piece.sample_count});
            }
            if (options.keep_samples) {
                // Strictly increasing angles (a track holds one sample per frame).
                for (size_t i = 0; i < n; ++i)
                    if (i == 0 || angles[i] > parameter.sample_angles_deg.back()) {
                        parameter.sample_angles_deg.push_back(angles[i]);
                        parameter.sample_values.push_back(series[i]);
                    }
            }
            ghost.parameters.push_back(std::move(parameter));
        }
        model.ghosts.push_back(std::move(ghost));
    }
    if (auto status = validateModel(model); !status) return status.error();
    return model;
}

ModelLens modelLens(const hdr::SweepLens& lens, double sensor_width_mm, double sensor_height_mm) {
    ModelLens out;
    out.description = lens.description;
    out.prescription_file = lens.prescription_file;
    out.prescription_sha256 = lens.prescription_sha256;
    out.f_number = lens.f_number;
    out.focal_length_mm = lens.focal_length_mm;
    out.sensor_width_mm = sensor_width_mm;
    out.sensor_height_mm = sensor_height_mm;
    out.aperture_blades = lens.aperture_blades;
    out.blade_rotation_deg = lens.blade_rotation_deg;
    out.stop_semi_aperture_mm = lens.stop_semi_aperture_mm;
    out.coat_unspecified_surfaces = lens.coat_unspecified_surfaces;
    return out;
}

Result<FlareModel> fitSweep(const hdr::Sweep& sweep,
                            double sensor_width_mm,
                            double sensor_height_mm,
                            const SweepFitOptions& options,
                            const std::function<void(const SweepFitProgress&)>& progress,
                            SweepFitResult* result) {
    const auto t_call = Clock::now();
    if (auto status = checkSweepFitOptions(options); !status) return status.error();
    std::vector<size_t> used;  // the sweep's frames fitted
    for (size_t i = 0; i < sweep.frames.size(); i += static_cast<size_t>(options.frame_stride))
        used.push_back(i);
    if (used.empty() ||
        !(sweep.frames[used.back()].angle_deg > sweep.frames[used.front()].angle_deg))
        return invalid("sweep " + sweep.directory + " has " + std::to_string(sweep.frames.size()) +
                       " frame(s)" +
                       (options.frame_stride > 1
                            ? " (fitting one in every " + std::to_string(options.frame_stride) +
                                  ": " + std::to_string(used.size()) + ")"
                            : std::string()) +
                       " at one angle; a model needs at least two angles");
    std::array<double, 2> given{sensor_width_mm, sensor_height_mm};
    auto sensor =
        sweepSensorSize(sweep, sensor_width_mm > 0.0 || sensor_height_mm > 0.0 ? &given : nullptr);
    if (!sensor) return sensor.error();
    const double width_mm = (*sensor)[0], height_mm = (*sensor)[1];

    FrameSource source;
    for (size_t i : used) source.angles_deg.push_back(sweep.frames[i].angle_deg);
    auto cache = std::make_shared<FrameCache>(
        [&](size_t index) { return loadFitFrame(sweep, used[index], width_mm, height_mm); },
        options.frame_cache_bytes);
    source.load = [cache](size_t index) { return cache->get(index); };
    source.detect = [cache](size_t index, const FitFrame& frame, const DetectOptions& detect) {
        return cache->detect(index, frame, detect);
    };
    source.prefetch = [cache](size_t index, const DetectOptions& detect) {
        cache->prefetch(index, detect);
    };
    auto fitted = fitSweepFrames(source, options, progress);
    if (!fitted) return fitted.error();

    const auto& header = sweep.header;
    FlareModel model;
    model.software_version = "flarelab fit";
    model.created_utc = nowUtc();
    model.lens = modelLens(header.lens, width_mm, height_mm);
    const double first = source.angles_deg.front(), last = source.angles_deg.back();
    model.capture.from_deg = std::min(header.capture.from_deg, first);
    model.capture.to_deg = std::max(header.capture.to_deg, last);
    model.capture.step_deg = header.capture.step_deg * options.frame_stride;
    model.capture.roll_deg = header.capture.roll_deg;
    model.capture.exposure_times_s = header.capture.exposure_times_s;
    model.capture.width_px = header.capture.width_px;
    model.capture.height_px = header.capture.height_px;
    model.capture.camera = header.camera.description;
    if (header.camera.raw_format)
        model.capture.raw_format = std::string(hdr::rawFormatName(*header.camera.raw_format));
    model.capture.light_power_dn_s = header.camera.light_power_dn_s;
    model.valid_from_deg = first;
    model.valid_to_deg = last;
    auto t_stage = Clock::now();
    auto built = buildModel(*fitted, std::move(model), options);
    if (!built) return built.error();
    fitted->stages.compress_ms = msSince(t_stage);
    t_stage = Clock::now();
    auto refit = refitShading(*built, source, fitted->sky, fitted->detect, options.frame.cost,
                              options.shading);
    if (!refit) return refit.error();
    if (refit->ghosts > 0) refreshResiduals(*built, *fitted);
    fitted->stages.shape_ms = refit->shape_ms;
    fitted->shape_refitted = refit->shape_ghosts;
    fitted->shape_unobserved = refit->shape_unobserved;
    fitted->stages.shading_ms = msSince(t_stage) - refit->shape_ms;
    fitted->stages.total_ms = msSince(t_call);
    if (result) *result = std::move(*fitted);
    return built;
}

}  // namespace flarelab::fit
