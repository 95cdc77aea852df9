//! E3CT and baseline representations on hand-computed windows, error handling, and
//! bit-identical results across thread counts.

use dhptam_core::events::{
    apply_scales, channel_scales, count_image, e3ct, scaled, time_surface, voxel_grid, E3ctParams,
    EventSlice, PolarityMode,
};
use dhptam_core::Error;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const MS: i64 = 1_000_000;

struct Events {
    x: Vec<u16>,
    y: Vec<u16>,
    t: Vec<i64>,
    p: Vec<i8>,
}

impl Events {
    fn new(list: &[(u16, u16, i64, i8)]) -> Self {
        Self {
            x: list.iter().map(|e| e.0).collect(),
            y: list.iter().map(|e| e.1).collect(),
            t: list.iter().map(|e| e.2).collect(),
            p: list.iter().map(|e| e.3).collect(),
        }
    }

    fn slice(&self) -> EventSlice<'_> {
        EventSlice::new(&self.x, &self.y, &self.t, &self.p).unwrap()
    }

    /// `n` events with µs-quantised sorted times spread over [0, span), seeded.
    fn random(n: usize, w: u16, h: u16, span_ns: i64, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut t: Vec<i64> = (0..n)
            .map(|_| rng.random_range(0..span_ns / 1000) * 1000)
            .collect();
        t.sort_unstable();
        Self {
            x: (0..n).map(|_| rng.random_range(0..w)).collect(),
            y: (0..n).map(|_| rng.random_range(0..h)).collect(),
            t,
            p: (0..n).map(|_| rng.random_range(0..2)).collect(),
        }
    }
}

fn at(img: &[f32], w: usize, c: usize, x: usize, y: usize) -> &[f32] {
    &img[(y * w + x) * c..(y * w + x + 1) * c]
}

fn close(a: &[f32], b: &[f64]) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert!((f64::from(*x) - y).abs() < 1e-6, "{a:?} != {b:?}");
    }
}

#[test]
fn hand_computed_values() {
    // Window [0, 30 ms), α = 0.5, η = 30 ms, 3 channels.
    // Event A at t = 15 ms: age 15 ms = η/2 so V1 = 1; τ = 0.5, s = 1: all of it in channel 1.
    // Event B at t = 20 ms: age 10 ms, z = (10 − 15)/5 = −1, V1 = e^{−1/2}; τ = 2/3,
    //   s = 4/3: channel 1 gets V1·2/3, channel 2 gets V1/3.
    // Event C at t = 0 (OFF) on the same pixel as A: age 30 ms, z = 3, V1 = e^{−4.5}; τ = 0,
    //   all in channel 0.
    let ev = Events::new(&[(3, 1, 0, 0), (3, 1, 15 * MS, 1), (0, 2, 20 * MS, 1)]);
    let img = e3ct(&ev.slice(), 4, 3, 0, 30 * MS, &E3ctParams::default()).unwrap();
    assert_eq!(img.len(), 4 * 3 * 3);
    let v_b = (-0.5f64).exp();
    close(at(&img, 4, 3, 3, 1), &[(-4.5f64).exp(), 1.0, 0.0]);
    close(at(&img, 4, 3, 0, 2), &[0.0, v_b * 2.0 / 3.0, v_b / 3.0]);
    let touched: f32 = img.iter().sum();
    let expected = 1.0 + v_b + (-4.5f64).exp();
    assert!((f64::from(touched) - expected).abs() < 1e-6);

    // Split polarity: the OFF event C moves to channels 3..6.
    let params = E3ctParams {
        polarity: PolarityMode::Split,
        ..E3ctParams::default()
    };
    let img = e3ct(&ev.slice(), 4, 3, 0, 30 * MS, &params).unwrap();
    close(
        at(&img, 4, 6, 3, 1),
        &[0.0, 1.0, 0.0, (-4.5f64).exp(), 0.0, 0.0],
    );
}

