#include "fit/detect.h"

#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <limits>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include "hdr/sweep.h"
#include "render/ghost_shape.h"
#include "tests/test_paths.h"

namespace flarelab::fit {
namespace {

struct Disc {
    double cx = 0.0, cy = 0.0, radius = 1.0;
    double inner = 1.0, rim = 1.0;  // added over the background; the rim is the outer 1.5 px
};

// A synthetic frame: background + Gaussian noise (fixed seed) + discs + a bright Gaussian light.
ImageRGB syntheticImage(int64_t width,
                        int64_t height,
                        const std::vector<Disc>& discs,
                        double light_x,
                        double light_y,
                        double light_peak,
                        double background = 10.0,
                        double noise = 1.0,
                        unsigned seed = 7) {
    ImageRGB image(width, height);
    std::mt19937 rng(seed);
    std::normal_distribution<double> gauss(0.0, noise);
    for (int64_t y = 0; y < height; ++y) {
        for (int64_t x = 0; x < width; ++x) {
            const double px = static_cast<double>(x) + 0.5;
            const double py = static_cast<double>(y) + 0.5;
            double v = background;
            for (const Disc& d : discs) {
                const double r = std::hypot(px - d.cx, py - d.cy);
                if (r <= d.radius) v += r > d.radius - 1.5 ? d.rim : d.inner;
            }
            if (light_peak > 0.0) {
                const double r2 = (px - light_x) * (px - light_x) + (py - light_y) * (py - light_y);
                v += light_peak * std::exp(-r2 / (2.0 * 2.0 * 2.0));
            }
            float* p = image.at(x, y);
            for (int c = 0; c < 3; ++c)
                p[c] = static_cast<float>(std::max(0.0, v + (noise > 0.0 ? gauss(rng) : 0.0)));
        }
    }
    return image;
}

FitFrame makeFrame(ImageRGB image, double angle_deg = 1.0) {
    auto frame = frameFromImage(std::move(image), angle_deg, 36.0, 24.0);
    EXPECT_TRUE(frame.has_value());
    return std::move(frame).value();
}

void expectFinite(const FrameDetection& d) {
    for (int c = 0; c < 3; ++c) {
        EXPECT_TRUE(std::isfinite(d.background[c]));
        EXPECT_TRUE(std::isfinite(d.noise_sigma[c]));
        EXPECT_GT(d.noise_sigma[c], 0.0);
    }
    EXPECT_TRUE(std::isfinite(d.light.centre_px.x()));
    EXPECT_TRUE(std::isfinite(d.light.centre_px.y()));
    EXPECT_TRUE(std::isfinite(d.light.radius_px));
    for (const GhostCandidate& g : d.candidates) {
        EXPECT_TRUE(std::isfinite(g.centroid_px.x()) && std::isfinite(g.centroid_px.y()));
        EXPECT_TRUE(validateGhostShape(g.initial.shape).has_value())
            << validateGhostShape(g.initial.shape).error().message;
        EXPECT_TRUE(validateShading(g.initial.shading).has_value())
            << validateShading(g.initial.shading).error().message;
        EXPECT_GE(g.area_px, 1);
        EXPECT_LE(g.x0, g.x1);
        EXPECT_LE(g.y0, g.y1);
        EXPECT_GT(g.left_px, 0.0);
        EXPECT_GT(g.right_px, 0.0);
        EXPECT_GT(g.up_px, 0.0);
        EXPECT_GT(g.down_px, 0.0);
        for (int c = 0; c < 3; ++c) {
            EXPECT_TRUE(std::isfinite(g.energy[c]));
            EXPECT_TRUE(std::isfinite(g.peak[c]));
        }
    }
}

// Centroid within 1 px and extents within 2 px of the drawn disc (its outermost pixel centres
// lie within the radius, their edges up to half a pixel beyond).
void expectMatches(const GhostCandidate& g, const Disc& d) {
    EXPECT_NEAR(g.centroid_px.x(), d.cx, 1.0);
    EXPECT_NEAR(g.centroid_px.y(), d.cy, 1.0);
    EXPECT_NEAR(g.left_px, d.radius + 0.5, 2.0);
    EXPECT_NEAR(g.right_px, d.radius + 0.5, 2.0);
    EXPECT_NEAR(g.up_px, d.radius + 0.5, 2.0);
    EXPECT_NEAR(g.down_px, d.radius + 0.5, 2.0);
}

TEST(DetectGhosts, BlackFrameGivesNoLightAndNoCandidates) {
    const FitFrame frame = makeFrame(ImageRGB(64, 48));
    auto d = detectGhosts(frame);
    ASSERT_TRUE(d.has_value()) << d.error().message;
    EXPECT_FALSE(d->light.found);
    EXPECT_TRUE(d->candidates.empty());
    EXPECT_EQ(d->background[0], 0.0);
    EXPECT_EQ(d->excluded.size(), 64u * 48u);
    expectFinite(*d);
}

TEST(DetectGhosts, PureNoiseGivesNoCandidates) {
    const FitFrame frame = makeFrame(syntheticImage(640, 427, {}, 0, 0, 0.0, 100.0, 3.0, 11));
    auto d = detectGhosts(frame);
    ASSERT_TRUE(d.has_value());
    EXPECT_TRUE(d->candidates.empty());
    EXPECT_NEAR(d->background[1], 100.0, 0.2);
    EXPECT_NEAR(d->noise_sigma[1], 3.0, 0.2);
    expectFinite(*d);
}

TEST(DetectGhosts, SaturatedFrameGivesNoCandidates) {
    ImageRGB image(80, 60);
    std::fill(image.pixels.begin(), image.pixels.end(), 3.0e38f);
    auto d = detectGhosts(makeFrame(std::move(image)));
    ASSERT_TRUE(d.has_value());
    EXPECT_FALSE(d->light.found);
    EXPECT_TRUE(d->candidates.empty());
    expectFinite(*d);
}

TEST(DetectGhosts, FindsThreeDiscsWithRimsByEnergy) {
    const std::vector<Disc> discs = {
        {100.3, 80.7, 12.0, 20.0, 60.0},  // bright, mid-sized
        {400.0, 300.2, 30.0, 5.0, 15.0},  // large and faint: the most energy
        {560.6, 120.4, 6.0, 30.0, 40.0},  // small
    };
    const FitFrame frame = makeFrame(syntheticImage(640, 427, discs, 320.5, 213.5, 1e5));
    auto d = detectGhosts(frame);
    ASSERT_TRUE(d.has_value());
    expectFinite(*d);
    ASSERT_TRUE(d->light.found);
    EXPECT_NEAR(d->light.centre_px.x(), 320.5, 0.5);
    EXPECT_NEAR(d->light.centre_px.y(), 213.5, 0.5);
    EXPECT_GT(d->light.radius_px, 5.0);
    EXPECT_LT(d->light.radius_px, 20.0);
    EXPECT_EQ(d->excluded[213 * 640 + 320], 1);
    EXPECT_EQ(d->excluded[0], 0);
    ASSERT_EQ(d->candidates.size(), 3u);
    expectMatches(d->candidates[0], discs[1]);
    expectMatches(d->candidates[1], discs[0]);
    expectMatches(d->candidates[2], discs[2]);
    for (size_t i = 1; i < d->candidates.size(); ++i)
        EXPECT_GE(d->candidates[i - 1].energy[0], d->candidates[i].energy[0]);
    // Energy close to what was drawn; shading from the rim and the inside.
    const GhostCandidate& bright = d->candidates[1];
    EXPECT_NEAR(bright.initial.shading.border_rgb[0], 60.0, 5.0);
    EXPECT_NEAR(bright.initial.shading.inner_rgb[0], 20.0, 2.0);
    EXPECT_NEAR(bright.peak[0], 63.0, 5.0);
    // The initial shape in sensor mm: 640 px over 36 mm, the axis at the image centre.
    const double ppm = 640.0 / 36.0;
    EXPECT_NEAR(bright.initial.shape.centre_x_mm, (100.3 - 320.0) / ppm, 1.0 / ppm);
    EXPECT_NEAR(bright.initial.shape.centre_y_mm, (80.7 - 213.5) / (427.0 / 24.0), 1.0 / ppm);
    EXPECT_NEAR(bright.initial.shape.left_mm, 12.5 / ppm, 2.0 / ppm);
    EXPECT_NEAR(bright.initial.shape.half_height_mm, 12.5 / ppm, 2.0 / ppm);
}

TEST(DetectGhosts, GhostTouchingTheBorder) {
    const Disc disc{10.0, 60.0, 20.0, 30.0, 50.0};  // cut by the left edge
    auto d = detectGhosts(makeFrame(syntheticImage(200, 150, {disc}, 150.5, 75.5, 1e5)));
    ASSERT_TRUE(d.has_value());
    expectFinite(*d);
    ASSERT_EQ(d->candidates.size(), 1u);
    const GhostCandidate& g = d->candidates[0];
    EXPECT_EQ(g.x0, 0);
    EXPECT_NEAR(g.right_px + g.centroid_px.x(), 30.5, 2.0);
    EXPECT_NEAR(g.up_px, 20.5, 2.0);
    EXPECT_NEAR(g.down_px, 20.5, 2.0);
}

TEST(DetectGhosts, TinyGhost) {
    const Disc disc{50.5, 40.5, 2.0, 40.0, 40.0};
    auto d = detectGhosts(makeFrame(syntheticImage(120, 90, {disc}, 100.5, 70.5, 1e5)));
    ASSERT_TRUE(d.has_value());
    expectFinite(*d);
    ASSERT_EQ(d->candidates.size(), 1u);
    EXPECT_NEAR(d->candidates[0].centroid_px.x(), 50.5, 1.0);
    EXPECT_NEAR(d->candidates[0].centroid_px.y(), 40.5, 1.0);
    EXPECT_NEAR(d->candidates[0].left_px, 2.5, 1.5);
}

// A frame with no light of its own (one ghost path rendered alone): a small bright ghost looks
// like a light to the default search, which leaves its disc out; with find_light off it is a
// candidate and none of its pixels are excluded.
TEST(DetectGhosts, WithoutALightASmallBrightGhostIsACandidate) {
    const Disc disc{50.5, 40.5, 3.0, 3000.0, 3000.0};
    const FitFrame frame = makeFrame(syntheticImage(120, 90, {disc}, 0.0, 0.0, 0.0));
    auto with_light = detectGhosts(frame);
    ASSERT_TRUE(with_light.has_value());
    EXPECT_TRUE(with_light->light.found);
    EXPECT_TRUE(with_light->candidates.empty());
    DetectOptions options;
    options.find_light = false;
    auto d = detectGhosts(frame, options);
    ASSERT_TRUE(d.has_value());
    expectFinite(*d);
    EXPECT_FALSE(d->light.found);
    ASSERT_EQ(d->candidates.size(), 1u);
    expectMatches(d->candidates[0], disc);
    for (uint8_t e : d->excluded) EXPECT_EQ(e, 0);
    // A floor under the light's peak above the ghost's does the same where a light may be in
    // view; a light above the floor is still the light.
    DetectOptions floor;
    floor.min_light_peak = 10.0 * disc.inner;
    auto floored = detectGhosts(frame, floor);
    ASSERT_TRUE(floored.has_value());
    EXPECT_FALSE(floored->light.found);
    ASSERT_EQ(floored->candidates.size(), 1u);
    expectMatches(floored->candidates[0], disc);
    auto lit = detectGhosts(makeFrame(syntheticImage(120, 90, {disc}, 100.5, 70.5, 1e5)), floor);
    ASSERT_TRUE(lit.has_value());
    ASSERT_TRUE(lit->light.found);
    EXPECT_NEAR(lit->light.centre_px.x(), 100.5, 1.0);
    EXPECT_GT(lit->light.peak, floor.min_light_peak);
    ASSERT_EQ(lit->candidates.size(), 1u);
}

// At angle 0 the light sits in the middle of a ghost that covers much of the image: the light's
// disc stops at the ghost's plateau instead of swallowing it.
TEST(DetectGhosts, ImageFillingGhostAroundTheLight) {
    const Disc disc{160.0, 107.0, 95.0, 150.0, 300.0};
    auto d = detectGhosts(makeFrame(syntheticImage(320, 214, {disc}, 160.0, 107.0, 1e5), 0.0));
    ASSERT_TRUE(d.has_value());
    expectFinite(*d);
    ASSERT_TRUE(d->light.found);
    EXPECT_LT(d->light.radius_px, 20.0);
    ASSERT_EQ(d->candidates.size(), 1u);
    expectMatches(d->candidates[0], disc);
}

TEST(DetectGhosts, OneByOneImage) {
    ImageRGB image(1, 1);
    image.pixels = {5.0f, 5.0f, 5.0f};
    auto d = detectGhosts(makeFrame(std::move(image)));
    ASSERT_TRUE(d.has_value());
    expectFinite(*d);
    EXPECT_TRUE(d->candidates.empty());
    EXPECT_EQ(d->excluded.size(), 1u);
}

TEST(DetectGhosts, OptionsOutOfRangeAreInvalidArguments) {
    const FitFrame frame = makeFrame(ImageRGB(8, 8));
    const auto check = [&](DetectOptions o, const char* field) {
        auto d = detectGhosts(frame, o);
        ASSERT_FALSE(d.has_value()) << field;
        EXPECT_EQ(d.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(d.error().message.find(field), std::string::npos) << d.error().message;
    };
    DetectOptions o;
    o.smoothing_px = -1.0;
    check(o, "smoothing_px");
    o = {};
    o.smoothing_px = std::nan("");
    check(o, "smoothing_px");
    o = {};
    o.threshold_sigmas = 0.0;
    check(o, "threshold_sigmas");
    o = {};
    o.min_area_px = 0;
    check(o, "min_area_px");
    o = {};
    o.min_energy_sigmas = -2.0;
    check(o, "min_energy_sigmas");
    o = {};
    o.min_light_peak = -1.0;
    check(o, "min_light_peak");
    o = {};
    o.min_light_peak = std::numeric_limits<double>::infinity();
    check(o, "min_light_peak");
    o = {};
    o.light_margin_px = -1.0;
    check(o, "light_margin_px");
    o = {};
    o.light_min_radius_px = std::numeric_limits<double>::infinity();
    check(o, "light_min_radius_px");
    o = {};
    o.max_candidates = -1;
    check(o, "max_candidates");
}

TEST(DetectGhosts, NoSmoothingAndCandidateCap) {
    const std::vector<Disc> discs = {{40.0, 40.0, 8.0, 30.0, 30.0}, {120.0, 40.0, 5.0, 30.0, 30.0}};
    const FitFrame frame = makeFrame(syntheticImage(160, 100, discs, 80.5, 80.5, 1e5));
    DetectOptions o;
    o.smoothing_px = 0.0;
    auto d = detectGhosts(frame, o);
    ASSERT_TRUE(d.has_value());
    ASSERT_EQ(d->candidates.size(), 2u);
    expectMatches(d->candidates[0], discs[0]);
    o.max_candidates = 1;
    d = detectGhosts(frame, o);
    ASSERT_TRUE(d.has_value());
    ASSERT_EQ(d->candidates.size(), 1u);
    expectMatches(d->candidates[0], discs[0]);
}

// A full-size frame, detected repeatedly with the same result. Its time is recorded, not
// limited: speed is measured by bench tools, and a shared machine would make a limit flaky.
TEST(DetectGhosts, FullSizeFrameGivesTheSameResultEveryRun) {
    const std::vector<Disc> discs = {{100.3, 80.7, 12.0, 20.0, 60.0},
                                     {400.0, 300.2, 30.0, 5.0, 15.0}};
    const FitFrame frame = makeFrame(syntheticImage(640, 427, discs, 320.5, 213.5, 1e5));
    constexpr int kRuns = 5;
    const auto first = detectGhosts(frame);
    ASSERT_TRUE(first.has_value());
    ASSERT_GE(first->candidates.size(), 2u);
    const auto start = std::chrono::steady_clock::now();
    for (int i = 0; i < kRuns; ++i) {
        const auto again = detectGhosts(frame);
        ASSERT_TRUE(again.has_value());
        ASSERT_EQ(again->candidates.size(), first->candidates.size());
        for (size_t c = 0; c < first->candidates.size(); ++c)
            EXPECT_EQ(again->candidates[c].centroid_px, first->candidates[c].centroid_px);
        EXPECT_EQ(again->excluded, first->excluded);
    }
    const double ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
            .count() /
        kRuns;
    RecordProperty("ms_per_frame", std::to_string(ms));
}

// A simulated sweep (mono 12-bit camera, merged brackets): frame 4 is at 2 deg.
TEST(DetectGhosts, SimulatedHeliarFrame) {
    auto sweep = hdr::readSweep(testing::sourcePath("tests/data/sweeps/heliar-raw"));
    ASSERT_TRUE(sweep.has_value()) << sweep.error().message;
    auto frame = loadFitFrame(*sweep, 4, 36.0, 24.0);
    ASSERT_TRUE(frame.has_value()) << frame.error().message;
    auto d = detectGhosts(*frame);
    ASSERT_TRUE(d.has_value());
    expectFinite(*d);
    // The brightest pixel (channel sum).
    const ImageRGB& image = frame->image;
    int64_t best = 0;
    for (int64_t i = 1; i < image.width * image.height; ++i)
        if (image.pixels[i * 3] + image.pixels[i * 3 + 1] + image.pixels[i * 3 + 2] >
            image.pixels[best * 3] + image.pixels[best * 3 + 1] + image.pixels[best * 3 + 2])
            best = i;
    ASSERT_TRUE(d->light.found);
    // The merged core is a saturated plateau: its brightest pixel is anywhere in it, inside the
    // disc.
    const Eigen::Vector2d brightest(static_cast<double>(best % image.width) + 0.5,
                                    static_cast<double>(best / image.width) + 0.5);
    EXPECT_LT((d->light.centre_px - brightest).norm(), d->light.radius_px);
    EXPECT_EQ(d->excluded[best], 1);
    EXPECT_LT(d->light.radius_px, 0.125 * std::hypot(160.0, 107.0) + 1e-9);
    EXPECT_GE(d->candidates.size(), 1u);
}

// Overlapping discs on the light line (y = 213.5, the light at its right): one component, split
// into its circles; the left one is cut by the frame's edge.
TEST(DetectGhosts, OverlappingDiscsOnTheLightLineAreSeparateCircles) {
    const std::vector<Disc> discs = {
        {200.0, 213.5, 120.0, 20.0, 20.0},
        {330.0, 213.5, 70.0, 60.0, 60.0},
        {-30.0, 213.5, 150.0, 8.0, 8.0},
    };
    const FitFrame frame = makeFrame(syntheticImage(640, 427, discs, 600.5, 213.5, 1e5));
    auto d = detectGhosts(frame);
    ASSERT_TRUE(d.has_value());
    expectFinite(*d);
    ASSERT_EQ(d->candidates.size(), 3u);
    for (const Disc& disc : discs) {
        int matches = 0;
        for (const GhostCandidate& g : d->candidates) {
            if (std::abs(g.centroid_px.x() - disc.cx) > 1.5 ||
                std::abs(g.centroid_px.y() - disc.cy) > 1.5)
                continue;
            ++matches;
            EXPECT_NEAR(g.left_px, disc.radius, 2.0);
            EXPECT_NEAR(g.initial.shape.left_mm, disc.radius * 36.0 / 640.0, 2.0 * 36.0 / 640.0);
            EXPECT_NEAR(g.initial.shading.border_rgb[0], disc.inner, 0.2 * disc.inner);
        }
        EXPECT_EQ(matches, 1) << "disc at " << disc.cx << " r " << disc.radius;
    }
    DetectOptions o;
    o.circles = false;
    auto plain = detectGhosts(frame, o);
    ASSERT_TRUE(plain.has_value());
    EXPECT_EQ(plain->candidates.size(), 1u);
}

// Angle 0: concentric ghosts around the light are separate circles.
TEST(DetectGhosts, ConcentricDiscsAreSeparateCircles) {
    const std::vector<Disc> discs = {{320.0, 213.5, 60.0, 40.0, 40.0},
                                     {320.0, 213.5, 130.0, 15.0, 15.0}};
    auto d = detectGhosts(makeFrame(syntheticImage(640, 427, discs, 320.0, 213.5, 1e5), 0.0));
    ASSERT_TRUE(d.has_value());
    expectFinite(*d);
    ASSERT_EQ(d->candidates.size(), 2u);
    EXPECT_NEAR(d->candidates[0].left_px, 130.0, 2.0);
    EXPECT_NEAR(d->candidates[1].left_px, 60.0, 2.0);
    for (const GhostCandidate& g : d->candidates) {
        EXPECT_NEAR(g.centroid_px.x(), 320.0, 1.5);
        EXPECT_NEAR(g.centroid_px.y(), 213.5, 1.5);
    }
}

TEST(DetectGhosts, CircleOptionsOutOfRange) {
    const FitFrame frame = makeFrame(ImageRGB(8, 8));
    DetectOptions o;
    o.max_circles = -1;
    EXPECT_FALSE(detectGhosts(frame, o).has_value());
    o = {};
    o.min_circle_support = 0.0;
    EXPECT_FALSE(detectGhosts(frame, o).has_value());
    o = {};
    o.max_edge_pixels = 3;
    EXPECT_FALSE(detectGhosts(frame, o).has_value());
    o = {};
    o.min_circle_step = -1.0;
    EXPECT_FALSE(detectGhosts(frame, o).has_value());
}

// Prints what it finds on the shipped sweep and, when present, a 640 x 427 one.
TEST(DetectGhosts, DISABLED_Probe) {
    for (const std::string& dir :
         {testing::sourcePath("tests/data/sweeps/heliar-raw"), std::string("/tmp/dev/heliar")}) {
        auto sweep = hdr::readSweep(dir);
        if (!sweep) continue;
        for (size_t i = 0; i < sweep->frames.size(); i += (sweep->frames.size() > 10 ? 25 : 1)) {
            auto frame = loadFitFrame(*sweep, i, 36.0, 24.0);
            if (!frame) continue;
            const auto start = std::chrono::steady_clock::now();
            auto d = detectGhosts(*frame);
            const double ms =
                std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
                    .count();
            std::printf(
                "%s frame %zu (%.1f deg) %lldx%lld ch %d: %.2f ms bg %.4g sigma %.4g light %d "
                "(%.1f, %.1f) r %.1f, %zu candidates\n",
                dir.c_str(), i, frame->angle_deg, (long long)frame->image.width,
                (long long)frame->image.height, frame->channels, ms, d->background[0],
                d->noise_sigma[0], d->light.found, d->light.centre_px.x(), d->light.centre_px.y(),
                d->light.radius_px, d->candidates.size());
            for (size_t k = 0; k < std::min<size_t>(d->candidates.size(), 40); ++k) {
                const auto& g = d->candidates[k];
                std::printf(
                    "   c mm (%.2f, %.2f) r %.2f px (%.1f, %.1f) area %lld E %.4g peak %.4g lrud "
                    "%.1f %.1f %.1f %.1f "
                    "border %.4g inner %.4g\n",
                    g.initial.shape.centre_x_mm, g.initial.shape.centre_y_mm,
                    g.initial.shape.left_mm, g.centroid_px.x(), g.centroid_px.y(),
                    (long long)g.area_px, g.energy[0], g.peak[0], g.left_px, g.right_px, g.up_px,
                    g.down_px, g.initial.shading.border_rgb[0], g.initial.shading.inner_rgb[0]);
            }
        }
    }
}

// An unclipped light, as the brackets capture plans record it: a core 1e11 above a sky whose
// noise is 1, with glare falling as (1 + r / 2)^-10 around it. The noise stays the sky's (a floor
// of a billionth of the core had put it at 100 and hidden this ghost, 3 sigmas deep), and the
// light's disc reaches out to where its glare falls to some 15 sigmas, not a few pixels.
TEST(DetectGhosts, AnUnclippedCoreLeavesTheNoiseAndTheGhostsAlone) {
    const double lx = 420.5, ly = 200.5;
    ImageRGB image =
        syntheticImage(640, 427, {{150.0, 220.0, 40.0, 3.0, 3.0}}, 0.0, 0.0, 0.0, 25.0, 1.0, 11);
    for (int64_t y = 0; y < image.height; ++y)
        for (int64_t x = 0; x < image.width; ++x) {
            const double r =
                std::hypot(static_cast<double>(x) + 0.5 - lx, static_cast<double>(y) + 0.5 - ly);
            const double glare = 1e11 * std::pow(1.0 + r / 2.0, -10.0);
            for (int c = 0; c < 3; ++c) image.at(x, y)[c] += static_cast<float>(glare);
        }
    auto detection = detectGhosts(makeFrame(std::move(image)));
    ASSERT_TRUE(detection) << detection.error().message;
    EXPECT_NEAR(detection->noise_sigma[0], 1.0, 0.25);
    ASSERT_TRUE(detection->light.found);
    EXPECT_NEAR(detection->light.centre_px.x(), lx, 1.0);
    // The glare falls to 15 sigmas at r of about 17 px, and the margin adds 3; a thousandth of the
    // core would have ended the disc at 2 px.
    EXPECT_GT(detection->light.radius_px, 14.0);
    EXPECT_LT(detection->light.radius_px, 30.0);
    bool ghost = false;
    for (const GhostCandidate& c : detection->candidates)
        ghost = ghost || std::hypot(c.centroid_px.x() - 150.0, c.centroid_px.y() - 220.0) < 8.0;
    EXPECT_TRUE(ghost) << detection->candidates.size() << " candidates";
}

}  // namespace
}  // namespace flarelab::fit
