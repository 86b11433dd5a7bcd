//! The safety campaign (`hapcloud experiment campaign`): randomized approach episodes
//! ([`crate::scene::episode`]) each run through the closed loop at every tested speed from
//! four surface sources (the exact surface, the delayed oracle, the visible oracle,
//! perception: see [`SurfaceSource`]), as `hapcloud experiment safe-speed` runs one scene. A run is safe when
//! the true surface never reaches the HIP centre and the controller never falls back.
//!
//! Per speed, camera rate and source the campaign reports the fraction of episodes safe with
//! its count, and the minimum-margin distribution (median, worst). An episode the exact
//! surface does not survive at a speed is infeasible there (no perception could do better)
//! and is counted apart; the oracles' and perception's fractions are over the feasible
//! episodes, and each source's is also given over the episodes the delayed oracle survives
//! (what latency allows) and over those the visible oracle survives (what latency and the
//! cameras' views allow: what any perception with these cameras could survive).
//!
//! Contact at the handle (the handle may touch the patient): per run, the closing speed of
//! body part and HIP at the true surface's first touch of the HIP sphere gives the transient
//! contact force of ISO/TS 15066's body model, `F = v sqrt(mu k)` with `mu` the reduced mass
//! of the handle and the body part (1/mu = 1/m_handle + 1/m_body), compared with the region's
//! transient limit ([`REGIONS`], REFERENCE.md).
//!
//! Aimed at the keep-off guards (`--target keep-off`, [`Target::KeepOff`]), each episode's
//! body comes at a keep-off guard drawn from the controller's config
//! ([`episode::generate_keep_off`]) and every run also runs the keep-off guards and tracks
//! each one's true `d_proj` (a keep-off guard may not touch at all). A run is contact-free
//! when no keep-off guard touches a body; an episode whose exact-surface run is not
//! contact-free is infeasible. Per speed, camera rate, target guard and source the
//! campaign reports the contact-free fraction over the feasible episodes and over the
//! delayed and the visible oracle's contact-free episodes, and counts apart the runs in which
//! the target guard touched and those in which another guard did (a reaction that pushed
//! another link into the patient); the handle's margin is reported as above.
//!
//! Episodes run in parallel (rayon, one per core, each rendering on one thread); results do
//! not depend on the thread count or order.

use super::safe_speed::{SpeedRow, run_at_speed};
use super::scene_loop::{SceneLoopError, SceneLoopOptions, SurfaceSource};
use crate::robot::guards::{GuardConfig, GuardRole};
use crate::scene::episode::{self, BodyKind, Episode};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::HashSet;

/// Most episodes one campaign runs (beyond it a typo: 100,000 episodes are days of CPU).
pub const MAX_EPISODES: u32 = 100_000;
/// Most speeds one campaign runs.
pub const MAX_SPEEDS: usize = 16;
/// Speeds a campaign accepts, m/s (an episode lasts as long as its body takes to travel).
pub const SPEEDS_MPS: std::ops::RangeInclusive<f64> = 0.1..=5.0;

/// Why a campaign could not run.
#[derive(Debug, thiserror::Error)]
pub enum CampaignError {
    #[error("campaign: {0}")]
    Value(String),
    #[error("episode {index}: {source}")]
    Episode {
        index: u32,
        #[source]
        source: SceneLoopError,
    },
}

/// What a campaign's episodes come at.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Target {
    /// The resting handle ([`episode::generate`]).
    #[default]
    Handle,
    /// A keep-off guard of the controller's config ([`episode::generate_keep_off`]); the
    /// keep-off guards run in every run ([`SceneLoopOptions::keep_off`]).
    KeepOff,
}

impl Target {
    pub const ALL: [Target; 2] = [Target::Handle, Target::KeepOff];

    /// The name on the command line (`--target`).
    pub fn name(self) -> &'static str {
        match self {
            Target::Handle => "handle",
            Target::KeepOff => "keep-off",
        }
    }
}

/// What to run.
#[derive(Clone, Debug, PartialEq)]
pub struct CampaignConfig {
    pub episodes: u32,
    pub seed: u64,
    pub speeds_mps: Vec<f64>,
    pub target: Target,
}

impl CampaignConfig {
    /// Checks the arguments; the error names the value.
    pub fn validate(&self) -> Result<(), CampaignError> {
        if !(1..=MAX_EPISODES).contains(&self.episodes) {
            return Err(CampaignError::Value(format!(
                "--episodes must be 1 to {MAX_EPISODES}, got {}",
                self.episodes
            )));
        }
        validate_speeds(&self.speeds_mps)
    }
}

/// Checks a campaign's `--speeds`: 1 to [`MAX_SPEEDS`], each within [`SPEEDS_MPS`]; the error
/// names the value.
pub fn validate_speeds(speeds_mps: &[f64]) -> Result<(), CampaignError> {
    if speeds_mps.is_empty() || speeds_mps.len() > MAX_SPEEDS {
        return Err(CampaignError::Value(format!(
            "--speeds takes 1 to {MAX_SPEEDS} speeds, got {}",
            speeds_mps.len()
        )));
    }
    if let Some(v) = speeds_mps.iter().find(|v| !SPEEDS_MPS.contains(*v)) {
        return Err(CampaignError::Value(format!(
            "--speeds must be finite and in [{}, {}] m/s, got {v}",
            SPEEDS_MPS.start(),
            SPEEDS_MPS.end()
        )));
    }
    Ok(())
}

/// A body region of ISO/TS 15066's body model (Table A.2, A.3 via REFERENCE.md).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Region {
    pub name: &'static str,
    /// Effective spring constant, N/m.
    pub stiffness_n_per_m: f64,
    /// Effective body mass, kg.
    pub mass_kg: f64,
    /// Transient-contact force limit, N: twice the quasi-static limit, except head and face,
    /// where contact is to be avoided and the quasi-static limit is kept.
    pub transient_limit_n: f64,
}

