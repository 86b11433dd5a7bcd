//! The node's CAN outputs (`hapcloud run --can IFACE`, `--can-log FILE`): what the control
//! loop puts on the bus, per the protocol of `hapcloud.dbc` ([`crate::io::can`]).
//!
//! Per control tick `k` (800 Hz), decimated by [`CanOutputConfig`] so that the bus keeps room:
//!
//! | message                     | frames | default rate        |
//! |-----------------------------|--------|---------------------|
//! | TorqueCommand_1_4, _5_6     | 2      | every tick (800 Hz) |
//! | HapticConstraint            | 1      | every tick (800 Hz) |
//! | JointState_1_2, _3_4, _5_6  | 3      | every 4th (200 Hz)  |
//! | NodeStatus                  | 1      | every 8th (100 Hz)  |
//! | KeepOffGuard (keep-off guards only) | 1 | with NodeStatus (100 Hz) |
//! | SurfaceCentroid, _Normal    | 2      | per camera estimate |
//!
//! Bus load ([`CanOutputConfig::bus_load`]): a classic data frame with an 11-bit id and 8 data
//! bytes is 108 bits on the wire (44 bits of frame overhead + 64 data bits) plus at most 24
//! stuff bits, plus the 3-bit interframe space: 135 bits worst case. With the defaults at
//! 800 Hz and two 30 Hz cameras: `(2 + 1) * 800 + 3 * 200 + 100 + 2 * 60 = 3220` frames/s,
//! `3220 * 135 = 434,700` bit/s, 43 % of a 1 Mbit/s bus, with keep-off guards 3320 frames/s,
//! 44.8 % (the guards' surfaces follow 30-90 Hz cameras: 100 Hz carries each frame's
//! news; the handle's constraint goes every tick for the haptic rendering) (every frame each tick would be
//! `7 * 800 * 135 = 756,000` bit/s, 76 %: too close to saturation for a bus the drives
//! share). Joint states are the drives' own messages on a real robot (the DBC names ROBOT as
//! their sender); the node sends the states it used, which a bus monitor can compare.
//!
//! The torque counter and the constraint counter are the tick index mod 256, so a log can be
//! matched to the recording tick by tick. The output runs on its own thread ([`CanThread`]):
//! the control loop hands over each tick's values without waiting (a full hand-off drops
//! and counts them). The SocketCAN sender never blocks (a full queue drops and counts the
//! frame); a write error on the log or the socket is reported once and the output is closed,
//! the control loop goes on.

use crate::control::ControlStatus;
use crate::control::record::TickRecord;
use crate::haptics::HapticStatus;
use crate::io::can::{
    CanBackend, CanConstraint, CanError, CanJointState, CanKeepOff, CanSender, CanStatus,
    CanSurface, CanTorqueCommand, CanValue, CandumpWriter, Encoded, NO_GUARD,
};
use crate::surface::SurfaceEstimate;
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::time::{Duration, Instant};

/// Worst-case bits of one classic 8-byte data frame with an 11-bit id, interframe space
/// included (see the module doc).
pub const FRAME_BITS_WORST: f64 = 135.0;

/// How often each message goes out, in control ticks (1 = every tick).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CanOutputConfig {
    pub torque_every_ticks: u32,
    pub constraint_every_ticks: u32,
    pub joint_state_every_ticks: u32,
    pub status_every_ticks: u32,
    /// Bus bit rate, bit/s (for the load estimate).
    pub bitrate_bit_per_s: f64,
    /// Camera frames per second over all cameras, Hz (for the load estimate: one surface pair
    /// per estimate).
    pub camera_frames_hz: f64,
}

impl Default for CanOutputConfig {
    fn default() -> Self {
        Self {
            torque_every_ticks: 1,
            constraint_every_ticks: 1,
            joint_state_every_ticks: 4,
            status_every_ticks: 8,
            bitrate_bit_per_s: 1e6,
            camera_frames_hz: 60.0,
        }
    }
}

