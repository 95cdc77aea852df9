//! The messages of a dhptam log: five Foxglove schemas and dhptam's own event batch, with
//! their protobuf encoders, decoders and `FileDescriptorSet`s.
//!
//! The Foxglove definitions mirror the published `foxglove/*.proto` files field for field (same
//! names, numbers and types, one file per message), so Foxglove decodes them with its built-in
//! panels. `dhptam.EventBatch` is ours:
//!
//! ```text
//! message EventBatch {                 // file dhptam/EventBatch.proto
//!   google.protobuf.Timestamp timestamp = 1;  // time of the batch's first event
//!   string frame_id = 2;               // the event camera, e.g. "event_left"
//!   uint32 count = 3;                  // number of events N
//!   bytes x = 4;                       // N × uint16 little-endian, pixel column
//!   bytes y = 5;                       // N × uint16 little-endian, pixel row
//!   bytes t_ns = 6;                    // N × int64 little-endian, ns, non-decreasing
//!   bytes p = 7;                       // N × int8, polarity 0/1
//!   uint64 first_index = 8;            // index of the first event in the whole stream
//! }
//! ```
//!
//! Arrays travel as raw little-endian bytes (13 bytes an event before compression) rather than
//! as repeated fields, so a batch is copied, not parsed, and the chunk compressor sees the
//! columns contiguously.

use super::proto::{self, file_descriptor_set, Dec, Enc, FieldDef, FileDef, MessageDef, Ty, Val};

/// A field definition; the helpers below name the four shapes the schemas use.
const fn def(
    name: &'static str,
    number: u32,
    ty: Ty,
    repeated: bool,
    type_name: &'static str,
) -> FieldDef {
    FieldDef {
        name,
        number,
        ty,
        repeated,
        type_name,
    }
}

/// A singular scalar field.
const fn field(name: &'static str, number: u32, ty: Ty) -> FieldDef {
    def(name, number, ty, false, "")
}

/// A repeated scalar field.
const fn repeated(name: &'static str, number: u32, ty: Ty) -> FieldDef {
    def(name, number, ty, true, "")
}

/// A singular message field of type `type_name` (fully qualified, `.foxglove.Pose`).
const fn sub(name: &'static str, number: u32, type_name: &'static str) -> FieldDef {
    def(name, number, Ty::Message, false, type_name)
}

/// A `.proto` file defining one message without nested enums (every file but
/// `PackedElementField.proto`): `proto_file!(file, package, [imports], Message, [fields])`.
/// A macro rather than a `const fn` so that the nested slices stay `'static` literals.
macro_rules! proto_file {
    ($file:expr, $package:expr, [$($dep:expr),* $(,)?], $message:expr, [$($field:expr),* $(,)?]) => {
        FileDef {
            name: $file,
            package: $package,
            deps: &[$($dep),*],
            messages: &[MessageDef {
                name: $message,
                fields: &[$($field),*],
                enums: &[],
            }],
        }
    };
}

const TS_DEP: &str = "google/protobuf/timestamp.proto";
const TS: &str = ".google.protobuf.Timestamp";
const POSE_DEP: &str = "foxglove/Pose.proto";
const POSE_TYPE: &str = ".foxglove.Pose";

const TIMESTAMP: FileDef = proto_file!(
    TS_DEP,
    "google.protobuf",
    [],
    "Timestamp",
    [field("seconds", 1, Ty::Int64), field("nanos", 2, Ty::Int32)]
);

const VECTOR3: FileDef = proto_file!(
    "foxglove/Vector3.proto",
    "foxglove",
    [],
    "Vector3",
    [
        field("x", 1, Ty::Double),
        field("y", 2, Ty::Double),
        field("z", 3, Ty::Double),
    ]
);

const QUATERNION: FileDef = proto_file!(
    "foxglove/Quaternion.proto",
    "foxglove",
    [],
    "Quaternion",
    [
        field("x", 1, Ty::Double),
        field("y", 2, Ty::Double),
        field("z", 3, Ty::Double),
        field("w", 4, Ty::Double),
    ]
);

