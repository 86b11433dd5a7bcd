//! `hapcloud surface` on a real PCL scan: JSON fields, both backends agree, bad input errors.

mod common;

use common::{BUN0, run_err, run_json};

#[test]
fn json_on_the_bunny_with_both_backends() {
    let mut results = Vec::new();
    for backend in ["cpu", "gpu"] {
        let v = run_json([
            "surface",
            BUN0,
            "--hip",
            "-0.03,0.12,0.05",
            "--view",
            "0,0,1",
            "--backend",
            backend,
            "--json",
        ]);
        assert_eq!(v["backend"], backend);
        assert_eq!(v["points_in"], 397);
        assert_eq!(
            v["isolated_points"], 0,
            "a real scan has no isolated points"
        );
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
        // The quadric refinement gave the estimate: its closest point and normal are it.
        let q = &v["quadric_refinement"];
        assert_eq!(q["closest"], v["centroid"], "{q}");
        assert_eq!(q["normal"], v["normal"], "{q}");
        assert!(q["residual_rms_m"].as_f64().unwrap() < 0.01, "{q}");
        results.push((v["centroid"].clone(), v["normal"].clone()));
    }
    assert_eq!(
        results[0], results[1],
        "GPU and CPU reference give the same estimate"
    );
}

#[test]
fn bad_arguments_and_files_are_errors() {
    assert!(run_err(["surface", BUN0, "--hip", "1,2"]).contains("--hip needs three"));
    let err = run_err(["surface", "/nonexistent/cloud.pcd", "--hip", "0,0,0"]);
    assert!(err.contains("cloud.pcd"), "{err}");
}
