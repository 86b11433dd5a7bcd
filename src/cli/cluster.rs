//! `hapcloud cluster`: Euclidean cluster extraction of one cloud, shaped like PCL's
//! `pcl_cluster_extraction` (same tolerance / min / max meaning, clusters largest first).

use anyhow::Context;
use hapcloud::gpu::{Backend, GpuContext};
use hapcloud::io::{self, Encoding};
use hapcloud::perception::cluster::{ClusterConfig, GpuClusterer, cluster_cpu};
use serde_json::json;
use std::path::PathBuf;
use std::time::Instant;

#[derive(clap::Args)]
pub struct Args {
    /// Input cloud (.pcd or .ply).
    input: PathBuf,
    /// Neighbour distance in metres: points closer than this are connected (PCL -tolerance).
    #[arg(long, default_value_t = 0.02)]
    tolerance: f64,
    /// Smallest cluster kept, points (PCL -min).
    #[arg(long, default_value_t = 100)]
    min_size: u32,
    /// Largest cluster kept, points (PCL -max).
    #[arg(long, default_value_t = 25_000)]
    max_size: u32,
    /// Write one binary PCD per kept cluster, `cluster_<k>.pcd`, k = 0 for the largest.
    #[arg(long)]
    out_dir: Option<PathBuf>,
    #[arg(long, value_enum, default_value_t = Backend::Gpu)]
    backend: Backend,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
}

fn ms(since: Instant) -> f64 {
    since.elapsed().as_secs_f64() * 1e3
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let config = ClusterConfig {
        // PCL's tool parses a double and its extractor casts it to float.
        tolerance_m: args.tolerance as f32,
        min_cluster_points: args.min_size,
        max_cluster_points: args.max_size,
        ..ClusterConfig::default()
    };
    config.validate()?;
    let mut timings = serde_json::Map::new();

    let t = Instant::now();
    let cloud = io::read_cloud(&args.input)?;
    timings.insert("read".into(), json!(ms(t)));

    let mut adapter = None;
    let mut submissions = None;
    let clustering = match args.backend {
        Backend::Cpu => {
            let t = Instant::now();
            let c = cluster_cpu(&cloud.points, &config)?;
            timings.insert("cluster".into(), json!(ms(t)));
            c
        }
        Backend::Gpu => {
            let t = Instant::now();
            let ctx = GpuContext::new()?;
            let mut clusterer = GpuClusterer::new(&ctx)?;
            timings.insert("gpu_init".into(), json!(ms(t)));
            let t = Instant::now();
            let (c, stats) = clusterer.cluster(&ctx, &cloud.points, &config)?;
            timings.insert("cluster_wall".into(), json!(ms(t)));
            if !stats.gpu_times.is_empty() {
                let total: f64 = stats.gpu_times.iter().map(|s| s.gpu_ms).sum();
                timings.insert("cluster".into(), json!(total));
            }
            for s in &stats.gpu_times {
                timings.insert(s.stage.into(), json!(s.gpu_ms));
            }
            adapter = Some(ctx.adapter().name.clone());
            submissions = Some(stats.submissions);
            c
        }
    };

    if let Some(dir) = &args.out_dir {
        let t = Instant::now();
        std::fs::create_dir_all(dir)
            .with_context(|| format!("creating output directory {}", dir.display()))?;
        for (k, part) in clustering.extract(&cloud).iter().enumerate() {
            io::write_cloud(
                &dir.join(format!("cluster_{k}.pcd")),
                part,
                Encoding::Binary,
            )?;
        }
        timings.insert("write".into(), json!(ms(t)));
    }

    let sizes = clustering.cluster_sizes();
    if args.json {
        let out = json!({
            "input": args.input,
            "points_in": cloud.len(),
            "points_finite": cloud.finite_count(),
            "clusters": sizes.len(),
            "cluster_sizes": sizes,
            "components": clustering.component_count(),
            "backend": args.backend,
            "adapter": adapter,
            "gpu_submissions": submissions,
            "timings_ms": timings,
        });
        println!("{out}");
    } else {
        println!(
            "{}: {} points ({} finite), {} clusters of sizes {:?} ({} backend{})",
            args.input.display(),
            cloud.len(),
            cloud.finite_count(),
            sizes.len(),
            sizes,
            args.backend,
            adapter.map(|a| format!(" on {a}")).unwrap_or_default()
        );
        let parts: Vec<String> = timings
            .iter()
            .map(|(k, v)| format!("{k} {:.3} ms", v.as_f64().unwrap_or(f64::NAN)))
            .collect();
        println!("timings: {}", parts.join(", "));
    }
    Ok(())
}
