//! Minimal NumPy `.npy` reader and writer for the float arrays motion data uses
//! (little-endian f32/f64, C order), so joints, features and stats interchange with numpy.

use crate::error::IngestError;
use std::path::Path;

/// A dense float array read from a `.npy` file, widened to f64.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray {
    /// Array shape (C order).
    pub shape: Vec<usize>,
    /// Values in C order.
    pub data: Vec<f64>,
}

/// Errors from parsing `.npy` bytes.
#[derive(Debug, thiserror::Error)]
pub enum NpyError {
    /// The bytes do not start with the NumPy magic string or the header is malformed.
    #[error("not a .npy file: {0}")]
    Format(String),
    /// The dtype is not one we read.
    #[error("unsupported dtype {0:?} (expected little-endian float32 or float64)")]
    Dtype(String),
    /// The array is stored in Fortran order.
    #[error("Fortran-ordered arrays are not supported")]
    FortranOrder,
    /// The data section is shorter than the header's shape says.
    #[error("truncated data: header says {expected} bytes, file has {actual}")]
    Truncated {
        /// Bytes required by the shape.
        expected: usize,
        /// Bytes present.
        actual: usize,
    },
}

fn header_value<'a>(header: &'a str, key: &str) -> Result<&'a str, NpyError> {
    let pat = format!("'{key}':");
    let start = header
        .find(&pat)
        .ok_or_else(|| NpyError::Format(format!("header lacks {key}")))?
        + pat.len();
    Ok(header[start..].trim_start())
}

/// Parse `.npy` bytes (format versions 1–3) holding f32 or f64 values.
pub fn parse(bytes: &[u8]) -> Result<NpyArray, NpyError> {
    parse_with(bytes, false)
}

/// Parse `.npy` bytes holding floats or little-endian integers (i4, i8, u4, u8), widened to f64
/// (exact below 2^53; index tables such as SMPL's `kintree_table` are stored as integers).
pub fn parse_numeric(bytes: &[u8]) -> Result<NpyArray, NpyError> {
    parse_with(bytes, true)
}

fn parse_with(bytes: &[u8], integers: bool) -> Result<NpyArray, NpyError> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(NpyError::Format("missing \\x93NUMPY magic".into()));
    }
    let (header_len, header_start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        v => return Err(NpyError::Format(format!("unknown format version {v}"))),
    };
    let data_start = header_start + header_len;
    let header = bytes
        .get(header_start..data_start)
        .and_then(|h| std::str::from_utf8(h).ok())
        .ok_or_else(|| NpyError::Format("header truncated or not text".into()))?;
    let descr = header_value(header, "descr")?;
    let descr = descr
        .trim_start_matches(['\'', '"'])
        .split(['\'', '"'])
        .next()
        .unwrap_or("");
    let (kind, width) = match descr.trim_start_matches(['<', '=']) {
        "f4" => ('f', 4),
        "f8" => ('f', 8),
        "i4" if integers => ('i', 4),
        "i8" if integers => ('i', 8),
        "u4" if integers => ('u', 4),
        "u8" if integers => ('u', 8),
        _ => return Err(NpyError::Dtype(descr.to_string())),
    };
    if header_value(header, "fortran_order")?.starts_with("True") {
        return Err(NpyError::FortranOrder);
    }
    let shape_text = header_value(header, "shape")?;
    let shape_text = shape_text
        .strip_prefix('(')
        .and_then(|s| s.split(')').next())
        .ok_or_else(|| NpyError::Format("malformed shape".into()))?;
    let shape = shape_text
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .map_err(|_| NpyError::Format(format!("bad shape entry {s:?}")))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let count: usize = shape.iter().product();
    let payload = &bytes[data_start.min(bytes.len())..];
    let expected = count * width;
    if payload.len() < expected {
        return Err(NpyError::Truncated {
            expected,
            actual: payload.len(),
        });
    }
    let data = payload[..expected]
        .chunks_exact(width)
        .map(|c| {
            let mut b = [0u8; 8];
            b[..width].copy_from_slice(c);
            match (kind, width) {
                ('f', 4) => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
                ('f', _) => f64::from_le_bytes(b),
                ('i', 4) => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
                ('i', _) => i64::from_le_bytes(b) as f64,
                ('u', 4) => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
                _ => u64::from_le_bytes(b) as f64,
            }
        })
        .collect();
    Ok(NpyArray { shape, data })
}

/// Read a `.npy` file; the error names the file.
pub fn read(path: &Path) -> Result<NpyArray, IngestError> {
    let bytes = std::fs::read(path).map_err(|e| IngestError::io(path, e))?;
    parse(&bytes).map_err(IngestError::at(path))
}

/// Encode f32 values with the given shape as `.npy` (version 1.0) bytes.
pub fn encode_f32(shape: &[usize], data: &[f32]) -> Vec<u8> {
    assert_eq!(
        shape.iter().product::<usize>(),
        data.len(),
        "shape does not match data"
    );
    let shape_text = match shape {
        [n] => format!("({n},)"),
        dims => format!(
            "({})",
            dims.iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape_text}, }}");
    // Pad so the data starts on a 64-byte boundary, header ends with '\n'.
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + data.len() * 4);
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Write an f32 array as a `.npy` file, atomically.
pub fn write_f32(path: &Path, shape: &[usize], data: &[f32]) -> std::io::Result<()> {
    motionscale_core::write_atomic(path, &encode_f32(shape, data))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_f32() {
        let data: Vec<f32> = (0..24).map(|i| i as f32 * 0.5).collect();
        let bytes = encode_f32(&[2, 4, 3], &data);
        assert_eq!((bytes.len() - data.len() * 4) % 64, 0);
        let arr = parse(&bytes).unwrap();
        assert_eq!(arr.shape, vec![2, 4, 3]);
        assert_eq!(arr.data[5], 2.5);
        let one_d = parse(&encode_f32(&[3], &[1.0, 2.0, 3.0])).unwrap();
        assert_eq!(one_d.shape, vec![3]);
    }

    #[test]
    fn rejects_bad_input() {
        assert!(matches!(parse(b"hello world"), Err(NpyError::Format(_))));
        let mut bytes = encode_f32(&[4], &[1.0; 4]);
        bytes.truncate(bytes.len() - 3);
        assert!(matches!(parse(&bytes), Err(NpyError::Truncated { .. })));
        let mut ints = encode_f32(&[1], &[0.0]);
        let at = ints.windows(3).position(|w| w == b"<f4").unwrap();
        ints[at + 1] = b'i';
        assert!(matches!(parse(&ints), Err(NpyError::Dtype(d)) if d == "<i4"));
    }

    #[test]
    fn numeric_parse_widens_integers() {
        let mut bytes = encode_f32(&[2], &[0.0; 2]);
        let at = bytes.windows(3).position(|w| w == b"<f4").unwrap();
        bytes[at + 1] = b'u';
        let n = bytes.len();
        bytes[n - 8..n - 4].copy_from_slice(&u32::MAX.to_le_bytes());
        bytes[n - 4..].copy_from_slice(&7u32.to_le_bytes());
        let arr = parse_numeric(&bytes).unwrap();
        assert_eq!(arr.data, vec![4294967295.0, 7.0]);
        bytes[at + 1] = b'i';
        assert_eq!(parse_numeric(&bytes).unwrap().data, vec![-1.0, 7.0]);
    }
}
