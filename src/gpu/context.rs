//! The wgpu device every GPU stage shares: adapter choice, error capture, readback.
//!
//! The context knows no stage. It opens one Vulkan adapter, chosen by the `WGPU_ADAPTER_NAME`
//! environment variable (case-insensitive substring of the adapter name) or, without it, the
//! best available one (discrete GPU, then integrated, virtual, CPU/software). Lavapipe (Mesa's
//! software Vulkan) is a CPU adapter and is used when nothing better exists.
//!
//! wgpu reports validation and out-of-memory problems asynchronously. The default handler
//! panics; this context installs its own handler that records uncaptured errors, and
//! [`GpuContext::scoped`] wraps work in error scopes so that every problem comes back as a
//! [`GpuError`], never a panic.
//!
//! Timestamp queries ([`wgpu::Features::TIMESTAMP_QUERY`], supported by lavapipe) are enabled
//! when the adapter has them; [`GpuContext::timestamp_period_ns`] is `None` otherwise and
//! stages then report no GPU times. With the `vulkan-calibrated` feature the device is opened
//! with calibrated timestamps where the adapter has them ([`super::clock`]), so those times can
//! be placed on the host clock ([`GpuContext::host_clock`], [`GpuContext::clock_sample`]).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

#[cfg(feature = "vulkan-calibrated")]
use super::clock::Calibrator;
use super::clock::{ClockSample, HostClock, open_device};

/// Environment variable that selects the adapter by (case-insensitive) name substring.
pub const ADAPTER_ENV: &str = "WGPU_ADAPTER_NAME";

/// What to tell a user whose machine has no Vulkan device.
pub const SOFTWARE_VULKAN_HINT: &str = "install Mesa's software Vulkan (lavapipe): \
     `apt-get install mesa-vulkan-drivers libvulkan1` (add `vulkan-tools` for `vulkaninfo`), \
     or run with `--backend cpu`";

/// Everything that can go wrong on the GPU side.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error("no Vulkan adapter found; {SOFTWARE_VULKAN_HINT}")]
    NoVulkanDevice,
    #[error(
        "no Vulkan adapter name contains {wanted:?} (from {ADAPTER_ENV}); available: {available:?}"
    )]
    AdapterNotFound {
        wanted: String,
        available: Vec<String>,
    },
    #[error("could not open a device on adapter {adapter:?}: {message}")]
    RequestDevice { adapter: String, message: String },
    #[error("GPU validation error in {context}: {message}")]
    Validation { context: String, message: String },
    #[error("GPU out of memory in {context}")]
    OutOfMemory { context: String },
    #[error("internal GPU error in {context}: {message}")]
    Internal { context: String, message: String },
    #[error("GPU readback failed in {context}: {message}")]
    Readback { context: String, message: String },
    #[error("{what} needs {needed} bytes but the device allows at most {limit} bytes")]
    TooLarge {
        what: String,
        needed: u64,
        limit: u64,
    },
}

/// The adapter actually opened, as reported to users (`adapter` in JSON output).
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct AdapterSummary {
    pub name: String,
    pub device_type: String,
    pub driver: String,
}

/// The shared wgpu device and queue plus what stages need to know about them.
pub struct GpuContext {
    device: wgpu::Device,
    queue: wgpu::Queue,
    adapter: AdapterSummary,
    timestamp_period_ns: Option<f32>,
    host_clock: HostClock,
    #[cfg(feature = "vulkan-calibrated")]
    calibrator: Option<Calibrator>,
    uncaptured: Arc<Mutex<Vec<wgpu::Error>>>,
    created: CreatedCounters,
    submissions: AtomicU64,
}

/// How many GPU objects the stages created through [`GpuContext::create_buffer`],
/// [`GpuContext::create_texture`] and [`GpuContext::create_bind_group`] since the context
/// opened: a frame that creates none allocates nothing on the device.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct Created {
    /// Buffers and textures.
    pub buffers: u64,
    pub bind_groups: u64,
}

impl std::ops::Sub for Created {
    type Output = Created;
    fn sub(self, earlier: Created) -> Created {
        Created {
            buffers: self.buffers - earlier.buffers,
            bind_groups: self.bind_groups - earlier.bind_groups,
        }
    }
}

#[derive(Default)]
struct CreatedCounters {
    buffers: AtomicU64,
    bind_groups: AtomicU64,
}

fn device_rank(t: wgpu::DeviceType) -> u8 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Cpu => 3,
        wgpu::DeviceType::Other => 4,
    }
}

/// A driver's timestamp period, ns per tick, if pass times can be computed from it (a zero,
/// negative, infinite or NaN period would turn every tick count into a wrong duration).
fn usable_period(period_ns: f32) -> Option<f32> {
    (period_ns.is_finite() && period_ns > 0.0).then_some(period_ns)
}

