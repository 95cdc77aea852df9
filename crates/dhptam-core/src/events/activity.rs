//! How much of an event window is scene structure rather than sensor noise.
//!
//! A moving camera's events line up along the edges of the scene, so a pixel that fired
//! mostly has a neighbour that fired too. A camera at rest sees only its noise, whose pixels
//! fire independently of each other: a noise pixel has a firing neighbour about as often as
//! chance allows at that density. [`activity`] counts, over one window, the pixels that
//! fired (`active`) and those among them with at least one firing pixel among their eight
//! neighbours (`supported`); [`Activity::structured_share`] is the excess of `supported` over
//! what independent pixels at the same density would give, as a share of the sensor. That
//! share is near zero for noise alone, whatever the noise rate, and grows with the edges in
//! view, with no history needed (the front-end's quiet windows, `[fusion] quiet_structure`).

use crate::error::{Error, Result};

/// Pixel activity of one event window on one sensor (see the module's docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Activity {
    /// Pixels of the sensor.
    pub pixels: u64,
    /// Pixels with at least one event.
    pub active: u64,
    /// Active pixels with at least one active pixel among their eight neighbours.
    pub supported: u64,
}

impl Activity {
    /// Share of the sensor's pixels that are active.
    pub fn active_share(&self) -> f64 {
        if self.pixels == 0 {
            return 0.0;
        }
        self.active as f64 / self.pixels as f64
    }

    /// Chance that at least one of a pixel's eight neighbours is active when active pixels
    /// are spread independently at the window's density.
    pub fn chance_support(&self) -> f64 {
        1.0 - (1.0 - self.active_share()).powi(8)
    }

    /// Active pixels supported beyond chance, as a share of the sensor's pixels:
    /// `(supported − active · chance) / pixels`. About zero for noise, about the share of
    /// pixels on moving edges for a moving camera; it loses its meaning when most pixels are
    /// active (chance near one), which only a busy window reaches.
    pub fn structured_share(&self) -> f64 {
        if self.pixels == 0 {
            return 0.0;
        }
        (self.supported as f64 - self.active as f64 * self.chance_support()) / self.pixels as f64
    }
}

/// Counts the active and supported pixels of a window with events at pixels `(x, y)` on a
/// `width × height` sensor. An event outside the sensor is an error naming it.
pub fn activity(x: &[u16], y: &[u16], width: u32, height: u32) -> Result<Activity> {
    if x.len() != y.len() {
        return Err(Error::invalid(
            "event window",
            "x and y of equal length",
            format!("{} and {}", x.len(), y.len()),
        ));
    }
    let (w, h) = (width as usize, height as usize);
    if let Some(k) = (0..x.len()).find(|&k| usize::from(x[k]) >= w || usize::from(y[k]) >= h) {
        return Err(Error::invalid(
            format!("event {k}"),
            format!("a pixel inside the {w}×{h} sensor"),
            format!("({}, {})", x[k], y[k]),
        ));
    }
    // A one-pixel frame of inactive pixels around the sensor: every neighbour is in bounds.
    let stride = w + 2;
    let mut fired = vec![0u8; stride * (h + 2)];
    for (&u, &v) in x.iter().zip(y) {
        fired[(usize::from(v) + 1) * stride + usize::from(u) + 1] = 1;
    }
    // Row by row, branch-free (the compiler vectorises it): a pixel is supported when it
    // fired and any of the eight around it did.
    let (mut active, mut supported) = (0u64, 0u64);
    for row in 1..=h {
        let (up, here, down) = (
            &fired[(row - 1) * stride..row * stride],
            &fired[row * stride..(row + 1) * stride],
            &fired[(row + 1) * stride..(row + 2) * stride],
        );
        let (mut a, mut s) = (0u32, 0u32);
        let columns = up.windows(3).zip(here.windows(3)).zip(down.windows(3));
        for ((u, c), d) in columns {
            let around = u[0] | u[1] | u[2] | c[0] | c[2] | d[0] | d[1] | d[2];
            a += u32::from(c[1]);
            s += u32::from(c[1] & around);
        }
        active += u64::from(a);
        supported += u64::from(s);
    }
    Ok(Activity {
        pixels: (w * h) as u64,
        active,
        supported,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    use rand::{rngs::StdRng, Rng, SeedableRng};

    /// `n` pixels drawn independently and uniformly: sensor noise.
    fn scattered(n: usize, w: u16, h: u16) -> (Vec<u16>, Vec<u16>) {
        let mut rng = StdRng::seed_from_u64(5);
        (0..n)
            .map(|_| (rng.random_range(0..w), rng.random_range(0..h)))
            .unzip()
    }

    #[test]
    fn counts_active_and_supported_pixels() {
        // A lone pixel, a pair of diagonal neighbours, a repeated event, the sensor's corner.
        let x = [1, 5, 6, 5, 9];
        let y = [1, 5, 6, 5, 9];
        let a = activity(&x, &y, 10, 10).unwrap();
        assert_eq!((a.pixels, a.active, a.supported), (100, 4, 2));
    }

    #[test]
    fn edges_are_structure_and_independent_noise_is_not() {
        let (w, h) = (320u16, 180u16);
        let (nx, ny) = scattered(2000, w, h);
        let noise = activity(&nx, &ny, w.into(), h.into()).unwrap();
        assert!(noise.active > 1900, "{noise:?}");
        // Noise: supported about as often as chance gives, a tiny share of the sensor.
        assert!(noise.structured_share().abs() < 0.002, "{noise:?}");
        // Two vertical edges, 150 pixels long: alone, all of their pixels are structure; in
        // the noise, over half of them are (their own pixels raise the density, hence chance).
        let (mut ex, mut ey) = (Vec::new(), Vec::new());
        for v in 10..160u16 {
            ex.extend([100, 200]);
            ey.extend([v, v]);
        }
        let edge_share = 300.0 / (f64::from(w) * f64::from(h));
        let alone = activity(&ex, &ey, w.into(), h.into()).unwrap();
        assert!(
            (alone.structured_share() - edge_share).abs() < 0.05 * edge_share,
            "{alone:?}"
        );
        let (x, y) = ([nx, ex].concat(), [ny, ey].concat());
        let both = activity(&x, &y, w.into(), h.into()).unwrap();
        let gained = both.structured_share() - noise.structured_share();
        assert!(
            gained > 0.5 * edge_share && gained < edge_share,
            "{gained} vs {edge_share}"
        );
    }

    #[test]
    fn an_empty_window_has_no_activity() {
        let a = activity(&[], &[], 4, 3).unwrap();
        assert_eq!((a.pixels, a.active, a.supported), (12, 0, 0));
        assert_eq!(a.structured_share(), 0.0);
    }

    #[test]
    fn a_pixel_outside_the_sensor_is_named() {
        let e = activity(&[0, 4], &[0, 0], 4, 3).unwrap_err().to_string();
        assert!(e.contains("event 1") && e.contains("4×3"), "{e}");
        assert!(activity(&[0], &[], 4, 3).is_err());
    }
}