#[test]
fn early_events_fill_channel_zero_and_late_ones_channel_two() {
    // A 30 ms window with the kernel centred so that early and late events weigh the same.
    let early = Events::new(&[(1, 1, MS, 1), (1, 1, 2 * MS, 0)]);
    let late = Events::new(&[(1, 1, 28 * MS, 1), (1, 1, 29 * MS, 0)]);
    let p = E3ctParams {
        eta_ms: 60.0,
        ..E3ctParams::default()
    };
    let a = e3ct(&early.slice(), 2, 2, 0, 30 * MS, &p).unwrap();
    let b = e3ct(&late.slice(), 2, 2, 0, 30 * MS, &p).unwrap();
    let (a, b) = (at(&a, 2, 3, 1, 1), at(&b, 2, 3, 1, 1));
    assert!(a[0] > a[1] && a[2] == 0.0, "{a:?}");
    assert!(b[2] > b[1] && b[0] == 0.0, "{b:?}");
}

#[test]
fn empty_window_gives_zeros_and_identical_streams_identical_tensors() {
    let none = Events::new(&[]);
    let img = e3ct(&none.slice(), 5, 4, 0, 10 * MS, &E3ctParams::default()).unwrap();
    assert_eq!(img.len(), 60);
    assert!(img.iter().all(|&v| v == 0.0));

    let ev = Events::random(5000, 64, 48, 50 * MS, 1);
    let left = e3ct(&ev.slice(), 64, 48, 0, 50 * MS, &E3ctParams::default()).unwrap();
    let right = e3ct(&ev.slice(), 64, 48, 0, 50 * MS, &E3ctParams::default()).unwrap();
    let scales = channel_scales(&[&left, &right], 3, 99.0).unwrap();
    let (mut l, mut r) = (left.clone(), right.clone());
    apply_scales(&mut l, &scales).unwrap();
    apply_scales(&mut r, &scales).unwrap();
    assert_eq!(l, r);
    assert!(l.iter().all(|v| (0.0..=1.0).contains(v)));
    assert!(l.contains(&1.0));
}

#[test]
fn bad_events_are_errors_naming_the_event() {
    let params = E3ctParams::default();
    let run = |list: &[(u16, u16, i64, i8)]| {
        let ev = Events::new(list);
        e3ct(&ev.slice(), 4, 3, 0, 10 * MS, &params).unwrap_err()
    };
    let field = |e: Error| match e {
        Error::InvalidInput { what, .. } => what,
        other => panic!("unexpected {other}"),
    };
    let ok = (0, 0, 0, 1);
    assert_eq!(field(run(&[ok, (4, 0, 1, 1)])), "event 1 (x, y)");
    assert_eq!(field(run(&[ok, ok, (0, 3, 1, 1)])), "event 2 (x, y)");
    assert_eq!(field(run(&[(0, 0, 5, 1), (0, 0, 4, 1)])), "event 1 t_ns");
    let unsorted = run(&[(0, 0, 5, 1), (0, 0, 4, 1)]).to_string();
    assert!(unsorted.contains("non-decreasing"), "{unsorted}");
    assert_eq!(field(run(&[ok, (0, 0, 10 * MS, 1)])), "event 1 t_ns");
    assert_eq!(field(run(&[(0, 0, -1, 1)])), "event 0 t_ns");
    assert_eq!(field(run(&[ok, (0, 0, 1, -1)])), "event 1 p");
    assert!(EventSlice::new(&[0], &[0, 1], &[0], &[1]).is_err());
    let ev = Events::new(&[ok]);
    assert!(e3ct(&ev.slice(), 4, 3, 5, 5, &params).is_err());
    assert!(e3ct(&ev.slice(), 0, 3, 0, 5, &params).is_err());
}

