//! The bridge's wire format: `b"MTE1"`, a little-endian `u32` header length, the header
//! (UTF-8 JSON object), then the raw little-endian bytes of the arrays the header's
//! `"arrays"` list names (`{"name", "dtype": "f32" | "f64" | "u8", "shape"}`), in order. No
//! pickle, nothing language-specific: the worker (`worker.py`) speaks the same format.

use std::io::{Read, Write};

use serde_json::{Map, Value, json};

/// The four bytes that start every frame.
pub const MAGIC: &[u8; 4] = b"MTE1";
/// Largest header accepted (bytes): a header is a few hundred bytes; more means a stream
/// out of step.
const MAX_HEADER: usize = 1 << 20;
/// Largest array accepted (elements): 64 Mi elements, far above any observation.
const MAX_ELEMENTS: usize = 1 << 26;

/// A malformed or interrupted frame.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FrameError {
    /// Reading or writing the stream failed.
    #[error("bridge stream: {0}")]
    Io(#[from] std::io::Error),
    /// The stream does not start a frame where one should start.
    #[error(
        "bridge frame starts with {got:?}: expected {:?} (is something else writing to the worker's stdout?)",
        MAGIC
    )]
    Magic {
        /// The bytes read instead.
        got: [u8; 4],
    },
    /// The header is not a JSON object, or names a bad array.
    #[error("bridge frame header: {0}")]
    Header(String),
}

/// One array of a frame.
#[derive(Clone, Debug, PartialEq)]
pub enum ArrayData {
    /// `f32` values.
    F32(Vec<f32>),
    /// `f64` values.
    F64(Vec<f64>),
    /// Bytes.
    U8(Vec<u8>),
}

impl ArrayData {
    fn dtype(&self) -> &'static str {
        match self {
            ArrayData::F32(_) => "f32",
            ArrayData::F64(_) => "f64",
            ArrayData::U8(_) => "u8",
        }
    }

    fn len(&self) -> usize {
        match self {
            ArrayData::F32(v) => v.len(),
            ArrayData::F64(v) => v.len(),
            ArrayData::U8(v) => v.len(),
        }
    }
}

/// A named array with its shape (C order).
#[derive(Clone, Debug, PartialEq)]
pub struct Array {
    /// Name.
    pub name: String,
    /// Shape.
    pub shape: Vec<usize>,
    /// Values (`shape`'s product of them).
    pub data: ArrayData,
}

/// One message: a JSON header and arrays.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Frame {
    /// The header's fields (without `"arrays"`, which the codec writes).
    pub header: Map<String, Value>,
    /// The arrays, in wire order.
    pub arrays: Vec<Array>,
}

impl Frame {
    /// A frame with header `value` (a JSON object; anything else becomes an empty header).
    pub fn new(value: Value) -> Self {
        Self {
            header: match value {
                Value::Object(m) => m,
                _ => Map::new(),
            },
            arrays: Vec::new(),
        }
    }

    /// Adds a 1-D `f32` array.
    pub fn with_f32(mut self, name: &str, values: &[f32]) -> Self {
        self.arrays.push(Array {
            name: name.into(),
            shape: vec![values.len()],
            data: ArrayData::F32(values.to_vec()),
        });
        self
    }

    /// The array called `name`.
    pub fn array(&self, name: &str) -> Option<&Array> {
        self.arrays.iter().find(|a| a.name == name)
    }
}

/// Writes `frame` and flushes.
pub fn write_frame(w: &mut impl Write, frame: &Frame) -> Result<(), FrameError> {
    let mut header = frame.header.clone();
    let specs: Vec<Value> = frame
        .arrays
        .iter()
        .map(|a| json!({"name": a.name, "dtype": a.data.dtype(), "shape": a.shape}))
        .collect();
    header.insert("arrays".into(), Value::Array(specs));
    let text = serde_json::to_vec(&Value::Object(header))
        .map_err(|e| FrameError::Header(e.to_string()))?;
    let n = u32::try_from(text.len())
        .map_err(|_| FrameError::Header(format!("{} bytes of header", text.len())))?;
    let mut buf = Vec::with_capacity(8 + text.len());
    buf.extend_from_slice(MAGIC);
    buf.extend_from_slice(&n.to_le_bytes());
    buf.extend_from_slice(&text);
    for a in &frame.arrays {
        match &a.data {
            ArrayData::F32(v) => v
                .iter()
                .for_each(|x| buf.extend_from_slice(&x.to_le_bytes())),
            ArrayData::F64(v) => v
                .iter()
                .for_each(|x| buf.extend_from_slice(&x.to_le_bytes())),
            ArrayData::U8(v) => buf.extend_from_slice(v),
        }
    }
    w.write_all(&buf)?;
    w.flush()?;
    Ok(())
}

