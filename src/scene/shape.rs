//! Analytic shapes of the simulated world: what scene files declare, and the posed form the
//! ray caster and the ground truth evaluate.
//!
//! A [`Shape`] is stored in its body's frame (scene-file form). [`Solid::new`] poses it into
//! another frame (a camera's optical frame for rendering, the world for ground truth) and
//! precomputes what the per-ray work needs. Every solid answers three questions exactly, in
//! `f64`:
//! - [`Solid::ray_hit`]: the first intersection of the ray `p(t) = t d` from the frame's
//!   origin (the camera centre) with the surface (sphere and ellipsoid: quadratic roots;
//!   capsule: the cylinder/caps formulation; box: slabs; plane patch: one plane and bounds);
//! - [`Solid::normal_at`]: the outward unit normal at a surface point (for incidence angles);
//! - [`Solid::closest`]: the surface point closest to any point, its outward normal and the
//!   signed distance (ellipsoid: Eberly's robust bisection, "Distance from a Point to an
//!   Ellipse, an Ellipsoid, or a Hyperellipsoid", 2013; the others in closed form).
//!
//! The robot's collision primitives ([`crate::geometry::Primitive`]) are a subset of these
//! shapes and convert with [`Shape::from`].

use crate::geometry::{Primitive, box_rotation, closest_point_on_segment};
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, SVector, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// A body part's shape in its body frame (scene-file form).
/// Largest magnitude of a shape's coordinate, size or angle (metres, radians).
pub const MAX_SHAPE_VALUE: f64 = 100.0;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shape", rename_all = "snake_case", deny_unknown_fields)]
pub enum Shape {
    /// Ball of `radius_m` around `center_m`.
    Sphere {
        center_m: Point3<f64>,
        radius_m: f64,
    },
    /// Ellipsoid with semi-axes `radii_m` along its own x, y, z, rotated by roll-pitch-yaw.
    Ellipsoid {
        center_m: Point3<f64>,
        radii_m: Vector3<f64>,
        #[serde(default)]
        rpy_rad: Vector3<f64>,
    },
    /// Segment `a_m`..`b_m` swept by a ball of `radius_m`.
    Capsule {
        a_m: Point3<f64>,
        b_m: Point3<f64>,
        radius_m: f64,
    },
    /// Box with half side lengths `half_extents_m`, rotated by roll-pitch-yaw; with
    /// `rounding_m > 0` its edges and corners are rounded with that radius (the box shrunk by
    /// `rounding_m` and swept by a ball of it: the faces stay where they are).
    Box {
        center_m: Point3<f64>,
        half_extents_m: Vector3<f64>,
        #[serde(default)]
        rpy_rad: Vector3<f64>,
        #[serde(default, skip_serializing_if = "is_zero")]
        rounding_m: f64,
    },
    /// Flat rectangle in its own x-y plane (normal = its z axis), half sides `half_extents_m`;
    /// seen from both sides. With `rpy_rad = 0` it is horizontal.
    PlanePatch {
        center_m: Point3<f64>,
        half_extents_m: Vector2<f64>,
        #[serde(default)]
        rpy_rad: Vector3<f64>,
    },
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

impl From<&Primitive> for Shape {
    fn from(p: &Primitive) -> Self {
        match p {
            Primitive::Sphere { center_m, radius_m } => Shape::Sphere {
                center_m: *center_m,
                radius_m: *radius_m,
            },
            Primitive::Capsule { a_m, b_m, radius_m } => Shape::Capsule {
                a_m: *a_m,
                b_m: *b_m,
                radius_m: *radius_m,
            },
            Primitive::OrientedBox {
                center_m,
                rpy_rad,
                half_extents_m,
            } => Shape::Box {
                center_m: *center_m,
                half_extents_m: *half_extents_m,
                rpy_rad: *rpy_rad,
                rounding_m: 0.0,
            },
        }
    }
}

impl Shape {
    /// Checks that every value is finite (and within [`MAX_SHAPE_VALUE`]) and every size
    /// positive; the message names the offending value.
    pub fn validate(&self) -> Result<(), String> {
        let values: Vec<(&str, &[f64])> = match self {
            Shape::Sphere { center_m, .. } => vec![("center_m", center_m.coords.as_slice())],
            Shape::Capsule { a_m, b_m, .. } => {
                vec![
                    ("a_m", a_m.coords.as_slice()),
                    ("b_m", b_m.coords.as_slice()),
                ]
            }
            Shape::Ellipsoid {
                center_m, rpy_rad, ..
            }
            | Shape::Box {
                center_m, rpy_rad, ..
            }
            | Shape::PlanePatch {
                center_m, rpy_rad, ..
            } => vec![
                ("center_m", center_m.coords.as_slice()),
                ("rpy_rad", rpy_rad.as_slice()),
            ],
        };
        let sizes: (&str, &[f64]) = match self {
            Shape::Sphere { radius_m, .. } | Shape::Capsule { radius_m, .. } => {
                ("radius_m", std::slice::from_ref(radius_m))
            }
            Shape::Ellipsoid { radii_m, .. } => ("radii_m", radii_m.as_slice()),
            Shape::Box { half_extents_m, .. } => ("half_extents_m", half_extents_m.as_slice()),
            Shape::PlanePatch { half_extents_m, .. } => {
                ("half_extents_m", half_extents_m.as_slice())
            }
        };
        /// Each value of a named group.
        fn each<'a>(
            &(name, v): &(&'static str, &'a [f64]),
        ) -> impl Iterator<Item = (&'static str, f64)> + 'a {
            v.iter().map(move |c| (name, *c))
        }
        if let Some((name, v)) = values
            .iter()
            .chain([&sizes])
            .flat_map(each)
            .find(|(_, v)| !v.is_finite())
        {
            return Err(format!("{name} has a non-finite value ({v})"));
        }
        if let Some((name, v)) = values
            .iter()
            .chain([&sizes])
            .flat_map(each)
            .find(|(_, v)| v.abs() > MAX_SHAPE_VALUE)
        {
            return Err(format!(
                "{name} = {v} is beyond {MAX_SHAPE_VALUE} (metres or radians)"
            ));
        }
        if let Some((name, v)) = each(&sizes).find(|(_, v)| *v <= 0.0) {
            return Err(format!("{name} must be positive, got {v} m"));
        }
        if let Shape::Box {
            half_extents_m,
            rounding_m,
            ..
        } = self
        {
            let smallest = half_extents_m.min();
            if !(*rounding_m >= 0.0 && *rounding_m <= smallest) {
                return Err(format!(
                    "rounding_m = {rounding_m} must be between 0 and the smallest half extent ({smallest} m)"
                ));
            }
        }
        Ok(())
    }
}

/// The closest surface point to a query point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Closest {
    pub point_m: Point3<f64>,
    /// Outward unit normal at `point_m` (for a plane patch: towards the query's side).
    pub normal: Vector3<f64>,
    /// Signed distance of the query from the surface, negative inside a solid.
    pub distance_m: f64,
}

