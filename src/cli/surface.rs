//! `hapcloud surface IN --hip x,y,z [--view x,y,z]`: the collision surface (paper Alg. 1-2)
//! of one cloud file around a HIP.
//!
//! The cloud (PCD or PLY) is taken as the front end's cleaned cloud in its own frame; the HIP
//! is in that frame too. Eq. 2 orients the normals against `--view`, or by default against
//! the rays from the file's sensor position (PCD `VIEWPOINT`). One frame has no memory yet, so
//! this shows the shell abstraction: every shell's outcome and fit, the paper's centroid and
//! the curvature-corrected one.

use anyhow::{Context, bail};
use clap::Args as ClapArgs;
use hapcloud::gpu::{Backend, GpuContext};
use hapcloud::io;
use hapcloud::perception::fit::CircleMethod;
use hapcloud::perception::pipeline::{SurfaceConfig, SurfaceEstimator};
use hapcloud::perception::shells::Viewpoint;
use nalgebra::{Point3, Vector3};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

#[derive(ClapArgs, Debug)]
pub struct Args {
    /// Input cloud: .pcd or .ply.
    pub input: PathBuf,
    /// HIP position in the cloud's frame, metres: x,y,z (each within +-100).
    #[arg(long, value_parser = super::numbers::coordinate, value_delimiter = ',', allow_hyphen_values = true)]
    pub hip: Vec<f64>,
    /// Camera viewing direction z^k of eq. 2 (normals are turned against it): x,y,z.
    /// Default: the rays from the file's sensor position (PCD VIEWPOINT) to each shell.
    #[arg(long, value_parser = super::numbers::coordinate, value_delimiter = ',', allow_hyphen_values = true)]
    pub view: Option<Vec<f64>>,
    /// Surface configuration (TOML of `SurfaceConfig`: [memory], [shells]).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Override the circle fit of the configuration.
    #[arg(long, value_parser = parse_method)]
    pub circle_method: Option<CircleMethod>,
    /// Shell moments on the GPU shader or its CPU reference.
    #[arg(long, value_enum, default_value = "gpu")]
    pub backend: Backend,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    limit: super::InputLimit,
}

pub(crate) fn parse_method(s: &str) -> Result<CircleMethod, String> {
    CircleMethod::ALL
        .into_iter()
        .find(|m| m.name() == s.replace('-', "_"))
        .ok_or_else(|| format!("unknown circle method {s:?}: kasa, taubin or sphere-cut"))
}

