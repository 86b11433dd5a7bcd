//! A deterministic timeline for the viewer tests: a head (sphere, r = 9 cm) seen by a front
//! camera and one 45 degrees to the right, the HIP sphere (r = 4 cm) approaching it.
//!
//! Points are a Fibonacci lattice on the head, split by role the way the pipeline would:
//! robot (HIP handle) points and points far from the HIP are cropped, a few floating speckles
//! are clustered out, head points hidden behind the HIP and inside r_in are memorised, the rest
//! are kept. Shell fits are the exact sphere/sphere intersection circles of each shell's
//! middle radius (the innermost non-empty shell gets a plane at its points' mean), with the
//! outer shells' normals tilted as short arcs tilt them; fits tilted more than 3 degrees are
//! marked rejected. The estimate averages the accepted fits weighted by 1/r (paper Alg. 2), so
//! it sits deeper than the true closest point, as DESIGN.md's pitfall describes.

use glam::Vec3;
use hapcloud::surface::{ShellFit, ShellFitKind, SurfaceEstimate, SurfacePoint};
use hapcloud::viewer::{
    CameraView, ConstraintSample, FrameSamples, PointLayer, PointRole, StageLatency, ViewFrame,
};
use nalgebra::{Isometry3, Point3, Rotation3, Translation3, Unit, UnitQuaternion, Vector3};

pub const HEAD_RADIUS_M: f64 = 0.09;
pub const HIP_RADIUS_M: f64 = 0.04;
pub const SHELL_RADII_M: [f64; 6] = [0.07, 0.08, 0.09, 0.10, 0.11, 0.12];
const CROP_RADIUS_M: f64 = 0.15;
pub const FRAME_COUNT: usize = 24;
const PERIOD_S: f64 = 1.0 / 30.0;

fn head_centre() -> Point3<f64> {
    Point3::new(0.0, 0.0, 1.40)
}

fn approach_dir() -> Unit<Vector3<f64>> {
    Unit::new_normalize(Vector3::new(1.0, -0.3, 0.25))
}

fn camera_positions() -> [Point3<f64>; 2] {
    let o = head_centre();
    let (s, c) = std::f64::consts::FRAC_PI_4.sin_cos();
    [
        o + Vector3::new(0.9, 0.0, 0.15),
        o + Vector3::new(0.9 * c, -0.9 * s, 0.15),
    ]
}

fn v3(p: &Point3<f64>) -> Vec3 {
    Vec3::new(p.x as f32, p.y as f32, p.z as f32)
}

/// `n` points evenly spread over a sphere (Fibonacci lattice).
fn fibonacci_sphere(centre: &Point3<f64>, radius_m: f64, n: usize) -> Vec<Point3<f64>> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let a = golden * i as f64;
            centre + radius_m * Vector3::new(r * a.cos(), r * a.sin(), z)
        })
        .collect()
}

/// True when the segment from `p` to `eye` passes through the sphere (`c`, `r`).
fn occluded_by(p: &Point3<f64>, eye: &Point3<f64>, c: &Point3<f64>, r: f64) -> bool {
    let d = eye - p;
    let t = ((c - p).dot(&d) / d.norm_squared()).clamp(0.0, 1.0);
    (p + t * d - c).norm() < r
}

fn tilted(n: &Unit<Vector3<f64>>, angle_rad: f64) -> Unit<Vector3<f64>> {
    let axis = Unit::new_normalize(n.cross(&Vector3::z()));
    Unit::new_normalize(Rotation3::from_axis_angle(&axis, angle_rad) * n.into_inner())
}

fn shell_fits(fit_points: &[Point3<f64>], hip: &Point3<f64>) -> Vec<ShellFit> {
    let o = head_centre();
    let dist = (hip - o).norm();
    let axis = Unit::new_normalize(hip - o);
    let mut fits = Vec::new();
    let mut inner = 0.0;
    for (i, &outer) in SHELL_RADII_M.iter().enumerate() {
        let pts: Vec<&Point3<f64>> = fit_points
            .iter()
            .filter(|p| {
                let d = (*p - hip).norm();
                d > inner && d <= outer
            })
            .collect();
        let shell_inner = inner;
        inner = outer;
        if pts.len() < 3 {
            continue;
        }
        let tilt_rad = (i as f64 * 1.2 * if i % 2 == 0 { 1.0 } else { -1.0 }).to_radians();
        let normal = tilted(&axis, tilt_rad);
        let (kind, center, radius) = if fits.is_empty() {
            let mean = pts.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / pts.len() as f64;
            (ShellFitKind::Plane, Point3::from(mean), None)
        } else {
            let rm = 0.5 * (shell_inner + outer);
            let a = (dist * dist + rm * rm - HEAD_RADIUS_M * HEAD_RADIUS_M) / (2.0 * dist);
            let rho = (rm * rm - a * a).max(0.0).sqrt();
            (ShellFitKind::Circle, hip - a * axis.into_inner(), Some(rho))
        };
        let residual_sq: f64 = pts
            .iter()
            .map(|p| {
                let rel = *p - center;
                let along = rel.dot(&normal);
                match radius {
                    None => along * along,
                    Some(rho) => {
                        along * along + ((rel - along * normal.into_inner()).norm() - rho).powi(2)
                    }
                }
            })
            .sum();
        fits.push(ShellFit {
            inner_radius_m: shell_inner,
            outer_radius_m: outer,
            point_count: pts.len() as u32,
            kind,
            center_m: center,
            normal,
            circle_radius_m: radius,
            residual_rms_m: (residual_sq / pts.len() as f64).sqrt(),
            rejected: tilt_rad.abs() > 3f64.to_radians(),
        });
    }
    fits
}

