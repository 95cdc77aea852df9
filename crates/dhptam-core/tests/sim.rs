//! Simulator tests: rendered texture lands at the projected pixel in every camera model,
//! the event generator is exact on log-brightness ramps, and whole simulations are
//! deterministic for a seed.

use dhptam_core::config::Config;
use dhptam_core::geometry::{Camera, Projective, Se3, So3};
use dhptam_core::sim::scene::{Face, SceneBox, Surface};
use dhptam_core::sim::{
    look_at, render_image, BuiltinMotion, Event, EventGenerator, EventParams, Profile, RayTable,
    RigCamera, Scene, Simulator, Texture, Wrap,
};
use nalgebra::{Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A room and one box, textured with noise whose features span ~10 pixels at the test
/// distances, so that a bilinear read of the image is close to the texture at a point and a
/// misplaced pixel is not. Texels (3 cm) are larger than the pixels' footprints, so the
/// renders read the full-resolution level like the reference lookups do.
fn smooth_scene() -> Scene {
    let noise = Texture::value_noise(128, 8, 2, 0.5, (0.1, 0.9), 5);
    let surface = Surface {
        texture: 0,
        tile_m: [4.0, 4.0],
        wrap: Wrap::Repeat,
        gain: 1.0,
    };
    let faces = || {
        std::array::from_fn(|i| Face {
            surface: Surface {
                gain: 1.0 - 0.05 * i as f32,
                ..surface
            },
            decals: Vec::new(),
        })
    };
    let room = SceneBox {
        min: [-2.5, -2.0, 0.0],
        max: [2.5, 2.5, 2.6],
        faces: faces(),
    };
    let block = |min: [f32; 3], max: [f32; 3]| SceneBox {
        min,
        max,
        faces: faces(),
    };
    // A box with a smaller one on top (one group) and a separate one.
    let boxes = vec![
        block([-0.4, 1.0, 0.7], [0.3, 1.5, 1.2]),
        block([-0.2, 1.1, 1.2], [0.0, 1.3, 1.4]),
        block([0.8, 1.2, 0.0], [1.2, 1.6, 0.8]),
    ];
    Scene::new(vec![noise], room, boxes).unwrap()
}

/// A TUM-VIE-like rig at low resolution: kb4 frame cameras 10 cm apart, kb4 event cameras
/// beside them, small rotations; plus a pinhole and a radtan camera.
fn cameras() -> Vec<RigCamera> {
    let kb4 = [0.004, 0.014, -0.028, 0.014];
    let frame =
        |cx: f64| Camera::new("kb4", &[[75.0, 75.2, cx, 79.1], kb4].concat(), 160, 160).unwrap();
    let event = Camera::new("kb4", &[[105.0, 105.0, 80.3, 44.8], kb4].concat(), 160, 90).unwrap();
    let tilt = |x: f64, y: f64, rx: f64| {
        Se3::new(
            So3::exp(&Vector3::new(rx, 0.01, -0.005)),
            Vector3::new(x, y, 0.0),
        )
    };
    vec![
        RigCamera {
            camera: frame(79.6),
            imu_from_cam: tilt(-0.05, 0.0, 0.01),
        },
        RigCamera {
            camera: frame(80.4),
            imu_from_cam: tilt(0.05, 0.0, -0.01),
        },
        RigCamera {
            camera: event,
            imu_from_cam: tilt(-0.055, 0.03, 0.005),
        },
        RigCamera {
            camera: event,
            imu_from_cam: tilt(0.055, 0.03, -0.005),
        },
        RigCamera {
            camera: Camera::new("pinhole", &[120.0, 121.0, 79.5, 59.5], 160, 120).unwrap(),
            imu_from_cam: tilt(0.0, -0.03, 0.0),
        },
        RigCamera {
            camera: Camera::new(
                "radtan",
                &[130.0, 129.0, 81.0, 61.0, -0.25, 0.07, 1e-3, -5e-4, 0.0],
                160,
                120,
            )
            .unwrap(),
            imu_from_cam: tilt(0.02, 0.0, 0.02),
        },
    ]
}

fn bilinear(image: &[f32], width: usize, uv: &Vector2<f64>) -> f32 {
    let (x0, y0) = (uv.x.floor() as usize, uv.y.floor() as usize);
    let (fx, fy) = ((uv.x - uv.x.floor()) as f32, (uv.y - uv.y.floor()) as f32);
    let at = |x: usize, y: usize| image[y * width + x];
    let top = at(x0, y0) * (1.0 - fx) + at(x0 + 1, y0) * fx;
    let bottom = at(x0, y0 + 1) * (1.0 - fx) + at(x0 + 1, y0 + 1) * fx;
    top * (1.0 - fy) + bottom * fy
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

#[test]
fn rendered_texture_appears_at_the_projected_pixel_in_every_camera() {
    let scene = smooth_scene();
    let world_from_imu = look_at(&Vector3::new(0.2, -0.3, 1.3), &Vector3::new(-0.1, 1.5, 0.9));
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for (index, rig_camera) in cameras().iter().enumerate() {
        let camera = rig_camera.camera;
        let world_from_cam = world_from_imu * rig_camera.imu_from_cam;
        let cam_from_world = world_from_cam.inverse();
        let image = render_image(&scene, &RayTable::new(&camera), &world_from_cam);
        let (mut errors, mut shifted_errors, mut checked) = (Vec::new(), Vec::new(), 0);
        while checked < 200 {
            // A random point on a random face of the box or of the room.
            let b = &scene.boxes[rng.random_range(0..scene.boxes.len())];
            let (lo, hi) = if rng.random::<bool>() {
                (b.min, b.max)
            } else {
                (scene.room.min, scene.room.max)
            };
            let mut p = Vector3::from_fn(|a, _| f64::from(rng.random_range(lo[a]..hi[a])));
            let axis = rng.random_range(0..3);
            p[axis] = f64::from(if rng.random::<bool>() {
                lo[axis]
            } else {
                hi[axis]
            });
            let Some(uv) = camera.project(&(cam_from_world * p)) else {
                continue;
            };
            let margin = 2.0;
            if uv.x < margin
                || uv.y < margin
                || uv.x > f64::from(camera.width) - 1.0 - margin
                || uv.y > f64::from(camera.height) - 1.0 - margin
            {
                continue;
            }
            // The texture at p, seen straight from the camera centre (no camera model);
            // skip points hidden behind something else.
            let origin = world_from_cam.translation;
            let ray = p - origin;
            let distance = ray.norm();
            let dir = ray / distance;
            let o = [origin.x as f32, origin.y as f32, origin.z as f32];
            let hit = scene
                .trace(o, [dir.x as f32, dir.y as f32, dir.z as f32], 1e-4)
                .unwrap();
            if (f64::from(hit.distance) - distance).abs() > 1e-3 {
                continue;
            }
            let width = camera.width as usize;
            errors.push(f64::from(
                (bilinear(&image, width, &uv) - hit.radiance).abs(),
            ));
            let off = uv + Vector2::new(1.5, -1.5);
            shifted_errors.push(f64::from(
                (bilinear(&image, width, &off) - hit.radiance).abs(),
            ));
            checked += 1;
        }
        // Medians: a few points sit next to an occlusion or face edge, where the bilinear
        // read mixes in the neighbouring surface.
        let (median, shifted) = (median(errors), median(shifted_errors));
        println!("camera {index}: median error {median:.4}, 2 px off {shifted:.4}");
        assert!(
            median < 0.008,
            "camera {index}: median |rendered − texture| = {median}"
        );
        // The same comparison 2 px away is several times worse: the test resolves pixels.
        assert!(
            shifted > 4.0 * median,
            "camera {index}: {median} vs shifted {shifted}"
        );
    }
}

fn ramp_params() -> EventParams {
    EventParams {
        contrast_on: 0.2,
        contrast_off: 0.25,
        contrast_sigma: 0.0,
        refractory_ns: 0,
        noise_rate_hz: 0.0,
        noise_reference_intensity: 0.5,
    }
}

#[test]
fn log_ramp_gives_exact_count_polarity_and_interpolated_timestamps() {
    // Four pixels with log intensity L_p(t) = L_p(0) + k_p·t (t in seconds), rendered at
    // uneven times: each threshold crossing must be found once, in order, at its exact time.
    let start = [0.0, -1.0, 0.3, 2.0];
    let slope = [3.1, -2.3, 0.0, 0.45]; // per second
    let times_ns = [0i64, 130_000_000, 400_000_000, 410_000_000, 1_000_000_000];
    let log_at = |t_ns: i64| -> Vec<f64> {
        (0..4)
            .map(|p| start[p] + slope[p] * t_ns as f64 * 1e-9)
            .collect()
    };
    let params = ramp_params();
    let mut generator = EventGenerator::new(4, params, 0, 0, &log_at(0)).unwrap();
    let mut events: Vec<Event> = Vec::new();
    for &t in &times_ns[1..] {
        generator.advance(t, &log_at(t), 1.0, &mut events).unwrap();
    }
    for (p, &k) in slope.iter().enumerate() {
        let mine: Vec<&Event> = events.iter().filter(|e| e.x as usize == p).collect();
        let c = if k > 0.0 {
            params.contrast_on
        } else {
            params.contrast_off
        };
        let total_change = k.abs() * 1.0;
        let expected = (total_change / c + 1e-9).floor() as usize;
        assert_eq!(mine.len(), expected, "pixel {p}: {mine:?}");
        for (n, e) in mine.iter().enumerate() {
            assert_eq!(e.on, k > 0.0, "pixel {p} polarity");
            // Level n+1 is crossed at t = (n + 1)·C / |k|.
            let t_exact = (n + 1) as f64 * c / k.abs() * 1e9;
            assert!(
                (e.t_ns as f64 - t_exact).abs() <= 1.0,
                "pixel {p} event {n}: {} ns, expected {t_exact}",
                e.t_ns
            );
        }
    }
    // 3.1/0.2 → 15 ON; 2.3/0.25 → 9 OFF; flat → 0; 0.45/0.2 → 2 ON.
    assert_eq!(events.len(), 15 + 9 + 2);
    assert!(events.windows(2).all(|w| w[0].t_ns <= w[1].t_ns));
}

#[test]
fn refractory_period_blanks_events_but_the_reference_still_moves() {
    let params = EventParams {
        refractory_ns: 100_000_000,
        ..ramp_params()
    };
    // 2.0 of log change per second with C⁺ = 0.2: a crossing every 100 ms.
    let mut generator = EventGenerator::new(1, params, 0, 0, &[0.0]).unwrap();
    let mut events = Vec::new();
    generator
        .advance(1_000_000_000, &[2.0], 1.0, &mut events)
        .unwrap();
    // Refractory 100 ms: none are blanked (t − last ≥ refractory).
    assert_eq!(events.len(), 10);
    let params = EventParams {
        refractory_ns: 150_000_000,
        ..ramp_params()
    };
    // Refractory 150 ms: every second crossing is blanked.
    let mut generator = EventGenerator::new(1, params, 0, 0, &[0.0]).unwrap();
    let mut events = Vec::new();
    generator
        .advance(1_000_000_000, &[2.0], 1.0, &mut events)
        .unwrap();
    let times: Vec<i64> = events.iter().map(|e| e.t_ns).collect();
    assert_eq!(
        times,
        vec![
            100_000_000,
            300_000_000,
            500_000_000,
            700_000_000,
            900_000_000
        ]
    );
    // The reference moved with every crossing: a further +0.2 fires exactly one more event.
    let mut more = Vec::new();
    generator
        .advance(1_200_000_000, &[2.2], 1.0, &mut more)
        .unwrap();
    assert_eq!(more.len(), 1);
    assert_eq!(more[0].t_ns, 1_200_000_000);
}

#[test]
fn threshold_mismatch_and_noise_follow_their_parameters() {
    let params = EventParams {
        contrast_sigma: 0.05,
        noise_rate_hz: 50.0,
        ..ramp_params()
    };
    let n = 4000;
    // Flat, mid-grey image: every event is background activity at ~50 Hz per pixel.
    let flat = vec![(0.5f64).ln(); n];
    let mut generator = EventGenerator::new(100, params, 3, 0, &flat).unwrap();
    let mut events = Vec::new();
    generator
        .advance(100_000_000, &flat, 1.0, &mut events)
        .unwrap();
    let expected = 50.0 * 0.1 * n as f64; // 20,000
    let count = events.len() as f64;
    assert!((count - expected).abs() < 5.0 * expected.sqrt(), "{count}");
    // Darker pixels are noisier: 1/100 of the intensity → 10× the rate.
    let dark = vec![(0.005f64).ln(); n];
    let mut generator = EventGenerator::new(100, params, 3, 0, &dark).unwrap();
    let mut dark_events = Vec::new();
    generator
        .advance(100_000_000, &dark, 1.0, &mut dark_events)
        .unwrap();
    let ratio = dark_events.len() as f64 / count;
    assert!((ratio - 10.0).abs() < 0.5, "{ratio}");
    // Mismatch: a uniform step of 0.6 fires exactly 3 events where the pixel's threshold c
    // lies in (0.15, 0.2], i.e. z ∈ (−1, 0] for c = 0.2 + 0.05 z: probability 0.3413.
    let quiet = EventParams {
        noise_rate_hz: 0.0,
        ..params
    };
    let mut generator = EventGenerator::new(100, quiet, 3, 0, &flat).unwrap();
    let up: Vec<f64> = flat.iter().map(|l| l + 0.6).collect();
    let mut ramp = Vec::new();
    generator.advance(1_000_000, &up, 1.0, &mut ramp).unwrap();
    let mut per_pixel = vec![0usize; n];
    for e in &ramp {
        per_pixel[usize::from(e.y) * 100 + usize::from(e.x)] += 1;
    }
    let three = per_pixel.iter().filter(|&&c| c == 3).count() as f64 / n as f64;
    assert!((three - 0.3413).abs() < 0.03, "{three}");
}

/// The rig of [`cameras`] at a quarter of the resolution (kept small: `cargo test` runs
/// unoptimised).
fn small_simulator(seed: u64, profile: Profile) -> Simulator {
    let rig: [RigCamera; 4] = std::array::from_fn(|i| {
        let c = cameras()[i];
        let p = c.camera.model.params();
        let scaled: Vec<f64> = p
            .iter()
            .enumerate()
            .map(|(k, v)| match k {
                0 | 1 => v / 4.0,
                2 | 3 => (v + 0.5) / 4.0 - 0.5,
                _ => *v,
            })
            .collect();
        let camera = Camera::new("kb4", &scaled, c.camera.width / 4, c.camera.height / 4).unwrap();
        RigCamera { camera, ..c }
    });
    let region = Scene::desk_room_region();
    let duration_ns = 200_000_000;
    let trajectory = BuiltinMotion::Shake6dof
        .trajectory(duration_ns, &region)
        .unwrap();
    Simulator::new(
        Scene::desk_room(Vec::new(), seed),
        rig,
        trajectory,
        profile,
        duration_ns,
        Config::default().sim.params(),
        seed,
    )
    .unwrap()
}

#[test]
fn simulation_is_deterministic_for_a_seed() {
    let run = |seed: u64| {
        let mut sim = small_simulator(seed, Profile::Hdr);
        let mut frames = Vec::new();
        let mut events = Vec::new();
        for k in 0..2 {
            let t = k * 50_000_000;
            frames.push(sim.frame_pair(t));
            events.push(sim.events_until(t + 50_000_000).unwrap());
        }
        (frames, events)
    };
    let (frames_a, events_a) = run(7);
    let (frames_b, events_b) = run(7);
    assert_eq!(frames_a, frames_b);
    assert_eq!(events_a, events_b);
    let total: usize = events_a.iter().map(|e| e[0].len() + e[1].len()).sum();
    assert!(total > 200, "a shaking camera must see events: {total}");
    for pair in &events_a {
        for side in pair {
            assert!(side.windows(2).all(|w| w[0].t_ns <= w[1].t_ns));
        }
    }
    let (frames_c, _) = run(8);
    assert_ne!(frames_a, frames_c);
}
