//! hapcloud: a perception and haptic-rendering node for rehabilitation exoskeletons.
//!
//! It implements Sommerhalder et al., "Physical Human-Robot Interaction with Real Active
//! Surfaces using Haptic Rendering on Point Clouds" (ETH, ANYexo). Data flows one way:
//!
//! ```text
//! source (scene | recording | files | stream) -> camera::Frame
//!   -> perception (GPU: crop -> voxel -> cluster; memory/ICP; shell moments; CPU fits)
//!   -> surface::SurfaceEstimate per camera
//!   -> fusion (800 Hz regression + PID) -> haptics (eq. 7-14) -> control (hierarchical QP)
//!   -> CAN frames, recording, overlay
//! ```
//!
//! Shared value types live at the top: [`cloud`], [`geometry`], [`camera`], [`surface`].

pub mod camera;
pub mod cloud;
pub mod control;
pub mod fusion;
pub mod geometry;
pub mod surface;

pub mod gpu;
pub mod haptics;
pub mod io;
#[cfg(feature = "lab")]
pub mod lab;
pub mod node;
pub mod perception;
pub mod robot;
pub mod scene;
pub mod timing;
#[cfg(feature = "viewer")]
pub mod viewer;
