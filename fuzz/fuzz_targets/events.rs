//! Event decoding: arbitrary event arrays (any pixel, time, polarity, order) and windows go
//! through `EventSlice` validation and every event representation. Each call returns a
//! result or `Error::InvalidInput`, never panics; accepted windows give finite images of the
//! promised size.
#![no_main]

use dhptam_core::events::e3ct::{e3ct, E3ctParams, PolarityMode};
use dhptam_core::events::{count_image, time_surface, voxel_grid, EventSlice};
use libfuzzer_sys::fuzz_target;

/// Bytes per fuzzed event: x u16, y u16, t i64 (ns), p i8.
const EVENT_BYTES: usize = 13;

fuzz_target!(|data: &[u8]| {
    if data.len() < 19 {
        return;
    }
    // Header: sensor size kept small (1..=64) so each run stays cheap; window bounds free.
    let width = u32::from(data[0] % 64) + 1;
    let height = u32::from(data[1] % 64) + 1;
    let t_start_ns = i64::from_le_bytes(data[2..10].try_into().unwrap_or_default());
    let t_end_ns = i64::from_le_bytes(data[10..18].try_into().unwrap_or_default());
    let flags = data[18];
    let body = &data[19..];
    let n = body.len() / EVENT_BYTES;
    let (mut x, mut y, mut t, mut p) = (vec![], vec![], vec![], vec![]);
    for e in body.chunks_exact(EVENT_BYTES).take(n) {
        x.push(u16::from_le_bytes([e[0], e[1]]));
        y.push(u16::from_le_bytes([e[2], e[3]]));
        t.push(i64::from_le_bytes(e[4..12].try_into().unwrap_or_default()));
        p.push(e[12] as i8);
    }
    // Mismatched lengths are an input error too: sometimes drop the last polarity.
    if flags & 0x80 != 0 {
        p.pop();
    }
    let Ok(events) = EventSlice::new(&x, &y, &t, &p) else {
        return;
    };
    let pixels = (width * height) as usize;
    let polarity = if flags & 1 == 0 {
        PolarityMode::Both
    } else {
        PolarityMode::Split
    };
    let params = E3ctParams {
        polarity,
        ..E3ctParams::default()
    };
    if let Ok(img) = e3ct(&events, width, height, t_start_ns, t_end_ns, &params) {
        assert_eq!(img.len(), pixels * params.output_channels());
        assert!(img.iter().all(|v| v.is_finite() && *v >= 0.0));
    }
    if let Ok(img) = count_image(&events, width, height, t_start_ns, t_end_ns, polarity) {
        assert!(img.iter().all(|v| v.is_finite()));
    }
    let tau_ms = f64::from(flags >> 1 & 0x3f) * 0.5;
    if let Ok(img) = time_surface(&events, width, height, t_start_ns, t_end_ns, tau_ms) {
        assert!(img.iter().all(|v| v.is_finite()));
    }
    let bins = usize::from(flags >> 2 & 0x1f);
    if let Ok(img) = voxel_grid(&events, width, height, t_start_ns, t_end_ns, bins) {
        assert_eq!(img.len(), pixels * bins);
        assert!(img.iter().all(|v| v.is_finite()));
    }
});
