//! Event rectification, the event→frame warp on a TUM-VIE-like synthetic rig with known
//! depth, and the online β / fusion.

use dhptam_core::config::{FusionConfig, RectificationConfig};
use dhptam_core::events::{channel_scales, e3ct, scaled, E3ctParams, EventSlice};
use dhptam_core::fusion::{
    choose_beta, fuse, fuse_e3ct, intensity_from_e3ct, Bias, Depth, EventFrameWarp, EventRectifier,
    FusionMode,
};
use dhptam_core::geometry::{Camera, Projective, RectifiedStereo, Se3, Side, So3, StereoRig};
use nalgebra::{Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Frame and event camera pairs; poses `cam_from_rig` with the rig frame at the left frame
/// camera. The event cameras sit 2–3 cm off the frame cameras and are turned by about 1°.
struct Rig {
    frame: [Camera; 2],
    event: [Camera; 2],
    frame_from_rig: [Se3; 2],
    event_from_rig: [Se3; 2],
}

fn rig() -> Rig {
    let frame = Camera::new(
        "kb4",
        &[750.0, 749.0, 511.0, 507.0, 0.0037, 0.0143, -0.0285, 0.0143],
        1024,
        1024,
    )
    .unwrap();
    let event = Camera::new(
        "kb4",
        &[1050.0, 1049.0, 641.0, 359.0, -0.02, 0.01, 0.0, 0.0],
        1280,
        720,
    )
    .unwrap();
    let turn = So3::exp(&Vector3::new(0.01, -0.015, 0.004));
    let at = |x: f64, y: f64, rot: So3| Se3::new(rot, Vector3::new(x, y, 0.0)).inverse();
    Rig {
        frame: [frame, frame],
        event: [event, event],
        frame_from_rig: [at(0.0, 0.0, So3::identity()), at(0.1, 0.0, So3::identity())],
        event_from_rig: [at(0.02, 0.03, turn), at(0.12, 0.03, turn)],
    }
}

fn rectified(cams: &[Camera; 2], from_rig: &[Se3; 2]) -> RectifiedStereo {
    let stereo = StereoRig {
        left: cams[0],
        right: cams[1],
        right_from_left: from_rig[1] * from_rig[0].inverse(),
    };
    RectifiedStereo::new(&stereo, &RectificationConfig::default()).unwrap()
}

fn rotation(r: So3) -> Se3 {
    Se3::new(r, Vector3::zeros())
}

#[test]
fn warp_puts_event_pixels_on_the_frame_pixels_of_the_same_point() {
    let rig = rig();
    let ev_rect = rectified(&rig.event, &rig.event_from_rig);
    let fr_rect = rectified(&rig.frame, &rig.frame_from_rig);
    // Rectified event-left frame → rectified frame-left frame.
    let rect_frame_from_rig = rotation(fr_rect.rect_left_from_left) * rig.frame_from_rig[0];
    let rect_event_from_rig = rotation(ev_rect.rect_left_from_left) * rig.event_from_rig[0];
    let frame_from_event = rect_frame_from_rig * rect_event_from_rig.inverse();

    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (mut checked, mut worst, mut worst_infinity) = (0, 0.0f64, 0.0f64);
    for _ in 0..400 {
        let p_rig = Vector3::new(
            rng.random_range(-0.6..0.6),
            rng.random_range(-0.4..0.4),
            rng.random_range(1.5..4.0),
        );
        let p_event = rect_event_from_rig * p_rig;
        let raw_event = rig.event[0].project(&(rig.event_from_rig[0] * p_rig));
        let raw_frame = rig.frame[0].project(&(rig.frame_from_rig[0] * p_rig));
        let (Some(raw_event), Some(raw_frame)) = (raw_event, raw_frame) else {
            continue;
        };
        if !rig.event[0].contains(&raw_event) || !rig.frame[0].contains(&raw_frame) {
            continue;
        }
        let uv_event = ev_rect.rectify_pixel(Side::Left, &raw_event).unwrap();
        let uv_frame = fr_rect.rectify_pixel(Side::Left, &raw_frame).unwrap();
        // A fronto-parallel plane through the point: the ground-truth depth of this pixel.
        let warp = EventFrameWarp::new(
            ev_rect.pinhole,
            fr_rect.pinhole,
            frame_from_event,
            Depth::Plane { depth_m: p_event.z },
            Vector2::zeros(),
        )
        .unwrap();
        let got = warp.warp_pixel(&uv_event).unwrap();
        worst = worst.max((got - uv_frame).norm());
        let back = warp.unwarp_pixel(&uv_frame).unwrap();
        assert!((back - uv_event).norm() < 1e-6, "{back} vs {uv_event}");
        let at_infinity = EventFrameWarp::new(
            ev_rect.pinhole,
            fr_rect.pinhole,
            frame_from_event,
            Depth::Infinity,
            Vector2::zeros(),
        )
        .unwrap();
        worst_infinity =
            worst_infinity.max((at_infinity.warp_pixel(&uv_event).unwrap() - uv_frame).norm());
        checked += 1;
    }
    assert!(checked > 200, "only {checked} points in both views");
    assert!(worst < 0.5, "warp error {worst} px");
    assert!(worst < 1e-4, "warp error {worst} px (exact geometry)");
    // The translation between the cameras matters at 1.5–4 m: ignoring depth is off by pixels.
    assert!(
        worst_infinity > 2.0,
        "infinity warp error only {worst_infinity} px"
    );
}

#[test]
fn alignment_offset_and_image_resampling() {
    let k_event = dhptam_core::geometry::Pinhole {
        fx: 500.0,
        fy: 500.0,
        cx: 31.5,
        cy: 23.5,
    };
    let k_frame = dhptam_core::geometry::Pinhole {
        fx: 600.0,
        fy: 600.0,
        cx: 40.0,
        cy: 30.0,
    };
    let frame_from_event = Se3::new(
        So3::exp(&Vector3::new(0.0, 0.01, 0.0)),
        Vector3::new(0.02, 0.0, 0.0),
    );
    let align = Vector2::new(1.5, -0.75);
    let warp = EventFrameWarp::new(
        k_event,
        k_frame,
        frame_from_event,
        Depth::Plane { depth_m: 2.0 },
        align,
    )
    .unwrap();
    let plain = EventFrameWarp::new(
        k_event,
        k_frame,
        frame_from_event,
        Depth::Plane { depth_m: 2.0 },
        Vector2::zeros(),
    )
    .unwrap();
    let p = Vector2::new(10.0, 20.0);
    assert!((warp.warp_pixel(&p).unwrap() - plain.warp_pixel(&p).unwrap() - align).norm() < 1e-12);
    // The step-by-step eq. 5 and the homography agree.
    let h = plain.homography() * Vector3::new(p.x, p.y, 1.0);
    assert!((h.xy() / h.z - plain.warp_pixel(&p).unwrap()).norm() < 1e-9);

    // A 2-channel image linear in (u, v) resamples exactly (bilinear is exact on it).
    let (w, h) = (64usize, 48usize);
    let src: Vec<f32> = (0..w * h)
        .flat_map(|i| [(i % w) as f32, (i / w) as f32])
        .collect();
    let dst = warp.warp_image(&src, w, h, 2, 80, 60).unwrap();
    let mut inside = 0;
    for v in 0..60 {
        for u in 0..80 {
            let q = warp
                .unwarp_pixel(&Vector2::new(u as f64, v as f64))
                .unwrap();
            let px = &dst[(v * 80 + u) * 2..(v * 80 + u) * 2 + 2];
            if q.x >= 0.0 && q.y >= 0.0 && q.x <= (w - 1) as f64 && q.y <= (h - 1) as f64 {
                assert!(
                    (f64::from(px[0]) - q.x).abs() < 1e-3 && (f64::from(px[1]) - q.y).abs() < 1e-3
                );
                inside += 1;
            } else if q.x < -1.0 || q.y < -1.0 || q.x > w as f64 || q.y > h as f64 {
                assert_eq!(px, [0.0, 0.0]);
            }
        }
    }
    assert!(inside > 1000, "{inside}");
    assert!(warp.warp_image(&src, w, h, 3, 80, 60).is_err());
    assert!(EventFrameWarp::new(
        k_event,
        k_frame,
        frame_from_event,
        Depth::Plane { depth_m: 0.0 },
        align
    )
    .is_err());
}

#[test]
fn event_rectifier_table_matches_per_pixel_rectification() {
    let rig = rig();
    let rect = rectified(&rig.event, &rig.event_from_rig);
    let lut = EventRectifier::new(&rect, Side::Right);
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let mut dropped = 0;
    for _ in 0..2000 {
        let (u, v) = (rng.random_range(0..1280u16), rng.random_range(0..720u16));
        let exact = rect.rectify_pixel(Side::Right, &Vector2::new(f64::from(u), f64::from(v)));
        match (lut.lookup(u, v), exact) {
            (Some((x, y)), Some(e)) => {
                assert_eq!((f64::from(x), f64::from(y)), (e.x.round(), e.y.round()));
            }
            (None, e) => {
                dropped += 1;
                if let Some(e) = e {
                    let (x, y) = (e.x.round(), e.y.round());
                    assert!(
                        x < 0.0
                            || y < 0.0
                            || x >= f64::from(rect.width)
                            || y >= f64::from(rect.height)
                    );
                }
            }
            (Some(_), None) => panic!("table has a pixel the model cannot rectify"),
        }
    }
    // balance = 0 crops: some border pixels leave the view, most stay.
    assert!(dropped > 0 && dropped < 1000, "{dropped}");

    let (x, y, t, p) = (
        [0u16, 640, 1279],
        [0u16, 360, 719],
        [0i64, 1, 2],
        [1i8, 0, 1],
    );
    let events = EventSlice::new(&x, &y, &t, &p).unwrap();
    let out = lut.apply(&events, 0, 10).unwrap();
    let centre = lut.lookup(640, 360).unwrap();
    assert!(out.x.contains(&centre.0) && out.t_ns.contains(&1) && out.len_check());
    let bad = ([1280u16], [0u16], [0i64], [1i8]);
    let events = EventSlice::new(&bad.0, &bad.1, &bad.2, &bad.3).unwrap();
    assert!(lut.apply(&events, 0, 10).is_err());
}

#[test]
fn masked_raw_pixels_lose_their_events_until_the_mask_is_replaced() {
    let rig = rig();
    let rect = rectified(&rig.event, &rig.event_from_rig);
    let mut lut = EventRectifier::new(&rect, Side::Left);
    let (x, y, t, p) = (
        [640u16, 641, 640],
        [360u16, 360, 360],
        [1i64, 2, 3],
        [1i8, 0, 1],
    );
    let events = EventSlice::new(&x, &y, &t, &p).unwrap();
    let all = lut.apply(&events, 0, 10).unwrap();
    assert_eq!(all.t_ns, [1, 2, 3]);
    lut.set_masked(&[360 * 1280 + 640]).unwrap();
    assert_eq!(lut.masked_count(), 1);
    assert_eq!(lut.lookup(640, 360), None);
    assert_eq!(lut.apply(&events, 0, 10).unwrap().t_ns, [2]);
    // A new mask replaces the old one; the empty mask restores the table exactly.
    lut.set_masked(&[360 * 1280 + 641]).unwrap();
    assert_eq!(lut.apply(&events, 0, 10).unwrap().t_ns, [1, 3]);
    assert!(lut.set_masked(&[1280 * 720]).is_err());
    assert_eq!(lut.apply(&events, 0, 10).unwrap().t_ns, [1, 3]);
    lut.set_masked(&[]).unwrap();
    assert_eq!(lut.apply(&events, 0, 10).unwrap(), all);
    assert_eq!(lut.masked_count(), 0);
}

#[test]
fn event_rectifier_apply_is_the_per_event_lookup_for_any_thread_count() {
    let rig = rig();
    let rect = rectified(&rig.event, &rig.event_from_rig);
    let lut = EventRectifier::new(&rect, Side::Left);
    // Several parallel chunks (65 536 events each) with a ragged last one.
    let n = 200_003;
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let x: Vec<u16> = (0..n).map(|_| rng.random_range(0..1280u16)).collect();
    let y: Vec<u16> = (0..n).map(|_| rng.random_range(0..720u16)).collect();
    let t: Vec<i64> = (0..n as i64).collect();
    let p: Vec<i8> = (0..n).map(|k| (k % 2) as i8).collect();
    let events = EventSlice::new(&x, &y, &t, &p).unwrap();
    let mut expected = dhptam_core::fusion::RectifiedEvents::default();
    for k in 0..n {
        if let Some((u, v)) = lut.lookup(x[k], y[k]) {
            expected.x.push(u);
            expected.y.push(v);
            expected.t_ns.push(t[k]);
            expected.p.push(p[k]);
        }
    }
    assert!(expected.t_ns.len() > n / 2 && expected.t_ns.len() < n);
    for threads in [1, 2, 3] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let out = pool.install(|| lut.apply(&events, 0, n as i64)).unwrap();
        assert_eq!(out, expected, "{threads} threads");
    }
    let empty = EventSlice::new(&[], &[], &[], &[]).unwrap();
    assert_eq!(lut.apply(&empty, 0, 1).unwrap(), Default::default());
    // Validation runs chunk by chunk inside the lookup pass: an out-of-range pixel in a later
    // chunk is reported (not looked up), and with bad events in two chunks the error names
    // the first one, whatever the thread count.
    let (mut bx, mut by, mut bt) = (x.clone(), y.clone(), t.clone());
    bx[150_000] = 1280;
    by[190_000] = 720;
    bt[70_000] = 5; // decreasing time
    for threads in [1, 2, 3] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let bad = EventSlice::new(&bx, &by, &bt, &p).unwrap();
        let err = pool
            .install(|| lut.apply(&bad, 0, n as i64))
            .unwrap_err()
            .to_string();
        assert!(err.contains("event 70000 "), "{threads} threads: {err}");
        let bad = EventSlice::new(&bx, &by, &t, &p).unwrap();
        let err = pool
            .install(|| lut.apply(&bad, 0, n as i64))
            .unwrap_err()
            .to_string();
        assert!(err.contains("event 150000 "), "{threads} threads: {err}");
        let bad = EventSlice::new(&x, &by, &t, &p).unwrap();
        let err = pool
            .install(|| lut.apply(&bad, 0, n as i64))
            .unwrap_err()
            .to_string();
        assert!(err.contains("event 190000 "), "{threads} threads: {err}");
    }
}

