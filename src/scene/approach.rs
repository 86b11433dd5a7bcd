//! The approach of a whole-arm scene, and the scene re-timed so that approach closes at a
//! chosen speed (`hapcloud experiment safe-speed --keep-off` on a scene without a body that
//! comes at the handle, and `experiment whole-arm`).
//!
//! [`candidates`] samples the scene as scripted (the robot on its inverse-kinematics path,
//! the bodies on their motions) every [`SAMPLE_S`] and takes each keep-off guard and body
//! whose true gap `g(t)` (the guard's `d_proj`, [`truth::closest_to_guard`]) comes within
//! [`APPROACH_GAP_M`], nearest first (a sweep uses the nearest that can be re-timed). Over the
//! final approach (the last [`FINAL_GAP_M`] of gap closed before that least gap) the gap's
//! change splits into what the robot's motion closes (bodies held) and what the bodies'
//! motions close (robot held); the larger part is the mover: a HIP path `move` segment, a
//! `constant_velocity` body, or the rotation of the `[[group]]` carrying the body.
//!
//! [`Approach::retime`] carries that motion on past contact and re-times it: the closing
//! speed is `v_c = -dg/dt` where the scripted gap crosses 0.
//! - The robot: the scene's move grazes the body, so the link is driven into it instead:
//!   one minimum-jerk HIP move along `u`, the direction of HIP motion that closes the gap
//!   fastest at the least gap's pose (through the inverse kinematics), from [`PASS_M`]
//!   before the contact to [`PASS_M`] past it (less where out of reach), so the contact is
//!   at mid-move, where the HIP is fastest and accelerates least; its duration `T` scales
//!   `v_c` as `1/T` (the path's geometry does not depend on `T`). The robot rests
//!   [`REST_S`] first.
//! - A `constant_velocity` body: the same direction at the speed that gives `v_c`, on until
//!   it is [`PASS_M`] past contact.
//! - A group: its rotation from the closing interval's first angle `a0` to
//!   `a0 + 2 (a_c - a0)` (contact at mid-rotation, minimum-jerk), starting when it did.
//!
//! Each ends with [`HOLD_S`] of rest. `T` (or the speed) comes from a first build at a
//! nominal timing and is corrected once against the re-timed scene's measured `v_c`.

use super::config::{HipSegment, RobotMotion};
use super::episode::{PASS_M, START_S, sample_times};
use super::motion::{Motion, Rotation, min_jerk};
use super::robot_track::IK_DAMPING_M;
use super::{BodyConfig, Scene, SceneError, Simulator, truth};
use crate::robot::guards::{GuardConfig, GuardSet};
use nalgebra::{Point3, Vector3};
use serde::Serialize;

/// Step of the scripted scene's scan for the approach, seconds.
pub const SAMPLE_S: f64 = 0.005;
/// Step of the scan for the scripted contact of a re-timed scene, seconds.
const CONTACT_STEP_S: f64 = 0.001;
/// A keep-off guard must come this near a body for the scene to have an approach, metres
/// (the whole-arm built-ins bring one to 0.4-3.9 cm).
pub const APPROACH_GAP_M: f64 = 0.05;
/// The final approach the mover is judged on: the last this much of gap closed, metres.
pub const FINAL_GAP_M: f64 = 0.01;
/// Rest before the re-timed robot moves, seconds (fusion and control settle on the static
/// scene first, as in a campaign episode).
pub const REST_S: f64 = START_S;
/// Rest after the re-timed motion ends, seconds.
pub const HOLD_S: f64 = 0.2;
/// Closing speeds a scene can be re-timed to, m/s: above 5 m/s no arm of a patient or of
/// the exoskeleton moves (ISO/TS 15066's transient limits are exceeded from about 0.5 m/s).
pub const CLOSING_SPEEDS_MPS: std::ops::RangeInclusive<f64> = 0.01..=5.0;
/// Least change of the gap per metre of HIP motion for the robot to be re-timed: below it
/// the HIP would have to move over 10 times faster than the closing speed.
const MIN_GAP_GRADIENT: f64 = 0.1;
/// How often the robot's move is shortened (by a quarter) when its far end is out of reach.
const REACH_TRIES: usize = 4;

