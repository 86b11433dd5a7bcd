//! Per-stage GPU time from timestamp queries.
//!
//! Each stage records its dispatches in one compute pass; the pass writes a timestamp at its
//! beginning and end (`ComputePassTimestampWrites`, feature `TIMESTAMP_QUERY`). The resolved
//! ticks are copied into the frame's single readback buffer, so timing adds no extra readback.
//! Without the feature a [`StageTimer`] is not created and stages report no GPU time.

use super::clock::{ClockSample, PassOnHost};
use super::context::{GpuContext, GpuError};

/// Bytes per resolved timestamp.
const TICK_BYTES: u64 = 8;

/// GPU time of one stage of a frame.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct StageTime {
    pub stage: &'static str,
    pub gpu_ms: f64,
}

/// The raw timestamps of one stage's pass: device ticks at its beginning and end.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PassTicks {
    pub stage: &'static str,
    pub begin: u64,
    pub end: u64,
}

impl PassTicks {
    /// The pass's duration, ticks of `period_ns`.
    pub fn time(&self, period_ns: f32) -> StageTime {
        StageTime {
            stage: self.stage,
            gpu_ms: self.end.saturating_sub(self.begin) as f64 * f64::from(period_ns) * 1e-6,
        }
    }

    /// The pass on the host's `CLOCK_MONOTONIC`, through a calibrated `sample`.
    pub fn on_host(&self, sample: &ClockSample, period_ns: f32) -> PassOnHost {
        PassOnHost {
            stage: self.stage,
            start_ns: sample.host_ns_of(self.begin, period_ns),
            end_ns: sample.host_ns_of(self.end, period_ns),
        }
    }
}

/// Timestamp queries for a fixed list of stages (two per stage: begin, end).
pub struct StageTimer {
    query_set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    stages: Vec<&'static str>,
    period_ns: f32,
}

impl StageTimer {
    /// A timer for `stages`, or `None` when the device has no timestamp queries.
    pub fn new(
        ctx: &GpuContext,
        label: &str,
        stages: &[&'static str],
    ) -> Result<Option<Self>, GpuError> {
        let Some(period_ns) = ctx.timestamp_period_ns() else {
            return Ok(None);
        };
        let count = 2 * stages.len() as u32;
        ctx.scoped(label, |device| {
            Some(Self {
                query_set: device.create_query_set(&wgpu::QuerySetDescriptor {
                    label: Some(&format!("{label} timestamps")),
                    ty: wgpu::QueryType::Timestamp,
                    count,
                }),
                resolve: ctx.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(&format!("{label} timestamp resolve")),
                    size: u64::from(count) * TICK_BYTES,
                    usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                    mapped_at_creation: false,
                }),
                stages: stages.to_vec(),
                period_ns,
            })
        })
    }

    /// Timestamp writes for the compute pass of stage number `stage`.
    pub fn pass_writes(&self, stage: usize) -> wgpu::ComputePassTimestampWrites<'_> {
        wgpu::ComputePassTimestampWrites {
            query_set: &self.query_set,
            beginning_of_pass_write_index: Some(2 * stage as u32),
            end_of_pass_write_index: Some(2 * stage as u32 + 1),
        }
    }

    /// Bytes the resolved timestamps occupy in a readback buffer.
    pub fn readback_bytes(&self) -> u64 {
        self.resolve.size()
    }

    /// Resolves the queries and copies the ticks into `dst` at `dst_offset` (a multiple of 4).
    pub fn resolve_into(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        dst: &wgpu::Buffer,
        dst_offset: u64,
    ) {
        let count = 2 * self.stages.len() as u32;
        encoder.resolve_query_set(&self.query_set, 0..count, &self.resolve, 0);
        encoder.copy_buffer_to_buffer(&self.resolve, 0, dst, dst_offset, self.resolve.size());
    }

    /// Stage times from the resolved ticks (`bytes` = the [`Self::readback_bytes`] region).
    pub fn read(&self, bytes: &[u8]) -> Vec<StageTime> {
        self.ticks(bytes)
            .iter()
            .map(|t| t.time(self.period_ns))
            .collect()
    }

    /// The raw begin and end ticks of each stage's pass (`bytes` as for [`Self::read`]).
    pub fn ticks(&self, bytes: &[u8]) -> Vec<PassTicks> {
        let ticks: Vec<u64> = bytes
            .chunks_exact(TICK_BYTES as usize)
            .map(|c| u64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
            .collect();
        self.stages
            .iter()
            .enumerate()
            .map(|(i, stage)| PassTicks {
                stage,
                begin: ticks.get(2 * i).copied().unwrap_or(0),
                end: ticks.get(2 * i + 1).copied().unwrap_or(0),
            })
            .collect()
    }
}
