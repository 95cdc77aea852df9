//! Batch projection and unprojection of 1,000,000 points through each camera model
//! (`Camera::project_points` / `unproject_points`, parallel over rayon chunks).
//!
//! The points are the unit bearings of a regular grid of pixels covering the image, scaled
//! to depths of 0.5–20 m, so every point is inside the field of view and every pixel
//! unprojects; pinhole is the baseline the distortion models are compared with.

use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use dhptam_core::geometry::{Camera, Projective};

const POINTS: usize = 1_000_000;

fn cameras() -> Vec<Camera> {
    vec![
        Camera::new("pinhole", &[460.0, 458.0, 319.5, 239.5], 640, 480).unwrap(),
        Camera::new(
            "radtan",
            &[460.0, 458.5, 318.2, 247.1, -0.28, 0.07, 1e-4, -2e-4, 0.0],
            640,
            480,
        )
        .unwrap(),
        Camera::new(
            "kb4",
            &[750.0, 749.2, 511.3, 506.8, 0.0037, 0.0143, -0.0285, 0.0143],
            1024,
            1024,
        )
        .unwrap(),
    ]
}

/// `POINTS` pixels on a grid over the image and the 3-D points they see.
fn inputs(camera: &Camera) -> (Vec<f64>, Vec<f64>) {
    let side = (POINTS as f64).sqrt().ceil() as usize;
    let (w, h) = (f64::from(camera.width - 1), f64::from(camera.height - 1));
    let mut uv = Vec::with_capacity(2 * POINTS);
    let mut xyz = Vec::with_capacity(3 * POINTS);
    for i in 0..POINTS {
        let (col, row) = (i % side, i / side);
        let u = w * col as f64 / (side - 1) as f64;
        let v = h * row as f64 / (side - 1) as f64;
        let bearing = camera
            .unproject(&nalgebra::Vector2::new(u, v))
            .expect("grid pixel inside the model's range");
        let depth = 0.5 + 19.5 * ((i * 7919) % 1000) as f64 / 1000.0;
        uv.extend([u, v]);
        xyz.extend((bearing * depth).iter());
    }
    (uv, xyz)
}

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("camera_1M_points");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3));
    group.throughput(Throughput::Elements(POINTS as u64));
    for camera in cameras() {
        let (uv, xyz) = inputs(&camera);
        let name = camera.model.name();
        let mut uv_out = vec![0.0; 2 * POINTS];
        group.bench_function(format!("project/{name}"), |b| {
            b.iter(|| {
                camera
                    .project_points(black_box(&xyz), black_box(&mut uv_out))
                    .unwrap()
            })
        });
        let mut xyz_out = vec![0.0; 3 * POINTS];
        group.bench_function(format!("unproject/{name}"), |b| {
            b.iter(|| {
                camera
                    .unproject_points(black_box(&uv), black_box(&mut xyz_out))
                    .unwrap()
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
