//! Motions of bodies and of the exoskeleton's HIP as functions of time.
//!
//! Body parts translate rigidly ([`Motion`]: static, constant velocity, piecewise-linear
//! waypoints, sinusoid). HIP paths and joint waypoints use the minimum-jerk profile
//! `s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5` between rest points (Flash and Hogan 1985), so
//! velocities and accelerations are continuous and zero at every waypoint, as in the paper's
//! planned approach, impact and sliding motions.

use super::config::HipSegment;
use nalgebra::{Isometry3, Point3, Translation3, Unit, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Fastest body motion a scene may declare, m/s (the safe-speed sweeps go to 2.5 m/s).
pub const MAX_BODY_SPEED_M_S: f64 = 20.0;
/// Largest offset or amplitude of a body motion, metres.
pub const MAX_OFFSET_M: f64 = 100.0;
/// Highest sinusoid frequency of a body, Hz (breathing 0.25 Hz, tremor up to about 12 Hz).
pub const MAX_BODY_FREQUENCY_HZ: f64 = 50.0;

/// Rigid translation of a body part over time (its offset from the scene-file position).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Motion {
    #[default]
    Static,
    /// Moves with `velocity_m_s` from `start_s` (before: at rest at offset zero).
    ConstantVelocity {
        velocity_m_s: Vector3<f64>,
        #[serde(default)]
        start_s: f64,
    },
    /// Offsets `offsets_m` at increasing `times_s`, linear in between, held outside.
    Waypoints {
        times_s: Vec<f64>,
        offsets_m: Vec<Vector3<f64>>,
    },
    /// `amplitude_m * sin(2 pi frequency_hz t + phase_rad)` (breathing, head sway).
    Sinusoid {
        amplitude_m: Vector3<f64>,
        frequency_hz: f64,
        #[serde(default)]
        phase_rad: f64,
    },
}

impl Motion {
    /// Offset of the body from its scene-file position at time `t_s`.
    pub fn offset_at(&self, t_s: f64) -> Vector3<f64> {
        match self {
            Motion::Static => Vector3::zeros(),
            Motion::ConstantVelocity {
                velocity_m_s,
                start_s,
            } => velocity_m_s * (t_s - start_s).max(0.0),
            Motion::Waypoints { times_s, offsets_m } => {
                let i = times_s.partition_point(|&t| t <= t_s);
                if i == 0 {
                    offsets_m[0]
                } else if i == times_s.len() {
                    offsets_m[i - 1]
                } else {
                    let f = (t_s - times_s[i - 1]) / (times_s[i] - times_s[i - 1]);
                    offsets_m[i - 1].lerp(&offsets_m[i], f)
                }
            }
            Motion::Sinusoid {
                amplitude_m,
                frequency_hz,
                phase_rad,
            } => amplitude_m * (std::f64::consts::TAU * frequency_hz * t_s + phase_rad).sin(),
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        use super::config::MAX_DURATION_S;
        use super::effects::in_range;
        match self {
            Motion::Static => Ok(()),
            Motion::ConstantVelocity {
                velocity_m_s,
                start_s,
            } => {
                if !velocity_m_s.iter().chain([start_s]).all(|v| v.is_finite()) {
                    return Err("constant_velocity has a non-finite value".into());
                }
                in_range(
                    "constant_velocity speed (m/s)",
                    velocity_m_s.norm(),
                    0.0,
                    MAX_BODY_SPEED_M_S,
                )?;
                in_range("start_s", *start_s, 0.0, MAX_DURATION_S)
            }
            Motion::Waypoints { times_s, offsets_m } => {
                if times_s.is_empty() || times_s.len() != offsets_m.len() {
                    return Err(format!(
                        "waypoints need one offset per time, got {} times and {} offsets",
                        times_s.len(),
                        offsets_m.len()
                    ));
                }
                if times_s.iter().any(|t| !t.is_finite())
                    || times_s.windows(2).any(|w| w[1] <= w[0])
                {
                    return Err("waypoint times_s must be finite and strictly increasing".into());
                }
                for t in times_s {
                    in_range("waypoint times_s", *t, -MAX_DURATION_S, MAX_DURATION_S)?;
                }
                for v in offsets_m.iter().flat_map(|o| o.iter()) {
                    in_range("waypoint offsets_m", *v, -MAX_OFFSET_M, MAX_OFFSET_M)?;
                }
                Ok(())
            }
            Motion::Sinusoid {
                amplitude_m,
                frequency_hz,
                phase_rad,
            } => {
                if !amplitude_m.iter().all(|v| v.is_finite()) {
                    return Err("sinusoid amplitude_m has a non-finite value".into());
                }
                if !phase_rad.is_finite() {
                    return Err(format!(
                        "sinusoid phase_rad must be finite, got {phase_rad}"
                    ));
                }
                for v in amplitude_m.iter() {
                    in_range("sinusoid amplitude_m", *v, -MAX_OFFSET_M, MAX_OFFSET_M)?;
                }
                let turn = std::f64::consts::TAU;
                in_range("sinusoid phase_rad", *phase_rad, -turn, turn)?;
                in_range(
                    "sinusoid frequency_hz",
                    *frequency_hz,
                    0.0,
                    MAX_BODY_FREQUENCY_HZ,
                )
            }
        }
    }
}

/// A rigid rotation over time about the axis `axis` through `pivot_m` (a seated patient's
/// upper body leaning about the hip axis): `angles_rad` at increasing `times_s`, minimum-jerk
/// blends between them, held outside. A point `x` of a carried body moves to
/// `pivot + R(angle(t)) (x - pivot)`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Rotation {
    pub pivot_m: Point3<f64>,
    /// Rotation axis (normalised when used); a positive angle turns right-handed about it.
    pub axis: Vector3<f64>,
    pub times_s: Vec<f64>,
    pub angles_rad: Vec<f64>,
}

