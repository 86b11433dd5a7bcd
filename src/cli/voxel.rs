//! `hapcloud voxel`: PCL VoxelGrid on a PCD/PLY file (like `pcl_voxel_grid`), on the GPU or
//! with the CPU reference.

use std::path::PathBuf;

use super::timing::Timings;
use anyhow::Context;
use hapcloud::cloud::PointCloud;
use hapcloud::gpu::Backend;
use hapcloud::perception::voxel::{Axis, FilterLimits, GpuVoxel, VoxelConfig, voxel_cpu};

#[derive(clap::Args)]
pub struct Args {
    /// Input cloud (.pcd or .ply).
    input: PathBuf,
    /// Cubic leaf size (m, above 0, at most 100).
    #[arg(long, value_parser = super::numbers::distance, allow_negative_numbers = true)]
    leaf: f64,
    /// Drop cells with fewer points (PCL setMinimumPointsNumberPerVoxel).
    #[arg(long, default_value_t = 1, allow_negative_numbers = true)]
    min_points: u32,
    /// Filter field (PCL setFilterFieldName); used with --fmin/--fmax.
    #[arg(long, value_enum, default_value = "z")]
    field: FieldArg,
    /// Lower filter limit (m, within +-100); no filter unless --fmin or --fmax is given.
    #[arg(long, value_parser = super::numbers::coordinate, allow_hyphen_values = true)]
    fmin: Option<f64>,
    /// Upper filter limit (m, within +-100).
    #[arg(long, value_parser = super::numbers::coordinate, allow_hyphen_values = true)]
    fmax: Option<f64>,
    /// Keep the points outside the filter limits instead.
    #[arg(long)]
    filter_negative: bool,
    /// Output cloud (.pcd or .ply, binary).
    #[arg(long)]
    out: Option<PathBuf>,
    #[arg(long, value_enum, default_value_t = Backend::Gpu)]
    backend: Backend,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    limit: super::InputLimit,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum FieldArg {
    X,
    Y,
    Z,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut timings = Timings::default();
    let cloud = timings.time("read", || {
        hapcloud::io::read_cloud_within(&args.input, &args.limit.limits())
    })?;
    let filter = (args.fmin.is_some() || args.fmax.is_some()).then(|| FilterLimits {
        axis: match args.field {
            FieldArg::X => Axis::X,
            FieldArg::Y => Axis::Y,
            FieldArg::Z => Axis::Z,
        },
        min_m: args.fmin.unwrap_or(f64::NEG_INFINITY),
        max_m: args.fmax.unwrap_or(f64::INFINITY),
        negative: args.filter_negative,
    });
    let config = VoxelConfig {
        leaf_m: args.leaf,
        min_points_per_voxel: args.min_points,
        filter,
        ..Default::default()
    };
    config.validate()?;
    let (out, adapter) = timings.run_stage(
        args.backend,
        "voxel",
        || Ok(voxel_cpu(&cloud.points, None, &config)?),
        |ctx| Ok(GpuVoxel::new(ctx)?),
        |voxel, ctx| Ok(voxel.run(ctx, &cloud.points, &config)?),
    )?;
    if let Some(path) = &args.out {
        let mut result = PointCloud::from_points(out.points.clone());
        result.sensor_pose = cloud.sensor_pose;
        timings
            .time("write", || {
                hapcloud::io::write_cloud(path, &result, hapcloud::io::Encoding::Binary)
            })
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if args.json {
        let json = serde_json::json!({
            "points_in": cloud.len(),
            "points_valid": out.valid_in,
            "points_out": out.points.len(),
            "leaf_m": out.leaf_m,
            "backend": args.backend,
            "adapter": adapter,
            "table_slots": out.table_slots,
            "retries": out.retries,
            "timings_ms": timings,
        });
        println!("{json}");
    } else {
        println!(
            "{}: {} points ({} valid) -> {} points at leaf {} m [{}{}]",
            args.input.display(),
            cloud.len(),
            out.valid_in,
            out.points.len(),
            out.leaf_m,
            args.backend,
            adapter.map(|a| format!(", {a}")).unwrap_or_default()
        );
        timings.print();
    }
    Ok(())
}
