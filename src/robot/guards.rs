//! Guards: the parts of the exoskeleton the controller keeps track of against the patient's
//! body, each a sphere or a capsule (a segment swept by a ball) fixed on one link.
//!
//! - The **handle** guard is the haptic interaction point (paper section VI): the sphere of
//!   the HIP link, where haptic contact is allowed (eq. 7-14 as in [`crate::haptics`]).
//! - **Keep-off** guards (forearm, elbow, upper arm, shoulder mechanism) must never touch:
//!   the controller holds their `d_proj >= keep_off_margin_m`.
//!
//! Geometry comes from the URDF: a link's collision element (a sphere stays a sphere, a
//! capsule a capsule, a box becomes its circumscribing capsule along its longest axis) or the
//! HIP sphere, each inflated by the guard's `inflation_m`. Where the URDF has no element
//! for a part (ANYexo's elbow drive), a guard gives its sphere or capsule in the link frame.
//!
//! For a capsule, eq. 7 is taken at the point of its segment closest to the surface's
//! centroid, `p* = closest(a, b; c)`: `d_proj = (p* - c) . n - r`, and the constraint
//! Jacobian (eq. 8) is `n^T J(p*)` with `J(p*)` the translational Jacobian of `p*` as a
//! point of the guard's link ([`super::RobotModel::point_kinematics`]).
//!
//! Rules checked when a set is built ([`GuardSet::new`]): every guard names an existing link
//! and collision element; radii are positive; its core (centre or segment) lies on its link
//! (within its own radius of the link's collision geometry or of the link's bones, the
//! segments from the link's joint to its children's joints); names are unique; exactly one
//! guard is the handle, and it is the HIP sphere. Overlaps: a keep-off guard must not
//! overlap the handle in the zero configuration (exact for guards on the same rigid body,
//! whose relative pose never changes), because the handle is meant to touch the surface and
//! an overlapping keep-off guard would forbid that contact. Keep-off guards may overlap one
//! another (neighbours at a joint always do): each keeps its own geometry off, their rows
//! all ask the same (approach no closer than the margin), so a region covered twice is only
//! guarded twice.

use super::{JointVector, RobotModel};
use crate::geometry::{MAX_PRIMITIVE_M, Primitive, box_rotation};
use crate::haptics::bounds::{MAX_DISTANCE_M, positive_at_most, within};
use nalgebra::{Isometry3, Point3, Vector3};
use serde::{Deserialize, Serialize};

/// Most guards one robot may have (the control tick's buffers are sized for it).
pub const MAX_GUARDS: usize = 8;

/// Most surfaces one keep-off guard holds rows for (`surfaces_per_guard`).
pub const MAX_SURFACES_PER_GUARD: usize = 3;

/// Largest inflation of a guard, metres.
pub const MAX_INFLATION_M: f64 = 0.2;

/// Largest guard radius given in a config, metres.
pub const MAX_GUARD_RADIUS_M: f64 = 0.5;

/// What the controller does with a guard.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GuardRole {
    /// The HIP: haptic contact allowed (position, velocity and force rows, eq. 9-14).
    Handle,
    /// Never touches: position and velocity rows hold `d_proj >= keep_off_margin_m`.
    KeepOff,
}

/// A collision element's index, refused with the key's name when it is negative or not an
/// integer (serde's own error names only the enclosing table).
fn collision_index<'de, D: serde::Deserializer<'de>>(d: D) -> Result<usize, D::Error> {
    let index = i64::deserialize(d)?;
    usize::try_from(index).map_err(|_| {
        serde::de::Error::custom(format!("collision: element index {index} is negative"))
    })
}

/// Where a guard's sphere or capsule comes from, in its link's frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum GuardGeometry {
    /// The HIP sphere: the link's origin, the radius of the URDF's HIP visual sphere.
    Hip,
    /// The link's URDF collision element with this index (0 = the first).
    Collision(#[serde(deserialize_with = "collision_index")] usize),
    /// A ball of `radius_m` around `center_m`, link frame.
    Sphere { center_m: [f64; 3], radius_m: f64 },
    /// The segment `a_m`..`b_m` swept by a ball of `radius_m`, link frame.
    Capsule {
        a_m: [f64; 3],
        b_m: [f64; 3],
        radius_m: f64,
    },
}