/// A shape posed in some frame, ready for ray casting and closest-point queries.
#[derive(Clone, Debug)]
pub struct Solid {
    kind: SolidKind,
    /// What the rays from the frame's origin share (computed once per pose).
    ray: RayPre,
    /// Bounding sphere (centre, radius) in the posed frame.
    pub bound_center: Vector3<f64>,
    pub bound_radius: f64,
}

/// Per-pose constants of the ray tests (rays start at the frame's origin).
#[derive(Clone, Debug)]
enum RayPre {
    /// `|t M d - cu|^2 = 1` (sphere: M = I / r).
    Quadric {
        m: Matrix3<f64>,
        cu: Vector3<f64>,
        cc: f64,
    },
    Capsule {
        a: Vector3<f64>,
        b: Vector3<f64>,
        ba: Vector3<f64>,
        baba: f64,
        baoa: f64,
        /// `baba (|a|^2 - r^2) - baoa^2`.
        qc: f64,
        /// `|a|^2 - r^2`, `|b|^2 - r^2`.
        cap_a: f64,
        cap_b: f64,
    },
    Box {
        local_from_frame: Matrix3<f64>,
        /// The origin in box coordinates.
        ol: Vector3<f64>,
        half: Vector3<f64>,
    },
    Plane {
        local_from_frame: Matrix3<f64>,
        n: Vector3<f64>,
        nc: f64,
        c: Vector3<f64>,
        half: Vector2<f64>,
    },
    /// A rounded box: its outer box (the first test, and the hit itself where it lands on a
    /// flat face), then the convex pieces whose union it is (the inner box stretched by the
    /// rounding along each axis, and a capsule on each of the inner box's 12 edges).
    Rounded {
        outer: std::boxed::Box<Solid>,
        inner: Oriented<3>,
        pieces: Vec<Solid>,
    },
}

impl RayPre {
    fn new(kind: &SolidKind) -> Self {
        match kind {
            SolidKind::Sphere { c, r } => RayPre::Quadric {
                m: Matrix3::identity() / *r,
                cu: c / *r,
                cc: (c / *r).norm_squared() - 1.0,
            },
            SolidKind::Ellipsoid {
                c, unit_from_frame, ..
            } => {
                let cu = unit_from_frame * c;
                RayPre::Quadric {
                    m: *unit_from_frame,
                    cu,
                    cc: cu.norm_squared() - 1.0,
                }
            }
            SolidKind::Capsule { a, b, r } => {
                let ba = b - a;
                let baba = ba.norm_squared();
                let baoa = -ba.dot(a);
                RayPre::Capsule {
                    a: *a,
                    b: *b,
                    ba,
                    baba,
                    baoa,
                    qc: baba * (a.norm_squared() - r * r) - baoa * baoa,
                    cap_a: a.norm_squared() - r * r,
                    cap_b: b.norm_squared() - r * r,
                }
            }
            SolidKind::Rounded { inner, r } => RayPre::rounded(inner, *r),
            SolidKind::Box(Oriented {
                c,
                local_from_frame,
                half,
            }) => RayPre::Box {
                local_from_frame: *local_from_frame,
                ol: -(local_from_frame * c),
                half: *half,
            },
            SolidKind::Plane(Oriented {
                c,
                local_from_frame,
                half,
            }) => {
                let n = local_from_frame.row(2).transpose();
                RayPre::Plane {
                    local_from_frame: *local_from_frame,
                    n,
                    nc: n.dot(c),
                    c: *c,
                    half: *half,
                }
            }
        }
    }
}