const POSE: FileDef = proto_file!(
    POSE_DEP,
    "foxglove",
    ["foxglove/Quaternion.proto", "foxglove/Vector3.proto"],
    "Pose",
    [
        sub("position", 1, ".foxglove.Vector3"),
        sub("orientation", 2, ".foxglove.Quaternion"),
    ]
);

const POSE_IN_FRAME: FileDef = proto_file!(
    "foxglove/PoseInFrame.proto",
    "foxglove",
    [POSE_DEP, TS_DEP],
    "PoseInFrame",
    [
        sub("timestamp", 1, TS),
        field("frame_id", 2, Ty::String),
        sub("pose", 3, POSE_TYPE),
    ]
);

const RAW_IMAGE: FileDef = proto_file!(
    "foxglove/RawImage.proto",
    "foxglove",
    [TS_DEP],
    "RawImage",
    [
        sub("timestamp", 1, TS),
        field("frame_id", 7, Ty::String),
        field("width", 2, Ty::Fixed32),
        field("height", 3, Ty::Fixed32),
        field("encoding", 4, Ty::String),
        field("step", 5, Ty::Fixed32),
        field("data", 6, Ty::Bytes),
    ]
);

const COMPRESSED_IMAGE: FileDef = proto_file!(
    "foxglove/CompressedImage.proto",
    "foxglove",
    [TS_DEP],
    "CompressedImage",
    [
        sub("timestamp", 1, TS),
        field("frame_id", 4, Ty::String),
        field("data", 2, Ty::Bytes),
        field("format", 3, Ty::String),
    ]
);

const CAMERA_CALIBRATION: FileDef = proto_file!(
    "foxglove/CameraCalibration.proto",
    "foxglove",
    [TS_DEP],
    "CameraCalibration",
    [
        sub("timestamp", 1, TS),
        field("frame_id", 9, Ty::String),
        field("width", 2, Ty::Fixed32),
        field("height", 3, Ty::Fixed32),
        field("distortion_model", 4, Ty::String),
        repeated("D", 5, Ty::Double),
        repeated("K", 6, Ty::Double),
        repeated("R", 7, Ty::Double),
        repeated("P", 8, Ty::Double),
    ]
);

const PACKED_ELEMENT_FIELD_DEP: &str = "foxglove/PackedElementField.proto";

const PACKED_ELEMENT_FIELD: FileDef = FileDef {
    name: PACKED_ELEMENT_FIELD_DEP,
    package: "foxglove",
    deps: &[],
    messages: &[MessageDef {
        name: "PackedElementField",
        fields: &[
            field("name", 1, Ty::String),
            field("offset", 2, Ty::Fixed32),
            def(
                "type",
                3,
                Ty::Enum,
                false,
                ".foxglove.PackedElementField.NumericType",
            ),
        ],
        enums: &[(
            "NumericType",
            &[
                ("UNKNOWN", 0),
                ("UINT8", 1),
                ("INT8", 2),
                ("UINT16", 3),
                ("INT16", 4),
                ("UINT32", 5),
                ("INT32", 6),
                ("FLOAT32", 7),
                ("FLOAT64", 8),
            ],
        )],
    }],
};
const FLOAT32: u64 = 7;

const POINT_CLOUD: FileDef = proto_file!(
    "foxglove/PointCloud.proto",
    "foxglove",
    [PACKED_ELEMENT_FIELD_DEP, POSE_DEP, TS_DEP],
    "PointCloud",
    [
        sub("timestamp", 1, TS),
        field("frame_id", 2, Ty::String),
        sub("pose", 3, POSE_TYPE),
        field("point_stride", 4, Ty::Fixed32),
        def(
            "fields",
            5,
            Ty::Message,
            true,
            ".foxglove.PackedElementField"
        ),
        field("data", 6, Ty::Bytes),
    ]
);