fn vec3(name: &str, v: &[f64]) -> anyhow::Result<Vector3<f64>> {
    match v {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok(Vector3::new(*x, *y, *z)),
        _ => bail!("--{name} needs three finite numbers x,y,z, got {v:?}"),
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let hip = Point3::from(vec3("hip", &args.hip)?);
    let mut config: SurfaceConfig = match &args.config {
        Some(path) => {
            let text = io::read_text(path)?;
            toml::from_str(&text)
                .with_context(|| format!("{}: bad surface configuration", path.display()))?
        }
        None => SurfaceConfig::default(),
    };
    if let Some(m) = args.circle_method {
        config.shells.circle_method = m;
    }
    config.validate().context("surface configuration")?;
    let cloud = io::read_cloud_within(&args.input, &args.limit.limits())?;
    let view = match &args.view {
        Some(v) => {
            let v = vec3("view", v)?;
            if v.norm() == 0.0 {
                bail!("--view must not be the zero vector");
            }
            Viewpoint::Direction(v)
        }
        None => Viewpoint::Position(Point3::from(cloud.sensor_pose.translation.vector)),
    };
    let (mut estimator, adapter) = match args.backend {
        Backend::Cpu => (SurfaceEstimator::new(config.clone())?, None),
        Backend::Gpu => {
            let ctx = Arc::new(GpuContext::new()?);
            let name = ctx.adapter().name.clone();
            (SurfaceEstimator::with_gpu(config.clone(), ctx)?, Some(name))
        }
    };
    let start = Instant::now();
    let frame = estimator.estimate(&cloud.points, &hip, view, 0, 0.0);
    let elapsed_ms = start.elapsed().as_secs_f64() * 1e3;
    if let Some(e) = &frame.gpu_error {
        hapcloud::stderr_line!("warning: GPU shell moments failed ({e}); used the CPU reference");
    }
    let ab = &frame.abstraction;
    let e = &ab.estimate;
    let shells: Vec<serde_json::Value> = ab
        .reports
        .iter()
        .map(|r| {
            let fit = e
                .shells
                .iter()
                .find(|f| f.outer_radius_m == r.outer_radius_m);
            serde_json::json!({
                "inner_radius_m": r.inner_radius_m,
                "outer_radius_m": r.outer_radius_m,
                "point_count": r.point_count,
                "status": r.status,
                "fell_back": r.fell_back,
                "fit": fit,
            })
        })
        .collect();
    if args.json {
        let out = serde_json::json!({
            "input": args.input.display().to_string(),
            "points_in": cloud.len(),
            "finite_points": cloud.finite_count(),
            "outside_shells": frame.sums.outside,
            "isolated_points": frame.isolated_points,
            "backend": frame.backend,
            "adapter": adapter,
            "circle_method": config.shells.circle_method,
            "centroid": e.surface.map(|s| [s.centroid_m.x, s.centroid_m.y, s.centroid_m.z]),
            "normal": e.surface.map(|s| [s.normal.x, s.normal.y, s.normal.z]),
            "valid": e.surface.is_some(),
            "invalid_reason": ab.invalid.as_ref().map(|r| r.to_string()),
            "quality": e.quality,
            "paper_centroid": [ab.paper_centroid_m.x, ab.paper_centroid_m.y, ab.paper_centroid_m.z],
            "curvature_correction": ab.correction,
            "quadric_refinement": ab.refinement.as_ref().map(|hf| serde_json::json!({
                "closest": [hf.closest_m.x, hf.closest_m.y, hf.closest_m.z],
                "normal": [hf.normal.x, hf.normal.y, hf.normal.z],
                "residual_rms_m": hf.residual_rms_m,
                "coefficients": hf.coefficients,
            })),
            "shells": shells,
            "timings_ms": { "surface": elapsed_ms },
        });
        println!("{out}");
        return Ok(());
    }
    println!(
        "{}: {} points ({} finite), HIP ({:.4}, {:.4}, {:.4}), backend {}{}",
        args.input.display(),
        cloud.len(),
        cloud.finite_count(),
        hip.x,
        hip.y,
        hip.z,
        frame.backend,
        adapter.map(|a| format!(" ({a})")).unwrap_or_default()
    );
    for (r, s) in ab.reports.iter().zip(&shells) {
        let fit = &s["fit"];
        let detail = if fit.is_null() {
            String::new()
        } else {
            format!(
                " {} residual {:.2} mm{}",
                fit["kind"].as_str().unwrap_or(""),
                fit["residual_rms_m"].as_f64().unwrap_or(f64::NAN) * 1e3,
                if fit["rejected"].as_bool() == Some(true) {
                    ", rejected"
                } else {
                    ""
                }
            )
        };
        println!(
            "  shell {:.3}-{:.3} m: {:5} points, {}{}",
            r.inner_radius_m, r.outer_radius_m, r.point_count, r.status, detail
        );
    }
    if let Some(s) = &e.surface {
        println!(
            "centroid ({:.5}, {:.5}, {:.5}) m, normal ({:.4}, {:.4}, {:.4}), quality {:.2}",
            s.centroid_m.x,
            s.centroid_m.y,
            s.centroid_m.z,
            s.normal.x,
            s.normal.y,
            s.normal.z,
            e.quality
        );
        if let Some(c) = ab.correction {
            println!(
                "curvature correction: depth {:.2} mm -> {:.2} mm below the HIP",
                c.paper_depth_m * 1e3,
                c.depth_m * 1e3
            );
        }
        match &ab.refinement {
            Some(hf) => println!(
                "quadric refinement: gave the estimate, residual {:.2} mm RMS",
                hf.residual_rms_m * 1e3
            ),
            None => println!("quadric refinement: not used (disabled, or no trusted fit)"),
        }
    } else {
        match &ab.invalid {
            Some(reason) => println!("no valid surface near the HIP: {reason}"),
            None => println!("no valid surface near the HIP"),
        }
    }
    Ok(())
}
