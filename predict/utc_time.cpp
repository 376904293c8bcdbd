#include "predict/utc_time.h"

#include <cstdint>
#include <cstdio>
#include <cstdlib>

namespace flarelab::predict {
namespace {

using std::chrono::days;
using std::chrono::hours;
using std::chrono::microseconds;
using std::chrono::minutes;
using std::chrono::seconds;

// Longer than any valid form ("+002003-10-17T12:30:30.123456789+05:30" is 38 characters); what
// is longer is refused before it is read.
constexpr size_t kMaxLength = 64;

// A cursor over the text; each read names the field it reads, for the error.
class Reader {
public:
    explicit Reader(std::string_view text) : text_(text) {}

    bool atEnd() const { return pos_ == text_.size(); }
    char peek() const { return atEnd() ? '\0' : text_[pos_]; }
    size_t position() const { return pos_; }

    bool accept(char c) {
        if (peek() != c) return false;
        ++pos_;
        return true;
    }
    // Exactly `count` digits.
    bool digits(int count, int& value) {
        value = 0;
        for (int i = 0; i < count; ++i) {
            const char c = peek();
            if (c < '0' || c > '9') return false;
            value = value * 10 + (c - '0');
            ++pos_;
        }
        return true;
    }
    // As many digits as there are, up to `most`; how many were read.
    int someDigits(int most, int64_t& value) {
        value = 0;
        int n = 0;
        while (n < most && peek() >= '0' && peek() <= '9') {
            value = value * 10 + (peek() - '0');
            ++pos_;
            ++n;
        }
        return n;
    }

private:
    std::string_view text_;
    size_t pos_ = 0;
};

Error parseError(std::string_view text, const std::string& what) {
    return makeError(ErrorCode::ParseError, "time \"" + std::string(text) + "\": " + what +
                                                " (expected ISO 8601 such as "
                                                "2003-10-17T12:30:30-07:00 or ...Z)");
}

std::string describe(const char* field, size_t position) {
    return std::string(field) + " at character " + std::to_string(position + 1);
}

}  // namespace

Result<UtcInstant> parseIso8601(std::string_view text) {
    if (text.empty()) return parseError(text, "empty");
    if (text.size() > kMaxLength)
        return makeError(ErrorCode::ParseError, "time: " + std::to_string(text.size()) +
                                                    " characters, longer than any ISO 8601 "
                                                    "date and time (at most " +
                                                    std::to_string(kMaxLength) + ")");
    Reader in(text);

    // Date: YYYY, or the expanded ±YYYY to ±YYYYYY.
    int year = 0;
    if (in.peek() == '+' || in.peek() == '-') {
        const bool negative = in.peek() == '-';
        in.accept(in.peek());
        int64_t value = 0;
        const int n = in.someDigits(6, value);
        if (n < 4) return parseError(text, "expected 4 to 6 digits of a signed (expanded) year");
        year = static_cast<int>(negative ? -value : value);
    } else if (!in.digits(4, year)) {
        return parseError(text, "expected a 4-digit year (or a sign and 4 to 6 digits)");
    }
    if (year < -32767 || year > 32767)
        return parseError(text, "year " + std::to_string(year) + " is beyond +-32767");
    int month = 0, day = 0;
    if (!in.accept('-')) return parseError(text, "expected '-' after the year");
    if (!in.digits(2, month)) return parseError(text, "expected a 2-digit month");
    if (month < 1 || month > 12)
        return parseError(text, "month " + std::to_string(month) + " is not 01..12");
    if (!in.accept('-')) return parseError(text, "expected '-' after the month");
    if (!in.digits(2, day)) return parseError(text, "expected a 2-digit day");
    const std::chrono::year_month_day date{std::chrono::year{year},
                                           std::chrono::month{static_cast<unsigned>(month)},
                                           std::chrono::day{static_cast<unsigned>(day)}};
    if (!date.ok()) return parseError(text, "day " + std::to_string(day) + " is not in that month");

    // Time: Thh:mm:ss[.f]
    if (!in.accept('T'))
        return parseError(text, "expected 'T' between the date and the time, " +
                                    describe("found", in.position()));
    int hour = 0, minute = 0, second = 0;
    if (!in.digits(2, hour)) return parseError(text, "expected a 2-digit hour");
    if (hour > 23) return parseError(text, "hour " + std::to_string(hour) + " is not 00..23");
    if (!in.accept(':')) return parseError(text, "expected ':' after the hour");
    if (!in.digits(2, minute)) return parseError(text, "expected 2-digit minutes");
    if (minute > 59) return parseError(text, "minute " + std::to_string(minute) + " is not 00..59");
    if (!in.accept(':')) return parseError(text, "expected ':' after the minutes (hh:mm:ss)");
    if (!in.digits(2, second)) return parseError(text, "expected 2-digit seconds");
    if (second > 60) return parseError(text, "second " + std::to_string(second) + " is not 00..60");
    int64_t fraction_us = 0;
    if (in.accept('.') || in.accept(',')) {
        int64_t value = 0;
        const int n = in.someDigits(9, value);
        if (n == 0) return parseError(text, "expected digits after the decimal sign");
        if (in.peek() >= '0' && in.peek() <= '9')
            return parseError(text, "more than 9 digits of a second");
        // Truncated to the microsecond.
        for (int i = n; i < 6; ++i) value *= 10;
        for (int i = 6; i < n; ++i) value /= 10;
        fraction_us = value;
    }

    // Offset: Z or ±hh:mm.
    int offset_minutes = 0;
    if (in.accept('Z')) {
    } else if (in.peek() == '+' || in.peek() == '-') {
        const int sign = in.peek() == '-' ? -1 : 1;
        in.accept(in.peek());
        int oh = 0, om = 0;
        if (!in.digits(2, oh) || !in.accept(':') || !in.digits(2, om))
            return parseError(text, "expected the UTC offset as ±hh:mm");
        if (oh > 23 || om > 59) return parseError(text, "UTC offset beyond ±23:59");
        offset_minutes = sign * (oh * 60 + om);
    } else if (in.atEnd()) {
        return parseError(text, "no UTC offset: add Z or ±hh:mm (a local time is ambiguous)");
    } else {
        return parseError(text,
                          "expected Z or a UTC offset ±hh:mm, " + describe("found", in.position()));
    }
    if (!in.atEnd()) return parseError(text, "unexpected text " + describe("from", in.position()));

    const int kept_second = second == 60 ? 59 : second;
    UtcInstant instant = std::chrono::sys_days{date} + hours{hour} + minutes{minute} +
                         seconds{kept_second} + microseconds{fraction_us} - minutes{offset_minutes};
    if (second == 60) {
        // A leap second is inserted after 23:59:59 UTC, whatever the local offset.
        const auto time_of_day = instant - std::chrono::floor<days>(instant);
        if (time_of_day < hours{23} + minutes{59} + seconds{59})
            return parseError(text, "second 60 (a leap second) only at 23:59:60 UTC");
        instant += seconds{1};
    }
    return instant;
}

std::string formatIso8601(UtcInstant instant) {
    const auto day = std::chrono::floor<days>(instant);
    const std::chrono::year_month_day date{day};
    const std::chrono::hh_mm_ss<microseconds> time{instant - day};
    const int year = static_cast<int>(date.year());
    char buffer[64];
    const char* year_format = year >= 0 && year <= 9999 ? "%04d" : "%+07d";
    int n = std::snprintf(buffer, sizeof buffer, year_format, year);
    n += std::snprintf(buffer + n, sizeof buffer - n, "-%02u-%02uT%02d:%02d:%02d",
                       static_cast<unsigned>(date.month()), static_cast<unsigned>(date.day()),
                       static_cast<int>(time.hours().count()),
                       static_cast<int>(time.minutes().count()),
                       static_cast<int>(time.seconds().count()));
    if (time.subseconds().count() != 0)
        n += std::snprintf(buffer + n, sizeof buffer - n, ".%06lld",
                           static_cast<long long>(time.subseconds().count()));
    std::snprintf(buffer + n, sizeof buffer - n, "Z");
    return buffer;
}

double daysSinceJ2000(UtcInstant instant) {
    // JD 2451545.0 = 2000-01-01T12:00:00 UTC; counted from there in exact integers first.
    constexpr auto kJ2000 = std::chrono::sys_days{std::chrono::year{2000} / 1 / 1} + hours{12};
    const int64_t us = (instant - kJ2000).count();
    const int64_t whole_days = us / 86'400'000'000LL;
    const int64_t rest_us = us % 86'400'000'000LL;
    return static_cast<double>(whole_days) + static_cast<double>(rest_us) / 86400e6;
}

double julianDay(UtcInstant instant) { return 2451545.0 + daysSinceJ2000(instant); }

int calendarYear(UtcInstant instant) {
    const std::chrono::year_month_day date{std::chrono::floor<days>(instant)};
    return static_cast<int>(date.year());
}

}  // namespace flarelab::predict
