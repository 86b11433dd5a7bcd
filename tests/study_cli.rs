//! `hapcloud study --quick`: the sweep runs end to end on a built-in scene and writes a
//! well-formed CSV (one row per setting, finite errors), a markdown table and a PNG.
#![cfg(feature = "lab")]

use std::process::Command;

#[test]
fn quick_study_writes_csv_markdown_and_png() {
    let dir = std::env::temp_dir().join(format!("hapcloud-study-{}", std::process::id()));
    let out = Command::new(env!("CARGO_BIN_EXE_hapcloud"))
        .args(["study", "--quick", "--backend", "cpu", "--out"])
        .arg(&dir)
        .output()
        .expect("run hapcloud");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    let settings = hapcloud::lab::study::settings();
    let mut reader = csv::Reader::from_path(dir.join("study.csv")).expect("study.csv");
    let header = reader.headers().expect("header").clone();
    let col = |name: &str| {
        header
            .iter()
            .position(|h| h == name)
            .unwrap_or_else(|| panic!("column {name} missing: {header:?}"))
    };
    let rows: Vec<csv::StringRecord> = reader.records().map(|r| r.expect("row")).collect();
    assert_eq!(rows.len(), settings.len());
    for (row, setting) in rows.iter().zip(&settings) {
        assert_eq!(row.len(), header.len());
        assert_eq!(&row[col("knob")], setting.knob);
        assert_eq!(&row[col("value")], setting.value);
        assert!(row[col("frames")].parse::<usize>().unwrap() > 0);
        let num = |name: &str| row[col(name)].parse::<f64>().unwrap();
        assert!(num("frame_ms") > 0.0 && num("frame_ms").is_finite());
        assert!((0.0..=1.0).contains(&num("valid_fraction")));
    }
    // The defaults and most settings find the surface: their errors are finite. (A setting
    // may legitimately find nothing, e.g. three shells up to 4 cm when the HIP is farther
    // than that from the surface: NaN, and no front.)
    let default = &rows[0];
    assert_eq!(&default[col("is_default")], "true");
    let finite: Vec<_> = rows
        .iter()
        .filter(|r| {
            r[col("fused_centroid_rms_mm")]
                .parse::<f64>()
                .unwrap()
                .is_finite()
        })
        .collect();
    assert!(
        finite.len() * 4 >= rows.len() * 3,
        "{} of {}",
        finite.len(),
        rows.len()
    );
    // Each camera's estimate of the torso is within a few centimetres of the truth (the
    // realistic scene's D435 noise and calibration bias stay in the error).
    for name in ["camera_centroid_rms_mm", "camera_normal_rms_deg"] {
        let v: f64 = default[col(name)].parse().unwrap();
        assert!(v.is_finite() && v < 30.0, "default {name} = {v}");
    }
    for name in ["fused_centroid_rms_mm", "fused_normal_rms_deg"] {
        let v: f64 = default[col(name)].parse().unwrap();
        assert!(v.is_finite(), "default {name} = {v}");
    }
    // The look-ahead's far-field ticks are reported apart (NaN where there were none).
    let far: f64 = default[col("far_field_centroid_rms_mm")].parse().unwrap();
    assert!(far.is_nan() || far >= 0.0, "{far}");
    // --quick skips the closed loop: its columns are there, empty of numbers.
    assert!(
        default[col("min_margin_mm")]
            .parse::<f64>()
            .unwrap()
            .is_nan()
    );
    assert!(
        default[col("max_penetration_mm")]
            .parse::<f64>()
            .unwrap()
            .is_nan()
    );
    let front: Vec<_> = rows
        .iter()
        .filter(|r| &r[col("pareto")] == "true")
        .collect();
    assert!(!front.is_empty());
    for r in &front {
        assert!(
            r[col("fused_centroid_rms_mm")]
                .parse::<f64>()
                .unwrap()
                .is_finite()
        );
    }

    let md = std::fs::read_to_string(dir.join("study.md")).expect("study.md");
    let table_rows = md.lines().filter(|l| l.starts_with("| ")).count();
    assert_eq!(table_rows, settings.len() + 1, "{md}");
    assert!(md.contains("| **default** |"));

    let png = std::fs::read(dir.join("pareto.png")).expect("pareto.png");
    let decoder = png::Decoder::new(std::io::Cursor::new(png));
    let reader = decoder.read_info().expect("valid PNG");
    assert_eq!((reader.info().width, reader.info().height), (1000, 700));
    std::fs::remove_dir_all(&dir).ok();
}
