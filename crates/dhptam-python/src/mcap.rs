//! MCAP logs: `McapWriter` and `McapReader`, thin wrappers of `dhptam_core::io::mcap`.
//!
//! Event columns go in borrowed (exact dtypes, C-contiguous) and come out as numpy arrays that
//! take over the decoded buffers (no copy). Writing and reading release the GIL.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Mutex;

use dhptam_core::io::mcap::{
    CameraCalibration, CompressedImage, LogCompression, LogOptions, LogReader, LogWriter,
    PointCloud, PoseInFrame, RawImage, SchemaKind,
};
use numpy::ndarray::{Array2, Array3};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArrayDyn, PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict};

use crate::arrays;
use crate::errors::{input_error, DetachGuarded, IntoPyResult};
use crate::events::exact;

/// Writes a dhptam MCAP log; see `dhptam_core::io::mcap` for the layout.
#[pyclass(name = "McapWriter", module = "dhptam._core")]
pub struct PyMcapWriter {
    inner: Mutex<Option<LogWriter>>,
    path: PathBuf,
}

impl PyMcapWriter {
    fn with<T>(
        &self,
        py: Python<'_>,
        f: impl FnOnce(&mut LogWriter) -> dhptam_core::Result<T> + Send,
    ) -> PyResult<T>
    where
        T: Send,
    {
        let mut guard = self
            .inner
            .lock()
            .map_err(|_| input_error("McapWriter", "a usable writer", "a poisoned lock"))?;
        let writer = guard.as_mut().ok_or_else(|| {
            input_error(
                "McapWriter",
                "an open writer",
                format!("a finished or aborted writer of {}", self.path.display()),
            )
        })?;
        py.detach_guarded("McapWriter", || f(writer))?.py()
    }
}

fn schema_kind(name: &str) -> PyResult<SchemaKind> {
    SchemaKind::from_name(name).ok_or_else(|| {
        input_error(
            "schema",
            "one of dhptam.EventBatch, foxglove.RawImage, foxglove.CompressedImage, \
             foxglove.CameraCalibration, foxglove.PoseInFrame, foxglove.PointCloud",
            format!("{name:?}"),
        )
    })
}

#[pymethods]
impl PyMcapWriter {
    /// Starts a log written to a temporary file next to `path`, renamed by `finish()`.
    #[new]
    #[pyo3(signature = (path, compression = "zstd", chunk_size_bytes = 4194304, batch_events = 32768))]
    fn new(
        path: PathBuf,
        compression: &str,
        chunk_size_bytes: u64,
        batch_events: usize,
    ) -> PyResult<Self> {
        let options = LogOptions {
            compression: LogCompression::parse(compression).py()?,
            chunk_size_bytes,
            batch_events,
        };
        let writer = LogWriter::create(&path, options).py()?;
        Ok(PyMcapWriter {
            inner: Mutex::new(Some(writer)),
            path,
        })
    }

    /// Appends events (x, y uint16; t_ns int64 non-decreasing; p int8) to an event channel.
    #[allow(clippy::too_many_arguments)]
    fn add_events(
        &self,
        py: Python<'_>,
        topic: &str,
        frame_id: &str,
        x: PyReadonlyArray1<'_, u16>,
        y: PyReadonlyArray1<'_, u16>,
        t_ns: PyReadonlyArray1<'_, i64>,
        p: PyReadonlyArray1<'_, i8>,
    ) -> PyResult<()> {
        let (x, y, t, p) = (
            exact(&x, "x")?,
            exact(&y, "y")?,
            exact(&t_ns, "t_ns")?,
            exact(&p, "p")?,
        );
        self.with(py, |w| w.add_events(topic, frame_id, x, y, t, p))
    }

    /// Writes an (H, W) uint8 image as `mono8` or an (H, W, 3) one as `rgb8`.
    fn add_image(
        &self,
        py: Python<'_>,
        topic: &str,
        frame_id: &str,
        t_ns: i64,
        image: PyReadonlyArrayDyn<'_, u8>,
    ) -> PyResult<()> {
        let shape = image.shape().to_vec();
        let (height, width, encoding, channels) = match shape.as_slice() {
            [h, w] => (*h, *w, "mono8", 1),
            [h, w, 3] => (*h, *w, "rgb8", 3),
            _ => {
                return Err(input_error(
                    "image",
                    "an (H, W) or (H, W, 3) uint8 array",
                    format!("shape {shape:?}"),
                ))
            }
        };
        let data = match image.as_slice() {
            Ok(s) => s.to_vec(),
            Err(_) => image.as_array().iter().copied().collect(),
        };
        let message = RawImage {
            t_ns,
            frame_id: frame_id.to_owned(),
            width: width as u32,
            height: height as u32,
            encoding: encoding.to_owned(),
            step: (width * channels) as u32,
            data,
        };
        self.with(py, |w| w.add_image(topic, &message))
    }