trait LenCheck {
    fn len_check(&self) -> bool;
}

impl LenCheck for dhptam_core::fusion::RectifiedEvents {
    fn len_check(&self) -> bool {
        let n = self.t_ns.len();
        self.x.len() == n && self.y.len() == n && self.p.len() == n
    }
}

/// A 64×48 frame: `base + gradient` clipped to 8 bits.
fn frame(base: f64, gradient: f64) -> Vec<u8> {
    (0..64 * 48)
        .map(|i| (base + gradient * f64::from((i % 64) as u32) / 63.0).clamp(0.0, 255.0) as u8)
        .collect()
}

fn ratio(f: &[u8]) -> f64 {
    let max = f64::from(*f.iter().max().unwrap());
    f.iter().map(|&v| f64::from(v)).sum::<f64>() / f.len() as f64 / max
}

#[test]
fn beta_switches_to_dvs_bias_on_dark_and_bright_frames_and_back() {
    // The paper's formula, without the cap on APS-biased frames (tested below).
    let config = FusionConfig {
        aps_beta_max: 1.0,
        ..FusionConfig::default()
    };
    let normal = frame(40.0, 180.0);
    let dark = frame(0.0, 30.0);
    let bright = frame(230.0, 25.0);
    let sequence = [&normal, &dark, &normal, &bright, &normal];
    let biases: Vec<Bias> = sequence
        .iter()
        .map(|f| choose_beta(f, None, &config).unwrap().bias)
        .collect();
    assert_eq!(
        biases,
        [Bias::Aps, Bias::Dvs, Bias::Aps, Bias::Dvs, Bias::Aps]
    );
    for f in sequence {
        let d = choose_beta(f, None, &config).unwrap();
        let r = ratio(f);
        assert!((d.ratio - r).abs() < 1e-12);
        let want = match d.bias {
            Bias::Aps => r.min(1.0 - r),
            _ => r.max(1.0 - r),
        };
        assert!((d.beta - want).abs() < 1e-12, "{d:?}");
    }
    // Too few features on a well-exposed frame also switch to DVS; the cap bounds β.
    assert_eq!(
        choose_beta(&normal, Some(20), &config).unwrap().bias,
        Bias::Dvs
    );
    assert_eq!(
        choose_beta(&normal, Some(500), &config).unwrap().bias,
        Bias::Aps
    );
    let capped = FusionConfig {
        beta_max: 0.3,
        ..FusionConfig::default()
    };
    let d = choose_beta(&dark, None, &capped).unwrap();
    assert_eq!((d.bias, d.beta), (Bias::Dvs, 0.3));
    for (mode, beta, bias) in [
        (FusionMode::Frames, 0.0, Bias::FramesOnly),
        (FusionMode::Events, 1.0, Bias::EventsOnly),
    ] {
        let c = FusionConfig {
            mode,
            ..FusionConfig::default()
        };
        let d = choose_beta(&dark, Some(0), &c).unwrap();
        assert_eq!((d.beta, d.bias), (beta, bias));
    }
    assert_eq!(choose_beta(&[0, 0], None, &config).unwrap().ratio, 0.0);
    assert!(choose_beta(&[], None, &config).is_err());
}