/// A line of HIP motion: its point `B`, direction `u`, the joints at `B` and the HIP travel
/// from `B` along `u` to contact.
type RobotLine = (Point3<f64>, Vector3<f64>, Vec<f64>, f64);

/// What closes the gap of an approach.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Mover {
    /// The robot's HIP path: its `move` segment `segment` (0-based).
    Robot { segment: usize },
    /// A body moving with `constant_velocity`.
    Body { name: String },
    /// The rotation of a `[[group]]` carrying the body, over waypoint interval `interval`
    /// (from `times_s[interval]` to the next).
    Group { name: String, interval: usize },
}

impl std::fmt::Display for Mover {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Mover::Robot { segment } => write!(f, "the robot's HIP path (segment {segment})"),
            Mover::Body { name } => write!(f, "body `{name}`'s constant velocity"),
            Mover::Group { name, .. } => write!(f, "group `{name}`'s rotation"),
        }
    }
}

/// The approach of a scene: the keep-off guard and body that come nearest, and what moves
/// them together.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Approach {
    pub guard: String,
    pub body: String,
    pub mover: Mover,
    /// The least true gap of guard and body in the scene as written, metres, and when.
    pub least_gap_m: f64,
    pub least_gap_t_s: f64,
    /// How much of the final approach's gap the mover closed, metres (the rest: the others).
    pub mover_closed_m: f64,
    pub others_closed_m: f64,
}

/// A scene re-timed to a closing speed.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Retimed {
    #[serde(skip)]
    pub scene: Scene,
    /// The closing speed asked for, m/s.
    pub speed_mps: f64,
    /// When the scripted guard would touch the body, seconds.
    pub contact_t_s: f64,
    /// The scripted closing speed there, m/s.
    pub closing_speed_mps: f64,
    /// The deepest scripted gap (negative: the unguarded guard inside the body), metres.
    pub deepest_gap_m: f64,
    /// The moving part's speed at nominal scale: the HIP's peak speed, the body's speed or
    /// the group's peak angular speed (rad/s).
    pub mover_speed: f64,
}

fn invalid(scene: &Scene, message: String) -> SceneError {
    SceneError::Invalid {
        origin: scene.origin.clone(),
        message,
    }
}

/// The gap of guard `guard` (index into the set's guards) posed by the robot at `t_q` to
/// body `body` posed at `t_b`.
struct GapProbe<'a> {
    sim: Simulator,
    set: GuardSet,
    guard: usize,
    body: &'a BodyConfig,
}

impl GapProbe<'_> {
    fn gap(&self, t_q: f64, t_b: f64) -> f64 {
        let (Some(model), Some(q)) = (self.sim.robot_model(), self.sim.joints_at(t_q)) else {
            return f64::INFINITY;
        };
        let seg = self.set.guards()[self.guard].world(&model.forward_kinematics(&q));
        truth::closest_to_guard(std::slice::from_ref(self.body), t_b, &seg)
            .map_or(f64::INFINITY, |t| t.gap_m)
    }
}

/// The guard set of `guards` on `sim`'s robot, with a keep-off guard.
fn guard_set(scene: &Scene, sim: &Simulator, guards: &GuardConfig) -> Result<GuardSet, SceneError> {
    let model = sim
        .robot_model()
        .ok_or_else(|| invalid(scene, "the scene has no robot: no link to approach".into()))?;
    let set = GuardSet::new(model, guards).map_err(|e| invalid(scene, e.to_string()))?;
    if set.keep_off().is_empty() {
        return Err(invalid(
            scene,
            "the guard config has no keep-off guard (a single-HIP config): no link to approach"
                .into(),
        ));
    }
    Ok(set)
}

