//! Nonlinear least squares: a Levenberg–Marquardt loop, robust losses, bundle adjustment with
//! the Schur complement and pose-graph optimisation, on faer's dense and sparse Cholesky.

pub mod ba;
pub mod linear;
pub mod lm;
pub mod pnp;
pub mod pose;
pub mod pose_graph;
pub mod robust;
mod schur;
pub mod stereo_ba;

pub use ba::{solve_bal, BundleAdjustment, BundleOptions};
pub use linear::LinearSolver;
pub use lm::{solve, LeastSquares, LmOptions, LmReport, Termination};
pub use pnp::{solve_pnp_ransac, PnpRansacOptions, PnpResult};
pub use pose::{
    refine_pose, refine_pose_seen_from, refine_pose_weighted, PoseObservation, PoseOptions,
    PoseResult, StereoIntrinsics,
};
pub use pose_graph::{
    solve_pose_graph2, solve_pose_graph3, GraphPose, PoseGraphOptions, PoseGraphSe2, PoseGraphSe3,
    PoseGraphSolver,
};
pub use robust::{Corrector, Loss};
pub use stereo_ba::{
    solve_stereo_ba, BaKeyframe, BaObservation, CentrePrior, StereoBaOptions, StereoBaResult,
};
