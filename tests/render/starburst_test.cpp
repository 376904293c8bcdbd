#include "render/starburst.h"

#include <gtest/gtest.h>

#include <cmath>
#include <vector>

namespace flarelab::render {
namespace {

// A small, fast configuration: the stop spans 64 samples in a 1024 FFT, so the reference
// wavelength's first Airy zero lies at 1.2197 * 1024 / 64 = 19.5 pattern pixels.
StarburstOptions smallOptions() {
    StarburstOptions o;
    o.mask_size = 64;
    o.fft_size = 1024;
    return o;
}

double channelSum(const ImageRGB& image, int c) {
    double sum = 0.0;
    for (int64_t i = 0; i < image.width * image.height; ++i) sum += image.pixels[i * 3 + c];
    return sum;
}

bool allFinite(const ImageRGB& image) {
    for (float x : image.pixels)
        if (!std::isfinite(x)) return false;
    return true;
}

// Bilinear sample of channel c at (x, y) relative to the centre, rotated by `angle`.
double rotatedSample(const ImageRGB& p, int c, double x, double y, double angle) {
    const double cx = static_cast<double>(p.width / 2), cy = static_cast<double>(p.height / 2);
    const double rx = cx + std::cos(angle) * x - std::sin(angle) * y;
    const double ry = cy + std::sin(angle) * x + std::cos(angle) * y;
    const int x0 = static_cast<int>(std::floor(rx)), y0 = static_cast<int>(std::floor(ry));
    const double tx = rx - x0, ty = ry - y0;
    return (1 - tx) * (1 - ty) * p.at(x0, y0)[c] + tx * (1 - ty) * p.at(x0 + 1, y0)[c] +
           (1 - tx) * ty * p.at(x0, y0 + 1)[c] + tx * ty * p.at(x0 + 1, y0 + 1)[c];
}

// Radius of the first local minimum beyond `from` pixels of channel c's azimuthal mean, sampled
// bilinearly along 90 directions every 0.05 pixels.
double firstDarkRing(const ImageRGB& p, int c, double from) {
    constexpr double kStep = 0.05;
    std::vector<double> profile;
    for (double r = 0.0; r < 60.0; r += kStep) {
        double sum = 0.0;
        for (int k = 0; k < 90; ++k) sum += rotatedSample(p, c, r, 0.0, 2.0 * kPi * k / 90.0);
        profile.push_back(sum);
    }
    for (size_t b = static_cast<size_t>(from / kStep) + 1; b + 1 < profile.size(); ++b)
        if (profile[b] <= profile[b - 1] && profile[b] < profile[b + 1]) return b * kStep;
    return -1.0;
}

TEST(RenderStarburst, EachChannelCarriesUnitEnergy) {
    StarburstOptions o = smallOptions();
    o.aperture.blades = 7;
    const Result<ImageRGB> p = renderStarburst(o);
    ASSERT_TRUE(p) << p.error().message;
    EXPECT_EQ(p->width, 1024);
    EXPECT_EQ(p->height, 1024);
    ASSERT_TRUE(allFinite(*p));
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(channelSum(*p, c), 1.0, 1e-5) << c;
    for (float x : p->pixels) ASSERT_GE(x, 0.0f);
}

TEST(RenderStarburst, CleanMaskGivesAPointSymmetricPattern) {
    StarburstOptions o = smallOptions();
    o.aperture.blades = 5;  // a pentagon is not symmetric itself; its |FFT|^2 is
    o.aperture.rotation_rad = 0.3;
    const Result<ImageRGB> p = renderStarburst(o);
    ASSERT_TRUE(p);
    const int64_t m = p->width;
    double worst = 0.0;
    for (int64_t y = 1; y < m; ++y)
        for (int64_t x = 1; x < m; ++x)
            for (int c = 0; c < 3; ++c)
                worst = std::max(worst, std::abs(double(p->at(x, y)[c]) - p->at(m - x, m - y)[c]));
    EXPECT_LE(worst, 1e-9);
}

TEST(RenderStarburst, CircularApertureGivesAnAiryPatternWithTheFirstZeroAt122LambdaOverD) {
    StarburstOptions o = smallOptions();
    o.wavelengths_nm = {450.0, 450.0, 450.0};
    const Result<ImageRGB> p = renderStarburst(o);
    ASSERT_TRUE(p);
    // Zero of J1 at 3.8317: sin(theta) = 1.2197 lambda / D, i.e. 1.2197 * fft / mask bins.
    const double expected = 1.2197 * o.fft_size / o.mask_size;
    EXPECT_NEAR(firstDarkRing(*p, 1, 5.0), expected, 1.0);
    // The Airy disc holds 84 % of the energy.
    double disc = 0.0;
    for (int64_t y = 0; y < p->height; ++y)
        for (int64_t x = 0; x < p->width; ++x)
            if (std::hypot(x - 512.0, y - 512.0) < expected) disc += p->at(x, y)[1];
    EXPECT_NEAR(disc, 0.838, 0.02);
}

TEST(RenderStarburst, RingsGrowInProportionToTheWavelength) {
    const StarburstOptions o = smallOptions();  // red 650, green 550, blue 450 nm
    const Result<ImageRGB> p = renderStarburst(o);
    ASSERT_TRUE(p);
    const double red = firstDarkRing(*p, 0, 5.0);
    const double green = firstDarkRing(*p, 1, 5.0);
    const double blue = firstDarkRing(*p, 2, 5.0);
    EXPECT_NEAR(blue, 19.5, 1.0);
    EXPECT_NEAR(red / blue, 650.0 / 450.0, 0.05);
    EXPECT_NEAR(green / blue, 550.0 / 450.0, 0.05);
}

// Relative L2 difference between the pattern and itself rotated by `angle`, over an annulus
// that leaves out the central peak.
double rotationMismatch(const ImageRGB& p, double angle) {
    double diff = 0.0, norm = 0.0;
    for (int y = -60; y <= 60; ++y) {
        for (int x = -60; x <= 60; ++x) {
            const double r = std::hypot(x, y);
            if (r < 8.0 || r > 60.0) continue;
            const double a = rotatedSample(p, 2, x, y, 0.0);
            const double b = rotatedSample(p, 2, x, y, angle);
            diff += (a - b) * (a - b);
            norm += a * a;
        }
    }
    return std::sqrt(diff / norm);
}

TEST(RenderStarburst, HexagonalApertureGivesSixFoldSymmetry) {
    StarburstOptions o;
    o.mask_size = 64;
    o.fft_size = 1024;
    o.aperture.blades = 6;
    const Result<ImageRGB> p = renderStarburst(o);
    ASSERT_TRUE(p);
    const double at60 = rotationMismatch(*p, kPi / 3.0);
    const double at30 = rotationMismatch(*p, kPi / 6.0);
    EXPECT_LT(at60, 0.01);
    EXPECT_GT(at30, 5.0 * at60);  // the spikes make it anything but round
}

TEST(RenderStarburst, DustChangesThePatternButKeepsItFiniteAndNormalized) {
    StarburstOptions o = smallOptions();
    o.aperture.blades = 6;
    const Result<ImageRGB> clean = renderStarburst(o);
    o.dust_count = 40;
    o.dust_radius_min = 0.03;
    o.dust_radius_max = 0.08;
    o.scratch_count = 5;
    o.scratch_width = 0.03;
    const Result<ImageRGB> dirty = renderStarburst(o);
    ASSERT_TRUE(clean && dirty);
    ASSERT_TRUE(allFinite(*dirty));
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(channelSum(*dirty, c), 1.0, 1e-5);
    double change = 0.0;
    for (size_t i = 0; i < clean->pixels.size(); ++i)
        change += std::abs(clean->pixels[i] - dirty->pixels[i]);
    EXPECT_GT(change, 0.01);
    // The same seed draws the same dirt; another seed draws other dirt.
    const Result<ImageRGB> again = renderStarburst(o);
    ASSERT_TRUE(again);
    EXPECT_EQ(again->pixels, dirty->pixels);
    o.seed = 2;
    const Result<ImageRGB> other = renderStarburst(o);
    ASSERT_TRUE(other);
    EXPECT_NE(other->pixels, dirty->pixels);
}

TEST(RenderStarburst, SeveralBandsPerChannelStayNormalized) {
    StarburstOptions o = smallOptions();
    o.bands_per_channel = 5;
    o.band_width_nm = 80.0;
    const Result<ImageRGB> p = renderStarburst(o);
    ASSERT_TRUE(p);
    ASSERT_TRUE(allFinite(*p));
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(channelSum(*p, c), 1.0, 1e-5);
    // The reference is now the shortest band, 450 - 32 nm: the pixel angle shrinks with it.
    EXPECT_NEAR(starburstPixelAngle(o, 10.0), 418e-6 * 64 / (1024 * 10.0), 1e-15);
}

TEST(RenderStarburst, FullyBlockedApertureIsAnError) {
    StarburstOptions o = smallOptions();
    o.dust_count = 200;
    o.dust_radius_min = 1.0;
    o.dust_radius_max = 1.0;
    const Result<ImageRGB> p = renderStarburst(o);
    ASSERT_FALSE(p);
    EXPECT_NE(p.error().message.find("block"), std::string::npos);
}

TEST(ValidateStarburstOptions, NamesTheBadField) {
    const auto message = [](auto change) {
        StarburstOptions o;
        change(o);
        const Status s = validateStarburstOptions(o);
        return s ? std::string() : s.error().message;
    };
    EXPECT_EQ(message([](StarburstOptions&) {}), "");
    EXPECT_NE(message([](StarburstOptions& o) { o.mask_size = 500; }).find("mask_size"),
              std::string::npos);
    EXPECT_NE(message([](StarburstOptions& o) { o.mask_size = 8; }).find("mask_size"),
              std::string::npos);
    EXPECT_NE(message([](StarburstOptions& o) { o.fft_size = 512; }).find("fft_size"),
              std::string::npos);
    EXPECT_NE(message([](StarburstOptions& o) { o.aperture.blades = 2; }).find("blades"),
              std::string::npos);
    EXPECT_NE(message([](StarburstOptions& o) { o.wavelengths_nm[1] = NAN; }).find("[1]"),
              std::string::npos);
    EXPECT_NE(message([](StarburstOptions& o) { o.dust_count = -1; }).find("dust_count"),
              std::string::npos);
    EXPECT_NE(message([](StarburstOptions& o) { o.dust_radius_min = 0.5; }).find("dust_radius"),
              std::string::npos);
    EXPECT_NE(message([](StarburstOptions& o) { o.scratch_count = -3; }).find("scratch_count"),
              std::string::npos);
    EXPECT_NE(message([](StarburstOptions& o) { o.scratch_width = 0.0; }).find("scratch_width"),
              std::string::npos);
    EXPECT_NE(message([](StarburstOptions& o) { o.bands_per_channel = 0; }).find("bands"),
              std::string::npos);
    EXPECT_NE(message([](StarburstOptions& o) { o.band_width_nm = -1.0; }).find("band_width"),
              std::string::npos);
    StarburstOptions bad;
    bad.fft_size = 3000;
    EXPECT_FALSE(renderStarburst(bad));
}

// A 5 x 5 pattern with a unit spike at its centre and a little energy elsewhere.
ImageRGB tinyPattern() {
    ImageRGB p(5, 5);
    for (int64_t i = 0; i < 25; ++i)
        for (int c = 0; c < 3; ++c) p.pixels[i * 3 + c] = 0.01f;
    for (int c = 0; c < 3; ++c) p.at(2, 2)[c] = 0.76f;
    return p;
}

TEST(AddStarburst, ConservesEnergyAndCentresOnTheLight) {
    const ImageRGB pattern = tinyPattern();
    const float intensity[3] = {2.0f, 3.0f, 0.5f};
    ImageRGB image(32, 32);
    addStarburst(image, pattern, 10.5, 20.5, intensity, 1.0);
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(channelSum(image, c), intensity[c], 1e-5);
    EXPECT_NEAR(image.at(10, 20)[1], 0.76f * 3.0f, 1e-6);
    // Magnified 3x: same energy, spread over 9x the area.
    ImageRGB big(64, 64);
    addStarburst(big, pattern, 30.0, 31.0, intensity, 3.0);
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(channelSum(big, c), intensity[c], 0.02 * intensity[c]);
}

TEST(AddStarburst, KeepsItsEnergyWhenThePatternIsFinerThanThePixels) {
    // A 64 x 64 pattern of unit total reduced to a few pixels: sampling pixel centres would pick
    // a handful of its samples and the energy would jump with the sub-pixel position.
    ImageRGB pattern(64, 64);
    for (int64_t j = 0; j < 64; ++j)
        for (int64_t i = 0; i < 64; ++i)
            for (int c = 0; c < 3; ++c)
                pattern.at(i, j)[c] = static_cast<float>((1 + (i * 7 + j * 13) % 5) / 192.0 / 64.0);
    double total[3] = {0, 0, 0};
    for (int64_t k = 0; k < 64 * 64; ++k)
        for (int c = 0; c < 3; ++c) total[c] += pattern.pixels[k * 3 + c];
    const float intensity[3] = {1.0f, 2.0f, 4.0f};
    for (const double scale : {0.06, 0.3, 0.99})
        for (const double offset : {0.0, 0.25, 0.5}) {
            ImageRGB image(100, 80);  // holds the whole pattern at every scale here
            addStarburst(image, pattern, 50.0 + offset, 40.0 - offset, intensity, scale);
            for (int c = 0; c < 3; ++c)
                EXPECT_NEAR(channelSum(image, c), total[c] * intensity[c], 1e-5 * intensity[c])
                    << scale << " " << offset;
        }
}

TEST(AddStarburst, ClipsAtTheBorderWithTheCentreOutside) {
    const ImageRGB pattern = tinyPattern();
    const float intensity[3] = {1.0f, 1.0f, 1.0f};
    ImageRGB image(16, 16);
    addStarburst(image, pattern, -1.0, 8.5, intensity, 2.0);  // half the pattern reaches in
    const double inside = channelSum(image, 0);
    EXPECT_GT(inside, 0.0);
    EXPECT_LT(inside, 0.5);
    ASSERT_TRUE(allFinite(image));
    ImageRGB far(16, 16);
    for (double c : {-1e300, -1e9, 1e9, 1e300}) {
        addStarburst(far, pattern, c, 8.0, intensity, 2.0);
        addStarburst(far, pattern, 8.0, c, intensity, 2.0);
    }
    EXPECT_EQ(channelSum(far, 0), 0.0);
}

TEST(AddStarburst, HandlesTinyImagesAndZeroIntensity) {
    const ImageRGB pattern = tinyPattern();
    const float intensity[3] = {1.0f, 2.0f, 3.0f};
    ImageRGB one(1, 1);
    addStarburst(one, pattern, 0.5, 0.5, intensity, 1.0);
    EXPECT_NEAR(one.at(0, 0)[2], 0.76f * 3.0f, 1e-6);
    addStarburst(one, pattern, 0.5, 0.5, intensity, 1e-3);  // the whole pattern in one pixel
    EXPECT_TRUE(allFinite(one));
    ImageRGB none;
    addStarburst(none, pattern, 0.0, 0.0, intensity, 1.0);
    const float zero[3] = {0.0f, 0.0f, 0.0f};
    ImageRGB dark(8, 8);
    addStarburst(dark, pattern, 4.0, 4.0, zero, 1.5);
    EXPECT_EQ(channelSum(dark, 0) + channelSum(dark, 1) + channelSum(dark, 2), 0.0);
    addStarburst(dark, ImageRGB(), 4.0, 4.0, intensity, 1.5);
    EXPECT_EQ(channelSum(dark, 0), 0.0);
}

TEST(AddStarburstDeathTest, RejectsANonPositiveScale) {
    const ImageRGB pattern = tinyPattern();
    const float intensity[3] = {1.0f, 1.0f, 1.0f};
    ImageRGB image(4, 4);
    EXPECT_DEATH(addStarburst(image, pattern, 2.0, 2.0, intensity, 0.0), "scale");
}

}  // namespace
}  // namespace flarelab::render