/// The approaches of `scene` for the keep-off guards of `guards`, nearest first (see the
/// module doc): each pair of keep-off guard and body that comes within [`APPROACH_GAP_M`],
/// with its least gap, as an approach or the error that says why it has none (a gap that
/// only opens, a mover that cannot be re-timed). An error names what is missing: no robot
/// or body, or no guard within [`APPROACH_GAP_M`] of a body (with the nearest pair).
pub fn candidates(
    scene: &Scene,
    guards: &GuardConfig,
) -> Result<Vec<Result<Approach, SceneError>>, SceneError> {
    let sim = Simulator::new(scene)?;
    let set = guard_set(scene, &sim, guards)?;
    let model = sim.robot_model().expect("guard_set checked the robot");
    let bodies = &scene.file.bodies;
    if bodies.is_empty() {
        return Err(invalid(scene, "the scene has no body to approach".into()));
    }
    // the least gap of each keep-off guard and body over time: (gap, t, guard, body)
    let mut least: Vec<(f64, f64, usize, usize)> = Vec::new();
    for &k in set.keep_off() {
        for b in 0..bodies.len() {
            least.push((f64::INFINITY, 0.0, k, b));
        }
    }
    for t in sample_times(sim.duration_s(), SAMPLE_S) {
        let Some(q) = sim.joints_at(t) else { continue };
        let poses = model.forward_kinematics(&q);
        for pair in &mut least {
            let seg = set.guards()[pair.2].world(&poses);
            let body = std::slice::from_ref(&bodies[pair.3]);
            if let Some(tr) = truth::closest_to_guard(body, t, &seg)
                && tr.gap_m < pair.0
            {
                (pair.0, pair.1) = (tr.gap_m, t);
            }
        }
    }
    least.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (gap, t, k, b) = least[0];
    if gap >= APPROACH_GAP_M {
        return Err(invalid(
            scene,
            format!(
                "no keep-off guard comes within {APPROACH_GAP_M} m of a body: the nearest, \
                 `{}`, stays {gap:.3} m from `{}` (t = {t:.3} s): no approach to re-time",
                set.guards()[k].name,
                bodies[b].name
            ),
        ));
    }
    Ok(least
        .iter()
        .take_while(|p| p.0 < APPROACH_GAP_M)
        .map(|&p| approach_of(scene, &set, p))
        .collect())
}

/// The approach of keep-off guard `guard` and body `b` of `scene`, nearest (`least_gap`)
/// at `t_min`.
fn approach_of(
    scene: &Scene,
    set: &GuardSet,
    (least_gap, t_min, guard, b): (f64, f64, usize, usize),
) -> Result<Approach, SceneError> {
    let guard_name = set.guards()[guard].name.clone();
    let body = &scene.file.bodies[b];
    let probe = GapProbe {
        sim: Simulator::new(scene)?,
        set: set.clone(),
        guard,
        body,
    };
    // the final approach: back from the least gap to where the gap was FINAL_GAP_M more
    let steps: Vec<f64> = sample_times(t_min, SAMPLE_S).collect();
    let mut first = steps.len() - 1;
    while first > 0 && probe.gap(steps[first], steps[first]) < least_gap + FINAL_GAP_M {
        first -= 1;
    }
    if probe.gap(steps[first], steps[first]) < least_gap + FINAL_GAP_M {
        return Err(invalid(
            scene,
            format!(
                "guard `{guard_name}` and body `{}` are nearest ({least_gap:.3} m) at t = \
                 {t_min:.3} s, but nothing closed their gap by {FINAL_GAP_M} m before: no \
                 approach to re-time",
                body.name
            ),
        ));
    }
    // what the robot and the bodies each close, step by step; the step where the robot
    // (or the bodies) close most says which segment (or interval) moves them
    let (mut robot, mut others) = (0.0, 0.0);
    let (mut robot_peak, mut body_peak) = ((0.0, t_min), (0.0, t_min));
    for w in steps[first..].windows(2) {
        let (t0, t1) = (w[0], w[1]);
        let here = probe.gap(t0, t0);
        let moved = probe.gap(t1, t0);
        let (r, o) = (moved - here, probe.gap(t1, t1) - moved);
        robot += r;
        others += o;
        if r < robot_peak.0 {
            robot_peak = (r, 0.5 * (t0 + t1));
        }
        if o < body_peak.0 {
            body_peak = (o, 0.5 * (t0 + t1));
        }
    }
    let mover = if robot <= others {
        robot_mover(scene, robot_peak.1)?
    } else {
        body_mover(scene, body, body_peak.1)?
    };
    let (mover_closed_m, others_closed_m) = if robot <= others {
        (-robot, -others)
    } else {
        (-others, -robot)
    };
    Ok(Approach {
        guard: guard_name,
        body: body.name.clone(),
        mover,
        least_gap_m: least_gap,
        least_gap_t_s: t_min,
        mover_closed_m,
        others_closed_m,
    })
}

