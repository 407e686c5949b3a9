//! ROS 2 message definitions as MCAP and rosbag2 carry them (schema encoding `ros2msg`),
//! and CDR read by them: an open payload shown to a user who has never seen its type.
//!
//! A definition is the root type's `.msg` text, then for every type it uses a line of
//! 80 `=`, a line `MSG: pkg/Type` and that type's text. [`Definitions::parse`] checks it;
//! [`Definitions::decode`] reads a CDR sample (with its 4-byte encapsulation header) into
//! JSON; [`Definitions::transcode`] walks any serde deserializer (the DDS reader's) in
//! the definition's order and writes the sample as little-endian CDR.

use serde::de::{self, DeserializeSeed, Deserializer, SeqAccess, Visitor};
use serde_json::{json, Map, Value};
use std::collections::BTreeMap;
use std::fmt;

/// Longest definition accepted (text, dependencies included).
pub const MAX_DEFINITION: usize = 64 * 1024;
/// Deepest nesting of message types.
const MAX_DEPTH: usize = 32;
/// Most elements a sequence may claim (more is a corrupt or hostile sample).
const MAX_ELEMENTS: usize = 1 << 24;

/// Why a definition or a sample is unusable.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Ros2MsgError {
    /// The definition text is malformed; the text says where.
    #[error("message definition: {0}")]
    Definition(String),
    /// A sample does not match its definition (cut short, a length past its end, bad
    /// text); the text says where.
    #[error("CDR sample: {0}")]
    Sample(String),
}

fn def_err(s: impl Into<String>) -> Ros2MsgError {
    Ros2MsgError::Definition(s.into())
}

/// A primitive field type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Prim {
    /// `bool`.
    Bool,
    /// `byte`, `uint8`, `char`.
    U8,
    /// `int8`.
    I8,
    /// `int16`.
    I16,
    /// `uint16`.
    U16,
    /// `int32`.
    I32,
    /// `uint32`.
    U32,
    /// `int64`.
    I64,
    /// `uint64`.
    U64,
    /// `float32`.
    F32,
    /// `float64`.
    F64,
    /// `string` (bounded or not).
    Str,
}

impl Prim {
    fn parse(s: &str) -> Option<Prim> {
        Some(match s {
            "bool" => Prim::Bool,
            "byte" | "uint8" | "char" => Prim::U8,
            "int8" => Prim::I8,
            "int16" => Prim::I16,
            "uint16" => Prim::U16,
            "int32" => Prim::I32,
            "uint32" => Prim::U32,
            "int64" => Prim::I64,
            "uint64" => Prim::U64,
            "float32" => Prim::F32,
            "float64" => Prim::F64,
            s if s == "string" || s.starts_with("string<=") => Prim::Str,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Prim::Bool | Prim::U8 | Prim::I8 => 1,
            Prim::I16 | Prim::U16 => 2,
            Prim::I32 | Prim::U32 | Prim::F32 | Prim::Str => 4,
            Prim::I64 | Prim::U64 | Prim::F64 => 8,
        }
    }
}

/// What one field holds.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Base {
    /// A primitive.
    Prim(Prim),
    /// A message, by its full name (`pkg/msg/Type`).
    Msg(String),
}

/// How many.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Arity {
    /// One.
    One,
    /// A fixed array (`T[N]`).
    Fixed(usize),
    /// A sequence (`T[]`, `T[<=N]`).
    Seq,
}

/// One field of a message.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Field {
    /// Its name.
    pub name: String,
    /// Its type.
    pub base: Base,
    /// One, a fixed array or a sequence.
    pub arity: Arity,
}

/// A parsed definition: the root type and every type it uses.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Definitions {
    root: String,
    types: BTreeMap<String, Vec<Field>>,
}

/// `pkg/Type` or `pkg/msg/Type` as `pkg/msg/Type`; a bare `Type` in package `pkg`.
pub fn full_name(name: &str, pkg: &str) -> String {
    let parts: Vec<&str> = name.split('/').collect();
    match parts[..] {
        ["Header"] => "std_msgs/msg/Header".into(),
        [t] => format!("{pkg}/msg/{t}"),
        [p, t] => format!("{p}/msg/{t}"),
        _ => name.to_string(),
    }
}

fn package_of(full: &str) -> &str {
    full.split('/').next().unwrap_or("")
}

