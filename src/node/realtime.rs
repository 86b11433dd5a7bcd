//! Real-time scheduling and memory locking of the control loop's thread (Linux): SCHED_FIFO at
//! a configured priority (else, where that is refused, the highest normal priority the system
//! grants, nice -20 by default), `mlockall`, a CPU of its own if configured, timer slack 1 ns and a
//! prefaulted stack, each asked for where the system allows, refused cleanly without the
//! privilege and reported in the summary; and the loop's wait for its deadline (an absolute
//! `clock_nanosleep`, then a short spin). The runtime of the design card's 800 Hz loop; no
//! paper equation.

use crate::gpu::clock::monotonic_ns;
use serde::{Deserialize, Serialize};
use std::time::{Duration, Instant};

/// What the control loop's thread asks the system for (Linux; refused without the
/// privilege, e.g. `CAP_SYS_NICE` / `CAP_IPC_LOCK` or an `rtprio` / `memlock` limit, which the
/// summary reports).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RealtimeConfig {
    /// SCHED_FIFO priority of the control loop's thread (1-99; 0: normal scheduling).
    pub fifo_priority: u8,
    /// Lock the process's memory (`mlockall`, pages locked as they are touched), so the loop
    /// never waits for a page fault.
    pub lock_memory: bool,
    /// The loop sleeps until this long before each deadline and spins the rest, us (0: it
    /// sleeps to the deadline): a wake-up that comes less than this late still starts the
    /// tick on time. Costs the loop's thread this long of CPU per tick.
    pub spin_us: u32,
    /// The CPU the loop's thread is pinned to (`None`: wherever the scheduler puts it).
    pub cpu: Option<usize>,
    /// Nice value (-20..=19) the loop's thread asks for when SCHED_FIFO is refused (a VM or
    /// container without a real-time budget): under the fair scheduler a thread at nice -20
    /// weighs about 87 times one at nice 0, so busy processes delay its wake-ups far less.
    /// `None`: no fallback.
    pub fallback_nice: Option<i8>,
    /// Most glibc malloc arenas the process's threads share (`mallopt(M_ARENA_MAX)`, set by
    /// [`limit_malloc_arenas`] before any thread starts; 0: glibc's default of 8 per core).
    /// Each arena keeps the memory of its busiest moment: with locked memory, resident
    /// memory is the sum of every arena's high-water mark, and one arena per thread (the
    /// Zenoh threads, perception) grows with each new burst. The control loop's thread
    /// allocates nothing, so sharing arenas costs it no lock.
    pub malloc_arenas: u32,
}

impl Default for RealtimeConfig {
    fn default() -> Self {
        Self {
            fifo_priority: 80,
            lock_memory: true,
            spin_us: 50,
            cpu: None,
            fallback_nice: Some(-20),
            malloc_arenas: 2,
        }
    }
}

impl RealtimeConfig {
    /// The largest `spin_us` (a spin of a whole 800 Hz period would be a busy loop).
    pub const MAX_SPIN_US: u32 = 500;

    pub(super) fn validate(&self) -> Result<(), String> {
        if self.fifo_priority > 99 {
            return Err(format!(
                "realtime.fifo_priority must be 0 (off) to 99, got {}",
                self.fifo_priority
            ));
        }
        if self.spin_us > Self::MAX_SPIN_US {
            return Err(format!(
                "realtime.spin_us must be 0 to {}, got {}",
                Self::MAX_SPIN_US,
                self.spin_us
            ));
        }
        if let Some(nice) = self.fallback_nice
            && !(-20..=19).contains(&nice)
        {
            return Err(format!(
                "realtime.fallback_nice must be -20 to 19, got {nice}"
            ));
        }
        if let Some(cpu) = self.cpu
            && cpu >= libc::CPU_SETSIZE as usize
        {
            return Err(format!(
                "realtime.cpu must be below {}, got {cpu}",
                libc::CPU_SETSIZE
            ));
        }
        if self.malloc_arenas > Self::MAX_MALLOC_ARENAS {
            return Err(format!(
                "realtime.malloc_arenas must be 0 (glibc's default) to {}, got {}",
                Self::MAX_MALLOC_ARENAS,
                self.malloc_arenas
            ));
        }
        Ok(())
    }

