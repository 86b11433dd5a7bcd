//! GPU pass times on the host clock: calibrated timestamps through wgpu's Vulkan interop.
//!
//! wgpu's timestamp queries ([`super::timing`]) count device ticks from an unknown origin:
//! enough for a pass's duration, not for where the pass lies in the node's latency account
//! (capture stamp -> estimate -> constraint, all on the host's `CLOCK_MONOTONIC`, the clock
//! of `std::time::Instant` on Linux). wgpu has no calibrated timestamps, so with the cargo
//! feature `vulkan-calibrated` the context opens its Vulkan device through wgpu-hal
//! (`open_with_callback`, the extension added to the device's list) with
//! `VK_KHR_calibrated_timestamps` or `VK_EXT_calibrated_timestamps` (lavapipe has the EXT one)
//! when the adapter offers one of them and both the device and the `CLOCK_MONOTONIC` time
//! domains, and reads both clocks at one instant with `ash` ([`ClockSample`]:
//! `vkGetCalibratedTimestamps*`, with the driver's bound on how far apart the two reads lay).
//! A pass's tick `t` then lies at `host_ns + (t - device_tick) * period` on the host clock.
//!
//! Without the feature, on an adapter without the extension or when opening the device that
//! way fails, the context opens its device the plain wgpu way and [`HostClock::Uncalibrated`]
//! says why: passes then carry durations only.

use serde::Serialize;

/// Whether the context's GPU timestamps can be placed on the host's `CLOCK_MONOTONIC`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum HostClock {
    /// Calibrated through the named Vulkan extension.
    Calibrated { extension: String },
    /// Durations only; `reason` says why.
    Uncalibrated { reason: String },
}

impl std::fmt::Display for HostClock {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            HostClock::Calibrated { extension } => {
                write!(f, "on the host's CLOCK_MONOTONIC ({extension})")
            }
            HostClock::Uncalibrated { reason } => {
                write!(f, "durations only, not on the host clock ({reason})")
            }
        }
    }
}

/// One device tick and the host's `CLOCK_MONOTONIC` read at the same instant.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct ClockSample {
    pub device_tick: u64,
    pub host_ns: u64,
    /// The driver's bound on the time between the two reads, nanoseconds.
    pub max_deviation_ns: u64,
}

/// Widest bound on the time between a sample's two reads the driver may report, ns: passes
/// take fractions of a millisecond to milliseconds, so a sample looser than this cannot place
/// them.
pub const MAX_SAMPLE_DEVIATION_NS: u64 = 1_000_000;

/// How long before the host clock read just after it a sample's host time may lie, ns.
pub const MAX_SAMPLE_AGE_NS: u64 = 1_000_000_000;

impl ClockSample {
    /// A sample from the driver's reads, checked against the host's `CLOCK_MONOTONIC` read
    /// just after them (`now_ns`): its host time must lie before `now_ns` by at most
    /// [`MAX_SAMPLE_AGE_NS`], its deviation must be at most [`MAX_SAMPLE_DEVIATION_NS`]. The
    /// error names the value.
    pub fn checked(
        device_tick: u64,
        host_ns: u64,
        max_deviation_ns: u64,
        now_ns: u64,
    ) -> Result<Self, String> {
        if host_ns > now_ns || now_ns - host_ns > MAX_SAMPLE_AGE_NS {
            return Err(format!(
                "calibrated host time {host_ns} ns is not within {MAX_SAMPLE_AGE_NS} ns before \
                 CLOCK_MONOTONIC {now_ns} ns"
            ));
        }
        if max_deviation_ns > MAX_SAMPLE_DEVIATION_NS {
            return Err(format!(
                "calibration deviation {max_deviation_ns} ns is above \
                 {MAX_SAMPLE_DEVIATION_NS} ns"
            ));
        }
        Ok(Self {
            device_tick,
            host_ns,
            max_deviation_ns,
        })
    }

    /// Host time (ns, `CLOCK_MONOTONIC`) of device tick `tick`, ticks of `period_ns`.
    pub fn host_ns_of(&self, tick: u64, period_ns: f32) -> u64 {
        // A signed tick difference: passes lie before the sample (it is read after the
        // frame's readback); wrapping keeps a counter that wrapped in between right.
        let ticks = tick.wrapping_sub(self.device_tick) as i64;
        let ns = (ticks as f64 * f64::from(period_ns)).round() as i64;
        self.host_ns.saturating_add_signed(ns)
    }
}

/// A GPU pass placed on the host's `CLOCK_MONOTONIC` (nanoseconds since boot).
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct PassOnHost {
    pub stage: &'static str,
    pub start_ns: u64,
    pub end_ns: u64,
}