/// The fields of one type's `.msg` text, its relative type names taken in package `pkg`.
pub fn parse_fields(text: &str, pkg: &str) -> Result<Vec<Field>, Ros2MsgError> {
    let mut fields = Vec::new();
    for (n, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let mut words = line.split_whitespace();
        let ty = words.next().unwrap_or("");
        let rest = line[ty.len()..].trim_start();
        let name_end = rest
            .find(|c: char| c.is_whitespace() || c == '=')
            .unwrap_or(rest.len());
        let name = &rest[..name_end];
        // A constant (`TYPE NAME=VALUE`) is not on the wire.
        if rest[name_end..].trim_start().starts_with('=') {
            continue;
        }
        if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
            return Err(def_err(format!(
                "line {}: {raw:?} has no field name",
                n + 1
            )));
        }
        let (base, arity) = match ty.find('[') {
            Some(i) => {
                let inner = ty[i + 1..]
                    .strip_suffix(']')
                    .ok_or_else(|| def_err(format!("line {}: bad array type {ty:?}", n + 1)))?;
                let arity = if inner.is_empty() || inner.starts_with("<=") {
                    Arity::Seq
                } else {
                    Arity::Fixed(inner.parse().map_err(|_| {
                        def_err(format!("line {}: bad array length in {ty:?}", n + 1))
                    })?)
                };
                (&ty[..i], arity)
            }
            None => (ty, Arity::One),
        };
        if base.starts_with("wstring") {
            return Err(def_err(format!("line {}: wstring is not supported", n + 1)));
        }
        let base = match Prim::parse(base) {
            Some(p) => Base::Prim(p),
            None => Base::Msg(full_name(base, pkg)),
        };
        if fields.iter().any(|f: &Field| f.name == name) {
            return Err(def_err(format!(
                "line {}: field {name:?} is declared twice",
                n + 1
            )));
        }
        fields.push(Field {
            name: name.to_string(),
            base,
            arity,
        });
    }
    Ok(fields)
}

impl Definitions {
    /// Parses the `ros2msg` definition of `root` (`pkg/msg/Type` or `pkg/Type`).
    pub fn parse(root: &str, text: &str) -> Result<Self, Ros2MsgError> {
        if text.len() > MAX_DEFINITION {
            return Err(def_err(format!(
                "{} bytes, at most {MAX_DEFINITION}",
                text.len()
            )));
        }
        let root = full_name(root, "");
        if package_of(&root).is_empty() {
            return Err(def_err(format!("{root:?} is not pkg/msg/Type")));
        }
        let mut types = BTreeMap::new();
        let mut name = root.clone();
        let mut body = String::new();
        let mut flush = |name: &str, body: &str| -> Result<(), Ros2MsgError> {
            let fields = parse_fields(body, package_of(name))?;
            types.insert(name.to_string(), fields);
            Ok(())
        };
        for line in text.lines() {
            if line.starts_with("====") && line.trim().chars().all(|c| c == '=') {
                flush(&name, &body)?;
                body.clear();
                name.clear();
                continue;
            }
            if name.is_empty() {
                if let Some(t) = line.trim().strip_prefix("MSG:") {
                    name = full_name(t.trim(), "");
                    continue;
                }
                if line.trim().is_empty() {
                    continue;
                }
                return Err(def_err(
                    "a section after ==== must start with MSG: pkg/Type",
                ));
            }
            body.push_str(line);
            body.push('\n');
        }
        if !name.is_empty() {
            flush(&name, &body)?;
        }
        let d = Definitions { root, types };
        d.check(&d.root, 0)?;
        Ok(d)
    }

    /// The root type's full name.
    pub fn root(&self) -> &str {
        &self.root
    }

    /// The fields of `ty`, if defined.
    pub fn fields(&self, ty: &str) -> Option<&[Field]> {
        self.types.get(ty).map(Vec::as_slice)
    }

    fn check(&self, ty: &str, depth: usize) -> Result<(), Ros2MsgError> {
        if depth > MAX_DEPTH {
            return Err(def_err(format!(
                "types nest deeper than {MAX_DEPTH} (a cycle?)"
            )));
        }
        let fields = self
            .types
            .get(ty)
            .ok_or_else(|| def_err(format!("{ty} is used but not defined")))?;
        for f in fields {
            if let Base::Msg(t) = &f.base {
                self.check(t, depth + 1)?;
            }
        }
        Ok(())
    }

    /// Reads a CDR sample (encapsulation header included) into JSON: objects by field
    /// name, numbers, strings; a non-finite float as the string `"inf"`, `"-inf"` or
    /// `"nan"`.
    pub fn decode(&self, bytes: &[u8]) -> Result<Value, Ros2MsgError> {
        if bytes.len() < 4 {
            return Err(Ros2MsgError::Sample(
                "shorter than its 4-byte header".into(),
            ));
        }
        let little = match bytes[1] {
            0 | 2 => false,
            1 | 3 => true,
            other => {
                return Err(Ros2MsgError::Sample(format!(
                    "encapsulation {other} is not plain CDR"
                )))
            }
        };
        let mut r = Reader {
            buf: &bytes[4..],
            at: 0,
            little,
        };
        self.read_msg(&self.root, &mut r, 0)
    }