    /// Writes an image file's bytes (`format` `png` or `jpeg`) as a `foxglove.CompressedImage`.
    fn add_compressed_image(
        &self,
        py: Python<'_>,
        topic: &str,
        frame_id: &str,
        t_ns: i64,
        data: &[u8],
        format: &str,
    ) -> PyResult<()> {
        let message = CompressedImage {
            t_ns,
            frame_id: frame_id.to_owned(),
            data: data.to_vec(),
            format: format.to_owned(),
        };
        self.with(py, |w| w.add_compressed_image(topic, &message))
    }

    /// Writes a `foxglove.CameraCalibration` (K, R row-major 3×3; P row-major 3×4).
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (topic, frame_id, t_ns, width, height, distortion_model, d, k, r, p))]
    fn add_calibration(
        &self,
        py: Python<'_>,
        topic: &str,
        frame_id: &str,
        t_ns: i64,
        width: u32,
        height: u32,
        distortion_model: &str,
        d: Vec<f64>,
        k: Vec<f64>,
        r: Vec<f64>,
        p: Vec<f64>,
    ) -> PyResult<()> {
        let message = CameraCalibration {
            t_ns,
            frame_id: frame_id.to_owned(),
            width,
            height,
            distortion_model: distortion_model.to_owned(),
            d,
            k,
            r,
            p,
        };
        self.with(py, |w| w.add_calibration(topic, &message))
    }

    /// Writes one `foxglove.PoseInFrame` per row of `poses` (N, 7): `x y z qx qy qz qw`.
    fn add_poses(
        &self,
        py: Python<'_>,
        topic: &str,
        frame_id: &str,
        t_ns: PyReadonlyArray1<'_, i64>,
        poses: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let rows = arrays::rows(poses, 7, "poses")?;
        let t = exact(&t_ns, "t_ns")?;
        let rows = rows.as_array();
        if rows.nrows() != t.len() {
            return Err(input_error(
                "poses",
                &format!("one row per timestamp ({})", t.len()),
                format!("{} rows", rows.nrows()),
            ));
        }
        let messages: Vec<PoseInFrame> = t
            .iter()
            .zip(rows.outer_iter())
            .map(|(&t_ns, r)| PoseInFrame {
                t_ns,
                frame_id: frame_id.to_owned(),
                translation: [r[0], r[1], r[2]],
                quat_xyzw: [r[3], r[4], r[5], r[6]],
            })
            .collect();
        self.with(py, |w| {
            messages.iter().try_for_each(|m| w.add_pose(topic, m))
        })
    }

    /// Writes a `foxglove.PointCloud` of (N, 3) points (stored as float32).
    fn add_point_cloud(
        &self,
        py: Python<'_>,
        topic: &str,
        frame_id: &str,
        t_ns: i64,
        points: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let rows = arrays::rows(points, 3, "points")?;
        let message = PointCloud {
            t_ns,
            frame_id: frame_id.to_owned(),
            points: rows
                .as_array()
                .outer_iter()
                .map(|r| [r[0] as f32, r[1] as f32, r[2] as f32])
                .collect(),
        };
        self.with(py, |w| w.add_point_cloud(topic, &message))
    }

    /// Writes a metadata record of string pairs.
    fn add_metadata(
        &self,
        py: Python<'_>,
        name: &str,
        entries: BTreeMap<String, String>,
    ) -> PyResult<()> {
        self.with(py, |w| w.add_metadata(name, entries))
    }

    /// Writes the summary and indexes and moves the log to its path.
    fn finish(&self, py: Python<'_>) -> PyResult<()> {
        let writer = self
            .inner
            .lock()
            .map_err(|_| input_error("McapWriter", "a usable writer", "a poisoned lock"))?
            .take();
        match writer {
            Some(w) => py.detach_guarded("McapWriter.finish", || w.finish())?.py(),
            None => Err(input_error(
                "McapWriter",
                "an open writer",
                "a finished or aborted writer",
            )),
        }
    }

    /// Drops the log: its temporary file is deleted and `path` is left untouched.
    fn abort(&self) -> PyResult<()> {
        if let Ok(mut guard) = self.inner.lock() {
            guard.take();
        }
        Ok(())
    }

    /// The path the finished log will have.
    #[getter]
    fn path(&self) -> PathBuf {
        self.path.clone()
    }
}

