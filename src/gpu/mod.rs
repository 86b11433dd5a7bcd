//! The GPU context (adapter choice, error capture) and the one place that loads WGSL shaders.