    /// The largest `malloc_arenas`.
    pub const MAX_MALLOC_ARENAS: u32 = 1024;
}

/// Limits glibc's malloc arenas to `config.malloc_arenas` (0: unchanged). Call it before
/// any thread is spawned (the Zenoh session's included): a thread takes an arena at its
/// first allocation, and the limit only stops new arenas.
pub fn limit_malloc_arenas(config: &RealtimeConfig) -> Result<(), String> {
    config.validate()?;
    if config.malloc_arenas == 0 {
        return Ok(());
    }
    // SAFETY: mallopt only sets glibc's allocator parameter; the value is at most 1024.
    if unsafe { libc::mallopt(libc::M_ARENA_MAX, config.malloc_arenas as libc::c_int) } != 1 {
        return Err(format!(
            "mallopt(M_ARENA_MAX, {}) failed",
            config.malloc_arenas
        ));
    }
    Ok(())
}

/// What the control loop's thread got from the system ([`RealtimeConfig`]).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct RealtimeStatus {
    /// The SCHED_FIFO priority the loop ran at (`None`: normal scheduling).
    pub fifo_priority: Option<u8>,
    /// The nice value the loop ran at after SCHED_FIFO was refused (`None`: unchanged).
    pub nice: Option<i8>,
    /// Whether the process's memory was locked.
    pub memory_locked: bool,
    /// The CPU the loop's thread was pinned to.
    pub cpu: Option<usize>,
    /// Page faults (minor and major) of the loop's thread after its first second of ticks
    /// (each one a wait inside a tick; 0 with locked, prefaulted memory).
    pub page_faults_after_warmup: Option<u64>,
    /// What was asked for and refused, with the system's reason.
    pub refused: Vec<String>,
}

impl std::fmt::Display for RealtimeStatus {
    /// One line for the run's summary: what the loop's thread got, and what was refused.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match (self.fifo_priority, self.nice) {
            (Some(p), _) => write!(f, "SCHED_FIFO {p}")?,
            (None, Some(n)) => write!(f, "normal scheduling at nice {n}")?,
            (None, None) => write!(f, "normal scheduling")?,
        }
        write!(
            f,
            ", memory {}",
            if self.memory_locked {
                "locked"
            } else {
                "not locked"
            }
        )?;
        if let Some(cpu) = self.cpu {
            write!(f, ", CPU {cpu}")?;
        }
        if let Some(faults) = self.page_faults_after_warmup {
            write!(f, ", {faults} page faults after warm-up")?;
        }
        if !self.refused.is_empty() {
            write!(f, "; refused: {}", self.refused.join("; "))?;
        }
        Ok(())
    }
}

/// Locked memory and SCHED_FIFO for the calling thread ([`RealtimeConfig`]), given back when
/// dropped (the thread that called `run` gets its scheduling back). Memory is locked before
/// the clock starts (locking a large process takes a while); SCHED_FIFO is asked for after
/// the workers are spawned (they would inherit it).
pub(super) struct RealtimeGuard {
    pub(super) status: RealtimeStatus,
    old_policy: libc::c_int,
    old_param: libc::sched_param,
    old_nice: libc::c_int,
}

impl RealtimeGuard {
    /// Locks memory if `config` asks for it.
    pub(super) fn lock_memory(config: &RealtimeConfig) -> Self {
        let mut status = RealtimeStatus::default();
        // SAFETY: plain syscalls on the calling thread with valid pointers to locals.
        let (old_policy, old_param) = unsafe {
            let mut policy = 0;
            let mut param: libc::sched_param = std::mem::zeroed();
            libc::pthread_getschedparam(libc::pthread_self(), &mut policy, &mut param);
            if config.lock_memory {
                let flags = libc::MCL_CURRENT | libc::MCL_FUTURE | libc::MCL_ONFAULT;
                if libc::mlockall(flags) == 0 {
                    status.memory_locked = true;
                } else {
                    status
                        .refused
                        .push(format!("mlockall: {}", std::io::Error::last_os_error()));
                }
            }
            (policy, param)
        };
        Self {
            status,
            old_policy,
            old_param,
            old_nice: thread_nice(),
        }
    }

