//! The safety campaign (`hapcloud experiment campaign`) and its episodes as a user runs them:
//! a 20-episode campaign end to end, a written episode reproducing its runs through
//! `experiment safe-speed`, the same for a small campaign aimed at the keep-off guards, and
//! bad input.

mod common;

use common::{TempDir, run_err, run_json};
use hapcloud::lab::campaign::run_episode;
use hapcloud::lab::safe_speed;
use hapcloud::lab::scene_loop::{SceneLoopOptions, SurfaceSource};
use hapcloud::scene::{Scene, episode};

/// An episode written as a scene file loads back to the same scene, and the safe-speed sweep
/// of that file gives every source's run exactly as the campaign's episode run gave it.
#[test]
fn a_written_episode_reproduces_the_campaigns_runs() {
    let e = episode::generate(3, 5).unwrap();
    let dir = TempDir::new("campaign_episode");
    let path = dir.path.join("episode.toml");
    std::fs::write(&path, toml::to_string(&e.scene.file).unwrap()).unwrap();
    let loaded = Scene::from_file(&path).unwrap();
    assert_eq!(loaded.file, e.scene.file);
    let options = SceneLoopOptions {
        render_threads: Some(1),
        ..SceneLoopOptions::default()
    };
    let speed = 1.5;
    let campaign = run_episode(e.clone(), &[speed], &options).unwrap();
    let sweep = safe_speed::sweep(&loaded, &[speed], e.camera_rate_hz, &options).unwrap();
    assert_eq!(campaign.rows.len(), 4);
    for row in &campaign.rows {
        let again = sweep.rows.iter().find(|r| r.source == row.source).unwrap();
        assert_eq!(
            (row.min_margin_m, row.safe, row.contact_speed_mps),
            (again.min_margin_m, again.safe, again.contact_speed_mps),
            "{:?}",
            row.source
        );
    }
    // the exact surface is the ceiling: no source does better
    let margin = |s| {
        campaign
            .rows
            .iter()
            .find(|r| r.source == s)
            .unwrap()
            .min_margin_m
    };
    assert!(margin(SurfaceSource::Exact) >= margin(SurfaceSource::DelayedOracle) - 1e-3);
}

/// Twenty episodes at 1.5 m/s: every file is written, every count adds up, the worst
/// episodes' scene files load, and the summary's fractions are those of the runs' CSV.
#[test]
fn a_twenty_episode_campaign_writes_its_tables_plots_and_worst_episodes() {
    let dir = TempDir::new("campaign_cli");
    let d = dir.path.to_str().unwrap();
    let json = run_json([
        "experiment",
        "campaign",
        "--episodes",
        "20",
        "--seed",
        "1",
        "--speeds",
        "1.5",
        "--worst",
        "3",
        "--out",
        d,
        "--json",
    ]);
    let details = &json["details"];
    assert_eq!(details["episodes"], 20);
    for f in [
        "campaign-runs.csv",
        "campaign-summary.csv",
        "campaign-kinds.csv",
        "campaign-views.csv",
        "campaign-contacts.csv",
        "campaign-episodes.csv",
        "campaign-safe.png",
        "campaign-margins.png",
    ] {
        assert!(dir.path.join(f).metadata().unwrap().len() > 100, "{f}");
    }
    let runs = std::fs::read_to_string(dir.path.join("campaign-runs.csv")).unwrap();
    assert_eq!(runs.lines().count(), 1 + 20 * 4);
    let summary = details["summary"].as_array().unwrap();
    // (3 rates + all) x 4 sources
    assert_eq!(summary.len(), 4 * 4);
    // 4 body kinds x 4 sources, and 0 to 2 cameras facing the leading surface x 4 sources,
    // each source's groups adding up to the 20 episodes
    let by_kind = details["by_kind"].as_array().unwrap();
    assert_eq!(by_kind.len(), 4 * 4);
    let by_view = details["by_view"].as_array().unwrap();
    assert!([4, 8, 12].contains(&by_view.len()), "{}", by_view.len());
    for groups in [by_kind, by_view] {
        for source in ["exact", "delayed_oracle", "visible_oracle", "perception"] {
            let episodes: u64 = groups
                .iter()
                .filter(|r| r["source"] == source)
                .map(|r| r["episodes"].as_u64().unwrap())
                .sum();
            assert_eq!(episodes, 20, "{source}");
        }
    }
    for row in summary.iter().filter(|r| r["camera_rate_hz"] == 0.0) {
        assert_eq!(row["episodes"], 20);
        let (safe, feasible) = (
            row["safe"].as_u64().unwrap(),
            row["feasible"].as_u64().unwrap(),
        );
        assert!(safe <= feasible && feasible <= 20, "{row}");
        if row["source"] == "exact" {
            assert_eq!(safe, feasible);
        }
        let csv_safe = runs
            .lines()
            .skip(1)
            .filter(|l| {
                let f: Vec<&str> = l.split(',').collect();
                f[5].parse::<f64>().unwrap() == row["speed_mps"].as_f64().unwrap()
                    && f[6] == row["source"].as_str().unwrap()
                    && f[9] == "true"
            })
            .count() as u64;
        assert!(csv_safe >= safe, "{row}");
    }
    let worst = details["worst"].as_array().unwrap();
    assert!(worst.len() <= 3);
    for w in worst {
        let scene = Scene::from_file(std::path::Path::new(w["file"].as_str().unwrap())).unwrap();
        assert!(scene.file.name.starts_with("episode_1_"));
    }
}

