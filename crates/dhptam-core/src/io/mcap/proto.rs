//! Just enough of the protobuf wire format for the MCAP log: an encoder, a field reader, and
//! `FileDescriptorSet`s built from a compact table of message definitions.
//!
//! The log's messages are few and flat, so they are encoded by hand rather than through a code
//! generator: varints (wire type 0), 64-bit (1), length-delimited (2) and 32-bit (5) fields;
//! repeated `double`s are written packed, as proto3 does by default.

/// Protobuf scalar and composite field types, numbered as in `FieldDescriptorProto.Type`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Ty {
    Double = 1,
    Int64 = 3,
    Uint64 = 4,
    Int32 = 5,
    Fixed32 = 7,
    String = 9,
    Message = 11,
    Bytes = 12,
    Uint32 = 13,
    Enum = 14,
}

/// One field of a message definition.
pub(crate) struct FieldDef {
    pub name: &'static str,
    pub number: u32,
    pub ty: Ty,
    pub repeated: bool,
    /// Fully qualified type name (`.foxglove.Pose`) for message and enum fields.
    pub type_name: &'static str,
}

/// A message definition with its nested enums (`(name, [(value name, number)])`).
pub(crate) struct MessageDef {
    pub name: &'static str,
    pub fields: &'static [FieldDef],
    pub enums: &'static [(&'static str, &'static [(&'static str, i32)])],
}

/// One `.proto` file: its package, the files it imports and the messages it defines.
pub(crate) struct FileDef {
    pub name: &'static str,
    pub package: &'static str,
    pub deps: &'static [&'static str],
    pub messages: &'static [MessageDef],
}

/// Appends protobuf fields to a byte buffer.
#[derive(Default)]
pub(crate) struct Enc {
    pub buf: Vec<u8>,
}

impl Enc {
    pub fn with_capacity(n: usize) -> Self {
        Enc {
            buf: Vec::with_capacity(n),
        }
    }

    fn varint(&mut self, mut v: u64) {
        while v >= 0x80 {
            self.buf.push((v as u8) | 0x80);
            v >>= 7;
        }
        self.buf.push(v as u8);
    }

    fn key(&mut self, field: u32, wire: u8) {
        self.varint((u64::from(field) << 3) | u64::from(wire));
    }

    /// A varint field (int32, int64, uint32, enum, bool); zero is skipped as proto3 does.
    pub fn uint(&mut self, field: u32, v: u64) {
        if v != 0 {
            self.key(field, 0);
            self.varint(v);
        }
    }

    /// A signed int64/int32 field (two's complement varint, not zigzag).
    pub fn int(&mut self, field: u32, v: i64) {
        self.uint(field, v as u64);
    }

    /// A `fixed32` field.
    pub fn fixed32(&mut self, field: u32, v: u32) {
        if v != 0 {
            self.key(field, 5);
            self.buf.extend_from_slice(&v.to_le_bytes());
        }
    }

    /// A `double` field.
    pub fn double(&mut self, field: u32, v: f64) {
        if v.to_bits() != 0 {
            self.key(field, 1);
            self.buf.extend_from_slice(&v.to_le_bytes());
        }
    }

    /// A packed `repeated double` field.
    pub fn doubles(&mut self, field: u32, v: &[f64]) {
        if !v.is_empty() {
            self.key(field, 2);
            self.varint(8 * v.len() as u64);
            for x in v {
                self.buf.extend_from_slice(&x.to_le_bytes());
            }
        }
    }

    /// A `bytes` or `string` field.
    pub fn bytes(&mut self, field: u32, v: &[u8]) {
        if !v.is_empty() {
            self.key(field, 2);
            self.varint(v.len() as u64);
            self.buf.extend_from_slice(v);
        }
    }

    /// A `bytes` field whose content is written by `f` straight into the buffer, with a known
    /// length (no intermediate copy of large arrays).
    pub fn bytes_with(&mut self, field: u32, len: usize, f: impl FnOnce(&mut Vec<u8>)) {
        if len != 0 {
            self.key(field, 2);
            self.varint(len as u64);
            let start = self.buf.len();
            f(&mut self.buf);
            debug_assert_eq!(self.buf.len() - start, len);
        }
    }

    /// A sub-message field, always written (an empty message still marks presence).
    pub fn message(&mut self, field: u32, sub: &Enc) {
        self.key(field, 2);
        self.varint(sub.buf.len() as u64);
        self.buf.extend_from_slice(&sub.buf);
    }
}

/// A field value as it appears on the wire.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Val<'a> {
    Varint(u64),
    Fixed64(u64),
    Bytes(&'a [u8]),
    Fixed32(u32),
}

impl Val<'_> {
    /// The field as an unsigned varint or fixed32 number, `None` for other wire types.
    pub fn as_u64(&self) -> Option<u64> {
        match *self {
            Val::Varint(v) => Some(v),
            Val::Fixed32(v) => Some(u64::from(v)),
            _ => None,
        }
    }
}

/// Iterates over the `(field number, value)` pairs of an encoded message.
pub(crate) struct Dec<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl<'a> Dec<'a> {
    pub fn new(buf: &'a [u8]) -> Self {
        Dec { buf, pos: 0 }
    }

