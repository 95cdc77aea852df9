//! `System::tracked_depth`: the median depth of the map points a frame was tracked with (the
//! front-end's event→frame warp depth, `[fusion] warp_depth = "tracked"`).

use dhptam_core::config::Config;
use dhptam_core::slam::synthetic::{generate, SyntheticOptions};
use dhptam_core::slam::{System, TrackState};

mod common;
use common::track;

/// Tracks a short synthetic sequence whose landmarks lie `wall_m` from the circle's axis
/// (the camera on a 1 m circle looking outwards, so the scene is `wall_m − 1` m away) and
/// returns the tracked depth after every frame.
fn depths(wall_m: (f64, f64)) -> Vec<Option<f64>> {
    let o = SyntheticOptions {
        landmarks: 800,
        frames: 12,
        turns: 0.03,
        wall_m,
        ..Default::default()
    };
    let mut system = System::new(o.calib, Config::default(), false).unwrap();
    assert_eq!(system.tracked_depth(), None, "no frame tracked yet");
    generate(&o)
        .iter()
        .map(|f| {
            let r = track(&mut system, f);
            assert!(matches!(r.state, TrackState::Ok | TrackState::Initialised));
            system.tracked_depth()
        })
        .collect()
}

#[test]
fn tracked_depth_is_the_median_depth_of_the_scene_the_frame_was_tracked_in() {
    for (wall, lo, hi) in [((2.0, 3.0), 1.0, 2.0), ((6.0, 8.0), 5.0, 7.0)] {
        let d = depths(wall);
        for (k, z) in d.iter().enumerate() {
            // Points straight ahead are wall − 1 m away, those at the image border a little
            // further (the wall curves away); the median sits inside the band.
            let z = z.unwrap_or_else(|| panic!("frame {k}: no tracked depth"));
            assert!(z > lo && z < hi + 0.5, "wall {wall:?}, frame {k}: {z} m");
        }
    }
}