/// The regions a campaign's contacts are judged by. The neck's limits are not among those
/// REFERENCE.md lists: it is judged as the face, the strictest.
pub const REGIONS: [Region; 6] = [
    Region {
        name: "skull",
        stiffness_n_per_m: 150e3,
        mass_kg: 4.4,
        transient_limit_n: 130.0,
    },
    Region {
        name: "face",
        stiffness_n_per_m: 75e3,
        mass_kg: 4.4,
        transient_limit_n: 65.0,
    },
    Region {
        name: "chest",
        stiffness_n_per_m: 25e3,
        mass_kg: 40.0,
        transient_limit_n: 280.0,
    },
    Region {
        name: "upper_arm",
        stiffness_n_per_m: 30e3,
        mass_kg: 3.0,
        transient_limit_n: 300.0,
    },
    Region {
        name: "forearm",
        stiffness_n_per_m: 40e3,
        mass_kg: 2.0,
        transient_limit_n: 320.0,
    },
    Region {
        name: "hand",
        stiffness_n_per_m: 75e3,
        mass_kg: 0.6,
        transient_limit_n: 280.0,
    },
];

/// Mass of the handle side of a contact, kg (REFERENCE.md: a 2 kg exoskeleton link).
pub const HANDLE_MASS_KG: f64 = 2.0;

fn region(name: &str) -> Region {
    REGIONS
        .iter()
        .copied()
        .find(|r| r.name == name)
        .unwrap_or(REGIONS[1])
}

/// The region a touching body stands for: the episode's approaching body by its kind (a
/// head-sized body as the skull, an arm as the forearm, a torso or plate as the chest), the
/// seated patient's parts by name.
pub fn region_of(body: &str, kind: BodyKind) -> Region {
    let name = if body == episode::MOVING_BODY {
        match kind {
            BodyKind::Head => "skull",
            BodyKind::Arm => "forearm",
            BodyKind::Torso | BodyKind::Plate => "chest",
        }
    } else if body == "head" {
        "skull"
    } else if body == "torso" {
        "chest"
    } else if body.contains("upper_arm") {
        "upper_arm"
    } else if body.contains("forearm") {
        "forearm"
    } else if body.contains("hand") {
        "hand"
    } else {
        "face"
    };
    region(name)
}

/// Transient contact force of the body model at closing speed `speed_mps`, N (zero when the
/// two part).
pub fn contact_force_n(region: &Region, speed_mps: f64) -> f64 {
    let mu = 1.0 / (1.0 / HANDLE_MASS_KG + 1.0 / region.mass_kg);
    speed_mps.max(0.0) * (mu * region.stiffness_n_per_m).sqrt()
}

/// One run of one episode: the CSV's row.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RunRow {
    pub episode: u32,
    pub kind: BodyKind,
    pub camera_rate_hz: f64,
    pub start_distance_m: f64,
    pub lateral_offset_m: f64,
    pub speed_mps: f64,
    pub source: SurfaceSource,
    pub min_margin_m: f64,
    pub fallback_ticks: usize,
    pub safe: bool,
    /// Body region of the first touch (empty: none).
    pub contact_region: String,
    pub contact_speed_mps: Option<f64>,
    /// Body-model transient force at the first touch, N.
    pub contact_force_n: Option<f64>,
    pub contact_handle_force_n: Option<f64>,
    /// No touch, or a touch within the region's transient limit.
    pub contact_within_limit: bool,
    /// Cameras facing the body's leading surface where it first meets the HIP
    /// ([`Episode::leading_face_cameras`]).
    pub leading_face_cameras: usize,
}

/// One keep-off guard in one run of a keep-off episode: `campaign-guards.csv`'s row, the
/// episode's draws and [`super::safe_speed::GuardSpeedRow`]'s fields.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GuardRow {
    pub episode: u32,
    pub kind: BodyKind,
    /// The keep-off guard the episode's body comes at.
    pub target: String,
    pub camera_rate_hz: f64,
    pub speed_mps: f64,
    pub source: SurfaceSource,
    pub guard: String,
    pub min_d_proj_m: f64,
    pub body: String,
    pub contact: bool,
    pub contact_t_s: Option<f64>,
}

/// An episode's runs and its cost.
#[derive(Clone, Debug)]
pub struct EpisodeResult {
    pub episode: Episode,
    pub rows: Vec<RunRow>,
    /// Each keep-off guard in each run (empty unless the keep-off guards run).
    pub guards: Vec<GuardRow>,
    /// CPU time of the episode's runs on its thread, seconds.
    pub cpu_s: f64,
}

/// Runs one episode at every speed from every source.
pub fn run_episode(
    episode: Episode,
    speeds_mps: &[f64],
    options: &SceneLoopOptions,
) -> Result<EpisodeResult, CampaignError> {
    let started = crate::timing::thread_cpu_s();
    let index = episode.index;
    let wrap = |source| CampaignError::Episode { index, source };
    let at_rate = episode
        .scene
        .with_camera_rate_hz(episode.camera_rate_hz)
        .map_err(|e| wrap(e.into()))?;
    let mut rows = Vec::with_capacity(speeds_mps.len() * SurfaceSource::ALL.len());
    let mut guards = Vec::new();
    for &speed in speeds_mps {
        for source in SurfaceSource::ALL {
            let (row, guard_rows, _) =
                run_at_speed(&at_rate, speed, source, options).map_err(wrap)?;
            rows.push(run_row(&episode, &row));
            guards.extend(guard_rows.into_iter().map(|g| GuardRow {
                episode: episode.index,
                kind: episode.kind,
                target: episode.guard.clone().unwrap_or_default(),
                camera_rate_hz: g.camera_rate_hz,
                speed_mps: g.speed_mps,
                source: g.source,
                guard: g.guard,
                min_d_proj_m: g.min_d_proj_m,
                body: g.body,
                contact: g.contact,
                contact_t_s: g.contact_t_s,
            }));
        }
    }
    Ok(EpisodeResult {
        episode,
        rows,
        guards,
        cpu_s: crate::timing::thread_cpu_s() - started,
    })
}