    fn read_msg(&self, ty: &str, r: &mut Reader, depth: usize) -> Result<Value, Ros2MsgError> {
        let fields = self
            .types
            .get(ty)
            .ok_or_else(|| def_err(format!("{ty} undefined")))?;
        if depth > MAX_DEPTH {
            return Err(def_err("nesting too deep"));
        }
        let mut obj = Map::new();
        for f in fields {
            let v = match f.arity {
                Arity::One => self.read_one(&f.base, r, depth)?,
                Arity::Fixed(n) => self.read_many(&f.base, n, r, depth)?,
                Arity::Seq => {
                    let n = r.u32()? as usize;
                    self.read_many(&f.base, n, r, depth)?
                }
            };
            obj.insert(f.name.clone(), v);
        }
        Ok(Value::Object(obj))
    }

    fn read_many(
        &self,
        base: &Base,
        n: usize,
        r: &mut Reader,
        depth: usize,
    ) -> Result<Value, Ros2MsgError> {
        // Each element takes at least a byte (a message at least one of its fields): a
        // count past the sample's end is corrupt, not a reason to allocate.
        if n > MAX_ELEMENTS || n > r.left() {
            return Err(Ros2MsgError::Sample(format!(
                "{n} elements claimed with {} bytes left",
                r.left()
            )));
        }
        let mut out = Vec::with_capacity(n);
        for _ in 0..n {
            out.push(self.read_one(base, r, depth)?);
        }
        Ok(Value::Array(out))
    }

    fn read_one(&self, base: &Base, r: &mut Reader, depth: usize) -> Result<Value, Ros2MsgError> {
        Ok(match base {
            Base::Msg(t) => self.read_msg(t, r, depth + 1)?,
            Base::Prim(p) => match read_prim(r, *p)? {
                PrimValue::Bool(b) => json!(b),
                PrimValue::U8(v) => json!(v),
                PrimValue::I8(v) => json!(v),
                PrimValue::I16(v) => json!(v),
                PrimValue::U16(v) => json!(v),
                PrimValue::I32(v) => json!(v),
                PrimValue::U32(v) => json!(v),
                PrimValue::I64(v) => json!(v),
                PrimValue::U64(v) => json!(v),
                PrimValue::F32(v) => float(f64::from(v)),
                PrimValue::F64(v) => float(v),
                PrimValue::Str(b) => json!(String::from_utf8_lossy(b)),
            },
        })
    }

    /// Encodes a sample given as JSON in the form [`Definitions::decode`] gives it (an
    /// object per message, arrays for arrays) as little-endian CDR: what a user was shown
    /// can be sent back. A field left out is zero, false, empty or a default message; a
    /// field the definition does not have, or a value of the wrong kind, is an error
    /// that names it.
    pub fn encode_json(&self, value: &Value) -> Result<Vec<u8>, Ros2MsgError> {
        let ordered = self.in_field_order(&self.root, value, 0)?;
        self.transcode(ordered)
            .map_err(|e| Ros2MsgError::Sample(format!("{}: {e}", self.root)))
    }

    /// `v` (an object, or null for a default message of type `ty`) as the arrays in field
    /// order that [`Definitions::transcode`] walks.
    fn in_field_order(&self, ty: &str, v: &Value, depth: usize) -> Result<Value, Ros2MsgError> {
        let bad = |s: String| Ros2MsgError::Sample(s);
        if depth > MAX_DEPTH {
            return Err(bad(format!("{ty}: nested deeper than {MAX_DEPTH}")));
        }
        let fields = self
            .types
            .get(ty)
            .ok_or_else(|| bad(format!("no definition of {ty}")))?;
        let empty = serde_json::Map::new();
        let obj = match v {
            Value::Object(m) => m,
            Value::Null => &empty,
            other => return Err(bad(format!("{ty}: an object expected, not {other}"))),
        };
        if let Some(k) = obj.keys().find(|k| !fields.iter().any(|f| &f.name == *k)) {
            return Err(bad(format!("{ty} has no field {k:?}")));
        }
        let one = |base: &Base, v: &Value| -> Result<Value, Ros2MsgError> {
            match (base, v) {
                (Base::Msg(t), v) => self.in_field_order(t, v, depth + 1),
                (Base::Prim(p), Value::Null) => Ok(match p {
                    Prim::Bool => Value::Bool(false),
                    Prim::Str => Value::String(String::new()),
                    _ => Value::from(0),
                }),
                (Base::Prim(_), v) => Ok(v.clone()),
            }
        };
        let mut out = Vec::with_capacity(fields.len());
        for f in fields {
            let fv = obj.get(&f.name).unwrap_or(&Value::Null);
            let many = |fv: &Value, n: Option<usize>| -> Result<Value, Ros2MsgError> {
                let items: &[Value] = match fv {
                    Value::Array(a) => a,
                    Value::Null => &[],
                    other => {
                        return Err(bad(format!(
                            "{ty}.{}: an array expected, not {other}",
                            f.name
                        )))
                    }
                };
                if items.len() > MAX_ELEMENTS {
                    return Err(bad(format!("{ty}.{}: too many elements", f.name)));
                }
                let mut a = items
                    .iter()
                    .map(|x| one(&f.base, x))
                    .collect::<Result<Vec<_>, _>>()?;
                if let Some(n) = n {
                    if a.len() > n {
                        return Err(bad(format!(
                            "{ty}.{}: {} elements for a fixed array of {n}",
                            f.name,
                            a.len()
                        )));
                    }
                    while a.len() < n {
                        a.push(one(&f.base, &Value::Null)?);
                    }
                }
                Ok(Value::Array(a))
            };
            out.push(match f.arity {
                Arity::One => one(&f.base, fv)?,
                Arity::Fixed(n) => many(fv, Some(n))?,
                Arity::Seq => many(fv, None)?,
            });
        }
        Ok(Value::Array(out))
    }

