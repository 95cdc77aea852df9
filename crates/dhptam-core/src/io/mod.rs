//! Readers and writers of solver problem files (BAL bundle-adjustment problems, g2o pose
//! graphs) and of MCAP logs ([`mcap`]). Malformed text files give [`crate::Error::Parse`]
//! naming the line, malformed logs [`crate::Error::Format`] naming the channel; never a panic.

pub mod bal;
pub mod g2o;
pub mod mcap;
mod text;

pub use bal::{BalObservation, BalProblem};
pub use g2o::{EdgeSe2, EdgeSe3, Pose2, PoseGraph, PoseGraph2, PoseGraph3};