/// The host's `CLOCK_MONOTONIC` now, nanoseconds (the clock `std::time::Instant` reads on
/// Linux; std does not expose its value, hence `libc`).
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec and CLOCK_MONOTONIC exists on every Linux
    // kernel; the call writes only through the pointer it is given.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Reads calibrated timestamps on the device the context opened with the extension.
#[cfg(feature = "vulkan-calibrated")]
pub(crate) enum Calibrator {
    Khr(ash::khr::calibrated_timestamps::Device),
    Ext(ash::ext::calibrated_timestamps::Device),
}

#[cfg(feature = "vulkan-calibrated")]
impl Calibrator {
    /// Device tick and `CLOCK_MONOTONIC` at one instant, or `None` when the driver fails or
    /// returns a sample [`ClockSample::checked`] refuses.
    pub(crate) fn sample(&self) -> Option<ClockSample> {
        self.read().ok()
    }

    /// [`Self::sample`], saying why there is none.
    fn read(&self) -> Result<ClockSample, String> {
        use ash::vk;
        let infos = [
            vk::TimeDomainKHR::DEVICE,
            vk::TimeDomainKHR::CLOCK_MONOTONIC,
        ]
        .map(|d| vk::CalibratedTimestampInfoKHR::default().time_domain(d));
        // SAFETY: the device was created with this calibrated-timestamps extension enabled
        // and both time domains were reported calibrateable for it; the context keeps the
        // device alive as long as this calibrator.
        let result = unsafe {
            match self {
                Calibrator::Khr(d) => d.get_calibrated_timestamps(&infos),
                Calibrator::Ext(d) => d.get_calibrated_timestamps(&infos),
            }
        };
        let (ticks, max_deviation_ns) =
            result.map_err(|e| format!("vkGetCalibratedTimestamps: {e}"))?;
        let now_ns = monotonic_ns();
        match ticks[..] {
            [device_tick, host_ns] => {
                ClockSample::checked(device_tick, host_ns, max_deviation_ns, now_ns)
            }
            _ => Err(format!("{} timestamps for 2 time domains", ticks.len())),
        }
    }
}

/// A device opened for `desc`, its queue, the host clock status and (when calibrated) the
/// calibrator. `calibrate = false` opens the plain wgpu way (the fallback, also for tests).
pub(crate) struct Opened {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub clock: HostClock,
    #[cfg(feature = "vulkan-calibrated")]
    pub calibrator: Option<Calibrator>,
}

pub(crate) fn open_device(
    adapter: &wgpu::Adapter,
    desc: &wgpu::DeviceDescriptor<'_>,
    calibrate: bool,
) -> Result<Opened, wgpu::RequestDeviceError> {
    #[cfg(feature = "vulkan-calibrated")]
    let reason = if calibrate {
        match calibrated::open(adapter, desc) {
            Ok(opened) => return Ok(opened),
            Err(reason) => reason,
        }
    } else {
        "calibration not requested".to_string()
    };
    #[cfg(not(feature = "vulkan-calibrated"))]
    let reason = if calibrate {
        "built without the vulkan-calibrated feature".to_string()
    } else {
        "calibration not requested".to_string()
    };
    let (device, queue) = pollster::block_on(adapter.request_device(desc))?;
    Ok(Opened {
        device,
        queue,
        clock: HostClock::Uncalibrated { reason },
        #[cfg(feature = "vulkan-calibrated")]
        calibrator: None,
    })
}

#[cfg(feature = "vulkan-calibrated")]
mod calibrated {
    use super::{Calibrator, HostClock, Opened};
    use ash::vk;
    use wgpu::hal::api::Vulkan;

