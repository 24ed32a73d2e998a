//! NPY (format version 1.0) arrays: streaming writer and reader for the few dtypes we store.
//!
//! The header is padded to a fixed [`HEADER_LEN`] bytes so that a writer can append rows and
//! rewrite the shape at the end without moving data. Files are little-endian, C order, and
//! load with `numpy.load` unchanged.

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::error::DataError;

/// Total header length (magic + version + length field + dict, padded): a multiple of 64.
pub const HEADER_LEN: usize = 128;
const MAGIC: &[u8] = b"\x93NUMPY";

/// Element types we store.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DType {
    /// `<f4`
    F32,
    /// `|u1`
    U8,
    /// `<i8`
    I64,
    /// `|b1`
    Bool,
}

impl DType {
    /// numpy's type string.
    pub fn descr(self) -> &'static str {
        match self {
            DType::F32 => "<f4",
            DType::U8 => "|u1",
            DType::I64 => "<i8",
            DType::Bool => "|b1",
        }
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            DType::F32 => 4,
            DType::U8 | DType::Bool => 1,
            DType::I64 => 8,
        }
    }

    fn from_descr(s: &str) -> Option<Self> {
        [DType::F32, DType::U8, DType::I64, DType::Bool]
            .into_iter()
            .find(|d| d.descr() == s)
    }
}

fn header(dtype: DType, rows: usize, inner: &[usize]) -> Vec<u8> {
    let mut shape = format!("({rows},");
    for d in inner {
        shape += &format!(" {d},");
    }
    if !inner.is_empty() {
        shape.pop();
    }
    shape.push(')');
    let dict = format!(
        "{{'descr': '{}', 'fortran_order': False, 'shape': {shape}, }}",
        dtype.descr()
    );
    let mut h = Vec::with_capacity(HEADER_LEN);
    h.extend_from_slice(MAGIC);
    h.extend_from_slice(&[1, 0]);
    let dict_len = HEADER_LEN - 10;
    h.extend_from_slice(&(dict_len as u16).to_le_bytes());
    h.extend_from_slice(dict.as_bytes());
    while h.len() < HEADER_LEN - 1 {
        h.push(b' ');
    }
    h.push(b'\n');
    h
}

/// Appends rows of a fixed inner shape to an `.npy` file; [`NpyWriter::finish`] writes the
/// final row count into the header.
pub struct NpyWriter {
    path: PathBuf,
    file: BufWriter<File>,
    dtype: DType,
    inner: Vec<usize>,
    row_len: usize,
    rows: usize,
}

impl NpyWriter {
    /// Create (truncate) `path` for rows of shape `inner`.
    pub fn create(path: &Path, dtype: DType, inner: &[usize]) -> Result<Self, DataError> {
        let file = File::create(path).map_err(|e| DataError::io(path, e))?;
        let mut file = BufWriter::with_capacity(1 << 20, file);
        let h = header(dtype, 0, inner);
        if h.len() != HEADER_LEN {
            return Err(DataError::Format {
                path: path.to_path_buf(),
                reason: format!("shape {inner:?} does not fit a {HEADER_LEN}-byte header"),
            });
        }
        file.write_all(&h).map_err(|e| DataError::io(path, e))?;
        Ok(NpyWriter {
            path: path.to_path_buf(),
            file,
            dtype,
            inner: inner.to_vec(),
            row_len: inner.iter().product(),
            rows: 0,
        })
    }

    fn check(&self, len: usize, dtype: DType) -> Result<usize, DataError> {
        if dtype != self.dtype || self.row_len == 0 || !len.is_multiple_of(self.row_len) {
            return Err(DataError::Format {
                path: self.path.clone(),
                reason: format!(
                    "appending {len} {dtype:?} values to rows of {} {:?} values",
                    self.row_len, self.dtype
                ),
            });
        }
        Ok(len / self.row_len)
    }

    /// Append f32 rows (length a multiple of the row length).
    pub fn append_f32(&mut self, values: &[f32]) -> Result<(), DataError> {
        let rows = self.check(values.len(), DType::F32)?;
        for v in values {
            self.file
                .write_all(&v.to_le_bytes())
                .map_err(|e| DataError::io(&self.path, e))?;
        }
        self.rows += rows;
        Ok(())
    }

