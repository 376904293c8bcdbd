#include "drivers/device.h"

#include <gtest/gtest.h>

#include "drivers/camera.h"

namespace flarelab::drivers {
namespace {

TEST(ParseDeviceUri, SplitsSchemePathAndParameters) {
    const auto uri = parseDeviceUri("aravis:Basler-40012345?packet_size=9000&trigger=soft");
    ASSERT_TRUE(uri);
    EXPECT_EQ(uri->scheme, "aravis");
    EXPECT_EQ(uri->path, "Basler-40012345");
    EXPECT_EQ(uri->params.at("packet_size"), "9000");
    EXPECT_EQ(uri->params.at("trigger"), "soft");
    const auto v4l2 = parseDeviceUri("v4l2:/dev/video0");
    ASSERT_TRUE(v4l2);
    EXPECT_EQ(v4l2->path, "/dev/video0");
    EXPECT_TRUE(v4l2->params.empty());
}

TEST(ParseDeviceUri, ReadsABareSchemeAsAnEmptyPath) {
    for (const char* text : {"sim", "sim:"}) {
        const auto uri = parseDeviceUri(text);
        ASSERT_TRUE(uri) << text;
        EXPECT_EQ(uri->scheme, "sim");
        EXPECT_EQ(uri->path, "");
    }
}

TEST(ParseDeviceUri, RejectsMalformedText) {
    for (const char* text : {"", ":x", "Sim:", "s m:", "sim:?width", "sim:?=3", "sim:?a=1&a=2"}) {
        const auto uri = parseDeviceUri(text);
        ASSERT_FALSE(uri) << text;
        EXPECT_EQ(uri.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(uri.error().message.find("device uri"), std::string::npos);
    }
}

TEST(DeviceUri, NumbersAndUnknownParametersNameTheKey) {
    const auto uri = parseDeviceUri("sim:?width=64&height=abc");
    ASSERT_TRUE(uri);
    EXPECT_EQ(*uri->number("width", 1.0), 64.0);
    EXPECT_EQ(*uri->number("seed", 7.0), 7.0);
    const auto bad = uri->number("height", 1.0);
    ASSERT_FALSE(bad);
    EXPECT_NE(bad.error().message.find("height"), std::string::npos);
    const Status unknown = uri->onlyParams({"width"});
    ASSERT_FALSE(unknown);
    EXPECT_NE(unknown.error().message.find("'height'"), std::string::npos);
}

TEST(DeviceError, TagSurvivesContextAndMapsToACode) {
    const Error e = deviceError(DeviceFault::Timeout, "cam 1", "no frame");
    EXPECT_EQ(e.code, ErrorCode::IoError);
    EXPECT_EQ(e.message, "[timeout] cam 1: no frame");
    EXPECT_EQ(deviceFaultOf(e.withContext("sweep step 3")), DeviceFault::Timeout);
    EXPECT_EQ(deviceError(DeviceFault::OutOfRange, "x", "y").code, ErrorCode::InvalidArgument);
    EXPECT_EQ(deviceError(DeviceFault::Disconnected, "x", "y").code, ErrorCode::NotFound);
    EXPECT_EQ(deviceFaultOf(makeError(ErrorCode::IoError, "disk full")), std::nullopt);
    for (DeviceFault f : {DeviceFault::OutOfRange, DeviceFault::Timeout, DeviceFault::Stalled,
                          DeviceFault::NotHomed, DeviceFault::LostPosition, DeviceFault::Stopped,
                          DeviceFault::Busy, DeviceFault::Disconnected, DeviceFault::BadFrame})
        EXPECT_EQ(deviceFaultOf(deviceError(f, "d", "m")), f) << deviceFaultName(f);
}

// A camera that only knows its URI, to test the registry alone.
class NamedCamera final : public Camera {
public:
    explicit NamedCamera(std::string uri) : uri_(std::move(uri)) {}
    DeviceIdentity identity() const override { return {"fake", "Fake", "0", uri_}; }
    CameraCapabilities capabilities() const override { return {}; }
    Status setExposure(double) override { return Ok{}; }
    double exposure_s() const override { return 1.0; }
    Status setGain(double) override { return Ok{}; }
    double gain() const override { return 1.0; }
    Status setFormat(hdr::RawFormat) override { return Ok{}; }
    hdr::RawFormat format() const override { return hdr::RawFormat::Mono; }
    Result<hdr::RawFrame> capture(double) override { return hdr::RawFrame{}; }
    void abort() override {}

private:
    std::string uri_;
};

TEST(DeviceRegistry, OpensByUriAndAliasAndEnumerates) {
    CameraRegistry registry;
    ASSERT_TRUE(registry.addBackend(
        "fake", "test backend",
        [](const DeviceUri& uri) -> Result<std::unique_ptr<Camera>> {
            return std::unique_ptr<Camera>(std::make_unique<NamedCamera>(uri.text));
        },
        [] {
            DeviceListing a, b;
            a.uri = "fake:a";
            b.uri = "fake:b";
            return std::vector<DeviceListing>{a, b};
        }));
    ASSERT_TRUE(registry.addAlias("bench", "fake:b"));
    const auto direct = registry.open("fake:a");
    ASSERT_TRUE(direct);
    EXPECT_EQ((*direct)->identity().uri, "fake:a");
    const auto aliased = registry.open("bench");
    ASSERT_TRUE(aliased);
    EXPECT_EQ((*aliased)->identity().uri, "fake:b");
    const auto listed = registry.enumerate();
    ASSERT_EQ(listed.size(), 2u);
    EXPECT_EQ(listed[0].uri, "fake:a");
    EXPECT_EQ(listed[1].uri, "fake:b");
    ASSERT_EQ(registry.backends().size(), 1u);

    const auto missing = registry.open("v4l2:/dev/video0");
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::NotFound);
    EXPECT_NE(missing.error().message.find("fake"), std::string::npos);  // lists known schemes
    EXPECT_FALSE(registry.addBackend("fake", "again", {}));
    EXPECT_FALSE(registry.addAlias("bench", "fake:a"));
    EXPECT_FALSE(registry.addAlias("a:b", "fake:a"));
}

}  // namespace
}  // namespace flarelab::drivers