/// Frames per second and the share of the bus they take.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct BusLoad {
    pub frames_per_s: f64,
    pub bits_per_s: f64,
    /// `bits_per_s / bitrate`, worst-case bit stuffing.
    pub load_fraction: f64,
}

impl CanOutputConfig {
    pub fn validate(&self) -> Result<(), String> {
        for (name, v) in [
            ("torque_every_ticks", self.torque_every_ticks),
            ("constraint_every_ticks", self.constraint_every_ticks),
            ("joint_state_every_ticks", self.joint_state_every_ticks),
            ("status_every_ticks", self.status_every_ticks),
        ] {
            if v == 0 {
                return Err(format!("can.{name} must be at least 1"));
            }
        }
        if !(self.bitrate_bit_per_s.is_finite() && self.bitrate_bit_per_s > 0.0) {
            return Err("can.bitrate_bit_per_s must be positive".into());
        }
        if !(self.camera_frames_hz.is_finite() && self.camera_frames_hz >= 0.0) {
            return Err("can.camera_frames_hz must be finite and not negative".into());
        }
        Ok(())
    }

    /// The bus load of these rates at control rate `tick_rate_hz`, with the KeepOffGuard
    /// frame when there are `keep_off` guards.
    pub fn bus_load(&self, tick_rate_hz: f64, keep_off: bool) -> BusLoad {
        let per = |frames: f64, every: u32| frames * tick_rate_hz / f64::from(every);
        let frames_per_s = per(2.0, self.torque_every_ticks)
            + per(1.0, self.constraint_every_ticks)
            + per(3.0, self.joint_state_every_ticks)
            + per(1.0 + f64::from(u8::from(keep_off)), self.status_every_ticks)
            + 2.0 * self.camera_frames_hz;
        let bits_per_s = frames_per_s * FRAME_BITS_WORST;
        BusLoad {
            frames_per_s,
            bits_per_s,
            load_fraction: bits_per_s / self.bitrate_bit_per_s,
        }
    }
}

/// What went out.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct CanCounters {
    pub frames_sent: u64,
    /// Frames the socket's full queue dropped.
    pub frames_dropped: u64,
    pub frames_logged: u64,
    /// Values with a signal out of range (sent saturated) or NaN (sent as 0).
    pub saturated_values: u64,
    /// Messages the control loop could not hand to the CAN thread (it was behind: a full
    /// hand-off queue drops, never waits).
    pub handoff_dropped: u64,
    /// The error that closed an output, if any.
    pub error: Option<String>,
}

/// The node's health at a tick, for NodeStatus.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Health {
    pub deadline_misses: u64,
    pub fault_flags: u16,
    pub gpu: bool,
    pub latency_ms: f64,
}

/// The SocketCAN socket and/or the candump log the loop writes to.
pub struct CanOutput {
    config: CanOutputConfig,
    sender: Option<CanSender>,
    log: Option<CandumpWriter<BufWriter<File>>>,
    counters: CanCounters,
    surface_counter: u8,
}

impl CanOutput {
    /// Opens the interface and creates the log; errors name the interface or the file.
    pub fn open(
        config: &CanOutputConfig,
        interface: Option<&str>,
        log: Option<&Path>,
    ) -> Result<Self, CanError> {
        let sender = interface.map(CanSender::open).transpose()?;
        let log = log
            .map(|path| {
                File::create(path)
                    .map(|f| CandumpWriter::new(BufWriter::new(f), interface.unwrap_or("can0")))
                    .map_err(|e| CanError::Log(format!("{}: {e}", path.display())))
            })
            .transpose()?;
        Ok(Self {
            config: config.clone(),
            sender,
            log,
            counters: CanCounters::default(),
            surface_counter: 0,
        })
    }

    /// True when there is nowhere to write.
    pub fn is_closed(&self) -> bool {
        self.sender.is_none() && self.log.is_none()
    }

