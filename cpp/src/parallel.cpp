#include "tpscore/parallel.hpp"

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdlib>
#include <deque>
#include <exception>
#include <memory>
#include <mutex>
#include <system_error>
#include <thread>

#if defined(__unix__) || defined(__APPLE__)
#include <pthread.h>
#endif

namespace tpscore {

namespace {
std::atomic<int> requested_threads{0};

int hardware_threads() {
    // Asked once: glibc answers by reading /sys/devices/system/cpu/online, which cost
    // a few microseconds on every call (a tenth of a 100-centre TPS fit).
    static const int count = [] {
        const unsigned hw = std::thread::hardware_concurrency();
        return hw > 0 ? static_cast<int>(hw) : 1;
    }();
    return count;
}

int default_threads() {
    if (const char* env = std::getenv("TPSCORE_NUM_THREADS")) {
        // strtol saturates instead of overflowing (atoi's overflow is undefined).
        const long n = std::strtol(env, nullptr, 10);
        if (n > 0) return static_cast<int>(std::min<long>(n, max_threads()));
    }
    return hardware_threads();
}

// --- the thread pool ----------------------------------------------------------------
//
// Starting a std::thread and joining it costs 30-40 microseconds here, and a kernel
// that waits to join a thread the scheduler has not yet run (another process holds
// the core) waits for milliseconds: on a busy machine that made a 0.3 ms TPS fit take
// 1 ms with two threads. So threads are started once and kept, asleep on a condition
// variable between jobs, and a job never waits for a thread that has not begun one
// of its tasks: tasks are claimed from a shared counter, the calling thread claims
// them too, and it waits only for tasks that others have claimed and are running.

struct Job {
    std::size_t count = 0;
    void (*task)(void*, std::size_t) = nullptr;
    void* context = nullptr;
    std::atomic<std::size_t> next{0};      // the next task to claim
    std::atomic<std::size_t> finished{0};  // tasks done
    std::size_t helpers_wanted = 0;        // guarded by the pool's mutex
    std::mutex mutex;                      // guards error, and pairs with done
    std::condition_variable done;
    std::exception_ptr error;

    // Claims and runs tasks until none is left.
    void work() {
        for (;;) {
            const std::size_t i = next.fetch_add(1, std::memory_order_relaxed);
            if (i >= count) return;
            try {
                task(context, i);
            } catch (...) {
                std::lock_guard<std::mutex> lock(mutex);
                if (!error) error = std::current_exception();
            }
            if (finished.fetch_add(1, std::memory_order_acq_rel) + 1 == count) {
                std::lock_guard<std::mutex> lock(mutex);
                done.notify_all();
            }
        }
    }
};

class Pool {
public:
    // Offers `job` to up to `helpers` pool threads, starting threads as needed.
    void submit(const std::shared_ptr<Job>& job, std::size_t helpers) {
        std::lock_guard<std::mutex> lock(mutex_);
        while (threads_ < helpers) {
            try {
                std::thread(&Pool::serve, this).detach();
            } catch (const std::system_error&) {
                break;  // no more threads (limits, memory): the caller does the rest
            }
            ++threads_;
        }
        job->helpers_wanted = std::min(helpers, threads_);
        if (job->helpers_wanted == 0) return;
        jobs_.push_back(job);
        submitted_.fetch_add(1, std::memory_order_release);
        for (std::size_t i = 0; i < job->helpers_wanted; ++i) wake_.notify_one();
    }

    // Takes `job` off the queue if helpers are still wanted for it (all its tasks are
    // claimed by now, so a helper picking it up would find nothing to do).
    void withdraw(const std::shared_ptr<Job>& job) {
        std::lock_guard<std::mutex> lock(mutex_);
        for (auto it = jobs_.begin(); it != jobs_.end(); ++it)
            if (*it == job) {
                jobs_.erase(it);
                return;
            }
    }

private:
    void serve() {
        std::unique_lock<std::mutex> lock(mutex_);
        for (;;) {
            if (jobs_.empty()) {
                // Kernels often come in runs (a pipeline's steps, a benchmark's rounds):
                // watch for the next job for a moment before going to sleep, since a
                // sleeping thread takes tens of microseconds to wake (a 22,500 x 60
                // TPS evaluation lasts about 0.7 ms on two threads).
                const std::size_t seen = submitted_.load(std::memory_order_acquire);
                lock.unlock();
                const auto until = std::chrono::steady_clock::now() + kSpin;
                while (submitted_.load(std::memory_order_acquire) == seen &&
                       std::chrono::steady_clock::now() < until)
                    pause();
                lock.lock();
            }
            wake_.wait(lock, [this] { return !jobs_.empty(); });
            std::shared_ptr<Job> job = jobs_.front();
            if (--job->helpers_wanted == 0) jobs_.pop_front();
            lock.unlock();
            job->work();
            lock.lock();
        }
    }

    static void pause() {
#if defined(__x86_64__) || defined(__i386__)
        __builtin_ia32_pause();
#else
        std::this_thread::yield();
#endif
    }

    static constexpr std::chrono::microseconds kSpin{100};

    std::mutex mutex_;
    std::condition_variable wake_;
    std::deque<std::shared_ptr<Job>> jobs_;
    std::size_t threads_ = 0;
    std::atomic<std::size_t> submitted_{0};  // jobs ever queued: a cheap "anything new?"
};

// The pool lives as long as the process: its threads sleep between jobs and are never
// joined (joining at exit could wait on a thread that is mid-task), so it is never
// destroyed. A child of fork() has none of the parent's threads; it gets a new pool.
std::atomic<Pool*> current_pool{nullptr};

void forget_pool_after_fork() { current_pool.store(nullptr); }

Pool& pool() {
    Pool* p = current_pool.load();
    if (p) return *p;
    static std::mutex creation;
    std::lock_guard<std::mutex> lock(creation);
    p = current_pool.load();
    if (!p) {
#if defined(__unix__) || defined(__APPLE__)
        static const bool registered = pthread_atfork(nullptr, nullptr, forget_pool_after_fork) == 0;
        (void)registered;
#endif
        p = new Pool;  // never deleted, see above
        current_pool.store(p);
    }
    return *p;
}
}  // namespace

int max_threads() { return 4 * hardware_threads(); }

int num_threads() {
    const int n = requested_threads.load(std::memory_order_relaxed);
    return std::min(n > 0 ? n : default_threads(), max_threads());
}

void set_num_threads(int n) {
    requested_threads.store(n > 0 ? std::min(n, max_threads()) : 0, std::memory_order_relaxed);
}

namespace detail {

void run_tasks(std::size_t count, std::size_t helpers, void (*task)(void*, std::size_t), void* context) {
    auto job = std::make_shared<Job>();
    job->count = count;
    job->task = task;
    job->context = context;
    helpers = std::min(helpers, count > 0 ? count - 1 : 0);
    Pool* used = nullptr;
    if (helpers > 0) {
        used = &pool();
        used->submit(job, helpers);
    }
    job->work();
    {
        std::unique_lock<std::mutex> lock(job->mutex);
        job->done.wait(lock, [&] { return job->finished.load(std::memory_order_acquire) == count; });
    }
    if (used) used->withdraw(job);
    if (job->error) std::rethrow_exception(job->error);
}

}  // namespace detail

}  // namespace tpscore
