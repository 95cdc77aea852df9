//! Event representations: the E3CT of DH-PTAM and the baselines used in ablations.
//!
//! - [`window`]: a borrowed window of events ([`EventSlice`]) and the checks every
//!   representation applies to it before touching its output.
//! - [`e3ct`]: the Event 3-Channel Tensor (decay kernel, trilinear temporal voting,
//!   per-channel normalisation shared by the left and right cameras); `docs/E3CT.md` states
//!   the formula and the decisions behind it.
//! - [`representations`]: event count image, time surface and voxel grid.
//! - [`activity`]: how much of a window is scene structure rather than sensor noise (active
//!   pixels with active neighbours beyond chance).
//! - [`hot`]: the running detector of hot pixels (pixels firing on their own), whose events
//!   the front-end drops before any representation.
//!
//! Images are row-major `height × width × channels` `f32` buffers (channel fastest), the
//! layout numpy sees as an `(H, W, C)` array.

pub mod activity;
pub mod e3ct;
pub mod hot;
pub mod representations;
pub mod window;

pub use activity::{activity, Activity};
pub use e3ct::{
    apply_scales, channel_scales, e3ct, e3ct_into, scaled, E3ctParams, E3ctWorkspace, PolarityMode,
};
pub use hot::{HotPixelParams, HotPixels};
pub use representations::{count_image, time_surface, voxel_grid};
pub use window::EventSlice;