#[derive(Clone, Debug)]
enum SolidKind {
    Sphere {
        c: Vector3<f64>,
        r: f64,
    },
    Ellipsoid {
        c: Vector3<f64>,
        /// Rotation from the posed frame into the ellipsoid's axes.
        local_from_frame: Matrix3<f64>,
        radii: Vector3<f64>,
        /// Maps posed-frame vectors into the unit-sphere space (diag(1/radii) * R^T).
        unit_from_frame: Matrix3<f64>,
    },
    Capsule {
        a: Vector3<f64>,
        b: Vector3<f64>,
        r: f64,
    },
    Box(Oriented<3>),
    /// A rectangle in its local xy plane (normal: local +z).
    Plane(Oriented<2>),
    /// The box `inner` swept by a ball of radius `r`.
    Rounded {
        inner: Oriented<3>,
        r: f64,
    },
}

impl RayPre {
    /// The ray constants of `inner` swept by a ball of radius `r`.
    fn rounded(inner: &Oriented<3>, r: f64) -> Self {
        let frame_from_local = inner.local_from_frame.transpose();
        let solid = |kind: SolidKind| Solid {
            ray: RayPre::new(&kind),
            kind,
            bound_center: inner.c,
            bound_radius: inner.half.norm() + r,
        };
        let stretched = |grow: Vector3<f64>| {
            solid(SolidKind::Box(Oriented {
                c: inner.c,
                local_from_frame: inner.local_from_frame,
                half: inner.half + grow,
            }))
        };
        let mut pieces: Vec<Solid> = (0..3)
            .map(|i| {
                let mut grow = Vector3::zeros();
                grow[i] = r;
                stretched(grow)
            })
            .collect();
        for axis in 0..3 {
            let (j, k) = ((axis + 1) % 3, (axis + 2) % 3);
            for corner in 0..4 {
                let mut end = Vector3::zeros();
                end[j] = if corner & 1 == 0 { -1.0 } else { 1.0 } * inner.half[j];
                end[k] = if corner & 2 == 0 { -1.0 } else { 1.0 } * inner.half[k];
                let (mut a, mut b) = (end, end);
                a[axis] = -inner.half[axis];
                b[axis] = inner.half[axis];
                pieces.push(solid(SolidKind::Capsule {
                    a: inner.c + frame_from_local * a,
                    b: inner.c + frame_from_local * b,
                    r,
                }));
            }
        }
        RayPre::Rounded {
            outer: std::boxed::Box::new(stretched(Vector3::repeat(r))),
            inner: inner.clone(),
            pieces,
        }
    }
}

/// A box (`D` = 3) or plane patch (`D` = 2) posed in some frame: what the two share.
#[derive(Clone, Debug)]
struct Oriented<const D: usize> {
    /// Centre in the posed frame.
    c: Vector3<f64>,
    /// Rotation from the posed frame into the shape's axes.
    local_from_frame: Matrix3<f64>,
    /// Half extents along the shape's first `D` axes.
    half: SVector<f64, D>,
}

impl<const D: usize> Oriented<D> {
    /// A shape stored in frame `b` at `center_m`, rotated by `rpy_rad`, expressed in frame
    /// `a`.
    fn new(
        a_from_b: &Isometry3<f64>,
        center_m: &Point3<f64>,
        rpy_rad: &Vector3<f64>,
        half: SVector<f64, D>,
    ) -> Self {
        let frame_from_local = a_from_b.rotation.to_rotation_matrix() * box_rotation(rpy_rad);
        Self {
            c: (a_from_b * center_m).coords,
            local_from_frame: frame_from_local.inverse().into_inner(),
            half,
        }
    }
}

impl Oriented<3> {
    /// The box's surface point closest to `p` (posed frame), its outward normal and the
    /// signed distance.
    fn closest(&self, p: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>, f64) {
        let Oriented {
            c,
            local_from_frame,
            half,
        } = self;
        let q = local_from_frame * (p - c);
        let clamped = q.zip_map(half, |v, h| v.clamp(-h, h));
        let world_from_local = local_from_frame.transpose();
        if clamped != q {
            let out = q - clamped;
            (
                c + world_from_local * clamped,
                world_from_local * out.normalize(),
                out.norm(),
            )
        } else {
            let gap = half - q.abs();
            let axis = gap.imin();
            let sign = if q[axis] < 0.0 { -1.0 } else { 1.0 };
            let mut x = q;
            x[axis] = sign * half[axis];
            let mut n = Vector3::zeros();
            n[axis] = sign;
            (c + world_from_local * x, world_from_local * n, -gap[axis])
        }
    }
}