    /// Makes the calling thread the loop's: its CPU if `config` names one, timer slack 1 ns,
    /// its stack prefaulted (locked with the rest of memory), SCHED_FIFO if `config` asks for
    /// it; then says once what was refused.
    pub(super) fn loop_thread(&mut self, config: &RealtimeConfig) {
        if let Some(cpu) = config.cpu {
            match pin_to(cpu) {
                Ok(()) => self.status.cpu = Some(cpu),
                Err(e) => self.status.refused.push(format!("CPU {cpu}: {e}")),
            }
        }
        let slack_ns: libc::c_ulong = 1;
        // SAFETY: a prctl on the calling thread with an integer argument.
        if unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, slack_ns) } != 0 {
            self.status.refused.push(format!(
                "timer slack 1 ns: {}",
                std::io::Error::last_os_error()
            ));
        }
        prefault_stack();
        if config.fifo_priority > 0 {
            match set_fifo(config.fifo_priority) {
                Ok(()) => self.status.fifo_priority = Some(config.fifo_priority),
                Err(e) => {
                    self.status
                        .refused
                        .push(format!("SCHED_FIFO priority {}: {e}", config.fifo_priority));
                    if let Some(nice) = config.fallback_nice {
                        match set_thread_nice(nice) {
                            Ok(()) => self.status.nice = Some(nice),
                            Err(e) => self.status.refused.push(format!("nice {nice}: {e}")),
                        }
                    }
                }
            }
        }
        if !self.status.refused.is_empty() {
            let instead = match self.status.nice {
                Some(nice) => format!("runs at nice {nice} instead"),
                None => "runs without it".into(),
            };
            crate::stderr_line!(
                "warning: real time refused ({}); the control loop {instead}",
                self.status.refused.join("; ")
            );
        }
    }
}

/// Stack the loop's thread may use, touched before the first tick.
const PREFAULT_STACK_BYTES: usize = 256 * 1024;

/// Touches `PREFAULT_STACK_BYTES` of the calling thread's stack, so a deep call inside a tick
/// finds its pages present (and locked, with `mlockall`).
#[inline(never)]
fn prefault_stack() {
    let mut stack = [0u8; PREFAULT_STACK_BYTES];
    std::hint::black_box(&mut stack);
}

/// The smallest page size Linux uses.
const MIN_PAGE_BYTES: usize = 4096;

/// Writes one value of every page of `values` back in place, so each page is present before
/// the loop runs: a zeroed allocation (`vec![0; n]`, mapped fresh by the kernel when large)
/// has no page behind it until its first write, and that write inside a tick is a page fault.
pub(super) fn touch_pages<T: Copy>(values: &mut [T]) {
    let per_page = (MIN_PAGE_BYTES / std::mem::size_of::<T>().max(1)).max(1);
    for v in values.iter_mut().step_by(per_page) {
        // SAFETY: `v` is a valid, aligned, exclusive reference; volatile so the write of an
        // unchanged value is not optimised away.
        unsafe { std::ptr::write_volatile(v, *v) };
    }
}

/// Pins the calling thread to `cpu`.
fn pin_to(cpu: usize) -> Result<(), std::io::Error> {
    // SAFETY: a zeroed cpu_set_t is the empty set; `cpu` is below CPU_SETSIZE (validated);
    // the calling thread, a valid pointer to a local.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        libc::CPU_SET(cpu, &mut set);
        if libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set) != 0 {
            return Err(std::io::Error::last_os_error());
        }
    }
    Ok(())
}

/// Page faults (minor and major) of the calling thread so far.
pub(super) fn thread_page_faults() -> u64 {
    // SAFETY: getrusage writes only the rusage it is given.
    let usage = unsafe {
        let mut usage: libc::rusage = std::mem::zeroed();
        libc::getrusage(libc::RUSAGE_THREAD, &mut usage);
        usage
    };
    (usage.ru_minflt + usage.ru_majflt) as u64
}

/// The loop's wait for a deadline: an absolute `clock_nanosleep` on CLOCK_MONOTONIC (the
/// clock of `Instant`; being preempted between reading the clock and sleeping does not
/// lengthen the sleep) until `spin` before the deadline, then a spin to it.
pub(super) struct DeadlineWait {
    /// One instant and its CLOCK_MONOTONIC reading, to turn instants into timespecs.
    anchor: Instant,
    anchor_ns: u64,
    spin: Duration,
}

