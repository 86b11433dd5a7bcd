//! Collision primitives shared by the robot model, the crop stage and the scene simulator.
//!
//! Paper section IV-A attaches primitive objects (spheres, capsules, boxes) to the robot's
//! links and removes every cloud point inside one of them. A primitive is stored in the frame
//! it was defined in (a link frame in the robot model, the cloud frame once posed) and moved
//! between frames with [`Primitive::transformed`]. All values are `f64` metres.

use nalgebra::{Isometry3, Point3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};

/// A convex collision primitive, in the frame of whoever holds it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shape", rename_all = "snake_case", deny_unknown_fields)]
pub enum Primitive {
    /// Ball of `radius_m` around `center_m`.
    Sphere {
        center_m: Point3<f64>,
        radius_m: f64,
    },
    /// Segment `a_m`..`b_m` swept by a ball of `radius_m`.
    Capsule {
        a_m: Point3<f64>,
        b_m: Point3<f64>,
        radius_m: f64,
    },
    /// Box with half side lengths `half_extents_m`, centred at `center_m` and rotated by
    /// roll-pitch-yaw `rpy_rad` (fixed axes x, then y, then z).
    OrientedBox {
        center_m: Point3<f64>,
        #[serde(default)]
        rpy_rad: Vector3<f64>,
        half_extents_m: Vector3<f64>,
    },
}

/// Largest coordinate and size of a primitive (m): a robot is a few metres across; beyond
/// this a value is a typo or a unit mix-up (a sphere of 1e300 m swallows every point).
pub const MAX_PRIMITIVE_M: f64 = 100.0;

/// Why a primitive is unusable.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PrimitiveError {
    #[error("primitive {name} must be finite and within +-{bound}, got {value}")]
    OutOfRange {
        name: &'static str,
        value: f64,
        bound: f64,
    },
    #[error("primitive {name} must be above 0 and at most {MAX_PRIMITIVE_M} m, got {value}")]
    BadSize { name: &'static str, value: f64 },
}

