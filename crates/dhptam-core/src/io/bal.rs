//! BAL ("Bundle Adjustment in the Large", Agarwal et al. 2010) problem files.
//!
//! Layout: a header `cameras points observations`; one line per observation
//! `camera point x y`; then 9 numbers per camera and 3 per point, whitespace separated (one
//! per line in the published files). A camera is the Snavely model: angle-axis ω, translation
//! t, focal f, radial k1, k2, projecting a world point X by
//!
//! ```text
//! P = R(ω) X + t,   p = −P_xy / P_z,   pixel = f (1 + k1‖p‖² + k2‖p‖⁴) p
//! ```
//!
//! with the pixel origin at the principal point and y up.

use std::fmt::Write as _;
use std::path::Path;

use super::text::{read_to_string, write_atomically, Line};
use crate::error::{Error, Result};

/// One observation of a point by a camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BalObservation {
    /// Camera index.
    pub camera: usize,
    /// Point index.
    pub point: usize,
    /// Measured pixel (x, y), principal point at the origin.
    pub pixel: [f64; 2],
}

/// A whole BAL problem.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BalProblem {
    /// Cameras `[ω (3), t (3), f, k1, k2]`.
    pub cameras: Vec<[f64; 9]>,
    /// World points.
    pub points: Vec<[f64; 3]>,
    /// Observations, in file order.
    pub observations: Vec<BalObservation>,
}

impl BalProblem {
    /// Reads a BAL file.
    pub fn read(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let text = read_to_string(path)?;
        Self::parse(path, &text)
    }

    /// Parses BAL text; `path` only names the source in errors.
    pub fn parse(path: &Path, text: &str) -> Result<Self> {
        let mut lines = text
            .lines()
            .enumerate()
            .map(|(i, l)| (i + 1, l))
            .filter(|(_, l)| !l.trim().is_empty());
        let end_error = |what: &str| Error::Parse {
            path: path.to_path_buf(),
            line: text.lines().count().max(1),
            message: format!("file ends before {what}"),
        };
        let (n, header) = lines.next().ok_or_else(|| end_error("the header"))?;
        let mut line = Line::new(path, n, header);
        let n_cameras = line.index("camera count", None)?;
        let n_points = line.index("point count", None)?;
        let n_observations = line.index("observation count", None)?;
        line.finish()?;
        // Counts beyond the file size would only allocate memory for nothing.
        let bound = text.len() / 2 + 1;
        if n_cameras.max(n_points).max(n_observations) > bound {
            return Err(Error::Parse {
                path: path.to_path_buf(),
                line: n,
                message: "counts larger than the file can hold".into(),
            });
        }
        let mut observations = Vec::with_capacity(n_observations);
        for k in 0..n_observations {
            let (n, l) = lines
                .next()
                .ok_or_else(|| end_error(&format!("observation {k}")))?;
            let mut line = Line::new(path, n, l);
            let camera = line.index("camera index", Some(n_cameras))?;
            let point = line.index("point index", Some(n_points))?;
            let x = line.float("pixel x")?;
            let y = line.float("pixel y")?;
            line.finish()?;
            observations.push(BalObservation {
                camera,
                point,
                pixel: [x, y],
            });
        }
        // Parameters: a stream of numbers, whatever the line breaks.
        let total = 9 * n_cameras + 3 * n_points;
        let mut params = Vec::with_capacity(total);
        for (n, l) in lines {
            let mut line = Line::new(path, n, l);
            while params.len() < total {
                match line.float("parameter") {
                    Ok(v) => params.push(v),
                    Err(Error::Parse { message, .. }) if message == "missing parameter" => break,
                    Err(e) => return Err(e),
                }
            }
            if params.len() == total {
                line.finish()?;
            }
        }
        if params.len() < total {
            return Err(end_error(&format!(
                "all {total} camera and point parameters (found {})",
                params.len()
            )));
        }
        let cameras = params[..9 * n_cameras]
            .chunks_exact(9)
            .map(|c| <[f64; 9]>::try_from(c).unwrap_or_default())
            .collect();
        let points = params[9 * n_cameras..]
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        Ok(Self {
            cameras,
            points,
            observations,
        })
    }

    /// The problem as BAL text.
    pub fn to_text(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "{} {} {}",
            self.cameras.len(),
            self.points.len(),
            self.observations.len()
        );
        for o in &self.observations {
            let _ = writeln!(
                s,
                "{} {} {:e} {:e}",
                o.camera, o.point, o.pixel[0], o.pixel[1]
            );
        }
        for v in self
            .cameras
            .iter()
            .flatten()
            .chain(self.points.iter().flatten())
        {
            let _ = writeln!(s, "{v:e}");
        }
        s
    }

    /// Writes the problem as a BAL file.
    pub fn write(&self, path: impl AsRef<Path>) -> Result<()> {
        write_atomically(path.as_ref(), &self.to_text())
    }
}
