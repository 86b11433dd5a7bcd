//! Synthetic depth views for the surface tests: a pinhole camera ray-casting analytic shapes
//! (spheres, planes) around the HIP, with optional D435 axial noise and a ball occluder at the
//! HIP (the robot's handle). Ground truth is the analytic closest point and normal.

use glam::Vec3;
use nalgebra::{Point3, Unit, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

#[derive(Clone, Copy, Debug)]
pub enum Shape {
    Sphere {
        center: Point3<f64>,
        radius: f64,
    },
    /// Plane through `point` with unit normal `normal` (facing the camera).
    Plane {
        point: Point3<f64>,
        normal: Vector3<f64>,
    },
}

impl Shape {
    fn ray(&self, o: &Point3<f64>, d: &Vector3<f64>) -> Option<f64> {
        match *self {
            Shape::Sphere { center, radius } => {
                let oc = o - center;
                let b = oc.dot(d);
                let c = oc.norm_squared() - radius * radius;
                let disc = b * b - c;
                (disc >= 0.0).then(|| -b - disc.sqrt()).filter(|t| *t > 0.0)
            }
            Shape::Plane { point, normal } => {
                let den = normal.dot(d);
                (den.abs() > 1e-12)
                    .then(|| normal.dot(&(point - o)) / den)
                    .filter(|t| *t > 0.0)
            }
        }
    }

    /// Closest point of the shape to `h` and the outward normal there.
    pub fn closest(&self, h: &Point3<f64>) -> (Point3<f64>, Unit<Vector3<f64>>) {
        match *self {
            Shape::Sphere { center, radius } => {
                let n = Unit::new_normalize(h - center);
                (center + radius * n.into_inner(), n)
            }
            Shape::Plane { point, normal } => {
                let n = Unit::new_normalize(normal);
                (h - n.dot(&(h - point)) * n.into_inner(), n)
            }
        }
    }
}

/// A camera looking at the HIP from `camera`, with D435-like angular resolution.
pub struct View {
    pub camera: Point3<f64>,
    /// Pixels per radian (fx of a 848x480 D435 is about 424).
    pub fx: f64,
    /// Half-width of the sampled cone around the HIP, metres at the HIP's distance.
    pub extent_m: f64,
    /// Axial noise: the D435 fit of REFERENCE.md when true.
    pub d435_noise: bool,
    /// Extra axial noise sigma, metres.
    pub extra_noise_m: f64,
    /// Rays passing closer than this to the HIP are blocked (robot occlusion), metres.
    pub occluder_radius_m: f64,
    pub seed: u64,
}

impl View {
    pub fn new(camera: Point3<f64>) -> Self {
        Self {
            camera,
            fx: 424.0,
            extent_m: 0.12,
            d435_noise: false,
            extra_noise_m: 0.0,
            occluder_radius_m: 0.0,
            seed: 1,
        }
    }

    /// Unit viewing direction from the camera to the HIP.
    pub fn direction(&self, hip: &Point3<f64>) -> Vector3<f64> {
        (hip - self.camera).normalize()
    }

    /// Ray-cast `shapes` (nearest hit wins) over a pixel grid centred on the HIP.
    pub fn render(&self, shapes: &[Shape], hip: &Point3<f64>) -> Vec<Vec3> {
        let axis = self.direction(hip);
        let e1 = axis.cross(&Vector3::new(0.31, 0.52, 0.79)).normalize();
        let e2 = axis.cross(&e1);
        let dist = (hip - self.camera).norm();
        let half = (self.extent_m / dist * self.fx).ceil() as i64;
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        let unit = Normal::new(0.0, 1.0).unwrap();
        let mut out = Vec::new();
        for v in -half..=half {
            for u in -half..=half {
                let d = (axis + (u as f64 / self.fx) * e1 + (v as f64 / self.fx) * e2).normalize();
                if self.occluder_radius_m > 0.0 {
                    let t = (hip - self.camera).dot(&d);
                    if t > 0.0 && (self.camera + t * d - hip).norm() < self.occluder_radius_m {
                        continue;
                    }
                }
                let hit = shapes
                    .iter()
                    .filter_map(|s| s.ray(&self.camera, &d))
                    .min_by(f64::total_cmp);
                let Some(t) = hit else { continue };
                let z = t * d.dot(&axis);
                let mut sigma = self.extra_noise_m;
                if self.d435_noise {
                    sigma += 0.000611 + 0.003587 * (z - 0.3515).powi(2);
                }
                let t = if sigma > 0.0 {
                    t * (1.0 + sigma * unit.sample(&mut rng) / z)
                } else {
                    t
                };
                let p = self.camera + t * d;
                out.push(Vec3::new(p.x as f32, p.y as f32, p.z as f32));
            }
        }
        out
    }
}

/// Angle between two unit vectors, degrees.
pub fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.normalize()
        .dot(&b.normalize())
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}