const EVENT_BATCH: FileDef = proto_file!(
    "dhptam/EventBatch.proto",
    "dhptam",
    [TS_DEP],
    "EventBatch",
    [
        sub("timestamp", 1, TS),
        field("frame_id", 2, Ty::String),
        field("count", 3, Ty::Uint32),
        field("x", 4, Ty::Bytes),
        field("y", 5, Ty::Bytes),
        field("t_ns", 6, Ty::Bytes),
        field("p", 7, Ty::Bytes),
        field("first_index", 8, Ty::Uint64),
    ]
);

/// Every `.proto` file the schemas use; a schema's descriptor set is its file plus the files
/// it imports, found here by name.
const FILES: [&FileDef; 11] = [
    &TIMESTAMP,
    &VECTOR3,
    &QUATERNION,
    &POSE,
    &POSE_IN_FRAME,
    &RAW_IMAGE,
    &COMPRESSED_IMAGE,
    &CAMERA_CALIBRATION,
    &PACKED_ELEMENT_FIELD,
    &POINT_CLOUD,
    &EVENT_BATCH,
];

/// `root` and everything it imports, each file after its imports (what a
/// `FileDescriptorSet` reader expects), each once.
fn with_imports(root: &'static FileDef) -> Vec<&'static FileDef> {
    fn visit(file: &'static FileDef, out: &mut Vec<&'static FileDef>) {
        if out.iter().any(|f| f.name == file.name) {
            return;
        }
        for dep in file.deps {
            // Every import names a file of `FILES` (checked by a test).
            if let Some(d) = FILES.iter().find(|f| f.name == *dep) {
                visit(d, out);
            }
        }
        out.push(file);
    }
    let mut out = Vec::new();
    visit(root, &mut out);
    out
}

/// The schemas a dhptam log uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SchemaKind {
    /// `dhptam.EventBatch` (see the module docs).
    EventBatch,
    /// `foxglove.RawImage`.
    RawImage,
    /// `foxglove.CompressedImage` (PNG or JPEG bytes).
    CompressedImage,
    /// `foxglove.CameraCalibration`.
    CameraCalibration,
    /// `foxglove.PoseInFrame`.
    PoseInFrame,
    /// `foxglove.PointCloud`.
    PointCloud,
}

impl SchemaKind {
    /// Every schema, in a fixed order.
    pub const ALL: [SchemaKind; 6] = [
        SchemaKind::EventBatch,
        SchemaKind::RawImage,
        SchemaKind::CompressedImage,
        SchemaKind::CameraCalibration,
        SchemaKind::PoseInFrame,
        SchemaKind::PointCloud,
    ];

    /// The schema's fully qualified protobuf name, as written in the MCAP Schema record.
    pub fn name(self) -> &'static str {
        match self {
            SchemaKind::EventBatch => "dhptam.EventBatch",
            SchemaKind::RawImage => "foxglove.RawImage",
            SchemaKind::CompressedImage => "foxglove.CompressedImage",
            SchemaKind::CameraCalibration => "foxglove.CameraCalibration",
            SchemaKind::PoseInFrame => "foxglove.PoseInFrame",
            SchemaKind::PointCloud => "foxglove.PointCloud",
        }
    }

    /// The schema with this protobuf name, if it is one of the log's.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }

    /// The `.proto` file defining the schema.
    fn file(self) -> &'static FileDef {
        match self {
            SchemaKind::EventBatch => &EVENT_BATCH,
            SchemaKind::RawImage => &RAW_IMAGE,
            SchemaKind::CompressedImage => &COMPRESSED_IMAGE,
            SchemaKind::CameraCalibration => &CAMERA_CALIBRATION,
            SchemaKind::PoseInFrame => &POSE_IN_FRAME,
            SchemaKind::PointCloud => &POINT_CLOUD,
        }
    }

    /// The serialized `FileDescriptorSet`: the schema's file and its imports, imports first.
    pub fn descriptor_set(self) -> Vec<u8> {
        file_descriptor_set(&with_imports(self.file()))
    }
}

