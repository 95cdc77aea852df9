//! Ray-casting rate of the simulator: one render of the desk room through a kb4 camera at
//! the demo's event resolution (320×180) and TUM-VIE's frame resolution (1024×1024), on one
//! thread (the baseline) and on every core, plus one ESIM step over the same image.
//!
//! Ten 512×512 value-noise textures stand in for the photographs (scikit-image is a Python
//! package); the lookup cost does not depend on the content.

use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use dhptam_core::config::Config;
use dhptam_core::geometry::Camera;
use dhptam_core::sim::{look_at, render, BuiltinMotion, EventGenerator, RayTable, Scene, Texture};
use nalgebra::Vector3;

fn scene() -> Scene {
    let photos = (0..10)
        .map(|i| Texture::value_noise(512, 8, 6, 0.6, (0.05, 0.95), i))
        .collect();
    Scene::desk_room(photos, 0)
}

fn cameras() -> Vec<(&'static str, Camera)> {
    let k = [-0.0308, 0.0151, -0.0139, 0.0040];
    vec![
        (
            "event 320x180",
            Camera::new("kb4", &[[262.3, 262.3, 158.7, 90.9], k].concat(), 320, 180).unwrap(),
        ),
        (
            "frame 1024x1024",
            Camera::new(
                "kb4",
                &[[747.3, 747.4, 490.8, 506.1], k].concat(),
                1024,
                1024,
            )
            .unwrap(),
        ),
    ]
}

fn bench_render(c: &mut Criterion) {
    let scene = scene();
    let pose = look_at(&Vector3::new(0.1, -0.2, 1.3), &Vector3::new(0.0, 1.3, 0.9));
    let mut group = c.benchmark_group("ray casting");
    group.measurement_time(Duration::from_secs(4));
    group.sample_size(20);
    let one_thread = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    for (name, camera) in cameras() {
        let rays = RayTable::new(&camera);
        let mut out = vec![0.0f32; rays.len()];
        group.throughput(Throughput::Elements(rays.len() as u64));
        group.bench_function(format!("{name}, 1 thread"), |b| {
            b.iter(|| one_thread.install(|| render(&scene, &rays, black_box(&pose), &mut out)))
        });
        group.bench_function(format!("{name}, all threads"), |b| {
            b.iter(|| render(&scene, &rays, black_box(&pose), &mut out))
        });
    }
    group.finish();

    // One event-generator step between two renders 1 ms apart on the desk spiral.
    let (_, camera) = cameras()[0];
    let rays = RayTable::new(&camera);
    let traj = BuiltinMotion::DeskSpiral
        .trajectory(1_000_000_000, &Scene::desk_room_region())
        .unwrap();
    let log = |t: i64| -> Vec<f64> {
        let mut img = vec![0.0f32; rays.len()];
        render(&scene, &rays, &traj.pose_at(t), &mut img);
        img.iter().map(|&r| (f64::from(r) + 2e-4).ln()).collect()
    };
    let (a, b) = (log(500_000_000), log(501_000_000));
    let params = Config::default().sim.params().events;
    let mut group = c.benchmark_group("events");
    group.throughput(Throughput::Elements(rays.len() as u64));
    group.bench_function("ESIM step 320x180", |bench| {
        bench.iter(|| {
            let mut generator = EventGenerator::new(320, params, 1, 0, &a).unwrap();
            let mut out = Vec::new();
            generator.advance(1_000_000, &b, 1.0, &mut out).unwrap();
            black_box(out.len())
        })
    });
    group.finish();
}

criterion_group!(benches, bench_render);
criterion_main!(benches);
