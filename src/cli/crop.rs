//! `hapcloud crop`: the crop stage on a PCD/PLY file: drops invalid points, points farther
//! than `--radius` from the HIP and points inside the robot's collision primitives.

use std::path::PathBuf;

use super::timing::Timings;
use anyhow::Context;
use hapcloud::geometry::Primitive;
use hapcloud::gpu::Backend;
use hapcloud::gpu::timing::{StageTime, StageTimer};
use hapcloud::perception::crop::{
    CropConfig, CropScene, GpuCrop, MAX_CROP_RADIUS_M, MAX_ROBOT_MARGIN_M, MAX_ROBOT_MARGIN_PER_M2,
    crop_cpu, kept_indices,
};
use nalgebra::Point3;

#[derive(clap::Args)]
pub struct Args {
    /// Input cloud (.pcd or .ply).
    input: PathBuf,
    /// Haptic interaction point `x,y,z` in the cloud frame (m, each within +-100).
    #[arg(long, value_parser = super::numbers::point, allow_hyphen_values = true)]
    hip: Point3<f64>,
    /// Keep points within this distance of the HIP (m, above 0, at most 100).
    #[arg(long, value_parser = super::numbers::positive_at_most(MAX_CROP_RADIUS_M), allow_negative_numbers = true)]
    radius: f64,
    /// TOML file with the robot's collision primitives in the cloud frame:
    /// `[[primitive]]` tables with `shape = "sphere" | "capsule" | "oriented_box"`.
    #[arg(long)]
    robot: Option<PathBuf>,
    /// Grow every robot primitive by this much before the test (m, 0 to 1) ...
    #[arg(long, value_parser = super::numbers::non_negative_at_most(MAX_ROBOT_MARGIN_M), allow_negative_numbers = true, default_value_t = CropConfig::default().robot_margin_m)]
    robot_margin: f64,
    /// ... plus this times the squared distance from `--camera` to the HIP (m per m^2, 0 to 1).
    #[arg(long, value_parser = super::numbers::non_negative_at_most(MAX_ROBOT_MARGIN_PER_M2), allow_negative_numbers = true, default_value_t = CropConfig::default().robot_margin_per_m2)]
    robot_margin_per_m2: f64,
    /// The camera's optical centre `x,y,z` in the cloud frame (m, each within +-100); without it the margin is
    /// `--robot-margin` alone.
    #[arg(long, value_parser = super::numbers::point, allow_hyphen_values = true)]
    camera: Option<Point3<f64>>,
    /// Output cloud (.pcd or .ply, binary), the kept points with their fields.
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

/// The robot file: a list of primitives.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct RobotFile {
    #[serde(default)]
    primitive: Vec<Primitive>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut timings = Timings::default();
    let (cloud, robot) = timings.time("read", || {
        let cloud = hapcloud::io::read_cloud_within(&args.input, &args.limit.limits())?;
        let robot = match &args.robot {
            Some(path) => {
                let text = hapcloud::io::read_text(path)?;
                toml::from_str::<RobotFile>(&text)
                    .with_context(|| format!("{}: not a robot primitive list", path.display()))?
                    .primitive
            }
            None => Vec::new(),
        };
        anyhow::Ok((cloud, robot))
    })?;
    let config = CropConfig {
        radius_m: args.radius,
        robot_margin_m: args.robot_margin,
        robot_margin_per_m2: args.robot_margin_per_m2,
    };
    let scene = CropScene {
        hip_m: args.hip,
        robot: &robot,
        camera_m: args.camera,
    };
    let (mask, adapter) = timings.run_stage(
        args.backend,
        "crop",
        || Ok(crop_cpu(&cloud.points, &config, &scene)?),
        |ctx| Ok((GpuCrop::new(ctx)?, StageTimer::new(ctx, "crop", &["crop"])?)),
        |(crop, timer), ctx| {
            let (mask, gpu_ms) = crop.run(ctx, &cloud.points, &config, &scene, timer.as_ref())?;
            let passes = gpu_ms.map(|gpu_ms| StageTime {
                stage: "crop",
                gpu_ms,
            });
            Ok((mask, passes.into_iter().collect()))
        },
    )?;
    let kept = kept_indices(&mask, cloud.len());
    if let Some(path) = &args.out {
        timings
            .time("write", || {
                hapcloud::io::write_cloud(
                    path,
                    &cloud.select(&kept),
                    hapcloud::io::Encoding::Binary,
                )
            })
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if args.json {
        let json = serde_json::json!({
            "points_in": cloud.len(),
            "points_out": kept.len(),
            "primitives": robot.len(),
            "backend": args.backend,
            "adapter": adapter,
            "timings_ms": timings,
        });
        println!("{json}");
    } else {
        println!(
            "{}: {} points -> {} kept ({} robot primitives) [{}{}]",
            args.input.display(),
            cloud.len(),
            kept.len(),
            robot.len(),
            args.backend,
            adapter.map(|a| format!(", {a}")).unwrap_or_default()
        );
        timings.print();
    }
    Ok(())
}