    /// Walks `d` (a CDR deserializer: the DDS reader's) in the definition's order and
    /// writes the sample as little-endian CDR with its encapsulation header, whatever the
    /// byte order it came in.
    pub fn transcode<'de, D: Deserializer<'de>>(&self, d: D) -> Result<Vec<u8>, D::Error> {
        let mut w = Writer {
            out: vec![0, 1, 0, 0],
        };
        MsgSeed {
            defs: self,
            ty: &self.root,
            w: &mut w,
            depth: 0,
        }
        .deserialize(d)?;
        Ok(w.out)
    }
}

impl Definitions {
    /// Writes `bytes` (a CDR sample with its encapsulation header) into `s` field by
    /// field, as serde calls in the definition's order: a CDR serializer (the DDS
    /// writer's) makes the same message again, so a sample taken as bytes can be
    /// published. A sample that does not match the definition is an error.
    pub fn reserialize<S: serde::Serializer>(&self, bytes: &[u8], s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::{Error, Serialize};
        // Check it whole first: a serializer cannot take back what it wrote.
        self.decode(bytes).map_err(S::Error::custom)?;
        let little = matches!(bytes.get(1), Some(1 | 3));
        let r = std::cell::RefCell::new(Reader {
            buf: &bytes[4..],
            at: 0,
            little,
        });
        MsgOut {
            defs: self,
            ty: &self.root,
            r: &r,
        }
        .serialize(s)
    }
}

struct MsgOut<'a, 'b> {
    defs: &'a Definitions,
    ty: &'a str,
    r: &'a std::cell::RefCell<Reader<'b>>,
}

impl serde::Serialize for MsgOut<'_, '_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::{Error, SerializeTuple};
        let fields = self
            .defs
            .types
            .get(self.ty)
            .ok_or_else(|| S::Error::custom(format!("{} undefined", self.ty)))?;
        let mut t = s.serialize_tuple(fields.len())?;
        for f in fields {
            t.serialize_element(&FieldOut {
                defs: self.defs,
                field: f,
                r: self.r,
            })?;
        }
        t.end()
    }
}

struct FieldOut<'a, 'b> {
    defs: &'a Definitions,
    field: &'a Field,
    r: &'a std::cell::RefCell<Reader<'b>>,
}

impl serde::Serialize for FieldOut<'_, '_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::{Error, SerializeSeq, SerializeTuple};
        let one = OneOut {
            defs: self.defs,
            base: &self.field.base,
            r: self.r,
        };
        match self.field.arity {
            Arity::One => one.serialize(s),
            Arity::Fixed(n) => {
                let mut t = s.serialize_tuple(n)?;
                for _ in 0..n {
                    t.serialize_element(&one)?;
                }
                t.end()
            }
            Arity::Seq => {
                let n = self.r.borrow_mut().u32().map_err(S::Error::custom)? as usize;
                let mut q = s.serialize_seq(Some(n))?;
                for _ in 0..n {
                    q.serialize_element(&one)?;
                }
                q.end()
            }
        }
    }
}

struct OneOut<'a, 'b> {
    defs: &'a Definitions,
    base: &'a Base,
    r: &'a std::cell::RefCell<Reader<'b>>,
}

impl serde::Serialize for OneOut<'_, '_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::Error;
        let p = match self.base {
            Base::Msg(t) => {
                return MsgOut {
                    defs: self.defs,
                    ty: t,
                    r: self.r,
                }
                .serialize(s)
            }
            Base::Prim(p) => *p,
        };
        let v = read_prim(&mut self.r.borrow_mut(), p).map_err(S::Error::custom)?;
        match v {
            PrimValue::Bool(b) => s.serialize_bool(b),
            PrimValue::U8(v) => s.serialize_u8(v),
            PrimValue::I8(v) => s.serialize_i8(v),
            PrimValue::I16(v) => s.serialize_i16(v),
            PrimValue::U16(v) => s.serialize_u16(v),
            PrimValue::I32(v) => s.serialize_i32(v),
            PrimValue::U32(v) => s.serialize_u32(v),
            PrimValue::I64(v) => s.serialize_i64(v),
            PrimValue::U64(v) => s.serialize_u64(v),
            PrimValue::F32(v) => s.serialize_f32(v),
            PrimValue::F64(v) => s.serialize_f64(v),
            PrimValue::Str(b) => s.serialize_str(&String::from_utf8_lossy(b)),
        }
    }
}

