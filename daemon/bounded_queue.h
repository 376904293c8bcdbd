// ============================================================================
//  flarelab daemon: BoundedQueue
// ============================================================================
//
// A first-in first-out queue between two threads of a job's pipeline (capture -> processing),
// bounded by the bytes its items hold (and by a count): push() waits while the queue is full, so
// memory stays bounded however long the sweep and however large its frames; pop() waits while it
// is empty and returns nullopt once the queue is closed and drained. One item is always admitted
// into an empty queue, however large, so that a frame larger than the bound still passes (alone).
// close() is called by the producer when it is done (or gives up), abort() by either side to stop
// at once: pending pushes return false, pending pops return nullopt.
#pragma once

#include <condition_variable>
#include <cstddef>
#include <deque>
#include <functional>
#include <limits>
#include <mutex>
#include <optional>
#include <utility>

#include "common/check.h"

namespace flarelab::daemon {

template <typename T>
class BoundedQueue {
public:
    // At most `capacity` items and, when `bytes_of` is given, items of at most `capacity_bytes`
    // bytes together (bytes_of(item) says what an item holds).
    explicit BoundedQueue(size_t capacity,
                          size_t capacity_bytes = std::numeric_limits<size_t>::max(),
                          std::function<size_t(const T&)> bytes_of = {})
        : capacity_(capacity), capacity_bytes_(capacity_bytes), bytes_of_(std::move(bytes_of)) {
        FLARELAB_CHECK_GT(capacity, 0u);
    }

    // False when the queue was closed or aborted (the item is dropped).
    bool push(T item) {
        const size_t bytes = bytes_of_ ? bytes_of_(item) : 0;
        std::unique_lock lock(mutex_);
        not_full_.wait(lock, [&] {
            return items_.empty() ||
                   (items_.size() < capacity_ && bytes_ <= capacity_bytes_ &&
                    bytes <= capacity_bytes_ - bytes_) ||
                   closed_ || aborted_;
        });
        if (closed_ || aborted_) return false;
        items_.emplace_back(std::move(item), bytes);
        bytes_ += bytes;
        high_water_ = std::max(high_water_, items_.size());
        high_water_bytes_ = std::max(high_water_bytes_, bytes_);
        not_empty_.notify_one();
        return true;
    }

    std::optional<T> pop() {
        std::unique_lock lock(mutex_);
        not_empty_.wait(lock, [&] { return !items_.empty() || closed_ || aborted_; });
        if (aborted_ || items_.empty()) return std::nullopt;
        auto [item, bytes] = std::move(items_.front());
        items_.pop_front();
        bytes_ -= bytes;
        not_full_.notify_one();
        return std::move(item);
    }

    void close() {
        std::lock_guard lock(mutex_);
        closed_ = true;
        not_empty_.notify_all();
        not_full_.notify_all();
    }

    void abort() {
        std::lock_guard lock(mutex_);
        aborted_ = true;
        not_empty_.notify_all();
        not_full_.notify_all();
    }

    // The most items, and the most bytes, the queue held at once.
    size_t highWater() const {
        std::lock_guard lock(mutex_);
        return high_water_;
    }
    size_t highWaterBytes() const {
        std::lock_guard lock(mutex_);
        return high_water_bytes_;
    }

private:
    const size_t capacity_;
    const size_t capacity_bytes_;
    const std::function<size_t(const T&)> bytes_of_;
    mutable std::mutex mutex_;
    std::condition_variable not_full_, not_empty_;
    std::deque<std::pair<T, size_t>> items_;
    size_t bytes_ = 0;
    size_t high_water_ = 0;
    size_t high_water_bytes_ = 0;
    bool closed_ = false;
    bool aborted_ = false;
};

}  // namespace flarelab::daemon
