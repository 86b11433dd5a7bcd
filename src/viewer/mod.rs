//! The shell overlay: an egui viewer of clouds, shells, fits and constraints (feature
//! "viewer"; the only module that imports egui).
//!
//! It shows in 3D what paper section IV does to each camera's cloud (Fig. 4: kept, cropped,
//! clustered-out and memorised points), the concentric shells around the HIP with each
//! shell's plane or circle fit and normal (Alg. 2, Fig. 7; rejected estimates marked), the
//! per-camera and fused surface estimates, the ground truth of simulated sources, and a
//! spade-triangulated patch of the reconstructed surface. Side panels plot d_proj (eq. 7),
//! its rate, constraint activity, errors against ground truth and per-stage latency over a
//! timeline that can be scrubbed and played.
//!
//! Input is plain data: a [`ViewFrame`] per instant, from a [`ViewerSource`] (a finished
//! timeline, or a channel fed live by the node). [`ViewerApp::ui`] draws into any `egui::Ui`
//! (the eframe window of [`run_window`] or a test harness).

mod app;
pub mod config;
pub mod constraints;
pub mod draw;
pub mod frame;
pub mod orbit;
pub mod overlay;
pub mod patch;
pub mod plots;
pub mod records;
pub mod simulated;
pub mod source;
mod window;

pub use app::ViewerApp;
pub use config::{ViewerConfig, ViewerConfigError};
pub use frame::{
    CameraView, ConstraintSample, EstimateError, FrameSamples, PointLayer, PointRole, StageLatency,
    ViewFrame, ViewerSource,
};
pub use window::{ScreenshotRequest, WindowError, run_window};