/// One guard as configured.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GuardSpec {
    /// Name in errors, status and outputs (unique).
    pub name: String,
    /// URDF link the guard is fixed on.
    pub link: String,
    /// `handle` (haptic contact allowed) or `keep_off` (never touches).
    pub role: GuardRole,
    /// `"hip"`, `{ collision = INDEX }`, `{ sphere = { center_m, radius_m } }` or
    /// `{ capsule = { a_m, b_m, radius_m } }`.
    pub geometry: GuardGeometry,
    /// Added to the geometry's radius, metres, at least 0 and at most 0.2.
    #[serde(default)]
    pub inflation_m: f64,
}

/// The guards of one robot.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GuardConfig {
    /// Distance every keep-off guard keeps from the surface, `d_proj >= keep_off_margin_m`,
    /// metres, at least 0 and at most 2.
    pub keep_off_margin_m: f64,
    /// How many distinct surfaces each keep-off guard holds rows for, 1 to
    /// [`MAX_SURFACES_PER_GUARD`]: its own, then the nearest-to-reach of the others the
    /// controller knows (the handle's and the other keep-off guards'),
    /// [`crate::control::Controller::tick_guarded`].
    pub surfaces_per_guard: usize,
    /// The guards: exactly one `handle`, at most 8 in all. ANYexo's set by default; the
    /// handle alone is the paper's single-HIP mode.
    pub guards: Vec<GuardSpec>,
}

impl Default for GuardConfig {
    /// ANYexo's set (`robots/anyexo.urdf`): the HIP, the forearm, the elbow drive, the upper
    /// arm and the shoulder mechanism (abduction drive and rotation stage), inflated by 2 cm.
    fn default() -> Self {
        let keep_off = |name: &str, link: &str, geometry| GuardSpec {
            name: name.into(),
            link: link.into(),
            role: GuardRole::KeepOff,
            geometry,
            inflation_m: 0.02,
        };
        Self {
            keep_off_margin_m: 0.01,
            surfaces_per_guard: 1,
            guards: vec![
                Self::handle(),
                keep_off("forearm", "forearm_link", GuardGeometry::Collision(0)),
                // the elbow drive, lateral of the elbow joint: the URDF has no element there
                keep_off(
                    "elbow",
                    "forearm_link",
                    GuardGeometry::Sphere {
                        center_m: [0.0, -0.07, 0.0],
                        radius_m: 0.04,
                    },
                ),
                keep_off("upper_arm", "upper_arm_link", GuardGeometry::Collision(0)),
                // the abduction drive's 8 x 10 x 12 cm box (URDF collision 0) as a capsule
                // on its 12 cm axis, 6 cm long, radius 5.1 cm: with the 2 cm inflation it
                // holds every corner of the box; the box's circumscribing capsule (radius
                // 6.4 cm, ends 6.4 cm beyond the box's end faces) would reach 5 cm below the
                // shoulder joint, into the patient's own strapped shoulder
                keep_off(
                    "shoulder",
                    "shoulder_abduction_link",
                    GuardGeometry::Capsule {
                        a_m: [-0.05, -0.06, 0.06],
                        b_m: [-0.05, -0.06, 0.12],
                        radius_m: 0.051,
                    },
                ),
                keep_off(
                    "shoulder_rotation",
                    "shoulder_rotation_link",
                    GuardGeometry::Collision(0),
                ),
            ],
        }
    }
}

/// A bad guard configuration; the message names the guard and the value.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("guards: {0}")]
pub struct GuardError(pub String);

impl GuardConfig {
    /// The paper's single-HIP mode: the handle alone.
    pub fn single_hip() -> Self {
        Self {
            guards: vec![Self::handle()],
            ..Self::default()
        }
    }

    fn handle() -> GuardSpec {
        GuardSpec {
            name: "handle".into(),
            link: super::HIP_LINK.into(),
            role: GuardRole::Handle,
            geometry: GuardGeometry::Hip,
            inflation_m: 0.0,
        }
    }