impl Rotation {
    /// The angle at `t_s`, radians.
    pub fn angle_at(&self, t_s: f64) -> f64 {
        let i = self.times_s.partition_point(|&t| t <= t_s);
        if i == 0 {
            return self.angles_rad[0];
        }
        if i == self.times_s.len() {
            return self.angles_rad[i - 1];
        }
        let (t0, t1) = (self.times_s[i - 1], self.times_s[i]);
        let (a0, a1) = (self.angles_rad[i - 1], self.angles_rad[i]);
        a0 + (a1 - a0) * min_jerk((t_s - t0) / (t1 - t0))
    }

    /// The rigid motion at `t_s`: world from the carried body's frame at rest.
    pub fn pose_at(&self, t_s: f64) -> Isometry3<f64> {
        let pivot = Translation3::from(self.pivot_m.coords);
        let turn =
            UnitQuaternion::from_axis_angle(&Unit::new_normalize(self.axis), self.angle_at(t_s));
        pivot * turn * pivot.inverse()
    }

    pub fn validate(&self) -> Result<(), String> {
        use super::config::MAX_DURATION_S;
        use super::effects::in_range;
        let (times, angles) = (&self.times_s, &self.angles_rad);
        if times.is_empty() || times.len() != angles.len() {
            return Err(format!(
                "a rotation needs one angle per time, got {} times and {} angles",
                times.len(),
                angles.len()
            ));
        }
        if times.iter().any(|t| !t.is_finite()) || times.windows(2).any(|w| w[1] <= w[0]) {
            return Err("rotation times_s must be finite and strictly increasing".into());
        }
        for t in times {
            in_range("rotation times_s", *t, -MAX_DURATION_S, MAX_DURATION_S)?;
        }
        for a in angles {
            in_range(
                "rotation angles_rad",
                *a,
                -std::f64::consts::PI,
                std::f64::consts::PI,
            )?;
        }
        for v in self.pivot_m.iter() {
            in_range("rotation pivot_m", *v, -MAX_OFFSET_M, MAX_OFFSET_M)?;
        }
        if !self
            .axis
            .iter()
            .all(|v| v.is_finite() && v.abs() <= MAX_OFFSET_M)
            || self.axis.norm() < 1e-9
        {
            return Err(format!(
                "rotation axis must be finite and non-zero, got {:?}",
                self.axis.as_slice()
            ));
        }
        Ok(())
    }
}

/// Minimum-jerk progress `s(tau)` for `tau` in [0, 1] (clamped outside).
pub fn min_jerk(tau: f64) -> f64 {
    let t = tau.clamp(0.0, 1.0);
    t * t * t * (10.0 - 15.0 * t + 6.0 * t * t)
}

/// The HIP target position at `t_s` along `segments` starting at `start_m` at time 0 (held
/// at the end).
pub fn hip_path_at(start_m: &Point3<f64>, segments: &[HipSegment], t_s: f64) -> Point3<f64> {
    let mut p = *start_m;
    let mut t0 = 0.0;
    for seg in segments {
        let d = seg.duration_s();
        let local = t_s - t0;
        let end = segment_point(&p, seg, d);
        if local < d {
            return segment_point(&p, seg, local.max(0.0));
        }
        p = end;
        t0 += d;
    }
    p
}