    fn emit(&mut self, t_s: f64, value: &CanValue) {
        if let Some(sender) = self.sender.as_mut() {
            match sender.send(value) {
                Ok(encoded) => {
                    self.counters.saturated_values += u64::from(encoded.saturated);
                    self.counters.frames_sent = sender.frames_sent;
                    self.counters.frames_dropped = sender.frames_dropped;
                }
                Err(e) => self.close(e.to_string(), true),
            }
        }
        if let Some(log) = self.log.as_mut() {
            match log.write_value(t_s, value) {
                Ok(Encoded { frames, saturated }) => {
                    self.counters.frames_logged += frames.len() as u64;
                    if self.sender.is_none() {
                        self.counters.saturated_values += u64::from(saturated);
                    }
                }
                Err(e) => self.close(format!("candump log: {e}"), false),
            }
        }
    }

    fn close(&mut self, error: String, socket: bool) {
        crate::stderr_line!("warning: CAN output closed: {error}");
        self.counters.error.get_or_insert(error);
        if socket {
            self.sender = None;
        } else {
            self.log = None;
        }
    }

    /// The messages of control tick `record.index` at node time `t_s`.
    pub fn tick(&mut self, t_s: f64, record: &TickRecord, health: &Health) {
        self.send(t_s, record, health, false);
    }

    /// The last messages of a node stopping on a fault: the torque command (the safe
    /// command, disabled), the constraint (inactive) and the status, whatever their rates;
    /// the log is flushed.
    pub fn safe_stop(&mut self, t_s: f64, record: &TickRecord, health: &Health) {
        self.send(t_s, record, health, true);
        if let Some(log) = self.log.as_mut()
            && let Err(e) = log.flush()
        {
            self.close(format!("candump log: {e}"), false);
        }
    }

    fn send(&mut self, t_s: f64, record: &TickRecord, health: &Health, every_message: bool) {
        let k = record.index;
        let due = |every: u32| every_message || k.is_multiple_of(u64::from(every));
        let c = &record.control;
        let counter = (k % 256) as u8;
        if due(self.config.torque_every_ticks) {
            self.emit(
                t_s,
                &CanValue::TorqueCommand(CanTorqueCommand {
                    torques_nm: c.tau_nm.into(),
                    enabled: c.status == ControlStatus::Ok,
                    counter,
                }),
            );
        }
        if due(self.config.constraint_every_ticks) {
            self.emit(
                t_s,
                &CanValue::Constraint(CanConstraint {
                    d_proj_m: c.d_proj_m,
                    alpha_p_m: c.alpha_p_m,
                    alpha_v_m_s: c.alpha_v_mps,
                    position_active: c.position_active(),
                    velocity_active: c.velocity_active(),
                    force_active: c.force_active,
                    surface_valid: c.haptic_status != HapticStatus::NoSurface,
                    counter,
                }),
            );
        }
        if due(self.config.joint_state_every_ticks) {
            self.emit(
                t_s,
                &CanValue::JointState(CanJointState {
                    positions_rad: c.joints.q_rad.into(),
                    velocities_rad_s: c.joints.qd_rad_per_s.into(),
                }),
            );
        }
        if due(self.config.status_every_ticks) && !record.keep_off.as_slice().is_empty() {
            self.emit(t_s, &CanValue::KeepOff(keep_off(record, counter)));
        }
        if due(self.config.status_every_ticks) {
            self.emit(
                t_s,
                &CanValue::Status(CanStatus {
                    deadline_misses: health.deadline_misses.min(u64::from(u32::MAX)) as u32,
                    fault_flags: health.fault_flags,
                    backend: if health.gpu {
                        CanBackend::Gpu
                    } else {
                        CanBackend::Cpu
                    },
                    latency_ms: health.latency_ms,
                    heartbeat: counter,
                }),
            );
        }
    }

    /// One camera's surface pair (SurfaceCentroid + SurfaceNormal), sent when fusion takes
    /// its estimate in, with the output's rolling counter.
    fn surface(&mut self, t_s: f64, mut surface: CanSurface) {
        surface.counter = self.surface_counter;
        self.surface_counter = (self.surface_counter + 1) & 0xF;
        self.emit(t_s, &CanValue::Surface(surface));
    }

