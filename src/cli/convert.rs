//! `hapcloud convert IN OUT`: point clouds and depth images between formats.
//!
//! IN is a PCD or PLY cloud, or a 16-bit depth image (PNG/TIFF) that is deprojected with
//! `--intrinsics fx,fy,cx,cy` and `--depth-scale-m` to an organized cloud (NaN where the
//! depth is 0). OUT is a PCD or PLY file; `--format` picks its encoding.

use anyhow::{Context, bail};
use clap::{Args as ClapArgs, ValueEnum};
use hapcloud::camera::PinholeIntrinsics;
use hapcloud::io::{self, Encoding, depth};
use std::path::PathBuf;

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum Format {
    Ascii,
    Binary,
    BinaryCompressed,
}

#[derive(ClapArgs, Debug)]
pub struct Args {
    /// Input: .pcd, .ply, or a 16-bit depth image (.png, .tif, .tiff).
    pub input: PathBuf,
    /// Output: .pcd or .ply.
    pub output: PathBuf,
    /// Output encoding (PLY: binary = binary_little_endian; no compressed PLY).
    #[arg(long, value_enum, default_value = "binary")]
    pub format: Format,
    /// Pinhole intrinsics of a depth-image input, pixels: fx,fy,cx,cy.
    #[arg(long, value_delimiter = ',')]
    pub intrinsics: Option<Vec<f64>>,
    /// Metres per depth unit of a depth-image input (1e-6 to 1).
    #[arg(long, value_parser = depth_scale, allow_negative_numbers = true, default_value_t = 0.001)]
    pub depth_scale_m: f64,
    /// Print one JSON object describing the conversion.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    limit: super::InputLimit,
}

/// `--depth-scale-m`: within [`depth::DEPTH_SCALE_RANGE_M`].
fn depth_scale(s: &str) -> Result<f64, String> {
    let v = super::numbers::positive(s)?;
    let (lo, hi) = depth::DEPTH_SCALE_RANGE_M;
    if (lo..=hi).contains(&v) {
        Ok(v)
    } else {
        Err(format!("must be {lo:?} to {hi:?} m per unit, got {v:?}"))
    }
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let cloud = if depth::ImageFormat::from_path(&args.input).is_some() {
        let Some(&[fx, fy, cx, cy]) = args.intrinsics.as_deref() else {
            bail!(
                "{}: a depth image needs --intrinsics fx,fy,cx,cy",
                args.input.display()
            );
        };
        if !(args.depth_scale_m > 0.0 && args.depth_scale_m.is_finite()) {
            bail!(
                "--depth-scale-m must be positive, got {}",
                args.depth_scale_m
            );
        }
        let image = depth::read_within(&args.input, args.depth_scale_m, &args.limit.limits())?;
        let intrinsics = PinholeIntrinsics {
            width: image.width,
            height: image.height,
            fx,
            fy,
            cx,
            cy,
        };
        depth::check_intrinsics(&intrinsics).context("--intrinsics")?;
        image
            .deproject(&intrinsics)
            .context("depth image and intrinsics disagree on the size")?
    } else {
        io::read_cloud_within(&args.input, &args.limit.limits())?
    };
    let encoding = match args.format {
        Format::Ascii => Encoding::Ascii,
        Format::Binary => Encoding::Binary,
        Format::BinaryCompressed => Encoding::BinaryCompressed,
    };
    io::write_cloud(&args.output, &cloud, encoding)?;
    if args.json {
        let summary = serde_json::json!({
            "input": args.input,
            "output": args.output,
            "points": cloud.len(),
            "finite_points": cloud.finite_count(),
            "width": cloud.width,
            "height": cloud.height,
            "has_rgba": cloud.rgba.is_some(),
            "has_normals": cloud.normals.is_some(),
        });
        println!("{summary}");
    } else {
        println!(
            "{} -> {}: {} points ({} finite, {} x {})",
            args.input.display(),
            args.output.display(),
            cloud.len(),
            cloud.finite_count(),
            cloud.width,
            cloud.height
        );
    }
    Ok(())
}
