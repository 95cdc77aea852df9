//! MCAP logs: round trips, time-range reads of events, and errors on damaged files.

use dhptam_core::io::mcap::{
    CameraCalibration, CompressedImage, LogCompression, LogOptions, LogReader, LogWriter,
    PointCloud, PoseInFrame, RawImage, SchemaKind,
};
use dhptam_core::Error;

fn tmp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("dhptam-mcap-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// 10 000 events with repeated timestamps, spanning batch and chunk boundaries.
fn events() -> (Vec<u16>, Vec<u16>, Vec<i64>, Vec<i8>) {
    let n = 10_000;
    let x = (0..n).map(|i| (i * 7 % 640) as u16).collect();
    let y = (0..n).map(|i| (i * 13 % 480) as u16).collect();
    let t = (0..n).map(|i| 1_000_000 + (i as i64 / 3) * 1_000).collect();
    let p = (0..n).map(|i| (i % 2) as i8).collect();
    (x, y, t, p)
}

fn write_log(path: &std::path::Path, compression: LogCompression) {
    let options = LogOptions {
        compression,
        chunk_size_bytes: 16 * 1024,
        batch_events: 1000,
    };
    let mut w = LogWriter::create(path, options).unwrap();
    let (x, y, t, p) = events();
    // Uneven appends: batches must not depend on how events arrive.
    for (a, b) in [(0, 1), (1, 2500), (2500, 2500), (2500, 10_000)] {
        w.add_events(
            "/events/left",
            "event_left",
            &x[a..b],
            &y[a..b],
            &t[a..b],
            &p[a..b],
        )
        .unwrap();
    }
    for k in 0..3 {
        let image = RawImage {
            t_ns: 1_000_000 + k * 50_000_000,
            frame_id: "frame_left".into(),
            width: 4,
            height: 2,
            encoding: "mono8".into(),
            step: 4,
            data: (0..8).map(|v| (v + k) as u8).collect(),
        };
        w.add_image("/frames/left", &image).unwrap();
        w.add_pose(
            "/ground_truth",
            &PoseInFrame {
                t_ns: image.t_ns,
                frame_id: "world".into(),
                translation: [k as f64, 0.5, -1.0],
                quat_xyzw: [0.0, 0.0, 0.6, 0.8],
            },
        )
        .unwrap();
    }
    w.add_calibration(
        "/calibration/frame_left",
        &CameraCalibration {
            t_ns: 0,
            frame_id: "frame_left".into(),
            width: 4,
            height: 2,
            distortion_model: "kannala_brandt".into(),
            d: vec![0.1, 0.2, 0.3, 0.4],
            k: vec![100.0, 0.0, 2.0, 0.0, 100.0, 1.0, 0.0, 0.0, 1.0],
            r: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: vec![
                100.0, 0.0, 2.0, 0.0, 0.0, 100.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0,
            ],
        },
    )
    .unwrap();
    w.add_point_cloud(
        "/slam/map",
        &PointCloud {
            t_ns: 200_000_000,
            frame_id: "world".into(),
            points: vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]],
        },
    )
    .unwrap();
    w.add_metadata("dhptam.test", [("k".to_string(), "v".to_string())].into())
        .unwrap();
    w.finish().unwrap();
}

#[test]
fn events_round_trip_and_windows_match_a_linear_scan() {
    for compression in [
        LogCompression::Zstd,
        LogCompression::Lz4,
        LogCompression::None,
    ] {
        let path = tmp(&format!("events-{compression:?}.mcap"));
        write_log(&path, compression);
        let r = LogReader::open(&path).unwrap();
        let (x, y, t, p) = events();
        assert_eq!(r.event_count("/events/left").unwrap(), t.len());
        assert_eq!(
            r.event_time_range("/events/left").unwrap(),
            (t[0], t[t.len() - 1] + 1)
        );
        let all = r.event_slice("/events/left", 0, usize::MAX).unwrap();
        assert_eq!((all.x, all.y, all.t_ns, all.p), (x, y, t.clone(), p));
        for (t0, t1) in [
            (0, 1_000_000),
            (1_000_000, 1_000_001),
            (1_333_000, 2_000_500),
            (1_999_000, 3_000_000),
            (4_332_000, 9_000_000),
            (5_000_000, 4_000_000),
        ] {
            let expected: Vec<i64> = t.iter().copied().filter(|&v| t0 <= v && v < t1).collect();
            let window = r.event_window("/events/left", t0, t1).unwrap();
            assert_eq!(window.t_ns, expected, "window [{t0}, {t1})");
        }
    }
}