#[test]
fn the_aps_cap_bounds_only_aps_biased_frames() {
    let normal = frame(40.0, 180.0);
    let dark = frame(0.0, 30.0);
    let r = ratio(&normal);
    assert!(
        r.min(1.0 - r) > 0.35,
        "the test frame's uncapped β is {}",
        r.min(1.0 - r)
    );
    // The default caps the events' weight in a well-exposed frame at 0.3 …
    let d = choose_beta(&normal, None, &FusionConfig::default()).unwrap();
    assert_eq!((d.bias, d.beta), (Bias::Aps, 0.3));
    // … and leaves a failing frame's DVS-biased β ≥ 1/2 alone.
    let uncapped = FusionConfig {
        aps_beta_max: 1.0,
        ..FusionConfig::default()
    };
    for f in [&dark, &normal] {
        let count = if std::ptr::eq(f, &normal) {
            Some(10)
        } else {
            None
        };
        let capped = choose_beta(f, count, &FusionConfig::default()).unwrap();
        let plain = choose_beta(f, count, &uncapped).unwrap();
        assert_eq!(capped.bias, Bias::Dvs);
        assert_eq!(capped.beta, plain.beta);
        assert!(capped.beta >= 0.5);
    }
    // A cap above min(r, 1 − r) changes nothing; β_max still bounds both modes.
    let loose = FusionConfig {
        aps_beta_max: 0.49,
        ..FusionConfig::default()
    };
    let d = choose_beta(&normal, None, &loose).unwrap();
    assert!((d.beta - r.min(1.0 - r)).abs() < 1e-12);
    let both = FusionConfig {
        beta_max: 0.2,
        ..FusionConfig::default()
    };
    assert_eq!(choose_beta(&normal, None, &both).unwrap().beta, 0.2);
    assert_eq!(choose_beta(&dark, None, &both).unwrap().beta, 0.2);
}