type DecResult<T> = Result<T, String>;

fn timestamp(t_ns: i64) -> Enc {
    let mut e = Enc::default();
    e.int(1, t_ns.div_euclid(1_000_000_000));
    e.int(2, t_ns.rem_euclid(1_000_000_000));
    e
}

fn read_timestamp(val: Val<'_>) -> DecResult<i64> {
    let mut d = Dec::new(proto::bytes(val)?);
    let (mut s, mut n) = (0i64, 0i64);
    while let Some((f, v)) = d.next_field()? {
        match f {
            1 => s = proto::number(v)? as i64,
            2 => n = i64::from(proto::number(v)? as i32),
            _ => {}
        }
    }
    s.checked_mul(1_000_000_000)
        .and_then(|x| x.checked_add(n))
        .ok_or_else(|| "timestamp overflows int64 nanoseconds".to_string())
}

/// A message of doubles numbered 1, 2, ... (`foxglove.Vector3`, `foxglove.Quaternion`).
fn doubles_message(values: &[f64]) -> Enc {
    let mut e = Enc::default();
    for (i, x) in values.iter().enumerate() {
        e.double(i as u32 + 1, *x);
    }
    e
}

fn pose(translation: &[f64; 3], quat_xyzw: &[f64; 4]) -> Enc {
    let mut p = Enc::default();
    p.message(1, &doubles_message(translation));
    p.message(2, &doubles_message(quat_xyzw));
    p
}

fn read_doubles<const N: usize>(val: Val<'_>) -> DecResult<[f64; N]> {
    let mut out = [0.0; N];
    let mut d = Dec::new(proto::bytes(val)?);
    while let Some((f, v)) = d.next_field()? {
        let i = f as usize;
        if (1..=N).contains(&i) {
            out[i - 1] = proto::double(v)?;
        }
    }
    Ok(out)
}

fn read_pose(val: Val<'_>) -> DecResult<([f64; 3], [f64; 4])> {
    // Foxglove's default orientation is all zeros when absent; ours always writes it.
    let (mut t, mut q) = ([0.0; 3], [0.0; 4]);
    let mut d = Dec::new(proto::bytes(val)?);
    while let Some((f, v)) = d.next_field()? {
        match f {
            1 => t = read_doubles::<3>(v)?,
            2 => q = read_doubles::<4>(v)?,
            _ => {}
        }
    }
    Ok((t, q))
}

/// `foxglove.RawImage`: an uncompressed image; `t_ns` is its timestamp.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RawImage {
    /// Timestamp, ns.
    pub t_ns: i64,
    /// Coordinate frame of the camera (`frame_left`, ...).
    pub frame_id: String,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Pixel encoding, e.g. `mono8` or `rgb8`.
    pub encoding: String,
    /// Bytes per row.
    pub step: u32,
    /// Row-major pixel data, `step * height` bytes.
    pub data: Vec<u8>,
}

impl RawImage {
    /// Protobuf encoding.
    pub fn encode(&self) -> Vec<u8> {
        let mut e = Enc::with_capacity(self.data.len() + 64);
        e.message(1, &timestamp(self.t_ns));
        e.fixed32(2, self.width);
        e.fixed32(3, self.height);
        e.bytes(4, self.encoding.as_bytes());
        e.fixed32(5, self.step);
        e.bytes(6, &self.data);
        e.bytes(7, self.frame_id.as_bytes());
        e.buf
    }

    /// Decodes a protobuf-encoded message.
    pub fn decode(buf: &[u8]) -> DecResult<Self> {
        let mut m = RawImage::default();
        let mut d = Dec::new(buf);
        while let Some((f, v)) = d.next_field()? {
            match f {
                1 => m.t_ns = read_timestamp(v)?,
                2 => m.width = proto::number(v)? as u32,
                3 => m.height = proto::number(v)? as u32,
                4 => m.encoding = proto::string(v)?,
                5 => m.step = proto::number(v)? as u32,
                6 => m.data = proto::bytes(v)?.to_vec(),
                7 => m.frame_id = proto::string(v)?,
                _ => {}
            }
        }
        Ok(m)
    }
}