#[test]
fn foxglove_messages_round_trip() {
    let path = tmp("messages.mcap");
    write_log(&path, LogCompression::Zstd);
    let r = LogReader::open(&path).unwrap();
    let images = r.images("/frames/left", 1..3).unwrap();
    assert_eq!(images.len(), 2);
    assert_eq!(images[1].data, (2..10).map(|v| v as u8).collect::<Vec<_>>());
    assert_eq!(
        r.log_times("/frames/left", SchemaKind::RawImage).unwrap(),
        vec![1_000_000, 51_000_000, 101_000_000]
    );
    let poses = r.poses("/ground_truth").unwrap();
    assert_eq!(poses[2].translation, [2.0, 0.5, -1.0]);
    assert_eq!(
        r.calibrations("/calibration/frame_left").unwrap()[0].d,
        vec![0.1, 0.2, 0.3, 0.4]
    );
    assert_eq!(
        r.point_clouds("/slam/map").unwrap()[0].points[1],
        [4.0, 5.0, 6.0]
    );
    assert_eq!(r.metadata("dhptam.test").unwrap().unwrap()["k"], "v");
    assert!(r.metadata("absent").unwrap().is_none());
    let info = &r.topics()["/frames/left"];
    assert_eq!(
        (info.schema_name.as_str(), info.message_encoding.as_str()),
        ("foxglove.RawImage", "protobuf")
    );
}

fn format_field(err: Error) -> (String, String) {
    match err {
        Error::Format { path, field, .. } => (path.display().to_string(), field),
        other => panic!("expected a format error, got {other}"),
    }
}

#[test]
fn damaged_logs_name_the_file_and_the_channel() {
    let path = tmp("good.mcap");
    write_log(&path, LogCompression::Zstd);
    let bytes = std::fs::read(&path).unwrap();

    let truncated = tmp("truncated.mcap");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let (p, field) = format_field(LogReader::open(&truncated).err().unwrap());
    assert!(
        p.ends_with("truncated.mcap") && field == "magic",
        "{p} {field}"
    );

    let wrong = tmp("wrong.mcap");
    let mut b = bytes.clone();
    b[1] = b'X';
    std::fs::write(&wrong, &b).unwrap();
    let (_, field) = format_field(LogReader::open(&wrong).err().unwrap());
    assert_eq!(field, "magic");

    let r = LogReader::open(&path).unwrap();
    let (p, field) = format_field(r.event_count("/events/right").unwrap_err());
    assert!(p.ends_with("good.mcap"));
    assert_eq!(field, "/events/right");
    let (_, field) = format_field(r.poses("/frames/left").unwrap_err());
    assert_eq!(field, "/frames/left");
}

#[test]
fn a_writer_dropped_unfinished_leaves_nothing() {
    let path = tmp("dropped.mcap");
    {
        let mut w = LogWriter::create(&path, LogOptions::default()).unwrap();
        w.add_events("/events/left", "e", &[1], &[2], &[3], &[1])
            .unwrap();
        let err = w
            .add_events("/events/left", "e", &[1], &[2], &[2], &[1])
            .unwrap_err();
        assert!(err.to_string().contains("non-decreasing"), "{err}");
    }
    assert!(!path.exists());
    let dir = path.parent().unwrap();
    let leftovers: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with("dropped.mcap"))
        .collect();
    assert!(leftovers.is_empty());
}

#[test]
fn compressed_images_round_trip_beside_raw_ones() {
    let path = tmp("compressed.mcap");
    let mut w = LogWriter::create(&path, LogOptions::default()).unwrap();
    let frames: Vec<CompressedImage> = (0..3)
        .map(|k| CompressedImage {
            t_ns: 10 + k,
            frame_id: "frame_left".into(),
            data: vec![k as u8; 5 + k as usize],
            format: "png".into(),
        })
        .collect();
    for f in &frames {
        w.add_compressed_image("/frames/left", f).unwrap();
    }
    let empty = CompressedImage {
        format: "png".into(),
        ..CompressedImage::default()
    };
    let err = w.add_compressed_image("/frames/left", &empty).unwrap_err();
    assert!(err.to_string().contains("non-empty data"), "{err}");
    w.finish().unwrap();
    let r = LogReader::open(&path).unwrap();
    assert_eq!(r.compressed_images("/frames/left", 0..3).unwrap(), frames);
    assert_eq!(
        r.compressed_images("/frames/left", 2..9).unwrap(),
        frames[2..]
    );
    assert_eq!(
        r.log_times("/frames/left", SchemaKind::CompressedImage)
            .unwrap(),
        vec![10, 11, 12]
    );
    // A compressed channel is not a raw one, and the error says which it is.
    let err = r.images("/frames/left", 0..1).unwrap_err();
    assert!(
        err.to_string().contains("foxglove.CompressedImage"),
        "{err}"
    );
    assert_eq!(format_field(err).1, "/frames/left");
}