/// The HIP path segment the robot moves in at `t_s`, which must be a `move`.
fn robot_mover(scene: &Scene, t_s: f64) -> Result<Mover, SceneError> {
    let Some(RobotMotion::HipPath { segments, .. }) = scene.file.robot.as_ref().map(|r| &r.motion)
    else {
        return Err(invalid(
            scene,
            "the robot closes the gap by joint waypoints: re-timing supports HIP paths (move \
             segments)"
                .into(),
        ));
    };
    let mut start = 0.0;
    for (i, seg) in segments.iter().enumerate() {
        let end = start + seg.duration_s();
        if t_s < end || i + 1 == segments.len() {
            return match seg {
                HipSegment::Move { .. } => Ok(Mover::Robot { segment: i }),
                other => Err(invalid(
                    scene,
                    format!(
                        "the robot closes the gap in HIP path segment {i}, a `{}`: re-timing \
                         supports `move` segments",
                        segment_kind(other)
                    ),
                )),
            };
        }
        start = end;
    }
    Err(invalid(scene, "the robot's HIP path has no segment".into()))
}

fn segment_kind(seg: &HipSegment) -> &'static str {
    match seg {
        HipSegment::Move { .. } => "move",
        HipSegment::Hold { .. } => "hold",
        HipSegment::Impacts { .. } => "impacts",
        HipSegment::Slide { .. } => "slide",
    }
}

/// What moves `body` at `t_s`: the rotation of its group when the angle changes then, else
/// its own `constant_velocity`.
fn body_mover(scene: &Scene, body: &BodyConfig, t_s: f64) -> Result<Mover, SceneError> {
    if let Some(group) = (scene.file.groups.iter()).find(|g| g.bodies.contains(&body.name)) {
        let r = &group.rotation;
        if let Some(i) = (0..r.times_s.len().saturating_sub(1))
            .find(|&i| r.times_s[i] <= t_s && t_s <= r.times_s[i + 1])
            .filter(|&i| r.angles_rad[i] != r.angles_rad[i + 1])
        {
            return Ok(Mover::Group {
                name: group.name.clone(),
                interval: i,
            });
        }
    }
    match &body.motion {
        Motion::ConstantVelocity { .. } => Ok(Mover::Body {
            name: body.name.clone(),
        }),
        other => Err(invalid(
            scene,
            format!(
                "body `{}` closes the gap by its `{}` motion: re-timing supports \
                 constant_velocity bodies, group rotations and HIP path moves",
                body.name,
                match other {
                    Motion::Static => "static",
                    Motion::ConstantVelocity { .. } => "constant_velocity",
                    Motion::Waypoints { .. } => "waypoints",
                    Motion::Sinusoid { .. } => "sinusoid",
                }
            ),
        )),
    }
}

impl Approach {
    /// `scene` (the one this approach was derived from, cameras at their rate) re-timed so
    /// the approach closes at `speed_mps` and carries on past contact (see the module doc).
    pub fn retime(
        &self,
        scene: &Scene,
        guards: &GuardConfig,
        speed_mps: f64,
    ) -> Result<Retimed, SceneError> {
        if !CLOSING_SPEEDS_MPS.contains(&speed_mps) {
            return Err(invalid(
                scene,
                format!(
                    "the closing speed must be finite and in [{}, {}] m/s, got {speed_mps}",
                    CLOSING_SPEEDS_MPS.start(),
                    CLOSING_SPEEDS_MPS.end()
                ),
            ));
        }
        // a build at a nominal scale, then the scale that gives the speed, corrected once
        let mut scale = 1.0;
        let mut last = None;
        for _ in 0..3 {
            let built = self.build(scene, guards, scale)?;
            let r = self.measure(built, guards, speed_mps)?;
            let ratio = r.closing_speed_mps / speed_mps;
            let done = (ratio - 1.0).abs() < 0.01;
            last = Some(r);
            if done {
                break;
            }
            scale *= ratio;
        }
        Ok(last.expect("at least one build"))
    }