impl Primitive {
    /// Checks that every coordinate is within [`MAX_PRIMITIVE_M`] (angles within one turn)
    /// and every size above 0 and at most [`MAX_PRIMITIVE_M`].
    pub fn validate(&self) -> Result<(), PrimitiveError> {
        let turn = std::f64::consts::TAU;
        // (field, value, largest magnitude) and (field, size)
        type Coordinate = (&'static str, f64, f64);
        type Size = (&'static str, f64);
        let (coords, sizes): (Vec<Coordinate>, Vec<Size>) = match self {
            Primitive::Sphere { center_m, radius_m } => (
                center_m
                    .iter()
                    .map(|&v| ("center_m", v, MAX_PRIMITIVE_M))
                    .collect(),
                vec![("radius_m", *radius_m)],
            ),
            Primitive::Capsule { a_m, b_m, radius_m } => (
                a_m.iter()
                    .map(|&v| ("a_m", v, MAX_PRIMITIVE_M))
                    .chain(b_m.iter().map(|&v| ("b_m", v, MAX_PRIMITIVE_M)))
                    .collect(),
                vec![("radius_m", *radius_m)],
            ),
            Primitive::OrientedBox {
                center_m,
                rpy_rad,
                half_extents_m,
            } => (
                center_m
                    .iter()
                    .map(|&v| ("center_m", v, MAX_PRIMITIVE_M))
                    .chain(rpy_rad.iter().map(|&v| ("rpy_rad", v, turn)))
                    .collect(),
                half_extents_m
                    .iter()
                    .map(|&v| ("half_extents_m", v))
                    .collect(),
            ),
        };
        if let Some(&(name, value, bound)) =
            coords.iter().find(|(_, v, b)| v.is_nan() || v.abs() > *b)
        {
            return Err(PrimitiveError::OutOfRange { name, value, bound });
        }
        match sizes
            .into_iter()
            .find(|&(_, v)| !(v > 0.0 && v <= MAX_PRIMITIVE_M))
        {
            Some((name, value)) => Err(PrimitiveError::BadSize { name, value }),
            None => Ok(()),
        }
    }

    /// Signed distance from `p` to the surface: negative inside, zero on it, positive outside.
    pub fn signed_distance(&self, p: &Point3<f64>) -> f64 {
        match self {
            Primitive::Sphere { center_m, radius_m } => (p - center_m).norm() - radius_m,
            Primitive::Capsule { a_m, b_m, radius_m } => {
                (p - closest_point_on_segment(a_m, b_m, p)).norm() - radius_m
            }
            Primitive::OrientedBox {
                center_m,
                rpy_rad,
                half_extents_m,
            } => box_signed_distance(
                &box_rotation(rpy_rad).inverse(),
                center_m,
                half_extents_m,
                p,
            ),
        }
    }

    /// True when `p` lies inside or on the primitive.
    pub fn contains(&self, p: &Point3<f64>) -> bool {
        self.signed_distance(p) <= 0.0
    }

    /// The primitive prepared for many point queries, e.g. a frame's crop.
    pub fn prepared(&self) -> PreparedPrimitive {
        let (bound_center_m, bound_radius_m, shape) = match self {
            Primitive::Sphere { center_m, radius_m } => {
                (*center_m, *radius_m, PreparedShape::Other(self.clone()))
            }
            Primitive::Capsule { a_m, b_m, radius_m } => (
                nalgebra::center(a_m, b_m),
                0.5 * (b_m - a_m).norm() + radius_m,
                PreparedShape::Other(self.clone()),
            ),
            Primitive::OrientedBox {
                center_m,
                rpy_rad,
                half_extents_m,
            } => (
                *center_m,
                half_extents_m.norm(),
                PreparedShape::OrientedBox {
                    center_m: *center_m,
                    box_from_frame: box_rotation(rpy_rad).inverse(),
                    half_extents_m: *half_extents_m,
                },
            ),
        };
        // Wider than any rounding of the distances (m-scale values, f64).
        let bound_radius_m = bound_radius_m * (1.0 + 1e-9) + 1e-9;
        PreparedPrimitive {
            bound_center_m,
            bound_r2: bound_radius_m * bound_radius_m,
            shape,
        }
    }

    /// The primitive grown by `margin_m` on every side (sphere and capsule radii, box half
    /// extents; a grown box stays a box, so it also covers its corners' neighbourhood).
    pub fn grown(&self, margin_m: f64) -> Primitive {
        match self {
            Primitive::Sphere { center_m, radius_m } => Primitive::Sphere {
                center_m: *center_m,
                radius_m: radius_m + margin_m,
            },
            Primitive::Capsule { a_m, b_m, radius_m } => Primitive::Capsule {
                a_m: *a_m,
                b_m: *b_m,
                radius_m: radius_m + margin_m,
            },
            Primitive::OrientedBox {
                center_m,
                rpy_rad,
                half_extents_m,
            } => Primitive::OrientedBox {
                center_m: *center_m,
                rpy_rad: *rpy_rad,
                half_extents_m: half_extents_m.add_scalar(margin_m),
            },
        }
    }

    /// The same primitive expressed in frame `a`, given the transform `a_from_b` from the
    /// frame `b` it is stored in.
    pub fn transformed(&self, a_from_b: &Isometry3<f64>) -> Primitive {
        match self {
            Primitive::Sphere { center_m, radius_m } => Primitive::Sphere {
                center_m: a_from_b * center_m,
                radius_m: *radius_m,
            },
            Primitive::Capsule { a_m, b_m, radius_m } => Primitive::Capsule {
                a_m: a_from_b * a_m,
                b_m: a_from_b * b_m,
                radius_m: *radius_m,
            },
            Primitive::OrientedBox {
                center_m,
                rpy_rad,
                half_extents_m,
            } => {
                let rotation = a_from_b.rotation.to_rotation_matrix() * box_rotation(rpy_rad);
                let (roll, pitch, yaw) = rotation.euler_angles();
                Primitive::OrientedBox {
                    center_m: a_from_b * center_m,
                    rpy_rad: Vector3::new(roll, pitch, yaw),
                    half_extents_m: *half_extents_m,
                }
            }
        }
    }
}

/// Rotation of an [`Primitive::OrientedBox`] from its roll-pitch-yaw angles.
pub fn box_rotation(rpy_rad: &Vector3<f64>) -> Rotation3<f64> {
    Rotation3::from_euler_angles(rpy_rad.x, rpy_rad.y, rpy_rad.z)
}

/// Signed distance from `p` to a box given the rotation from its parent frame into the box's.
fn box_signed_distance(
    box_from_frame: &Rotation3<f64>,
    center_m: &Point3<f64>,
    half_extents_m: &Vector3<f64>,
    p: &Point3<f64>,
) -> f64 {
    let q = (box_from_frame * (p - center_m)).abs() - half_extents_m;
    let outside = q.map(|v| v.max(0.0)).norm();
    let inside = q.max().min(0.0);
    outside + inside
}

/// A [`Primitive`] prepared for many point queries: a bounding sphere rejects the points far
/// from it, and a box's rotation is computed once (three sines and cosines per query
/// otherwise); what is left is the arithmetic of [`Primitive::contains`], so the answers are
/// the same.
#[derive(Clone, Debug, PartialEq)]
pub struct PreparedPrimitive {
    bound_center_m: Point3<f64>,
    bound_r2: f64,
    shape: PreparedShape,
}

#[derive(Clone, Debug, PartialEq)]
enum PreparedShape {
    OrientedBox {
        center_m: Point3<f64>,
        box_from_frame: Rotation3<f64>,
        half_extents_m: Vector3<f64>,
    },
    Other(Primitive),
}

impl PreparedPrimitive {
    /// The bounding sphere: its centre and squared radius (no point outside it lies inside
    /// the primitive).
    pub fn bounding_ball(&self) -> (Point3<f64>, f64) {
        (self.bound_center_m, self.bound_r2)
    }

    /// False when no point within `radius_m` of the segment `a_m`-`b_m` (a ball when they
    /// coincide) lies inside the primitive: its bounding sphere does not meet that capsule
    /// (1 um of slack for rounding).
    pub fn may_meet_capsule(&self, a_m: &Point3<f64>, b_m: &Point3<f64>, radius_m: f64) -> bool {
        let reach = self.bound_r2.sqrt() + radius_m + 1e-6;
        let nearest = closest_point_on_segment(a_m, b_m, &self.bound_center_m);
        (nearest - self.bound_center_m).norm_squared() <= reach * reach
    }

    /// True when `p` lies inside or on the primitive.
    pub fn contains(&self, p: &Point3<f64>) -> bool {
        if (p - self.bound_center_m).norm_squared() > self.bound_r2 {
            return false;
        }
        let distance = match &self.shape {
            PreparedShape::OrientedBox {
                center_m,
                box_from_frame,
                half_extents_m,
            } => box_signed_distance(box_from_frame, center_m, half_extents_m, p),
            PreparedShape::Other(primitive) => primitive.signed_distance(p),
        };
        distance <= 0.0
    }
}

/// The point of segment `a`..`b` closest to `p` (a degenerate segment returns `a`).
pub fn closest_point_on_segment(a: &Point3<f64>, b: &Point3<f64>, p: &Point3<f64>) -> Point3<f64> {
    let ab = b - a;
    let len2 = ab.norm_squared();
    if len2 <= f64::MIN_POSITIVE {
        return *a;
    }
    let t = ((p - a).dot(&ab) / len2).clamp(0.0, 1.0);
    a + ab * t
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};
    use proptest::prelude::*;

    #[test]
    fn box_distance_inside_and_outside() {
        let b = Primitive::OrientedBox {
            center_m: Point3::new(1.0, 0.0, 0.0),
            rpy_rad: Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2),
            half_extents_m: Vector3::new(0.5, 0.1, 0.1),
        };
        // Rotated 90 deg about z: the long axis now runs along y.
        assert!(b.contains(&Point3::new(1.0, 0.4, 0.0)));
        assert!(!b.contains(&Point3::new(1.4, 0.0, 0.0)));
        assert!((b.signed_distance(&Point3::new(1.0, 0.0, 0.0)) + 0.1).abs() < 1e-12);
    }