    /// Every value in range, names unique, exactly one handle, at most [`MAX_GUARDS`]; the
    /// error names the guard and key. What needs the robot is checked by [`GuardSet::new`].
    pub fn validate(&self) -> Result<(), GuardError> {
        self.check().map_err(GuardError)
    }

    fn check(&self) -> Result<(), String> {
        within(
            "keep_off_margin_m",
            self.keep_off_margin_m,
            0.0,
            MAX_DISTANCE_M,
        )?;
        if !(1..=MAX_SURFACES_PER_GUARD).contains(&self.surfaces_per_guard) {
            return Err(format!(
                "surfaces_per_guard must be 1 to {MAX_SURFACES_PER_GUARD}, got {}",
                self.surfaces_per_guard
            ));
        }
        if self.guards.len() > MAX_GUARDS {
            return Err(format!(
                "at most {MAX_GUARDS} guards, got {}",
                self.guards.len()
            ));
        }
        for (i, g) in self.guards.iter().enumerate() {
            let key = |k: &str| format!("guard `{}` {k}", g.name);
            if g.name.is_empty() {
                return Err(format!("guard {i} has an empty name"));
            }
            if self.guards[..i].iter().any(|h| h.name == g.name) {
                return Err(format!("two guards are named `{}`", g.name));
            }
            within(&key("inflation_m"), g.inflation_m, 0.0, MAX_INFLATION_M)?;
            let (points, radius): (&[[f64; 3]], _) = match &g.geometry {
                GuardGeometry::Hip | GuardGeometry::Collision(_) => (&[], None),
                GuardGeometry::Sphere { center_m, radius_m } => {
                    (std::slice::from_ref(center_m), Some(*radius_m))
                }
                GuardGeometry::Capsule { a_m, b_m, radius_m } => {
                    for v in a_m.iter().chain(b_m) {
                        within(
                            &key("geometry.a_m/b_m"),
                            *v,
                            -MAX_PRIMITIVE_M,
                            MAX_PRIMITIVE_M,
                        )?;
                    }
                    (&[], Some(*radius_m))
                }
            };
            for v in points.iter().flatten() {
                within(
                    &key("geometry.center_m"),
                    *v,
                    -MAX_PRIMITIVE_M,
                    MAX_PRIMITIVE_M,
                )?;
            }
            if let Some(r) = radius {
                positive_at_most(&key("geometry.radius_m"), r, MAX_GUARD_RADIUS_M)?;
            }
            match (g.role, &g.geometry) {
                (GuardRole::Handle, GuardGeometry::Hip) | (GuardRole::KeepOff, _) => {}
                (GuardRole::Handle, other) => {
                    return Err(format!(
                        "guard `{}` is the handle and must be the HIP sphere (geometry = \"hip\"), got {other:?}",
                        g.name
                    ));
                }
            }
            if g.role == GuardRole::KeepOff && g.geometry == GuardGeometry::Hip {
                return Err(format!(
                    "guard `{}`: geometry \"hip\" is the handle's; a keep-off guard needs a collision element, sphere or capsule",
                    g.name
                ));
            }
        }
        match self
            .guards
            .iter()
            .filter(|g| g.role == GuardRole::Handle)
            .count()
        {
            1 => Ok(()),
            0 => Err("the guard list has no handle (role = \"handle\", the HIP)".into()),
            n => Err(format!(
                "the guard list has {n} handles, exactly one is needed"
            )),
        }
    }
}

/// One guard on the robot: a segment `a_m`..`b_m` in its link's frame (equal ends: a
/// sphere) swept by a ball of `radius_m` (inflation included).
#[derive(Clone, Debug, PartialEq)]
pub struct Guard {
    pub name: String,
    pub role: GuardRole,
    /// Index of the link it is fixed on ([`RobotModel::links`]).
    pub link: usize,
    pub a_m: Point3<f64>,
    pub b_m: Point3<f64>,
    pub radius_m: f64,
}

