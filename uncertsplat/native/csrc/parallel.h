// Minimal fork-join over a pool of std::threads (the library links no OpenMP runtime; torch brings its own).
#pragma once

#include <pthread.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdlib>
#include <condition_variable>
#include <cstdint>
#include <exception>
#include <mutex>
#include <thread>
#include <vector>

#if defined(__SSE__) || defined(__x86_64__)
#include <xmmintrin.h>
#define USKERN_HAS_MXCSR 1
#endif

namespace uskern {

// Flushes denormal inputs and results to zero while alive, then restores the thread's mode. Without
// it, a few denormal intermediates (e.g. exp() near the bottom of the float range) cost microcode
// assists that made the vectorised KL loop 3x slower; values below 1.2e-38 carry no information here.
class FlushDenormals {
   public:
    FlushDenormals() {
#ifdef USKERN_HAS_MXCSR
        saved_ = _mm_getcsr();
        _mm_setcsr(saved_ | 0x8040);  // FTZ | DAZ
#endif
    }
    ~FlushDenormals() {
#ifdef USKERN_HAS_MXCSR
        _mm_setcsr(saved_);
#endif
    }
    FlushDenormals(const FlushDenormals&) = delete;
    FlushDenormals& operator=(const FlushDenormals&) = delete;

   private:
    unsigned int saved_ = 0;
};

// The pool's state is this library's own: without hidden visibility its function-local statics (pool_slot()'s slot,
// on_worker()'s flag) were STB_GNU_UNIQUE symbols, which the dynamic linker binds once per process even across
// libraries loaded RTLD_LOCAL (as ctypes does): a second kernels library loaded in the process (another cache folder,
// another build) used the first one's Pool with its own idea of the Pool's layout.
#pragma GCC visibility push(hidden)
namespace detail {

// Threads kept between kernel calls. A training step makes 15-20 parallel kernel calls, and creating and joining a
// std::thread for each cost 35 us on a 2-core VM (0.5 ms a step, 2 % of a bonsai step): the pool's threads wait on a
// condition variable instead and are woken for each call. One call at a time uses it (`busy`); a call that finds it
// taken (another thread's kernel, or a kernel called from inside a worker) makes its own threads as before. The pool
// is never destroyed (its threads may still wait when the process exits), and a child made by fork() starts a new
// one (the parent's threads do not exist there).
class Pool {
   public:
    using Call = void (*)(void*, int64_t);

    // Claims the pool for one call; false when another call holds it.
    bool acquire() { return !busy_.exchange(true, std::memory_order_acquire); }

    // Runs call(ctx, id) for id = 1 .. helpers on the pool's threads (started here when there are too few) and
    // returns at once; wait() returns when all of them are done. When a thread cannot be started (std::system_error)
    // nothing runs, the pool is released and the error thrown; threads_ counts only threads that exist (one counted
    // but missing would leave a later call's wait() waiting for it forever).
    void start(int64_t helpers, Call call, void* ctx) {
        std::lock_guard<std::mutex> lock(mutex_);
        try {
            while (static_cast<int64_t>(threads_) < helpers) {
                const int64_t id = static_cast<int64_t>(threads_) + 1;
                std::thread([this, id] { serve(id); }).detach();
                threads_ = static_cast<size_t>(id);
            }
        } catch (...) {
            busy_.store(false, std::memory_order_release);
            throw;
        }
        call_ = call;
        ctx_ = ctx;
#ifdef USKERN_HAS_MXCSR
        csr_ = _mm_getcsr();  // the caller's floating-point mode, as a thread made for the call would inherit it
#endif
        helpers_ = helpers;
        pending_.store(helpers, std::memory_order_relaxed);
        generation_.fetch_add(1, std::memory_order_release);
        wake_.notify_all();
    }

    // Waits for the helpers of start() and releases the pool.
    void wait() {
        if (!spin([this] { return pending_.load(std::memory_order_acquire) == 0; })) {
            std::unique_lock<std::mutex> lock(mutex_);
            done_.wait(lock, [this] { return pending_.load(std::memory_order_relaxed) == 0; });
        }
        busy_.store(false, std::memory_order_release);
    }

    // True on the pool's own threads (a kernel called from a worker must not wait for the pool it runs in).
    static bool& on_worker() {
        thread_local bool flag = false;
        return flag;
    }

   private:
    // Polls ready() for up to spin_us() microseconds; whether it became true. Kernel calls come in bursts tens of
    // microseconds apart (a render's projection, binning and compositing, then the loss's), and a thread put to sleep
    // on a VM takes tens of microseconds to wake: waiting on the condition variable alone made a bonsai training
    // step no faster than threads made per call in one of two runs (x1.04, x0.94), polling 50 us x0.94-0.95
    // (BENCHMARKS.md, "The kernels' threads kept between calls"). UNCERTSPLAT_KERNEL_SPIN_US sets the time (0: no polling).
    template <typename Ready>
    static bool spin(Ready ready) {
        const int64_t limit_us = spin_us();
        if (limit_us <= 0) return ready();
        const auto t0 = std::chrono::steady_clock::now();
        for (int64_t i = 1;; ++i) {
            if (ready()) return true;
#ifdef USKERN_HAS_MXCSR
            _mm_pause();
#endif
            if (i % 64 == 0 && std::chrono::steady_clock::now() - t0 > std::chrono::microseconds(limit_us))
                return ready();
        }
    }

