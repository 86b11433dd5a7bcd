//! `hapcloud surface` on a real PCL scan: JSON fields, both backends agree, bad input errors.

use std::process::Command;

fn surface(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .arg("surface")
        .args(args)
        .output()
        .expect("runs hapcloud")
}

const BUN0: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/pcl/bun0.pcd");

#[test]
fn json_on_the_bunny_with_both_backends() {
    let mut results = Vec::new();
    for backend in ["cpu", "gpu"] {
        let out = surface(&[
            BUN0,
            "--hip",
            "-0.03,0.12,0.05",
            "--view",
            "0,0,1",
            "--backend",
            backend,
            "--json",
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(v["backend"], backend);
        assert_eq!(v["points_in"], 397);
        assert_eq!(v["valid"], true);
        assert_eq!(v["shells"].as_array().unwrap().len(), 9);
        let n: Vec<f64> = v["normal"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        assert!(n[2] < 0.0, "eq. 2: normal against the view direction");
        assert!(((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt() - 1.0).abs() < 1e-9);
        results.push((v["centroid"].clone(), v["normal"].clone()));
    }
    assert_eq!(
        results[0], results[1],
        "GPU and CPU reference give the same estimate"
    );
}

#[test]
fn bad_arguments_and_files_are_errors() {
    let out = surface(&[BUN0, "--hip", "1,2"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--hip needs three"));
    let out = surface(&["/nonexistent/cloud.pcd", "--hip", "0,0,0"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("cloud.pcd"));
}