/// `foxglove.CompressedImage`: an image in a compressed file format; `t_ns` is its timestamp.
///
/// dhptam writes lossless PNG (`format = "png"`); the reader accepts whatever `format` says and
/// leaves the decoding to the caller (the Python side decodes PNG and JPEG with OpenCV).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CompressedImage {
    /// Timestamp, ns.
    pub t_ns: i64,
    /// Coordinate frame of the camera (`frame_left`, ...).
    pub frame_id: String,
    /// The image file's bytes.
    pub data: Vec<u8>,
    /// Image format: `png`, `jpeg` or `webp` (Foxglove's names).
    pub format: String,
}

impl CompressedImage {
    /// Protobuf encoding.
    pub fn encode(&self) -> Vec<u8> {
        let mut e = Enc::with_capacity(self.data.len() + 64);
        e.message(1, &timestamp(self.t_ns));
        e.bytes(2, &self.data);
        e.bytes(3, self.format.as_bytes());
        e.bytes(4, self.frame_id.as_bytes());
        e.buf
    }

    /// Decodes a protobuf-encoded message.
    pub fn decode(buf: &[u8]) -> DecResult<Self> {
        let mut m = CompressedImage::default();
        let mut d = Dec::new(buf);
        while let Some((f, v)) = d.next_field()? {
            match f {
                1 => m.t_ns = read_timestamp(v)?,
                2 => m.data = proto::bytes(v)?.to_vec(),
                3 => m.format = proto::string(v)?,
                4 => m.frame_id = proto::string(v)?,
                _ => {}
            }
        }
        Ok(m)
    }
}

/// `foxglove.CameraCalibration`, ROS `CameraInfo` conventions (K, R, P row-major).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CameraCalibration {
    /// Timestamp, ns.
    pub t_ns: i64,
    /// Coordinate frame of the camera.
    pub frame_id: String,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Distortion model name (`plumb_bob`, `kannala_brandt`, ...).
    pub distortion_model: String,
    /// Distortion coefficients.
    pub d: Vec<f64>,
    /// 3×3 intrinsic matrix, row-major.
    pub k: Vec<f64>,
    /// 3×3 rectification rotation, row-major.
    pub r: Vec<f64>,
    /// 3×4 projection matrix, row-major.
    pub p: Vec<f64>,
}

impl CameraCalibration {
    /// Protobuf encoding.
    pub fn encode(&self) -> Vec<u8> {
        let mut e = Enc::default();
        e.message(1, &timestamp(self.t_ns));
        e.fixed32(2, self.width);
        e.fixed32(3, self.height);
        e.bytes(4, self.distortion_model.as_bytes());
        e.doubles(5, &self.d);
        e.doubles(6, &self.k);
        e.doubles(7, &self.r);
        e.doubles(8, &self.p);
        e.bytes(9, self.frame_id.as_bytes());
        e.buf
    }

    /// Decodes a protobuf-encoded message.
    pub fn decode(buf: &[u8]) -> DecResult<Self> {
        let mut m = CameraCalibration::default();
        let mut d = Dec::new(buf);
        while let Some((f, v)) = d.next_field()? {
            match f {
                1 => m.t_ns = read_timestamp(v)?,
                2 => m.width = proto::number(v)? as u32,
                3 => m.height = proto::number(v)? as u32,
                4 => m.distortion_model = proto::string(v)?,
                5 => proto::push_doubles(v, &mut m.d)?,
                6 => proto::push_doubles(v, &mut m.k)?,
                7 => proto::push_doubles(v, &mut m.r)?,
                8 => proto::push_doubles(v, &mut m.p)?,
                9 => m.frame_id = proto::string(v)?,
                _ => {}
            }
        }
        Ok(m)
    }
}

