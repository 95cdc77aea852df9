//! Saving and loading a map with the tracker state: a little-endian binary file.
//!
//! Layout: the magic `DHPTAMAP`, a `u32` version (6), the calibration, the descriptor kind
//! and width, the tracker state, the id counters, the keyframes (per keypoint x, y, u_right
//! and, since version 3, its σ), the map points, the loops, the trajectory (since version 4
//! with a flag per record: 0 measured, 1 predicted, 2 held at rest; since version 5 with the camera centre's covariance when
//! the tracker measured one: a flag and the upper triangle, 6 × f64) and (since version 2) the first keyframes of unjoined
//! map segments; since version 6 each keypoint also stores its viewpoint (3 × f32, see
//! `Keyframe::viewpoints`) after its σ; a map without viewpoints (all zero) is written as
//! version 5. Version-1 files (no segment list), version-2 files
//! (no σ: 1 px each), version-3 files (no predicted flags: every record measured),
//! version-4 files (no covariances) and version-5 files (no viewpoints: every keypoint the
//! frame cameras') are still read. Poses are stored as
//! translation (3 × f64) and quaternion x-y-z-w (4 × f64) of `world_from_cam` /
//! `kf_from_cam`. The file is written to `<path>.tmp` and
//! renamed, so a crash never leaves a truncated map under the final name.

use std::collections::BTreeMap;
use std::io::{BufWriter, Read, Write};
use std::path::Path;

use nalgebra::{Matrix3, Vector3};

use super::map::{FrameRecord, Keyframe, Map, MapPoint};
use super::tracking::TrackerState;
use super::StereoCalibration;
use crate::error::{Error, Result};
use crate::geometry::Se3;
use crate::matching::{DescriptorKind, Descriptors, OwnedDescriptors};

const MAGIC: &[u8; 8] = b"DHPTAMAP";
const VERSION: u32 = 6;

/// The stored entries (row, column) of a symmetric 3×3 covariance: its upper triangle.
const COV_ENTRIES: [(usize, usize); 6] = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)];

struct Writer(Vec<u8>);

impl Writer {
    fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn i64(&mut self, v: i64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn vec3(&mut self, v: &Vector3<f64>) {
        (0..3).for_each(|i| self.f64(v[i]));
    }
    fn se3(&mut self, p: &Se3) {
        self.vec3(&p.translation);
        p.rotation
            .to_quaternion_xyzw()
            .iter()
            .for_each(|&q| self.f64(q));
    }
    fn descriptors(&mut self, d: Descriptors) {
        match d {
            Descriptors::Float { data, .. } => {
                self.u64(data.len() as u64);
                data.iter().for_each(|&v| self.f32(v));
            }
            Descriptors::Binary { data, .. } => {
                self.u64(data.len() as u64);
                self.0.extend_from_slice(data);
            }
        }
    }
}

struct Reader<'a> {
    data: &'a [u8],
    at: usize,
    path: &'a Path,
}

