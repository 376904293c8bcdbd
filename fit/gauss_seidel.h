#pragma once

#include <cstddef>
#include <functional>
#include <span>
#include <vector>

// Gauss-Seidel sweeps run on every core without changing a bit of their result.
//
// A Gauss-Seidel sweep updates its items one step at a time, each step reading the latest values
// of the items it depends on. Two steps conflict when they update the same item or when one's
// item is among the other's neighbours (it reads that item, or that item reads it); steps that do
// not conflict see the same values in either order, so they may run at once. Each step here
// waits for the earlier steps it conflicts with and nothing else, which leaves every step exactly
// the inputs the plain loop would have given it.
namespace flarelab::fit {

// The steps each step waits for: for step k (updating item `items[k]`), the last earlier step of
// that item and of each of its neighbours, ascending, without repeats. `neighbours[i]` lists the
// items item i reads or is read by (either way round is enough: the relation is made symmetric
// here); every item index must be below neighbours.size().
std::vector<std::vector<size_t>> gaussSeidelWaits(
    std::span<const size_t> items, const std::vector<std::vector<size_t>>& neighbours);

// Runs step(k) for every k in items' order's dependencies (gaussSeidelWaits) on TBB's threads:
// each step starts once those it waits for have finished. An exception thrown by a step is
// rethrown here after the steps already started have finished; steps waiting on it do not run.
void runGaussSeidel(std::span<const size_t> items,
                    const std::vector<std::vector<size_t>>& neighbours,
                    const std::function<void(size_t step)>& step);

}  // namespace flarelab::fit