    fn varint(&mut self) -> Result<u64, String> {
        let mut v = 0u64;
        for shift in (0..64).step_by(7) {
            let b = *self
                .buf
                .get(self.pos)
                .ok_or_else(|| "message ends inside a varint".to_string())?;
            self.pos += 1;
            v |= u64::from(b & 0x7f) << shift;
            if b & 0x80 == 0 {
                return Ok(v);
            }
        }
        Err("varint longer than 10 bytes".into())
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.buf.len())
            .ok_or_else(|| format!("field of {n} bytes runs past the end of the message"))?;
        let s = &self.buf[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    /// The next field, `None` at the end of the message.
    pub fn next_field(&mut self) -> Result<Option<(u32, Val<'a>)>, String> {
        if self.pos >= self.buf.len() {
            return Ok(None);
        }
        let key = self.varint()?;
        let field = u32::try_from(key >> 3).map_err(|_| "field number too large".to_string())?;
        let val = match key & 7 {
            0 => Val::Varint(self.varint()?),
            1 => Val::Fixed64(u64::from_le_bytes(
                self.take(8)?.try_into().map_err(|_| "short fixed64")?,
            )),
            2 => {
                let n = usize::try_from(self.varint()?).map_err(|_| "length too large")?;
                Val::Bytes(self.take(n)?)
            }
            5 => Val::Fixed32(u32::from_le_bytes(
                self.take(4)?.try_into().map_err(|_| "short fixed32")?,
            )),
            w => return Err(format!("unsupported wire type {w} (field {field})")),
        };
        Ok(Some((field, val)))
    }
}

/// Reads a `repeated double` field, packed or not, appending to `out`.
pub(crate) fn push_doubles(val: Val<'_>, out: &mut Vec<f64>) -> Result<(), String> {
    match val {
        Val::Fixed64(bits) => out.push(f64::from_bits(bits)),
        Val::Bytes(b) if b.len() % 8 == 0 => out.extend(
            b.chunks_exact(8)
                .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]])),
        ),
        _ => return Err("expected a repeated double".into()),
    }
    Ok(())
}

/// Reads a `double` field.
pub(crate) fn double(val: Val<'_>) -> Result<f64, String> {
    match val {
        Val::Fixed64(bits) => Ok(f64::from_bits(bits)),
        _ => Err("expected a double".into()),
    }
}

/// Reads a `string` field.
pub(crate) fn string(val: Val<'_>) -> Result<String, String> {
    match val {
        Val::Bytes(b) => std::str::from_utf8(b)
            .map(str::to_owned)
            .map_err(|_| "string is not UTF-8".to_string()),
        _ => Err("expected a string".into()),
    }
}

/// Reads a `bytes` field.
pub(crate) fn bytes(val: Val<'_>) -> Result<&[u8], String> {
    match val {
        Val::Bytes(b) => Ok(b),
        _ => Err("expected bytes".into()),
    }
}

/// Reads a number field (varint or fixed32).
pub(crate) fn number(val: Val<'_>) -> Result<u64, String> {
    val.as_u64().ok_or_else(|| "expected a number".to_string())
}

/// Encodes a `FileDescriptorSet` holding `files` (dependencies must come first), the schema
/// data MCAP's `protobuf` schema encoding expects.
pub(crate) fn file_descriptor_set(files: &[&FileDef]) -> Vec<u8> {
    let mut set = Enc::default();
    for file in files {
        let mut f = Enc::default();
        f.bytes(1, file.name.as_bytes());
        f.bytes(2, file.package.as_bytes());
        for dep in file.deps {
            f.bytes(3, dep.as_bytes());
        }
        for msg in file.messages {
            f.message(4, &descriptor(msg));
        }
        f.bytes(12, b"proto3");
        set.message(1, &f);
    }
    set.buf
}

fn descriptor(msg: &MessageDef) -> Enc {
    let mut d = Enc::default();
    d.bytes(1, msg.name.as_bytes());
    for field in msg.fields {
        let mut fd = Enc::default();
        fd.bytes(1, field.name.as_bytes());
        fd.uint(3, u64::from(field.number));
        fd.uint(4, if field.repeated { 3 } else { 1 });
        fd.uint(5, field.ty as u64);
        fd.bytes(6, field.type_name.as_bytes());
        d.message(2, &fd);
    }
    for (name, values) in msg.enums {
        let mut e = Enc::default();
        e.bytes(1, name.as_bytes());
        for (value, number) in values.iter() {
            let mut v = Enc::default();
            v.bytes(1, value.as_bytes());
            v.int(2, i64::from(*number));
            e.message(2, &v);
        }
        d.message(4, &e);
    }
    d
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_round_trip_through_the_wire_format() {
        let mut e = Enc::default();
        e.int(1, -5);
        e.fixed32(2, 640);
        e.double(3, 1.5);
        e.doubles(4, &[1.0, -2.0]);
        e.bytes(5, b"abc");
        let mut d = Dec::new(&e.buf);
        let mut seen = Vec::new();
        while let Some((f, v)) = d.next_field().unwrap() {
            seen.push(f);
            match f {
                1 => assert_eq!(number(v).unwrap() as i64, -5),
                2 => assert_eq!(number(v).unwrap(), 640),
                3 => assert_eq!(double(v).unwrap(), 1.5),
                4 => {
                    let mut out = Vec::new();
                    push_doubles(v, &mut out).unwrap();
                    assert_eq!(out, vec![1.0, -2.0]);
                }
                5 => assert_eq!(bytes(v).unwrap(), b"abc"),
                _ => unreachable!(),
            }
        }
        assert_eq!(seen, vec![1, 2, 3, 4, 5]);
    }

    #[test]
    fn truncated_messages_are_errors() {
        let mut e = Enc::default();
        e.bytes(5, b"abcdef");
        let cut = &e.buf[..e.buf.len() - 2];
        assert!(Dec::new(cut).next_field().is_err());
    }
}