/// Reads a dhptam MCAP log through its indexes.
#[pyclass(name = "McapReader", module = "dhptam._core", frozen)]
pub struct PyMcapReader {
    inner: LogReader,
}

#[pymethods]
impl PyMcapReader {
    /// Opens a log and reads its summary and indexes.
    #[new]
    fn new(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let inner = py
            .detach_guarded("McapReader.open", || LogReader::open(&path))?
            .py()?;
        Ok(PyMcapReader { inner })
    }

    /// The log's path.
    #[getter]
    fn path(&self) -> PathBuf {
        self.inner.path().to_path_buf()
    }

    /// Channels by topic: `schema_name`, `schema_encoding`, `message_encoding`, `metadata`,
    /// `message_count`.
    fn topics<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let out = PyDict::new(py);
        for (topic, info) in self.inner.topics() {
            let d = PyDict::new(py);
            d.set_item("schema_name", &info.schema_name)?;
            d.set_item("schema_encoding", &info.schema_encoding)?;
            d.set_item("message_encoding", &info.message_encoding)?;
            d.set_item("metadata", info.metadata.clone())?;
            d.set_item("message_count", info.message_count)?;
            out.set_item(topic, d)?;
        }
        Ok(out)
    }

    /// A metadata record's entries, or None.
    fn metadata(&self, name: &str) -> PyResult<Option<BTreeMap<String, String>>> {
        self.inner.metadata(name).py()
    }

    /// Log times (ns) of a channel's messages; `schema` is checked against the channel's.
    fn log_times<'py>(
        &self,
        py: Python<'py>,
        topic: &str,
        schema: &str,
    ) -> PyResult<Bound<'py, PyArray1<i64>>> {
        let kind = schema_kind(schema)?;
        Ok(self.inner.log_times(topic, kind).py()?.into_pyarray(py))
    }

    /// Images `start .. stop` of a RawImage channel as `(t_ns, frame_id, array)` with arrays
    /// (H, W) for `mono8`, (H, W, 3) for `rgb8`/`bgr8`.
    fn images<'py>(
        &self,
        py: Python<'py>,
        topic: &str,
        start: usize,
        stop: usize,
    ) -> PyResult<Vec<(i64, String, Bound<'py, PyAny>)>> {
        let images = py
            .detach_guarded("McapReader.images", || {
                self.inner.images(topic, start..stop)
            })?
            .py()?;
        images
            .into_iter()
            .map(|m| {
                let (h, w) = (m.height as usize, m.width as usize);
                let channels = match m.encoding.as_str() {
                    "mono8" => 1,
                    "rgb8" | "bgr8" => 3,
                    other => {
                        return Err(input_error(
                            &format!("{topic} encoding"),
                            "mono8, rgb8 or bgr8",
                            other,
                        ))
                    }
                };
                let (len, step) = (m.data.len(), m.step);
                let mismatch = move |_: ()| {
                    input_error(
                        &format!("{topic} image"),
                        &format!("{h}×{w}×{channels} bytes with step {}", w * channels),
                        format!("{len} bytes, step {step}"),
                    )
                };
                if m.step as usize != w * channels {
                    return Err(mismatch(()));
                }
                let array = if channels == 1 {
                    Array2::from_shape_vec((h, w), m.data)
                        .map_err(|_| mismatch(()))?
                        .into_pyarray(py)
                        .into_any()
                } else {
                    Array3::from_shape_vec((h, w, 3), m.data)
                        .map_err(|_| mismatch(()))?
                        .into_pyarray(py)
                        .into_any()
                };
                Ok((m.t_ns, m.frame_id, array))
            })
            .collect()
    }

    /// Images `start .. stop` of a CompressedImage channel as `(t_ns, frame_id, format, data)`,
    /// `data` the image file's bytes (decode with OpenCV or PIL).
    fn compressed_images<'py>(
        &self,
        py: Python<'py>,
        topic: &str,
        start: usize,
        stop: usize,
    ) -> PyResult<Vec<(i64, String, String, Bound<'py, PyBytes>)>> {
        let images = py
            .detach_guarded("McapReader.compressed_images", || {
                self.inner.compressed_images(topic, start..stop)
            })?
            .py()?;
        Ok(images
            .into_iter()
            .map(|m| (m.t_ns, m.frame_id, m.format, PyBytes::new(py, &m.data)))
            .collect())
    }

    /// Every pose of a PoseInFrame channel: `(t_ns, poses (N, 7) x y z qx qy qz qw, frame_ids)`.
    fn poses<'py>(
        &self,
        py: Python<'py>,
        topic: &str,
    ) -> PyResult<(
        Bound<'py, PyArray1<i64>>,
        Bound<'py, PyArray2<f64>>,
        Vec<String>,
    )> {
        let poses = py
            .detach_guarded("McapReader.poses", || self.inner.poses(topic))?
            .py()?;
        let t: Vec<i64> = poses.iter().map(|m| m.t_ns).collect();
        let mut rows = Array2::<f64>::zeros((poses.len(), 7));
        for (i, m) in poses.iter().enumerate() {
            for j in 0..3 {
                rows[[i, j]] = m.translation[j];
            }
            for j in 0..4 {
                rows[[i, 3 + j]] = m.quat_xyzw[j];
            }
        }
        let frames = poses.into_iter().map(|m| m.frame_id).collect();
        Ok((t.into_pyarray(py), rows.into_pyarray(py), frames))
    }

    /// Every CameraCalibration message as a dict (`t_ns`, `frame_id`, `width`, `height`,
    /// `distortion_model`, `D`, `K`, `R`, `P`).
    fn calibrations<'py>(&self, py: Python<'py>, topic: &str) -> PyResult<Vec<Bound<'py, PyDict>>> {
        let messages = py
            .detach_guarded("McapReader.calibrations", || self.inner.calibrations(topic))?
            .py()?;
        messages
            .into_iter()
            .map(|m| {
                let d = PyDict::new(py);
                d.set_item("t_ns", m.t_ns)?;
                d.set_item("frame_id", m.frame_id)?;
                d.set_item("width", m.width)?;
                d.set_item("height", m.height)?;
                d.set_item("distortion_model", m.distortion_model)?;
                d.set_item("D", m.d)?;
                d.set_item("K", m.k)?;
                d.set_item("R", m.r)?;
                d.set_item("P", m.p)?;
                Ok(d)
            })
            .collect()
    }

    /// Every PointCloud message as `(t_ns, frame_id, points (N, 3) float32)`.
    fn point_clouds<'py>(
        &self,
        py: Python<'py>,
        topic: &str,
    ) -> PyResult<Vec<(i64, String, Bound<'py, PyArray2<f32>>)>> {
        let clouds = py
            .detach_guarded("McapReader.point_clouds", || self.inner.point_clouds(topic))?
            .py()?;
        Ok(clouds
            .into_iter()
            .map(|c| {
                let n = c.points.len();
                let flat: Vec<f32> = c.points.into_iter().flatten().collect();
                let array = Array2::from_shape_vec((n, 3), flat)
                    .unwrap_or_else(|_| Array2::zeros((0, 3)))
                    .into_pyarray(py);
                (c.t_ns, c.frame_id, array)
            })
            .collect())
    }

    /// Number of events of an event channel.
    fn event_count(&self, topic: &str) -> PyResult<usize> {
        self.inner.event_count(topic).py()
    }

    /// Half-open `[first, last + 1)` span of an event channel's times, ns.
    fn event_time_range(&self, topic: &str) -> PyResult<(i64, i64)> {
        self.inner.event_time_range(topic).py()
    }

    /// Indices `[i0, i1)` of the events with `t0_ns <= t < t1_ns`.
    fn event_index_range(
        &self,
        py: Python<'_>,
        topic: &str,
        t0_ns: i64,
        t1_ns: i64,
    ) -> PyResult<(usize, usize)> {
        py.detach_guarded("McapReader.event_index_range", || {
            self.inner.event_index_range(topic, t0_ns, t1_ns)
        })?
        .py()
    }

    /// Events `i0 .. i1 - 1` as `(x uint16, y uint16, t_ns int64, p int8)`.
    fn event_slice<'py>(
        &self,
        py: Python<'py>,
        topic: &str,
        i0: usize,
        i1: usize,
    ) -> PyResult<(
        Bound<'py, PyArray1<u16>>,
        Bound<'py, PyArray1<u16>>,
        Bound<'py, PyArray1<i64>>,
        Bound<'py, PyArray1<i8>>,
    )> {
        let e = py
            .detach_guarded("McapReader.event_slice", || {
                self.inner.event_slice(topic, i0, i1)
            })?
            .py()?;
        Ok((
            e.x.into_pyarray(py),
            e.y.into_pyarray(py),
            e.t_ns.into_pyarray(py),
            e.p.into_pyarray(py),
        ))
    }
}