impl Solid {
    /// `shape` (stored in frame `b`) expressed in frame `a`.
    pub fn new(shape: &Shape, a_from_b: &Isometry3<f64>) -> Self {
        let rot = |rpy: &Vector3<f64>| -> Rotation3<f64> {
            a_from_b.rotation.to_rotation_matrix() * box_rotation(rpy)
        };
        let pos = |p: &Point3<f64>| (a_from_b * p).coords;
        let (kind, bound_center, bound_radius) = match shape {
            Shape::Sphere { center_m, radius_m } => {
                let c = pos(center_m);
                (SolidKind::Sphere { c, r: *radius_m }, c, *radius_m)
            }
            Shape::Ellipsoid {
                center_m,
                radii_m,
                rpy_rad,
            } => {
                let c = pos(center_m);
                let local_from_frame = rot(rpy_rad).inverse().into_inner();
                let unit_from_frame =
                    Matrix3::from_diagonal(&radii_m.map(|r| 1.0 / r)) * local_from_frame;
                (
                    SolidKind::Ellipsoid {
                        c,
                        local_from_frame,
                        radii: *radii_m,
                        unit_from_frame,
                    },
                    c,
                    radii_m.max(),
                )
            }
            Shape::Capsule { a_m, b_m, radius_m } => {
                let (a, b) = (pos(a_m), pos(b_m));
                (
                    SolidKind::Capsule { a, b, r: *radius_m },
                    (a + b) * 0.5,
                    (b - a).norm() * 0.5 + radius_m,
                )
            }
            Shape::Box {
                center_m,
                half_extents_m,
                rpy_rad,
                rounding_m,
            } => {
                let r = *rounding_m;
                let o = Oriented::new(a_from_b, center_m, rpy_rad, half_extents_m.add_scalar(-r));
                let c = o.c;
                let kind = if r > 0.0 {
                    SolidKind::Rounded { inner: o, r }
                } else {
                    SolidKind::Box(o)
                };
                (kind, c, half_extents_m.norm())
            }
            Shape::PlanePatch {
                center_m,
                half_extents_m,
                rpy_rad,
            } => {
                let o = Oriented::new(a_from_b, center_m, rpy_rad, *half_extents_m);
                let c = o.c;
                (SolidKind::Plane(o), c, half_extents_m.norm())
            }
        };
        Self {
            ray: RayPre::new(&kind),
            kind,
            bound_center,
            bound_radius,
        }
    }

    /// Corners of a convex polytope containing the solid (for screen-space bounds).
    pub fn hull_corners(&self) -> Vec<Vector3<f64>> {
        let signs = |i: usize| {
            Vector3::new(
                if i & 1 == 0 { -1.0 } else { 1.0 },
                if i & 2 == 0 { -1.0 } else { 1.0 },
                if i & 4 == 0 { -1.0 } else { 1.0 },
            )
        };
        let oriented = |c: &Vector3<f64>, local_from_frame: &Matrix3<f64>, half: Vector3<f64>| {
            (0..8)
                .map(|i| c + local_from_frame.transpose() * signs(i).component_mul(&half))
                .collect()
        };
        match &self.kind {
            SolidKind::Sphere { c, r } => oriented(c, &Matrix3::identity(), Vector3::repeat(*r)),
            SolidKind::Ellipsoid {
                c,
                local_from_frame,
                radii,
                ..
            } => oriented(c, local_from_frame, *radii),
            SolidKind::Capsule { a, b, r } => {
                let lo = a.inf(b).add_scalar(-r);
                let hi = a.sup(b).add_scalar(*r);
                oriented(&((lo + hi) * 0.5), &Matrix3::identity(), (hi - lo) * 0.5)
            }
            SolidKind::Box(Oriented {
                c,
                local_from_frame,
                half,
            }) => oriented(c, local_from_frame, *half),
            SolidKind::Rounded {
                inner:
                    Oriented {
                        c,
                        local_from_frame,
                        half,
                    },
                r,
            } => oriented(c, local_from_frame, half.add_scalar(*r)),
            SolidKind::Plane(Oriented {
                c,
                local_from_frame,
                half,
            }) => {
                let corners: Vec<Vector3<f64>> =
                    oriented(c, local_from_frame, Vector3::new(half.x, half.y, 0.0));
                corners.into_iter().take(4).collect()
            }
        }
    }

