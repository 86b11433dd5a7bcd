//! Rendering benchmark of the scene simulator: steps per second, one step being one frame of
//! each of the scene's cameras (the built-in scenes: two 848x480 D435 views), for the clean
//! and the realistic variant of each built-in experiment. Target: >= 90 steps/s.
//!
//! Besides wall time it reports the process CPU time per step (all threads, from
//! `/proc/self/stat`, Linux USER_HZ = 100): on a shared machine the wall rate depends on the
//! load, `threads / cpu_ms_per_step` is the rate an idle machine would give.
//!
//! `cargo bench --bench scene_render [-- SECONDS_PER_SCENE [THREADS [NAME_FILTER]]]`

use hapcloud::scene::{Scene, Simulator, builtin};
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let seconds: f64 = args.first().map_or(Ok(2.0), |s| s.parse())?;
    let threads: Option<usize> = args.get(1).map(|s| s.parse()).transpose()?;
    let filter = args.get(2).cloned().unwrap_or_default();
    println!(
        "{:<28} {:>6} {:>9} {:>9} {:>12} {:>13}",
        "scene", "steps", "steps/s", "ms/step", "cpu ms/step", "valid px/view"
    );
    for name in builtin::names().into_iter().filter(|n| n.contains(&filter)) {
        let scene = Scene::from_builtin(&name)?;
        let mut sim = Simulator::new(&scene)?;
        if let Some(n) = threads {
            sim = sim.with_threads(n);
        }
        let cams = sim.cameras().len() as u32;
        let rate = sim.cameras()[0].rate_hz;
        let frames_in_scene = (sim.duration_s() * rate) as u64;
        // Warm up (allocations, caches).
        for c in 0..cams {
            if let Some(t) = sim.timing(c, 0) {
                std::hint::black_box(sim.frame(&t));
            }
        }
        let cpu0 = cpu_seconds()?;
        let start = Instant::now();
        let mut steps = 0u64;
        let mut valid = 0usize;
        let mut views = 0usize;
        while start.elapsed().as_secs_f64() < seconds {
            let index = steps % frames_in_scene.max(1);
            for c in 0..cams {
                if let Some(t) = sim.timing(c, index) {
                    let f = sim.frame(&t);
                    if steps == 0 {
                        valid += f.frame.cloud().finite_count();
                        views += 1;
                    }
                }
            }
            steps += 1;
        }
        let dt = start.elapsed().as_secs_f64();
        let cpu = cpu_seconds()? - cpu0;
        println!(
            "{:<28} {:>6} {:>9.1} {:>9.2} {:>12.2} {:>13}",
            name,
            steps,
            steps as f64 / dt,
            1e3 * dt / steps as f64,
            1e3 * cpu / steps as f64,
            valid / views.max(1)
        );
    }
    Ok(())
}

/// User plus system CPU time of this process (all threads), seconds.
fn cpu_seconds() -> anyhow::Result<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat")?;
    let after_name = stat
        .rsplit_once(')')
        .ok_or_else(|| anyhow::anyhow!("unexpected /proc/self/stat"))?
        .1;
    // Fields after the name start at field 3 (state); utime and stime are fields 14 and 15.
    let fields: Vec<&str> = after_name.split_whitespace().collect();
    let ticks: f64 = fields[11].parse::<f64>()? + fields[12].parse::<f64>()?;
    Ok(ticks / 100.0)
}