    /// Opens `adapter` through wgpu-hal with a calibrated-timestamps extension enabled, or
    /// says why it cannot.
    pub(super) fn open(
        adapter: &wgpu::Adapter,
        desc: &wgpu::DeviceDescriptor<'_>,
    ) -> Result<Opened, String> {
        // SAFETY: the hal adapter is only read here and used to open a device with wgpu's own
        // extension list plus one extension the adapter reports, within the callback's rules
        // (nothing removed, no feature turned off); the device goes straight back to wgpu.
        let (open, extension) = unsafe {
            let hal = adapter
                .as_hal::<Vulkan>()
                .ok_or_else(|| "not a Vulkan adapter".to_string())?;
            let caps = hal.physical_device_capabilities();
            let extension = if caps.supports_extension(ash::khr::calibrated_timestamps::NAME) {
                ash::khr::calibrated_timestamps::NAME
            } else if caps.supports_extension(ash::ext::calibrated_timestamps::NAME) {
                ash::ext::calibrated_timestamps::NAME
            } else {
                return Err("the adapter has no VK_KHR/EXT_calibrated_timestamps".into());
            };
            let shared = hal.shared_instance();
            let domains = ash::ext::calibrated_timestamps::Instance::new(
                shared.entry(),
                shared.raw_instance(),
            )
            .get_physical_device_calibrateable_time_domains(hal.raw_physical_device())
            .map_err(|e| format!("time domains: {e}"))?;
            for needed in [
                vk::TimeDomainKHR::DEVICE,
                vk::TimeDomainKHR::CLOCK_MONOTONIC,
            ] {
                if !domains.contains(&needed) {
                    return Err(format!(
                        "the adapter cannot calibrate the {needed:?} time domain"
                    ));
                }
            }
            let open = hal
                .open_with_callback(
                    desc.required_features,
                    &desc.required_limits,
                    &desc.memory_hints,
                    Some(add_extension(extension)),
                )
                .map_err(|e| format!("opening the device with {extension:?}: {e}"))?;
            (open, extension)
        };
        // SAFETY: `open` was created from this adapter's hal handle with `desc`'s features.
        let (device, queue) = unsafe { adapter.create_device_from_hal(open, desc) }
            .map_err(|e| format!("wrapping the hal device: {e}"))?;
        let name = extension.to_string_lossy().into_owned();
        // SAFETY: the raw ash handles belong to the device just created, which the context
        // keeps alive beside the calibrator.
        let calibrator = unsafe {
            let hal = device
                .as_hal::<Vulkan>()
                .ok_or_else(|| "the new device is not a Vulkan device".to_string())?;
            let (instance, raw) = (hal.shared_instance().raw_instance(), hal.raw_device());
            if extension == ash::khr::calibrated_timestamps::NAME {
                Calibrator::Khr(ash::khr::calibrated_timestamps::Device::new(instance, raw))
            } else {
                Calibrator::Ext(ash::ext::calibrated_timestamps::Device::new(instance, raw))
            }
        };
        if let Err(reason) = calibrator.read() {
            return Err(format!("{name}: {reason}"));
        }
        Ok(Opened {
            device,
            queue,
            clock: HostClock::Calibrated { extension: name },
            calibrator: Some(calibrator),
        })
    }

    /// The device-creation callback that adds `extension` to wgpu's list.
    fn add_extension(
        extension: &'static std::ffi::CStr,
    ) -> Box<wgpu::hal::vulkan::CreateDeviceCallback<'static>> {
        Box::new(move |args| {
            if !args.extensions.contains(&extension) {
                args.extensions.push(extension);
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_map_around_the_sample_in_both_directions() {
        let s = ClockSample {
            device_tick: 1_000,
            host_ns: 5_000_000,
            max_deviation_ns: 10,
        };
        assert_eq!(s.host_ns_of(1_000, 1.0), 5_000_000);
        assert_eq!(s.host_ns_of(500, 2.0), 4_999_000);
        assert_eq!(s.host_ns_of(1_250, 4.0), 5_001_000);
        // A counter that wrapped between the pass and the sample.
        let w = ClockSample {
            device_tick: 5,
            ..s
        };
        assert_eq!(w.host_ns_of(u64::MAX - 4, 1.0), 5_000_000 - 10);
    }

    /// A driver's sample is refused, naming the value, when its host time lies after the
    /// host clock or long before it, or its deviation is too wide to place a pass.
    #[test]
    fn implausible_driver_samples_are_refused() {
        let now = 10_000_000_000;
        let ok = ClockSample::checked(7, now - 5_000, 20, now).unwrap();
        assert_eq!(
            (ok.device_tick, ok.host_ns, ok.max_deviation_ns),
            (7, now - 5_000, 20)
        );
        for (host_ns, deviation, says) in [
            (now + 1, 20, "not within"),
            (0, 20, "not within"),
            (u64::MAX, 20, "not within"),
            (now - MAX_SAMPLE_AGE_NS - 1, 20, "not within"),
            (now, MAX_SAMPLE_DEVIATION_NS + 1, "deviation 1000001 ns"),
            (now, u64::MAX, "deviation"),
        ] {
            let err = ClockSample::checked(7, host_ns, deviation, now).unwrap_err();
            assert!(err.contains(says), "{host_ns} {deviation}: {err}");
        }
    }

    #[test]
    fn monotonic_ns_is_monotonic_and_matches_instant_steps() {
        let (a, i) = (monotonic_ns(), std::time::Instant::now());
        std::thread::sleep(std::time::Duration::from_millis(2));
        let (b, di) = (monotonic_ns(), i.elapsed());
        assert!(b > a);
        let d = (b - a) as i128 - di.as_nanos() as i128;
        assert!(d.abs() < 1_000_000, "{d} ns apart");
    }
}