#[test]
fn results_are_bit_identical_across_thread_counts() {
    // Enough events for the parallel path; clustered rows make bands uneven.
    let mut ev = Events::random(300_000, 320, 240, 50 * MS, 7);
    for y in ev.y.iter_mut().step_by(3) {
        *y %= 16;
    }
    for polarity in [PolarityMode::Both, PolarityMode::Split] {
        let params = E3ctParams {
            polarity,
            ..E3ctParams::default()
        };
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| e3ct(&ev.slice(), 320, 240, 0, 50 * MS, &params).unwrap())
        };
        let one = run(1);
        for threads in [2, 3, 8] {
            let many = run(threads);
            assert!(
                one.iter()
                    .zip(&many)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "{threads} threads differ from 1"
            );
        }
        // And the same totals as a plain f64 sum of the kernel (guards a no-op accumulator).
        let total: f64 = one.iter().map(|&v| f64::from(v)).sum();
        assert!(total > 1000.0, "{total}");
    }
}

#[test]
fn scales_are_a_percentile_of_non_zero_values_pooled_over_tensors() {
    // Channel 0 values 1..=100 spread over two tensors, channel 1 empty.
    let mut a = vec![0f32; 200];
    let mut b = vec![0f32; 200];
    for k in 0..50 {
        a[2 * k] = (k + 1) as f32;
        b[2 * k] = (k + 51) as f32;
    }
    let s = channel_scales(&[&a, &b], 2, 90.0).unwrap();
    assert_eq!(s, vec![90.0, 1.0]);
    let s = channel_scales(&[&a], 2, 90.0).unwrap();
    assert_eq!(s, vec![45.0, 1.0]);
    apply_scales(&mut b, &[90.0, 1.0]).unwrap();
    assert_eq!(b[0], 51.0 / 90.0);
    assert_eq!(b[98], 1.0);
    assert!(channel_scales(&[&a], 2, 0.0).is_err());
    assert!(channel_scales(&[&a[..3]], 2, 50.0).is_err());
    assert!(apply_scales(&mut b, &[0.0, 1.0]).is_err());
}

#[test]
fn baselines_on_hand_computed_windows() {
    let ev = Events::new(&[
        (1, 0, 0, 1),
        (1, 0, 5 * MS, 0),
        (1, 0, 8 * MS, 1),
        (0, 1, 10 * MS, 1),
    ]);
    let s = ev.slice();
    let count = count_image(&s, 2, 2, 0, 20 * MS, PolarityMode::Both).unwrap();
    assert_eq!(count, vec![0.0, 3.0, 1.0, 0.0]);
    let split = count_image(&s, 2, 2, 0, 20 * MS, PolarityMode::Split).unwrap();
    assert_eq!(split, vec![0.0, 0.0, 2.0, 1.0, 1.0, 0.0, 0.0, 0.0]);

    let ts = time_surface(&s, 2, 2, 0, 20 * MS, 10.0).unwrap();
    close(
        &ts,
        &[
            0.0,
            0.0,
            (-1.2f64).exp(),
            (-1.5f64).exp(),
            (-1.0f64).exp(),
            0.0,
            0.0,
            0.0,
        ],
    );

    // 3 bins over 20 ms: t = 0 → bin 0; 5 ms → s = 0.5; 8 ms → s = 0.8; 10 ms → s = 1.
    let vg = voxel_grid(&s, 2, 2, 0, 20 * MS, 3).unwrap();
    close(&vg[3..6], &[1.0 - 0.5 + 0.2, -0.5 + 0.8, 0.0]);
    close(&vg[6..9], &[0.0, 1.0, 0.0]);
    assert!(voxel_grid(&s, 2, 2, 0, 20 * MS, 1).is_err());
    assert!(time_surface(&s, 1, 2, 0, 20 * MS, 10.0).is_err());
}

