// ============================================================================
//  flarelab predict: UtcInstant, parseIso8601, formatIso8601, julianDay
// ============================================================================
//
// Instants in UTC for the sun's position and timelines. An instant is a std::chrono::sys_time in
// microseconds: the proleptic Gregorian calendar with no leap seconds (as POSIX time), and a
// 64-bit count that spans ±292 000 years, far beyond the years the sun's position supports.
#pragma once

#include <chrono>
#include <string>
#include <string_view>

#include "common/result.h"

namespace flarelab::predict {

using UtcInstant = std::chrono::sys_time<std::chrono::microseconds>;

// Parses one ISO 8601 date and time with its UTC offset, the extended format only:
//   YYYY-MM-DDThh:mm:ss[.f]Z   or   YYYY-MM-DDThh:mm:ss[.f]±hh:mm
// e.g. "2003-10-17T12:30:30-07:00", "2024-06-21T00:00:00Z", "2024-06-21T05:30:00.25+05:30".
// The fraction (a '.' or ',' and 1 to 9 digits) is kept to the microsecond, truncated. A year
// outside 0000..9999 takes ISO 8601's expanded form, a sign and 4 to 6 digits ("-2000-06-21...",
// astronomical numbering: year 0 is 1 BC). "23:59:60" (a leap second) is read as the midnight
// that follows it: sys_time has no leap seconds, and the instant is then at most a second off.
// A time without an offset is refused (local time is ambiguous), as is anything else: lowercase
// 't' or 'z', a space for 'T', basic format, week or ordinal dates, 24:00, an offset beyond
// ±23:59, a day the month does not have. The error (ParseError) names the field at fault.
Result<UtcInstant> parseIso8601(std::string_view text);

// The instant as "YYYY-MM-DDThh:mm:ss[.ffffff]Z" (the fraction only where it is not zero), in
// the expanded form for years outside 0000..9999; parseIso8601 reads it back exactly.
std::string formatIso8601(UtcInstant instant);

// The Julian date of the instant on the UTC time scale (JD 2451545.0 is 2000-01-01T12:00:00Z).
double julianDay(UtcInstant instant);
// The same less 2451545, in days: what astronomical series take, without the rounding of a
// seven-digit Julian date (a double of it resolves 40 microseconds; this one, at year 6000, 20).
double daysSinceJ2000(UtcInstant instant);

// The (proleptic Gregorian) calendar year of the instant.
int calendarYear(UtcInstant instant);

}  // namespace flarelab::predict