    /// Smallest `t > 0` with `t d` on the surface (ray from the frame's origin), if any.
    #[inline]
    pub fn ray_hit(&self, d: &Vector3<f64>) -> Option<f64> {
        match &self.ray {
            RayPre::Quadric { m, cu, cc } => {
                let du = m * d;
                quadric_root(du.norm_squared(), du.dot(cu), *cc)
            }
            RayPre::Capsule {
                a,
                b,
                ba,
                baba,
                baoa,
                qc,
                cap_a,
                cap_b,
            } => {
                // Cylinder body (Quilez's capsule intersection with the ray origin at 0).
                let dd = d.norm_squared();
                let bard = ba.dot(d);
                let rdoa = -d.dot(a);
                let qa = baba * dd - bard * bard;
                let qb = baba * rdoa - baoa * bard;
                if qa > 0.0 {
                    let disc = qb * qb - qa * qc;
                    if disc < 0.0 {
                        // Misses the infinite cylinder, hence both caps.
                        return None;
                    }
                    let t = (-qb - disc.sqrt()) / qa;
                    let y = baoa + t * bard;
                    if t > 0.0 && y > 0.0 && y < *baba {
                        return Some(t);
                    }
                }
                // The caps: the nearer ball hit (a ray entering the capsule through a cap
                // meets that cap's ball first).
                let hit_a = quadric_root(dd, d.dot(a), *cap_a);
                let hit_b = quadric_root(dd, d.dot(b), *cap_b);
                match (hit_a, hit_b) {
                    (Some(x), Some(y)) => Some(x.min(y)),
                    (x, y) => x.or(y),
                }
            }
            RayPre::Box {
                local_from_frame,
                ol,
                half,
            } => {
                let dl = local_from_frame * d;
                let mut t_near = f64::NEG_INFINITY;
                let mut t_far = f64::INFINITY;
                for i in 0..3 {
                    if dl[i] == 0.0 {
                        if ol[i].abs() > half[i] {
                            return None;
                        }
                        continue;
                    }
                    let inv = 1.0 / dl[i];
                    let t0 = (-half[i] - ol[i]) * inv;
                    let t1 = (half[i] - ol[i]) * inv;
                    t_near = t_near.max(t0.min(t1));
                    t_far = t_far.min(t0.max(t1));
                }
                if t_near > t_far || t_far <= 0.0 {
                    None
                } else if t_near > 0.0 {
                    Some(t_near)
                } else {
                    Some(t_far)
                }
            }
            RayPre::Plane {
                local_from_frame,
                n,
                nc,
                c,
                half,
            } => {
                let dn = n.dot(d);
                if dn == 0.0 {
                    return None;
                }
                let t = nc / dn;
                if t <= 0.0 {
                    return None;
                }
                let q = local_from_frame * (d * t - c);
                (q.x.abs() <= half.x && q.y.abs() <= half.y).then_some(t)
            }
            RayPre::Rounded {
                outer,
                inner,
                pieces,
            } => {
                let t = outer.ray_hit(d)?;
                // On a flat face of the outer box (at most one coordinate beyond the inner
                // box) the outer hit is on the rounded surface, hence its first point.
                let q = inner.local_from_frame * (d * t - inner.c);
                let beyond = (0..3).filter(|&i| q[i].abs() > inner.half[i]).count();
                if beyond <= 1 {
                    return Some(t);
                }
                pieces
                    .iter()
                    .filter_map(|p| p.ray_hit(d))
                    .min_by(f64::total_cmp)
            }
        }
    }

    /// Outward unit normal at a surface point `p` (a plane patch returns its +z axis).
    pub fn normal_at(&self, p: &Vector3<f64>) -> Vector3<f64> {
        match &self.kind {
            SolidKind::Sphere { c, .. } => (p - c).normalize(),
            SolidKind::Ellipsoid {
                c,
                local_from_frame,
                radii,
                ..
            } => {
                let q = local_from_frame * (p - c);
                let g = q.component_div(&radii.component_mul(radii));
                (local_from_frame.transpose() * g).normalize()
            }
            SolidKind::Capsule { a, b, .. } => {
                let s =
                    closest_point_on_segment(&Point3::from(*a), &Point3::from(*b), &(*p).into());
                (p - s.coords).normalize()
            }
            SolidKind::Box(Oriented {
                c,
                local_from_frame,
                half,
            }) => {
                let q = local_from_frame * (p - c);
                let gap = half - q.abs();
                let axis = gap.imin();
                let mut n = Vector3::zeros();
                n[axis] = q[axis].signum();
                local_from_frame.transpose() * n
            }
            SolidKind::Plane(Oriented {
                local_from_frame, ..
            }) => local_from_frame.row(2).transpose(),
            SolidKind::Rounded { inner, .. } => {
                let q = inner.local_from_frame * (p - inner.c);
                let out = q - q.zip_map(&inner.half, |v, h| v.clamp(-h, h));
                inner.local_from_frame.transpose() * out.normalize()
            }
        }
    }