/// The point `local_s` seconds into `seg`, which starts at `from`.
fn segment_point(from: &Point3<f64>, seg: &HipSegment, local_s: f64) -> Point3<f64> {
    match seg {
        HipSegment::Move { to_m, duration_s } => {
            from + (to_m - from) * min_jerk(local_s / duration_s)
        }
        HipSegment::Hold { .. } => *from,
        HipSegment::Impacts {
            target_m,
            count,
            period_s,
        } => {
            let k = (local_s / period_s).floor();
            if k >= f64::from(*count) {
                return *from;
            }
            // Out in the first half period, back in the second.
            let phase = local_s / period_s - k;
            let s = if phase < 0.5 {
                min_jerk(2.0 * phase)
            } else {
                1.0 - min_jerk(2.0 * phase - 1.0)
            };
            from + (target_m - from) * s
        }
        HipSegment::Slide {
            center_m,
            axis,
            angle_rad,
            duration_s,
        } => {
            let rot = UnitQuaternion::from_axis_angle(
                &Unit::new_normalize(*axis),
                angle_rad * min_jerk(local_s / duration_s),
            );
            center_m + rot * (from - center_m)
        }
    }
}

/// Minimum-jerk interpolation of joint waypoints (held outside `times_s`).
pub fn joints_at(times_s: &[f64], joints_rad: &[Vec<f64>], t_s: f64) -> Vec<f64> {
    let i = times_s.partition_point(|&t| t <= t_s);
    if i == 0 {
        return joints_rad[0].clone();
    }
    if i == times_s.len() {
        return joints_rad[i - 1].clone();
    }
    let s = min_jerk((t_s - times_s[i - 1]) / (times_s[i] - times_s[i - 1]));
    joints_rad[i - 1]
        .iter()
        .zip(&joints_rad[i])
        .map(|(a, b)| a + (b - a) * s)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn motions_evaluate() {
        let cv = Motion::ConstantVelocity {
            velocity_m_s: Vector3::new(0.0, 0.0, 0.5),
            start_s: 1.0,
        };
        assert_eq!(cv.offset_at(0.5), Vector3::zeros());
        assert!((cv.offset_at(3.0).z - 1.0).abs() < 1e-12);
        let wp = Motion::Waypoints {
            times_s: vec![0.0, 2.0],
            offsets_m: vec![Vector3::zeros(), Vector3::new(0.2, 0.0, 0.0)],
        };
        assert!((wp.offset_at(1.0).x - 0.1).abs() < 1e-12);
        assert!((wp.offset_at(5.0).x - 0.2).abs() < 1e-12);
        let sin = Motion::Sinusoid {
            amplitude_m: Vector3::new(0.0, 0.01, 0.0),
            frequency_hz: 0.25,
            phase_rad: 0.0,
        };
        assert!((sin.offset_at(1.0).y - 0.01).abs() < 1e-12);
    }

    #[test]
    fn hip_path_segments_chain() {
        let start = Point3::new(0.5, 0.0, 0.8);
        let segs = vec![
            HipSegment::Move {
                to_m: Point3::new(0.3, 0.0, 0.8),
                duration_s: 1.0,
            },
            HipSegment::Impacts {
                target_m: Point3::new(0.2, 0.0, 0.8),
                count: 2,
                period_s: 1.0,
            },
            HipSegment::Slide {
                center_m: Point3::new(0.0, 0.0, 0.8),
                axis: Vector3::z(),
                angle_rad: std::f64::consts::FRAC_PI_2,
                duration_s: 1.0,
            },
        ];
        assert_eq!(hip_path_at(&start, &segs, 0.0), start);
        assert!((hip_path_at(&start, &segs, 1.0) - Point3::new(0.3, 0.0, 0.8)).norm() < 1e-12);
        // Mid-impact: at the target.
        assert!((hip_path_at(&start, &segs, 1.5) - Point3::new(0.2, 0.0, 0.8)).norm() < 1e-12);
        assert!((hip_path_at(&start, &segs, 2.0) - Point3::new(0.3, 0.0, 0.8)).norm() < 1e-12);
        // After the quarter turn about z through the origin: (0.3, 0) -> (0, 0.3).
        assert!((hip_path_at(&start, &segs, 9.0) - Point3::new(0.0, 0.3, 0.8)).norm() < 1e-12);
    }
}