    /// Flushes the log and returns the counters.
    pub fn finish(mut self) -> CanCounters {
        if let Some(log) = self.log.as_mut()
            && let Err(e) = log.flush()
        {
            self.counters
                .error
                .get_or_insert(format!("candump log: {e}"));
        }
        self.counters
    }
}

/// The KeepOffGuard value of a tick: the keep-off guard nearest its surface, or none.
fn keep_off(record: &TickRecord, counter: u8) -> CanKeepOff {
    let guards = record.keep_off.as_slice();
    let blind_guard = guards
        .iter()
        .any(|g| g.haptic_status == HapticStatus::NoSurface);
    let status = |s: HapticStatus| match s {
        HapticStatus::Active => 0,
        HapticStatus::Far => 1,
        HapticStatus::NoSurface => 2,
    };
    let finite_or_zero = |v: f64| if v.is_finite() { v } else { 0.0 };
    match record.keep_off.nearest() {
        Some((i, g)) => CanKeepOff {
            d_proj_m: g.d_proj_m,
            d_rate_m_s: finite_or_zero(g.d_rate_mps),
            alpha_p_m: finite_or_zero(g.alpha_p_m),
            guard_index: (i as u8).min(NO_GUARD - 1),
            status: status(g.haptic_status),
            position_active: !g.alpha_p_m.is_nan(),
            blind_guard,
            held: g.held,
            counter,
        },
        None => CanKeepOff {
            d_proj_m: 0.0,
            d_rate_m_s: 0.0,
            alpha_p_m: 0.0,
            guard_index: NO_GUARD,
            status: status(HapticStatus::NoSurface),
            position_active: false,
            blind_guard,
            held: false,
            counter,
        },
    }
}

/// What the control loop hands the CAN thread, by value (queuing it allocates nothing).
enum Item {
    Tick(f64, TickRecord, Health),
    Surface(f64, CanSurface),
    SafeStop(f64, TickRecord, Health),
}

/// Messages the CAN thread may be behind by (about 40 ms of ticks at 800 Hz).
pub const QUEUE_ITEMS: usize = 64;

/// How long the node waits for a stalled CAN thread when it stops, before leaving it.
pub const STOP_WAIT: Duration = Duration::from_secs(2);

/// [`CanOutput`] on its own thread: the control loop hands each tick's messages over
/// without waiting ([`CanThread::tick`], [`CanThread::estimate`]: `try_send` into a bounded
/// channel whose slots are allocated once; a full channel drops the messages, counted in
/// [`CanCounters::handoff_dropped`]), so a slow log file or socket never delays a tick. The
/// thread runs at SCHED_FIFO one below the loop where the system allows, so the torque
/// command follows the tick closely under load.
pub struct CanThread {
    tx: SyncSender<Item>,
    dropped: u64,
    done: Receiver<CanCounters>,
    handle: std::thread::JoinHandle<()>,
}

impl CanThread {
    /// Starts sending `output`'s messages; `fifo_priority` (1-99) is asked for on the thread
    /// (refused silently without the privilege: the loop's own refusal is reported).
    pub fn spawn(mut output: CanOutput, fifo_priority: Option<u8>) -> Result<Self, CanError> {
        let (tx, rx) = mpsc::sync_channel::<Item>(QUEUE_ITEMS);
        let (done_tx, done) = mpsc::channel();
        let handle = std::thread::Builder::new()
            .name("can-out".into())
            .spawn(move || {
                if let Some(p) = fifo_priority.filter(|p| *p > 0) {
                    let _ = super::realtime::set_fifo(p);
                }
                for item in rx {
                    match item {
                        Item::Tick(t_s, record, health) => output.tick(t_s, &record, &health),
                        Item::Surface(t_s, surface) => output.surface(t_s, surface),
                        Item::SafeStop(t_s, record, health) => {
                            output.safe_stop(t_s, &record, &health)
                        }
                    }
                }
                let _ = done_tx.send(output.finish());
            })
            .map_err(|e| CanError::Log(format!("CAN output thread: {e}")))?;
        Ok(Self {
            tx,
            dropped: 0,
            done,
            handle,
        })
    }

