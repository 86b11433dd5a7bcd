//! Commands that explain themselves: `--help` in the order a user meets the commands,
//! `config --print` loadable as a node config, the progress line without frames or surface,
//! `run --record` naming the file it wants, `experiment safe-speed` naming its scenes.

mod common;

use common::{TempDir, hapcloud, run_ok};

#[test]
fn help_lists_the_commands_in_order_one_line_each() {
    let out = run_ok(["--help"]);
    let help = String::from_utf8_lossy(&out.stdout);
    let commands: Vec<&str> = help
        .lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| !l.trim().is_empty())
        .map(|l| {
            assert!(
                l.starts_with("  ") && !l.starts_with("   "),
                "wrapped: {l:?}"
            );
            l.split_whitespace().next().unwrap()
        })
        .collect();
    let mut expected = vec!["run", "replay"];
    if cfg!(feature = "viewer") {
        expected.push("view");
    }
    if cfg!(feature = "lab") {
        expected.extend(["experiment", "study", "accuracy"]);
    }
    expected.extend([
        "scenes",
        "sim",
        "convert",
        "crop",
        "voxel",
        "cluster",
        "surface",
        "config",
        "can-decode",
        "gpu-info",
        "help",
    ]);
    assert_eq!(commands, expected, "{help}");
}

/// What `config --print` prints is a config `hapcloud run` takes; a section prints alone.
#[test]
fn the_printed_config_runs_the_node() {
    let tmp = TempDir::new("cli_config");
    let out = run_ok(["config", "--print"]);
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("tick_rate_hz = 800.0"), "{text}");
    assert!(text.contains("\n[frontend.voxel]\n"), "{text}");
    let path = tmp.path.join("node.toml");
    std::fs::write(&path, &text).unwrap();
    let out = run_ok([
        "run".as_ref(),
        "head_close_clean".as_ref(),
        "--config".as_ref(),
        path.as_os_str(),
        "--duration".as_ref(),
        "0.2".as_ref(),
        "--backend".as_ref(),
        "cpu".as_ref(),
        "--json".as_ref(),
    ]);
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(summary["ticks"].as_u64().unwrap() > 100, "{summary}");

    let out = run_ok(["config", "--print", "surface.shells"]);
    let section: toml::Table = toml::from_slice(&out.stdout).unwrap();
    assert!(section["surface"]["shells"].is_table(), "{section}");
    let out = hapcloud()
        .args(["config", "--print", "no_such"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("no config section `no_such`") && err.contains("frontend"),
        "{err}"
    );
    let out = run_ok(["config"]);
    let list = String::from_utf8_lossy(&out.stdout);
    assert!(list.lines().any(|l| l.starts_with("frontend ")), "{list}");
}

/// After the scene's cameras stop (1.4 s), the progress lines show no rate, no latency and
/// no `d_proj` (`-`), never `NaN`.
#[test]
fn the_progress_line_without_frames_or_surface() {
    let out = run_ok([
        "run",
        "rising_surface_clean",
        "--duration",
        "3.3",
        "--backend",
        "cpu",
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("t ")).collect();
    assert!(lines.len() >= 2, "{err}");
    assert!(!err.contains("NaN"), "{err}");
    let last = lines.last().unwrap();
    assert!(
        last.contains("no frames  latency last -") && last.ends_with("d_proj -"),
        "{last}"
    );
    assert!(
        lines[0].contains(" Hz") && lines[0].contains(" mm"),
        "{err}"
    );
}

#[test]
fn record_names_the_file_it_wants_before_anything_runs() {
    let tmp = TempDir::new("cli_record_dir");
    let out = hapcloud()
        .arg("run")
        .arg("--record")
        .arg(&tmp.path)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("is a directory; a recording is written to one file")
            && err.contains("run.mcap"),
        "{err}"
    );
    assert!(!err.contains("not a readable recording"), "{err}");
    assert!(!err.contains("scene rendered"), "{err}");
    let out = hapcloud()
        .args(["run", "--record", "out.txt"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("FILE.mcap"), "{err}");
}

#[cfg(feature = "lab")]
#[test]
fn safe_speed_without_a_scene_names_the_scenes_it_can_sweep() {
    let tmp = TempDir::new("cli_safe_speed");
    let out = hapcloud()
        .args(["experiment", "safe-speed", "--out"])
        .arg(&tmp.path)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    for scene in ["rising_surface_realistic", "oblique_head_clean"] {
        assert!(err.contains(scene), "{err}");
    }
    assert!(!err.contains("torso_approach"), "{err}");
}