fn run_row(e: &Episode, r: &SpeedRow) -> RunRow {
    let region = r.contact_body.as_deref().map(|b| region_of(b, e.kind));
    let force = region
        .zip(r.contact_speed_mps)
        .map(|(g, v)| contact_force_n(&g, v));
    RunRow {
        episode: e.index,
        kind: e.kind,
        camera_rate_hz: r.camera_rate_hz,
        start_distance_m: e.start_distance_m,
        lateral_offset_m: e.lateral_offset_m,
        speed_mps: r.speed_mps,
        source: r.source,
        min_margin_m: r.min_margin_m,
        fallback_ticks: r.fallback_ticks,
        safe: r.safe,
        contact_region: region.map_or(String::new(), |g| g.name.into()),
        contact_speed_mps: r.contact_speed_mps,
        contact_force_n: force,
        contact_handle_force_n: r.contact_handle_force_n,
        contact_within_limit: region
            .zip(force)
            .is_none_or(|(g, f)| f <= g.transient_limit_n),
        leading_face_cameras: e.leading_face_cameras,
    }
}

/// Fraction safe and margins of one source at one speed and camera rate.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SummaryRow {
    pub speed_mps: f64,
    /// Camera rate, Hz (0: every rate together).
    pub camera_rate_hz: f64,
    /// The approaching body's kind (none: every kind together).
    pub kind: Option<BodyKind>,
    /// Cameras facing the leading surface (none: any number).
    pub leading_face_cameras: Option<usize>,
    pub source: SurfaceSource,
    /// Episodes at this speed, rate and kind.
    pub episodes: usize,
    /// Of them, those the exact surface survives (the others are infeasible).
    pub feasible: usize,
    /// Feasible episodes this source survives, and their fraction.
    pub safe: usize,
    pub safe_fraction: f64,
    /// Episodes the delayed oracle survives, this source's safe ones among them and their
    /// fraction (perception's target).
    pub oracle_survived: usize,
    pub safe_of_oracle_survived: usize,
    pub safe_fraction_of_oracle_survived: f64,
    /// Median and worst minimum margin over the feasible episodes, metres.
    pub median_margin_m: f64,
    pub worst_margin_m: f64,
    /// Runs whose first touch stayed within its region's transient limit (or had none),
    /// and their share of all episodes at this speed and rate.
    pub contact_within_limit: usize,
    pub contact_within_limit_fraction: f64,
    /// Highest closing speed at a first touch, m/s (0: no touch).
    pub worst_contact_speed_mps: f64,
    /// Episodes the visible oracle survives, this source's safe ones among them and their
    /// fraction (perception's share of what these cameras' views allow).
    pub visible_survived: usize,
    pub safe_of_visible_survived: usize,
    pub safe_fraction_of_visible_survived: f64,
}