/// A guard posed in the world: the segment `a_m`..`b_m` swept by `radius_m`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GuardSegment {
    pub a_m: Point3<f64>,
    pub b_m: Point3<f64>,
    pub radius_m: f64,
}

impl GuardSegment {
    /// The point of the segment closest to `x` (the centre of a sphere).
    pub fn closest_point(&self, x: &Point3<f64>) -> Point3<f64> {
        let ab = self.b_m - self.a_m;
        let len2 = ab.norm_squared();
        if len2 <= 0.0 {
            return self.a_m;
        }
        let t = ((x - self.a_m).dot(&ab) / len2).clamp(0.0, 1.0);
        self.a_m + ab * t
    }

    /// Distance from `x` to the guard's surface (negative inside), metres.
    pub fn signed_distance_m(&self, x: &Point3<f64>) -> f64 {
        (x - self.closest_point(x)).norm() - self.radius_m
    }
}

impl Guard {
    /// The guard in the world for the link poses `world_from_link` (one per link, as
    /// [`RobotModel::forward_kinematics`] gives them).
    pub fn world(&self, world_from_link: &[Isometry3<f64>]) -> GuardSegment {
        let pose = &world_from_link[self.link];
        GuardSegment {
            a_m: pose * self.a_m,
            b_m: pose * self.b_m,
            radius_m: self.radius_m,
        }
    }

    /// Distance between the cores (segments) of two guards posed in one frame, metres
    /// (Ericson, Real-Time Collision Detection, 5.1.9).
    fn core_distance(u: &GuardSegment, v: &GuardSegment) -> f64 {
        let (d1, d2, r) = (u.b_m - u.a_m, v.b_m - v.a_m, u.a_m - v.a_m);
        let (a, e, f) = (d1.norm_squared(), d2.norm_squared(), d2.dot(&r));
        let eps = 1e-18;
        let (s, t) = if a <= eps && e <= eps {
            (0.0, 0.0)
        } else if a <= eps {
            (0.0, (f / e).clamp(0.0, 1.0))
        } else {
            let c = d1.dot(&r);
            if e <= eps {
                ((-c / a).clamp(0.0, 1.0), 0.0)
            } else {
                let b = d1.dot(&d2);
                let denom = a * e - b * b;
                let s = if denom > eps {
                    ((b * f - c * e) / denom).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let t = (b * s + f) / e;
                if t < 0.0 {
                    ((-c / a).clamp(0.0, 1.0), 0.0)
                } else if t > 1.0 {
                    (((b - c) / a).clamp(0.0, 1.0), 1.0)
                } else {
                    (s, t)
                }
            }
        };
        ((u.a_m + d1 * s) - (v.a_m + d2 * t)).norm()
    }
}

/// The guards of a robot, checked against its model (see the module doc for the rules).
#[derive(Clone, Debug, PartialEq)]
pub struct GuardSet {
    guards: Vec<Guard>,
    handle: usize,
    keep_off: Vec<usize>,
    keep_off_margin_m: f64,
    surfaces_per_guard: usize,
}

impl GuardSet {
    /// Builds the guards of `config` on `model`; the error names the guard and the value.
    pub fn new(model: &RobotModel, config: &GuardConfig) -> Result<Self, GuardError> {
        config.validate()?;
        let mut guards = Vec::with_capacity(config.guards.len());
        for spec in &config.guards {
            guards.push(Self::guard(model, spec).map_err(GuardError)?);
        }
        let handle = guards
            .iter()
            .position(|g| g.role == GuardRole::Handle)
            .ok_or_else(|| GuardError("the guard list has no handle".into()))?;
        let poses = model.forward_kinematics(&model.clamp_to_limits(&JointVector::zeros()));
        let handle_world = guards[handle].world(&poses);
        for g in guards.iter().filter(|g| g.role == GuardRole::KeepOff) {
            let gap = Guard::core_distance(&g.world(&poses), &handle_world)
                - g.radius_m
                - handle_world.radius_m;
            if gap < 0.0 {
                return Err(GuardError(format!(
                    "keep-off guard `{}` overlaps the handle by {:.4} m in the zero configuration: the handle could not touch the surface without it",
                    g.name, -gap
                )));
            }
        }
        let keep_off = (0..guards.len())
            .filter(|&i| guards[i].role == GuardRole::KeepOff)
            .collect();
        Ok(Self {
            guards,
            handle,
            keep_off,
            keep_off_margin_m: config.keep_off_margin_m,
            surfaces_per_guard: config.surfaces_per_guard,
        })
    }

