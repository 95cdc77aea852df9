//! Readers and writers of solver problem files: BAL bundle-adjustment problems and g2o pose
//! graphs. Malformed files give [`crate::Error::Parse`] naming the line, never a panic.

pub mod bal;
pub mod g2o;
mod text;

pub use bal::{BalObservation, BalProblem};
pub use g2o::{EdgeSe2, EdgeSe3, Pose2, PoseGraph, PoseGraph2, PoseGraph3};
