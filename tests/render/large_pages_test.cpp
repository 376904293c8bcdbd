#include "common/large_pages.h"

#include <gtest/gtest.h>

#include <cerrno>
#include <cstdint>
#include <numeric>

#include "common/image.h"

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace flarelab {
namespace {

// Whether the page holding p is mapped in this process (Linux: mincore fails with ENOMEM on
// addresses that are not).
#if defined(__linux__)
bool mapped(const void* p) {
    const uintptr_t page = reinterpret_cast<uintptr_t>(p) & ~uintptr_t{4095};
    unsigned char resident = 0;
    return mincore(reinterpret_cast<void*>(page), 4096, &resident) == 0 || errno != ENOMEM;
}
#endif

TEST(LargePageAllocator, SmallAndLargeArraysHoldTheirValuesThroughGrowthCopiesAndMoves) {
    LargePageVector<int32_t> v;
    // From the heap to a mapping of its own and on, one element at a time.
    const size_t n = 3 * kLargePageAllocatorMinBytes / sizeof(int32_t) + 17;
    for (size_t i = 0; i < n; ++i) v.push_back(static_cast<int32_t>(i * 7));
    ASSERT_EQ(v.size(), n);
    for (size_t i = 0; i < n; ++i) ASSERT_EQ(v[i], static_cast<int32_t>(i * 7)) << i;
    LargePageVector<int32_t> copy = v;
    EXPECT_EQ(copy, v);
    LargePageVector<int32_t> moved = std::move(copy);
    EXPECT_EQ(moved, v);
    moved.resize(5);
    moved.shrink_to_fit();  // back to the heap
    EXPECT_EQ(moved, LargePageVector<int32_t>({0, 7, 14, 21, 28}));
}

TEST(LargePageAllocator, LargeArraysAreZeroedOnALargePageBoundaryAndGivenBack) {
    const size_t n = kLargePageAllocatorMinBytes / sizeof(double) + 1;
    const void* data = nullptr;
    {
        LargePageVector<double> v(n);
        data = v.data();
        EXPECT_EQ(reinterpret_cast<uintptr_t>(data) % kLargePageBytes, 0u);
        EXPECT_EQ(std::accumulate(v.begin(), v.end(), 0.0), 0.0);
        v.back() = 1.0;
#if defined(__linux__)
        EXPECT_TRUE(mapped(data));
#endif
    }
#if defined(__linux__)
    EXPECT_FALSE(mapped(data)) << "a freed large array's mapping is given back";
#endif
    // Below the threshold: the usual heap, any alignment.
    LargePageVector<double> small(16, 2.0);
    EXPECT_EQ(std::accumulate(small.begin(), small.end(), 0.0), 32.0);
}

TEST(LargePageAllocator, AnImpossibleSizeIsRefusedNotWrapped) {
    LargePageAllocator<double> allocator;
    EXPECT_THROW((void)allocator.allocate(SIZE_MAX / 4), std::bad_array_new_length);
}

TEST(LargePages, AdviceOnAnyRangeIsOnlyARequest) {
    adviseLargePages(nullptr, 0);
    adviseLargePages(nullptr, size_t{64} << 20);
    std::vector<char> small(100, 'a');
    adviseLargePages(small.data(), small.size());
    std::vector<char> big;
    reserveLargePages(big, 5 * kLargePageBytes + 3);
    EXPECT_GE(big.capacity(), 5 * kLargePageBytes + 3);
    big.assign(5 * kLargePageBytes + 3, 'b');
    EXPECT_EQ(big.front(), 'b');
    EXPECT_EQ(big.back(), 'b');
    // A vector that already holds storage is reserved as usual and keeps its elements.
    reserveLargePages(small, 10 * kLargePageBytes);
    EXPECT_EQ(small.size(), 100u);
    EXPECT_EQ(small.back(), 'a');
}

TEST(LargePages, AFullHdImageIsZeroed) {
    const ImageRGB image(1920, 1080);
    ASSERT_EQ(image.pixels.size(), 1920u * 1080u * 3u);
    EXPECT_EQ(std::accumulate(image.pixels.begin(), image.pixels.end(), 0.0), 0.0);
    const ImageRGB empty(0, 7);
    EXPECT_TRUE(empty.empty());
    EXPECT_TRUE(empty.pixels.empty());
}

}  // namespace
}  // namespace flarelab