/// A keep-off episode written as a scene file: `safe-speed --keep-off` on it gives every
/// source's run and every keep-off guard's least d_proj exactly as the campaign's run gave
/// them.
#[test]
fn a_written_keep_off_episode_reproduces_the_campaigns_guard_rows() {
    let guards = hapcloud::robot::guards::GuardConfig::default();
    let e = episode::generate_keep_off(2, 1, &guards).unwrap();
    let dir = TempDir::new("campaign_keep_off_episode");
    let path = dir.path.join("episode.toml");
    std::fs::write(&path, toml::to_string(&e.scene.file).unwrap()).unwrap();
    let loaded = Scene::from_file(&path).unwrap();
    assert_eq!(loaded.file, e.scene.file);
    let options = SceneLoopOptions {
        render_threads: Some(1),
        keep_off: true,
        ..SceneLoopOptions::default()
    };
    let speed = 1.5;
    let campaign = run_episode(e.clone(), &[speed], &options).unwrap();
    let sweep = safe_speed::sweep(&loaded, &[speed], e.camera_rate_hz, &options).unwrap();
    // 4 sources x 5 keep-off guards
    assert_eq!(campaign.guards.len(), 4 * 5);
    assert_eq!(sweep.guard_rows.len(), campaign.guards.len());
    let target = e.guard.as_deref().unwrap();
    for row in &campaign.guards {
        assert_eq!(row.target, target);
        let again = (sweep.guard_rows.iter())
            .find(|r| r.source == row.source && r.guard == row.guard)
            .unwrap();
        assert_eq!(
            (row.min_d_proj_m, row.contact, &row.body),
            (again.min_d_proj_m, again.contact, &again.body),
            "{:?} {}",
            row.source,
            row.guard
        );
    }
}

/// Two keep-off episodes through the command: the guard tables are written with a row per
/// episode, source and keep-off guard, the summary has every target guard; a single-HIP
/// config has no keep-off guard to aim at and says so.
#[test]
fn a_keep_off_campaign_writes_its_guard_tables() {
    let dir = TempDir::new("campaign_keep_off_cli");
    let d = dir.path.to_str().unwrap();
    let json = run_json([
        "experiment",
        "campaign",
        "--target",
        "keep-off",
        "--episodes",
        "2",
        "--seed",
        "2",
        "--speeds",
        "1.5",
        "--out",
        d,
        "--json",
    ]);
    let details = &json["details"];
    assert_eq!(details["target"], "keep-off");
    let guards = std::fs::read_to_string(dir.path.join("campaign-guards.csv")).unwrap();
    assert_eq!(guards.lines().count(), 1 + 2 * 4 * 5);
    assert!(guards.starts_with("episode,kind,target,"), "{guards}");
    let episodes = std::fs::read_to_string(dir.path.join("campaign-episodes.csv")).unwrap();
    assert!(episodes.starts_with("episode,kind,target,"), "{episodes}");
    let summary = details["keep_off"].as_array().unwrap();
    // 4 rates x (5 targets + all) x 4 sources
    assert_eq!(summary.len(), 4 * 6 * 4);
    for row in summary
        .iter()
        .filter(|r| r["camera_rate_hz"] == 0.0 && r["target"] == "all")
    {
        assert_eq!(row["episodes"], 2, "{row}");
        let (free, feasible) = (
            row["contact_free"].as_u64().unwrap(),
            row["feasible"].as_u64().unwrap(),
        );
        assert!(free <= feasible, "{row}");
        if row["source"] == "exact" {
            assert_eq!(free, feasible, "{row}");
        }
    }
    let single = concat!(env!("CARGO_MANIFEST_DIR"), "/tools/configs/single_hip.toml");
    let err = run_err([
        "experiment",
        "campaign",
        "--target",
        "keep-off",
        "--config",
        single,
        "--episodes",
        "1",
        "--out",
        d,
    ]);
    assert!(
        err.contains("single-HIP") && err.contains("single_hip.toml"),
        "{err}"
    );
    let err = run_err(["experiment", "campaign", "--target", "elbow", "--out", d]);
    assert!(
        err.contains("--target") && err.contains("keep-off"),
        "{err}"
    );
}