/// Reads one frame; `None` at a clean end of stream (before a frame starts).
pub fn read_frame(r: &mut impl Read) -> Result<Option<Frame>, FrameError> {
    let mut head = [0u8; 8];
    match r.read(&mut head[..1])? {
        0 => return Ok(None),
        _ => r.read_exact(&mut head[1..])?,
    }
    let got: [u8; 4] = [head[0], head[1], head[2], head[3]];
    if &got != MAGIC {
        return Err(FrameError::Magic { got });
    }
    let n = u32::from_le_bytes([head[4], head[5], head[6], head[7]]) as usize;
    if n > MAX_HEADER {
        return Err(FrameError::Header(format!(
            "{n} bytes: expected at most {MAX_HEADER}"
        )));
    }
    let mut text = vec![0u8; n];
    r.read_exact(&mut text)?;
    let Value::Object(mut header) =
        serde_json::from_slice(&text).map_err(|e| FrameError::Header(e.to_string()))?
    else {
        return Err(FrameError::Header("not a JSON object".into()));
    };
    let specs = match header.remove("arrays") {
        None | Some(Value::Null) => Vec::new(),
        Some(Value::Array(s)) => s,
        Some(other) => {
            return Err(FrameError::Header(format!(
                "\"arrays\" = {other}: expected a list"
            )));
        }
    };
    let arrays = specs
        .iter()
        .map(|s| read_array(r, s))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Some(Frame { header, arrays }))
}

fn read_array(r: &mut impl Read, spec: &Value) -> Result<Array, FrameError> {
    let bad = |what: &str| FrameError::Header(format!("array spec {spec}: {what}"));
    let name = spec["name"].as_str().ok_or_else(|| bad("no \"name\""))?;
    let shape: Vec<usize> = spec["shape"]
        .as_array()
        .ok_or_else(|| bad("no \"shape\" list"))?
        .iter()
        .map(|d| {
            d.as_u64()
                .map(|d| d as usize)
                .ok_or_else(|| bad("a negative or non-integer dimension"))
        })
        .collect::<Result<_, _>>()?;
    let count = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .filter(|&c| c <= MAX_ELEMENTS)
        .ok_or_else(|| bad(&format!("more than {MAX_ELEMENTS} elements")))?;
    let data = match spec["dtype"].as_str() {
        Some("f32") => ArrayData::F32(
            read_bytes(r, count * 4)?
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect(),
        ),
        Some("f64") => ArrayData::F64(
            read_bytes(r, count * 8)?
                .chunks_exact(8)
                .map(|b| f64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
                .collect(),
        ),
        Some("u8") => ArrayData::U8(read_bytes(r, count)?),
        _ => return Err(bad("dtype: expected \"f32\", \"f64\" or \"u8\"")),
    };
    debug_assert_eq!(data.len(), count);
    Ok(Array {
        name: name.into(),
        shape,
        data,
    })
}

fn read_bytes(r: &mut impl Read, n: usize) -> Result<Vec<u8>, FrameError> {
    let mut b = vec![0u8; n];
    r.read_exact(&mut b)?;
    Ok(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Frame {
        let mut f = Frame::new(json!({"op": "observe", "seed": 7})).with_f32("state", &[1.5, -2.0]);
        f.arrays.push(Array {
            name: "image".into(),
            shape: vec![2, 1, 3],
            data: ArrayData::U8(vec![0, 1, 2, 253, 254, 255]),
        });
        f.arrays.push(Array {
            name: "x".into(),
            shape: vec![0],
            data: ArrayData::F64(vec![]),
        });
        f
    }

    #[test]
    fn frames_round_trip_back_to_back() {
        let mut buf = Vec::new();
        write_frame(&mut buf, &sample()).unwrap();
        write_frame(&mut buf, &Frame::new(json!({"ok": true}))).unwrap();
        let mut r = buf.as_slice();
        assert_eq!(read_frame(&mut r).unwrap(), Some(sample()));
        let second = read_frame(&mut r).unwrap().expect("second frame");
        assert_eq!(second.header["ok"], json!(true));
        assert!(second.arrays.is_empty());
        assert!(read_frame(&mut r).unwrap().is_none(), "clean end");
    }

    #[test]
    fn malformed_frames_are_typed_errors() {
        let mut buf = Vec::new();
        write_frame(&mut buf, &sample()).unwrap();
        // Noise where a frame should start (a library printing to stdout).
        let e = read_frame(&mut &b"Hello from pygame"[..]).unwrap_err();
        assert!(
            matches!(e, FrameError::Magic { got } if &got == b"Hell"),
            "{e}"
        );
        // Truncated inside an array.
        let e = read_frame(&mut &buf[..buf.len() - 2]).unwrap_err();
        assert!(matches!(e, FrameError::Io(_)), "{e}");
        // A header that is not an object, and a bad dtype.
        for text in [
            &b"[1, 2]"[..],
            br#"{"arrays": [{"name": "a", "dtype": "i64", "shape": [1]}]}"#,
        ] {
            let mut f = MAGIC.to_vec();
            f.extend_from_slice(&(text.len() as u32).to_le_bytes());
            f.extend_from_slice(text);
            let e = read_frame(&mut f.as_slice()).unwrap_err();
            assert!(matches!(e, FrameError::Header(_)), "{e}");
        }
        // A header length far beyond the limit.
        let mut f = MAGIC.to_vec();
        f.extend_from_slice(&u32::MAX.to_le_bytes());
        assert!(
            read_frame(&mut f.as_slice())
                .unwrap_err()
                .to_string()
                .contains("at most")
        );
    }
}
