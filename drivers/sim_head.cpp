#include "drivers/sim_head.h"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "common/check.h"

namespace flarelab::drivers {
namespace {

std::string fmt(double x) {
    std::ostringstream out;
    out << x;
    return out.str();
}

bool finite(double x) { return std::isfinite(x); }

Error badOption(const std::string& what) {
    return makeError(ErrorCode::InvalidArgument, "sim head options: " + what);
}

// A move stalled by an obstacle stops this far before it, so that the next move towards the
// obstacle stalls again instead of starting on top of it.
constexpr double kStallGap_deg = 1e-3;
// A move that loses steps covers only this share of its way (and the head notices).
constexpr double kLostStepsShare = 0.7;

}  // namespace

Status SimHeadOptions::validate() const {
    if (!finite(min_deg) || !finite(max_deg) || !(min_deg < max_deg))
        return badOption("min_deg < max_deg, both finite, is required (" + fmt(min_deg) + ", " +
                         fmt(max_deg) + ")");
    if (!finite(max_speed_deg_s) || !(max_speed_deg_s > 0.0))
        return badOption("max_speed_deg_s must be positive");
    if (!finite(speed_deg_s) || !(speed_deg_s > 0.0) || speed_deg_s > max_speed_deg_s)
        return badOption("speed_deg_s = " + fmt(speed_deg_s) + " must lie in (0, max_speed_deg_s]");
    if (!finite(acceleration_deg_s2) || acceleration_deg_s2 < 0.0)
        return badOption("acceleration_deg_s2 must be >= 0");
    if (!finite(settle_s) || settle_s < 0.0) return badOption("settle_s must be >= 0");
    if (!finite(backlash_deg) || backlash_deg < 0.0) return badOption("backlash_deg must be >= 0");
    if (!finite(position_noise_deg) || position_noise_deg < 0.0)
        return badOption("position_noise_deg must be >= 0");
    if (!finite(start_deg) || start_deg < min_deg || start_deg > max_deg)
        return badOption("start_deg must lie in [min_deg, max_deg]");
    if (faults.stall_at_deg && !finite(*faults.stall_at_deg))
        return badOption("faults.stall_at_deg must be finite");
    if (faults.hang_moves < 0) return badOption("faults.hang_moves must be >= 0");
    if (faults.lose_position_in_moves < 0)
        return badOption("faults.lose_position_in_moves must be >= 0");
    return Ok{};
}

Result<std::unique_ptr<SimHead>> SimHead::make(const SimHeadOptions& options,
                                               std::shared_ptr<SimClock> clock) {
    if (Status ok = options.validate(); !ok) return ok.error();
    if (!clock) clock = std::make_shared<SimClock>(SimTime::Fast);
    return std::make_unique<SimHead>(options, std::move(clock));
}

SimHead::SimHead(const SimHeadOptions& options, std::shared_ptr<SimClock> clock)
    : options_(options),
      clock_(std::move(clock)),
      speed_deg_s_(options.speed_deg_s),
      reported_deg_(options.start_deg),
      true_deg_(options.start_deg),
      homed_(options.homed),
      faults_(options.faults),
      rng_(options.seed) {
    FLARELAB_CHECK(options.validate().has_value());
    FLARELAB_CHECK(clock_ != nullptr);
}

double SimHead::moveDuration_s(double distance_deg,
                               double speed_deg_s,
                               double acceleration_deg_s2) {
    FLARELAB_CHECK_GT(speed_deg_s, 0.0);
    if (!(distance_deg > 0.0)) return 0.0;
    const double v = speed_deg_s, a = acceleration_deg_s2;
    if (a <= 0.0) return distance_deg / v;
    if (distance_deg >= v * v / a) return distance_deg / v + v / a;  // trapezoid
    return 2.0 * std::sqrt(distance_deg / a);                        // triangle
}

double SimHead::moveDistance_deg(double t_s,
                                 double distance_deg,
                                 double speed_deg_s,
                                 double acceleration_deg_s2) {
    const double total = moveDuration_s(distance_deg, speed_deg_s, acceleration_deg_s2);
    if (!(t_s > 0.0)) return 0.0;
    if (t_s >= total) return distance_deg;
    const double v = speed_deg_s, a = acceleration_deg_s2;
    if (a <= 0.0) return v * t_s;
    // Ramp time: to full speed, or to the middle of a triangle.
    const double ramp = distance_deg >= v * v / a ? v / a : 0.5 * total;
    if (t_s <= ramp) return 0.5 * a * t_s * t_s;
    if (t_s >= total - ramp) {
        const double left = total - t_s;
        return distance_deg - 0.5 * a * left * left;
    }
    return 0.5 * a * ramp * ramp + v * (t_s - ramp);
}

std::pair<double, double> SimHead::along(const Motion& m, double elapsed_s) const {
    const double s =
        moveDistance_deg(elapsed_s, m.distance_deg, m.speed_deg_s, options_.acceleration_deg_s2);
    const double reported = m.from_deg + m.direction * s;
    // The camera follows the motor through the backlash dead band: it stays put until the motor
    // has taken up the slack, then trails by half the band.
    const double half = 0.5 * options_.backlash_deg;
    const double camera = std::clamp(m.true_from_deg, reported - half, reported + half);
    return {reported, camera};
}

std::string SimHead::name() const { return "sim head " + options_.serial; }

Error SimHead::disconnectedError() const {
    return deviceError(DeviceFault::Disconnected, name(), "not connected");
}

DeviceIdentity SimHead::identity() const {
    return DeviceIdentity{"sim", "flarelab SimHead", options_.serial, "sim:"};
}

HeadLimits SimHead::limits() const {
    return HeadLimits{options_.min_deg, options_.max_deg, options_.max_speed_deg_s};
}

double SimHead::speed_deg_s() const {
    std::lock_guard lock(mutex_);
    return speed_deg_s_;
}

Status SimHead::setSpeed(double speed_deg_s) {
    std::lock_guard lock(mutex_);
    if (faults_.disconnected) return disconnectedError();
    if (!finite(speed_deg_s) || !(speed_deg_s > 0.0) || speed_deg_s > options_.max_speed_deg_s)
        return deviceError(DeviceFault::OutOfRange, name(),
                           "speed_deg_s = " + fmt(speed_deg_s) + " outside (0, " +
                               fmt(options_.max_speed_deg_s) + "]");
    speed_deg_s_ = speed_deg_s;
    return Ok{};
}

bool SimHead::homed() const {
    std::lock_guard lock(mutex_);
    return homed_;
}

void SimHead::setFaults(const SimHeadFaults& faults) {
    std::lock_guard lock(mutex_);
    faults_ = faults;
}

double SimHead::lastMoveDuration_s() const {
    std::lock_guard lock(mutex_);
    return last_move_s_;
}

double SimHead::trueAngle_deg() const {
    std::lock_guard lock(mutex_);
    if (moving_) return along(*moving_, (clock_->now_ns() - moving_->start_ns) * 1e-9).second;
    return true_deg_;
}

Result<double> SimHead::position() {
    std::lock_guard lock(mutex_);
    if (faults_.disconnected) return disconnectedError();
    if (!homed_) return deviceError(DeviceFault::NotHomed, name(), "position unknown: home first");
    if (moving_) return along(*moving_, (clock_->now_ns() - moving_->start_ns) * 1e-9).first;
    return reported_deg_;
}

Status SimHead::stop() {
    std::lock_guard lock(mutex_);
    if (faults_.disconnected) return disconnectedError();
    if (moving_) stop_requested_ = true;
    return Ok{};
}

SimHead::Ran SimHead::run(std::unique_lock<std::mutex>& lock,
                          const Motion& m,
                          double duration_s,
                          double timeout_s) {
    const double allowed_s = std::min(duration_s, timeout_s);
    moving_ = m;
    stop_requested_ = false;
    lock.unlock();
    const bool completed = clock_->waitUntil(m.start_ns + secondsToNs(allowed_s), &stop_requested_);
    lock.lock();
    moving_.reset();
    Ran ran;
    ran.stopped = !completed;
    ran.elapsed_s =
        completed ? allowed_s : std::min(allowed_s, (clock_->now_ns() - m.start_ns) * 1e-9);
    ran.timed_out = completed && duration_s > timeout_s;
    std::tie(reported_deg_, true_deg_) = along(m, ran.elapsed_s);
    last_move_s_ = ran.elapsed_s;
    return ran;
}

Result<double> SimHead::moveTo(double angle_deg, double timeout_s) {
    std::unique_lock lock(mutex_);
    if (faults_.disconnected) return disconnectedError();
    if (!finite(angle_deg) || angle_deg < options_.min_deg || angle_deg > options_.max_deg)
        return deviceError(DeviceFault::OutOfRange, name(),
                           "angle_deg = " + fmt(angle_deg) + " outside the limits [" +
                               fmt(options_.min_deg) + ", " + fmt(options_.max_deg) + "]");
    if (!finite(timeout_s) || !(timeout_s > 0.0))
        return deviceError(DeviceFault::OutOfRange, name(), "timeout_s must be positive");
    if (moving_) return deviceError(DeviceFault::Busy, name(), "another move is running");
    if (!homed_) return deviceError(DeviceFault::NotHomed, name(), "cannot move: home first");
    const std::string what = "move to " + fmt(angle_deg) + " deg";
    if (faults_.hang_moves > 0) {
        --faults_.hang_moves;
        Motion still{clock_->now_ns(), reported_deg_, 0.0, 1.0, true_deg_, speed_deg_s_};
        run(lock, still, timeout_s + 1.0, timeout_s);
        return deviceError(DeviceFault::Timeout, name(),
                           what + " did not arrive within timeout_s = " + fmt(timeout_s));
    }

    Motion m;
    m.start_ns = clock_->now_ns();
    m.from_deg = reported_deg_;
    m.distance_deg = std::abs(angle_deg - reported_deg_);
    m.direction = angle_deg >= reported_deg_ ? 1.0 : -1.0;
    m.true_from_deg = true_deg_;
    m.speed_deg_s = speed_deg_s_;
    bool stalled = false;
    if (faults_.stall_at_deg) {
        const double to_obstacle = (*faults_.stall_at_deg - m.from_deg) * m.direction;
        if (to_obstacle > 0.0 && to_obstacle <= m.distance_deg + kStallGap_deg) {
            stalled = true;
            m.distance_deg = std::max(0.0, to_obstacle - kStallGap_deg);
        }
    }
    bool loses = false;
    if (faults_.lose_position_in_moves > 0) loses = --faults_.lose_position_in_moves == 0;

    const double motion_s =
        moveDuration_s(m.distance_deg, m.speed_deg_s, options_.acceleration_deg_s2);
    const Ran ran = run(lock, m, motion_s + options_.settle_s, timeout_s);
    if (ran.stopped)
        return deviceError(DeviceFault::Stopped, name(),
                           what + " stopped at " + fmt(reported_deg_) + " deg");
    if (ran.timed_out)
        return deviceError(DeviceFault::Timeout, name(),
                           what + " needs " + fmt(motion_s + options_.settle_s) +
                               " s, more than timeout_s = " + fmt(timeout_s) + "; stopped at " +
                               fmt(reported_deg_) + " deg");
    if (m.distance_deg > 0.0 && options_.position_noise_deg > 0.0)
        true_deg_ += std::normal_distribution<double>(0.0, options_.position_noise_deg)(rng_);
    if (stalled)
        return deviceError(DeviceFault::Stalled, name(),
                           what + " stalled at " + fmt(reported_deg_) + " deg");
    if (loses) {
        true_deg_ = m.true_from_deg + kLostStepsShare * (true_deg_ - m.true_from_deg);
        homed_ = false;
        return deviceError(DeviceFault::LostPosition, name(),
                           what + " lost steps; home before the next move");
    }
    return reported_deg_;
}

Status SimHead::home(double timeout_s) {
    std::unique_lock lock(mutex_);
    if (faults_.disconnected) return disconnectedError();
    if (!finite(timeout_s) || !(timeout_s > 0.0))
        return deviceError(DeviceFault::OutOfRange, name(), "timeout_s must be positive");
    if (moving_) return deviceError(DeviceFault::Busy, name(), "another move is running");
    homed_ = false;
    // The home switch is at true angle 0; the drive runs on its own sense of position, so for
    // the way there both angles are the true one, and backlash is taken up on arrival.
    Motion m;
    m.start_ns = clock_->now_ns();
    m.from_deg = true_deg_;
    m.true_from_deg = true_deg_;
    m.distance_deg = std::abs(true_deg_);
    m.direction = true_deg_ > 0.0 ? -1.0 : 1.0;
    m.speed_deg_s = speed_deg_s_;
    double duration_s =
        moveDuration_s(m.distance_deg, m.speed_deg_s, options_.acceleration_deg_s2) +
        options_.settle_s;
    if (faults_.hang_moves > 0) {
        --faults_.hang_moves;
        m.distance_deg = 0.0;
        duration_s = timeout_s + 1.0;
    }
    const Ran ran = run(lock, m, duration_s, timeout_s);
    if (ran.stopped) return deviceError(DeviceFault::Stopped, name(), "homing stopped");
    if (ran.timed_out)
        return deviceError(DeviceFault::Timeout, name(),
                           "homing did not finish within timeout_s = " + fmt(timeout_s));
    reported_deg_ = 0.0;
    true_deg_ = 0.0;
    homed_ = true;
    return Ok{};
}

Status addSimHeadBackend(HeadRegistry& registry,
                         const SimHeadOptions& defaults,
                         std::shared_ptr<SimClock> clock) {
    auto open = [defaults, clock](const DeviceUri& uri) -> Result<std::unique_ptr<Head>> {
        if (Status ok = uri.onlyParams({"speed_deg_s", "acceleration_deg_s2", "settle_s",
                                        "backlash_deg", "position_noise_deg", "seed", "time"});
            !ok)
            return ok.error();
        SimHeadOptions options = defaults;
        for (auto [key, field] :
             {std::pair<const char*, double*>{"speed_deg_s", &options.speed_deg_s},
              {"acceleration_deg_s2", &options.acceleration_deg_s2},
              {"settle_s", &options.settle_s},
              {"backlash_deg", &options.backlash_deg},
              {"position_noise_deg", &options.position_noise_deg}}) {
            auto value = uri.number(key, *field);
            if (!value) return value.error();
            *field = *value;
        }
        auto seed = uri.number("seed", static_cast<double>(options.seed));
        if (!seed) return seed.error();
        if (*seed < 0.0 || *seed != std::floor(*seed) || *seed > 9.007199254740992e15)
            return makeError(ErrorCode::InvalidArgument,
                             "device uri '" + uri.text + "': seed must be a whole number >= 0");
        options.seed = static_cast<uint64_t>(*seed);
        std::shared_ptr<SimClock> chosen = clock;
        if (auto it = uri.params.find("time"); it != uri.params.end()) {
            if (it->second != "fast" && it->second != "real")
                return makeError(ErrorCode::InvalidArgument,
                                 "device uri '" + uri.text + "': time must be fast or real");
            chosen = std::make_shared<SimClock>(it->second == "fast" ? SimTime::Fast
                                                                     : SimTime::RealTime);
        }
        auto head = SimHead::make(options, chosen);
        if (!head) return head.error().withContext("device uri '" + uri.text + "'");
        return std::unique_ptr<Head>(std::move(*head));
    };
    const SimHeadOptions listed = defaults;
    return registry.addBackend("sim", "simulated panorama head", std::move(open), [listed] {
        DeviceListing d;
        d.uri = "sim:";
        d.kind = "head";
        d.backend = "sim";
        d.model = "flarelab simulated head";
        d.serial = listed.serial;
        std::ostringstream range;
        range << "range: " << listed.min_deg << " .. " << listed.max_deg << " deg";
        d.details = {range.str()};
        return std::vector<DeviceListing>{d};
    });
}

}  // namespace flarelab::drivers
