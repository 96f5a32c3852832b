// Deterministic parallel loops over independent output rows.
#pragma once

#include <algorithm>
#include <cstddef>
#include <type_traits>

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

namespace detail {
/// Runs task(context, i) for every i in [0, count) exactly once, on the calling
/// thread and on up to `helpers` threads of a process-wide pool; returns when all
/// have run, rethrowing the first exception a task threw. See parallel.cpp.
void run_tasks(std::size_t count, std::size_t helpers, void (*task)(void*, std::size_t), void* context);
}  // namespace detail

/// Calls body(begin, end) on disjoint chunks that cover [0, n).
///
/// Each chunk holds at least `min_chunk` items, so small problems run serially on
/// the calling thread. Every index is visited by exactly one chunk, so a body that
/// writes only its own rows gives the same result whatever the thread count (and
/// whichever thread runs which chunk). The calling thread works too, and takes any chunk no other thread
/// has started: a pool thread that cannot start, or that another process keeps off
/// a core, slows nothing down beyond its share. The first exception thrown by a body
/// is rethrown on the calling thread after every chunk has finished.
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
    // Up to four chunks per thread, taken in turn from a shared counter: a thread that
    // another process keeps off its core then holds up a quarter of its share, not all.
    const std::size_t tasks = std::min(4 * workers, std::max<std::size_t>(1, n / min_chunk));
    using Callable = std::remove_reference_t<Body>;
    struct Chunks {
        Callable* body;
        std::size_t n, chunk;
    } chunks{&body, n, (n + tasks - 1) / tasks};
    detail::run_tasks((n + chunks.chunk - 1) / chunks.chunk, workers - 1,
                      [](void* context, std::size_t w) {
                          const Chunks& c = *static_cast<const Chunks*>(context);
                          const std::size_t begin = w * c.chunk;
                          const std::size_t end = std::min(c.n, begin + c.chunk);
                          if (begin < end) (*c.body)(begin, end);
                      },
                      &chunks);
}

}  // namespace tpscore