    fn guard(model: &RobotModel, spec: &GuardSpec) -> Result<Guard, String> {
        let name = &spec.name;
        let link = model.link_index(&spec.link).ok_or_else(|| {
            format!(
                "guard `{name}` names link `{}`, which the robot does not have",
                spec.link
            )
        })?;
        let p = |v: &[f64; 3]| Point3::new(v[0], v[1], v[2]);
        let (a_m, b_m, radius_m) = match &spec.geometry {
            GuardGeometry::Hip => {
                if link != model.hip_link() {
                    return Err(format!(
                        "guard `{name}`: geometry \"hip\" is on link `{}`, not `{}`",
                        model.links()[model.hip_link()].name,
                        spec.link
                    ));
                }
                (Point3::origin(), Point3::origin(), model.hip_radius_m())
            }
            GuardGeometry::Sphere { center_m, radius_m } => (p(center_m), p(center_m), *radius_m),
            GuardGeometry::Capsule { a_m, b_m, radius_m } => (p(a_m), p(b_m), *radius_m),
            GuardGeometry::Collision(i) => {
                let elements = &model.links()[link].collision;
                let prim = elements.get(*i).ok_or_else(|| {
                    format!(
                        "guard `{name}`: link `{}` has {} collision elements, no element {i}",
                        spec.link,
                        elements.len()
                    )
                })?;
                bounding_segment(prim)
            }
        };
        let guard = Guard {
            name: name.clone(),
            role: spec.role,
            link,
            a_m,
            b_m,
            radius_m: radius_m + spec.inflation_m,
        };
        let keys = match &spec.geometry {
            GuardGeometry::Hip => ["hip", "hip"],
            GuardGeometry::Collision(_) => ["collision", "collision"],
            GuardGeometry::Sphere { .. } => ["center_m", "center_m"],
            GuardGeometry::Capsule { .. } => ["a_m", "b_m"],
        };
        for (end, key) in [a_m, b_m].into_iter().zip(keys) {
            let off = off_link_m(model, link, &end);
            if off > radius_m + 1e-12 {
                return Err(format!(
                    "guard `{name}` lies outside link `{}`: its {key} {:?} is {off:.4} m from the link's geometry and bones, more than its radius {radius_m} m",
                    spec.link,
                    end.coords.as_slice()
                ));
            }
        }
        Ok(guard)
    }

    /// All guards, in the configured order.
    pub fn guards(&self) -> &[Guard] {
        &self.guards
    }

    /// The handle guard (the HIP).
    pub fn handle(&self) -> &Guard {
        &self.guards[self.handle]
    }

    /// Indices (into [`GuardSet::guards`]) of the keep-off guards, in the configured order:
    /// the order of the controller's keep-off surfaces and outputs.
    pub fn keep_off(&self) -> &[usize] {
        &self.keep_off
    }

    /// `d_proj` every keep-off guard keeps, metres.
    pub fn keep_off_margin_m(&self) -> f64 {
        self.keep_off_margin_m
    }