/// `foxglove.PoseInFrame`: the pose of a body in `frame_id` (for dhptam logs the frame is
/// `world` and the pose is `world_from_cam`); quaternion x-y-z-w, Hamilton.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PoseInFrame {
    /// Timestamp, ns.
    pub t_ns: i64,
    /// Parent frame of the pose.
    pub frame_id: String,
    /// Position, metres.
    pub translation: [f64; 3],
    /// Orientation quaternion x, y, z, w.
    pub quat_xyzw: [f64; 4],
}

impl PoseInFrame {
    /// Protobuf encoding.
    pub fn encode(&self) -> Vec<u8> {
        let mut e = Enc::default();
        e.message(1, &timestamp(self.t_ns));
        e.bytes(2, self.frame_id.as_bytes());
        e.message(3, &pose(&self.translation, &self.quat_xyzw));
        e.buf
    }

    /// Decodes a protobuf-encoded message.
    pub fn decode(buf: &[u8]) -> DecResult<Self> {
        let mut m = PoseInFrame::default();
        let mut d = Dec::new(buf);
        while let Some((f, v)) = d.next_field()? {
            match f {
                1 => m.t_ns = read_timestamp(v)?,
                2 => m.frame_id = proto::string(v)?,
                3 => (m.translation, m.quat_xyzw) = read_pose(v)?,
                _ => {}
            }
        }
        Ok(m)
    }
}

/// `foxglove.PointCloud` restricted to what dhptam writes: `x, y, z` float32 points in
/// `frame_id` (identity pose, 12-byte stride).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PointCloud {
    /// Timestamp, ns.
    pub t_ns: i64,
    /// Frame of the points (`world` for the map).
    pub frame_id: String,
    /// Points, metres.
    pub points: Vec<[f32; 3]>,
}

impl PointCloud {
    /// Protobuf encoding.
    pub fn encode(&self) -> Vec<u8> {
        let mut e = Enc::with_capacity(12 * self.points.len() + 160);
        e.message(1, &timestamp(self.t_ns));
        e.bytes(2, self.frame_id.as_bytes());
        e.message(3, &pose(&[0.0; 3], &[0.0, 0.0, 0.0, 1.0]));
        e.fixed32(4, 12);
        for (i, name) in ["x", "y", "z"].iter().enumerate() {
            let mut f = Enc::default();
            f.bytes(1, name.as_bytes());
            f.fixed32(2, 4 * i as u32);
            f.uint(3, FLOAT32);
            e.message(5, &f);
        }
        e.bytes_with(6, 12 * self.points.len(), |buf| {
            for p in &self.points {
                for c in p {
                    buf.extend_from_slice(&c.to_le_bytes());
                }
            }
        });
        e.buf
    }

    /// Decodes a message written by [`PointCloud::encode`]: float32 `x, y, z` at offsets 0, 4,
    /// 8 of each point; other layouts are an error.
    pub fn decode(buf: &[u8]) -> DecResult<Self> {
        let mut m = PointCloud::default();
        let (mut stride, mut data, mut fields) = (0usize, &[][..], Vec::new());
        let mut d = Dec::new(buf);
        while let Some((f, v)) = d.next_field()? {
            match f {
                1 => m.t_ns = read_timestamp(v)?,
                2 => m.frame_id = proto::string(v)?,
                4 => stride = proto::number(v)? as usize,
                5 => {
                    let (mut name, mut offset, mut ty) = (String::new(), 0, 0);
                    let mut fd = Dec::new(proto::bytes(v)?);
                    while let Some((g, w)) = fd.next_field()? {
                        match g {
                            1 => name = proto::string(w)?,
                            2 => offset = proto::number(w)?,
                            3 => ty = proto::number(w)?,
                            _ => {}
                        }
                    }
                    fields.push((name, offset, ty));
                }
                6 => data = proto::bytes(v)?,
                _ => {}
            }
        }
        let expected: Vec<(String, u64, u64)> = ["x", "y", "z"]
            .iter()
            .enumerate()
            .map(|(i, n)| (n.to_string(), 4 * i as u64, FLOAT32))
            .collect();
        if fields != expected || stride != 12 || data.len() % 12 != 0 {
            return Err(format!(
                "point layout {fields:?} with stride {stride} and {} data bytes; expected float32 \
                 x, y, z at offsets 0, 4, 8 and stride 12",
                data.len()
            ));
        }
        m.points = data
            .chunks_exact(12)
            .map(|c| {
                let f = |i: usize| f32::from_le_bytes([c[i], c[i + 1], c[i + 2], c[i + 3]]);
                [f(0), f(4), f(8)]
            })
            .collect();
        Ok(m)
    }
}

