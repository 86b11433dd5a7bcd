//! File formats: PCD, PLY and 16-bit depth images.
