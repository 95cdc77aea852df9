//! Stereo matches of event images warped into the rectified frame cameras, read through the
//! event cameras' geometry (issue 8).
//!
//! A DVS-biased fused pair shows what the event cameras saw, resampled into the frame cameras
//! through a plane ([`super::warp`]). A point off that plane lands where the event camera
//! sees it, not where the frame camera would: with the simulator's event cameras 3 cm below
//! the frame cameras and a 200 px focal length, 6 px away at 1 m through the plane at infinity,
//! mostly in v, which no disparity correction reaches. Tracked as if the
//! frame cameras had measured them, such keypoints pull the pose and the map points they
//! create off.
//!
//! A stereo match `(u_l, v)`, `u_r` of such a pair is read back exactly: both pixels go back
//! through the inverse warps into the rectified event cameras (the inverse of the resampling
//! is exact whatever the point's depth), the match is triangulated with the event pair's
//! baseline, and the point is projected into the rectified frame cameras. The result is the
//! `(u_l, v)`, `u_r` the frame cameras would have measured, so the tracker and the map need
//! no notion of a second pair of cameras. It subsumes the disparity-only correction
//! (`slam::DisparityCorrection`), which is its first-order part along the rows.

use nalgebra::{Vector2, Vector3};

use super::warp::{Depth, EventFrameWarp};
use crate::error::{ensure_finite, Error, Result};
use crate::geometry::{Pinhole, Se3};

/// Reads stereo matches of a warped event pair as rectified frame-camera measurements.
#[derive(Clone, Debug)]
pub struct EventStereo {
    left: EventFrameWarp,
    right: EventFrameWarp,
    k_event: Pinhole,
    event_baseline_m: f64,
    frame_from_event_left: Se3,
    k_frame: Pinhole,
    frame_baseline_m: f64,
}

impl EventStereo {
    /// The reading for event images warped through `depth` with δP_align `align_px`.
    ///
    /// `k_event` and `event_baseline_m` are the rectified event pair's intrinsics and
    /// baseline (right camera at +baseline along x), `k_frame` and `frame_baseline_m` the
    /// rectified frame pair's; `frame_from_event` maps, per side (left, right), points of the
    /// rectified event camera into the rectified frame camera of that side, as the warps do.
    pub fn new(
        k_event: Pinhole,
        event_baseline_m: f64,
        k_frame: Pinhole,
        frame_baseline_m: f64,
        frame_from_event: [Se3; 2],
        depth: Depth,
        align_px: Vector2<f64>,
    ) -> Result<Self> {
        for (what, b) in [
            ("event_baseline_m", event_baseline_m),
            ("frame_baseline_m", frame_baseline_m),
        ] {
            if !(b.is_finite() && b > 0.0) {
                return Err(Error::invalid(what, "a positive baseline in metres", b));
            }
        }
        for (what, k) in [("k_event", &k_event), ("k_frame", &k_frame)] {
            ensure_finite(what, &[k.fx, k.fy, k.cx, k.cy])?;
            if !(k.fx > 0.0 && k.fy > 0.0) {
                return Err(Error::invalid(
                    format!("{what} fx, fy"),
                    "positive focal lengths",
                    format!("{}, {}", k.fx, k.fy),
                ));
            }
        }
        let [left, right] = frame_from_event;
        Ok(Self {
            left: EventFrameWarp::new(k_event, k_frame, left, depth, align_px)?,
            right: EventFrameWarp::new(k_event, k_frame, right, depth, align_px)?,
            k_event,
            event_baseline_m,
            frame_from_event_left: left,
            k_frame,
            frame_baseline_m,
        })
    }