    fn offer(&mut self, item: Item) {
        if self.tx.try_send(item).is_err() {
            self.dropped += 1;
        }
    }

    /// The messages of control tick `record.index` at node time `t_s`, without waiting.
    pub fn tick(&mut self, t_s: f64, record: &TickRecord, health: &Health) {
        self.offer(Item::Tick(t_s, *record, *health));
    }

    /// One camera's estimate, without waiting.
    pub fn estimate(&mut self, t_s: f64, estimate: &SurfaceEstimate) {
        self.offer(Item::Surface(t_s, CanSurface::from_estimate(estimate, 0)));
    }

    /// Ends the output: the safe command last if given (waiting up to [`STOP_WAIT`] for a
    /// slot: it must go out), then the thread flushes the log and ends. A thread stalled past
    /// [`STOP_WAIT`] is left behind (the node must stop) and the counters say so.
    pub fn finish(self, safe_stop: Option<(f64, TickRecord, Health)>) -> CanCounters {
        let Self {
            tx,
            dropped,
            done,
            handle,
        } = self;
        let deadline = Instant::now() + STOP_WAIT;
        let mut stop_lost = false;
        if let Some((t_s, record, health)) = safe_stop {
            let mut item = Item::SafeStop(t_s, record, health);
            loop {
                match tx.try_send(item) {
                    Ok(()) | Err(TrySendError::Disconnected(_)) => break,
                    Err(TrySendError::Full(back)) if Instant::now() < deadline => {
                        item = back;
                        std::thread::sleep(Duration::from_millis(1));
                    }
                    Err(TrySendError::Full(_)) => {
                        stop_lost = true;
                        break;
                    }
                }
            }
        }
        drop(tx);
        let wait = deadline.saturating_duration_since(Instant::now());
        let mut counters = match done.recv_timeout(wait) {
            Ok(counters) => {
                let _ = handle.join();
                counters
            }
            Err(_) => CanCounters {
                error: Some(format!(
                    "the CAN output thread was stalled for {} s at the stop and was left{}",
                    STOP_WAIT.as_secs(),
                    if stop_lost {
                        ": the safe command could not be queued"
                    } else {
                        ""
                    }
                )),
                ..CanCounters::default()
            },
        };
        counters.handoff_dropped = dropped;
        counters
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_rates_fit_a_1_mbit_bus_and_every_tick_would_not() {
        let load = CanOutputConfig::default().bus_load(800.0, false);
        assert_eq!(load.frames_per_s, 3220.0);
        assert!((load.load_fraction - 0.4347).abs() < 1e-4, "{load:?}");
        let guarded = CanOutputConfig::default().bus_load(800.0, true);
        assert_eq!(guarded.frames_per_s, 3320.0);
        assert!((guarded.load_fraction - 0.4482).abs() < 1e-4, "{guarded:?}");
        let every = CanOutputConfig {
            joint_state_every_ticks: 1,
            status_every_ticks: 1,
            camera_frames_hz: 0.0,
            ..CanOutputConfig::default()
        };
        assert!((every.bus_load(800.0, false).load_fraction - 0.756).abs() < 1e-9);
        let bad = CanOutputConfig {
            status_every_ticks: 0,
            ..CanOutputConfig::default()
        };
        assert!(bad.validate().unwrap_err().contains("status_every_ticks"));
    }

    #[test]
    fn a_missing_interface_is_an_error_naming_it() {
        let err = CanOutput::open(&CanOutputConfig::default(), Some("hapcloud_nope9"), None)
            .err()
            .unwrap();
        assert!(err.to_string().contains("hapcloud_nope9"), "{err}");
        let err = CanOutput::open(
            &CanOutputConfig::default(),
            None,
            Some(Path::new("/nonexistent-dir/x.log")),
        )
        .err()
        .unwrap();
        assert!(err.to_string().contains("/nonexistent-dir/x.log"), "{err}");
    }
}