    #[test]
    fn transform_preserves_distances() {
        let prims = [
            Primitive::Sphere {
                center_m: Point3::new(0.1, 0.2, 0.3),
                radius_m: 0.05,
            },
            Primitive::Capsule {
                a_m: Point3::new(0.0, 0.0, 0.0),
                b_m: Point3::new(0.0, 0.3, 0.0),
                radius_m: 0.04,
            },
            Primitive::OrientedBox {
                center_m: Point3::new(0.2, 0.0, 0.1),
                rpy_rad: Vector3::new(0.3, -0.2, 0.9),
                half_extents_m: Vector3::new(0.1, 0.05, 0.02),
            },
        ];
        let a_from_b = Isometry3::from_parts(
            Translation3::new(0.5, -1.0, 2.0),
            UnitQuaternion::from_euler_angles(0.4, 1.1, -0.7),
        );
        let p_b = Point3::new(0.15, 0.1, 0.05);
        for prim in &prims {
            let moved = prim.transformed(&a_from_b);
            let d_b = prim.signed_distance(&p_b);
            let d_a = moved.signed_distance(&(a_from_b * p_b));
            assert!((d_a - d_b).abs() < 1e-12, "{prim:?}: {d_a} vs {d_b}");
        }
    }

    #[test]
    fn validate_rejects_bad_sizes() {
        let s = Primitive::Sphere {
            center_m: Point3::origin(),
            radius_m: -1.0,
        };
        assert_eq!(
            s.validate(),
            Err(PrimitiveError::BadSize {
                name: "radius_m",
                value: -1.0
            })
        );
        let huge = Primitive::Sphere {
            center_m: Point3::origin(),
            radius_m: 1e300,
        };
        assert!(
            huge.validate()
                .unwrap_err()
                .to_string()
                .contains("radius_m")
        );
        let c = Primitive::Capsule {
            a_m: Point3::new(f64::NAN, 0.0, 0.0),
            b_m: Point3::origin(),
            radius_m: 0.1,
        };
        assert!(matches!(
            c.validate(),
            Err(PrimitiveError::OutOfRange { name: "a_m", value, .. }) if value.is_nan()
        ));
    }

