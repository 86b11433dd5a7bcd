//! Per-camera perception stages (paper section IV-A to IV-E), each with a GPU and a CPU
//! reference implementation.

pub mod closure;
pub mod cluster;
pub mod crop;
pub mod fit;
pub mod flying;
pub mod frontend;
pub mod lookahead;
pub mod memory;
pub mod outliers;
pub mod pipeline;
pub mod shells;
pub mod voxel;

#[cfg(test)]
pub(crate) mod test_data;