/// `--write-episodes` writes the listed episodes, drawn as the campaign draws them, as scene
/// files headed by the command that runs them, and runs none; an index no campaign reaches
/// is refused with its value.
#[test]
fn listed_episodes_are_written_as_scene_files_without_running() {
    let dir = TempDir::new("campaign_write_episodes");
    let d = dir.path.to_str().unwrap();
    let json = run_json([
        "experiment",
        "campaign",
        "--seed",
        "35",
        "--write-episodes",
        "748,3",
        "--speeds",
        "1.5,2",
        "--out",
        d,
        "--json",
    ]);
    let written = json["details"]["written"].as_array().unwrap();
    assert_eq!(written.len(), 2);
    for (w, index) in written.iter().zip([748, 3]) {
        let path = std::path::Path::new(w["file"].as_str().unwrap());
        let text = std::fs::read_to_string(path).unwrap();
        let drawn = episode::generate(35, index).unwrap();
        let command = format!(
            "safe-speed --scene {} --speeds 1.5,2 --camera-rate-hz {}",
            path.display(),
            drawn.camera_rate_hz
        );
        assert!(text.contains(&command), "{text}");
        assert_eq!(Scene::from_file(path).unwrap().file, drawn.scene.file);
        assert_eq!(w["camera_rate_hz"], drawn.camera_rate_hz);
    }
    assert!(!dir.path.join("campaign-runs.csv").exists());
    let err = run_err([
        "experiment",
        "campaign",
        "--write-episodes",
        "100000",
        "--out",
        d,
    ]);
    assert!(err.contains("episode 100000"), "{err}");
    let err = run_err([
        "experiment",
        "campaign",
        "--write-episodes",
        "3",
        "--speeds",
        "9",
        "--out",
        d,
    ]);
    assert!(err.contains("got 9"), "{err}");
}

#[test]
fn bad_campaign_arguments_are_refused_with_the_value() {
    let dir = TempDir::new("campaign_bad");
    let d = dir.path.to_str().unwrap();
    let err = run_err(["experiment", "campaign", "--episodes", "0", "--out", d]);
    assert!(
        err.contains("--episodes must be 1 to") && err.contains("got 0"),
        "{err}"
    );
    let err = run_err(["experiment", "campaign", "--speeds", "9", "--out", d]);
    assert!(err.contains("got 9"), "{err}");
    // an episode file edited into nonsense: the error names the value
    let e = episode::generate(1, 0).unwrap();
    let text = toml::to_string(&e.scene.file)
        .unwrap()
        .replace("rate_hz = ", "rate_hz = 1");
    let path = dir.path.join("edited.toml");
    std::fs::write(&path, text).unwrap();
    let err = run_err([
        "experiment",
        "safe-speed",
        "--scene",
        path.to_str().unwrap(),
        "--out",
        d,
    ]);
    assert!(err.contains("rate_hz must be 30, 60 or 90"), "{err}");
    // a body that moves away from the HIP
    let mut file = e.scene.file.clone();
    for b in &mut file.bodies {
        if let hapcloud::scene::Motion::ConstantVelocity { velocity_m_s, .. } = &mut b.motion {
            *velocity_m_s = -*velocity_m_s;
        }
    }
    let path = dir.path.join("away.toml");
    std::fs::write(&path, toml::to_string(&file).unwrap()).unwrap();
    let err = run_err([
        "experiment",
        "safe-speed",
        "--scene",
        path.to_str().unwrap(),
        "--speeds",
        "1",
        "--out",
        d,
    ]);
    assert!(err.contains("never approaches the HIP"), "{err}");
}
