//! Per-camera perception stages (paper section IV-A to IV-E), each with a GPU and a CPU
//! reference implementation.

pub mod fit;
pub mod memory;
pub mod pipeline;
pub mod shells;