/// Events of one camera, column-wise (the payload of `dhptam.EventBatch`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct EventColumns {
    /// Pixel columns.
    pub x: Vec<u16>,
    /// Pixel rows.
    pub y: Vec<u16>,
    /// Times, ns, non-decreasing.
    pub t_ns: Vec<i64>,
    /// Polarities (0/1).
    pub p: Vec<i8>,
}

impl EventColumns {
    /// Number of events.
    pub fn len(&self) -> usize {
        self.t_ns.len()
    }

    /// Whether there are no events.
    pub fn is_empty(&self) -> bool {
        self.t_ns.is_empty()
    }
}

/// Encodes events `[i0, i1)` of the given columns as a `dhptam.EventBatch`.
pub(crate) fn encode_event_batch(
    frame_id: &str,
    first_index: u64,
    x: &[u16],
    y: &[u16],
    t_ns: &[i64],
    p: &[i8],
) -> Vec<u8> {
    let n = t_ns.len();
    let mut e = Enc::with_capacity(13 * n + 64);
    e.message(1, &timestamp(t_ns.first().copied().unwrap_or(0)));
    e.bytes(2, frame_id.as_bytes());
    e.uint(3, n as u64);
    e.bytes_with(4, 2 * n, |b| {
        x.iter().for_each(|v| b.extend_from_slice(&v.to_le_bytes()))
    });
    e.bytes_with(5, 2 * n, |b| {
        y.iter().for_each(|v| b.extend_from_slice(&v.to_le_bytes()))
    });
    e.bytes_with(6, 8 * n, |b| {
        t_ns.iter()
            .for_each(|v| b.extend_from_slice(&v.to_le_bytes()))
    });
    e.bytes_with(7, n, |b| b.extend(p.iter().map(|&v| v as u8)));
    e.uint(8, first_index);
    e.buf
}

/// A decoded `dhptam.EventBatch`.
pub(crate) struct EventBatch {
    pub first_index: u64,
    pub events: EventColumns,
}

