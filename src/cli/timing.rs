//! Stage timings of the one-stage commands (`hapcloud crop|voxel|cluster`), so all three report
//! the same keys: `read` and `write` (wall), the stage on the CPU (wall), and on the GPU
//! `gpu_init` (context and pipelines), `<stage>_wall` (submit to readback) and `<stage>` from the
//! GPU timestamp queries (with one key per pass when a stage has several).

use hapcloud::gpu::timing::StageTime;
use hapcloud::gpu::{Backend, GpuContext};
use std::collections::BTreeMap;
use std::time::Instant;

/// Milliseconds per named step, printed as text or JSON.
#[derive(Default, serde::Serialize)]
#[serde(transparent)]
pub struct Timings(BTreeMap<String, f64>);

impl Timings {
    /// Runs `step` and records its wall time under `key`.
    pub fn time<T>(&mut self, key: &str, step: impl FnOnce() -> T) -> T {
        let t = Instant::now();
        let out = step();
        self.0.insert(key.into(), t.elapsed().as_secs_f64() * 1e3);
        out
    }

    /// One line per step, `  key: 1.234 ms`.
    pub fn print(&self) {
        for (step, t) in &self.0 {
            println!("  {step}: {t:.3} ms");
        }
    }

    /// Runs one stage on `backend`. On the GPU, `gpu_new` opens the stage (timed as `gpu_init`
    /// with the context) and `gpu_run` runs it and returns its GPU timestamp passes. Returns
    /// the stage's output and, on the GPU, the adapter's name.
    pub fn run_stage<S, T>(
        &mut self,
        backend: Backend,
        stage: &str,
        cpu: impl FnOnce() -> anyhow::Result<T>,
        gpu_new: impl FnOnce(&GpuContext) -> anyhow::Result<S>,
        gpu_run: impl FnOnce(&mut S, &GpuContext) -> anyhow::Result<(T, Vec<StageTime>)>,
    ) -> anyhow::Result<(T, Option<String>)> {
        match backend {
            Backend::Cpu => Ok((self.time(stage, cpu)?, None)),
            Backend::Gpu => {
                let (ctx, mut gpu_stage) = self.time("gpu_init", || {
                    let ctx = GpuContext::new()?;
                    let gpu_stage = gpu_new(&ctx)?;
                    anyhow::Ok((ctx, gpu_stage))
                })?;
                let (out, passes) =
                    self.time(&format!("{stage}_wall"), || gpu_run(&mut gpu_stage, &ctx))?;
                if !passes.is_empty() {
                    self.0
                        .insert(stage.into(), passes.iter().map(|p| p.gpu_ms).sum());
                }
                for pass in passes.iter().filter(|p| p.stage != stage) {
                    self.0.insert(pass.stage.into(), pass.gpu_ms);
                }
                Ok((out, Some(ctx.adapter().name.clone())))
            }
        }
    }
}
