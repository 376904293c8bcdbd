// ============================================================================
//  flarelab daemon: BoundedQueue
// ============================================================================
//
// A first-in first-out queue of at most `capacity` items between two threads of a job's pipeline
// (capture -> processing). push() waits while the queue is full, so memory stays bounded however
// long the sweep; pop() waits while it is empty and returns nullopt once the queue is closed and
// drained. close() is called by the producer when it is done (or gives up), abort() by either
// side to stop at once: pending pushes return false, pending pops return nullopt.
#pragma once

#include <condition_variable>
#include <cstddef>
#include <deque>
#include <mutex>
#include <optional>

#include "common/check.h"

namespace flarelab::daemon {

template <typename T>
class BoundedQueue {
public:
    explicit BoundedQueue(size_t capacity) : capacity_(capacity) {
        FLARELAB_CHECK_GT(capacity, 0u);
    }

    // False when the queue was closed or aborted (the item is dropped).
    bool push(T item) {
        std::unique_lock lock(mutex_);
        not_full_.wait(lock, [&] { return items_.size() < capacity_ || closed_ || aborted_; });
        if (closed_ || aborted_) return false;
        items_.push_back(std::move(item));
        high_water_ = std::max(high_water_, items_.size());
        not_empty_.notify_one();
        return true;
    }

    std::optional<T> pop() {
        std::unique_lock lock(mutex_);
        not_empty_.wait(lock, [&] { return !items_.empty() || closed_ || aborted_; });
        if (aborted_ || items_.empty()) return std::nullopt;
        T item = std::move(items_.front());
        items_.pop_front();
        not_full_.notify_one();
        return item;
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

    size_t highWater() const {
        std::lock_guard lock(mutex_);
        return high_water_;
    }

private:
    const size_t capacity_;
    mutable std::mutex mutex_;
    std::condition_variable not_full_, not_empty_;
    std::deque<T> items_;
    size_t high_water_ = 0;
    bool closed_ = false;
    bool aborted_ = false;
};

}  // namespace flarelab::daemon
