// ============================================================================
//  flarelab common: FLARELAB_CHECK, FLARELAB_DCHECK
// ============================================================================
//
// Broken invariants are bugs, not input errors: they abort with the file, line, the failed
// expression and, for the comparison forms, both values. FLARELAB_DCHECK* compile away in
// release builds and belong in hot loops.
#pragma once

#include <cstdio>
#include <cstdlib>
#include <sstream>
#include <string>

namespace flarelab::detail {

[[noreturn]] inline void checkFailed(const char* file, int line, const std::string& what) {
    std::fprintf(stderr, "%s:%d: check failed: %s\n", file, line, what.c_str());
    std::fflush(stderr);
    std::abort();
}

template <typename A, typename B>
std::string describeComparison(const char* expr, const A& a, const B& b) {
    std::ostringstream out;
    out << expr << " (" << a << " vs " << b << ")";
    return out.str();
}

}  // namespace flarelab::detail

#define FLARELAB_CHECK(cond)                                                     \
    do {                                                                         \
        if (!(cond)) ::flarelab::detail::checkFailed(__FILE__, __LINE__, #cond); \
    } while (false)

#define FLARELAB_CHECK_OP(a, op, b)                                                            \
    do {                                                                                       \
        const auto& flarelab_a_ = (a);                                                         \
        const auto& flarelab_b_ = (b);                                                         \
        if (!(flarelab_a_ op flarelab_b_))                                                     \
            ::flarelab::detail::checkFailed(__FILE__, __LINE__,                                \
                                            ::flarelab::detail::describeComparison(            \
                                                #a " " #op " " #b, flarelab_a_, flarelab_b_)); \
    } while (false)

#define FLARELAB_CHECK_EQ(a, b) FLARELAB_CHECK_OP(a, ==, b)
#define FLARELAB_CHECK_NE(a, b) FLARELAB_CHECK_OP(a, !=, b)
#define FLARELAB_CHECK_LT(a, b) FLARELAB_CHECK_OP(a, <, b)
#define FLARELAB_CHECK_LE(a, b) FLARELAB_CHECK_OP(a, <=, b)
#define FLARELAB_CHECK_GT(a, b) FLARELAB_CHECK_OP(a, >, b)
#define FLARELAB_CHECK_GE(a, b) FLARELAB_CHECK_OP(a, >=, b)

#ifdef NDEBUG
#define FLARELAB_DCHECK(cond) \
    do {                      \
    } while (false)
#define FLARELAB_DCHECK_OP(a, op, b) \
    do {                             \
    } while (false)
#else
#define FLARELAB_DCHECK(cond) FLARELAB_CHECK(cond)
#define FLARELAB_DCHECK_OP(a, op, b) FLARELAB_CHECK_OP(a, op, b)
#endif
#define FLARELAB_DCHECK_LT(a, b) FLARELAB_DCHECK_OP(a, <, b)
#define FLARELAB_DCHECK_LE(a, b) FLARELAB_DCHECK_OP(a, <=, b)
