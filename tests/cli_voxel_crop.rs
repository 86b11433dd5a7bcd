//! The `hapcloud voxel` and `hapcloud crop` commands on PCL's bun0.pcd, both backends.

use std::process::Command;

fn data(name: &str) -> String {
    format!("{}/../shared/data/pcl/{name}", env!("CARGO_MANIFEST_DIR"))
}

fn run_json(args: &[&str]) -> serde_json::Value {
    let out = Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .args(args)
        .output()
        .expect("hapcloud runs");
    assert!(
        out.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("one JSON object")
}

#[test]
fn voxel_command_reproduces_pcl_counts_on_both_backends() {
    let bun0 = data("bun0.pcd");
    let dir = std::env::temp_dir().join(format!("hapcloud-cli-voxel-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for backend in ["gpu", "cpu"] {
        let v = run_json(&[
            "voxel",
            &bun0,
            "--leaf",
            "0.02",
            "--json",
            "--backend",
            backend,
        ]);
        assert_eq!(v["points_in"], 397);
        assert_eq!(v["points_out"], 103);
        assert_eq!(v["backend"], backend);
        assert!(v["timings_ms"]["voxel"].as_f64().is_some());
        assert_eq!(v["adapter"].is_string(), backend == "gpu");
        let out = dir.join(format!("band_{backend}.pcd"));
        let v = run_json(&[
            "voxel",
            &bun0,
            "--leaf",
            "0.02",
            "--fmin",
            "0.05",
            "--fmax",
            "0.1",
            "--json",
            "--backend",
            backend,
            "--out",
            out.to_str().unwrap(),
        ]);
        assert_eq!(v["points_out"], 14);
        let written = hapcloud::io::read_cloud(&out).unwrap();
        assert_eq!(written.len(), 14);
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn crop_command_with_a_robot_file() {
    let bun0 = data("bun0.pcd");
    let dir = std::env::temp_dir().join(format!("hapcloud-cli-crop-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let robot = dir.join("robot.toml");
    std::fs::write(
        &robot,
        r#"
[[primitive]]
shape = "sphere"
center_m = [-0.03, 0.1, 0.03]
radius_m = 0.03

[[primitive]]
shape = "oriented_box"
center_m = [-0.05, 0.15, 0.0]
rpy_rad = [0.0, 0.0, 0.5]
half_extents_m = [0.02, 0.02, 0.1]
"#,
    )
    .unwrap();
    let mut counts = Vec::new();
    for backend in ["gpu", "cpu"] {
        let v = run_json(&[
            "crop",
            &bun0,
            "--hip",
            "-0.03,0.1,0.03",
            "--radius",
            "0.06",
            "--robot",
            robot.to_str().unwrap(),
            "--json",
            "--backend",
            backend,
        ]);
        assert_eq!(v["points_in"], 397);
        assert_eq!(v["primitives"], 2);
        counts.push(v["points_out"].as_u64().unwrap());
    }
    assert_eq!(counts[0], counts[1]);
    assert!(counts[0] > 10 && counts[0] < 397, "{counts:?}");
    // A malformed robot file is a clear error naming the file.
    std::fs::write(&robot, "[[primitive]]\nshape = \"cone\"\n").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .args([
            "crop",
            &bun0,
            "--hip",
            "0,0,0",
            "--radius",
            "1",
            "--robot",
            robot.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("robot.toml"));
    std::fs::remove_dir_all(&dir).ok();
}
