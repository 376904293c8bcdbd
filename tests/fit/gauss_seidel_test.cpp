#include "fit/gauss_seidel.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <random>
#include <stdexcept>
#include <vector>

namespace flarelab::fit {
namespace {

TEST(GaussSeidel, EachStepWaitsForTheLastConflictingStepsOnly) {
    // Item 1 reads item 0; item 2 reads nothing and nothing reads it.
    const std::vector<size_t> items = {0, 1, 2, 0, 1, 2};
    const std::vector<std::vector<size_t>> neighbours = {{}, {0}, {}};
    const auto waits = gaussSeidelWaits(items, neighbours);
    ASSERT_EQ(waits.size(), items.size());
    EXPECT_EQ(waits[0], (std::vector<size_t>{}));
    EXPECT_EQ(waits[1], (std::vector<size_t>{0}));     // reads what step 0 wrote
    EXPECT_EQ(waits[2], (std::vector<size_t>{}));      // conflicts with nothing
    EXPECT_EQ(waits[3], (std::vector<size_t>{0, 1}));  // its own last step; step 1 read item 0
    EXPECT_EQ(waits[4], (std::vector<size_t>{1, 3}));
    EXPECT_EQ(waits[5], (std::vector<size_t>{2}));
}

TEST(GaussSeidel, StepsOnEveryCoreGiveThePlainLoopsValuesBitForBit) {
    // Items reading a few others each, updated by a map whose result depends on the order of
    // the updates in every bit; several passes in a shuffled order.
    std::mt19937 random(7);
    constexpr size_t kItems = 60;
    std::vector<std::vector<size_t>> reads(kItems);
    for (size_t i = 0; i < kItems; ++i)
        for (int k = 0; k < 3; ++k) {
            const size_t j = random() % kItems;
            if (j != i && random() % 2 == 0) reads[i].push_back(j);
        }
    std::vector<size_t> order(kItems);
    for (size_t i = 0; i < kItems; ++i) order[i] = i;
    std::shuffle(order.begin(), order.end(), random);
    std::vector<size_t> items;
    for (int pass = 0; pass < 5; ++pass) items.insert(items.end(), order.begin(), order.end());
    std::vector<double> start(kItems);
    for (double& x : start) x = std::uniform_real_distribution<double>(-1.0, 1.0)(random);
    const auto update = [&](std::vector<double>& x, size_t i) {
        double v = x[i];
        for (int spin = 0; spin < 2000; ++spin) {  // long enough for steps to overlap
            double sum = 1.3 * v;
            for (const size_t j : reads[i]) sum += 0.7 * x[j] + 1e-3 * spin;
            v = std::sin(sum);
        }
        x[i] = v;
    };
    std::vector<double> plain = start;
    for (const size_t i : items) update(plain, i);
    for (int run = 0; run < 3; ++run) {
        std::vector<double> parallel = start;
        runGaussSeidel(items, reads, [&](size_t k) { update(parallel, items[k]); });
        for (size_t i = 0; i < kItems; ++i) EXPECT_EQ(parallel[i], plain[i]) << "item " << i;
    }
}

TEST(GaussSeidel, AFailedStepIsRethrownAndWhatWaitsForItDoesNotRun) {
    const std::vector<size_t> items = {0, 1, 0, 1};
    const std::vector<std::vector<size_t>> neighbours = {{1}, {}};
    std::atomic<int> ran{0};
    EXPECT_THROW(runGaussSeidel(items, neighbours,
                                [&](size_t k) {
                                    if (k == 1) throw std::runtime_error("step 1");
                                    ran.fetch_add(1);
                                }),
                 std::runtime_error);
    EXPECT_EQ(ran.load(), 1);  // step 0 only: steps 2 and 3 wait for step 1
}

TEST(GaussSeidel, NoStepsRunNothing) {
    int ran = 0;
    runGaussSeidel({}, {}, [&](size_t) { ++ran; });
    EXPECT_EQ(ran, 0);
}

}  // namespace
}  // namespace flarelab::fit