    fn any_primitive() -> impl Strategy<Value = Primitive> {
        let point = || prop::array::uniform3(-1.0..1.0f64).prop_map(Point3::from);
        prop_oneof![
            (point(), 0.01..0.3f64)
                .prop_map(|(center_m, radius_m)| Primitive::Sphere { center_m, radius_m }),
            (point(), point(), 0.01..0.3f64)
                .prop_map(|(a_m, b_m, radius_m)| { Primitive::Capsule { a_m, b_m, radius_m } }),
            (
                point(),
                prop::array::uniform3(-3.2..3.2f64),
                prop::array::uniform3(0.01..0.3f64)
            )
                .prop_map(|(center_m, rpy, half)| Primitive::OrientedBox {
                    center_m,
                    rpy_rad: Vector3::from(rpy),
                    half_extents_m: Vector3::from(half),
                }),
        ]
    }

    /// The points of a primitive farthest from its bounding sphere's centre: a box's
    /// corners, a capsule's cap tips.
    fn extreme_points(prim: &Primitive) -> Vec<Point3<f64>> {
        match prim {
            Primitive::Sphere { center_m, radius_m } => {
                vec![center_m + Vector3::new(*radius_m, 0.0, 0.0)]
            }
            Primitive::Capsule { a_m, b_m, radius_m } => {
                let axis = (b_m - a_m).try_normalize(1e-12).unwrap_or(Vector3::x());
                vec![a_m - axis * *radius_m, b_m + axis * *radius_m]
            }
            Primitive::OrientedBox {
                center_m,
                rpy_rad,
                half_extents_m: h,
            } => (0..8)
                .map(|k| {
                    let sign = |bit: i32| if k >> bit & 1 == 1 { 1.0 } else { -1.0 };
                    let corner = Vector3::new(sign(0) * h.x, sign(1) * h.y, sign(2) * h.z);
                    center_m + box_rotation(rpy_rad) * corner
                })
                .collect(),
        }
    }

    proptest! {
        #[test]
        fn prepared_primitives_answer_as_the_primitive_does(
            prim in any_primitive(),
            points in prop::collection::vec(prop::array::uniform3(-1.5..1.5f64), 64),
        ) {
            let prepared = prim.prepared();
            let extremes = extreme_points(&prim);
            for p in points.into_iter().map(Point3::from).chain(extremes) {
                prop_assert_eq!(prepared.contains(&p), prim.contains(&p), "{:?} at {}", prim, p);
            }
        }
    }

    #[test]
    fn grown_moves_every_surface_out_by_the_margin() {
        let p = Point3::new(0.1, 0.0, 0.0);
        for prim in [
            Primitive::Sphere {
                center_m: Point3::origin(),
                radius_m: 0.05,
            },
            Primitive::Capsule {
                a_m: Point3::new(0.0, -0.1, 0.0),
                b_m: Point3::new(0.0, 0.1, 0.0),
                radius_m: 0.05,
            },
            Primitive::OrientedBox {
                center_m: Point3::origin(),
                rpy_rad: Vector3::new(0.0, 0.0, 0.3),
                half_extents_m: Vector3::new(0.05, 0.05, 0.05),
            },
        ] {
            let (d0, d1) = (
                prim.signed_distance(&p),
                prim.grown(0.02).signed_distance(&p),
            );
            assert!((d0 - d1 - 0.02).abs() < 1e-12, "{prim:?}: {d0} -> {d1}");
        }
    }
}