fn estimate(camera_id: u32, stamp_s: f64, shells: Vec<ShellFit>) -> SurfaceEstimate {
    let accepted: Vec<&ShellFit> = shells.iter().filter(|s| !s.rejected).collect();
    let weights: Vec<f64> = accepted.iter().map(|s| 1.0 / s.outer_radius_m).collect();
    let total: f64 = weights.iter().sum();
    let valid = !accepted.is_empty();
    let centroid = accepted
        .iter()
        .zip(&weights)
        .fold(Vector3::zeros(), |s, (f, w)| s + f.center_m.coords * *w);
    let normal = accepted
        .iter()
        .zip(&weights)
        .fold(Vector3::zeros(), |s, (f, w)| s + f.normal.into_inner() * *w);
    let quality = accepted.len() as f64 / SHELL_RADII_M.len() as f64;
    SurfaceEstimate {
        camera_id,
        stamp_s,
        surface: valid.then(|| SurfacePoint {
            centroid_m: Point3::from(centroid / total),
            normal: Unit::new_normalize(normal),
        }),
        shells,
        quality: if valid { quality } else { 0.0 },
    }
}

fn camera_view(camera_id: u32, eye: &Point3<f64>, hip: &Point3<f64>, stamp_s: f64) -> CameraView {
    let o = head_centre();
    let r_in = SHELL_RADII_M[0];
    let mut layers: Vec<PointLayer> = PointRole::ALL
        .iter()
        .map(|&role| PointLayer::new(role, Vec::new()))
        .collect();
    let mut push = |role: PointRole, p: &Point3<f64>| {
        let layer = layers
            .iter_mut()
            .find(|l| l.role == role)
            .expect("every role has a layer");
        layer.points_m.push(v3(p));
        layer.count += 1;
    };
    let mut fit_points = Vec::new();
    for p in fibonacci_sphere(&o, HEAD_RADIUS_M, 5000) {
        if (p - o).dot(&(eye - p)) <= 0.0 {
            continue; // back face
        }
        let near_hip = (p - hip).norm();
        if occluded_by(&p, eye, hip, HIP_RADIUS_M) {
            if near_hip < r_in {
                push(PointRole::Memorised, &p);
                fit_points.push(p);
            }
        } else if near_hip > CROP_RADIUS_M {
            push(PointRole::Cropped, &p);
        } else {
            push(PointRole::Kept, &p);
            fit_points.push(p);
        }
    }
    // The HIP handle itself is seen by the camera and cropped as a robot primitive.
    for p in fibonacci_sphere(hip, HIP_RADIUS_M, 600) {
        if (p - hip).dot(&(eye - p)) > 0.0 {
            push(PointRole::Cropped, &p);
        }
    }
    // Speckles floating between the head and the camera, removed by clustering.
    for k in 0..24 {
        let f = k as f64;
        let p = o + Vector3::new(
            0.13 + 0.004 * (f * 1.7).sin(),
            -0.05 + 0.004 * f,
            0.02 * (f * 0.9).cos(),
        );
        push(PointRole::ClusteredOut, &p);
    }
    let pose = Isometry3::from_parts(
        Translation3::from(eye.coords),
        UnitQuaternion::face_towards(&(o - eye), &Vector3::z()),
    );
    CameraView {
        camera_id,
        world_from_camera: Some(pose),
        layers,
        estimate: Some(estimate(camera_id, stamp_s, shell_fits(&fit_points, hip))),
    }
}

