#include "drivers/apt_head.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <thread>

#include "drivers/rig.h"
#include "drivers/stage_sim.h"
#include "stage_test_util.h"

namespace flarelab::drivers {
namespace {

using stage_testing::faultOf;
using stage_testing::messageOf;
using stage_testing::waitUntil;

// ---------------------------------------------------------------------------------------------
// The protocol

AptMessage moveAbsolute(int32_t counts) {
    AptMessage m;
    m.id = apt::kMotMoveAbsolute;
    m.destination = apt::kGenericUsb;
    m.source = apt::kHost;
    m.has_data = true;
    m.data = {0x01,
              0x00,
              static_cast<uint8_t>(counts & 0xFF),
              static_cast<uint8_t>((counts >> 8) & 0xFF),
              static_cast<uint8_t>((counts >> 16) & 0xFF),
              static_cast<uint8_t>((counts >> 24) & 0xFF)};
    return m;
}

TEST(EncodeAptMessage, LaysOutTheHeaderAsTheManualDoes) {
    AptMessage home;
    home.id = apt::kMotMoveHome;
    home.param1 = 0x01;
    home.destination = apt::kGenericUsb;
    home.source = apt::kHost;
    EXPECT_EQ(encodeAptMessage(home), (std::vector<uint8_t>{0x43, 0x04, 0x01, 0x00, 0x50, 0x01}));
    // A long message: the data length in bytes 2-3, the destination with bit 0x80.
    EXPECT_EQ(encodeAptMessage(moveAbsolute(-2)),
              (std::vector<uint8_t>{0x53, 0x04, 0x06, 0x00, 0xD0, 0x01, 0x01, 0x00, 0xFE, 0xFF,
                                    0xFF, 0xFF}));
}

TEST(ParseAptMessage, RoundTripsAndNamesWhatIsWrong) {
    const std::vector<uint8_t> bytes = encodeAptMessage(moveAbsolute(27307));
    auto m = parseAptMessage(bytes);
    ASSERT_TRUE(m) << m.error().message;
    EXPECT_EQ(*m, moveAbsolute(27307));

    const auto fails = [](std::vector<uint8_t> b, const char* why) {
        auto r = parseAptMessage(b);
        ASSERT_FALSE(r) << why;
        EXPECT_EQ(r.error().code, ErrorCode::ParseError);
        EXPECT_NE(r.error().message.find(why), std::string::npos) << r.error().message;
    };
    fails({0x53, 0x04, 0x06}, "6-byte header");
    fails({0x34, 0x12, 0x00, 0x00, 0x50, 0x01}, "unknown message 0x1234");
    fails({0x53, 0x04, 0x05, 0x00, 0xD0, 0x01, 1, 0, 0, 0, 0}, "with 5 data bytes");
    fails({0x53, 0x04, 0x06, 0x00, 0xD0, 0x01, 1, 0, 0, 0}, "4 follow");
    fails({0x53, 0x04, 0x01, 0x00, 0x50, 0x01}, "without its 6 data bytes");
    fails({0x43, 0x04, 0x01, 0x00, 0x50, 0x01, 0x00}, "followed by 1 more");
    fails({0x43, 0x04, 0x01, 0x00, 0x33, 0x01}, "destination 0x33");
    fails({0x43, 0x04, 0x01, 0x00, 0x50, 0x02}, "source 0x02");
}

TEST(ParseAptMessage, AcceptsBothFormsOfTheMoveAnnouncements) {
    for (const uint16_t id : {apt::kMotMoveCompleted, apt::kMotMoveStopped}) {
        AptMessage bare;
        bare.id = id;
        bare.param1 = 1;
        bare.destination = apt::kHost;
        bare.source = apt::kGenericUsb;
        auto parsed = parseAptMessage(encodeAptMessage(bare));
        ASSERT_TRUE(parsed) << parsed.error().message;
        auto status = decodeAptStatus(*parsed);
        ASSERT_TRUE(status);
        EXPECT_FALSE(status->full);
        EXPECT_EQ(status->channel, 1);
    }
    AptMessage full;
    full.id = apt::kMotMoveCompleted;
    full.destination = apt::kHost;
    full.source = apt::kGenericUsb;
    full.has_data = true;
    full.data = {1, 0, 0x39, 0x30, 0, 0, 0, 0, 0, 0, 0x00, 0x04, 0x00, 0x80};
    auto status = decodeAptStatus(*parseAptMessage(encodeAptMessage(full)));
    ASSERT_TRUE(status);
    EXPECT_TRUE(status->full);
    EXPECT_EQ(status->position, 12345);
    EXPECT_EQ(status->status_bits, apt::kHomed | apt::kEnabled);
    EXPECT_EQ(describeAptStatusBits(status->status_bits), "homed, enabled (0x80000400)");
}

TEST(FindAptFrame, FindsMessagesAndSkipsGarbage) {
    const std::vector<uint8_t> move = encodeAptMessage(moveAbsolute(100));
    std::vector<uint8_t> stream{0xFF, 0x00, 0x13};  // line noise
    stream.insert(stream.end(), move.begin(), move.end());
    size_t dropped = 0;
    std::span<const uint8_t> rest(stream);
    for (;;) {
        const AptFraming f = findAptFrame(rest);
        ASSERT_NE(f.kind, AptFraming::Kind::NeedMore);
        if (f.kind == AptFraming::Kind::Message) {
            EXPECT_EQ(f.length, move.size());
            auto m = parseAptMessage(rest.first(f.length));
            ASSERT_TRUE(m);
            EXPECT_EQ(*m, moveAbsolute(100));
            break;
        }
        dropped += f.length;
        rest = rest.subspan(f.length);
    }
    EXPECT_EQ(dropped, 3u);
    // A message that has not fully arrived: wait for the rest.
    EXPECT_EQ(findAptFrame(std::span<const uint8_t>(move).first(8)).kind,
              AptFraming::Kind::NeedMore);
    EXPECT_EQ(findAptFrame(std::span<const uint8_t>(move).first(1)).kind,
              AptFraming::Kind::NeedMore);
    EXPECT_EQ(findAptFrame({}).kind, AptFraming::Kind::NeedMore);
}

TEST(FindAptFrame, EveryFrameOfRandomBytesParses) {
    std::mt19937_64 rng(17);
    for (int trial = 0; trial < 2000; ++trial) {
        std::vector<uint8_t> bytes(std::uniform_int_distribution<size_t>(0, 64)(rng));
        for (uint8_t& b : bytes) b = static_cast<uint8_t>(rng());
        // Seed some plausible headers among the noise.
        if (bytes.size() >= 6 && trial % 2) {
            bytes[0] = 0x12;
            bytes[1] = 0x04;
            bytes[4] = 0xD0 | (bytes[4] & 1 ? 0x80 : 0);
            bytes[5] = 0x01;
        }
        std::span<const uint8_t> rest(bytes);
        while (!rest.empty()) {
            const AptFraming f = findAptFrame(rest);
            if (f.kind == AptFraming::Kind::NeedMore) break;
            ASSERT_GE(f.length, 1u);
            ASSERT_LE(f.length, rest.size());
            if (f.kind == AptFraming::Kind::Message) {
                ASSERT_TRUE(parseAptMessage(rest.first(f.length))) << "trial " << trial;
            }
            rest = rest.subspan(f.length);
        }
    }
}

TEST(DecodeAptHwInfo, ReadsModelSerialFirmwareAndChannels) {
    AptMessage m;
    m.id = apt::kHwGetInfo;
    m.has_data = true;
    m.data.assign(84, 0);
    m.data[0] = 0xC1;  // serial 55000001 = 0x03473BC1, little-endian
    m.data[1] = 0x3B;
    m.data[2] = 0x47;
    m.data[3] = 0x03;
    const std::string model = "K10CR1";
    std::copy(model.begin(), model.end(), m.data.begin() + 4);
    m.data[14] = 7;  // minor
    m.data[15] = 0;
    m.data[16] = 2;  // major
    m.data[82] = 1;
    auto info = decodeAptHwInfo(m);
    ASSERT_TRUE(info) << info.error().message;
    EXPECT_EQ(info->serial, 55000001u);
    EXPECT_EQ(info->model, "K10CR1");
    EXPECT_EQ(info->firmware, "2.0.7");
    EXPECT_EQ(info->channels, 1);
    m.data[6] = 0x07;
    EXPECT_FALSE(decodeAptHwInfo(m));
    m.data.resize(80);
    EXPECT_FALSE(decodeAptHwInfo(m));
}

TEST(AptHeadOptions, ReadsTheUriAndNamesBadParameters) {
    auto uri = parseDeviceUri("apt:/dev/ttyUSB0?channel=2&counts_per_deg=1919.64&max_deg=90");
    ASSERT_TRUE(uri);
    auto o = AptHeadOptions::fromUri(*uri);
    ASSERT_TRUE(o) << o.error().message;
    EXPECT_EQ(o->channel, 2);
    EXPECT_EQ(o->counts_per_deg, 1919.64);
    EXPECT_EQ(o->max_deg, 90.0);
    EXPECT_EQ(o->min_deg, -180.0);
    for (const char* bad :
         {"apt:", "apt:/dev/x?channel=0", "apt:/dev/x?address=2", "apt:/dev/x?counts_per_deg=0",
          "apt:/dev/x?max_deg=100000", "apt:/dev/x?poll_s=-1", "apt:/dev/x?speed=1"}) {
        auto u = parseDeviceUri(bad);
        ASSERT_TRUE(u) << bad;
        auto options = AptHeadOptions::fromUri(*u);
        ASSERT_FALSE(options) << bad;
        EXPECT_EQ(options.error().code, ErrorCode::InvalidArgument) << bad;
    }
}

// ---------------------------------------------------------------------------------------------
// The driver against the simulator

constexpr double kCounts = kK10cr1CountsPerDeg;

AptSimOptions fastMount() {
    AptSimOptions o;
    o.speed_deg_s = 250.0;  // near the top a 32-bit velocity parameter can hold
    o.accel_deg_s2 = 1.0e6;
    return o;
}

AptSimOptions slowMount() {
    AptSimOptions o;
    o.speed_deg_s = 10.0;
    o.accel_deg_s2 = 1000.0;
    return o;
}

std::string uriOf(const StageSim& sim, const std::string& extra = "") {
    return "apt:" + sim.slavePath() +
           "?poll_s=0.002&reply_timeout_s=0.15&init_dwell_s=0.005&max_speed_deg_s=280" + extra;
}

Result<std::unique_ptr<AptHead>> openHead(const StageSim& sim, const std::string& extra = "") {
    auto uri = parseDeviceUri(uriOf(sim, extra));
    if (!uri) return uri.error();
    auto options = AptHeadOptions::fromUri(*uri);
    if (!options) return options.error();
    return AptHead::open(*options);
}

struct Mount {
    std::unique_ptr<AptSim> sim;
    std::unique_ptr<AptHead> head;
};

Mount mount(AptSimOptions options, bool home = true, const std::string& extra = "") {
    Mount m;
    auto sim = AptSim::start(options);
    EXPECT_TRUE(sim) << messageOf(sim);
    if (!sim) return m;
    m.sim = std::move(*sim);
    auto head = openHead(*m.sim, extra);
    EXPECT_TRUE(head) << messageOf(head);
    if (!head) return m;
    m.head = std::move(*head);
    if (home) {
        const Status homed = m.head->home(5.0);
        EXPECT_TRUE(homed) << messageOf(homed);
    }
    return m;
}

TEST(AptHead, OpensWithTheInitialisationAndReadsIdentitySpeedAndHomedState) {
    AptSimOptions options = slowMount();
    options.start_position = 5000;
    options.enabled = false;
    Mount m = mount(options, false);
    ASSERT_TRUE(m.head);
    EXPECT_FALSE(m.head->rtsApplied());  // a pty has no RTS line, and that is no error
    EXPECT_TRUE(m.sim->enabled());       // MGMSG_MOD_SET_CHANENABLESTATE was sent
    const DeviceIdentity id = m.head->identity();
    EXPECT_EQ(id.backend, "apt");
    EXPECT_EQ(id.serial, "55000001");
    EXPECT_EQ(id.model, "Thorlabs K10CR1 (firmware 1.0.3)");
    EXPECT_NEAR(m.head->speed_deg_s(), 10.0, 1e-6);
    EXPECT_DOUBLE_EQ(m.head->countsPerDeg(), kCounts);
    EXPECT_EQ(faultOf(m.head->position()), DeviceFault::NotHomed);
    EXPECT_EQ(faultOf(m.head->moveTo(1.0, 1.0)), DeviceFault::NotHomed);
    ASSERT_TRUE(m.head->home(5.0));
    EXPECT_TRUE(m.sim->homed());
    auto at = m.head->position();
    ASSERT_TRUE(at);
    EXPECT_EQ(*at, 0.0);
    // A mount already homed stays homed for the next program.
    m.head.reset();
    auto again = openHead(*m.sim);
    ASSERT_TRUE(again) << messageOf(again);
    EXPECT_TRUE((*again)->position());
}

TEST(AptHead, AMoveGoesToTheCountOfItsOwnAngleNotASumOfSteps) {
    Mount m = mount(fastMount());
    ASSERT_TRUE(m.head);
    // 0.2 deg is 27306.67 counts: adding rounded steps drifts from the true count.
    const int64_t step = std::llround(0.2 * kCounts);
    bool drifts = false;
    for (int i = 0; i <= 150; ++i) drifts = drifts || i * step != std::llround(i * 0.2 * kCounts);
    ASSERT_TRUE(drifts);
    for (int i = 0; i <= 150; ++i) {
        const double angle = i * 0.2;
        auto at = m.head->moveTo(angle, 2.0);
        ASSERT_TRUE(at) << "step " << i << ": " << messageOf(at);
        const int64_t expected = std::llround(angle * kCounts);
        ASSERT_EQ(m.sim->position(), expected) << "step " << i;
        EXPECT_EQ(m.head->targetCounts(angle), expected);
        EXPECT_DOUBLE_EQ(*at, static_cast<double>(expected) / kCounts);
    }
    ASSERT_TRUE(m.head->moveTo(-90.0, 2.0));
    EXPECT_EQ(m.sim->position(), std::llround(-90.0 * kCounts));
}

TEST(AptHead, WaitsWhileMovingAndReportsWhereItIsMeanwhile) {
    Mount m = mount(slowMount());
    ASSERT_TRUE(m.head);
    std::optional<Result<double>> result;
    std::thread mover([&] { result = m.head->moveTo(3.0, 5.0); });
    ASSERT_TRUE(waitUntil([&] { return m.sim->position() > 0; }, 5.0));
    auto midway = m.head->position();
    ASSERT_TRUE(midway) << messageOf(midway);
    EXPECT_GT(*midway, 0.0);
    EXPECT_LT(*midway, 3.0);
    EXPECT_EQ(faultOf(m.head->moveTo(1.0, 1.0)), DeviceFault::Busy);
    mover.join();
    ASSERT_TRUE(*result) << messageOf(*result);
    EXPECT_EQ(m.sim->position(), std::llround(3.0 * kCounts));
}

TEST(AptHead, StopFromAnotherThreadEndsTheMoveAsStopped) {
    Mount m = mount(slowMount());
    ASSERT_TRUE(m.head);
    std::optional<Result<double>> result;
    std::thread mover([&] { result = m.head->moveTo(90.0, 20.0); });
    ASSERT_TRUE(waitUntil([&] { return m.sim->position() > 0; }, 5.0));
    ASSERT_TRUE(m.head->stop());
    mover.join();
    EXPECT_EQ(faultOf(*result), DeviceFault::Stopped) << messageOf(*result);
    EXPECT_FALSE(m.sim->moving());
    EXPECT_GT(m.sim->position(), 0);
    EXPECT_LT(m.sim->position(), std::llround(90.0 * kCounts));
    EXPECT_TRUE(m.head->stop());  // idle: nothing to do
    auto next = m.head->moveTo(0.5, 5.0);
    EXPECT_TRUE(next) << messageOf(next);
}

TEST(AptHead, LimitsGiveOutOfRange) {
    Mount m = mount(fastMount(), true, "&min_deg=-30&max_deg=30");
    ASSERT_TRUE(m.head);
    EXPECT_EQ(m.head->limits().max_deg, 30.0);
    EXPECT_EQ(faultOf(m.head->moveTo(30.5, 1.0)), DeviceFault::OutOfRange);
    EXPECT_EQ(faultOf(m.head->moveTo(-31.0, 1.0)), DeviceFault::OutOfRange);
    EXPECT_EQ(faultOf(m.head->moveTo(INFINITY, 1.0)), DeviceFault::OutOfRange);
    EXPECT_EQ(faultOf(m.head->moveTo(1.0, -1.0)), DeviceFault::OutOfRange);
    EXPECT_TRUE(m.head->moveTo(30.0, 2.0));
    EXPECT_EQ(m.sim->position(), std::llround(30.0 * kCounts));
}

TEST(AptHead, SetsSpeedInVelocityUnitsAndReadsItBack) {
    Mount m = mount(fastMount());
    ASSERT_TRUE(m.head);
    ASSERT_TRUE(m.head->setSpeed(7.5));
    EXPECT_EQ(m.sim->maxVelocity(), std::llround(7.5 * kK10cr1VelocityPerDegS));
    EXPECT_NEAR(m.head->speed_deg_s(), 7.5, 1e-6);
    EXPECT_EQ(faultOf(m.head->setSpeed(-1.0)), DeviceFault::OutOfRange);
    EXPECT_EQ(faultOf(m.head->setSpeed(281.0)), DeviceFault::OutOfRange);
    m.head.reset();
    // The K10CR1's 10 deg/s cap applies by default: 7.5 is below it and stays.
    AptHeadOptions plain;
    plain.port = m.sim->slavePath();
    plain.init_dwell_s = 0.0;
    plain.reply_timeout_s = 0.15;
    auto capped = AptHead::open(plain);
    ASSERT_TRUE(capped) << messageOf(capped);
    EXPECT_NEAR((*capped)->speed_deg_s(), 7.5, 1e-6);
    capped->reset();
    // A mount running faster than the cap is slowed down at open.
    {
        auto fast = openHead(*m.sim);
        ASSERT_TRUE(fast) << messageOf(fast);
        ASSERT_TRUE((*fast)->setSpeed(200.0));
    }
    auto slowed = AptHead::open(plain);
    ASSERT_TRUE(slowed) << messageOf(slowed);
    EXPECT_NEAR((*slowed)->speed_deg_s(), 10.0, 1e-6);
    EXPECT_EQ(m.sim->maxVelocity(), std::llround(10.0 * kK10cr1VelocityPerDegS));
}

TEST(AptHead, AMoveThatOutlastsItsTimeoutIsStoppedAndTimesOut) {
    Mount m = mount(slowMount());
    ASSERT_TRUE(m.head);
    auto late = m.head->moveTo(90.0, 0.1);
    EXPECT_EQ(faultOf(late), DeviceFault::Timeout) << messageOf(late);
    EXPECT_TRUE(waitUntil([&] { return !m.sim->moving(); }, 1.0));
}

TEST(AptHead, FinishesAMoveWhoseAnnouncementIsLost) {
    AptSimOptions options = fastMount();
    options.faults.drop_announcements = true;
    Mount m = mount(options);
    ASSERT_TRUE(m.head);  // homing ends on the "homed" status bit
    auto at = m.head->moveTo(12.0, 2.0);
    ASSERT_TRUE(at) << messageOf(at);
    EXPECT_EQ(m.sim->position(), std::llround(12.0 * kCounts));
}

TEST(AptHead, IgnoresUnsolicitedStatusMessages) {
    AptSimOptions options = fastMount();
    options.faults.unsolicited_status_s = 0.001;
    Mount m = mount(options);
    ASSERT_TRUE(m.head);
    for (const double angle : {1.0, 2.0, -3.0}) {
        auto at = m.head->moveTo(angle, 2.0);
        EXPECT_TRUE(at) << messageOf(at);
    }
}

TEST(AptHead, RecoversFromOneBadReply) {
    for (int kind = 0; kind < 6; ++kind) {
        Mount m = mount(fastMount());
        ASSERT_TRUE(m.head);
        StageSimFaults once;
        (kind == 0   ? once.garble_replies
         : kind == 1 ? once.truncate_replies
         : kind == 2 ? once.wrong_address_replies
         : kind == 3 ? once.wrong_id_replies
         : kind == 4 ? once.wrong_channel_replies
                     : once.drop_replies) = 1;
        m.sim->setFaults(once);
        auto at = m.head->moveTo(2.0, 2.0);
        EXPECT_TRUE(at) << "fault " << kind << ": " << messageOf(at);
        EXPECT_EQ(m.sim->position(), std::llround(2.0 * kCounts)) << "fault " << kind;
    }
}

struct PersistentFault {
    const char* name;
    void (*set)(StageSimFaults&);
    std::optional<DeviceFault> fault;  // nullopt: an untagged IoError
    const char* says;
};

TEST(AptHead, EveryPersistentReplyFaultGivesAClearError) {
    const PersistentFault cases[] = {
        {"garbled", [](StageSimFaults& f) { f.garble_replies = 100; }, DeviceFault::Timeout,
         "no MGMSG_MOT_GET_POSCOUNTER"},
        {"truncated", [](StageSimFaults& f) { f.truncate_replies = 100; }, DeviceFault::Timeout,
         "cut short"},
        {"wrong address", [](StageSimFaults& f) { f.wrong_address_replies = 100; }, std::nullopt,
         "from address 0x21"},
        {"wrong channel", [](StageSimFaults& f) { f.wrong_channel_replies = 100; }, std::nullopt,
         "for channel 2"},
        {"wrong id", [](StageSimFaults& f) { f.wrong_id_replies = 100; }, DeviceFault::Timeout,
         "other messages: MGMSG_MOT_GET_STATUSBITS"},
        {"no reply", [](StageSimFaults& f) { f.drop_replies = 100; }, DeviceFault::Timeout,
         "no MGMSG_MOT_GET_POSCOUNTER"},
    };
    for (const PersistentFault& c : cases) {
        Mount m = mount(fastMount());
        ASSERT_TRUE(m.head);
        StageSimFaults faults;
        c.set(faults);
        m.sim->setFaults(faults);
        auto at = m.head->position();
        ASSERT_FALSE(at) << c.name;
        EXPECT_EQ(faultOf(at), c.fault) << c.name << ": " << messageOf(at);
        if (!c.fault) {
            EXPECT_EQ(at.error().code, ErrorCode::IoError) << c.name;
        }
        EXPECT_NE(messageOf(at).find(c.says), std::string::npos) << c.name << ": " << messageOf(at);
        EXPECT_NE(messageOf(at).find(m.sim->slavePath()), std::string::npos) << c.name;
        // The same faults during a move: the move fails as clearly, and the motor is stopped.
        auto move = m.head->moveTo(5.0, 2.0);
        ASSERT_FALSE(move) << c.name;
        EXPECT_EQ(faultOf(move), c.fault) << c.name << ": " << messageOf(move);
    }
}

TEST(AptHead, ADeviceThatVanishesMidMoveIsDisconnected) {
    Mount m = mount(slowMount());
    ASSERT_TRUE(m.head);
    StageSimFaults faults;
    faults.vanish_after_s = 0.05;
    m.sim->setFaults(faults);
    auto at = m.head->moveTo(45.0, 5.0);
    EXPECT_EQ(faultOf(at), DeviceFault::Disconnected) << messageOf(at);
    EXPECT_EQ(faultOf(m.head->position()), DeviceFault::Disconnected);
}

TEST(AptHead, AStallIsStalled) {
    Mount m = mount(fastMount());
    ASSERT_TRUE(m.head);
    StageSimFaults faults;
    faults.stall_at = std::llround(10.0 * kCounts);
    m.sim->setFaults(faults);
    auto at = m.head->moveTo(20.0, 2.0);
    EXPECT_EQ(faultOf(at), DeviceFault::Stalled) << messageOf(at);
    EXPECT_NE(messageOf(at).find("motion error"), std::string::npos);
    EXPECT_EQ(m.sim->position(), std::llround(10.0 * kCounts));
    // Masked by the URI, the same bit is no fault: the move ends short, still [stalled].
    m.head.reset();
    auto masked = openHead(*m.sim, "&ignore_status_bits=16384");
    ASSERT_TRUE(masked) << messageOf(masked);
    ASSERT_TRUE((*masked)->moveTo(5.0, 2.0));
    auto short_move = (*masked)->moveTo(15.0, 2.0);
    EXPECT_EQ(faultOf(short_move), DeviceFault::Stalled) << messageOf(short_move);
}

TEST(AptHead, AControllerFaultReportFailsTheMoveWithItsCode) {
    Mount m = mount(fastMount());
    ASSERT_TRUE(m.head);
    StageSimFaults faults;
    faults.fault_code = 42;
    m.sim->setFaults(faults);
    auto at = m.head->moveTo(5.0, 2.0);
    ASSERT_FALSE(at);
    EXPECT_EQ(at.error().code, ErrorCode::IoError);
    EXPECT_NE(at.error().message.find("fault code 42"), std::string::npos) << messageOf(at);
    EXPECT_NE(at.error().message.find("MGMSG_MOT_MOVE_ABSOLUTE"), std::string::npos);
    EXPECT_NE(at.error().message.find("simulated controller fault"), std::string::npos);
}

TEST(AptHead, AnotherControllerNeedsItsScaleFactors) {
    AptSimOptions options = fastMount();
    options.model = "KDC101";
    auto sim = AptSim::start(options);
    ASSERT_TRUE(sim);
    auto refused = openHead(**sim);
    ASSERT_FALSE(refused);
    EXPECT_EQ(refused.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(refused.error().message.find("KDC101"), std::string::npos);
    auto scaled = openHead(**sim,
                           "&counts_per_deg=1919.64&vel_per_deg_s=42941.66"
                           "&acc_per_deg_s2=14.66");
    ASSERT_TRUE(scaled) << messageOf(scaled);
    EXPECT_DOUBLE_EQ((*scaled)->countsPerDeg(), 1919.64);
    auto channel = openHead(**sim, "&channel=2&counts_per_deg=1&vel_per_deg_s=1&acc_per_deg_s2=1");
    ASSERT_FALSE(channel);
    EXPECT_EQ(channel.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(channel.error().message.find("1 channel"), std::string::npos);
}

TEST(AptHead, NoControllerOnTheLineTimesOutAtOpen) {
    AptSimOptions options = fastMount();
    options.faults.drop_replies = 1000;
    auto sim = AptSim::start(options);
    ASSERT_TRUE(sim);
    auto head = openHead(**sim);
    EXPECT_EQ(faultOf(head), DeviceFault::Timeout) << messageOf(head);
    EXPECT_NE(messageOf(head).find("MGMSG_HW_REQ_INFO"), std::string::npos);
}

TEST(AptHead, OpensThroughTheRigRegistry) {
    auto sim = AptSim::start(fastMount());
    ASSERT_TRUE(sim);
    auto registries = makeRigRegistries(RigOptions{});
    ASSERT_TRUE(registries) << messageOf(registries);
    auto head = registries->heads.open(uriOf(**sim));
    ASSERT_TRUE(head) << messageOf(head);
    EXPECT_EQ((*head)->identity().backend, "apt");
    ASSERT_TRUE((*head)->home(5.0));
    EXPECT_TRUE((*head)->moveTo(1.0, 2.0));
    auto bad = registries->heads.open("apt:" + (*sim)->slavePath() + "?chanel=1");
    ASSERT_FALSE(bad);
    EXPECT_NE(bad.error().message.find("'chanel'"), std::string::npos);
}

}  // namespace
}  // namespace flarelab::drivers