    /// The surface point closest to `p`, its outward normal and the signed distance.
    pub fn closest(&self, p: &Point3<f64>) -> Closest {
        let p = p.coords;
        let (point, normal, distance) = match &self.kind {
            SolidKind::Sphere { c, r } => {
                let n = unit_or_z(p - c);
                (c + n * *r, n, (p - c).norm() - r)
            }
            SolidKind::Capsule { a, b, r } => {
                let s = closest_point_on_segment(&Point3::from(*a), &Point3::from(*b), &p.into())
                    .coords;
                let n = unit_or_perpendicular(p - s, b - a);
                (s + n * *r, n, (p - s).norm() - r)
            }
            SolidKind::Ellipsoid {
                c,
                local_from_frame,
                radii,
                ..
            } => {
                let q = local_from_frame * (p - c);
                let x = closest_on_ellipsoid(radii, &q);
                let g = x.component_div(&radii.component_mul(radii)).normalize();
                let inside = (q.component_div(radii)).norm_squared() < 1.0;
                let dist = (q - x).norm();
                let world_from_local = local_from_frame.transpose();
                (
                    c + world_from_local * x,
                    world_from_local * g,
                    if inside { -dist } else { dist },
                )
            }
            SolidKind::Box(o) => o.closest(&p),
            SolidKind::Rounded { inner, r } => {
                // The surface of a convex solid swept by a ball is its own pushed out by the
                // ball's radius, along the normal, inside and out.
                let (x, n, d) = inner.closest(&p);
                (x + n * *r, n, d - r)
            }
            SolidKind::Plane(Oriented {
                c,
                local_from_frame,
                half,
            }) => {
                let q = local_from_frame * (p - c);
                let x = Vector3::new(q.x.clamp(-half.x, half.x), q.y.clamp(-half.y, half.y), 0.0);
                let world_from_local = local_from_frame.transpose();
                let off = q - x;
                let n_local = if off.norm_squared() > 0.0 && (off.x != 0.0 || off.y != 0.0) {
                    off.normalize()
                } else if q.z < 0.0 {
                    -Vector3::z()
                } else {
                    Vector3::z()
                };
                (
                    c + world_from_local * x,
                    world_from_local * n_local,
                    off.norm(),
                )
            }
        };
        Closest {
            point_m: point.into(),
            normal,
            distance_m: distance,
        }
    }

    /// Signed distance of `p` from the surface (negative inside; a plane patch is unsigned).
    pub fn signed_distance(&self, p: &Point3<f64>) -> f64 {
        self.closest(p).distance_m
    }
}

fn unit_or_z(v: Vector3<f64>) -> Vector3<f64> {
    v.try_normalize(0.0).unwrap_or_else(Vector3::z)
}

/// `v` normalised; when `v` vanishes, any unit vector perpendicular to `axis`.
fn unit_or_perpendicular(v: Vector3<f64>, axis: Vector3<f64>) -> Vector3<f64> {
    v.try_normalize(0.0).unwrap_or_else(|| {
        let helper = if axis.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        axis.cross(&helper)
            .try_normalize(0.0)
            .unwrap_or_else(Vector3::z)
    })
}

/// First positive root of `dd t^2 - 2 b t + cc = 0` (the ray `t d` against a ball: `dd =
/// |d|^2`, `b = d.c`, `cc = |c|^2 - r^2`), computed without cancellation.
#[inline]
fn quadric_root(dd: f64, b: f64, cc: f64) -> Option<f64> {
    let disc = b * b - dd * cc;
    if disc < 0.0 {
        return None;
    }
    let s = disc.sqrt();
    // Stable roots: q = b + sign(b) s; t0 = cc / q, t1 = q / dd.
    let q = if b >= 0.0 { b + s } else { b - s };
    let (ta, tb) = if q == 0.0 {
        (0.0, 0.0)
    } else {
        (cc / q, q / dd)
    };
    let (t0, t1) = if ta <= tb { (ta, tb) } else { (tb, ta) };
    if t0 > 0.0 {
        Some(t0)
    } else if t1 > 0.0 {
        Some(t1)
    } else {
        None
    }
}

/// Closest point on the ellipsoid `sum (x_i / e_i)^2 = 1` to `y`, all in the ellipsoid's axes
/// (Eberly 2013, robust for points inside, outside and on the symmetry planes).
fn closest_on_ellipsoid(e: &Vector3<f64>, y: &Vector3<f64>) -> Vector3<f64> {
    // Sort the axes by decreasing semi-axis and work in the first octant.
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| e[j].total_cmp(&e[i]));
    let es = [e[order[0]], e[order[1]], e[order[2]]];
    let ys = [y[order[0]].abs(), y[order[1]].abs(), y[order[2]].abs()];
    let xs = ellipsoid_octant(es, ys);
    let mut x = Vector3::zeros();
    for k in 0..3 {
        x[order[k]] = xs[k].copysign(y[order[k]]);
    }
    x
}

fn ellipsoid_octant(e: [f64; 3], y: [f64; 3]) -> [f64; 3] {
    if y[2] > 0.0 {
        if y[1] > 0.0 {
            if y[0] > 0.0 {
                let z = [y[0] / e[0], y[1] / e[1], y[2] / e[2]];
                let g = z[0] * z[0] + z[1] * z[1] + z[2] * z[2] - 1.0;
                if g != 0.0 {
                    let r0 = (e[0] / e[2]).powi(2);
                    let r1 = (e[1] / e[2]).powi(2);
                    let s = root3(r0, r1, z, g);
                    [r0 * y[0] / (s + r0), r1 * y[1] / (s + r1), y[2] / (s + 1.0)]
                } else {
                    y
                }
            } else {
                let [x1, x2] = ellipse_quadrant([e[1], e[2]], [y[1], y[2]]);
                [0.0, x1, x2]
            }
        } else if y[0] > 0.0 {
            let [x0, x2] = ellipse_quadrant([e[0], e[2]], [y[0], y[2]]);
            [x0, 0.0, x2]
        } else {
            [0.0, 0.0, e[2]]
        }
    } else {
        let denom = [e[0] * e[0] - e[2] * e[2], e[1] * e[1] - e[2] * e[2]];
        let numer = [e[0] * y[0], e[1] * y[1]];
        if numer[0] < denom[0] && numer[1] < denom[1] {
            let xde = [numer[0] / denom[0], numer[1] / denom[1]];
            let discr = 1.0 - xde[0] * xde[0] - xde[1] * xde[1];
            if discr > 0.0 {
                return [e[0] * xde[0], e[1] * xde[1], e[2] * discr.sqrt()];
            }
        }
        let [x0, x1] = ellipse_quadrant([e[0], e[1]], [y[0], y[1]]);
        [x0, x1, 0.0]
    }
}