/// The fixture timeline: the HIP centre goes from 9 cm to 5 cm off the head surface.
pub fn timeline() -> Vec<ViewFrame> {
    let o = head_centre();
    let u = approach_dir();
    let mut frames: Vec<ViewFrame> = Vec::with_capacity(FRAME_COUNT);
    for k in 0..FRAME_COUNT {
        let stamp_s = 100.0 + k as f64 * PERIOD_S;
        let gap_m = 0.09 - 0.04 * k as f64 / (FRAME_COUNT - 1) as f64;
        let hip = o + (HEAD_RADIUS_M + gap_m) * u.into_inner();
        let cameras: Vec<CameraView> = camera_positions()
            .iter()
            .enumerate()
            .map(|(i, eye)| camera_view(i as u32, eye, &hip, stamp_s))
            .collect();
        let valid: Vec<SurfacePoint> = cameras
            .iter()
            .filter_map(|c| c.estimate.as_ref()?.surface)
            .collect();
        let fused = (!valid.is_empty()).then(|| SurfacePoint {
            centroid_m: Point3::from(
                valid
                    .iter()
                    .fold(Vector3::zeros(), |s, e| s + e.centroid_m.coords)
                    / valid.len() as f64,
            ),
            normal: Unit::new_normalize(
                valid
                    .iter()
                    .fold(Vector3::zeros(), |s, e| s + e.normal.into_inner()),
            ),
        });
        let d_proj_m = fused.map(|f| f.d_proj_m(&hip, HIP_RADIUS_M));
        let rate = match (d_proj_m, frames.last().and_then(|f| f.samples.d_proj_m)) {
            (Some(d), Some(prev)) => Some((d - prev) / PERIOD_S),
            _ => None,
        };
        let phase = k as f64 * 0.7;
        let latencies = [
            ("crop", 0.8),
            ("voxel", 1.1),
            ("cluster", 2.3),
            ("memory", 3.4),
            ("shells", 0.9),
        ]
        .iter()
        .enumerate()
        .map(|(i, (stage, ms))| StageLatency {
            stage: (*stage).to_owned(),
            latency_s: (ms + 0.15 * (phase + i as f64).sin()) * 1e-3,
        })
        .collect();
        frames.push(ViewFrame {
            stamp_s,
            hip_m: hip,
            hip_radius_m: HIP_RADIUS_M,
            shell_radii_m: SHELL_RADII_M.to_vec(),
            cameras,
            fused,
            truth: Some(SurfacePoint {
                centroid_m: o + HEAD_RADIUS_M * u.into_inner(),
                normal: u,
            }),
            guards: Vec::new(),
            samples: FrameSamples {
                d_proj_m,
                d_proj_rate_m_per_s: rate,
                haptic_status: None,
                speed_limit_m_per_s: d_proj_m.map(|d| (d / 0.1).clamp(0.0, 1.0) * 2.0),
                constraints: vec![
                    ConstraintSample {
                        name: "position".into(),
                        active: d_proj_m.is_some_and(|d| d < 0.02),
                        binding: None,
                    },
                    ConstraintSample {
                        name: "velocity".into(),
                        active: d_proj_m.is_some_and(|d| d < 0.04),
                        binding: None,
                    },
                ],
                latencies,
            },
        });
    }
    frames
}

/// The simulated scene the viewer tests show: `head_sliding_realistic` (two D435 views with
/// noise, holes and timing effects) as the HIP reaches the forehead, 1.5 s to 2.2 s at 10 view
/// ticks per second, through `hapcloud::viewer::simulated` (ground truth and haptic
/// constraints), with the stage latencies measured on this machine (wall-clock times).
pub fn scene_timeline_wall_clock() -> Vec<ViewFrame> {
    use hapcloud::node::NodeConfig;
    use hapcloud::scene::{Scene, Simulator};
    use hapcloud::viewer::simulated::{SceneViewConfig, timeline_from_scene};
    static TIMELINE: std::sync::OnceLock<Vec<ViewFrame>> = std::sync::OnceLock::new();
    TIMELINE
        .get_or_init(|| {
            let scene = Scene::from_builtin("head_sliding_realistic").expect("built-in scene");
            let simulator = std::sync::Arc::new(Simulator::new(&scene).expect("scene runs"));
            let config = SceneViewConfig {
                start_s: 1.5,
                duration_s: 0.7,
                view_rate_hz: 10.0,
                ..SceneViewConfig::default()
            };
            timeline_from_scene(&simulator, &NodeConfig::default(), &config).unwrap()
        })
        .clone()
}

/// [`scene_timeline_wall_clock`] with each stage latency replaced by a fixed value (1 ms
/// times the stage's position), so that snapshots do not depend on the machine's speed.
pub fn scene_timeline() -> Vec<ViewFrame> {
    let mut timeline = scene_timeline_wall_clock();
    for f in &mut timeline {
        for (i, l) in f.samples.latencies.iter_mut().enumerate() {
            l.latency_s = (i + 1) as f64 * 1e-3;
        }
    }
    timeline
}

/// Index of the frame of [`scene_timeline`] the tests look at: t = 2.2 s, the HIP at the skin.
pub const SCENE_FRAME: usize = 7;