    /// How many distinct surfaces each keep-off guard holds rows for.
    pub fn surfaces_per_guard(&self) -> usize {
        self.surfaces_per_guard
    }
}

/// The sphere or capsule of a collision primitive (link frame): a box gives its
/// circumscribing capsule along its longest axis.
fn bounding_segment(prim: &Primitive) -> (Point3<f64>, Point3<f64>, f64) {
    match prim {
        Primitive::Sphere { center_m, radius_m } => (*center_m, *center_m, *radius_m),
        Primitive::Capsule { a_m, b_m, radius_m } => (*a_m, *b_m, *radius_m),
        Primitive::OrientedBox {
            center_m,
            rpy_rad,
            half_extents_m: h,
        } => {
            let long = h.imax();
            let axis = box_rotation(rpy_rad) * Vector3::ith(long, h[long]);
            let across = (h.norm_squared() - h[long] * h[long]).sqrt();
            (center_m - axis, center_m + axis, across)
        }
    }
}

/// How far `x` (link frame) lies from link `link`'s material: the least of its signed
/// distance to the link's collision primitives and its distance to the link's bones (the
/// segments from its origin to each child joint's origin), metres.
fn off_link_m(model: &RobotModel, link: usize, x: &Point3<f64>) -> f64 {
    let prims = model.links()[link]
        .collision
        .iter()
        .map(|p| p.signed_distance(x));
    let bones = model
        .links()
        .iter()
        .filter(|l| l.parent == Some(link))
        .map(|child| {
            GuardSegment {
                a_m: Point3::origin(),
                b_m: child.parent_from_joint * Point3::origin(),
                radius_m: 0.0,
            }
            .signed_distance_m(x)
        });
    let origin = std::iter::once(x.coords.norm());
    prims
        .chain(bones)
        .chain(origin)
        .fold(f64::INFINITY, f64::min)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::robot::DOF;

    fn model() -> RobotModel {
        RobotModel::anyexo().unwrap()
    }

    #[test]
    fn anyexos_default_set() {
        let m = model();
        let set = GuardSet::new(&m, &GuardConfig::default()).unwrap();
        let names: Vec<_> = set.guards().iter().map(|g| g.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "handle",
                "forearm",
                "elbow",
                "upper_arm",
                "shoulder",
                "shoulder_rotation"
            ]
        );
        assert_eq!(set.handle().radius_m, m.hip_radius_m());
        assert_eq!(set.handle().link, m.hip_link());
        assert_eq!(set.keep_off(), [1, 2, 3, 4, 5]);
        // the forearm capsule of the URDF (r 0.025, 0.18 m long) inflated by 2 cm
        let fa = &set.guards()[1];
        assert!((fa.radius_m - 0.045).abs() < 1e-15);
        assert!(((fa.b_m - fa.a_m).norm() - 0.18).abs() < 1e-12);
        // a box's circumscribing capsule (the shoulder's 0.08 x 0.10 x 0.12 m box): along z,
        // radius the half diagonal of the 0.08 x 0.10 cross-section
        let sh = &set.guards()[4];
        let shoulder_box = &m.links()[sh.link].collision[0];
        let (a, b, r) = bounding_segment(shoulder_box);
        assert!(((b - a).norm() - 0.12).abs() < 1e-12);
        assert!((r - 0.04f64.hypot(0.05)).abs() < 1e-12);
        // the default shoulder guard fits the box tighter: every corner of the box lies
        // within the guard (inflation included)
        let seg = GuardSegment {
            a_m: sh.a_m,
            b_m: sh.b_m,
            radius_m: sh.radius_m,
        };
        let Primitive::OrientedBox {
            center_m,
            half_extents_m: h,
            ..
        } = shoulder_box
        else {
            panic!("{shoulder_box:?}")
        };
        for k in 0..8 {
            let sign = |bit: usize| if k >> bit & 1 == 1 { 1.0 } else { -1.0 };
            let corner = center_m + Vector3::new(sign(0) * h.x, sign(1) * h.y, sign(2) * h.z);
            let d = seg.signed_distance_m(&corner);
            assert!(d < 0.0, "corner {corner:?}: {d}");
        }
        // single-HIP mode: the handle alone
        let single = GuardSet::new(&m, &GuardConfig::single_hip()).unwrap();
        assert_eq!(single.guards().len(), 1);
        assert!(single.keep_off().is_empty());
    }

