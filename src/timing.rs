//! Stage timing on the CPU: wall time and the calling thread's CPU time side by side.
//!
//! Wall time on a loaded machine counts every moment the thread waited for a core, so it is
//! noisy; the thread's CPU time (`clock_gettime(CLOCK_THREAD_CPUTIME_ID)`, POSIX) counts only
//! the time the thread itself ran. `std` exposes no per-thread CPU clock, hence the `libc`
//! call. A GPU stage's work runs elsewhere (on the device, or on lavapipe's own worker
//! threads): its cost is the GPU timestamp time of [`crate::gpu::timing`], and the thread CPU
//! time of a GPU stage is only what the submitting thread spent (recording, upload, readback
//! decoding).

use std::time::Instant;

/// CPU time the calling thread has consumed since it started, seconds (`NaN` if the clock
/// cannot be read, which POSIX systems do not do for this clock).
pub fn thread_cpu_s() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec; CLOCK_THREAD_CPUTIME_ID is a clock id every
    // Linux kernel provides and the call writes only through the pointer it is given.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return f64::NAN;
    }
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// The load average over 1, 5 and 15 minutes as `/proc/loadavg` gives it ("unknown" where it
/// cannot be read): printed by the benchmarks, since wall times depend on it.
pub fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "unknown".into())
}

/// Wall and thread CPU time of one measured span, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct SpanTime {
    pub wall_ms: f64,
    pub cpu_ms: f64,
}

impl std::ops::AddAssign for SpanTime {
    fn add_assign(&mut self, other: Self) {
        self.wall_ms += other.wall_ms;
        self.cpu_ms += other.cpu_ms;
    }
}

/// Started at a point in time; [`Stopwatch::elapsed`] gives the wall and thread CPU time since.
/// Read it on the thread that started it (the CPU clock is per thread).
#[derive(Clone, Copy, Debug)]
pub struct Stopwatch {
    wall: Instant,
    cpu_s: f64,
}

impl Stopwatch {
    pub fn start() -> Self {
        Self {
            wall: Instant::now(),
            cpu_s: thread_cpu_s(),
        }
    }

    pub fn elapsed(&self) -> SpanTime {
        SpanTime {
            wall_ms: self.wall.elapsed().as_secs_f64() * 1e3,
            cpu_ms: (thread_cpu_s() - self.cpu_s) * 1e3,
        }
    }

    /// Runs `f` and returns its result with the time it took.
    pub fn time<T>(f: impl FnOnce() -> T) -> (T, SpanTime) {
        let watch = Self::start();
        let out = f();
        (out, watch.elapsed())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn busy_work_costs_cpu_time_and_sleeping_does_not() {
        let (sum, busy) = Stopwatch::time(|| {
            let mut x = 0u64;
            for i in 0..5_000_000u64 {
                x = std::hint::black_box(x.wrapping_mul(31).wrapping_add(i));
            }
            x
        });
        std::hint::black_box(sum);
        assert!(busy.cpu_ms > 0.0, "{busy:?}");
        let (_, idle) =
            Stopwatch::time(|| std::thread::sleep(std::time::Duration::from_millis(30)));
        assert!(idle.wall_ms >= 30.0, "{idle:?}");
        // Sleeping consumes (almost) no CPU: far less than the wall time it took.
        assert!(idle.cpu_ms < 10.0, "{idle:?}");
    }

    #[test]
    fn the_thread_clock_is_monotonic_and_per_thread() {
        let a = thread_cpu_s();
        let b = thread_cpu_s();
        assert!(a.is_finite() && b >= a);
        // A fresh thread starts near zero whatever this thread has consumed.
        let other = std::thread::spawn(thread_cpu_s).join().unwrap();
        assert!(other < 0.05, "{other}");
    }
}