#[test]
fn reused_workspace_and_output_give_the_same_tensors() {
    use dhptam_core::events::{e3ct_into, E3ctWorkspace};
    let params = E3ctParams::default();
    let mut workspace = E3ctWorkspace::default();
    let mut out = vec![f32::NAN; 320 * 240 * 3];
    // Windows of different sizes one after another, on different thread counts: leftovers of
    // a previous window must not leak into the next.
    for (n, seed, threads) in [(200_000, 1, 2), (50_000, 2, 1), (0, 3, 2), (120_000, 4, 3)] {
        let ev = Events::random(n, 320, 240, 50 * MS, seed);
        let fresh = e3ct(&ev.slice(), 320, 240, 0, 50 * MS, &params).unwrap();
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                e3ct_into(
                    &ev.slice(),
                    320,
                    240,
                    0,
                    50 * MS,
                    &params,
                    &mut workspace,
                    &mut out,
                )
                .unwrap()
            });
        assert!(fresh
            .iter()
            .zip(&out)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
    }
    let ev = Events::random(10, 320, 240, 50 * MS, 5);
    assert!(e3ct_into(
        &ev.slice(),
        320,
        240,
        0,
        50 * MS,
        &params,
        &mut workspace,
        &mut out[1..]
    )
    .is_err());
}

/// The E3CT written as plainly as possible: each event's weights from the formula (f64, cast
/// to f32 at the end as the library does), added straight into the image in input order.
fn direct_e3ct(ev: &Events, w: usize, h: usize, span_ns: i64, params: &E3ctParams) -> Vec<f32> {
    let b = params.channels;
    let c = params.output_channels();
    let mut out = vec![0f32; w * h * c];
    for k in 0..ev.x.len() {
        let age_ms = (span_ns - ev.t[k]) as f64 * 1e-6;
        let z = (age_ms - 0.5 * params.eta_ms) * (6.0 / params.eta_ms);
        let v1 = (-params.alpha * z * z).exp();
        let s = ev.t[k] as f64 / span_ns as f64 * (b - 1) as f64;
        let i = (s as usize).min(b - 2);
        let f = s - i as f64;
        let group = if params.polarity == PolarityMode::Split && ev.p[k] == 0 {
            b
        } else {
            0
        };
        let at = (usize::from(ev.y[k]) * w + usize::from(ev.x[k])) * c + group + i;
        out[at] += (v1 * (1.0 - f)) as f32;
        out[at + 1] += (v1 * f) as f32;
    }
    out
}

#[test]
fn banded_accumulation_is_the_direct_accumulation_bit_for_bit() {
    // 1280×720×3 spans many cache bands; 6 channels and split polarity shift the offsets.
    // The same bits mean the same additions in the same order per pixel, on any thread count.
    let (w, h, span) = (1280u16, 720u16, 50 * MS);
    let mut ev = Events::random(400_000, w, h, span, 11);
    for (k, x) in ev.x.iter_mut().enumerate().step_by(2) {
        // Half the events on a few hot pixels: long per-pixel sums, where order matters.
        *x = (k % 7) as u16;
    }
    for (channels, polarity) in [(3, PolarityMode::Both), (6, PolarityMode::Split)] {
        let params = E3ctParams {
            channels,
            polarity,
            ..E3ctParams::default()
        };
        let want = direct_e3ct(&ev, w.into(), h.into(), span, &params);
        for threads in [1, 2, 5] {
            let got = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| e3ct(&ev.slice(), w.into(), h.into(), 0, span, &params).unwrap());
            let differ = got
                .iter()
                .zip(&want)
                .filter(|(a, b)| a.to_bits() != b.to_bits())
                .count();
            assert_eq!(differ, 0, "{channels} channels, {threads} threads");
        }
    }
}

