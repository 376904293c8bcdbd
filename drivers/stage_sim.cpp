#include "drivers/stage_sim.h"

#include <fcntl.h>
#include <poll.h>
#include <pty.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstring>

#include "drivers/sim_head.h"

namespace flarelab::drivers {
namespace {

std::optional<int64_t> integer(std::string_view s) {
    int64_t value = 0;
    const auto [ptr, ec] = std::from_chars(s.data(), s.data() + s.size(), value);
    if (ec != std::errc() || ptr != s.data() + s.size() || s.empty()) return std::nullopt;
    return value;
}

std::vector<std::string_view> words(std::string_view s) {
    std::vector<std::string_view> out;
    size_t i = 0;
    while (i < s.size()) {
        while (i < s.size() && s[i] == ' ') ++i;
        const size_t start = i;
        while (i < s.size() && s[i] != ' ') ++i;
        if (i > start) out.push_back(s.substr(start, i - start));
    }
    return out;
}

void put16(std::vector<uint8_t>& out, uint16_t v) {
    out.push_back(static_cast<uint8_t>(v & 0xFF));
    out.push_back(static_cast<uint8_t>(v >> 8));
}

void put32(std::vector<uint8_t>& out, uint32_t v) {
    for (int i = 0; i < 4; ++i) out.push_back(static_cast<uint8_t>((v >> (8 * i)) & 0xFF));
}

uint32_t le32(const std::vector<uint8_t>& b, size_t at) {
    return static_cast<uint32_t>(b[at]) | (static_cast<uint32_t>(b[at + 1]) << 8) |
           (static_cast<uint32_t>(b[at + 2]) << 16) | (static_cast<uint32_t>(b[at + 3]) << 24);
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// StageSim

StageSim::StageSim(uint64_t seed) : rng_(seed) {}

StageSim::~StageSim() {
    stopThread();
    closeMaster();
    if (slave_ >= 0) ::close(slave_);
}

Status StageSim::openLine(const std::string& tty) {
    if (!tty.empty()) {
        master_ = ::open(tty.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
        if (master_ < 0)
            return makeError(ErrorCode::IoError,
                             "stage simulator: " + tty + ": " + std::strerror(errno));
        termios tio{};
        if (::tcgetattr(master_, &tio) != 0) {
            const std::string why = std::strerror(errno);
            closeMaster();
            return makeError(ErrorCode::IoError,
                             "stage simulator: " + tty + " is not a terminal: " + why);
        }
        ::cfmakeraw(&tio);
        ::tcsetattr(master_, TCSANOW, &tio);
        return Ok{};
    }
    char name[256] = {};
    if (::openpty(&master_, &slave_, name, nullptr, nullptr) != 0)
        return makeError(ErrorCode::IoError,
                         std::string("stage simulator: openpty: ") + std::strerror(errno));
    slave_path_ = name;
    ::fcntl(master_, F_SETFL, ::fcntl(master_, F_GETFL) | O_NONBLOCK);
    ::fcntl(master_, F_SETFD, FD_CLOEXEC);
    ::fcntl(slave_, F_SETFD, FD_CLOEXEC);
    // Raw from the start, so that whoever opens the slave sees the bytes as sent.
    termios tio{};
    if (::tcgetattr(slave_, &tio) == 0) {
        ::cfmakeraw(&tio);
        ::tcsetattr(slave_, TCSANOW, &tio);
    }
    return Ok{};
}

void StageSim::startThread() {
    thread_ = std::jthread([this](std::stop_token stop) { serve(stop); });
}

void StageSim::stopThread() {
    if (thread_.joinable()) {
        thread_.request_stop();
        thread_.join();
    }
}

void StageSim::closeMaster() {
    if (master_ >= 0) {
        ::close(master_);
        master_ = -1;
    }
}

void StageSim::serve(std::stop_token stop) {
    std::vector<uint8_t> buffer(4096);
    while (!stop.stop_requested()) {
        int master = -1;
        {
            std::lock_guard lock(mutex_);
            const auto now = Clock::now();
            if (vanish_at_ && now >= *vanish_at_) {
                vanish_at_.reset();
                vanished_ = true;
                closeMaster();
            }
            if (vanished_) break;
            if (motion_) {
                const double elapsed = std::chrono::duration<double>(now - motion_->start).count();
                const double total = SimHead::moveDuration_s(
                    static_cast<double>(std::llabs(motion_->to - motion_->from)), motion_->speed,
                    motion_->accel);
                if (elapsed >= total) {
                    const Motion ended = *motion_;
                    motion_.reset();
                    position_ = ended.to;
                    onMotionEnd(ended, now);
                }
            }
            onTick(now);
            master = master_;
        }
        pollfd p{master, POLLIN, 0};
        const int r = ::poll(&p, 1, 2);
        if (r <= 0) continue;
        if (p.revents & POLLIN) {
            const ssize_t n = ::read(master, buffer.data(), buffer.size());
            if (n > 0) {
                std::lock_guard lock(mutex_);
                if (!vanished_)
                    onBytes(std::span<const uint8_t>(buffer.data(), static_cast<size_t>(n)),
                            Clock::now());
            }
        } else if (p.revents & (POLLHUP | POLLERR)) {
            // Nobody holds the slave (we do, so this is transient): do not spin.
            std::this_thread::sleep_for(std::chrono::milliseconds(2));
        }
    }
}

void StageSim::setFaults(const StageSimFaults& faults) {
    std::lock_guard lock(mutex_);
    faults_ = faults;
}

StageSimFaults StageSim::faults() const {
    std::lock_guard lock(mutex_);
    return faults_;
}

void StageSim::vanish() {
    std::lock_guard lock(mutex_);
    vanished_ = true;
    closeMaster();
}

bool StageSim::vanished() const {
    std::lock_guard lock(mutex_);
    return vanished_;
}

int64_t StageSim::position() const {
    std::lock_guard lock(mutex_);
    return positionAt(Clock::now());
}

bool StageSim::moving() const {
    std::lock_guard lock(mutex_);
    return motion_.has_value();
}

bool StageSim::homed() const {
    std::lock_guard lock(mutex_);
    return homed_;
}

size_t StageSim::requests() const {
    std::lock_guard lock(mutex_);
    return requests_;
}

void StageSim::write(std::span<const uint8_t> bytes) {
    if (master_ < 0) return;
    size_t done = 0;
    while (done < bytes.size()) {
        const ssize_t n = ::write(master_, bytes.data() + done, bytes.size() - done);
        if (n > 0) {
            done += static_cast<size_t>(n);
        } else if (n < 0 && errno == EINTR) {
            continue;
        } else {
            return;  // the buffer is full because nobody reads: drop, like a line would
        }
    }
}

void StageSim::write(std::string_view text) {
    write(std::span<const uint8_t>(reinterpret_cast<const uint8_t*>(text.data()), text.size()));
}

int64_t StageSim::positionAt(Clock::time_point now) const {
    if (!motion_) return position_;
    const double elapsed = std::chrono::duration<double>(now - motion_->start).count();
    const double distance = static_cast<double>(std::llabs(motion_->to - motion_->from));
    const double covered =
        SimHead::moveDistance_deg(elapsed, distance, motion_->speed, motion_->accel);
    const int64_t step = std::llround(covered);
    return motion_->to >= motion_->from ? motion_->from + step : motion_->from - step;
}

void StageSim::startMotion(
    int64_t to, double speed, double accel, bool homing, Clock::time_point now) {
    const int64_t from = positionAt(now);
    Motion m;
    m.from = from;
    m.to = to;
    m.speed = std::max(speed, 1e-9);
    m.accel = std::max(accel, 0.0);
    m.start = now;
    m.homing = homing;
    if (faults_.stall_at) {
        const int64_t obstacle = *faults_.stall_at;
        const bool crosses = (to >= from) ? (obstacle > from && obstacle <= to)
                                          : (obstacle < from && obstacle >= to);
        if (crosses) {
            m.to = obstacle;
            m.stalls = true;
        }
    }
    position_ = from;
    motion_ = m;
    if (faults_.vanish_after_s) {
        vanish_at_ = now + std::chrono::duration_cast<Clock::duration>(
                               std::chrono::duration<double>(*faults_.vanish_after_s));
        faults_.vanish_after_s.reset();
    }
}

std::optional<StageSim::Motion> StageSim::halt(Clock::time_point now) {
    if (!motion_) return std::nullopt;
    position_ = positionAt(now);
    const Motion was = *motion_;
    motion_.reset();
    return was;
}

bool StageSim::take(int& counter) {
    if (counter <= 0) return false;
    --counter;
    return true;
}

void StageSim::garble(std::vector<uint8_t>& bytes, bool non_ascii) {
    if (bytes.size() < 4) return;
    std::uniform_int_distribution<size_t> where(1, bytes.size() - 3);
    std::uniform_int_distribution<int> value(non_ascii ? 0x80 : 0x00, 0xFF);
    for (int i = 0; i < 3; ++i) bytes[where(rng_)] = static_cast<uint8_t>(value(rng_));
}

// ---------------------------------------------------------------------------------------------
// ZaberSim

ZaberSim::ZaberSim(Key, const ZaberSimOptions& options)
    : StageSim(options.seed),
      options_(options),
      maxspeed_(options.maxspeed),
      checksums_(options.checksums) {
    faults_ = options.faults;
    position_ = options.start_position;
    homed_ = options.homed;
}

Result<std::unique_ptr<ZaberSim>> ZaberSim::start(const ZaberSimOptions& options) {
    if (options.device < 1 || options.device > 99 || options.axes < 1 || options.axes > 9 ||
        !(options.limit_min < options.limit_max) || options.maxspeed < 1 ||
        options.max_maxspeed < options.maxspeed || options.resolution < 1 ||
        !(options.accel_steps_s2 >= 0.0))
        return makeError(ErrorCode::InvalidArgument, "zaber simulator: options out of range");
    auto sim = std::make_unique<ZaberSim>(Key{}, options);
    if (Status ok = sim->openLine(options.serve_tty); !ok) return ok.error();
    sim->startThread();
    return sim;
}

ZaberSim::~ZaberSim() { stopThread(); }

double ZaberSim::speed() const {
    return static_cast<double>(maxspeed_) / kZaberSpeedUnitsPerStepPerS;
}

std::vector<std::string> ZaberSim::flags() const {
    std::lock_guard lock(mutex_);
    std::vector<std::string> out(flags_.begin(), flags_.end());
    if (!homed_) out.push_back("WR");
    std::sort(out.begin(), out.end(), [](const std::string& a, const std::string& b) {
        return zaberWarningRank(a) < zaberWarningRank(b);
    });
    return out;
}

int64_t ZaberSim::maxspeed() const {
    std::lock_guard lock(mutex_);
    return maxspeed_;
}

std::string ZaberSim::topFlag() const {
    std::string top = "--";
    int rank = 1 << 20;
    const auto consider = [&](const std::string& f) {
        if (zaberWarningRank(f) < rank) {
            rank = zaberWarningRank(f);
            top = f;
        }
    };
    for (const std::string& f : flags_) consider(f);
    if (!homed_) consider("WR");
    return top;
}

void ZaberSim::onBytes(std::span<const uint8_t> bytes, Clock::time_point now) {
    for (const uint8_t b : bytes) {
        if (b == '\n' || b == '\r') {
            if (!line_.empty()) handle(line_, now);
            line_.clear();
        } else if (line_.size() < 1024) {
            line_ += static_cast<char>(b);
        }
    }
}

void ZaberSim::onMotionEnd(const Motion& motion, Clock::time_point) {
    if (motion.stalls) flags_.insert("FS");
    if (motion.homing && !motion.stalls) {
        homed_ = true;
        position_ = 0;
    }
    if (!faults_.flag_after_move.empty()) {
        if (faults_.flag_after_move == "WR")
            homed_ = false;
        else
            flags_.insert(faults_.flag_after_move);
        faults_.flag_after_move.clear();
    }
}

void ZaberSim::reply(ZaberReply r) {
    if (take(faults_.drop_replies)) return;
    if (take(faults_.wrong_address_replies)) r.device = r.device % 99 + 1;
    if (take(faults_.wrong_id_replies)) r.message_id = r.message_id ? (*r.message_id + 1) % 100 : 1;
    std::string text = formatZaberReply(r);
    if (take(faults_.bad_checksum_replies)) {
        // The checksum of a different message: off by one.
        r.has_checksum = false;
        std::string plain = formatZaberReply(r);
        plain.resize(plain.size() - 2);
        const std::string body = plain.substr(1);
        char sum[8];
        std::snprintf(sum, sizeof(sum), ":%02X",
                      static_cast<unsigned>((zaberChecksum(body) + 1) & 0xFF));
        text = plain + sum + "\r\n";
    }
    std::vector<uint8_t> bytes(text.begin(), text.end());
    if (take(faults_.truncate_replies)) bytes.resize(bytes.size() / 2);
    if (take(faults_.garble_replies)) garble(bytes, true);
    write(bytes);
}

void ZaberSim::handle(std::string_view line, Clock::time_point now) {
    ++requests_;
    auto parsed = parseZaberCommand(line);
    // A device discards what it cannot read; so does the simulator (the driver times out).
    if (!parsed) return;
    const ZaberCommand& c = *parsed;
    if (c.device != 0 && c.device != options_.device) return;

    ZaberReply r;
    r.device = options_.device;
    r.axis = c.axis;
    r.message_id = c.message_id;
    r.has_checksum = checksums_;
    const auto finish = [&](bool rejected, std::string data) {
        r.rejected = rejected;
        r.busy = motion_.has_value();
        r.warning = topFlag();
        r.data = std::move(data);
        reply(r);
    };
    const auto reject = [&](const char* reason) { finish(true, reason); };
    if (c.axis > options_.axes) return reject("BADAXIS");

    const std::vector<std::string_view> w = words(c.text);
    const auto is = [&](std::initializer_list<std::string_view> expected) {
        if (w.size() != expected.size()) return false;
        size_t i = 0;
        for (std::string_view e : expected)
            if (w[i++] != e) return false;
        return true;
    };
    if (w.empty()) return finish(false, "0");
    if (w[0] == "get" && w.size() == 2) {
        const std::string_view s = w[1];
        if (s == "pos") return finish(false, std::to_string(positionAt(now)));
        if (s == "maxspeed") return finish(false, std::to_string(maxspeed_));
        if (s == "limit.min") return finish(false, std::to_string(options_.limit_min));
        if (s == "limit.max") return finish(false, std::to_string(options_.limit_max));
        if (s == "resolution") return finish(false, std::to_string(options_.resolution));
        if (s == "deviceid") return finish(false, std::to_string(options_.device_id));
        if (s == "system.serial") return finish(false, options_.serial);
        if (s == "version") return finish(false, options_.version);
        if (s == "comm.checksum") return finish(false, checksums_ ? "1" : "0");
        return reject("BADCOMMAND");
    }
    if (w[0] == "set" && w.size() == 3) {
        const auto value = integer(w[2]);
        if (!value) return reject("BADDATA");
        if (w[1] == "maxspeed") {
            if (*value < 1 || *value > options_.max_maxspeed) return reject("BADDATA");
            maxspeed_ = *value;
            return finish(false, "0");
        }
        if (w[1] == "comm.checksum") {
            if (*value != 0 && *value != 1) return reject("BADDATA");
            checksums_ = *value == 1;
            r.has_checksum = checksums_;
            return finish(false, "0");
        }
        return reject("BADCOMMAND");
    }
    if (is({"warnings"}) || is({"warnings", "clear"})) {
        std::vector<std::string> standing(flags_.begin(), flags_.end());
        if (!homed_) standing.push_back("WR");
        std::sort(standing.begin(), standing.end(), [](const auto& a, const auto& b) {
            return zaberWarningRank(a) < zaberWarningRank(b);
        });
        char count[8];
        std::snprintf(count, sizeof(count), "%02zu", standing.size());
        std::string data = count;
        for (const std::string& f : standing) data += " " + f;
        finish(false, data);
        if (w.size() == 2) flags_.clear();  // WR is a condition, not a flag to clear
        return;
    }
    if (is({"stop"})) {
        if (halt(now)) flags_.insert("NI");
        return finish(false, "0");
    }
    if (is({"home"})) {
        if (motion_) flags_.insert("NI");
        homed_ = false;
        startMotion(0, speed(), options_.accel_steps_s2, true, now);
        return finish(false, "0");
    }
    if (w[0] == "move" && w.size() == 3 && (w[1] == "abs" || w[1] == "rel")) {
        const auto value = integer(w[2]);
        if (!value) return reject("BADDATA");
        if (!faults_.reject_moves.empty()) return finish(true, faults_.reject_moves);
        const int64_t target = w[1] == "abs" ? *value : positionAt(now) + *value;
        if (target < options_.limit_min || target > options_.limit_max) return reject("BADDATA");
        if (motion_) flags_.insert("NI");
        startMotion(target, speed(), options_.accel_steps_s2, false, now);
        return finish(false, "0");
    }
    reject("BADCOMMAND");
}

// ---------------------------------------------------------------------------------------------
// AptSim

AptSim::AptSim(Key, const AptSimOptions& options)
    : StageSim(options.seed),
      options_(options),
      enabled_(options.enabled),
      acceleration_(
          static_cast<int32_t>(std::llround(options.accel_deg_s2 * options.acc_per_deg_s2))),
      max_velocity_(
          static_cast<int32_t>(std::llround(options.speed_deg_s * options.vel_per_deg_s))) {
    faults_ = options.faults;
    position_ = options.start_position;
    homed_ = options.homed;
}

Result<std::unique_ptr<AptSim>> AptSim::start(const AptSimOptions& options) {
    if (options.channels < 1 || options.channels > 16 || options.model.size() > 8 ||
        !(options.counts_per_deg > 0.0) || !(options.vel_per_deg_s > 0.0) ||
        !(options.acc_per_deg_s2 > 0.0) || !(options.speed_deg_s > 0.0) ||
        !(options.accel_deg_s2 > 0.0) || options.speed_deg_s * options.vel_per_deg_s > 2.0e9)
        return makeError(ErrorCode::InvalidArgument, "apt simulator: options out of range");
    auto sim = std::make_unique<AptSim>(Key{}, options);
    if (Status ok = sim->openLine(options.serve_tty); !ok) return ok.error();
    sim->startThread();
    return sim;
}

AptSim::~AptSim() { stopThread(); }

double AptSim::countsPerS() const {
    return max_velocity_ / options_.vel_per_deg_s * options_.counts_per_deg;
}

double AptSim::countsPerS2() const {
    return acceleration_ / options_.acc_per_deg_s2 * options_.counts_per_deg;
}

uint32_t AptSim::bitsAt(Clock::time_point now) const {
    uint32_t bits = error_bits_;
    if (enabled_) bits |= apt::kEnabled;
    if (homed_) bits |= apt::kHomed;
    if (motion_) {
        if (motion_->homing) bits |= apt::kHoming;
        bits |= motion_->to >= motion_->from ? apt::kMovingForward : apt::kMovingReverse;
    }
    // The home switch of a rotation mount sits at count 0 and is read as the reverse limit.
    if (positionAt(now) == 0) bits |= apt::kReverseLimit;
    return bits;
}

uint32_t AptSim::statusBits() const {
    std::lock_guard lock(mutex_);
    return bitsAt(Clock::now());
}

bool AptSim::enabled() const {
    std::lock_guard lock(mutex_);
    return enabled_;
}

int32_t AptSim::maxVelocity() const {
    std::lock_guard lock(mutex_);
    return max_velocity_;
}

AptMessage AptSim::header(uint16_t id, uint8_t param1, uint8_t param2) const {
    AptMessage m;
    m.id = id;
    m.param1 = param1;
    m.param2 = param2;
    m.destination = apt::kHost;
    m.source = options_.address;
    return m;
}

AptMessage AptSim::status(uint16_t id, Clock::time_point now) const {
    AptMessage m = header(id);
    m.has_data = true;
    put16(m.data, 1);
    put32(m.data, static_cast<uint32_t>(static_cast<int32_t>(positionAt(now))));
    put32(m.data, 0);  // encoder count (a stepper has none) or velocity + reserved
    put32(m.data, bitsAt(now));
    return m;
}

void AptSim::onBytes(std::span<const uint8_t> bytes, Clock::time_point now) {
    rx_.insert(rx_.end(), bytes.begin(), bytes.end());
    for (;;) {
        const AptFraming f = findAptFrame(rx_);
        if (f.kind == AptFraming::Kind::NeedMore) break;
        if (f.kind == AptFraming::Kind::Message) {
            auto message = parseAptMessage(std::span<const uint8_t>(rx_.data(), f.length));
            if (message) handle(*message, now);
        }
        rx_.erase(rx_.begin(), rx_.begin() + static_cast<std::ptrdiff_t>(f.length));
    }
    if (rx_.size() > 4096) rx_.clear();
}

void AptSim::onMotionEnd(const Motion& motion, Clock::time_point now) {
    if (motion.stalls) {
        error_bits_ |= apt::kMotionError;
        announce(status(apt::kMotMoveStopped, now));
        return;
    }
    if (motion.homing) {
        homed_ = true;
        position_ = 0;
        if (!faults_.drop_announcements) announce(header(apt::kMotMoveHomed, 1));
        return;
    }
    if (!faults_.drop_announcements) announce(status(apt::kMotMoveCompleted, now));
}

void AptSim::onTick(Clock::time_point now) {
    if (faults_.unsolicited_status_s > 0.0 &&
        std::chrono::duration<double>(now - last_unsolicited_).count() >=
            faults_.unsolicited_status_s) {
        last_unsolicited_ = now;
        announce(status(apt::kMotGetStatusUpdate, now));
    }
}

void AptSim::announce(const AptMessage& message) { write(encodeAptMessage(message)); }

void AptSim::reply(AptMessage m) {
    if (take(faults_.drop_replies)) return;
    if (take(faults_.wrong_address_replies)) m.source = 0x21;
    if (take(faults_.wrong_id_replies)) {
        // Another message of the same shape, so that only its id gives it away.
        switch (m.id) {
            case apt::kMotGetPosCounter:
                m.id = apt::kMotGetStatusBits;
                break;
            case apt::kMotGetStatusBits:
                m.id = apt::kMotGetPosCounter;
                break;
            case apt::kMotGetVelParams:
                m.id = apt::kMotGetStatusUpdate;
                break;
            case apt::kModGetChanEnableState:
                m.id = apt::kMotMoveHomed;
                break;
            default:
                m.id = apt::kHwDisconnect;
                m.has_data = false;
                m.data.clear();
        }
    }
    if (take(faults_.wrong_channel_replies)) {
        if (m.has_data && m.data.size() >= 2 && m.id != apt::kHwGetInfo)
            m.data[0] = static_cast<uint8_t>(m.data[0] + 1);
        else
            m.param1 = static_cast<uint8_t>(m.param1 + 1);
    }
    std::vector<uint8_t> bytes = encodeAptMessage(m);
    if (take(faults_.truncate_replies)) bytes.resize(bytes.size() / 2);
    if (take(faults_.garble_replies)) {
        std::uniform_int_distribution<int> value(0, 255);
        for (uint8_t& b : bytes) b = static_cast<uint8_t>(value(rng_));
    }
    write(bytes);
}

void AptSim::handle(const AptMessage& m, Clock::time_point now) {
    ++requests_;
    if (m.destination != options_.address) return;
    const auto channel = [&]() -> int {
        return m.has_data && m.data.size() >= 2 ? (m.data[0] | (m.data[1] << 8)) : m.param1;
    };
    switch (m.id) {
        case apt::kHwReqInfo: {
            AptMessage info = header(apt::kHwGetInfo);
            info.has_data = true;
            put32(info.data, options_.serial);
            std::string model = options_.model;
            model.resize(8, '\0');
            info.data.insert(info.data.end(), model.begin(), model.end());
            put16(info.data, 45);    // hardware type
            info.data.push_back(3);  // firmware 1.0.3: minor, interim, major, unused
            info.data.push_back(0);
            info.data.push_back(1);
            info.data.push_back(0);
            std::string notes = "flarelab APT simulator";
            notes.resize(48, '\0');
            info.data.insert(info.data.end(), notes.begin(), notes.end());
            info.data.resize(info.data.size() + 12, 0);
            put16(info.data, 1);  // hardware version
            put16(info.data, 0);  // modification state
            put16(info.data, static_cast<uint16_t>(options_.channels));
            return reply(info);
        }
        case apt::kHwStartUpdateMsgs:
        case apt::kHwStopUpdateMsgs:
        case apt::kHwDisconnect:
            return;
        default:
            break;
    }
    if (channel() < 1 || channel() > options_.channels) return;  // a channel it does not have
    switch (m.id) {
        case apt::kModSetChanEnableState:
            enabled_ = m.param2 == 0x01;
            return;
        case apt::kModReqChanEnableState:
            return reply(header(apt::kModGetChanEnableState, m.param1, enabled_ ? 0x01 : 0x02));
        case apt::kMotReqPosCounter: {
            AptMessage r = header(apt::kMotGetPosCounter);
            r.has_data = true;
            put16(r.data, static_cast<uint16_t>(m.param1));
            put32(r.data, static_cast<uint32_t>(static_cast<int32_t>(positionAt(now))));
            return reply(r);
        }
        case apt::kMotReqStatusBits: {
            AptMessage r = header(apt::kMotGetStatusBits);
            r.has_data = true;
            put16(r.data, static_cast<uint16_t>(m.param1));
            put32(r.data, bitsAt(now));
            return reply(r);
        }
        case apt::kMotReqStatusUpdate:
            return reply(status(apt::kMotGetStatusUpdate, now));
        case apt::kMotReqVelParams: {
            AptMessage r = header(apt::kMotGetVelParams);
            r.has_data = true;
            put16(r.data, static_cast<uint16_t>(m.param1));
            put32(r.data, static_cast<uint32_t>(min_velocity_));
            put32(r.data, static_cast<uint32_t>(acceleration_));
            put32(r.data, static_cast<uint32_t>(max_velocity_));
            return reply(r);
        }
        case apt::kMotSetVelParams: {
            const auto accel = static_cast<int32_t>(le32(m.data, 6));
            const auto velocity = static_cast<int32_t>(le32(m.data, 10));
            if (accel > 0 && velocity > 0) {  // a controller ignores nonsense
                acceleration_ = accel;
                max_velocity_ = velocity;
                min_velocity_ = static_cast<int32_t>(le32(m.data, 2));
            }
            return;
        }
        case apt::kMotMoveHome:
            if (!enabled_) return;
            error_bits_ = 0;
            homed_ = false;
            startMotion(0, countsPerS(), countsPerS2(), true, now);
            return;
        case apt::kMotMoveAbsolute: {
            if (!enabled_) return;
            if (faults_.fault_code) {
                AptMessage r = header(apt::kHwRichResponse);
                r.has_data = true;
                put16(r.data, apt::kMotMoveAbsolute);
                put16(r.data, *faults_.fault_code);
                std::string notes = "simulated controller fault";
                notes.resize(64, '\0');
                r.data.insert(r.data.end(), notes.begin(), notes.end());
                faults_.fault_code.reset();
                return announce(r);
            }
            error_bits_ = 0;
            halt(now);
            startMotion(static_cast<int32_t>(le32(m.data, 2)), countsPerS(), countsPerS2(), false,
                        now);
            return;
        }
        case apt::kMotMoveStop:
            if (halt(now)) announce(status(apt::kMotMoveStopped, now));
            return;
        default:
            return;  // controllers ignore messages they do not serve
    }
}

}  // namespace flarelab::drivers