    /// The scene carried past contact, its mover's timing stretched by `scale` (a move or
    /// rotation lasting `scale` seconds, a body at `scale` times its speed... inverted so a
    /// larger `scale` is slower): returns the scene and the mover's nominal speed.
    fn build(
        &self,
        scene: &Scene,
        guards: &GuardConfig,
        scale: f64,
    ) -> Result<(Scene, f64), SceneError> {
        let mut file = scene.file.clone();
        let origin = format!("{} re-timed", scene.origin);
        match &self.mover {
            Mover::Robot { .. } => {
                let (from, u, q_b, s_c) = self.robot_line(scene, guards)?;
                let mut half = PASS_M;
                for _ in 0..REACH_TRIES {
                    let (p0, p1) = (from + u * (s_c - half), from + u * (s_c + half));
                    let mut f = file.clone();
                    f.duration_s = REST_S + scale + HOLD_S;
                    if let Some(robot) = &mut f.robot {
                        robot.motion = RobotMotion::HipPath {
                            start_m: p0,
                            initial_joints_rad: q_b.clone(),
                            segments: vec![
                                HipSegment::Hold { duration_s: REST_S },
                                HipSegment::Move {
                                    to_m: p1,
                                    duration_s: scale,
                                },
                                HipSegment::Hold { duration_s: HOLD_S },
                            ],
                        };
                    }
                    let s = Scene::new(f, &origin)?;
                    match Simulator::new(&s) {
                        Ok(_) => return Ok((s, 1.875 * 2.0 * half / scale)),
                        Err(SceneError::Robot { .. }) => half *= 0.75,
                        Err(e) => return Err(e),
                    }
                }
                Err(invalid(
                    scene,
                    format!(
                        "the robot's move driving guard `{}` into body `{}` is out of reach \
                         even {:.3} m either side of contact",
                        self.guard,
                        self.body,
                        half / 0.75
                    ),
                ))
            }
            Mover::Body { name } => {
                let body = (file.bodies.iter_mut())
                    .find(|b| &b.name == name)
                    .ok_or_else(|| invalid(scene, format!("no body `{name}`")))?;
                let Motion::ConstantVelocity {
                    velocity_m_s,
                    start_s,
                } = &mut body.motion
                else {
                    return Err(invalid(
                        scene,
                        format!("body `{name}` is not constant_velocity"),
                    ));
                };
                let speed0 = velocity_m_s.norm();
                let start = *start_s;
                // travel to contact at the scene's own speed, then PASS_M on
                let travel = self.body_contact_travel(scene, guards, name)? + PASS_M;
                let speed = speed0 / scale;
                *velocity_m_s *= 1.0 / scale;
                file.duration_s = start + travel / speed + HOLD_S;
                Ok((Scene::new(file, &origin)?, speed))
            }
            Mover::Group { name, interval } => {
                let group = (file.groups.iter_mut())
                    .find(|g| &g.name == name)
                    .ok_or_else(|| invalid(scene, format!("no group `{name}`")))?;
                let r = &group.rotation;
                let (t0, a0, a1) = (
                    r.times_s[*interval],
                    r.angles_rad[*interval],
                    r.angles_rad[*interval + 1],
                );
                let a_c = self.group_contact_angle(scene, guards, name, (t0, a0, a1))?;
                let end = a0 + 2.0 * (a_c - a0);
                group.rotation = Rotation {
                    times_s: vec![t0, t0 + scale],
                    angles_rad: vec![a0, end],
                    ..r.clone()
                };
                file.duration_s = t0 + scale + HOLD_S;
                let s = Scene::new(file, &origin)?;
                Ok((s, 1.875 * (end - a0).abs() / scale))
            }
        }
    }

