// The "aravis:" URI and the kernel-limit message, which need no camera (the camera itself:
// tests/aravis).
#if FLARELAB_HAVE_ARAVIS
#include <gtest/gtest.h>

#include "drivers/aravis_camera.h"

namespace flarelab::drivers {
namespace {

Result<AravisOptions> optionsOf(const std::string& text) {
    auto uri = parseDeviceUri(text);
    if (!uri) return uri.error();
    return aravisOptions(*uri);
}

TEST(AravisOptions, ReadsEveryParameter) {
    const auto o = optionsOf(
        "aravis:Basler-40012345?roi=16,8,640,480&pixel_format=Mono12p&packet_size=9000&"
        "socket_buffer=8388608&timeout_s=1.5&retries=4&trigger=single-frame&gain_db_per_raw=0."
        "0359");
    ASSERT_TRUE(o) << o.error().message;
    EXPECT_EQ(o->device, "Basler-40012345");
    EXPECT_EQ(o->roi, (AravisRoi{16, 8, 640, 480}));
    EXPECT_EQ(o->pixel_format, "Mono12p");
    EXPECT_EQ(o->packet_size, 9000);
    EXPECT_EQ(o->socket_buffer, 8388608);
    EXPECT_EQ(o->timeout_s, 1.5);
    EXPECT_EQ(o->retries, 4);
    EXPECT_EQ(o->trigger, AravisTrigger::SingleFrame);
    EXPECT_EQ(o->gain_db_per_raw, 0.0359);
    const auto defaults = optionsOf("aravis:192.168.10.2");
    ASSERT_TRUE(defaults);
    EXPECT_EQ(defaults->device, "192.168.10.2");
    AravisOptions expected;
    expected.device = "192.168.10.2";
    EXPECT_EQ(*defaults, expected);
    EXPECT_EQ(optionsOf("aravis:")->device, "");
}

TEST(AravisOptions, RefusesUnknownAndOutOfRangeParametersByName) {
    struct Case {
        const char* uri;
        const char* named;
    };
    for (const Case c : {
             Case{"aravis:x?exposure=1", "'exposure'"},
             Case{"aravis:x?roi=1,2,3", "roi=1,2,3"},
             Case{"aravis:x?roi=1,2,3,4,5", "roi="},
             Case{"aravis:x?roi=-1,0,8,8", "roi=-1,0,8,8"},
             Case{"aravis:x?roi=0,0,0,8", "roi="},
             Case{"aravis:x?roi=a,b,c,d", "roi="},
             Case{"aravis:x?roi=1,,3,4", "roi="},
             Case{"aravis:x?pixel_format=RGB8", "pixel_format=RGB8"},
             Case{"aravis:x?packet_size=100", "packet_size=100"},
             Case{"aravis:x?packet_size=9000.5", "packet_size="},
             Case{"aravis:x?socket_buffer=12", "socket_buffer=12"},
             Case{"aravis:x?timeout_s=0", "timeout_s"},
             Case{"aravis:x?timeout_s=nan", "timeout_s"},
             Case{"aravis:x?retries=-1", "retries=-1"},
             Case{"aravis:x?retries=1000", "retries=1000"},
             Case{"aravis:x?trigger=hardware", "trigger=hardware"},
             Case{"aravis:x?gain_db_per_raw=0", "gain_db_per_raw"},
         }) {
        const auto o = optionsOf(c.uri);
        ASSERT_FALSE(o) << c.uri;
        EXPECT_EQ(o.error().code, ErrorCode::InvalidArgument) << c.uri;
        EXPECT_NE(o.error().message.find(c.named), std::string::npos)
            << c.uri << ": " << o.error().message;
    }
}

TEST(AravisSocketBuffer, TooLargeNamesTheSysctlAndTheValueToSet) {
    const Error e = socketBufferTooLarge(8388608, 212992);
    EXPECT_EQ(e.code, ErrorCode::InvalidArgument);
    EXPECT_NE(e.message.find("net.core.rmem_max = 212992"), std::string::npos) << e.message;
    EXPECT_NE(e.message.find("sysctl -w net.core.rmem_max=8388608"), std::string::npos);
    EXPECT_NE(e.message.find("/etc/sysctl.d/"), std::string::npos);
    const auto limit = kernelReceiveBufferLimit();
    ASSERT_TRUE(limit) << "/proc/sys/net/core/rmem_max is not readable";
    EXPECT_GT(*limit, 0);
}

}  // namespace
}  // namespace flarelab::drivers
#endif