fn fraction(part: usize, whole: usize) -> f64 {
    if whole == 0 {
        f64::NAN
    } else {
        part as f64 / whole as f64
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// The summary of `rows` per speed, camera rate (each, then all together) and source.
pub fn summarize(rows: &[RunRow], speeds_mps: &[f64]) -> Vec<SummaryRow> {
    let mut out = Vec::new();
    for &speed in speeds_mps {
        for rate in [30.0, 60.0, 90.0, 0.0] {
            out.extend(summary_at(rows, speed, rate, Group::default()));
        }
    }
    out
}

/// The summary of `rows` per speed, body kind and source, every camera rate together: which
/// bodies perception loses (the worst episodes' cause).
pub fn summarize_by_kind(rows: &[RunRow], speeds_mps: &[f64]) -> Vec<SummaryRow> {
    let mut out = Vec::new();
    for &speed in speeds_mps {
        for kind in BodyKind::ALL {
            let group = Group {
                kind: Some(kind),
                ..Group::default()
            };
            out.extend(summary_at(rows, speed, 0.0, group));
        }
    }
    out
}

/// The summary of `rows` per speed, number of cameras facing the approaching body's leading
/// surface (0 up to the most any episode has) and source, every rate and kind together: how
/// much of what perception loses no camera could see.
pub fn summarize_by_view(rows: &[RunRow], speeds_mps: &[f64]) -> Vec<SummaryRow> {
    let most = rows
        .iter()
        .map(|r| r.leading_face_cameras)
        .max()
        .unwrap_or(0);
    let mut out = Vec::new();
    for &speed in speeds_mps {
        for cameras in 0..=most {
            let group = Group {
                leading_face_cameras: Some(cameras),
                ..Group::default()
            };
            out.extend(summary_at(rows, speed, 0.0, group));
        }
    }
    out
}

/// The episodes one summary row counts: of one body kind, with so many cameras facing the
/// leading surface, or (none) all.
#[derive(Clone, Copy, Debug, Default)]
struct Group {
    kind: Option<BodyKind>,
    leading_face_cameras: Option<usize>,
}

impl Group {
    fn holds(&self, row: &RunRow) -> bool {
        self.kind.is_none_or(|k| row.kind == k)
            && (self.leading_face_cameras).is_none_or(|n| row.leading_face_cameras == n)
    }
}

/// The episodes a summary cell's fractions count over: those whose exact-surface run
/// succeeded (feasible; the others are infeasible) and those each oracle's run succeeded in
/// (what latency, and latency and the cameras' views, allow). The handle's summary and the
/// keep-off summary differ only in what success is.
struct Survivors {
    feasible: HashSet<u32>,
    oracle: HashSet<u32>,
    visible: HashSet<u32>,
}

impl Survivors {
    /// From the episodes whose run from each source succeeded.
    fn new<I: Iterator<Item = u32>>(succeeded: impl Fn(SurfaceSource) -> I) -> Self {
        Self {
            feasible: succeeded(SurfaceSource::Exact).collect(),
            oracle: succeeded(SurfaceSource::DelayedOracle).collect(),
            visible: succeeded(SurfaceSource::VisibleOracle).collect(),
        }
    }

    /// How many of a source's `succeeded` episodes are feasible, how many the delayed oracle
    /// and how many the visible oracle survived.
    fn count(&self, succeeded: impl Iterator<Item = u32>) -> [usize; 3] {
        let mut counts = [0; 3];
        for episode in succeeded {
            for (n, set) in counts
                .iter_mut()
                .zip([&self.feasible, &self.oracle, &self.visible])
            {
                *n += usize::from(set.contains(&episode));
            }
        }
        counts
    }
}

/// One summary row per source of the runs at `speed`, camera `rate` (0: every rate) in
/// `group`.
fn summary_at(rows: &[RunRow], speed: f64, rate: f64, group: Group) -> Vec<SummaryRow> {
    let at = |source: SurfaceSource| {
        rows.iter().filter(move |r| {
            r.speed_mps == speed
                && r.source == source
                && (rate == 0.0 || r.camera_rate_hz == rate)
                && group.holds(r)
        })
    };
    let survivors = Survivors::new(|source| at(source).filter(|r| r.safe).map(|r| r.episode));
    let Survivors {
        feasible,
        oracle,
        visible,
    } = &survivors;
    SurfaceSource::ALL
        .into_iter()
        .map(|source| {
            let all: Vec<&RunRow> = at(source).collect();
            let [safe, safe_of_oracle, safe_of_visible] =
                survivors.count(all.iter().filter(|r| r.safe).map(|r| r.episode));
            let margins: Vec<f64> = (all.iter())
                .filter(|r| feasible.contains(&r.episode))
                .map(|r| r.min_margin_m)
                .collect();
            let within = all.iter().filter(|r| r.contact_within_limit).count();
            SummaryRow {
                speed_mps: speed,
                camera_rate_hz: rate,
                kind: group.kind,
                leading_face_cameras: group.leading_face_cameras,
                source,
                episodes: all.len(),
                feasible: feasible.len(),
                safe,
                safe_fraction: fraction(safe, feasible.len()),
                oracle_survived: oracle.len(),
                safe_of_oracle_survived: safe_of_oracle,
                safe_fraction_of_oracle_survived: fraction(safe_of_oracle, oracle.len()),
                worst_margin_m: margins.iter().copied().fold(f64::NAN, f64::min),
                median_margin_m: median(margins),
                contact_within_limit: within,
                contact_within_limit_fraction: fraction(within, all.len()),
                worst_contact_speed_mps: all
                    .iter()
                    .filter_map(|r| r.contact_speed_mps)
                    .fold(0.0, f64::max),
                visible_survived: visible.len(),
                safe_of_visible_survived: safe_of_visible,
                safe_fraction_of_visible_survived: fraction(safe_of_visible, visible.len()),
            }
        })
        .collect()
}

/// Contacts of one source at one speed in one body region.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ContactRow {
    pub speed_mps: f64,
    pub source: SurfaceSource,
    pub region: String,
    pub contacts: usize,
    pub within_limit: usize,
    pub median_speed_mps: f64,
    pub worst_speed_mps: f64,
    pub worst_force_n: f64,
    pub transient_limit_n: f64,
}

/// First touches per speed, source and body region.
pub fn contacts(rows: &[RunRow], speeds_mps: &[f64]) -> Vec<ContactRow> {
    let mut out = Vec::new();
    for &speed in speeds_mps {
        for source in SurfaceSource::ALL {
            for g in REGIONS {
                let touching: Vec<&RunRow> = rows
                    .iter()
                    .filter(|r| r.speed_mps == speed && r.source == source)
                    .filter(|r| r.contact_region == g.name)
                    .collect();
                if touching.is_empty() {
                    continue;
                }
                let speeds: Vec<f64> = touching
                    .iter()
                    .filter_map(|r| r.contact_speed_mps)
                    .collect();
                out.push(ContactRow {
                    speed_mps: speed,
                    source,
                    region: g.name.into(),
                    contacts: touching.len(),
                    within_limit: touching.iter().filter(|r| r.contact_within_limit).count(),
                    worst_speed_mps: speeds.iter().copied().fold(f64::NAN, f64::max),
                    median_speed_mps: median(speeds),
                    worst_force_n: touching
                        .iter()
                        .filter_map(|r| r.contact_force_n)
                        .fold(f64::NAN, f64::max),
                    transient_limit_n: g.transient_limit_n,
                });
            }
        }
    }
    out
}

/// One run of a keep-off episode over all its guards.
#[derive(Clone, Debug, PartialEq)]
struct KeepOffRun<'a> {
    episode: u32,
    camera_rate_hz: f64,
    target: &'a str,
    speed_mps: f64,
    source: SurfaceSource,
    /// The target guard's least true `d_proj`, metres.
    target_d_proj_m: f64,
    target_contact: bool,
    /// Another keep-off guard touched a body.
    other_contact: bool,
    /// Another keep-off guard touched one of the patient's own bodies (not the approaching
    /// one): a reaction that pushed another link into the patient.
    other_patient_contact: bool,
}

impl KeepOffRun<'_> {
    fn contact_free(&self) -> bool {
        !self.target_contact && !self.other_contact
    }
}

