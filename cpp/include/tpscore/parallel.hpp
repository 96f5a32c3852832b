// Deterministic parallel loops over independent output rows.
#pragma once

#include <algorithm>
#include <cstddef>
#include <exception>
#include <system_error>
#include <thread>
#include <vector>

namespace tpscore {

/// The most threads a kernel uses: 4x the hardware concurrency. More would only
/// share the cores, and every thread costs a stack; a request above it (from
/// set_num_threads or TPSCORE_NUM_THREADS) is capped here.
int max_threads();

/// Number of threads a kernel may use: set_num_threads() if called with n > 0,
/// else the environment variable TPSCORE_NUM_THREADS, else the hardware concurrency;
/// never more than max_threads().
int num_threads();

/// Sets the thread count for later kernel calls; n <= 0 restores the default, and
/// n > max_threads() means max_threads().
void set_num_threads(int n);

/// Calls body(begin, end) on disjoint chunks that cover [0, n).
///
/// Each chunk holds at least `min_chunk` items, so small problems run serially on
/// the calling thread (spawning threads costs tens of microseconds). Every index is
/// visited by exactly one chunk, and the chunks depend only on n, min_chunk and the
/// thread count, so a body that writes only its own rows gives the same result
/// whatever the thread count. When the system refuses to start a thread (too many
/// threads, no memory for a stack), the calling thread runs that chunk itself after
/// its own: slower, never an abort. The first exception thrown by a body is rethrown
/// on the calling thread after all workers have joined.
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
    // Chunks [1, started] run on their own threads; the rest on the calling thread.
    std::size_t started = 0;
    for (std::size_t w = 1; w < workers; ++w) {
        try {
            threads.emplace_back(run, w);
        } catch (const std::system_error&) {
            break;  // std::thread reports a failed pthread_create as system_error
        }
        started = w;
    }
    run(0);  // the calling thread takes the first chunk
    for (std::size_t w = started + 1; w < workers; ++w) run(w);
    for (auto& t : threads) t.join();
    for (auto& e : errors)
        if (e) std::rethrow_exception(e);
}

}  // namespace tpscore
