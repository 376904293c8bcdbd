#include "fit/gauss_seidel.h"

#include <tbb/task_group.h>

#include <algorithm>
#include <atomic>
#include <limits>
#include <memory>

#include "common/check.h"

namespace flarelab::fit {

std::vector<std::vector<size_t>> gaussSeidelWaits(
    std::span<const size_t> items, const std::vector<std::vector<size_t>>& neighbours) {
    const size_t n = neighbours.size();
    // Symmetric: i reads j or j reads i, either way the two steps conflict.
    std::vector<std::vector<size_t>> touching(n);
    for (size_t i = 0; i < n; ++i)
        for (const size_t j : neighbours[i]) {
            FLARELAB_CHECK(j < n);
            if (j == i) continue;
            touching[i].push_back(j);
            touching[j].push_back(i);
        }
    for (auto& t : touching) {
        std::sort(t.begin(), t.end());
        t.erase(std::unique(t.begin(), t.end()), t.end());
    }
    constexpr size_t kNone = std::numeric_limits<size_t>::max();
    std::vector<size_t> last(n, kNone);  // the latest step so far of each item
    std::vector<std::vector<size_t>> waits(items.size());
    for (size_t k = 0; k < items.size(); ++k) {
        const size_t item = items[k];
        FLARELAB_CHECK(item < n);
        // The item's own last step and its neighbours' cover every earlier conflicting step: an
        // item's steps wait for each other in turn.
        if (last[item] != kNone) waits[k].push_back(last[item]);
        for (const size_t j : touching[item])
            if (last[j] != kNone) waits[k].push_back(last[j]);
        std::sort(waits[k].begin(), waits[k].end());
        waits[k].erase(std::unique(waits[k].begin(), waits[k].end()), waits[k].end());
        last[item] = k;
    }
    return waits;
}

void runGaussSeidel(std::span<const size_t> items,
                    const std::vector<std::vector<size_t>>& neighbours,
                    const std::function<void(size_t step)>& step) {
    const auto waits = gaussSeidelWaits(items, neighbours);
    const size_t count = items.size();
    std::vector<std::vector<size_t>> next(count);
    auto pending = std::make_unique<std::atomic<size_t>[]>(count);
    for (size_t k = 0; k < count; ++k) {
        pending[k].store(waits[k].size(), std::memory_order_relaxed);
        for (const size_t w : waits[k]) next[w].push_back(k);
    }
    tbb::task_group group;
    std::atomic<bool> failed{false};
    // A step, then every step it was the last to wait for. The counter's release and acquire
    // order a step's writes before what the steps after it read.
    std::function<void(size_t)> launch = [&](size_t k) {
        group.run([&, k] {
            if (failed.load(std::memory_order_acquire)) return;
            try {
                step(k);
            } catch (...) {
                failed.store(true, std::memory_order_release);
                throw;  // task_group::wait rethrows the first
            }
            for (const size_t s : next[k])
                if (pending[s].fetch_sub(1, std::memory_order_acq_rel) == 1) launch(s);
        });
    };
    for (size_t k = 0; k < count; ++k)
        if (waits[k].empty()) launch(k);
    group.wait();
}

}  // namespace flarelab::fit