    #[test]
    fn closest_point_on_a_segment() {
        let s = GuardSegment {
            a_m: Point3::new(0.0, 0.0, 0.0),
            b_m: Point3::new(1.0, 0.0, 0.0),
            radius_m: 0.1,
        };
        assert_eq!(
            s.closest_point(&Point3::new(0.3, 2.0, 0.0)),
            Point3::new(0.3, 0.0, 0.0)
        );
        assert_eq!(s.closest_point(&Point3::new(-1.0, 1.0, 0.0)), s.a_m);
        assert_eq!(s.closest_point(&Point3::new(4.0, 0.0, 1.0)), s.b_m);
        assert!((s.signed_distance_m(&Point3::new(0.5, 0.0, 0.05)) + 0.05).abs() < 1e-15);
        let ball = GuardSegment { b_m: s.a_m, ..s };
        assert_eq!(ball.closest_point(&Point3::new(3.0, 1.0, 2.0)), s.a_m);
        // segment-segment distance: crossing, parallel, end to end
        let seg = |a: [f64; 3], b: [f64; 3]| GuardSegment {
            a_m: Point3::from(a),
            b_m: Point3::from(b),
            radius_m: 0.0,
        };
        let crossing = seg([0.5, -1.0, 0.3], [0.5, 1.0, 0.3]);
        assert!((Guard::core_distance(&s, &crossing) - 0.3).abs() < 1e-15);
        let parallel = seg([0.2, 0.4, 0.0], [2.0, 0.4, 0.0]);
        assert!((Guard::core_distance(&s, &parallel) - 0.4).abs() < 1e-15);
        let beyond = seg([2.0, 0.0, 0.0], [3.0, 0.0, 0.0]);
        assert!((Guard::core_distance(&s, &beyond) - 1.0).abs() < 1e-15);
    }

    /// The Jacobian and bias acceleration of a guard's closest point, a point of its link,
    /// match finite differences of forward kinematics.
    #[test]
    fn closest_point_jacobian_matches_finite_differences() {
        let m = model();
        let set = GuardSet::new(&m, &GuardConfig::default()).unwrap();
        let q = JointVector::from_column_slice(&[0.1, -0.2, 0.4, 0.3, 0.9, 1.2]);
        let qd = JointVector::from_column_slice(&[0.5, -0.3, 0.8, -1.1, 0.6, 1.4]);
        let motion = m.link_motion(&q, &qd);
        let h = 1e-6;
        for g in set.guards() {
            let seg = g.world(&motion.world_from_link);
            let target = Point3::new(0.3, 0.1, -0.5);
            let p = seg.closest_point(&target);
            let k = m.point_kinematics(&motion, &qd, g.link, &p);
            let local = motion.world_from_link[g.link].inverse() * p;
            let at = |q: &JointVector| m.forward_kinematics(q)[g.link] * local;
            for j in 0..DOF {
                let (mut qp, mut qm) = (q, q);
                qp[j] += h;
                qm[j] -= h;
                let fd = (at(&qp) - at(&qm)) / (2.0 * h);
                assert!((k.jacobian.column(j) - fd).norm() < 1e-8, "{} {j}", g.name);
            }
            let jac = |q: &JointVector| m.point_jacobian(q, g.link, &local);
            let fd = (jac(&(q + qd * h)) - jac(&(q - qd * h))) * qd / (2.0 * h);
            assert!(
                (k.bias_acceleration_mps2 - fd).norm() < 1e-6,
                "{}: {} vs {fd}",
                g.name,
                k.bias_acceleration_mps2
            );
        }
        // the HIP through the general path is the HIP kinematics
        let hip = m.hip_kinematics(&q, &qd);
        let via = m.point_kinematics(&motion, &qd, m.hip_link(), &hip.position_m);
        assert_eq!(hip, via);
    }

    fn with(f: impl FnOnce(&mut GuardConfig)) -> Result<GuardSet, GuardError> {
        let mut config = GuardConfig::default();
        f(&mut config);
        GuardSet::new(&model(), &config)
    }

    fn fails_naming(f: impl FnOnce(&mut GuardConfig), words: &[&str]) {
        let err = with(f).unwrap_err().to_string();
        for w in words {
            assert!(err.contains(w), "`{err}` should name `{w}`");
        }
    }