#[test]
fn scales_equal_a_sorted_nearest_rank_on_random_tensors() {
    // Values over many octaves, negative ones (magnitudes count), zeros, and tiny subnormal
    // values that share the histogram's first bin with nothing else.
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut tensor = |n: usize| -> Vec<f32> {
        (0..n)
            .map(|_| match rng.random_range(0..10) {
                0..=4 => 0.0,
                5 => -rng.random_range(0.0..3.0f32),
                6 => f32::from_bits(rng.random_range(1..1000)),
                _ => rng.random_range(0.0f32..1.0).powi(3) * 50.0,
            })
            .collect()
    };
    let (a, b) = (tensor(3 * 70_001), tensor(3 * 50_000));
    for percentile in [0.001, 1.0, 50.0, 99.0, 99.9, 100.0] {
        let got = channel_scales(&[&a, &b], 3, percentile).unwrap();
        for (ch, &scale) in got.iter().enumerate() {
            let mut values: Vec<f32> = a
                .iter()
                .chain(&b)
                .skip(ch)
                .step_by(3)
                .filter(|v| **v != 0.0)
                .map(|v| v.abs())
                .collect();
            values.sort_by(f32::total_cmp);
            let rank =
                ((percentile / 100.0 * values.len() as f64).ceil() as usize).clamp(1, values.len());
            assert_eq!(
                scale,
                values[rank - 1],
                "channel {ch}, percentile {percentile}"
            );
        }
    }
    // Every channel count (1–4 and 6 have their own unrolled pass, 5 and 7 the general one),
    // with a ragged last piece (70,001 pixels).
    for channels in 1..=7usize {
        let t = tensor(channels * 70_001);
        let got = channel_scales(&[&t], channels, 99.0).unwrap();
        for (ch, &scale) in got.iter().enumerate() {
            let mut values: Vec<f32> = t
                .iter()
                .skip(ch)
                .step_by(channels)
                .filter(|v| **v != 0.0)
                .map(|v| v.abs())
                .collect();
            values.sort_by(f32::total_cmp);
            let rank = ((0.99 * values.len() as f64).ceil() as usize).clamp(1, values.len());
            assert_eq!(scale, values[rank - 1], "{channels} channels, channel {ch}");
        }
    }
    let mut bad = a.clone();
    bad[3 * 10 + 2] = f32::NAN;
    let err = channel_scales(&[&b, &bad], 3, 99.0).unwrap_err();
    assert!(err.to_string().contains("tensors[1][32]"), "{err}");
    // `scaled` is `apply_scales` into a new buffer.
    let scales = channel_scales(&[&a], 3, 90.0).unwrap();
    let copy = scaled(&a, &scales).unwrap();
    let mut in_place = a.clone();
    apply_scales(&mut in_place, &scales).unwrap();
    assert_eq!(copy, in_place);
    assert!(copy.iter().all(|v| (0.0..=1.0).contains(v)));
    assert!(scaled(&a[..4], &scales).is_err());
}

/// Regression from the `events` fuzz target (issue 10): a window whose length overflows i64
/// (here from near `i64::MIN` to a positive end) is an input error for every
/// representation, not an arithmetic overflow inside the kernels.
#[test]
fn a_window_longer_than_i64_is_refused() {
    use dhptam_core::events::e3ct::{e3ct, E3ctParams, PolarityMode};
    use dhptam_core::events::{count_image, time_surface, voxel_grid, EventSlice};

    let (x, y, t, p) = ([1u16], [2u16], [5i64], [1i8]);
    let events = EventSlice::new(&x, &y, &t, &p).expect("consistent arrays");
    let (t0, t1) = (i64::MIN + 7, 10);
    let refused = |r: dhptam_core::Result<Vec<f32>>| matches!(r, Err(Error::InvalidInput { ref what, .. }) if what == "t_end_ns");
    assert!(refused(e3ct(&events, 8, 8, t0, t1, &E3ctParams::default())));
    assert!(refused(count_image(
        &events,
        8,
        8,
        t0,
        t1,
        PolarityMode::Both
    )));
    assert!(refused(time_surface(&events, 8, 8, t0, t1, 10.0)));
    assert!(refused(voxel_grid(&events, 8, 8, t0, t1, 3)));
    // The longest representable window is still accepted.
    assert!(e3ct(&events, 8, 8, 0, i64::MAX, &E3ctParams::default()).is_ok());
}