    /// Append u8 rows.
    pub fn append_u8(&mut self, values: &[u8]) -> Result<(), DataError> {
        let rows = self.check(values.len(), DType::U8)?;
        self.file
            .write_all(values)
            .map_err(|e| DataError::io(&self.path, e))?;
        self.rows += rows;
        Ok(())
    }

    /// Append i64 rows.
    pub fn append_i64(&mut self, values: &[i64]) -> Result<(), DataError> {
        let rows = self.check(values.len(), DType::I64)?;
        for v in values {
            self.file
                .write_all(&v.to_le_bytes())
                .map_err(|e| DataError::io(&self.path, e))?;
        }
        self.rows += rows;
        Ok(())
    }

    /// Append bool rows.
    pub fn append_bool(&mut self, values: &[bool]) -> Result<(), DataError> {
        let rows = self.check(values.len(), DType::Bool)?;
        for &v in values {
            self.file
                .write_all(&[u8::from(v)])
                .map_err(|e| DataError::io(&self.path, e))?;
        }
        self.rows += rows;
        Ok(())
    }

    /// Rewrite the header with the final row count and flush. Returns the row count.
    pub fn finish(mut self) -> Result<usize, DataError> {
        let h = header(self.dtype, self.rows, &self.inner);
        if h.len() != HEADER_LEN {
            return Err(DataError::Format {
                path: self.path.clone(),
                reason: format!("{} rows do not fit a {HEADER_LEN}-byte header", self.rows),
            });
        }
        let p = self.path.clone();
        self.file.flush().map_err(|e| DataError::io(&p, e))?;
        let file = self.file.get_mut();
        file.seek(SeekFrom::Start(0))
            .map_err(|e| DataError::io(&p, e))?;
        file.write_all(&h).map_err(|e| DataError::io(&p, e))?;
        file.sync_all().map_err(|e| DataError::io(&p, e))?;
        Ok(self.rows)
    }
}

/// An array read back from an `.npy` file.
#[derive(Clone, Debug, PartialEq)]
pub struct NpyArray {
    /// Element type.
    pub dtype: DType,
    /// Full shape, rows first.
    pub shape: Vec<usize>,
    /// Raw little-endian bytes, C order.
    pub data: Vec<u8>,
}