fn ellipse_quadrant(e: [f64; 2], y: [f64; 2]) -> [f64; 2] {
    if y[1] > 0.0 {
        if y[0] > 0.0 {
            let z = [y[0] / e[0], y[1] / e[1]];
            let g = z[0] * z[0] + z[1] * z[1] - 1.0;
            if g != 0.0 {
                let r0 = (e[0] / e[1]).powi(2);
                let s = root2(r0, z, g);
                [r0 * y[0] / (s + r0), y[1] / (s + 1.0)]
            } else {
                y
            }
        } else {
            [0.0, e[1]]
        }
    } else {
        let numer = e[0] * y[0];
        let denom = e[0] * e[0] - e[1] * e[1];
        if numer < denom {
            let xde = numer / denom;
            [e[0] * xde, e[1] * (1.0 - xde * xde).max(0.0).sqrt()]
        } else {
            [e[0], 0.0]
        }
    }
}

/// Bisection for the root `s` of `(r0 z0/(s+r0))^2 + (z1/(s+1))^2 = 1` (Eberly's GetRoot).
fn root2(r0: f64, z: [f64; 2], g: f64) -> f64 {
    let n0 = r0 * z[0];
    let mut s0 = z[1] - 1.0;
    let mut s1 = if g < 0.0 { 0.0 } else { n0.hypot(z[1]) - 1.0 };
    bisect(&mut s0, &mut s1, |s| {
        (n0 / (s + r0)).powi(2) + (z[1] / (s + 1.0)).powi(2) - 1.0
    })
}

fn root3(r0: f64, r1: f64, z: [f64; 3], g: f64) -> f64 {
    let (n0, n1) = (r0 * z[0], r1 * z[1]);
    let mut s0 = z[2] - 1.0;
    let mut s1 = if g < 0.0 {
        0.0
    } else {
        (n0 * n0 + n1 * n1 + z[2] * z[2]).sqrt() - 1.0
    };
    bisect(&mut s0, &mut s1, |s| {
        (n0 / (s + r0)).powi(2) + (n1 / (s + r1)).powi(2) + (z[2] / (s + 1.0)).powi(2) - 1.0
    })
}