#[test]
fn the_dvs_floor_bounds_only_dvs_biased_frames() {
    let normal = frame(40.0, 180.0);
    let dark = frame(0.0, 30.0);
    let bright = frame(230.0, 25.0);
    let floor = |dvs_beta_min: f64| FusionConfig {
        dvs_beta_min,
        ..FusionConfig::default()
    };
    // Up to 1/2 the floor leaves the paper's max(r, 1 − r) as it is.
    for f in [&dark, &bright] {
        let r = ratio(f);
        for paper in [0.0, 0.5] {
            let d = choose_beta(f, None, &floor(paper)).unwrap();
            assert_eq!(d.bias, Bias::Dvs);
            assert!((d.beta - r.max(1.0 - r)).abs() < 1e-12, "{d:?}");
        }
        // 1 renders a failing frame from its events alone, β_max still bounds it.
        let d = choose_beta(f, None, &floor(1.0)).unwrap();
        assert_eq!((d.bias, d.beta), (Bias::Dvs, 1.0));
        let capped = FusionConfig {
            beta_max: 0.3,
            ..floor(1.0)
        };
        assert_eq!(choose_beta(f, None, &capped).unwrap().beta, 0.3);
    }
    // Too few features make a well-exposed frame DVS-biased, so the floor applies; with
    // enough features it stays APS-biased under the APS cap.
    let starved = choose_beta(&normal, Some(10), &floor(1.0)).unwrap();
    assert_eq!((starved.bias, starved.beta), (Bias::Dvs, 1.0));
    let fine = choose_beta(&normal, Some(500), &floor(1.0)).unwrap();
    assert_eq!((fine.bias, fine.beta), (Bias::Aps, 0.3));
}

