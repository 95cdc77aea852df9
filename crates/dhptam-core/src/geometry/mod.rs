//! Geometry: Lie groups, camera models, stereo rectification and triangulation.

pub mod camera;
pub mod rectify;
pub mod se3;
pub mod so3;
pub mod triangulate;

pub use camera::{Camera, CameraModel, Kb4, Pinhole, Projective, RadTan};
pub use rectify::{remap_bilinear_f32, remap_bilinear_u8, RectifiedStereo, Side, StereoRig};
pub use se3::Se3;
pub use so3::So3;
pub use triangulate::{
    triangulate, triangulate_linear, triangulate_rectified, Rejected, Triangulated,
};