/// The runs of `rows` (one per episode, speed and source, in `rows`' order).
fn keep_off_runs(rows: &[GuardRow]) -> Vec<KeepOffRun<'_>> {
    let mut runs: Vec<KeepOffRun<'_>> = Vec::new();
    for r in rows {
        let is_target = r.guard == r.target;
        let same = |k: &KeepOffRun<'_>| {
            k.episode == r.episode && k.speed_mps == r.speed_mps && k.source == r.source
        };
        let run = match runs.last_mut().filter(|k| same(k)) {
            Some(run) => run,
            None => {
                runs.push(KeepOffRun {
                    episode: r.episode,
                    camera_rate_hz: r.camera_rate_hz,
                    target: &r.target,
                    speed_mps: r.speed_mps,
                    source: r.source,
                    target_d_proj_m: f64::INFINITY,
                    target_contact: false,
                    other_contact: false,
                    other_patient_contact: false,
                });
                runs.last_mut().unwrap_or_else(|| unreachable!("pushed"))
            }
        };
        if is_target {
            run.target_d_proj_m = r.min_d_proj_m;
            run.target_contact = r.contact;
        } else {
            run.other_contact |= r.contact;
            run.other_patient_contact |= r.contact && r.body != episode::MOVING_BODY;
        }
    }
    runs
}

/// Keep-off guards' contacts of one source at one speed, camera rate and target guard.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GuardSummaryRow {
    pub speed_mps: f64,
    /// Camera rate, Hz (0: every rate together).
    pub camera_rate_hz: f64,
    /// The keep-off guard the episodes' bodies come at (`all`: every target together).
    pub target: String,
    pub source: SurfaceSource,
    /// Episodes at this speed, rate and target.
    pub episodes: usize,
    /// Of them, those whose exact-surface run no keep-off guard touches (the others are
    /// infeasible).
    pub feasible: usize,
    /// Feasible episodes this source runs without any keep-off guard touching, and their
    /// fraction.
    pub contact_free: usize,
    pub contact_free_fraction: f64,
    /// Episodes the delayed oracle runs contact-free, this source's contact-free ones among
    /// them and their fraction.
    pub oracle_survived: usize,
    pub contact_free_of_oracle_survived: usize,
    pub contact_free_fraction_of_oracle_survived: f64,
    /// The same over the visible oracle's contact-free episodes.
    pub visible_survived: usize,
    pub contact_free_of_visible_survived: usize,
    pub contact_free_fraction_of_visible_survived: f64,
    /// Runs (of all episodes) in which the target guard touched the body.
    pub target_contacts: usize,
    /// Runs (of all episodes) in which another keep-off guard touched a body (the
    /// approaching one sweeping on past its target, or the patient).
    pub other_guard_contacts: usize,
    /// Of them, the runs in which another keep-off guard touched the patient's own bodies
    /// (deepest there): a reaction that pushed another link into the patient.
    pub other_guard_patient_contacts: usize,
    /// Median and worst least `d_proj` of the target guard over the feasible episodes,
    /// metres.
    pub median_target_d_proj_m: f64,
    pub worst_target_d_proj_m: f64,
}

/// The keep-off summary of `rows` per speed, camera rate (each, then all together), target
/// guard (each in `targets`' order, then all together) and source.
pub fn summarize_keep_off(
    rows: &[GuardRow],
    speeds_mps: &[f64],
    targets: &[String],
) -> Vec<GuardSummaryRow> {
    let runs = keep_off_runs(rows);
    let mut out = Vec::new();
    for &speed in speeds_mps {
        for rate in [30.0, 60.0, 90.0, 0.0] {
            for target in targets.iter().map(|t| Some(t.as_str())).chain([None]) {
                out.extend(keep_off_summary_at(&runs, speed, rate, target));
            }
        }
    }
    out
}