    /// The approach's guard and body in `scene` as `sim` poses it.
    fn gap_probe<'s>(
        &self,
        scene: &'s Scene,
        sim: Simulator,
        guards: &GuardConfig,
    ) -> Result<GapProbe<'s>, SceneError> {
        let set = guard_set(scene, &sim, guards)?;
        let guard = (set.guards().iter())
            .position(|g| g.name == self.guard)
            .ok_or_else(|| invalid(scene, format!("no guard `{}`", self.guard)))?;
        let body = (scene.file.bodies.iter())
            .find(|b| b.name == self.body)
            .ok_or_else(|| invalid(scene, format!("no body `{}`", self.body)))?;
        Ok(GapProbe {
            sim,
            set,
            guard,
            body,
        })
    }

    /// The first time the probed gap falls below 0 after `from_s` (None: never), and the
    /// deepest gap after `from_s`.
    fn first_contact(
        &self,
        scene: &Scene,
        probe: &GapProbe,
        from_s: f64,
    ) -> Result<(Option<f64>, f64), SceneError> {
        let end = probe.sim.duration_s();
        let mut deepest = f64::INFINITY;
        let mut prev: Option<(f64, f64)> = None;
        let mut contact = None;
        for t in sample_times(end, CONTACT_STEP_S).filter(|&t| t >= from_s) {
            let g = probe.gap(t, t);
            deepest = deepest.min(g);
            if let Some((tp, gp)) = prev
                && contact.is_none()
                && gp >= 0.0
                && g < 0.0
            {
                contact = Some(tp + (t - tp) * gp / (gp - g));
            }
            prev = Some((t, g));
        }
        if contact.is_none() && deepest < 0.0 {
            return Err(invalid(
                scene,
                format!(
                    "guard `{}` is inside body `{}` from the start: nothing to approach",
                    self.guard, self.body
                ),
            ));
        }
        Ok((contact, deepest))
    }

    /// `scene` with `f` applied, and the first contact in it after `from_s`.
    fn probe_contact(
        &self,
        scene: &Scene,
        guards: &GuardConfig,
        from_s: f64,
        f: impl FnOnce(&mut super::SceneFile),
    ) -> Result<(Option<f64>, f64), SceneError> {
        let mut file = scene.file.clone();
        f(&mut file);
        let s = Scene::new(file, &format!("{} (approach probe)", scene.origin))?;
        let probe = self.gap_probe(&s, Simulator::new(&s)?, guards)?;
        self.first_contact(&s, &probe, from_s)
    }

    /// The line the re-timed robot's HIP moves on: through the HIP at the least gap, `B`,
    /// along `u`, the direction of HIP motion that closes the gap fastest (the gap's
    /// gradient through the damped least-squares inverse kinematics at `B`'s joints), and
    /// the HIP travel from `B` along `u` to contact (probed up to `2 PASS_M`).
    /// Returns `B`, `u`, the joints at `B` and that travel.
    fn robot_line(&self, scene: &Scene, guards: &GuardConfig) -> Result<RobotLine, SceneError> {
        let sim = Simulator::new(scene)?;
        let probe = self.gap_probe(scene, Simulator::new(scene)?, guards)?;
        let t = self.least_gap_t_s;
        let (Some(model), Some(q)) = (sim.robot_model(), sim.joints_at(t)) else {
            return Err(invalid(scene, "the scene has no robot".into()));
        };
        let hk = model.hip_kinematics(&q, &crate::robot::JointVector::zeros());
        let j = hk.jacobian;
        let damping = nalgebra::Matrix3::identity() * IK_DAMPING_M.powi(2);
        let jjt = (j * j.transpose() + damping)
            .try_inverse()
            .ok_or_else(|| invalid(scene, "the HIP Jacobian is singular at the approach".into()))?;
        let gap_at = |dq: &crate::robot::JointVector| {
            let seg = probe.set.guards()[probe.guard].world(&model.forward_kinematics(&(q + dq)));
            truth::closest_to_guard(std::slice::from_ref(probe.body), t, &seg)
                .map_or(f64::INFINITY, |tr| tr.gap_m)
        };
        let h = 1e-4;
        let grad = Vector3::from_fn(|i, _| {
            let dq = j.transpose() * (jjt * (Vector3::ith(i, h)));
            (gap_at(&dq) - gap_at(&-dq)) / (2.0 * h)
        });
        if grad.norm() < MIN_GAP_GRADIENT {
            return Err(invalid(
                scene,
                format!(
                    "moving the HIP hardly moves guard `{}` towards body `{}` (gap gradient \
                     {:.3} m per m): no robot approach to re-time",
                    self.guard,
                    self.body,
                    grad.norm()
                ),
            ));
        }
        let (b, u, q_b) = (
            hk.position_m,
            -grad.normalize(),
            q.iter().copied().collect(),
        );
        // the travel to contact along the line (the gap is not linear in it)
        let mut far = 2.0 * PASS_M;
        let mut tried = Err(invalid(scene, "no probe".into()));
        for _ in 0..REACH_TRIES {
            tried = self.probe_contact(scene, guards, 0.0, |f| {
                f.duration_s = 1.0;
                if let Some(robot) = &mut f.robot {
                    robot.motion = RobotMotion::HipPath {
                        start_m: b,
                        initial_joints_rad: Vec::clone(&q_b),
                        segments: vec![HipSegment::Move {
                            to_m: b + u * far,
                            duration_s: 1.0,
                        }],
                    };
                }
            });
            match tried {
                Err(SceneError::Robot { .. }) => far *= 0.75,
                _ => break,
            }
        }
        let (contact, deepest) = tried?;
        let t = contact.ok_or_else(|| {
            invalid(
                scene,
                format!(
                    "the robot's HIP moved {far:.3} m along the gap's steepest direction does \
                     not bring guard `{}` to body `{}` (least gap {deepest:.3} m)",
                    self.guard, self.body
                ),
            )
        })?;
        Ok((b, u, q_b, far * min_jerk(t)))
    }

    /// How far body `name` travels from its start to contact at its scene speed (carried
    /// up to 0.5 m on).
    fn body_contact_travel(
        &self,
        scene: &Scene,
        guards: &GuardConfig,
        name: &str,
    ) -> Result<f64, SceneError> {
        let body = (scene.file.bodies.iter())
            .find(|b| b.name == name)
            .ok_or_else(|| invalid(scene, format!("no body `{name}`")))?;
        let Motion::ConstantVelocity {
            velocity_m_s,
            start_s,
        } = body.motion
        else {
            return Err(invalid(
                scene,
                format!("body `{name}` is not constant_velocity"),
            ));
        };
        let speed = velocity_m_s.norm();
        let far = (scene.file.duration_s - start_s).max(0.0) * speed + 0.5;
        let (contact, deepest) =
            self.probe_contact(scene, guards, 0.0, |f| f.duration_s = start_s + far / speed)?;
        let t = contact.ok_or_else(|| {
            invalid(
                scene,
                format!(
                    "body `{name}` carried 0.5 m on does not touch guard `{}` (least gap \
                     {deepest:.3} m)",
                    self.guard
                ),
            )
        })?;
        Ok((t - start_s) * speed)
    }

    /// The angle of group `name`'s rotation at which the guard would touch the body (the
    /// interval `(t0, a0, a1)` carried on to twice its angle).
    fn group_contact_angle(
        &self,
        scene: &Scene,
        guards: &GuardConfig,
        name: &str,
        (t0, a0, a1): (f64, f64, f64),
    ) -> Result<f64, SceneError> {
        let far = a0 + 2.0 * (a1 - a0);
        let (contact, deepest) = self.probe_contact(scene, guards, t0, |f| {
            f.duration_s = t0 + 1.0;
            for g in f.groups.iter_mut().filter(|g| g.name == name) {
                g.rotation.times_s = vec![t0, t0 + 1.0];
                g.rotation.angles_rad = vec![a0, far];
            }
        })?;
        let t = contact.ok_or_else(|| {
            invalid(
                scene,
                format!(
                    "group `{name}` rotated on to {far:.3} rad does not bring body `{}` to guard \
                     `{}` (least gap {deepest:.3} m)",
                    self.body, self.guard
                ),
            )
        })?;
        Ok(a0 + (far - a0) * min_jerk(t - t0))
    }

    /// The scripted contact of a built re-timed scene and its closing speed.
    fn measure(
        &self,
        (scene, mover_speed): (Scene, f64),
        guards: &GuardConfig,
        speed_mps: f64,
    ) -> Result<Retimed, SceneError> {
        let probe = self.gap_probe(&scene, Simulator::new(&scene)?, guards)?;
        let (contact, deepest) = self.first_contact(&scene, &probe, 0.0)?;
        let t_c = contact.ok_or_else(|| {
            invalid(
                &scene,
                format!(
                    "the re-timed scene does not bring guard `{}` to body `{}` (least gap \
                     {deepest:.3} m)",
                    self.guard, self.body
                ),
            )
        })?;
        let h = CONTACT_STEP_S;
        let closing = -(probe.gap(t_c + h, t_c + h) - probe.gap(t_c - h, t_c - h)) / (2.0 * h);
        drop(probe);
        Ok(Retimed {
            scene,
            speed_mps,
            contact_t_s: t_c,
            closing_speed_mps: closing,
            deepest_gap_m: deepest,
            mover_speed,
        })
    }
}