/// One primitive read from a sample.
enum PrimValue<'b> {
    Bool(bool),
    U8(u8),
    I8(i8),
    I16(i16),
    U16(u16),
    I32(i32),
    U32(u32),
    I64(i64),
    U64(u64),
    F32(f32),
    F64(f64),
    /// A string's bytes, without its NUL.
    Str(&'b [u8]),
}

fn read_prim<'b>(r: &mut Reader<'b>, p: Prim) -> Result<PrimValue<'b>, Ros2MsgError> {
    Ok(match p {
        Prim::Bool => PrimValue::Bool(r.take(1, 1)?[0] != 0),
        Prim::U8 => PrimValue::U8(r.take(1, 1)?[0]),
        Prim::I8 => PrimValue::I8(r.take(1, 1)?[0] as i8),
        Prim::I16 => PrimValue::I16(r.u16()? as i16),
        Prim::U16 => PrimValue::U16(r.u16()?),
        Prim::I32 => PrimValue::I32(r.u32()? as i32),
        Prim::U32 => PrimValue::U32(r.u32()?),
        Prim::I64 => PrimValue::I64(r.u64()? as i64),
        Prim::U64 => PrimValue::U64(r.u64()?),
        Prim::F32 => PrimValue::F32(f32::from_bits(r.u32()?)),
        Prim::F64 => PrimValue::F64(f64::from_bits(r.u64()?)),
        Prim::Str => {
            let n = r.u32()? as usize;
            let b = r.take(n, 1)?;
            PrimValue::Str(b.strip_suffix(&[0]).unwrap_or(b))
        }
    })
}

fn float(v: f64) -> Value {
    if v.is_finite() {
        json!(v)
    } else if v.is_nan() {
        json!("nan")
    } else if v > 0.0 {
        json!("inf")
    } else {
        json!("-inf")
    }
}

struct Reader<'a> {
    buf: &'a [u8],
    at: usize,
    little: bool,
}

impl<'a> Reader<'a> {
    fn left(&self) -> usize {
        self.buf.len().saturating_sub(self.at)
    }

    fn take(&mut self, n: usize, align: usize) -> Result<&'a [u8], Ros2MsgError> {
        let start = self.at.div_ceil(align) * align;
        let end = start
            .checked_add(n)
            .filter(|&e| e <= self.buf.len())
            .ok_or_else(|| {
                Ros2MsgError::Sample(format!(
                    "cut short: {n} bytes wanted at offset {start} of {}",
                    self.buf.len()
                ))
            })?;
        self.at = end;
        Ok(&self.buf[start..end])
    }

    fn u16(&mut self) -> Result<u16, Ros2MsgError> {
        let b: [u8; 2] = self.take(2, 2)?.try_into().unwrap_or([0; 2]);
        Ok(if self.little {
            u16::from_le_bytes(b)
        } else {
            u16::from_be_bytes(b)
        })
    }

    fn u32(&mut self) -> Result<u32, Ros2MsgError> {
        let b: [u8; 4] = self.take(4, 4)?.try_into().unwrap_or([0; 4]);
        Ok(if self.little {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    }

    fn u64(&mut self) -> Result<u64, Ros2MsgError> {
        let b: [u8; 8] = self.take(8, 8)?.try_into().unwrap_or([0; 8]);
        Ok(if self.little {
            u64::from_le_bytes(b)
        } else {
            u64::from_be_bytes(b)
        })
    }
}

/// Little-endian CDR, aligned from after the encapsulation header.
struct Writer {
    out: Vec<u8>,
}

impl Writer {
    fn align(&mut self, n: usize) {
        while !(self.out.len() - 4).is_multiple_of(n) {
            self.out.push(0);
        }
    }
    fn put(&mut self, bytes: &[u8], align: usize) {
        self.align(align);
        self.out.extend_from_slice(bytes);
    }
    fn string(&mut self, s: &[u8]) {
        self.put(&((s.len() + 1) as u32).to_le_bytes(), 4);
        self.out.extend_from_slice(s);
        self.out.push(0);
    }
}

struct MsgSeed<'a, 'w> {
    defs: &'a Definitions,
    ty: &'a str,
    w: &'w mut Writer,
    depth: usize,
}

impl<'de> DeserializeSeed<'de> for MsgSeed<'_, '_> {
    type Value = ();
    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        let fields = self
            .defs
            .types
            .get(self.ty)
            .ok_or_else(|| de::Error::custom(format!("{} undefined", self.ty)))?;
        if self.depth > MAX_DEPTH {
            return Err(de::Error::custom("nesting too deep"));
        }
        d.deserialize_tuple(fields.len(), FieldsVisitor { seed: self, fields })
    }
}