impl GpuContext {
    /// Opens the adapter named by `WGPU_ADAPTER_NAME`, or the best available one.
    pub fn new() -> Result<Self, GpuError> {
        let wanted = std::env::var(ADAPTER_ENV).ok().filter(|s| !s.is_empty());
        Self::with_adapter_name(wanted.as_deref())
    }

    /// Opens the first adapter whose name contains `wanted` (case-insensitive), or the best
    /// available one when `wanted` is `None`; with calibrated timestamps where it can.
    pub fn with_adapter_name(wanted: Option<&str>) -> Result<Self, GpuError> {
        Self::open(wanted, true)
    }

    /// [`Self::with_adapter_name`] with a choice: `calibrate_clock = false` opens the device
    /// the plain wgpu way, GPU times as durations only.
    pub fn open(wanted: Option<&str>, calibrate_clock: bool) -> Result<Self, GpuError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
            backends: wgpu::Backends::VULKAN,
            // No indirect-call validation: wgpu would add a compute dispatch and barriers
            // before every indirect dispatch to check its arguments (measured on an H100: the
            // voxel sort's ~20 indirect dispatches took 0.29 ms with it, 0.11 ms without).
            // Every indirect argument here is written by our own shaders from a count the
            // host bounded (voxel: at most 2^22 table slots and MAX_POINTS points; cluster:
            // at most MAX_GPU_POINTS points), within WebGPU's default 65,535 workgroups per
            // dimension (compile-time checks in voxel.rs).
            // `WGPU_VALIDATION_INDIRECT_CALL=1` turns it back on.
            flags: wgpu::InstanceFlags::default()
                .difference(wgpu::InstanceFlags::VALIDATION_INDIRECT_CALL)
                .with_env(),
            ..wgpu::InstanceDescriptor::new_without_display_handle()
        });
        let mut adapters = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::VULKAN));
        if adapters.is_empty() {
            return Err(GpuError::NoVulkanDevice);
        }
        // Stable order: best device type first, then by name, so the choice is reproducible.
        adapters.sort_by_key(|a| {
            let info = a.get_info();
            (device_rank(info.device_type), info.name)
        });
        let adapter = match wanted {
            None => adapters.swap_remove(0),
            Some(w) => {
                let needle = w.to_lowercase();
                match adapters
                    .iter()
                    .position(|a| a.get_info().name.to_lowercase().contains(&needle))
                {
                    Some(i) => adapters.swap_remove(i),
                    None => {
                        return Err(GpuError::AdapterNotFound {
                            wanted: w.to_string(),
                            available: adapters.iter().map(|a| a.get_info().name).collect(),
                        });
                    }
                }
            }
        };
        let info = adapter.get_info();
        let features = adapter.features() & wgpu::Features::TIMESTAMP_QUERY;
        let desc = wgpu::DeviceDescriptor {
            label: Some("hapcloud device"),
            required_features: features,
            required_limits: adapter.limits(),
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        };
        let opened =
            open_device(&adapter, &desc, calibrate_clock).map_err(|e| GpuError::RequestDevice {
                adapter: info.name.clone(),
                message: e.to_string(),
            })?;
        let (device, queue) = (opened.device, opened.queue);
        let uncaptured = Arc::new(Mutex::new(Vec::new()));
        let sink = Arc::clone(&uncaptured);
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            if let Ok(mut v) = sink.lock() {
                v.push(e);
            }
        }));
        let timestamp_period_ns = features
            .contains(wgpu::Features::TIMESTAMP_QUERY)
            .then(|| queue.get_timestamp_period())
            .and_then(usable_period);
        Ok(Self {
            device,
            queue,
            adapter: AdapterSummary {
                name: info.name,
                device_type: format!("{:?}", info.device_type),
                driver: format!("{} {}", info.driver, info.driver_info)
                    .trim()
                    .to_string(),
            },
            timestamp_period_ns,
            host_clock: match timestamp_period_ns {
                Some(_) => opened.clock,
                None => HostClock::Uncalibrated {
                    reason: "no timestamp queries".into(),
                },
            },
            #[cfg(feature = "vulkan-calibrated")]
            calibrator: opened.calibrator.filter(|_| timestamp_period_ns.is_some()),
            uncaptured,
            created: CreatedCounters::default(),
            submissions: AtomicU64::new(0),
        })
    }

    pub fn device(&self) -> &wgpu::Device {
        &self.device
    }

    pub fn queue(&self) -> &wgpu::Queue {
        &self.queue
    }

    pub fn adapter(&self) -> &AdapterSummary {
        &self.adapter
    }

    /// Nanoseconds per timestamp tick, or `None` when the device has no timestamp queries
    /// or reports a period that is not a positive finite number.
    pub fn timestamp_period_ns(&self) -> Option<f32> {
        self.timestamp_period_ns
    }

    /// Whether GPU pass times can be placed on the host's `CLOCK_MONOTONIC`, and how.
    pub fn host_clock(&self) -> &HostClock {
        &self.host_clock
    }

    /// A device tick and `CLOCK_MONOTONIC` read at one instant, `None` when the clock is not
    /// calibrated ([`Self::host_clock`]) or the driver failed this time.
    pub fn clock_sample(&self) -> Option<ClockSample> {
        #[cfg(feature = "vulkan-calibrated")]
        return self.calibrator.as_ref().and_then(Calibrator::sample);
        #[cfg(not(feature = "vulkan-calibrated"))]
        None
    }

    /// Creates a buffer, counted in [`Self::created`].
    pub fn create_buffer(&self, desc: &wgpu::BufferDescriptor<'_>) -> wgpu::Buffer {
        self.created.buffers.fetch_add(1, Ordering::Relaxed);
        self.device.create_buffer(desc)
    }

    /// Creates a texture, counted in [`Self::created`] with the buffers.
    pub fn create_texture(&self, desc: &wgpu::TextureDescriptor<'_>) -> wgpu::Texture {
        self.created.buffers.fetch_add(1, Ordering::Relaxed);
        self.device.create_texture(desc)
    }

    /// Creates a bind group, counted in [`Self::created`].
    pub fn create_bind_group(&self, desc: &wgpu::BindGroupDescriptor<'_>) -> wgpu::BindGroup {
        self.created.bind_groups.fetch_add(1, Ordering::Relaxed);
        self.device.create_bind_group(desc)
    }

    /// GPU objects created so far (all users of this context together).
    pub fn created(&self) -> Created {
        Created {
            buffers: self.created.buffers.load(Ordering::Relaxed),
            bind_groups: self.created.bind_groups.load(Ordering::Relaxed),
        }
    }

    /// Submissions [`Self::submit_and_read`] made so far (all users of this context).
    pub fn submissions(&self) -> u64 {
        self.submissions.load(Ordering::Relaxed)
    }

    /// Runs `f` inside validation, out-of-memory and internal error scopes and returns the
    /// first error any of them caught (or one the uncaptured handler recorded meanwhile).
    /// `context` names the work in the error message.
    pub fn scoped<T>(
        &self,
        context: &str,
        f: impl FnOnce(&wgpu::Device) -> T,
    ) -> Result<T, GpuError> {
        let internal = self.device.push_error_scope(wgpu::ErrorFilter::Internal);
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let value = f(&self.device);
        let errors = [
            pollster::block_on(validation.pop()),
            pollster::block_on(oom.pop()),
            pollster::block_on(internal.pop()),
        ];
        if let Some(e) = errors.into_iter().flatten().next() {
            return Err(convert(context, e));
        }
        self.take_uncaptured(context)?;
        Ok(value)
    }

    /// Returns the oldest error the uncaptured-error handler recorded, if any.
    pub fn take_uncaptured(&self, context: &str) -> Result<(), GpuError> {
        let first = match self.uncaptured.lock() {
            Ok(mut v) if !v.is_empty() => Some(v.remove(0)),
            _ => None,
        };
        match first {
            Some(e) => Err(convert(context, e)),
            None => Ok(()),
        }
    }

    /// Errors unless a buffer of `bytes` fits the device's storage-binding and buffer limits.
    pub fn check_storage_size(&self, what: &str, bytes: u64) -> Result<(), GpuError> {
        let limits = self.device.limits();
        let limit = limits
            .max_buffer_size
            .min(limits.max_storage_buffer_binding_size);
        if bytes > limit {
            return Err(GpuError::TooLarge {
                what: what.to_string(),
                needed: bytes,
                limit,
            });
        }
        Ok(())
    }

    /// Submits `commands`, waits for this submission (not for the device: another thread's
    /// later submission on the same queue is not waited for), maps the first `bytes` of the
    /// `readback` buffer (which `commands` must have filled; usage `MAP_READ | COPY_DST`;
    /// `bytes` a multiple of 4 and nonzero) and hands them to `read`. This is the one blocking
    /// readback of a frame; errors come back as [`GpuError`].
    pub fn submit_and_read<R>(
        &self,
        context: &str,
        commands: wgpu::CommandBuffer,
        (readback, bytes): (&wgpu::Buffer, u64),
        read: impl FnOnce(&[u8]) -> R,
    ) -> Result<R, GpuError> {
        let (tx, rx) = std::sync::mpsc::channel();
        self.submissions.fetch_add(1, Ordering::Relaxed);
        let submission = self.scoped(context, |_| {
            let submission = self.queue.submit([commands]);
            readback.map_async(wgpu::MapMode::Read, ..bytes, move |r| {
                // The receiver lives until this function returns; a send error cannot happen
                // while it waits, and afterwards nobody needs the result.
                let _ = tx.send(r);
            });
            submission
        })?;
        let readback_err = |message: String| GpuError::Readback {
            context: context.to_string(),
            message,
        };
        // The mapping completes with the submission that last used the buffer: this one.
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(submission),
                timeout: None,
            })
            .map_err(|e| readback_err(e.to_string()))?;
        rx.recv()
            .map_err(|e| readback_err(e.to_string()))?
            .map_err(|e| readback_err(e.to_string()))?;
        let value = {
            let view = readback
                .get_mapped_range(..bytes)
                .map_err(|e| readback_err(e.to_string()))?;
            read(&view)
        };
        readback.unmap();
        self.take_uncaptured(context)?;
        Ok(value)
    }
}