impl Reader<'_> {
    fn bytes(&mut self, n: usize) -> Result<&[u8]> {
        if self.data.len() - self.at < n {
            return Err(Error::Parse {
                path: self.path.to_owned(),
                line: 0,
                message: format!(
                    "truncated map file: {n} more bytes needed at byte {}",
                    self.at
                ),
            });
        }
        let s = &self.data[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8> {
        Ok(self.bytes(1)?[0])
    }
    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(
            self.bytes(4)?.try_into().unwrap_or([0; 4]),
        ))
    }
    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(
            self.bytes(8)?.try_into().unwrap_or([0; 8]),
        ))
    }
    fn i64(&mut self) -> Result<i64> {
        Ok(i64::from_le_bytes(
            self.bytes(8)?.try_into().unwrap_or([0; 8]),
        ))
    }
    fn f32(&mut self) -> Result<f32> {
        Ok(f32::from_le_bytes(
            self.bytes(4)?.try_into().unwrap_or([0; 4]),
        ))
    }
    fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_le_bytes(
            self.bytes(8)?.try_into().unwrap_or([0; 8]),
        ))
    }
    fn len(&mut self, what: &str) -> Result<usize> {
        let n = self.u64()?;
        // Every element takes at least one byte: a larger count is a corrupt file.
        if n as usize > self.data.len() - self.at {
            return Err(self.corrupt(&format!("{what} count {n} exceeds the file size")));
        }
        Ok(n as usize)
    }
    fn vec3(&mut self) -> Result<Vector3<f64>> {
        Ok(Vector3::new(self.f64()?, self.f64()?, self.f64()?))
    }
    fn se3(&mut self) -> Result<Se3> {
        let t = self.vec3()?;
        let q = [self.f64()?, self.f64()?, self.f64()?, self.f64()?];
        Se3::from_translation_quaternion_xyzw([t.x, t.y, t.z], q)
            .map_err(|e| self.corrupt(&format!("bad pose: {e}")))
    }
    fn corrupt(&self, message: &str) -> Error {
        Error::Parse {
            path: self.path.to_owned(),
            line: 0,
            message: format!("corrupt map file at byte {}: {message}", self.at),
        }
    }
    fn descriptors(&mut self, kind: DescriptorKind, width: usize) -> Result<OwnedDescriptors> {
        let n = self.len("descriptor values")?;
        if width == 0 || n % width != 0 {
            return Err(self.corrupt("descriptor data is not whole rows"));
        }
        let d = match kind {
            DescriptorKind::Float => {
                let mut v = Vec::with_capacity(n);
                for _ in 0..n {
                    v.push(self.f32()?);
                }
                Descriptors::float(&v, width)?.to_owned()
            }
            DescriptorKind::Binary => Descriptors::binary(self.bytes(n)?, width)?.to_owned(),
        };
        Ok(d)
    }
}

fn kind_code(kind: DescriptorKind) -> u8 {
    match kind {
        DescriptorKind::Float => 0,
        DescriptorKind::Binary => 1,
    }
}

/// Writes a map with the tracker state.
pub(crate) fn save(
    path: &Path,
    calib: &StereoCalibration,
    descriptor: Option<(DescriptorKind, usize)>,
    map: &Map,
    state: &TrackerState,
) -> Result<()> {
    let mut w = Writer(Vec::new());
    w.0.extend_from_slice(MAGIC);
    // A map whose keypoints are all the frame cameras' own is written as version 5, which
    // builds from before viewpoints read too.
    let with_viewpoints = map
        .keyframes
        .values()
        .any(|k| k.viewpoints.iter().any(|c| *c != [0.0; 3]));
    w.u32(if with_viewpoints { VERSION } else { 5 });
    for v in [calib.fx, calib.fy, calib.cx, calib.cy, calib.baseline_m] {
        w.f64(v);
    }
    w.u32(calib.width);
    w.u32(calib.height);
    let (kind, width) = descriptor.unwrap_or((DescriptorKind::Float, 0));
    w.u8(descriptor.is_some() as u8);
    w.u8(kind_code(kind));
    w.u64(width as u64);
    // Tracker state.
    w.u8(state.last.is_some() as u8);
    if let Some(r) = &state.last {
        w.i64(r.t_ns);
        w.u64(r.keyframe);
        w.se3(&r.kf_from_cam);
    }
    w.se3(&state.velocity);
    w.u8(state.reference.is_some() as u8);
    w.u64(state.reference.unwrap_or(0));
    w.u8(state.lost as u8);
    // Map.
    w.u64(map.next_keyframe);
    w.u64(map.next_point);
    w.u64(map.keyframes.len() as u64);
    for k in map.keyframes.values() {
        w.u64(k.id);
        w.i64(k.t_ns);
        w.se3(&k.world_from_cam);
        w.u64(k.keypoints.len() as u64);
        let per_keypoint = k.keypoints.iter().zip(&k.u_right).zip(&k.sigmas);
        for (((p, ur), sigma), c) in per_keypoint.zip(&k.viewpoints) {
            w.f32(p[0]);
            w.f32(p[1]);
            w.f32(*ur);
            w.f32(*sigma);
            if with_viewpoints {
                for v in c {
                    w.f32(*v);
                }
            }
        }
        w.descriptors(k.descriptors.view());
        for p in &k.points {
            w.u64(p.map_or(u64::MAX, |p| p));
        }
        w.u64(k.covisible.len() as u64);
        for (o, c) in &k.covisible {
            w.u64(*o);
            w.u32(*c);
        }
        w.u64(k.tracked as u64);
    }
    w.u64(map.points.len() as u64);
    for p in map.points.values() {
        w.u64(p.id);
        w.vec3(&p.position);
        w.descriptors(p_descriptor(p));
        w.u64(p.observations.len() as u64);
        for (k, f) in &p.observations {
            w.u64(*k);
            w.u32(*f);
        }
        w.vec3(&p.normal);
        w.u64(p.first_keyframe);
    }
    w.u64(map.loops.len() as u64);
    for (a, b) in &map.loops {
        w.u64(*a);
        w.u64(*b);
    }
    w.u64(map.trajectory.len() as u64);
    for r in &map.trajectory {
        w.i64(r.t_ns);
        w.u64(r.keyframe);
        w.se3(&r.kf_from_cam);
        // 0 measured, 1 predicted, 2 held at rest (read as predicted by builds before it).
        w.u8(if r.held { 2 } else { r.predicted as u8 });
        match &r.position_cov {
            Some(c) => {
                w.u8(1);
                for (i, j) in COV_ENTRIES {
                    w.f64(c[(i, j)]);
                }
            }
            None => w.u8(0),
        }
    }
    w.u64(map.segment_starts.len() as u64);
    for s in &map.segment_starts {
        w.u64(*s);
    }
    let tmp = path.with_extension("tmp");
    let io = |action: &'static str, p: &Path| {
        let p = p.to_owned();
        move |source| Error::Io {
            action,
            path: p,
            source,
        }
    };
    let file = std::fs::File::create(&tmp).map_err(io("create", &tmp))?;
    let mut out = BufWriter::new(file);
    out.write_all(&w.0).map_err(io("write", &tmp))?;
    out.flush().map_err(io("write", &tmp))?;
    drop(out);
    std::fs::rename(&tmp, path).map_err(io("write", path))
}