/// Decodes a `dhptam.EventBatch`, checking that every column holds `count` events.
pub(crate) fn decode_event_batch(buf: &[u8]) -> DecResult<EventBatch> {
    let mut d = Dec::new(buf);
    let (mut count, mut first_index) = (0usize, 0u64);
    let (mut xb, mut yb, mut tb, mut pb): (&[u8], &[u8], &[u8], &[u8]) = (&[], &[], &[], &[]);
    while let Some((f, v)) = d.next_field()? {
        match f {
            3 => count = proto::number(v)? as usize,
            4 => xb = proto::bytes(v)?,
            5 => yb = proto::bytes(v)?,
            6 => tb = proto::bytes(v)?,
            7 => pb = proto::bytes(v)?,
            8 => first_index = proto::number(v)?,
            _ => {}
        }
    }
    if xb.len() != 2 * count || yb.len() != 2 * count || tb.len() != 8 * count || pb.len() != count
    {
        return Err(format!(
            "event batch of {count} events has column sizes x {} B, y {} B, t_ns {} B, p {} B \
             (expected {}, {}, {}, {})",
            xb.len(),
            yb.len(),
            tb.len(),
            pb.len(),
            2 * count,
            2 * count,
            8 * count,
            count
        ));
    }
    let u16s = |b: &[u8]| -> Vec<u16> {
        b.chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect()
    };
    let events = EventColumns {
        x: u16s(xb),
        y: u16s(yb),
        t_ns: tb
            .chunks_exact(8)
            .map(|c| i64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
            .collect(),
        p: pb.iter().map(|&v| v as i8).collect(),
    };
    Ok(EventBatch {
        first_index,
        events,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_round_trip() {
        let img = RawImage {
            t_ns: -1_500_000_001,
            frame_id: "frame_left".into(),
            width: 3,
            height: 2,
            encoding: "mono8".into(),
            step: 3,
            data: vec![1, 2, 3, 4, 5, 6],
        };
        assert_eq!(RawImage::decode(&img.encode()).unwrap(), img);
        let png = CompressedImage {
            t_ns: 42,
            frame_id: "frame_right".into(),
            data: b"\x89PNG\r\n\x1a\n...".to_vec(),
            format: "png".into(),
        };
        assert_eq!(CompressedImage::decode(&png.encode()).unwrap(), png);
        let cal = CameraCalibration {
            t_ns: 7,
            frame_id: "a".into(),
            width: 640,
            height: 480,
            distortion_model: "kannala_brandt".into(),
            d: vec![0.1, -0.2, 0.0, 0.3],
            k: vec![1.0; 9],
            r: vec![2.0; 9],
            p: vec![3.0; 12],
        };
        assert_eq!(CameraCalibration::decode(&cal.encode()).unwrap(), cal);
        let pose = PoseInFrame {
            t_ns: 123,
            frame_id: "world".into(),
            translation: [1.0, -2.0, 3.5],
            quat_xyzw: [0.0, 0.6, 0.0, 0.8],
        };
        assert_eq!(PoseInFrame::decode(&pose.encode()).unwrap(), pose);
        let cloud = PointCloud {
            t_ns: 5,
            frame_id: "world".into(),
            points: vec![[1.0, 2.0, 3.0], [-4.0, 5.5, 0.0]],
        };
        assert_eq!(PointCloud::decode(&cloud.encode()).unwrap(), cloud);
        let buf = encode_event_batch("e", 10, &[1, 2], &[3, 4], &[5, 6], &[0, 1]);
        let batch = decode_event_batch(&buf).unwrap();
        assert_eq!(batch.first_index, 10);
        assert_eq!(batch.events.t_ns, vec![5, 6]);
        assert_eq!(batch.events.p, vec![0, 1]);
    }

    #[test]
    fn every_schema_has_a_descriptor_set() {
        for kind in SchemaKind::ALL {
            assert_eq!(SchemaKind::from_name(kind.name()), Some(kind));
            assert!(kind.descriptor_set().len() > 50);
        }
    }

    #[test]
    fn every_import_is_a_known_file_listed_before_its_importer() {
        for file in FILES {
            for dep in file.deps {
                assert!(
                    FILES.iter().any(|f| f.name == *dep),
                    "{} imports unknown {dep}",
                    file.name
                );
            }
        }
        for kind in SchemaKind::ALL {
            let files = with_imports(kind.file());
            let names: Vec<&str> = files.iter().map(|f| f.name).collect();
            assert_eq!(names.last(), Some(&kind.file().name));
            for (i, f) in files.iter().enumerate() {
                assert_eq!(names.iter().filter(|n| **n == f.name).count(), 1);
                for dep in f.deps {
                    let at = names.iter().position(|n| n == dep);
                    assert!(at.is_some_and(|j| j < i), "{dep} must precede {}", f.name);
                }
            }
        }
        // PointCloud needs every Foxglove file of a pose plus its own field type.
        let names: Vec<&str> = with_imports(&POINT_CLOUD).iter().map(|f| f.name).collect();
        assert_eq!(
            names,
            [
                "foxglove/PackedElementField.proto",
                "foxglove/Quaternion.proto",
                "foxglove/Vector3.proto",
                "foxglove/Pose.proto",
                "google/protobuf/timestamp.proto",
                "foxglove/PointCloud.proto",
            ]
        );
    }
}