impl NpyArray {
    /// Read a whole file (format 1.0 or 2.0, C order, one of our dtypes).
    pub fn read(path: &Path) -> Result<Self, DataError> {
        let bad = |reason: String| DataError::Format {
            path: path.to_path_buf(),
            reason,
        };
        let mut f = BufReader::new(File::open(path).map_err(|e| DataError::io(path, e))?);
        let mut pre = [0u8; 8];
        f.read_exact(&mut pre).map_err(|e| DataError::io(path, e))?;
        if &pre[..6] != MAGIC {
            return Err(bad("not an .npy file (bad magic)".into()));
        }
        let hlen = match pre[6] {
            1 => {
                let mut b = [0u8; 2];
                f.read_exact(&mut b).map_err(|e| DataError::io(path, e))?;
                usize::from(u16::from_le_bytes(b))
            }
            2 | 3 => {
                let mut b = [0u8; 4];
                f.read_exact(&mut b).map_err(|e| DataError::io(path, e))?;
                u32::from_le_bytes(b) as usize
            }
            v => return Err(bad(format!("unsupported .npy version {v}"))),
        };
        let mut dict = vec![0u8; hlen];
        f.read_exact(&mut dict)
            .map_err(|e| DataError::io(path, e))?;
        let dict = String::from_utf8_lossy(&dict);
        let field = |key: &str| -> Option<String> {
            let i = dict.find(&format!("'{key}':"))? + key.len() + 3;
            let rest = dict[i..].trim_start();
            if let Some(r) = rest.strip_prefix('\'') {
                Some(r[..r.find('\'')?].to_string())
            } else if let Some(r) = rest.strip_prefix('(') {
                Some(r[..r.find(')')?].to_string())
            } else {
                Some(rest[..rest.find(',')?].trim().to_string())
            }
        };
        let descr = field("descr").ok_or_else(|| bad("header has no descr".into()))?;
        let dtype =
            DType::from_descr(&descr).ok_or_else(|| bad(format!("unsupported dtype {descr}")))?;
        if field("fortran_order").as_deref() != Some("False") {
            return Err(bad("Fortran-ordered arrays are not supported".into()));
        }
        let shape_s = field("shape").ok_or_else(|| bad("header has no shape".into()))?;
        let shape = shape_s
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(|s| {
                s.parse::<usize>()
                    .map_err(|_| bad(format!("bad shape ({shape_s})")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let n: usize = shape.iter().product::<usize>() * dtype.size();
        let mut data = Vec::with_capacity(n);
        f.read_to_end(&mut data)
            .map_err(|e| DataError::io(path, e))?;
        if data.len() != n {
            return Err(bad(format!(
                "shape {shape:?} needs {n} bytes of data, the file has {}",
                data.len()
            )));
        }
        Ok(NpyArray { dtype, shape, data })
    }

    /// Number of rows (first dimension).
    pub fn rows(&self) -> usize {
        self.shape.first().copied().unwrap_or(1)
    }

    /// Elements per row.
    pub fn row_len(&self) -> usize {
        self.shape.iter().skip(1).product()
    }

    fn expect(&self, dtype: DType) -> Result<(), DataError> {
        if self.dtype == dtype {
            Ok(())
        } else {
            Err(DataError::Format {
                path: PathBuf::new(),
                reason: format!("array has dtype {:?}, expected {dtype:?}", self.dtype),
            })
        }
    }

    /// The values as f32.
    pub fn to_f32(&self) -> Result<Vec<f32>, DataError> {
        self.expect(DType::F32)?;
        Ok(self
            .data
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect())
    }

    /// The values as i64.
    pub fn to_i64(&self) -> Result<Vec<i64>, DataError> {
        self.expect(DType::I64)?;
        Ok(self
            .data
            .chunks_exact(8)
            .map(|b| i64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
            .collect())
    }

    /// The values as bool.
    pub fn to_bool(&self) -> Result<Vec<bool>, DataError> {
        self.expect(DType::Bool)?;
        Ok(self.data.iter().map(|&b| b != 0).collect())
    }

    /// The values as u8 (images).
    pub fn into_u8(self) -> Result<Vec<u8>, DataError> {
        self.expect(DType::U8)?;
        Ok(self.data)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_every_dtype() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = dir.path().join("a.npy");
        let mut w = NpyWriter::create(&p, DType::F32, &[2, 3]).expect("create");
        w.append_f32(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
            .expect("append");
        w.append_f32(&[-1.5; 6]).expect("append");
        assert_eq!(w.finish().expect("finish"), 2);
        let a = NpyArray::read(&p).expect("read");
        assert_eq!(a.shape, vec![2, 2, 3]);
        assert_eq!(a.to_f32().expect("f32")[5], 6.0);
        assert_eq!(
            std::fs::metadata(&p).expect("meta").len() as usize,
            HEADER_LEN + 48
        );

        let p = dir.path().join("b.npy");
        let mut w = NpyWriter::create(&p, DType::I64, &[]).expect("create");
        w.append_i64(&[3, -4, 5]).expect("append");
        w.finish().expect("finish");
        let a = NpyArray::read(&p).expect("read");
        assert_eq!(a.shape, vec![3]);
        assert_eq!(a.to_i64().expect("i64"), vec![3, -4, 5]);

        let p = dir.path().join("c.npy");
        let mut w = NpyWriter::create(&p, DType::Bool, &[]).expect("create");
        w.append_bool(&[true, false]).expect("append");
        w.finish().expect("finish");
        assert_eq!(
            NpyArray::read(&p).expect("read").to_bool().expect("bool"),
            vec![true, false]
        );
    }

    #[test]
    fn wrong_row_length_and_dtype_are_errors() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = dir.path().join("a.npy");
        let mut w = NpyWriter::create(&p, DType::F32, &[2]).expect("create");
        assert!(w.append_f32(&[1.0, 2.0, 3.0]).is_err());
        assert!(w.append_u8(&[1, 2]).is_err());
    }

    #[test]
    fn truncated_file_is_an_error_naming_the_sizes() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = dir.path().join("a.npy");
        let mut w = NpyWriter::create(&p, DType::F32, &[2]).expect("create");
        w.append_f32(&[1.0, 2.0, 3.0, 4.0]).expect("append");
        w.finish().expect("finish");
        let bytes = std::fs::read(&p).expect("read");
        std::fs::write(&p, &bytes[..bytes.len() - 3]).expect("write");
        let e = NpyArray::read(&p).expect_err("truncated").to_string();
        assert!(e.contains("needs 16 bytes"), "{e}");
    }
}