struct FieldsVisitor<'a, 'w> {
    seed: MsgSeed<'a, 'w>,
    fields: &'a [Field],
}

impl<'de> Visitor<'de> for FieldsVisitor<'_, '_> {
    type Value = ();
    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "a {}", self.seed.ty)
    }
    fn visit_seq<A: SeqAccess<'de>>(self, mut a: A) -> Result<(), A::Error> {
        let MsgSeed { defs, w, depth, .. } = self.seed;
        for f in self.fields {
            let seed = FieldSeed {
                defs,
                field: f,
                w: &mut *w,
                depth,
            };
            a.next_element_seed(seed)?
                .ok_or_else(|| de::Error::custom(format!("field {} missing", f.name)))?;
        }
        Ok(())
    }
}

struct FieldSeed<'a, 'w> {
    defs: &'a Definitions,
    field: &'a Field,
    w: &'w mut Writer,
    depth: usize,
}

impl<'de> DeserializeSeed<'de> for FieldSeed<'_, '_> {
    type Value = ();
    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        let FieldSeed {
            defs,
            field,
            w,
            depth,
        } = self;
        match field.arity {
            Arity::One => OneSeed {
                defs,
                base: &field.base,
                w,
                depth,
            }
            .deserialize(d),
            Arity::Fixed(n) => d.deserialize_tuple(
                n,
                ManyVisitor {
                    defs,
                    base: &field.base,
                    w,
                    depth,
                    count: Some(n),
                },
            ),
            Arity::Seq => d.deserialize_seq(ManyVisitor {
                defs,
                base: &field.base,
                w,
                depth,
                count: None,
            }),
        }
    }
}

struct ManyVisitor<'a, 'w> {
    defs: &'a Definitions,
    base: &'a Base,
    w: &'w mut Writer,
    depth: usize,
    count: Option<usize>,
}

impl<'de> Visitor<'de> for ManyVisitor<'_, '_> {
    type Value = ();
    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("an array")
    }
    fn visit_seq<A: SeqAccess<'de>>(self, mut a: A) -> Result<(), A::Error> {
        let ManyVisitor {
            defs,
            base,
            w,
            depth,
            count,
        } = self;
        // A sequence's length goes first; the CDR reader does not tell it (no size
        // hint), so it is counted and written back.
        let at = count.is_none().then(|| {
            w.align(4);
            w.out.extend_from_slice(&[0; 4]);
            w.out.len() - 4
        });
        let mut n = 0usize;
        while a
            .next_element_seed(OneSeed {
                defs,
                base,
                w: &mut *w,
                depth,
            })?
            .is_some()
        {
            n += 1;
            if n > MAX_ELEMENTS {
                return Err(de::Error::custom(format!(
                    "more than {MAX_ELEMENTS} elements"
                )));
            }
        }
        match (at, count) {
            (Some(at), _) => w.out[at..at + 4].copy_from_slice(&(n as u32).to_le_bytes()),
            (None, Some(c)) if c != n => {
                return Err(de::Error::custom(format!("{n} elements of a [{c}] array")))
            }
            _ => {}
        }
        Ok(())
    }
    // A byte sequence may come as bytes.
    fn visit_bytes<E: de::Error>(self, v: &[u8]) -> Result<(), E> {
        if self.count.is_none() {
            self.w.put(&(v.len() as u32).to_le_bytes(), 4);
        }
        self.w.out.extend_from_slice(v);
        Ok(())
    }
}

struct OneSeed<'a, 'w> {
    defs: &'a Definitions,
    base: &'a Base,
    w: &'w mut Writer,
    depth: usize,
}

impl<'de> DeserializeSeed<'de> for OneSeed<'_, '_> {
    type Value = ();
    fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        let OneSeed {
            defs,
            base,
            w,
            depth,
        } = self;
        match base {
            Base::Msg(t) => MsgSeed {
                defs,
                ty: t,
                w,
                depth: depth + 1,
            }
            .deserialize(d),
            Base::Prim(p) => {
                let v = PrimVisitor { w, prim: *p };
                match p {
                    Prim::Bool => d.deserialize_bool(v),
                    Prim::U8 => d.deserialize_u8(v),
                    Prim::I8 => d.deserialize_i8(v),
                    Prim::I16 => d.deserialize_i16(v),
                    Prim::U16 => d.deserialize_u16(v),
                    Prim::I32 => d.deserialize_i32(v),
                    Prim::U32 => d.deserialize_u32(v),
                    Prim::I64 => d.deserialize_i64(v),
                    Prim::U64 => d.deserialize_u64(v),
                    Prim::F32 => d.deserialize_f32(v),
                    Prim::F64 => d.deserialize_f64(v),
                    Prim::Str => d.deserialize_string(v),
                }
            }
        }
    }
}

