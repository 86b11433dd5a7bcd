//! `hapcloud cluster`: Euclidean cluster extraction of one cloud, shaped like PCL's
//! `pcl_cluster_extraction` (same tolerance / min / max meaning, clusters largest first).

use super::timing::Timings;
use anyhow::Context;
use hapcloud::gpu::Backend;
use hapcloud::io::{self, Encoding};
use hapcloud::perception::cluster::{ClusterConfig, GpuClusterer, cluster_cpu};
use serde_json::json;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Input cloud (.pcd or .ply).
    input: PathBuf,
    /// Neighbour distance in metres: points closer than this are connected (PCL -tolerance;
    /// above 0, at most 100).
    #[arg(long, value_parser = super::numbers::distance, allow_negative_numbers = true, default_value_t = 0.02)]
    tolerance: f64,
    /// Smallest cluster kept, points (PCL -min).
    #[arg(long, default_value_t = 100, allow_negative_numbers = true)]
    min_size: u32,
    /// Largest cluster kept, points (PCL -max).
    #[arg(long, default_value_t = 25_000, allow_negative_numbers = true)]
    max_size: u32,
    /// Write one binary PCD per kept cluster, `cluster_<k>.pcd`, k = 0 for the largest.
    #[arg(long)]
    out_dir: Option<PathBuf>,
    #[arg(long, value_enum, default_value_t = Backend::Gpu)]
    backend: Backend,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    limit: super::InputLimit,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if args.min_size > args.max_size {
        anyhow::bail!(
            "--min-size {} exceeds --max-size {}",
            args.min_size,
            args.max_size
        );
    }
    let config = ClusterConfig {
        // PCL's tool parses a double and its extractor casts it to float.
        tolerance_m: args.tolerance as f32,
        min_cluster_points: args.min_size,
        max_cluster_points: args.max_size,
        ..ClusterConfig::default()
    };
    config.validate()?;
    let mut timings = Timings::default();
    let cloud = timings.time("read", || {
        io::read_cloud_within(&args.input, &args.limit.limits())
    })?;
    let ((clustering, submissions), adapter) = timings.run_stage(
        args.backend,
        "cluster",
        || Ok((cluster_cpu(&cloud.points, &config)?, None)),
        |ctx| Ok(GpuClusterer::new(ctx)?),
        |clusterer, ctx| {
            let (c, stats) = clusterer.cluster(ctx, &cloud.points, &config)?;
            Ok(((c, Some(stats.submissions)), stats.gpu_times))
        },
    )?;

    if let Some(dir) = &args.out_dir {
        timings.time("write", || {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("creating output directory {}", dir.display()))?;
            for (k, part) in clustering.extract(&cloud).iter().enumerate() {
                io::write_cloud(
                    &dir.join(format!("cluster_{k}.pcd")),
                    part,
                    Encoding::Binary,
                )?;
            }
            anyhow::Ok(())
        })?;
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
        timings.print();
    }
    Ok(())
}