#[test]
fn a_chunk_with_an_unknown_compression_names_the_file_and_the_channel() {
    let path = tmp("lz4.mcap");
    write_log(&path, LogCompression::Lz4);
    let mut bytes = std::fs::read(&path).unwrap();
    // Rename the compression of every chunk (and its index entry) to one no reader knows:
    // the string is stored as a u32 length and the name.
    let needle = b"\x03\x00\x00\x00lz4";
    let mut renamed = 0;
    for i in 0..bytes.len() - needle.len() {
        if &bytes[i..i + needle.len()] == needle {
            bytes[i + 6] = b'9';
            renamed += 1;
        }
    }
    assert!(renamed >= 2, "{renamed}");
    let bad = tmp("unknown-compression.mcap");
    std::fs::write(&bad, &bytes).unwrap();
    // Opening reads the last event batch, so the event channel is named.
    let err = LogReader::open(&bad).err().unwrap();
    let message = err.to_string();
    let (p, field) = format_field(err);
    assert!(p.ends_with("unknown-compression.mcap"), "{p}");
    assert_eq!(field, "/events/left");
    assert!(message.contains("lz9"), "{message}");
}

/// Inputs the `mcap` fuzz target once crashed on (`fuzz/regressions/mcap/`): each must open
/// with an error or read consistently.
#[test]
fn fuzz_regressions_are_refused_or_read_consistently() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/regressions/mcap");
    let mut seen = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        seen += 1;
        let reader = match LogReader::open(&path) {
            Err(Error::Format { .. }) => continue,
            Err(other) => panic!("{}: unexpected error kind {other}", path.display()),
            Ok(reader) => reader,
        };
        for (topic, info) in reader.topics() {
            if info.schema_name != SchemaKind::EventBatch.name() {
                continue;
            }
            let count = reader.event_count(topic).unwrap();
            let (t0, t1) = reader.event_time_range(topic).unwrap();
            assert!(count == 0 || t0 < t1, "{}: [{t0}, {t1})", path.display());
        }
    }
    assert!(seen >= 1, "no regression inputs in {}", dir.display());
}

#[test]
fn a_record_longer_than_its_chunk_is_an_error_not_an_allocation_or_a_panic() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/regressions/mcap");
    // A compressed chunk whose message claims 2^56 bytes, and an uncompressed one whose record
    // runs past the chunk's data.
    for (name, expected) in [
        ("record-length-beyond-its-chunk.mcap", "exceeds limit"),
        (
            "record-past-its-uncompressed-chunk.mcap",
            "past the chunk's end",
        ),
        (
            "summary-chunk-record-past-its-end.mcap",
            "past the chunk's end",
        ),
    ] {
        let path = dir.join(name);
        let message = match LogReader::open(&path) {
            Err(err) => err.to_string(),
            // Some channel must fail to read, with an error and not an allocation or a panic.
            Ok(reader) => reader
                .topics()
                .iter()
                .filter_map(|(topic, info)| {
                    let n = info.message_count;
                    match SchemaKind::from_name(&info.schema_name)? {
                        SchemaKind::EventBatch => reader.event_slice(topic, 0, usize::MAX).err(),
                        SchemaKind::RawImage => reader.images(topic, 0..n).err(),
                        SchemaKind::CompressedImage => reader.compressed_images(topic, 0..n).err(),
                        SchemaKind::CameraCalibration => reader.calibrations(topic).err(),
                        SchemaKind::PoseInFrame => reader.poses(topic).err(),
                        SchemaKind::PointCloud => reader.point_clouds(topic).err(),
                    }
                })
                .map(|e| e.to_string())
                .find(|m| m.to_lowercase().contains(expected))
                .unwrap_or_default(),
        };
        assert!(
            message.to_lowercase().contains(expected) && message.contains(name),
            "{name}: {message:?}"
        );
    }
}

#[test]
fn event_batches_whose_log_time_is_not_their_first_event_are_refused() {
    // The first regression input: a batch logged at 16 057 320 ns whose events end at 1 040 ns.
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fuzz/regressions/mcap/batch-log-time-after-its-events.mcap");
    let err = LogReader::open(&path).err().expect("a damaged log");
    let message = err.to_string();
    assert!(message.contains("/events/left"), "{message}");
    assert!(
        message.contains("logged at") && message.contains("ns"),
        "{message}"
    );
}