struct PrimVisitor<'w> {
    w: &'w mut Writer,
    prim: Prim,
}

impl PrimVisitor<'_> {
    fn int<E: de::Error>(self, v: i128) -> Result<(), E> {
        let size = self.prim.size();
        let b = v.to_le_bytes();
        self.w.put(&b[..size], size);
        Ok(())
    }
}

impl<'de> Visitor<'de> for PrimVisitor<'_> {
    type Value = ();
    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "a {:?}", self.prim)
    }
    fn visit_bool<E: de::Error>(self, v: bool) -> Result<(), E> {
        self.w.out.push(u8::from(v));
        Ok(())
    }
    fn visit_i64<E: de::Error>(self, v: i64) -> Result<(), E> {
        self.int(i128::from(v))
    }
    fn visit_u64<E: de::Error>(self, v: u64) -> Result<(), E> {
        self.int(i128::from(v))
    }
    fn visit_f32<E: de::Error>(self, v: f32) -> Result<(), E> {
        if self.prim == Prim::F64 {
            return self.visit_f64(f64::from(v));
        }
        self.w.put(&v.to_le_bytes(), 4);
        Ok(())
    }
    fn visit_f64<E: de::Error>(self, v: f64) -> Result<(), E> {
        if self.prim == Prim::F32 {
            self.w.put(&(v as f32).to_le_bytes(), 4);
        } else {
            self.w.put(&v.to_le_bytes(), 8);
        }
        Ok(())
    }
    fn visit_str<E: de::Error>(self, v: &str) -> Result<(), E> {
        self.w.string(v.as_bytes());
        Ok(())
    }
    fn visit_bytes<E: de::Error>(self, v: &[u8]) -> Result<(), E> {
        self.w.string(v);
        Ok(())
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    const POINTS: &str = "# A named cloud\nstring name   # who\ngeometry_msgs/Point[] points\nint8 KIND=3\nuint8[2] flags\nfloat32 scale 1.0\n================================================================================\nMSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n";

    fn sample() -> Vec<u8> {
        let mut b = vec![0, 1, 0, 0];
        b.extend_from_slice(&3u32.to_le_bytes());
        b.extend_from_slice(b"ab\0");
        b.push(0); // pad to 4
        b.extend_from_slice(&1u32.to_le_bytes());
        b.extend_from_slice(&[0; 4]); // pad to 8
        for v in [1.5f64, -2.0, f64::INFINITY] {
            b.extend_from_slice(&v.to_le_bytes());
        }
        b.extend_from_slice(&[7, 9]);
        b.extend_from_slice(&[0; 2]);
        b.extend_from_slice(&0.5f32.to_le_bytes());
        b
    }

    #[test]
    fn a_definition_with_dependencies_reads_a_sample() {
        let d = Definitions::parse("my_pkg/Cloud", POINTS).unwrap();
        assert_eq!(d.root(), "my_pkg/msg/Cloud");
        let fields = d.fields("my_pkg/msg/Cloud").unwrap();
        assert_eq!(fields.len(), 4, "the constant is not a field: {fields:?}");
        assert_eq!(fields[1].base, Base::Msg("geometry_msgs/msg/Point".into()));
        assert_eq!(fields[2].arity, Arity::Fixed(2));
        let v = d.decode(&sample()).unwrap();
        assert_eq!(
            v,
            json!({"name": "ab", "points": [{"x": 1.5, "y": -2.0, "z": "inf"}], "flags": [7, 9], "scale": 0.5})
        );
    }

    #[test]
    fn big_endian_samples_read_too() {
        let d = Definitions::parse("p/T", "uint16 a\nuint32 b\n").unwrap();
        let v = d.decode(&[0, 0, 0, 0, 0, 5, 0, 0, 0, 0, 1, 0]).unwrap();
        assert_eq!(v, json!({"a": 5, "b": 256}));
    }

    #[test]
    fn bad_definitions_and_samples_are_errors() {
        assert!(Definitions::parse("p/T", "Missing thing\n")
            .unwrap_err()
            .to_string()
            .contains("p/msg/Missing is used but not defined"));
        assert!(Definitions::parse("p/T", "int32\n").is_err());
        assert!(Definitions::parse("p/T", "int32[x] a\n").is_err());
        assert!(Definitions::parse("p/T", "wstring a\n").is_err());
        // Found by the fuzzer: a name twice (its JSON would keep one of the two).
        let e = Definitions::parse("p/T", "int16 a\nfloat32 a\n").unwrap_err();
        assert!(
            e.to_string().contains("field \"a\" is declared twice"),
            "{e}"
        );
        assert!(Definitions::parse("T", "int32 a\n").is_err());
        let cyclic = "p/A a\n================================================================================\nMSG: p/A\np/A a\n";
        assert!(Definitions::parse("p/T", cyclic).is_err());
        let d = Definitions::parse("my_pkg/Cloud", POINTS).unwrap();
        let s = sample();
        // Every cut of a good sample is an error, never a panic.
        for n in 0..s.len() {
            assert!(d.decode(&s[..n]).is_err(), "cut at {n}");
        }
        // A sequence claiming more elements than bytes.
        let mut huge = s.clone();
        huge[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(d
            .decode(&huge)
            .unwrap_err()
            .to_string()
            .contains("elements claimed"));
        assert!(d.decode(&[0, 9, 0, 0]).is_err());
    }

    proptest::proptest! {
        // Any bytes, and any corruption of a good sample: a value or an error, never a
        // panic; what decodes re-serializes and transcodes back to a sample that decodes
        // the same (non-finite floats aside: JSON has none).
        #[test]
        fn any_sample_decodes_or_is_refused(
            bytes in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..200),
            flips in proptest::collection::vec((0usize..64, proptest::prelude::any::<u8>()), 0..6),
        ) {
            let d = Definitions::parse("my_pkg/Cloud", POINTS).unwrap();
            let _ = d.decode(&bytes);
            let mut s = sample();
            for (at, v) in flips {
                let n = s.len();
                s[at % n] = v;
            }
            if let Ok(v) = d.decode(&s) {
                let walked = d.reserialize(&s, serde_json::value::Serializer).unwrap();
                let text = v.to_string();
                if !text.contains("inf") && !text.contains("nan") {
                    let again = d.decode(&d.transcode(walked).unwrap()).unwrap();
                    proptest::prop_assert_eq!(again, v);
                }
            }
        }
    }

    #[test]
    fn a_sample_reserialized_and_transcoded_comes_back_byte_for_byte() {
        let d = Definitions::parse("my_pkg/Cloud", POINTS).unwrap();
        let s = sample();
        let walked = d.reserialize(&s, serde_json::value::Serializer).unwrap();
        assert_eq!(walked, json!(["ab", [[1.5, -2.0, null]], [7, 9], 0.5]));
        // (JSON has no infinity; through CDR it survives, see the ros2 crate's tests.)
        let mut finite = s.clone();
        finite[36..44].copy_from_slice(&3.0f64.to_le_bytes());
        let walked = d
            .reserialize(&finite, serde_json::value::Serializer)
            .unwrap();
        assert_eq!(d.transcode(walked).unwrap(), finite);
        // A sample that does not match is refused before anything is written.
        assert!(d
            .reserialize(&s[..20], serde_json::value::Serializer)
            .is_err());
    }

    #[test]
    fn a_sample_as_decode_shows_it_encodes_back_and_bad_ones_say_where() {
        let d = Definitions::parse("my_pkg/Cloud", POINTS).unwrap();
        let shown = json!({"name": "ab", "points": [{"x": 1.5, "y": -2.0, "z": 3.0}], "flags": [7, 9], "scale": 0.5});
        let bytes = d.encode_json(&shown).unwrap();
        assert_eq!(d.decode(&bytes).unwrap(), shown);
        // Left out: zero, empty, a default message; a short fixed array is filled.
        let bytes = d
            .encode_json(&json!({"points": [{"x": 1.0}], "flags": [4]}))
            .unwrap();
        assert_eq!(
            d.decode(&bytes).unwrap(),
            json!({"name": "", "points": [{"x": 1.0, "y": 0.0, "z": 0.0}], "flags": [4, 0], "scale": 0.0})
        );
        for (bad, says) in [
            (json!({"nmae": "x"}), "has no field \"nmae\""),
            (json!({"points": 3}), "points: an array expected"),
            (
                json!({"flags": [1, 2, 3]}),
                "3 elements for a fixed array of 2",
            ),
            (json!({"points": [7]}), "an object expected"),
            (json!({"name": 5}), "my_pkg/msg/Cloud"),
            (json!([1]), "an object expected"),
        ] {
            let e = d.encode_json(&bad).unwrap_err().to_string();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn transcoding_gives_little_endian_cdr_that_decodes_the_same() {
        // A JSON deserializer in the definition's field order stands in for the DDS
        // reader's CDR deserializer: both are walked by the definition.
        let d = Definitions::parse("my_pkg/Cloud", POINTS).unwrap();
        let input = json!(["ab", [[1.5, -2.0, 3.0]], [7, 9], 0.5]);
        let bytes = d.transcode(input).unwrap();
        assert_eq!(
            d.decode(&bytes).unwrap(),
            json!({"name": "ab", "points": [{"x": 1.5, "y": -2.0, "z": 3.0}], "flags": [7, 9], "scale": 0.5})
        );
        let mut expect = sample();
        expect[36..44].copy_from_slice(&3.0f64.to_le_bytes());
        assert_eq!(bytes, expect);
    }
}
