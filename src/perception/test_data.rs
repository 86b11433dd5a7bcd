//! Test clouds: a synthetic 640x480 RGB-D frame (depth quantised to 1 mm, dropouts) built
//! with the camera model, so GPU and CPU stages can be compared on frame-sized input.

use crate::camera::{DepthImage, PinholeIntrinsics};
use glam::Vec3;
use rand::{RngExt, SeedableRng};

/// A wall at 1.5 m, a tilted table plane and a 9 cm sphere (a head) at 0.9 m; 5 % of the
/// pixels have no return.
pub fn synthetic_frame(seed: u64) -> Vec<Vec3> {
    synthetic_depth(seed)
        .deproject(&PinholeIntrinsics::PCL_GRABBER)
        .expect("sizes match")
        .points
}

/// The depth image behind [`synthetic_frame`] (1 mm units, [`PinholeIntrinsics::PCL_GRABBER`]).
pub fn synthetic_depth(seed: u64) -> DepthImage {
    let k = PinholeIntrinsics::PCL_GRABBER;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut data = Vec::with_capacity((k.width * k.height) as usize);
    let centre = nalgebra::Vector3::new(0.05, -0.05, 0.9);
    for v in 0..k.height {
        for u in 0..k.width {
            let ray = nalgebra::Vector3::new(
                (f64::from(u) - k.cx) / k.fx,
                (f64::from(v) - k.cy) / k.fy,
                1.0,
            );
            let mut z: f64 = 1.5;
            // Table: y = 0.3 - 0.2 z (camera frame, y down).
            let t = 0.3 / (ray.y + 0.2);
            if ray.y + 0.2 > 0.0 && t < z {
                z = t;
            }
            // Sphere of radius 0.09 m.
            let b = ray.dot(&centre);
            let disc = b * b - ray.norm_squared() * (centre.norm_squared() - 0.0081);
            if disc >= 0.0 {
                let t = (b - disc.sqrt()) / ray.norm_squared();
                if t > 0.0 && t < z {
                    z = t;
                }
            }
            let noise: f64 = rng.random_range(-0.002..0.002);
            let dropout = rng.random_range(0.0..1.0) < 0.05;
            data.push(if dropout {
                0
            } else {
                ((z + noise) * 1000.0).round() as u16
            });
        }
    }
    DepthImage {
        width: k.width,
        height: k.height,
        depth_scale_m: 0.001,
        data,
    }
}

/// Uniform random points in a cube of side `side_m` centred at the origin, with a few
/// non-finite ones.
pub fn random_cloud(seed: u64, n: usize, side_m: f32) -> Vec<Vec3> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|i| {
            if i % 97 == 13 {
                Vec3::new(f32::NAN, 0.0, 1.0)
            } else {
                Vec3::new(
                    rng.random_range(-0.5..0.5) * side_m,
                    rng.random_range(-0.5..0.5) * side_m,
                    rng.random_range(-0.5..0.5) * side_m,
                )
            }
        })
        .collect()
}

/// A cloud from PCL's test data (`$HAPCLOUD_PCL_DATA/<name>`, else `../shared/data/pcl/<name>`
/// beside the crate, as the benchmarks look for it).
pub fn pcl_cloud(name: &str) -> crate::cloud::PointCloud {
    let dir = std::env::var_os("HAPCLOUD_PCL_DATA").map_or_else(
        || std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/pcl"),
        std::path::PathBuf::from,
    );
    let path = dir.join(name);
    crate::io::read_cloud(&path).unwrap_or_else(|e| panic!("{e}"))
}

/// A PCL frame as a 640x480 depth camera delivers it: each pixel's z in 1 mm units (0 where
/// the frame has no point), for [`PinholeIntrinsics::PCL_GRABBER`].
pub fn pcl_depth(name: &str) -> DepthImage {
    let cloud = pcl_cloud(name);
    let k = PinholeIntrinsics::PCL_GRABBER;
    assert_eq!((cloud.width, cloud.height), (k.width, k.height), "{name}");
    let data = (cloud.points.iter())
        .map(|p| {
            if p.z.is_finite() {
                (p.z * 1000.0).round().clamp(0.0, 65535.0) as u16
            } else {
                0
            }
        })
        .collect();
    DepthImage {
        width: k.width,
        height: k.height,
        depth_scale_m: 0.001,
        data,
    }
}

/// PCL's real 640x480 frames: the mug scene, five people, and the three grabber frames.
pub const PCL_FRAMES: [&str; 5] = [
    "table_scene_mug_stereo_textured.pcd",
    "five_people.pcd",
    "grabber_sequences/pcd/frame_20121214T142255.814212.pcd",
    "grabber_sequences/pcd/frame_20121214T142256.068683.pcd",
    "grabber_sequences/pcd/frame_20121214T142256.332395.pcd",
];
