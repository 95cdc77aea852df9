//! E3CT throughput at 1280×720 (TUM-VIE's event camera resolution) on 1 and 2 rayon threads.
//!
//! The window holds 1,000,000 events over 50 ms (20 Hz frames) with µs-quantised sorted
//! stamps, as TUM-VIE stores them, at pixels drawn from a seeded generator: 70 % along a few
//! hundred random line segments (edges moving through the scene), 30 % uniform noise. The
//! count image is measured in the same run as the cheapest possible accumulation.
//! `e3ct` allocates its output and scratch memory per call; `e3ct_into_reused` reuses both,
//! as a stream of windows does.

use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use dhptam_core::events::{
    count_image, e3ct, e3ct_into, E3ctParams, E3ctWorkspace, EventSlice, PolarityMode,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const W: u32 = 1280;
const H: u32 = 720;
const EVENTS: usize = 1_000_000;
const SPAN_NS: i64 = 50_000_000;

struct Window {
    x: Vec<u16>,
    y: Vec<u16>,
    t: Vec<i64>,
    p: Vec<i8>,
}

fn window() -> Window {
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let segments: Vec<[f64; 4]> = (0..300)
        .map(|_| {
            [
                rng.random_range(0.0..f64::from(W)),
                rng.random_range(0.0..f64::from(H)),
                rng.random_range(-60.0..60.0),
                rng.random_range(-60.0..60.0),
            ]
        })
        .collect();
    let mut t: Vec<i64> = (0..EVENTS)
        .map(|_| rng.random_range(0..SPAN_NS / 1000) * 1000)
        .collect();
    t.sort_unstable();
    let (mut x, mut y) = (Vec::with_capacity(EVENTS), Vec::with_capacity(EVENTS));
    for _ in 0..EVENTS {
        let (u, v) = if rng.random_bool(0.7) {
            let s = segments[rng.random_range(0..segments.len())];
            let a: f64 = rng.random();
            (s[0] + a * s[2], s[1] + a * s[3])
        } else {
            (
                rng.random_range(0.0..f64::from(W)),
                rng.random_range(0.0..f64::from(H)),
            )
        };
        x.push(u.clamp(0.0, f64::from(W - 1)) as u16);
        y.push(v.clamp(0.0, f64::from(H - 1)) as u16);
    }
    let p = (0..EVENTS).map(|_| rng.random_range(0..2)).collect();
    Window { x, y, t, p }
}

fn bench(c: &mut Criterion) {
    let w = window();
    let events = EventSlice::new(&w.x, &w.y, &w.t, &w.p).expect("equal lengths");
    let params = E3ctParams::default();
    let mut group = c.benchmark_group("e3ct_1280x720_1M_events");
    group
        .sample_size(20)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3))
        .throughput(Throughput::Elements(EVENTS as u64));
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("thread pool");
        group.bench_function(format!("e3ct/{threads}_threads"), |b| {
            b.iter(|| {
                pool.install(|| {
                    black_box(e3ct(black_box(&events), W, H, 0, SPAN_NS, &params).unwrap())
                })
            })
        });
    }
    // A stream of windows: the output and the scratch memory are reused from window to window.
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("thread pool");
        let mut workspace = E3ctWorkspace::default();
        let mut out = vec![0f32; (W * H * 3) as usize];
        group.bench_function(format!("e3ct_into_reused/{threads}_threads"), |b| {
            b.iter(|| {
                pool.install(|| {
                    e3ct_into(
                        black_box(&events),
                        W,
                        H,
                        0,
                        SPAN_NS,
                        &params,
                        &mut workspace,
                        &mut out,
                    )
                    .unwrap()
                });
                black_box(&out);
            })
        });
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("thread pool");
    group.bench_function("count_image/1_thread", |b| {
        b.iter(|| {
            pool.install(|| {
                black_box(
                    count_image(black_box(&events), W, H, 0, SPAN_NS, PolarityMode::Both).unwrap(),
                )
            })
        })
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