fn p_descriptor(p: &MapPoint) -> Descriptors<'_> {
    match &p.descriptor {
        crate::matching::OwnedDescriptor::Float(v) => Descriptors::Float {
            dim: v.len().max(1),
            data: v,
        },
        crate::matching::OwnedDescriptor::Binary(v) => Descriptors::Binary {
            bytes: v.len().max(1),
            data: v,
        },
    }
}

/// The contents of a saved map.
pub(crate) type Loaded = (
    StereoCalibration,
    Option<(DescriptorKind, usize)>,
    Map,
    TrackerState,
);

/// Reads a map written by [`save`].
pub(crate) fn load(path: &Path) -> Result<Loaded> {
    let mut data = Vec::new();
    std::fs::File::open(path)
        .and_then(|mut f| f.read_to_end(&mut data))
        .map_err(|source| Error::Io {
            action: "read",
            path: path.to_owned(),
            source,
        })?;
    let mut r = Reader {
        data: &data,
        at: 0,
        path,
    };
    if r.bytes(8)? != MAGIC {
        return Err(r.corrupt("not a dhptam map (magic DHPTAMAP missing)"));
    }
    let version = r.u32()?;
    if !(1..=VERSION).contains(&version) {
        return Err(r.corrupt(&format!(
            "map version {version}, this build reads 1 to {VERSION}"
        )));
    }
    let calib = StereoCalibration {
        fx: r.f64()?,
        fy: r.f64()?,
        cx: r.f64()?,
        cy: r.f64()?,
        baseline_m: r.f64()?,
        width: r.u32()?,
        height: r.u32()?,
    };
    let has_descriptor = r.u8()? != 0;
    let kind = match r.u8()? {
        0 => DescriptorKind::Float,
        1 => DescriptorKind::Binary,
        k => return Err(r.corrupt(&format!("descriptor kind {k}"))),
    };
    let width = r.u64()? as usize;
    let descriptor = has_descriptor.then_some((kind, width));
    let last = if r.u8()? != 0 {
        Some(FrameRecord {
            t_ns: r.i64()?,
            keyframe: r.u64()?,
            kf_from_cam: r.se3()?,
            predicted: false,
            held: false,
            position_cov: None,
        })
    } else {
        None
    };
    let velocity = r.se3()?;
    let has_reference = r.u8()? != 0;
    let reference = r.u64()?;
    let state = TrackerState {
        last,
        velocity,
        reference: has_reference.then_some(reference),
        lost: r.u8()? != 0,
        // Not saved: a loaded map resumes from its last frame as a measured one.
        measured: last,
        // Not saved either: a loaded map's velocity counts as measured.
        velocity_relocalised: false,
        fresh_segment: false,
        at_rest: false,
    };
    let mut map = Map {
        next_keyframe: r.u64()?,
        next_point: r.u64()?,
        ..Default::default()
    };
    let n = r.len("keyframe")?;
    for _ in 0..n {
        let id = r.u64()?;
        let t_ns = r.i64()?;
        let world_from_cam = r.se3()?;
        let m = r.len("keypoint")?;
        let (mut keypoints, mut u_right) = (Vec::with_capacity(m), Vec::with_capacity(m));
        let mut sigmas = Vec::with_capacity(m);
        let mut viewpoints = Vec::with_capacity(m);
        for _ in 0..m {
            keypoints.push([r.f32()?, r.f32()?]);
            u_right.push(r.f32()?);
            let sigma = if version >= 3 { r.f32()? } else { 1.0 };
            if !(sigma.is_finite() && sigma > 0.0) {
                return Err(r.corrupt(&format!("keyframe {id}: keypoint σ {sigma}")));
            }
            sigmas.push(sigma);
            let c = if version >= 6 {
                [r.f32()?, r.f32()?, r.f32()?]
            } else {
                [0.0; 3]
            };
            if !c.iter().all(|v| v.is_finite()) {
                return Err(r.corrupt(&format!("keyframe {id}: keypoint viewpoint {c:?}")));
            }
            viewpoints.push(c);
        }
        let descriptors = r.descriptors(kind, width)?;
        if descriptors.view().len() != m {
            return Err(r.corrupt(&format!("keyframe {id}: descriptor rows ≠ keypoints")));
        }
        let mut points = Vec::with_capacity(m);
        for _ in 0..m {
            let p = r.u64()?;
            points.push((p != u64::MAX).then_some(p));
        }
        let c = r.len("covisibility")?;
        let mut covisible = BTreeMap::new();
        for _ in 0..c {
            covisible.insert(r.u64()?, r.u32()?);
        }
        let tracked = r.u64()? as usize;
        map.keyframes.insert(
            id,
            Keyframe {
                id,
                t_ns,
                world_from_cam,
                keypoints,
                u_right,
                sigmas,
                viewpoints,
                descriptors,
                points,
                covisible,
                tracked,
            },
        );
    }
    let n = r.len("map point")?;
    for _ in 0..n {
        let id = r.u64()?;
        let position = r.vec3()?;
        let d = r.descriptors(kind, width)?;
        if d.view().len() != 1 {
            return Err(r.corrupt(&format!("map point {id}: not one descriptor")));
        }
        let descriptor = d.view().row(0).to_owned();
        let m = r.len("observation")?;
        let mut observations = BTreeMap::new();
        for _ in 0..m {
            observations.insert(r.u64()?, r.u32()?);
        }
        map.points.insert(
            id,
            MapPoint {
                id,
                position,
                descriptor,
                observations,
                normal: r.vec3()?,
                first_keyframe: r.u64()?,
            },
        );
    }
    let n = r.len("loop")?;
    for _ in 0..n {
        map.loops.push((r.u64()?, r.u64()?));
    }
    let n = r.len("trajectory record")?;
    for _ in 0..n {
        let (t_ns, keyframe, kf_from_cam) = (r.i64()?, r.u64()?, r.se3()?);
        let flag = if version >= 4 { r.u8()? } else { 0 };
        map.trajectory.push(FrameRecord {
            t_ns,
            keyframe,
            kf_from_cam,
            predicted: flag != 0,
            held: flag == 2,
            position_cov: if version >= 5 && r.u8()? != 0 {
                let mut c = Matrix3::zeros();
                for (i, j) in COV_ENTRIES {
                    let v = r.f64()?;
                    c[(i, j)] = v;
                    c[(j, i)] = v;
                }
                Some(c)
            } else {
                None
            },
        });
    }
    if version >= 2 {
        let n = r.len("segment start")?;
        for _ in 0..n {
            map.segment_starts.insert(r.u64()?);
        }
    }
    if r.at != data.len() {
        return Err(r.corrupt("trailing bytes"));
    }
    Ok((calib, descriptor, map, state))
}