impl DeadlineWait {
    pub(super) fn new(spin: Duration) -> Self {
        Self {
            anchor: Instant::now(),
            anchor_ns: monotonic_ns(),
            spin,
        }
    }

    /// Returns at `deadline` or, when it has passed, at once.
    pub(super) fn until(&self, deadline: Instant) {
        let wake = deadline.checked_sub(self.spin).unwrap_or(deadline);
        if wake > Instant::now() {
            let ns = self.anchor_ns + wake.saturating_duration_since(self.anchor).as_nanos() as u64;
            let at = libc::timespec {
                tv_sec: (ns / 1_000_000_000) as libc::time_t,
                tv_nsec: (ns % 1_000_000_000) as libc::c_long,
            };
            // SAFETY: a valid timespec; no remaining time is asked for (absolute sleep).
            while unsafe {
                libc::clock_nanosleep(
                    libc::CLOCK_MONOTONIC,
                    libc::TIMER_ABSTIME,
                    &at,
                    std::ptr::null_mut(),
                )
            } == libc::EINTR
            {}
        }
        while Instant::now() < deadline {
            std::hint::spin_loop();
        }
    }
}

/// SCHED_FIFO at `priority` (1-99) for the calling thread.
pub(super) fn set_fifo(priority: u8) -> Result<(), std::io::Error> {
    let fifo = libc::sched_param {
        sched_priority: libc::c_int::from(priority),
    };
    // SAFETY: the calling thread, a valid pointer to a local.
    match unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &fifo) } {
        0 => Ok(()),
        e => Err(std::io::Error::from_raw_os_error(e)),
    }
}

/// The calling thread's nice value (Linux keeps one per thread).
fn thread_nice() -> libc::c_int {
    // SAFETY: getpriority on the calling thread's id; -1 is also a valid nice value, so errno
    // is not consulted (the call cannot fail for the caller's own id).
    unsafe { libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t) }
}

/// Sets the calling thread's nice value (lowering it needs `CAP_SYS_NICE` or an `RLIMIT_NICE`).
fn set_thread_nice(nice: i8) -> Result<(), std::io::Error> {
    // SAFETY: setpriority on the calling thread's id with an integer.
    match unsafe {
        libc::setpriority(
            libc::PRIO_PROCESS,
            libc::gettid() as libc::id_t,
            libc::c_int::from(nice),
        )
    } {
        0 => Ok(()),
        _ => Err(std::io::Error::last_os_error()),
    }
}

