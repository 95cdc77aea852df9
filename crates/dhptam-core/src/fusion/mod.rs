//! Spatial hybridisation and fusion of events and frames (DH-PTAM eqs. 5–6, SPEC-NOTES §4).
//!
//! - [`rectify`]: raw event pixels → pixels of the rectified event camera, through a lookup
//!   table built once from the calibration.
//! - [`warp`]: the rectified E3CT → the rectified frame camera, with a real perspective divide
//!   (a fronto-parallel plane at a given depth, or infinity) plus the constant δP_align.
//! - [`event_stereo`]: stereo matches of the warped event images read back as the frame
//!   cameras would have measured them (the event cameras' centres are elsewhere).
//! - [`exposure`]: failed (under/over-exposed) frames stretched to full contrast when their
//!   signal allows, before β is chosen.
//! - [`blend`]: the online β (APS- or DVS-biased) and `f(C, D) = (1 − β) C + β D`.

pub mod blend;
pub mod event_stereo;
pub mod exposure;
pub mod rectify;
pub mod warp;

pub use blend::{
    choose_beta, fuse, fuse_e3ct, intensity_from_e3ct, BetaDecision, Bias, FusionMode,
};
pub use event_stereo::EventStereo;
pub use exposure::{check_exposure, recover_exposure, stretch_levels, ExposureCheck};
pub use rectify::{EventRectifier, RectifiedEvents};
pub use warp::{Depth, EventFrameWarp, WarpMap};
