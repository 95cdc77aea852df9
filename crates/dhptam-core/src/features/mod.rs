//! CPU kernels for the learned feature extractors, which otherwise run in torch.
//!
//! The networks' convolutions stay in torch; what moves here are the memory-bound steps
//! after them that torch can only express as several passes over full-resolution
//! 128-channel maps.

mod heads;

pub use heads::{r2d2_heads, FeatureMap, HeadMaps, HeadWeights};