    /// The rectified frame cameras' `(u_l, v)` and `u_r` of the point a match at left pixel
    /// `left` and right column `u_right` (same row) of the warped pair shows; `None` when the
    /// pixels unwarp behind the event cameras, the event disparity is not positive, or the
    /// point lies behind the frame camera.
    pub fn frame_reading(&self, left: [f32; 2], u_right: f32) -> Option<([f32; 2], f32)> {
        let v = f64::from(left[1]);
        let pl = self
            .left
            .unwarp_pixel(&Vector2::new(f64::from(left[0]), v))?;
        let pr = self
            .right
            .unwarp_pixel(&Vector2::new(f64::from(u_right), v))?;
        let disparity = pl.x - pr.x;
        // NaN disparities fail this test too.
        if disparity.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let k = &self.k_event;
        let z = k.fx * self.event_baseline_m / disparity;
        let x_event = Vector3::new((pl.x - k.cx) / k.fx * z, (pl.y - k.cy) / k.fy * z, z);
        let x = self.frame_from_event_left * x_event;
        if x.z.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let k = &self.k_frame;
        let iz = 1.0 / x.z;
        let u = k.fx * x.x * iz + k.cx;
        let v = k.fy * x.y * iz + k.cy;
        let ur = (k.fx * (x.x - self.frame_baseline_m) * iz + k.cx) as f32;
        let out = [u as f32, v as f32];
        (out.iter().all(|c| c.is_finite()) && ur.is_finite()).then_some((out, ur))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::so3::So3;

    fn rig(depth: Depth) -> (EventStereo, Pinhole, Pinhole, [Se3; 2]) {
        let k_event = Pinhole {
            fx: 180.0,
            fy: 181.0,
            cx: 161.0,
            cy: 92.0,
        };
        let k_frame = Pinhole {
            fx: 200.6,
            fy: 200.6,
            cx: 158.0,
            cy: 161.0,
        };
        // A rectified event pair 3 cm below the frame cameras (y down), slightly turned,
        // baseline 11 cm against the frames' 10 cm: the right event camera sits at +11 cm
        // along the left event camera's x axis, the right frame camera at +10 cm along x.
        let rot = So3::exp(&Vector3::new(0.004, -0.003, 0.002));
        let t_left = Vector3::new(-0.005, 0.03, 0.002);
        let left = Se3::new(rot, t_left);
        let right = Se3::new(
            rot,
            t_left + rot * Vector3::new(0.11, 0.0, 0.0) - Vector3::new(0.10, 0.0, 0.0),
        );
        let reading = EventStereo::new(
            k_event,
            0.11,
            k_frame,
            0.10,
            [left, right],
            depth,
            Vector2::new(0.3, -0.2),
        )
        .unwrap();
        (reading, k_event, k_frame, [left, right])
    }

    /// A world point in the left frame camera, seen by the event cameras and warped.
    fn warped_match(
        reading: &EventStereo,
        k_event: &Pinhole,
        frame_from_event: &[Se3; 2],
        x: Vector3<f64>,
    ) -> ([f32; 2], f32) {
        // Right rectified frame camera ← left one: −baseline along x.
        let right_from_left = Se3::new(So3::identity(), Vector3::new(-0.10, 0.0, 0.0));
        let project = |k: &Pinhole, p: Vector3<f64>| {
            Vector2::new(k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy)
        };
        let pl = project(k_event, frame_from_event[0].inverse() * x);
        let pr = project(
            k_event,
            frame_from_event[1].inverse() * (right_from_left * x),
        );
        let wl = reading.left.warp_pixel(&pl).unwrap();
        let wr = reading.right.warp_pixel(&pr).unwrap();
        ([wl.x as f32, wl.y as f32], wr.x as f32)
    }

    #[test]
    fn reads_warped_matches_as_the_frame_cameras_see_them() {
        for depth in [Depth::Infinity, Depth::Plane { depth_m: 1.5 }] {
            let (reading, k_event, k_frame, fe) = rig(depth);
            for x in [
                Vector3::new(0.1, -0.2, 0.6),
                Vector3::new(-0.3, 0.25, 1.4),
                Vector3::new(0.5, 0.1, 4.0),
            ] {
                let (left, u_right) = warped_match(&reading, &k_event, &fe, x);
                let want = [
                    k_frame.fx * x.x / x.z + k_frame.cx,
                    k_frame.fy * x.y / x.z + k_frame.cy,
                    k_frame.fx * (x.x - 0.10) / x.z + k_frame.cx,
                ];
                // The warped rows of the two sides differ by a fraction of a pixel (the event
                // cameras are not exactly row-aligned with the frames); the reading takes the
                // left row for both.
                let (got, ur) = reading.frame_reading(left, u_right).unwrap();
                let err = [
                    f64::from(got[0]) - want[0],
                    f64::from(got[1]) - want[1],
                    f64::from(ur) - want[2],
                ];
                assert!(
                    err.iter().all(|e| e.abs() < 0.02),
                    "{depth:?} {x:?}: errors {err:?} px"
                );
                // Read as frame pixels, the warped match is off by pixels at 0.6 m.
                let raw = (f64::from(left[1]) - want[1]).abs();
                if x.z < 1.0 {
                    assert!(raw > 3.0, "{depth:?}: the warp alone is {raw} px off");
                }
            }
        }
    }

    #[test]
    fn refuses_matches_without_positive_event_disparity() {
        let (reading, ..) = rig(Depth::Infinity);
        assert!(reading.frame_reading([100.0, 120.0], 140.0).is_none());
    }

    #[test]
    fn rejects_bad_baselines() {
        let k = Pinhole {
            fx: 100.0,
            fy: 100.0,
            cx: 50.0,
            cy: 50.0,
        };
        let id = Se3::identity();
        for (be, bf) in [(0.0, 0.1), (0.1, f64::NAN), (-0.1, 0.1)] {
            let e = EventStereo::new(k, be, k, bf, [id, id], Depth::Infinity, Vector2::zeros());
            assert!(e.is_err(), "baselines {be}, {bf}");
        }
    }
}