#[test]
fn fusion_blends_frame_and_event_intensity() {
    let e3ct = [0.2f32, 0.9, 0.1, 0.0, 0.0, 0.0, 1.0, 0.5, 0.0];
    let d = intensity_from_e3ct(&e3ct, 3).unwrap();
    assert_eq!(d, vec![0.9, 0.0, 1.0]);
    let c = [100u8, 200, 0];
    assert_eq!(fuse(&c, &d, 0.0).unwrap(), c.to_vec());
    assert_eq!(fuse(&c, &d, 1.0).unwrap(), vec![230, 0, 255]);
    // 0.75·100 + 0.25·229.5 = 132.375; 0.75·200 = 150; 0.25·255 = 63.75.
    assert_eq!(fuse(&c, &d, 0.25).unwrap(), vec![132, 150, 64]);
    assert!(fuse(&c, &d[..2], 0.5).is_err());
    assert!(fuse(&c, &d, 1.5).is_err());
}

#[test]
fn beta_statistics_and_one_pass_fusion_equal_their_plain_forms_on_random_images() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    // More pixels than one parallel piece; values everywhere in 0..=255.
    let (w, h) = (700usize, 300usize);
    let frame: Vec<u8> = (0..w * h).map(|_| rng.random_range(0..=255u8)).collect();
    for (dark_level, bright_level) in [(20.0, 235.0), (10.5, 244.5), (0.0, 255.0), (254.9, 255.0)] {
        let config = FusionConfig {
            dark_level,
            bright_level,
            ..FusionConfig::default()
        };
        let d = choose_beta(&frame, None, &config).unwrap();
        let clipped = frame
            .iter()
            .filter(|&&v| f64::from(v) <= dark_level || f64::from(v) >= bright_level)
            .count();
        assert_eq!(d.clipped_fraction, clipped as f64 / frame.len() as f64);
        let sum: f64 = frame.iter().map(|&v| f64::from(v)).sum();
        let max = f64::from(*frame.iter().max().unwrap());
        assert!((d.ratio - sum / frame.len() as f64 / max).abs() < 1e-12);
    }
    let e3ct: Vec<f32> = (0..w * h * 3)
        .map(|_| rng.random_range(-0.2f32..1.3))
        .collect();
    for beta in [0.0, 0.37, 1.0] {
        let plain = fuse(&frame, &intensity_from_e3ct(&e3ct, 3).unwrap(), beta).unwrap();
        assert_eq!(
            fuse_e3ct(&frame, &e3ct, 3, beta).unwrap(),
            plain,
            "β = {beta}"
        );
    }
    assert!(fuse_e3ct(&frame, &e3ct[..w * h * 2], 3, 0.5).is_err());
    assert!(fuse_e3ct(&frame, &e3ct, 3, -0.1).is_err());
}

