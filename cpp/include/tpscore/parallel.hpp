// Deterministic parallel loops over independent output rows.
#pragma once

#include <algorithm>
#include <cstddef>
#include <exception>
#include <thread>
#include <vector>

namespace tpscore {

/// Number of threads a kernel may use: set_num_threads() if called with n > 0,
/// else the environment variable TPSCORE_NUM_THREADS, else the hardware concurrency.
int num_threads();

/// Sets the thread count for later kernel calls; n <= 0 restores the default.
void set_num_threads(int n);

/// Calls body(begin, end) on disjoint chunks that cover [0, n).
///
/// Each chunk holds at least `min_chunk` items, so small problems run serially on
/// the calling thread (spawning threads costs tens of microseconds). Every index is
/// visited by exactly one chunk, so a body that writes only its own rows gives the
/// same result whatever the thread count. The first exception thrown by a worker is
/// rethrown on the calling thread after all workers have joined.
template <class Body>
void parallel_for(std::size_t n, std::size_t min_chunk, Body&& body) {
    if (n == 0) return;
    min_chunk = std::max<std::size_t>(min_chunk, 1);
    const std::size_t max_workers = static_cast<std::size_t>(std::max(1, num_threads()));
    const std::size_t workers = std::min(max_workers, std::max<std::size_t>(1, n / min_chunk));
    if (workers <= 1) {
        body(std::size_t{0}, n);
        return;
    }
    const std::size_t chunk = (n + workers - 1) / workers;
    std::vector<std::exception_ptr> errors(workers);
    std::vector<std::thread> threads;
    threads.reserve(workers - 1);
    auto run = [&](std::size_t w) {
        const std::size_t begin = w * chunk;
        const std::size_t end = std::min(n, begin + chunk);
        if (begin >= end) return;
        try {
            body(begin, end);
        } catch (...) {
            errors[w] = std::current_exception();
        }
    };
    for (std::size_t w = 1; w < workers; ++w) threads.emplace_back(run, w);
    run(0);  // the calling thread takes the first chunk
    for (auto& t : threads) t.join();
    for (auto& e : errors)
        if (e) std::rethrow_exception(e);
}

}  // namespace tpscore