/// Bisects a decreasing function on `[s0, s1]` until the interval stops shrinking (at most
/// 1100 halvings, enough to exhaust f64).
fn bisect(s0: &mut f64, s1: &mut f64, f: impl Fn(f64) -> f64) -> f64 {
    let mut s = *s0;
    for _ in 0..1100 {
        s = 0.5 * (*s0 + *s1);
        if s == *s0 || s == *s1 {
            break;
        }
        let g = f(s);
        if g > 0.0 {
            *s0 = s;
        } else if g < 0.0 {
            *s1 = s;
        } else {
            break;
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};
    use proptest::prelude::*;

    fn shapes() -> Vec<Shape> {
        vec![
            Shape::Sphere {
                center_m: Point3::new(0.05, -0.02, 1.0),
                radius_m: 0.1,
            },
            Shape::Ellipsoid {
                center_m: Point3::new(-0.03, 0.04, 0.9),
                radii_m: Vector3::new(0.10, 0.078, 0.115),
                rpy_rad: Vector3::new(0.3, -0.2, 0.5),
            },
            Shape::Capsule {
                a_m: Point3::new(-0.1, 0.0, 0.8),
                b_m: Point3::new(0.1, 0.05, 1.1),
                radius_m: 0.045,
            },
            Shape::Box {
                center_m: Point3::new(0.0, 0.0, 1.2),
                half_extents_m: Vector3::new(0.11, 0.18, 0.07),
                rpy_rad: Vector3::new(0.2, 0.4, -0.3),
                rounding_m: 0.0,
            },
            Shape::Box {
                center_m: Point3::new(0.02, -0.03, 0.95),
                half_extents_m: Vector3::new(0.10, 0.17, 0.12),
                rpy_rad: Vector3::new(-0.3, 0.5, 0.4),
                rounding_m: 0.05,
            },
            Shape::PlanePatch {
                center_m: Point3::new(0.0, 0.1, 0.7),
                half_extents_m: Vector2::new(0.15, 0.1),
                rpy_rad: Vector3::new(1.2, 0.0, 0.3),
            },
        ]
    }

    fn pose() -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(0.01, -0.02, 0.03),
            UnitQuaternion::from_euler_angles(0.05, -0.04, 0.1),
        )
    }

    proptest! {
        /// A ray hit lies on the surface: the exact closest-point distance there is ~0.
        #[test]
        fn ray_hits_lie_on_the_surface(u in -0.25f64..0.25, v in -0.25f64..0.25, k in 0usize..6) {
            let solid = Solid::new(&shapes()[k], &pose());
            let d = Vector3::new(u, v, 1.0);
            if let Some(t) = solid.ray_hit(&d) {
                let p = Point3::from(d * t);
                prop_assert!(solid.signed_distance(&p).abs() < 1e-12, "{k}: {}", solid.signed_distance(&p));
                prop_assert!(t > 0.0);
            }
        }

        /// The closest point beats every surface point found by dense ray sampling.
        #[test]
        fn closest_point_is_closest(px in -0.3f64..0.3, py in -0.3f64..0.3, pz in 0.5f64..1.5, k in 0usize..6) {
            let solid = Solid::new(&shapes()[k], &pose());
            let p = Point3::new(px, py, pz);
            let c = solid.closest(&p);
            // The reported point lies on the surface and the distance is consistent.
            prop_assert!(solid.signed_distance(&c.point_m).abs() < 1e-9);
            prop_assert!(((p - c.point_m).norm() - c.distance_m.abs()).abs() < 1e-9);
            prop_assert!((c.normal.norm() - 1.0).abs() < 1e-12);
            for i in 0..40 {
                for j in 0..40 {
                    let d = Vector3::new(-0.4 + 0.02 * f64::from(i), -0.4 + 0.02 * f64::from(j), 1.0);
                    if let Some(t) = solid.ray_hit(&d) {
                        prop_assert!((p - Point3::from(d * t)).norm() >= c.distance_m.abs() - 1e-9);
                    }
                }
            }
        }
    }

    #[test]
    fn normals_point_outward() {
        for (k, shape) in shapes().iter().enumerate().take(5) {
            let solid = Solid::new(shape, &pose());
            let d = (solid.bound_center + Vector3::new(0.01, 0.005, 0.0)).normalize();
            let t = solid.ray_hit(&d).unwrap();
            let p = d * t;
            let n = solid.normal_at(&p);
            assert!(n.dot(&d) < 0.0, "{k}: normal faces the camera");
            let outside = Point3::from(p + n * 1e-4);
            assert!((solid.signed_distance(&outside) - 1e-4).abs() < 1e-7, "{k}");
        }
    }

    #[test]
    fn ellipsoid_closest_on_symmetry_planes_and_inside() {
        let shape = Shape::Ellipsoid {
            center_m: Point3::origin(),
            radii_m: Vector3::new(0.3, 0.2, 0.1),
            rpy_rad: Vector3::zeros(),
        };
        let s = Solid::new(&shape, &Isometry3::identity());
        let c = s.closest(&Point3::new(0.0, 0.0, 0.5));
        assert!((c.point_m - Point3::new(0.0, 0.0, 0.1)).norm() < 1e-12);
        assert!((c.distance_m - 0.4).abs() < 1e-12);
        let c = s.closest(&Point3::origin());
        assert!((c.distance_m + 0.1).abs() < 1e-12, "{c:?}");
        let c = s.closest(&Point3::new(0.05, 0.02, 0.0));
        assert!(c.distance_m < 0.0);
        assert!(s.signed_distance(&c.point_m).abs() < 1e-12);
    }

    /// A rounded box keeps its faces and pulls its corners in: beyond a corner the distance is
    /// to the inner box's corner less the rounding; a rounding beyond a half extent is named.
    #[test]
    fn rounded_box_keeps_faces_and_rounds_corners() {
        let shape = |rounding_m| Shape::Box {
            center_m: Point3::origin(),
            half_extents_m: Vector3::new(0.10, 0.17, 0.26),
            rpy_rad: Vector3::zeros(),
            rounding_m,
        };
        let s = Solid::new(&shape(0.05), &Isometry3::identity());
        let face = s.closest(&Point3::new(0.3, 0.02, -0.1));
        assert!((face.distance_m - 0.2).abs() < 1e-12, "{face:?}");
        let corner = Point3::new(0.2, 0.27, 0.36);
        let inner = Point3::new(0.05, 0.12, 0.21);
        let c = s.closest(&corner);
        assert!((c.distance_m - ((corner - inner).norm() - 0.05)).abs() < 1e-12);
        let sharp = Solid::new(&shape(0.0), &Isometry3::identity()).closest(&corner);
        assert!(c.distance_m > sharp.distance_m + 0.03);
        assert!(shape(0.05).validate().is_ok());
        assert_eq!(
            shape(0.11).validate().unwrap_err(),
            "rounding_m = 0.11 must be between 0 and the smallest half extent (0.1 m)"
        );
    }

    #[test]
    fn validate_names_the_bad_value() {
        let bad = Shape::Capsule {
            a_m: Point3::origin(),
            b_m: Point3::new(0.0, 0.0, 0.3),
            radius_m: 0.0,
        };
        assert_eq!(
            bad.validate().unwrap_err(),
            "radius_m must be positive, got 0 m"
        );
    }
}
