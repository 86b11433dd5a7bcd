//! Shared by the integration tests that run the `hapcloud` binary: the command, its JSON
//! output or its error message, PCL's real grabber frames and bunny scan, scratch
//! directories, running the node with a JSON summary, and a built-in scene's frames posed.
// Each test binary compiles this module and uses only part of it.
#![allow(dead_code)]

use std::ffi::OsStr;
use std::path::PathBuf;
use std::process::{Command, Output};

/// The `hapcloud` binary of this build.
pub fn hapcloud() -> Command {
    Command::new(env!("CARGO_BIN_EXE_hapcloud"))
}

/// PCL's grabber sequence: three Kinect-class frames named by their stamps.
pub fn grabber_pcd() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/pcl/grabber_sequences/pcd"
    ))
}

/// PCL's bunny scan `bun0.pcd` (397 points).
pub const BUN0: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/pcl/bun0.pcd");

/// A directory under the target's tmp dir, empty at the start, removed on drop.
pub struct TempDir {
    pub path: PathBuf,
}

impl TempDir {
    pub fn new(name: &str) -> Self {
        let path = PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
            .join(format!("{name}_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&path);
        std::fs::create_dir_all(&path).unwrap();
        Self { path }
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.path);
    }
}

/// Runs `hapcloud ARGS`, asserts success (printing its stderr otherwise).
pub fn run_ok<I, S>(args: I) -> Output
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    let out = hapcloud().args(args).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Runs `hapcloud ARGS`, asserts success and parses its stdout as one JSON value.
pub fn run_json<I, S>(args: I) -> serde_json::Value
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    serde_json::from_slice(&run_ok(args).stdout).unwrap()
}

/// Runs `hapcloud ARGS`, asserts that it fails and returns its stderr (the message).
pub fn run_err<I, S>(args: I) -> String
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    let out = hapcloud().args(args).output().unwrap();
    assert!(!out.status.success(), "expected a failure");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// `hapcloud run --json --backend cpu ARGS SOURCE`: the node's JSON summary.
pub fn run_node<S: AsRef<OsStr>>(source: S, args: &[&OsStr]) -> serde_json::Value {
    let mut all: Vec<&OsStr> = ["run", "--json", "--backend", "cpu"]
        .iter()
        .map(OsStr::new)
        .collect();
    all.extend_from_slice(args);
    all.push(source.as_ref());
    run_json(all)
}

/// Two keep-off guards of a tick at `stamp_s`: one with a tracked surface (its centroid `z_m`
/// up) and its constraint, one without a surface (NaN distances, no data).
pub fn two_guard_records(stamp_s: f64, z_m: f64) -> hapcloud::control::record::GuardRecords {
    use hapcloud::control::record::GuardRecord;
    use hapcloud::haptics::HapticStatus;
    use hapcloud::surface::{FusedSurface, FusionStatus, SurfaceState};
    use nalgebra::{Point3, Unit, Vector3};
    let fused = FusedSurface {
        stamp_s,
        status: FusionStatus::Tracking,
        age_s: 0.03,
        surface: Some(SurfaceState {
            centroid_m: Point3::new(0.1, 0.2, 0.3 + z_m),
            normal: Unit::new_normalize(Vector3::new(0.0, 0.6, 0.8)),
            velocity_m_per_s: Vector3::new(0.0, 0.0, -0.01),
            fit_centroid_m: Point3::new(0.11, 0.2, 0.3),
            fit_normal: Unit::new_normalize(Vector3::new(0.0, 0.6, 0.8)),
        }),
        fit_degree: 1,
        sample_count: 7,
        camera_count: 1,
    };
    [
        GuardRecord {
            fused,
            held: false,
            haptic_status: HapticStatus::Active,
            d_proj_m: 0.012 + z_m * 1e-3,
            d_rate_mps: -0.3,
            alpha_p_m: 0.002,
            alpha_v_mps: -0.1,
        },
        GuardRecord::no_surface(stamp_s),
    ]
    .into_iter()
    .collect()
}

/// A simulated camera frame with what perception is given at its stamp: the HIP, the posed
/// robot primitives and ANYexo's keep-off guards.
pub struct PosedFrame {
    pub frame: hapcloud::camera::Frame,
    pub hip: nalgebra::Point3<f64>,
    pub robot: Vec<hapcloud::geometry::Primitive>,
    pub guards: Vec<hapcloud::robot::guards::GuardSegment>,
}

/// Every `step`-th of the first 120 frames of each camera of built-in scene `name`, posed.
pub fn posed_frames(name: &str, step: usize) -> Vec<PosedFrame> {
    use hapcloud::robot::guards::{GuardConfig, GuardSet};
    let scene = hapcloud::scene::Scene::from_builtin(name).unwrap();
    let sim = hapcloud::scene::Simulator::new(&scene).unwrap();
    let base = scene.file.robot.as_ref().unwrap().world_from_base();
    let model = hapcloud::robot::RobotModel::anyexo()
        .unwrap()
        .with_base(base);
    let set = GuardSet::new(&model, &GuardConfig::default()).unwrap();
    let mut frames = Vec::new();
    for index in (0..120).step_by(step) {
        for camera in 0..sim.cameras().len() as u32 {
            let Some(timing) = sim.timing(camera, index) else {
                continue;
            };
            let t = timing.stamp_s;
            let (hip, joints) = (sim.hip_at(t).unwrap(), sim.joints_at(t).unwrap());
            let robot = model
                .collision_primitives_world(&joints)
                .into_iter()
                .map(|(_, p)| p)
                .collect();
            let poses = model.forward_kinematics(&joints);
            let guards = set
                .keep_off()
                .iter()
                .map(|&i| set.guards()[i].world(&poses))
                .collect();
            frames.push(PosedFrame {
                frame: sim.frame(&timing).frame,
                hip,
                robot,
                guards,
            });
        }
    }
    frames
}