impl Drop for RealtimeGuard {
    fn drop(&mut self) {
        if self.status.nice.is_some() {
            let old = i8::try_from(self.old_nice).unwrap_or(0);
            let _ = set_thread_nice(old);
        }
        // SAFETY: restores what `lock_memory` read, on the same thread.
        unsafe {
            if self.status.fifo_priority.is_some() {
                libc::pthread_setschedparam(libc::pthread_self(), self.old_policy, &self.old_param);
            }
            if self.status.memory_locked {
                libc::munlockall();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_status_line_names_what_was_granted_and_refused() {
        let granted = RealtimeStatus {
            fifo_priority: Some(80),
            memory_locked: true,
            page_faults_after_warmup: Some(0),
            ..Default::default()
        };
        assert_eq!(
            granted.to_string(),
            "SCHED_FIFO 80, memory locked, 0 page faults after warm-up"
        );
        let refused = RealtimeStatus {
            nice: Some(-20),
            refused: vec!["SCHED_FIFO: Operation not permitted".into()],
            ..Default::default()
        };
        assert_eq!(
            refused.to_string(),
            "normal scheduling at nice -20, memory not locked; refused: SCHED_FIFO: Operation \
             not permitted"
        );
    }

    #[test]
    fn out_of_range_settings_are_errors_naming_them() {
        assert_eq!(RealtimeConfig::default().validate(), Ok(()));
        let bad = |config: RealtimeConfig, name: &str| {
            let e = config.validate().unwrap_err();
            assert!(e.contains(name), "{e}");
        };
        bad(
            RealtimeConfig {
                fifo_priority: 100,
                ..Default::default()
            },
            "realtime.fifo_priority",
        );
        bad(
            RealtimeConfig {
                spin_us: RealtimeConfig::MAX_SPIN_US + 1,
                ..Default::default()
            },
            "realtime.spin_us",
        );
        bad(
            RealtimeConfig {
                cpu: Some(libc::CPU_SETSIZE as usize),
                ..Default::default()
            },
            "realtime.cpu",
        );
        bad(
            RealtimeConfig {
                fallback_nice: Some(-21),
                ..Default::default()
            },
            "realtime.fallback_nice",
        );
    }

    /// The fallback's nice value is the calling thread's own: set on a thread of its own, it
    /// reads back there and leaves this thread's unchanged (raising it needs no privilege).
    #[test]
    fn the_fallback_nice_value_is_per_thread() {
        let mine = thread_nice();
        let theirs = std::thread::spawn(|| set_thread_nice(7).map(|()| thread_nice()))
            .join()
            .unwrap();
        assert_eq!(theirs.unwrap(), 7);
        assert_eq!(thread_nice(), mine);
    }

    /// The wait turns instants into CLOCK_MONOTONIC timespecs: a deadline a few ms ahead is
    /// reached by sleeping, and one already past returns at once (no sleep to a wrapped time).
    #[test]
    fn the_wait_returns_at_its_deadline_and_at_once_for_a_past_one() {
        let wait = DeadlineWait::new(Duration::ZERO);
        let deadline = Instant::now() + Duration::from_millis(3);
        wait.until(deadline);
        assert!(Instant::now() >= deadline);
        let past = Instant::now() - Duration::from_millis(5);
        let before = Instant::now();
        wait.until(past);
        assert!(before.elapsed() < Duration::from_secs(1));
    }

    /// Threads started after [`limit_malloc_arenas`] share the limited arenas (without it,
    /// each new thread takes an arena of its own). Run in a child process of this test
    /// binary: arenas are never given back, so the count needs a process of its own.
    #[test]
    fn threads_share_the_limited_malloc_arenas() {
        const CHILD: &str = "HAPCLOUD_ARENA_TEST_LIMIT";
        const THREADS: usize = 8;
        if let Some(limit) = std::env::var_os(CHILD) {
            let limit: u32 = limit.to_str().unwrap().parse().unwrap();
            limit_malloc_arenas(&RealtimeConfig {
                malloc_arenas: limit,
                ..Default::default()
            })
            .unwrap();
            let all_started = std::sync::Barrier::new(THREADS);
            std::thread::scope(|s| {
                for _ in 0..THREADS {
                    s.spawn(|| {
                        let block = std::hint::black_box(vec![1u8; 4096]);
                        all_started.wait();
                        drop(block);
                    });
                }
            });
            println!("arenas {}", malloc_arena_count());
            return;
        }
        let arenas_with = |limit: u32| {
            let out = std::process::Command::new(std::env::current_exe().unwrap())
                .args([
                    "--exact",
                    "node::realtime::tests::threads_share_the_limited_malloc_arenas",
                    "--nocapture",
                    "--test-threads=1",
                ])
                .env(CHILD, limit.to_string())
                .output()
                .unwrap();
            let stdout = String::from_utf8_lossy(&out.stdout);
            stdout
                .lines()
                .find_map(|l| l.rsplit_once("arenas ")?.1.trim().parse::<usize>().ok())
                .unwrap_or_else(|| panic!("child said: {stdout}"))
        };
        // The harness's test thread has an arena before the limit is set.
        assert!(arenas_with(2) <= 2);
        assert!(arenas_with(0) >= THREADS);
    }

    /// The number of glibc malloc arenas (`<heap nr=...>` of `malloc_info`).
    fn malloc_arena_count() -> usize {
        let path = std::env::temp_dir().join(format!("hapcloud-arenas-{}", std::process::id()));
        let c_path = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
        // SAFETY: a valid path and mode; malloc_info writes to the FILE it is given, which is
        // closed once.
        unsafe {
            let file = libc::fopen(c_path.as_ptr(), c"w".as_ptr());
            assert!(!file.is_null());
            libc::malloc_info(0, file);
            libc::fclose(file);
        }
        let xml = std::fs::read_to_string(&path).unwrap();
        let _ = std::fs::remove_file(&path);
        xml.matches("<heap nr=").count()
    }
}