fn convert(context: &str, e: wgpu::Error) -> GpuError {
    let context = context.to_string();
    match e {
        wgpu::Error::OutOfMemory { .. } => GpuError::OutOfMemory { context },
        wgpu::Error::Validation { description, .. } => GpuError::Validation {
            context,
            message: description,
        },
        wgpu::Error::Internal { description, .. } => GpuError::Internal {
            context,
            message: description,
        },
    }
}

/// The context GPU tests share (opening a device per test is slow on lavapipe). GPU tests
/// need a Vulkan device; CI installs lavapipe (see .ci/run).
#[cfg(test)]
pub(crate) fn test_context() -> &'static GpuContext {
    static CTX: std::sync::OnceLock<GpuContext> = std::sync::OnceLock::new();
    CTX.get_or_init(|| GpuContext::new().unwrap_or_else(|e| panic!("GPU tests need Vulkan: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ctx() -> &'static GpuContext {
        test_context()
    }

    #[test]
    fn only_a_positive_finite_timestamp_period_is_used() {
        assert_eq!(usable_period(1.0), Some(1.0));
        assert_eq!(usable_period(41.666), Some(41.666));
        for bad in [0.0, -1.0, f32::INFINITY, f32::NEG_INFINITY, f32::NAN] {
            assert_eq!(usable_period(bad), None, "{bad}");
        }
    }

    #[test]
    fn opens_an_adapter_and_reports_its_name() {
        let ctx = ctx();
        assert!(!ctx.adapter().name.is_empty());
    }

    #[test]
    fn unknown_adapter_name_is_an_error_listing_the_available_ones() {
        let err = GpuContext::with_adapter_name(Some("no-such-adapter-xyz"))
            .err()
            .expect("must fail");
        match err {
            GpuError::AdapterNotFound { available, .. } => assert!(!available.is_empty()),
            other => panic!("unexpected {other}"),
        }
    }

    #[test]
    fn validation_errors_are_results_not_panics() {
        let ctx = ctx();
        // MAP_READ together with STORAGE is invalid without MAPPABLE_PRIMARY_BUFFERS.
        let err = ctx
            .scoped("bad buffer", |device| {
                device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("invalid usage"),
                    size: 16,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::STORAGE,
                    mapped_at_creation: false,
                })
            })
            .expect_err("validation error");
        assert!(matches!(err, GpuError::Validation { .. }), "{err}");
        // The device stays usable afterwards.
        ctx.scoped("good buffer", |device| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("valid"),
                size: 16,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            })
        })
        .unwrap();
    }

    #[test]
    fn readback_round_trip() {
        let ctx = ctx();
        let data: Vec<u32> = (0..64).collect();
        let (src, dst) = ctx
            .scoped("buffers", |device| {
                let src = device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("test src"),
                    size: 256,
                    usage: wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                let dst = device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("test readback"),
                    size: 256,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                (src, dst)
            })
            .unwrap();
        ctx.queue()
            .write_buffer(&src, 0, bytemuck::cast_slice(&data));
        let mut encoder = ctx
            .device()
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("test copy"),
            });
        encoder.copy_buffer_to_buffer(&src, 0, &dst, 0, 256);
        let back: Vec<u32> = ctx
            .submit_and_read("test", encoder.finish(), (&dst, 256), |b| {
                bytemuck::cast_slice(b).to_vec()
            })
            .unwrap();
        assert_eq!(back, data);
    }

    #[test]
    fn oversized_buffers_are_rejected_before_allocation() {
        let ctx = ctx();
        assert!(matches!(
            ctx.check_storage_size("huge", u64::MAX),
            Err(GpuError::TooLarge { .. })
        ));
        ctx.check_storage_size("small", 1024).unwrap();
    }
}
