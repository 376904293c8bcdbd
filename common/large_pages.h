// ============================================================================
//  flarelab common: large pages for large, freshly allocated arrays
// ============================================================================
//
// A frame's big arrays (the image, a ghost's ray grid and quads, its primitives) are allocated
// fresh and touched once. Faulting them in 4 KiB at a time is slow where page faults are dear: on
// the shared virtual machines this project is measured on, zeroing a 1920x1080 RGB float image
// (24.9 MB) took 97 ms, and 9 to 10 ms once its pages were 2 MiB ones. Linux backs an anonymous
// range with such pages when asked (transparent huge pages in their "madvise" mode, Debian's
// default); elsewhere, or where the kernel has none free, the request does nothing and the pages
// come as usual. Two ways in: large pages asked for under a vector's fresh storage
// (reserveLargePages, for types whose vectors are shared widely, like ImageRGB's pixels), and an
// allocator whose large arrays are mappings of their own on large-page boundaries
// (LargePageVector, for the renderer's per-grid arrays of 1 to 20 MB, which a heap block would
// seldom hold a whole aligned large page of).
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <new>
#include <vector>

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace flarelab {

inline constexpr size_t kLargePageBytes = size_t{2} << 20;
// Below this an array may share its pages with others; a large page would mostly hold them.
inline constexpr size_t kLargePageMinBytes = size_t{4} << 20;

// Asks for large pages under [data, data + bytes): only the 2 MiB-aligned part inside it, so no
// other allocation's pages are touched. A request only; never fails.
inline void adviseLargePages(const void* data, size_t bytes) {
#if defined(__linux__) && defined(MADV_HUGEPAGE)
    if (data == nullptr || bytes < kLargePageMinBytes) return;
    constexpr uintptr_t kLarge = uintptr_t{2} << 20;
    const uintptr_t first = reinterpret_cast<uintptr_t>(data);
    const uintptr_t begin = (first + kLarge - 1) & ~(kLarge - 1);
    const uintptr_t end = (first + bytes) & ~(kLarge - 1);
    if (end > begin) (void)madvise(reinterpret_cast<void*>(begin), end - begin, MADV_HUGEPAGE);
#else
    (void)data;
    (void)bytes;
#endif
}

// reserve(n), with large pages asked for the reserved storage when it is freshly allocated (an
// empty vector's first allocation): call before the elements are written.
template <typename T, typename A>
void reserveLargePages(std::vector<T, A>& v, size_t n) {
    const bool fresh = v.capacity() == 0;
    v.reserve(n);
    if (fresh) adviseLargePages(v.data(), v.capacity() * sizeof(T));
}

// Arrays from this size on get their own large pages (LargePageAllocator): faulting in a 1 MiB
// array 4 KiB at a time costs some 256 faults, a large page one, for at most 1 MiB more memory.
inline constexpr size_t kLargePageAllocatorMinBytes = size_t{1} << 20;

// Maps `bytes` (at least kLargePageAllocatorMinBytes) of zeroed memory on a 2 MiB boundary, its
// length rounded up to whole large pages, with large pages asked for. nullptr where the system
// has no memory to give. Released with unmapLargePages(p, bytes).
inline void* mapLargePages(size_t bytes) {
    const size_t length = (bytes + kLargePageBytes - 1) & ~(kLargePageBytes - 1);
#if defined(__linux__) && defined(MADV_HUGEPAGE)
    // Mapped one large page longer than asked, then trimmed to the 2 MiB boundary.
    const size_t total = length + kLargePageBytes;
    void* base = mmap(nullptr, total, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (base == MAP_FAILED) return nullptr;
    const uintptr_t first = reinterpret_cast<uintptr_t>(base);
    const uintptr_t aligned = (first + kLargePageBytes - 1) & ~(uintptr_t{kLargePageBytes} - 1);
    if (aligned > first) (void)munmap(base, aligned - first);
    const uintptr_t end = first + total;
    if (end > aligned + length)
        (void)munmap(reinterpret_cast<void*>(aligned + length), end - aligned - length);
    (void)madvise(reinterpret_cast<void*>(aligned), length, MADV_HUGEPAGE);
    return reinterpret_cast<void*>(aligned);
#else
    return ::operator new (length, std::align_val_t{kLargePageBytes}, std::nothrow);
#endif
}
inline void unmapLargePages(void* p, size_t bytes) noexcept {
    const size_t length = (bytes + kLargePageBytes - 1) & ~(kLargePageBytes - 1);
#if defined(__linux__) && defined(MADV_HUGEPAGE)
    (void)munmap(p, length);
#else
    (void)length;
    ::operator delete (p, std::align_val_t{kLargePageBytes});
#endif
}

// The allocator of a frame's big, short-lived arrays (ray grids, quads, primitives): small ones
// from the usual heap, from kLargePageAllocatorMinBytes on a mapping of their own on large pages,
// given back to the system when freed.
template <typename T>
struct LargePageAllocator {
    using value_type = T;
    LargePageAllocator() noexcept = default;
    template <typename U>
    LargePageAllocator(const LargePageAllocator<U>&) noexcept {}
    T* allocate(size_t n) {
        if (n > static_cast<size_t>(PTRDIFF_MAX) / sizeof(T)) throw std::bad_array_new_length();
        const size_t bytes = n * sizeof(T);
        if (bytes < kLargePageAllocatorMinBytes) return std::allocator<T>{}.allocate(n);
        void* p = mapLargePages(bytes);
        if (p == nullptr) throw std::bad_alloc();
        return static_cast<T*>(p);
    }
    void deallocate(T* p, size_t n) noexcept {
        const size_t bytes = n * sizeof(T);
        if (bytes < kLargePageAllocatorMinBytes)
            std::allocator<T>{}.deallocate(p, n);
        else
            unmapLargePages(p, bytes);
    }
    template <typename U>
    bool operator==(const LargePageAllocator<U>&) const noexcept {
        return true;
    }
};

template <typename T>
using LargePageVector = std::vector<T, LargePageAllocator<T>>;

}  // namespace flarelab