    #[test]
    fn bad_guards_are_refused_with_their_name_and_value() {
        fails_naming(
            |c| c.guards[1].link = "wrist_link".into(),
            &["forearm", "wrist_link"],
        );
        fails_naming(
            |c| c.guards[3].geometry = GuardGeometry::Collision(2),
            &["upper_arm", "upper_arm_link", "no element 2"],
        );
        for r in [0.0, -0.01] {
            fails_naming(
                |c| {
                    c.guards[2].geometry = GuardGeometry::Sphere {
                        center_m: [0.0, -0.07, 0.0],
                        radius_m: r,
                    }
                },
                &["elbow", "radius_m", &format!("{r:?}")],
            );
        }
        fails_naming(
            |c| c.guards[1].inflation_m = -0.01,
            &["forearm", "inflation_m"],
        );
        fails_naming(
            |c| c.guards[1].inflation_m = f64::NAN,
            &["forearm", "inflation_m"],
        );
        // a sphere 0.4 m off the forearm
        fails_naming(
            |c| {
                c.guards[2].geometry = GuardGeometry::Sphere {
                    center_m: [0.4, 0.0, 0.0],
                    radius_m: 0.04,
                }
            },
            &["elbow", "outside link `forearm_link`"],
        );
        fails_naming(
            |c| {
                c.guards[2].geometry = GuardGeometry::Capsule {
                    a_m: [0.0, -0.07, 0.0],
                    b_m: [0.0, -0.07, 1.0],
                    radius_m: 0.04,
                }
            },
            &["elbow", "outside link"],
        );
        fails_naming(|c| c.guards.remove(0).name.clear(), &["no handle"]);
        fails_naming(
            |c| {
                c.guards.push(GuardSpec {
                    name: "handle2".into(),
                    ..GuardConfig::handle()
                })
            },
            &["2 handles"],
        );
        fails_naming(
            |c| c.guards[1].name = "elbow".into(),
            &["two guards", "elbow"],
        );
        fails_naming(
            |c| c.guards[0].geometry = GuardGeometry::Collision(0),
            &["handle", "HIP sphere"],
        );
        // a keep-off sphere on the handle bar, where the HIP touches
        fails_naming(
            |c| {
                c.guards.push(GuardSpec {
                    name: "grip".into(),
                    link: "handle_link".into(),
                    role: GuardRole::KeepOff,
                    geometry: GuardGeometry::Collision(0),
                    inflation_m: 0.0,
                })
            },
            &["grip", "overlaps the handle"],
        );
        fails_naming(
            |c| {
                let extra = c.guards[1].clone();
                for i in 0..3 {
                    c.guards.push(GuardSpec {
                        name: format!("extra{i}"),
                        ..extra.clone()
                    });
                }
            },
            &["at most 8 guards", "9"],
        );
        fails_naming(|c| c.keep_off_margin_m = -0.1, &["keep_off_margin_m"]);
        // keep-off guards overlapping one another are allowed (module doc)
        with(|c| {
            c.guards.push(GuardSpec {
                name: "forearm_twice".into(),
                ..c.guards[1].clone()
            })
        })
        .unwrap();
    }

    #[test]
    fn toml_config() {
        let text = r#"
            keep_off_margin_m = 0.02
            [[guards]]
            name = "handle"
            link = "hip"
            role = "handle"
            geometry = "hip"
            [[guards]]
            name = "forearm"
            link = "forearm_link"
            role = "keep_off"
            geometry = { collision = 0 }
            inflation_m = 0.03
            [[guards]]
            name = "elbow"
            link = "forearm_link"
            role = "keep_off"
            geometry = { sphere = { center_m = [0.0, -0.07, 0.0], radius_m = 0.05 } }
        "#;
        let config: GuardConfig = toml::from_str(text).unwrap();
        let set = GuardSet::new(&model(), &config).unwrap();
        assert_eq!(set.keep_off().len(), 2);
        assert!((set.guards()[1].radius_m - 0.055).abs() < 1e-15);
        assert_eq!(set.guards()[2].radius_m, 0.05);
        assert!(toml::from_str::<GuardConfig>("keep_off_margin = 0.1").is_err());
        let round: GuardConfig =
            toml::from_str(&toml::to_string(&GuardConfig::default()).unwrap()).unwrap();
        assert_eq!(round, GuardConfig::default());
    }
}
