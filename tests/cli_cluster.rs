//! The `hapcloud cluster` command on PCL's bun0.pcd, both backends, against the sizes
//! `pcl_cluster_extraction bun0.pcd out.pcd -tolerance 0.01 -min 1` prints (PCL 1.13):
//! 357, 23, 12, 3, 1, 1.

use std::process::Command;

fn run(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .args(args)
        .output()
        .expect("hapcloud runs")
}

#[test]
fn cluster_command_reproduces_pcl_sizes_and_writes_one_file_per_cluster() {
    let bun0 = format!("{}/../shared/data/pcl/bun0.pcd", env!("CARGO_MANIFEST_DIR"));
    let dir = std::env::temp_dir().join(format!("hapcloud-cli-cluster-{}", std::process::id()));
    for backend in ["gpu", "cpu"] {
        let out_dir = dir.join(backend);
        let out = run(&[
            "cluster",
            &bun0,
            "--tolerance",
            "0.01",
            "--min-size",
            "2",
            "--out-dir",
            out_dir.to_str().unwrap(),
            "--json",
            "--backend",
            backend,
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
        assert_eq!(v["points_in"], 397);
        assert_eq!(v["cluster_sizes"], serde_json::json!([357, 23, 12, 3]));
        assert_eq!(v["components"], 6);
        assert_eq!(v["backend"], backend);
        assert_eq!(v["adapter"].is_string(), backend == "gpu");
        assert!(v["timings_ms"]["cluster_wall"].as_f64().is_some() || backend == "cpu");
        let mut files: Vec<String> = std::fs::read_dir(&out_dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        files.sort();
        assert_eq!(
            files,
            [
                "cluster_0.pcd",
                "cluster_1.pcd",
                "cluster_2.pcd",
                "cluster_3.pcd"
            ]
        );
        let second = hapcloud::io::read_cloud(&out_dir.join("cluster_1.pcd")).unwrap();
        assert_eq!(second.len(), 23);
    }
    std::fs::remove_dir_all(&dir).ok();
    let bad = run(&["cluster", &bun0, "--min-size", "5", "--max-size", "4"]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--min-size 5 exceeds --max-size 4"));
}
