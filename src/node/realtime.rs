//! Real-time scheduling and memory locking of the control loop's thread (Linux): SCHED_FIFO at
//! a configured priority and `mlockall`, each asked for where the system allows, refused
//! cleanly without the privilege and reported in the summary. The runtime of the design
//! card's 800 Hz loop; no paper equation.

use serde::{Deserialize, Serialize};

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
}

impl Default for RealtimeConfig {
    fn default() -> Self {
        Self {
            fifo_priority: 80,
            lock_memory: true,
        }
    }
}

/// What the control loop's thread got from the system ([`RealtimeConfig`]).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct RealtimeStatus {
    /// The SCHED_FIFO priority the loop ran at (`None`: normal scheduling).
    pub fifo_priority: Option<u8>,
    /// Whether the process's memory was locked.
    pub memory_locked: bool,
    /// What was asked for and refused, with the system's reason.
    pub refused: Vec<String>,
}

/// Locked memory and SCHED_FIFO for the calling thread ([`RealtimeConfig`]), given back when
/// dropped (the thread that called `run` gets its scheduling back). Memory is locked before
/// the clock starts (locking a large process takes a while); SCHED_FIFO is asked for after
/// the workers are spawned (they would inherit it).
pub(super) struct RealtimeGuard {
    pub(super) status: RealtimeStatus,
    old_policy: libc::c_int,
    old_param: libc::sched_param,
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
        }
    }

    /// Asks for SCHED_FIFO on the calling thread if `config` does, then says once what was
    /// refused.
    pub(super) fn fifo(&mut self, config: &RealtimeConfig) {
        if config.fifo_priority > 0 {
            match set_fifo(config.fifo_priority) {
                Ok(()) => self.status.fifo_priority = Some(config.fifo_priority),
                Err(e) => self
                    .status
                    .refused
                    .push(format!("SCHED_FIFO priority {}: {e}", config.fifo_priority)),
            }
        }
        if !self.status.refused.is_empty() {
            eprintln!(
                "warning: real time refused ({}); the control loop runs without it",
                self.status.refused.join("; ")
            );
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

impl Drop for RealtimeGuard {
    fn drop(&mut self) {
        // SAFETY: restores what `acquire` read, on the same thread.
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