    // Read once, without a function-local static's guard: a fork() while another thread held that guard (its
    // first call) left the child's first call waiting for it forever. Racing first calls read the same value.
    static int64_t spin_us() {
        static std::atomic<int64_t> cached{-1};
        int64_t us = cached.load(std::memory_order_relaxed);
        if (us < 0) {
            const char* env = std::getenv("UNCERTSPLAT_KERNEL_SPIN_US");
            us = env != nullptr ? std::max<int64_t>(0, std::atoll(env)) : 50;
            cached.store(us, std::memory_order_relaxed);
        }
        return us;
    }

    void serve(int64_t id) {
        on_worker() = true;
        uint64_t seen = 0;
        for (;;) {
            spin([&] { return generation_.load(std::memory_order_acquire) != seen; });
            std::unique_lock<std::mutex> lock(mutex_);
            // A thread the call does not need sleeps on until a call needs it: it used to take the call as seen and
            // poll again for spin_us(), so every call with fewer workers than the pool has threads (a small image's
            // SSIM, the reducers of a small scene, after one call on more threads) kept each idle thread polling a
            // core for 50 us, taken from the threads doing the work (x2.5 on 2 cores: see the commit message).
            wake_.wait(lock, [&] { return generation_.load(std::memory_order_relaxed) != seen && id <= helpers_; });
            seen = generation_.load(std::memory_order_relaxed);
            const Call call = call_;
            void* const ctx = ctx_;
#ifdef USKERN_HAS_MXCSR
            _mm_setcsr(csr_);
#endif
            lock.unlock();
            call(ctx, id);
            lock.lock();
            if (pending_.fetch_sub(1, std::memory_order_acq_rel) == 1) done_.notify_one();
        }
    }

    std::atomic<bool> busy_{false};
    std::mutex mutex_;  // guards the call's fields below and the condition variables' waits
    std::condition_variable wake_, done_;
    std::atomic<uint64_t> generation_{0};
    std::atomic<int64_t> pending_{0};
    size_t threads_ = 0;
    int64_t helpers_ = 0;
    Call call_ = nullptr;
    void* ctx_ = nullptr;
    unsigned int csr_ = 0;
};

inline std::atomic<Pool*>& pool_slot() {
    static std::atomic<Pool*> slot{nullptr};
    return slot;
}

// fork() leaves the child an empty slot. Registered when the library is loaded, not on the first call: a fork() while
// another thread made the first pool under a lock (or a static's guard) left the child's first call waiting forever
// for a lock whose owner does not exist there.
inline const int pool_slot_cleared_on_fork =
    pthread_atfork(nullptr, nullptr, [] { pool_slot().store(nullptr, std::memory_order_relaxed); });

// This process's pool, made on first use, lock-free (see above): racing first calls each make one, one is kept and
// the others, which have no threads yet, are deleted.
inline Pool* pool() {
    (void)pool_slot_cleared_on_fork;  // used, so every compiler keeps its initialisation
    Pool* p = pool_slot().load(std::memory_order_acquire);
    if (p != nullptr) return p;
    Pool* fresh = new Pool();  // never deleted once in the slot: see Pool
    if (pool_slot().compare_exchange_strong(p, fresh, std::memory_order_acq_rel, std::memory_order_acquire))
        return fresh;
    delete fresh;
    return p;
}

template <typename G>
void call_guarded(void* ctx, int64_t id) {
    (*static_cast<G*>(ctx))(id);
}

// The first exception thrown by any worker of a call, thrown again on the calling thread once every worker is done.
class FirstError {
   public:
    void keep() noexcept {
        if (!taken_.exchange(true, std::memory_order_relaxed)) error_ = std::current_exception();
    }
    void rethrow() const {
        if (error_) std::rethrow_exception(error_);
    }

   private:
    std::atomic<bool> taken_{false};
    std::exception_ptr error_;
};

}  // namespace detail
#pragma GCC visibility pop

// Runs fn(worker) for worker = 0 .. workers - 1, worker 0 on the calling thread, and waits for all;
// every worker runs with denormals flushed (FlushDenormals) unless FLUSH is false (a kernel that must give
// torch's bits: torch keeps denormals). The others run on the pool's threads (detail::Pool), or on threads made
// for this call when the pool is taken; which thread runs a worker never changes what it computes.
// An exception from a worker (e.g. std::bad_alloc, which the rasterizer's entry points turn into an error code) is
// thrown here after every worker has finished: the workers use the caller's stack (fn, its captures), so returning
// while one still runs was a use after scope, and an exception thrown past the pool's wait() kept it taken for good.
template <bool FLUSH = true, typename Fn>
void run_workers(int64_t workers, Fn fn) {
    if (workers <= 1) {
        if constexpr (FLUSH) {
            FlushDenormals ftz;
            fn(int64_t{0});
        } else {
            fn(int64_t{0});
        }
        return;
    }
    detail::FirstError error;
    auto guarded = [&fn, &error](int64_t id) noexcept {
        try {
            if constexpr (FLUSH) {
                FlushDenormals ftz;
                fn(id);
            } else {
                fn(id);
            }
        } catch (...) {
            error.keep();
        }
    };
    detail::Pool* pool = detail::Pool::on_worker() ? nullptr : detail::pool();
    if (pool != nullptr && pool->acquire()) {
        pool->start(workers - 1, &detail::call_guarded<decltype(guarded)>, &guarded);
        guarded(int64_t{0});
        pool->wait();
        error.rethrow();
        return;
    }
    std::vector<std::thread> threads;
    threads.reserve(workers - 1);
    try {
        for (int64_t i = 1; i < workers; ++i) threads.emplace_back(guarded, i);
    } catch (...) {  // a thread that cannot be started: the ones that were finish before the error leaves
        for (auto& th : threads) th.join();
        throw;
    }
    guarded(int64_t{0});
    for (auto& th : threads) th.join();
    error.rethrow();
}

}  // namespace uskern