fn keep_off_summary_at(
    runs: &[KeepOffRun<'_>],
    speed: f64,
    rate: f64,
    target: Option<&str>,
) -> Vec<GuardSummaryRow> {
    let at = |source: SurfaceSource| {
        runs.iter().filter(move |r| {
            r.speed_mps == speed
                && r.source == source
                && (rate == 0.0 || r.camera_rate_hz == rate)
                && target.is_none_or(|t| r.target == t)
        })
    };
    let survivors =
        Survivors::new(|source| at(source).filter(|r| r.contact_free()).map(|r| r.episode));
    let Survivors {
        feasible,
        oracle,
        visible,
    } = &survivors;
    SurfaceSource::ALL
        .into_iter()
        .map(|source| {
            let all: Vec<&KeepOffRun<'_>> = at(source).collect();
            let [contact_free, of_oracle, of_visible] =
                survivors.count((all.iter()).filter(|r| r.contact_free()).map(|r| r.episode));
            let gaps: Vec<f64> = all
                .iter()
                .filter(|r| feasible.contains(&r.episode))
                .map(|r| r.target_d_proj_m)
                .collect();
            GuardSummaryRow {
                speed_mps: speed,
                camera_rate_hz: rate,
                target: target.unwrap_or("all").to_string(),
                source,
                episodes: all.len(),
                feasible: feasible.len(),
                contact_free,
                contact_free_fraction: fraction(contact_free, feasible.len()),
                oracle_survived: oracle.len(),
                contact_free_of_oracle_survived: of_oracle,
                contact_free_fraction_of_oracle_survived: fraction(of_oracle, oracle.len()),
                visible_survived: visible.len(),
                contact_free_of_visible_survived: of_visible,
                contact_free_fraction_of_visible_survived: fraction(of_visible, visible.len()),
                target_contacts: all.iter().filter(|r| r.target_contact).count(),
                other_guard_contacts: all.iter().filter(|r| r.other_contact).count(),
                other_guard_patient_contacts: all
                    .iter()
                    .filter(|r| r.other_patient_contact)
                    .count(),
                worst_target_d_proj_m: gaps.iter().copied().fold(f64::NAN, f64::min),
                median_target_d_proj_m: median(gaps),
            }
        })
        .collect()
}

/// A finished campaign.
#[derive(Clone, Debug)]
pub struct Campaign {
    pub config: CampaignConfig,
    pub episodes: Vec<EpisodeResult>,
    pub summary: Vec<SummaryRow>,
    /// The summary per body kind, every camera rate together.
    pub by_kind: Vec<SummaryRow>,
    /// The summary per number of cameras facing the leading surface, every rate and kind
    /// together.
    pub by_view: Vec<SummaryRow>,
    pub contacts: Vec<ContactRow>,
    /// The keep-off summary (empty for a handle campaign).
    pub keep_off: Vec<GuardSummaryRow>,
}

impl Campaign {
    /// Every run, episode by episode.
    pub fn rows(&self) -> impl Iterator<Item = &RunRow> {
        self.episodes.iter().flat_map(|e| e.rows.iter())
    }

    /// The `count` perception runs with the lowest margin among those the delayed oracle
    /// survives, one per episode (the episode's worst speed), worst first.
    pub fn worst_perception(&self, count: usize) -> Vec<(&EpisodeResult, &RunRow)> {
        let mut worst: Vec<(&EpisodeResult, &RunRow)> = self
            .episodes
            .iter()
            .filter_map(|e| {
                e.rows
                    .iter()
                    .filter(|r| r.source == SurfaceSource::Perception)
                    .filter(|r| {
                        e.rows.iter().any(|o| {
                            o.source == SurfaceSource::DelayedOracle
                                && o.speed_mps == r.speed_mps
                                && o.safe
                        })
                    })
                    .min_by(|a, b| a.min_margin_m.total_cmp(&b.min_margin_m))
                    .map(|r| (e, r))
            })
            .collect();
        worst.sort_by(|a, b| a.1.min_margin_m.total_cmp(&b.1.min_margin_m));
        worst.truncate(count);
        worst
    }

    /// Every keep-off guard's row, episode by episode.
    pub fn guard_rows(&self) -> impl Iterator<Item = &GuardRow> {
        self.episodes.iter().flat_map(|e| e.guards.iter())
    }

    /// The `count` perception runs of a keep-off campaign with the least target-guard
    /// `d_proj` among those the delayed oracle runs contact-free, one per episode (the
    /// episode's worst speed), worst first: the episode and the speed.
    pub fn worst_keep_off(&self, count: usize) -> Vec<(&EpisodeResult, f64, f64)> {
        let mut worst: Vec<(&EpisodeResult, f64, f64)> = self
            .episodes
            .iter()
            .filter_map(|e| {
                let runs = keep_off_runs(&e.guards);
                runs.iter()
                    .filter(|r| r.source == SurfaceSource::Perception)
                    .filter(|r| {
                        runs.iter().any(|o| {
                            o.source == SurfaceSource::DelayedOracle
                                && o.speed_mps == r.speed_mps
                                && o.contact_free()
                        })
                    })
                    .min_by(|a, b| a.target_d_proj_m.total_cmp(&b.target_d_proj_m))
                    .map(|r| (e, r.speed_mps, r.target_d_proj_m))
            })
            .collect();
        worst.sort_by(|a, b| a.2.total_cmp(&b.2));
        worst.truncate(count);
        worst
    }
}

/// The keep-off guards a campaign aimed at `target` can draw (none for the handle); an
/// error when it aims at keep-off guards and `guards` is a single-HIP config.
pub fn keep_off_targets(
    target: Target,
    guards: &GuardConfig,
) -> Result<Vec<String>, CampaignError> {
    let targets: Vec<String> = (guards.guards.iter())
        .filter(|g| g.role == GuardRole::KeepOff)
        .map(|g| g.name.clone())
        .collect();
    if target == Target::KeepOff && targets.is_empty() {
        return Err(CampaignError::Value(
            "--target keep-off needs keep-off guards, but the controller's guards are a \
             single-HIP config (the handle alone)"
                .into(),
        ));
    }
    Ok(targets)
}

/// Episode `index` of seed `seed` aimed at `target` (a keep-off guard of `guards`), as the
/// campaign runs it.
pub fn draw(
    seed: u64,
    target: Target,
    guards: &GuardConfig,
    index: u32,
) -> Result<Episode, CampaignError> {
    match target {
        Target::Handle => episode::generate(seed, index),
        Target::KeepOff => episode::generate_keep_off(seed, index, guards),
    }
    .map_err(|e| CampaignError::Episode {
        index,
        source: e.into(),
    })
}

/// Runs the campaign (see the module doc); `progress` is called after each episode.
pub fn run(
    config: &CampaignConfig,
    options: &SceneLoopOptions,
    progress: &(dyn Fn() + Sync),
) -> Result<Campaign, CampaignError> {
    config.validate()?;
    let guards = &options.sim.controller.guards;
    let targets = keep_off_targets(config.target, guards)?;
    let keep_off = config.target == Target::KeepOff;
    let mut speeds = config.speeds_mps.clone();
    speeds.sort_by(f64::total_cmp);
    speeds.dedup();
    let options = SceneLoopOptions {
        render_threads: Some(1),
        keep_off,
        ..options.clone()
    };
    let episodes: Vec<EpisodeResult> = (0..config.episodes)
        .into_par_iter()
        .map(|index| {
            let result = draw(config.seed, config.target, guards, index)
                .and_then(|e| run_episode(e, &speeds, &options));
            progress();
            result
        })
        .collect::<Result<_, _>>()?;
    let rows: Vec<RunRow> = episodes.iter().flat_map(|e| e.rows.clone()).collect();
    let guard_rows: Vec<GuardRow> = episodes.iter().flat_map(|e| e.guards.clone()).collect();
    Ok(Campaign {
        keep_off: if keep_off {
            summarize_keep_off(&guard_rows, &speeds, &targets)
        } else {
            Vec::new()
        },
        summary: summarize(&rows, &speeds),
        by_kind: summarize_by_kind(&rows, &speeds),
        by_view: summarize_by_view(&rows, &speeds),
        contacts: contacts(&rows, &speeds),
        config: CampaignConfig {
            speeds_mps: speeds,
            ..config.clone()
        },
        episodes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// REFERENCE.md's transient speeds with a 2 kg link: skull about 0.3 m/s, chest 1.3,
    /// forearm 1.6, hand 1.5 (the force reaches the limit there).
    #[test]
    fn the_body_model_reaches_each_limit_at_the_reference_speeds() {
        for (name, v) in [
            ("skull", 0.3),
            ("chest", 1.3),
            ("forearm", 1.6),
            ("hand", 1.5),
        ] {
            let g = region(name);
            let at_limit = g.transient_limit_n / contact_force_n(&g, 1.0);
            assert!((at_limit - v).abs() < 0.05, "{name}: {at_limit}");
        }
        assert_eq!(contact_force_n(&region("chest"), -1.0), 0.0);
    }

    #[test]
    fn bad_campaign_arguments_name_the_value() {
        let ok = CampaignConfig {
            episodes: 10,
            seed: 1,
            speeds_mps: vec![1.0],
            target: Target::Handle,
        };
        ok.validate().unwrap();
        for (config, needle) in [
            (
                CampaignConfig {
                    episodes: 0,
                    ..ok.clone()
                },
                "got 0",
            ),
            (
                CampaignConfig {
                    speeds_mps: vec![1.0, f64::NAN],
                    ..ok.clone()
                },
                "got NaN",
            ),
            (
                CampaignConfig {
                    speeds_mps: vec![],
                    ..ok.clone()
                },
                "--speeds takes",
            ),
            (
                CampaignConfig {
                    speeds_mps: vec![50.0],
                    ..ok.clone()
                },
                "got 50",
            ),
        ] {
            let err = config.validate().unwrap_err().to_string();
            assert!(err.contains(needle), "{err}");
        }
    }

    fn row(episode: u32, source: SurfaceSource, safe: bool, margin: f64) -> RunRow {
        RunRow {
            episode,
            kind: BodyKind::Plate,
            camera_rate_hz: 30.0,
            start_distance_m: 0.4,
            lateral_offset_m: 0.0,
            speed_mps: 1.0,
            source,
            min_margin_m: margin,
            fallback_ticks: 0,
            safe,
            contact_region: String::new(),
            contact_speed_mps: None,
            contact_force_n: None,
            contact_handle_force_n: None,
            contact_within_limit: true,
            leading_face_cameras: 1,
        }
    }

    /// Episode 2 is infeasible (the exact surface fails): counted apart; perception's share
    /// of the oracle's survivors counts only episodes the oracle survives.
    #[test]
    fn the_summary_counts_infeasible_episodes_apart() {
        use SurfaceSource::{DelayedOracle, Exact, Perception};
        let rows = [
            row(0, Exact, true, 0.05),
            row(0, DelayedOracle, true, 0.04),
            row(0, Perception, true, 0.03),
            row(1, Exact, true, 0.05),
            row(1, DelayedOracle, false, -0.01),
            row(1, Perception, false, -0.02),
            row(2, Exact, false, -0.01),
            row(2, DelayedOracle, false, -0.02),
            row(2, Perception, false, -0.03),
        ];
        let s = summarize(&rows, &[1.0]);
        let p = s
            .iter()
            .find(|r| r.source == Perception && r.camera_rate_hz == 30.0)
            .unwrap();
        assert_eq!((p.episodes, p.feasible, p.safe), (3, 2, 1));
        assert_eq!(p.safe_fraction, 0.5);
        assert_eq!((p.oracle_survived, p.safe_of_oracle_survived), (1, 1));
        // without visible-oracle runs nothing survives it
        assert_eq!((p.visible_survived, p.safe_of_visible_survived), (0, 0));
        assert!(p.safe_fraction_of_visible_survived.is_nan());
        assert_eq!(p.worst_margin_m, -0.02);
        assert!((p.median_margin_m - 0.005).abs() < 1e-12);
        let none = s
            .iter()
            .find(|r| r.source == Perception && r.camera_rate_hz == 60.0)
            .unwrap();
        assert_eq!(none.episodes, 0);
        assert!(none.safe_fraction.is_nan());
    }

    /// Episode 1's near face is hidden: the delayed oracle survives it, the visible oracle
    /// and perception do not. Perception's share is 1 of 2 of the delayed oracle's survivors
    /// and 1 of 1 of the visible oracle's.
    #[test]
    fn perception_is_also_counted_over_the_visible_oracles_survivors() {
        use SurfaceSource::{DelayedOracle, Exact, Perception, VisibleOracle};
        let rows = [
            row(0, Exact, true, 0.05),
            row(0, DelayedOracle, true, 0.04),
            row(0, VisibleOracle, true, 0.04),
            row(0, Perception, true, 0.03),
            row(1, Exact, true, 0.05),
            row(1, DelayedOracle, true, 0.03),
            row(1, VisibleOracle, false, -0.01),
            row(1, Perception, false, -0.02),
        ];
        let s = summarize(&rows, &[1.0]);
        let at = |source| {
            s.iter()
                .find(|r| r.source == source && r.camera_rate_hz == 0.0)
                .unwrap()
        };
        let p = at(Perception);
        assert_eq!((p.oracle_survived, p.safe_of_oracle_survived), (2, 1));
        assert_eq!((p.visible_survived, p.safe_of_visible_survived), (1, 1));
        assert_eq!(p.safe_fraction_of_oracle_survived, 0.5);
        assert_eq!(p.safe_fraction_of_visible_survived, 1.0);
        let v = at(VisibleOracle);
        assert_eq!((v.safe, v.safe_of_oracle_survived), (1, 1));
    }

    fn guard_row(episode: u32, source: SurfaceSource, guard: &str, min_d_proj_m: f64) -> GuardRow {
        GuardRow {
            episode,
            kind: BodyKind::Arm,
            target: "forearm".into(),
            camera_rate_hz: 30.0,
            speed_mps: 1.5,
            source,
            guard: guard.into(),
            min_d_proj_m,
            body: "approaching".into(),
            contact: min_d_proj_m < 0.0,
            contact_t_s: (min_d_proj_m < 0.0).then_some(1.0),
        }
    }

    /// Episode 0: every source keeps the forearm off, perception pushes the elbow into the
    /// torso (another guard's contact with the patient: not contact-free). Episode 1: the delayed oracle lets
    /// the forearm touch. Episode 2: infeasible (the exact surface pushes the upper arm in).
    #[test]
    fn the_keep_off_summary_counts_target_and_other_guards_apart() {
        use SurfaceSource::{DelayedOracle, Exact, Perception};
        let mut rows = Vec::new();
        for (episode, source, forearm, elbow, upper_arm) in [
            (0, Exact, 0.02, 0.03, 0.05),
            (0, DelayedOracle, 0.01, 0.03, 0.05),
            (0, Perception, 0.005, -0.004, 0.05),
            (1, Exact, 0.02, 0.03, 0.05),
            (1, DelayedOracle, -0.01, 0.03, 0.05),
            (1, Perception, 0.004, 0.03, 0.05),
            (2, Exact, 0.02, 0.03, -0.002),
            (2, DelayedOracle, -0.03, 0.03, 0.05),
            (2, Perception, -0.02, 0.03, 0.05),
        ] {
            rows.push(guard_row(episode, source, "forearm", forearm));
            rows.push(guard_row(episode, source, "elbow", elbow));
            rows.push(guard_row(episode, source, "upper_arm", upper_arm));
        }
        // episode 0's elbow is pushed into the torso, episode 2's upper arm meets the
        // approaching body
        rows[7].body = "torso".into();
        let targets = ["forearm".to_string(), "elbow".to_string()];
        let s = summarize_keep_off(&rows, &[1.5], &targets);
        // 4 rates x (2 targets + all) x 4 sources
        assert_eq!(s.len(), 4 * 3 * 4);
        let at = |target: &str, source| {
            s.iter()
                .find(|r| r.camera_rate_hz == 0.0 && r.target == target && r.source == source)
                .unwrap()
        };
        let p = at("forearm", Perception);
        assert_eq!((p.episodes, p.feasible, p.contact_free), (3, 2, 1));
        assert_eq!(p.contact_free_fraction, 0.5);
        assert_eq!(
            (p.oracle_survived, p.contact_free_of_oracle_survived),
            (1, 0)
        );
        assert_eq!(
            (
                p.target_contacts,
                p.other_guard_contacts,
                p.other_guard_patient_contacts
            ),
            (1, 1, 1)
        );
        assert_eq!(p.worst_target_d_proj_m, 0.004);
        assert!((p.median_target_d_proj_m - 0.0045).abs() < 1e-12);
        let o = at("forearm", DelayedOracle);
        assert_eq!((o.contact_free, o.target_contacts), (1, 2));
        let e = at("forearm", Exact);
        assert_eq!(
            (
                e.contact_free,
                e.other_guard_contacts,
                e.other_guard_patient_contacts
            ),
            (2, 1, 0)
        );
        assert_eq!(at("all", Perception).episodes, 3);
        assert_eq!(at("elbow", Perception).episodes, 0);
    }

    /// Per body kind and per cameras facing the leading surface: each group's rows count
    /// its own episodes only, and the groups' counts add up to the all-kinds row.
    #[test]
    fn the_summaries_by_kind_and_by_view_split_the_episodes() {
        use SurfaceSource::{DelayedOracle, Exact, Perception};
        let with_kind = |kind, r: RunRow| RunRow {
            kind,
            leading_face_cameras: 0,
            ..r
        };
        let rows = [
            row(0, Exact, true, 0.05),
            row(0, DelayedOracle, true, 0.04),
            row(0, Perception, true, 0.03),
            with_kind(BodyKind::Torso, row(1, Exact, true, 0.05)),
            with_kind(BodyKind::Torso, row(1, DelayedOracle, true, 0.04)),
            with_kind(BodyKind::Torso, row(1, Perception, false, -0.08)),
            with_kind(BodyKind::Torso, row(2, Exact, true, 0.05)),
            with_kind(BodyKind::Torso, row(2, DelayedOracle, true, 0.03)),
            with_kind(BodyKind::Torso, row(2, Perception, true, 0.01)),
        ];
        let kinds = summarize_by_kind(&rows, &[1.0]);
        assert_eq!(kinds.len(), BodyKind::ALL.len() * SurfaceSource::ALL.len());
        let perception = |kind| {
            kinds
                .iter()
                .find(|r| r.source == Perception && r.kind == Some(kind))
                .unwrap()
        };
        let torso = perception(BodyKind::Torso);
        assert_eq!((torso.episodes, torso.safe_of_oracle_survived), (2, 1));
        assert_eq!(torso.worst_margin_m, -0.08);
        let plate = perception(BodyKind::Plate);
        assert_eq!((plate.episodes, plate.safe), (1, 1));
        assert_eq!(perception(BodyKind::Head).episodes, 0);
        let all = summarize(&rows, &[1.0]);
        let all = all
            .iter()
            .find(|r| r.source == Perception && r.camera_rate_hz == 0.0)
            .unwrap();
        assert_eq!((all.kind, all.leading_face_cameras), (None, None));
        let views = summarize_by_view(&rows, &[1.0]);
        assert_eq!(views.len(), 2 * SurfaceSource::ALL.len());
        let unseen = (views.iter())
            .find(|r| r.source == Perception && r.leading_face_cameras == Some(0))
            .unwrap();
        assert_eq!((unseen.episodes, unseen.safe_of_oracle_survived), (2, 1));
        for groups in [&kinds, &views] {
            let sum = |f: fn(&SummaryRow) -> usize| {
                (groups.iter())
                    .filter(|r| r.source == Perception)
                    .map(f)
                    .sum::<usize>()
            };
            assert_eq!(sum(|r| r.episodes), all.episodes);
            assert_eq!(
                sum(|r| r.safe_of_oracle_survived),
                all.safe_of_oracle_survived
            );
        }
    }
}