/// The E3CT (default parameters, window `[0, span_ns)`) added event by event in input order,
/// weights in f64 as `docs/E3CT.md` writes them: the reference the kernels must equal bit
/// for bit.
fn direct_e3ct(ev: &EventSlice<'_>, w: usize, h: usize, span_ns: i64) -> Vec<f32> {
    let mut out = vec![0f32; w * h * 3];
    for k in 0..ev.len() {
        let age_ms = (span_ns - ev.t_ns[k]) as f64 * 1e-6;
        let z = (age_ms - 15.0) * (6.0 / 30.0);
        let v1 = (-0.5 * z * z).exp();
        let s = ev.t_ns[k] as f64 / span_ns as f64 * 2.0;
        let i = (s as usize).min(1);
        let f = s - i as f64;
        let at = (usize::from(ev.y[k]) * w + usize::from(ev.x[k])) * 3 + i;
        out[at] += (v1 * (1.0 - f)) as f32;
        out[at + 1] += (v1 * f) as f32;
    }
    out
}

#[test]
fn e3ct_of_rectified_events_is_the_direct_accumulation_bit_for_bit() {
    // Raw µs-stamped events over 50 ms, some leaving the rectified view; several segments
    // (more than 65,536 distinct stamps with ns stamps).
    let rig = rig();
    let rect = rectified(&rig.event, &rig.event_from_rig);
    let lut = EventRectifier::new(&rect, Side::Left);
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let n = 300_000;
    let span = 50_000_000i64;
    for stamp_ns in [1000i64, 1] {
        let mut t: Vec<i64> = (0..n)
            .map(|_| rng.random_range(0..span / stamp_ns) * stamp_ns)
            .collect();
        t.sort_unstable();
        let x: Vec<u16> = (0..n).map(|_| rng.random_range(0..1280u16)).collect();
        let y: Vec<u16> = (0..n).map(|_| rng.random_range(0..720u16)).collect();
        let p: Vec<i8> = (0..n).map(|_| rng.random_range(0..2i8)).collect();
        let events = EventSlice::new(&x, &y, &t, &p).unwrap();
        let params = E3ctParams::default();
        let (w, h) = (rect.width, rect.height);
        let rectified = lut.apply(&events, 0, span).unwrap();
        assert!(rectified.t_ns.len() < n);
        let want = direct_e3ct(&rectified.as_slice(), w as usize, h as usize, span);
        let banded = e3ct(&rectified.as_slice(), w, h, 0, span, &params).unwrap();
        assert!(banded
            .iter()
            .zip(&want)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        assert!(want.iter().map(|&v| f64::from(v)).sum::<f64>() > 1000.0);
    }
}

#[test]
fn warp_map_with_scales_is_normalise_then_warp_bit_for_bit() {
    let k_event = dhptam_core::geometry::Pinhole {
        fx: 500.0,
        fy: 500.0,
        cx: 63.5,
        cy: 47.5,
    };
    let k_frame = dhptam_core::geometry::Pinhole {
        fx: 560.0,
        fy: 560.0,
        cx: 90.0,
        cy: 70.0,
    };
    let frame_from_event = Se3::new(
        So3::exp(&Vector3::new(0.01, -0.02, 0.005)),
        Vector3::new(0.03, 0.01, 0.0),
    );
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let (sw, sh, c) = (128usize, 96usize, 3usize);
    // Sparse raw values, some above the scales (clipped to 1 after scaling).
    let src: Vec<f32> = (0..sw * sh * c)
        .map(|_| {
            if rng.random_bool(0.3) {
                rng.random_range(0.0..3.0f32)
            } else {
                0.0
            }
        })
        .collect();
    let scales = channel_scales(&[&src], c, 99.0).unwrap();
    // The frame sees past the event image: frame pixels outside it and on its border occur.
    let (fw, fh) = (180usize, 140usize);
    for (depth, align) in [
        (Depth::Plane { depth_m: 1.5 }, Vector2::new(0.7, -1.2)),
        (Depth::Infinity, Vector2::zeros()),
    ] {
        let warp = EventFrameWarp::new(k_event, k_frame, frame_from_event, depth, align).unwrap();
        let normalised = scaled(&src, &scales).unwrap();
        let want = stepped_warp(&warp, align, &normalised, sw, sh, c, fw, fh);
        let map = warp.map(sw, sh, fw, fh).unwrap();
        assert_eq!((map.src_size(), map.dst_size()), ((sw, sh), (fw, fh)));
        let fused = map.apply(&src, c, Some(&scales)).unwrap();
        let staged = warp.warp_image(&normalised, sw, sh, c, fw, fh).unwrap();
        for got in [&fused, &staged] {
            let differ = got
                .iter()
                .zip(&want)
                .filter(|(a, b)| a.to_bits() != b.to_bits())
                .count();
            assert_eq!(differ, 0, "{depth:?}");
        }
        // Without scales the raw values are warped, equal to the reference too.
        let raw = map.apply(&src, c, None).unwrap();
        let raw_want = stepped_warp(&warp, align, &src, sw, sh, c, fw, fh);
        assert!(raw
            .iter()
            .zip(&raw_want)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        // Not two blank images: many values are non-zero, some raw ones above the scales.
        assert!(fused.iter().filter(|&&v| v > 0.0).count() > fw * fh / 2);
        assert!(raw.iter().any(|&v| v > 1.0));
        let outside = (0..fw * fh)
            .filter(|&i| {
                let q = warp.unwarp_pixel(&Vector2::new((i % fw) as f64, (i / fw) as f64));
                q.is_some_and(|q| q.x < -1.0 || q.x > sw as f64 || q.y < -1.0 || q.y > sh as f64)
            })
            .inspect(|&i| assert_eq!(&fused[i * c..(i + 1) * c], &[0.0; 3]))
            .count();
        assert!(outside > fw * fh / 10, "{outside}");
        assert!(map.apply(&src, c, Some(&[1.0, 0.0, 1.0])).is_err());
        assert!(map.apply(&src, c, Some(&scales[..2])).is_err());
        assert!(map.apply(&src[1..], c, None).is_err());
    }
}

#[test]
fn warp_map_apply_fused_is_apply_then_fuse_e3ct_bit_for_bit() {
    let k_event = dhptam_core::geometry::Pinhole {
        fx: 500.0,
        fy: 500.0,
        cx: 63.5,
        cy: 47.5,
    };
    let k_frame = dhptam_core::geometry::Pinhole {
        fx: 560.0,
        fy: 560.0,
        cx: 90.0,
        cy: 70.0,
    };
    let frame_from_event = Se3::new(
        So3::exp(&Vector3::new(0.01, -0.02, 0.005)),
        Vector3::new(0.03, 0.01, 0.0),
    );
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let (sw, sh) = (128usize, 96usize);
    // Two pieces of the parallel pass (16,384 pixels each), the second ragged; frame pixels
    // outside the event image and on its border.
    let (fw, fh) = (180usize, 140usize);
    let frame: Vec<u8> = (0..fw * fh).map(|_| rng.random_range(0..=255u8)).collect();
    let warp = EventFrameWarp::new(
        k_event,
        k_frame,
        frame_from_event,
        Depth::Plane { depth_m: 1.5 },
        Vector2::new(0.7, -1.2),
    )
    .unwrap();
    let map = warp.map(sw, sh, fw, fh).unwrap();
    // 3 channels (an unrolled loop) and 5 (the general one).
    for c in [3usize, 5] {
        let src: Vec<f32> = (0..sw * sh * c)
            .map(|_| {
                if rng.random_bool(0.3) {
                    rng.random_range(0.0..3.0f32)
                } else {
                    0.0
                }
            })
            .collect();
        let scales = channel_scales(&[&src], c, 99.0).unwrap();
        for scale in [None, Some(scales.as_slice())] {
            for beta in [0.0, 0.37, 1.0] {
                for threads in [1, 2] {
                    let pool = rayon::ThreadPoolBuilder::new()
                        .num_threads(threads)
                        .build()
                        .unwrap();
                    let (warped, fused) = pool
                        .install(|| map.apply_fused(&src, c, scale, &frame, beta))
                        .unwrap();
                    let want = map.apply(&src, c, scale).unwrap();
                    assert!(warped
                        .iter()
                        .zip(&want)
                        .all(|(a, b)| a.to_bits() == b.to_bits()));
                    assert_eq!(warped.len(), want.len());
                    let want_fused = fuse_e3ct(&frame, &want, c, beta).unwrap();
                    assert_eq!(
                        fused, want_fused,
                        "{c} channels, β {beta}, {threads} threads"
                    );
                }
            }
        }
        // Not a trivial blend: with β = 1 some pixels are bright events, some black.
        let (_, events_only) = map
            .apply_fused(&src, c, Some(&scales), &frame, 1.0)
            .unwrap();
        assert!(events_only.iter().any(|&v| v > 200) && events_only.contains(&0));
        assert!(map.apply_fused(&src, c, None, &frame[1..], 0.5).is_err());
        assert!(map.apply_fused(&src, c, None, &frame, 1.5).is_err());
        assert!(map.apply_fused(&src[1..], c, None, &frame, 0.5).is_err());
    }
}

/// The warp as it was computed before the precomputed map: the source point stepped along
/// each frame row, bilinear taps tested one by one (pixel centres at integers, 0 outside):
/// the reference the map must equal bit for bit.
#[allow(clippy::too_many_arguments)]
fn stepped_warp(
    warp: &EventFrameWarp,
    align: Vector2<f64>,
    src: &[f32],
    w: usize,
    h: usize,
    c: usize,
    fw: usize,
    fh: usize,
) -> Vec<f32> {
    let hinv = warp.homography().try_inverse().unwrap();
    let step = hinv.column(0).into_owned();
    let mut out = vec![0f32; fw * fh * c];
    for v in 0..fh {
        let start = hinv * Vector3::new(-align.x, v as f64 - align.y, 1.0);
        for u in 0..fw {
            let p = start + step * u as f64;
            let (x, y) = (p.x / p.z, p.y / p.z);
            if !(p.z > 0.0 && x > -1.0 && y > -1.0 && x < w as f64 && y < h as f64) {
                continue;
            }
            let (xf, yf) = (x.floor(), y.floor());
            let (ax, ay) = ((x - xf) as f32, (y - yf) as f32);
            let taps = [
                (0, 0, (1.0 - ax) * (1.0 - ay)),
                (1, 0, ax * (1.0 - ay)),
                (0, 1, (1.0 - ax) * ay),
                (1, 1, ax * ay),
            ];
            for (dx, dy, weight) in taps {
                let (xi, yi) = (xf as isize + dx, yf as isize + dy);
                if xi < 0 || yi < 0 || xi as usize >= w || yi as usize >= h || weight == 0.0 {
                    continue;
                }
                for k in 0..c {
                    out[(v * fw + u) * c + k] +=
                        weight * src[(yi as usize * w + xi as usize) * c + k];
                }
            }
        }
    }
    out
}
