//! Reading and writing 2-D NumPy `.npy` arrays (heightmaps exchanged with Python tools).
//!
//! Reads format versions 1.0, 2.0 and 3.0 holding a 2-D array of `<f4`/`<f8`/`>f4`/`>f8`, or, as a
//! convenience for integer maps, `i1`/`u1`/`i2`/`u2`/`i4`/`u4` in either byte order. Both C order
//! and Fortran order (`fortran_order: True`, column-major bytes) are read into row-major samples.
//! Writes version 1.0 `<f8` in C order. Row index = y, column index = x (design notes, Sec. 1).

use crate::error::{Error, Result};
use std::path::Path;

const MAGIC: &[u8; 6] = b"\x93NUMPY";

/// Element type of the array, from its `descr` string.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Kind {
    F4,
    F8,
    I1,
    U1,
    I2,
    U2,
    I4,
    U4,
}

impl Kind {
    fn size(self) -> usize {
        match self {
            Kind::I1 | Kind::U1 => 1,
            Kind::I2 | Kind::U2 => 2,
            Kind::F4 | Kind::I4 | Kind::U4 => 4,
            Kind::F8 => 8,
        }
    }
}

/// Parse a `descr` such as `<f8`, `>f4`, `|u1` into (kind, big_endian).
fn parse_descr(descr: &str, ctx: &str) -> Result<(Kind, bool)> {
    let bad = || {
        Error::new(
            ctx,
            format!(
                "unsupported dtype '{descr}' (expected a 2-D array of <f4, <f8, >f4, >f8, or the integer \
                 types i1, u1, i2, u2, i4, u4)"
            ),
        )
    };
    let mut chars = descr.chars();
    let order = chars.next().ok_or_else(bad)?;
    let big = match order {
        '<' | '|' => false,
        '>' => true,
        '=' => cfg!(target_endian = "big"),
        _ => return Err(bad()),
    };
    let kind = match chars.as_str() {
        "f4" => Kind::F4,
        "f8" => Kind::F8,
        "i1" | "b" => Kind::I1,
        "u1" | "B" => Kind::U1,
        "i2" => Kind::I2,
        "u2" => Kind::U2,
        "i4" => Kind::I4,
        "u4" => Kind::U4,
        _ => return Err(bad()),
    };
    Ok((kind, big))
}

/// Value of `key` in the header dictionary: the text after `'key':` up to the matching end.
fn header_value<'a>(header: &'a str, key: &str, ctx: &str) -> Result<&'a str> {
    let pat_s = format!("'{key}'");
    let pat_d = format!("\"{key}\"");
    let pos = header
        .find(&pat_s)
        .map(|p| p + pat_s.len())
        .or_else(|| header.find(&pat_d).map(|p| p + pat_d.len()))
        .ok_or_else(|| {
            Error::new(
                ctx,
                format!("the .npy header has no '{key}' entry (header: {header})"),
            )
        })?;
    let rest = header[pos..].trim_start();
    let rest = rest.strip_prefix(':').ok_or_else(|| {
        Error::new(
            ctx,
            format!("the .npy header entry '{key}' has no ':' (header: {header})"),
        )
    })?;
    Ok(rest.trim_start())
}

struct Header {
    kind: Kind,
    big: bool,
    fortran: bool,
    shape: Vec<usize>,
}

fn parse_header(header: &str, ctx: &str) -> Result<Header> {
    // descr: a quoted string
    let d = header_value(header, "descr", ctx)?;
    let quote = d.chars().next().unwrap_or(' ');
    if quote != '\'' && quote != '"' {
        return Err(Error::new(
            ctx,
            format!("the .npy 'descr' is not a simple dtype string (structured arrays are not supported): {header}"),
        ));
    }
    let end = d[1..].find(quote).ok_or_else(|| {
        Error::new(
            ctx,
            format!("unterminated 'descr' in the .npy header: {header}"),
        )
    })?;
    let (kind, big) = parse_descr(&d[1..1 + end], ctx)?;

    let f = header_value(header, "fortran_order", ctx)?;
    let fortran = if f.starts_with("True") {
        true
    } else if f.starts_with("False") {
        false
    } else {
        return Err(Error::new(
            ctx,
            format!("'fortran_order' must be True or False in the .npy header: {header}"),
        ));
    };

    let s = header_value(header, "shape", ctx)?;
    let s = s.strip_prefix('(').ok_or_else(|| {
        Error::new(
            ctx,
            format!("'shape' must be a tuple in the .npy header: {header}"),
        )
    })?;
    let close = s.find(')').ok_or_else(|| {
        Error::new(
            ctx,
            format!("unterminated 'shape' tuple in the .npy header: {header}"),
        )
    })?;
    let mut shape = Vec::new();
    for part in s[..close].split(',') {
        let p = part.trim().trim_end_matches('L');
        if p.is_empty() {
            continue;
        }
        let v: usize = p.parse().map_err(|_| {
            Error::new(
                ctx,
                format!("'shape' entry '{p}' is not a non-negative integer: {header}"),
            )
        })?;
        shape.push(v);
    }
    Ok(Header {
        kind,
        big,
        fortran,
        shape,
    })
}

fn decode(kind: Kind, big: bool, b: &[u8]) -> f64 {
    macro_rules! get {
        ($t:ty, $n:expr) => {{
            let mut a = [0u8; $n];
            a.copy_from_slice(b);
            if big {
                <$t>::from_be_bytes(a)
            } else {
                <$t>::from_le_bytes(a)
            }
        }};
    }
    match kind {
        Kind::F4 => get!(f32, 4) as f64,
        Kind::F8 => get!(f64, 8),
        Kind::I1 => b[0] as i8 as f64,
        Kind::U1 => b[0] as f64,
        Kind::I2 => get!(i16, 2) as f64,
        Kind::U2 => get!(u16, 2) as f64,
        Kind::I4 => get!(i32, 4) as f64,
        Kind::U4 => get!(u32, 4) as f64,
    }
}

/// Parse the bytes of a `.npy` file; `ctx` names the file in errors.
pub fn parse_npy_2d(bytes: &[u8], ctx: &str) -> Result<(usize, usize, Vec<f64>)> {
    if bytes.len() < 10 || &bytes[..6] != MAGIC {
        return Err(Error::new(
            ctx,
            "not a NumPy .npy file (expected the magic bytes \\x93NUMPY at the start)",
        ));
    }
    let (major, minor) = (bytes[6], bytes[7]);
    let (hlen, hstart) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10usize),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(Error::new(
                    ctx,
                    "truncated .npy file: the header length is missing",
                ));
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        _ => {
            return Err(Error::new(
                ctx,
                format!(
                    "unsupported .npy format version {major}.{minor} (expected 1.0, 2.0 or 3.0)"
                ),
            ))
        }
    };
    let data_start = hstart
        .checked_add(hlen)
        .filter(|&e| e <= bytes.len())
        .ok_or_else(|| {
            Error::new(
                ctx,
                format!(
                    "truncated .npy file: header of {hlen} bytes but the file has {} bytes",
                    bytes.len()
                ),
            )
        })?;
    let header = std::str::from_utf8(&bytes[hstart..data_start])
        .map_err(|_| Error::new(ctx, "the .npy header is not valid text"))?;
    let hd = parse_header(header, ctx)?;
    if hd.shape.len() != 2 {
        return Err(Error::new(
            ctx,
            format!(
                "expected a 2-D array (rows H × columns W), got {} dimension(s) with shape {:?}",
                hd.shape.len(),
                hd.shape
            ),
        ));
    }
    let (rows, cols) = (hd.shape[0], hd.shape[1]);
    if rows == 0 || cols == 0 {
        return Err(Error::new(
            ctx,
            format!("the array is empty (shape {rows}×{cols}); expected at least one sample"),
        ));
    }
    let count = rows
        .checked_mul(cols)
        .ok_or_else(|| Error::new(ctx, format!("shape {rows}×{cols} is too large")))?;
    let size = hd.kind.size();
    let need = count
        .checked_mul(size)
        .ok_or_else(|| Error::new(ctx, format!("shape {rows}×{cols} is too large")))?;
    let have = bytes.len() - data_start;
    if have < need {
        return Err(Error::new(
            ctx,
            format!("truncated .npy file: shape {rows}×{cols} needs {need} data bytes, the file has {have}"),
        ));
    }
    if have > need {
        return Err(Error::new(
            ctx,
            format!("the .npy file has {} bytes after the {rows}×{cols} array (expected exactly {need} data bytes)", have - need),
        ));
    }
    let raw = &bytes[data_start..];
    let mut out = vec![0.0; count];
    if hd.fortran {
        // Column-major: element (r, c) is at c * rows + r.
        for (i, chunk) in raw.chunks_exact(size).enumerate() {
            let (c, r) = (i / rows, i % rows);
            out[r * cols + c] = decode(hd.kind, hd.big, chunk);
        }
    } else {
        for (o, chunk) in out.iter_mut().zip(raw.chunks_exact(size)) {
            *o = decode(hd.kind, hd.big, chunk);
        }
    }
    Ok((rows, cols, out))
}

/// Read a 2-D `.npy` array: `(rows H, columns W, row-major samples)`.
pub fn read_npy_2d(path: &Path) -> Result<(usize, usize, Vec<f64>)> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, "read the .npy file", e))?;
    parse_npy_2d(&bytes, &path.display().to_string())
}

/// The bytes of a version 1.0 `<f8` C-order `.npy` file of shape `(h, w)`.
pub fn npy_f64_bytes(h: usize, w: usize, data: &[f64]) -> Vec<u8> {
    let dict = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({h}, {w}), }}");
    // Pad with spaces so that magic + version + length + header is a multiple of 64, ending in '\n'.
    let unpadded = 10 + dict.len() + 1;
    let pad = (64 - unpadded % 64) % 64;
    let mut header = dict;
    header.push_str(&" ".repeat(pad));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + data.len() * 8);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Write a version 1.0 `<f8` C-order `.npy` file of shape `(h, w)` from row-major `data`, through a
/// temporary file in the same directory and a rename (never a half-written file).
pub fn write_npy_f64(path: &Path, h: usize, w: usize, data: &[f64]) -> Result<()> {
    if h.checked_mul(w) != Some(data.len()) {
        return Err(Error::new(
            path.display().to_string(),
            format!(
                "cannot write a {h}×{w} array from {} samples (expected {} samples)",
                data.len(),
                h.saturating_mul(w)
            ),
        ));
    }
    crate::atomic_write::write_bytes(path, &npy_f64_bytes(h, w, data))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testdir::TestDir;

    fn header_bytes(major: u8, dict: &str) -> Vec<u8> {
        let mut h = dict.to_string();
        let pre = if major == 1 { 10 } else { 12 };
        while !(pre + h.len() + 1).is_multiple_of(64) {
            h.push(' ');
        }
        h.push('\n');
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&[major, 0]);
        if major == 1 {
            out.extend_from_slice(&(h.len() as u16).to_le_bytes());
        } else {
            out.extend_from_slice(&(h.len() as u32).to_le_bytes());
        }
        out.extend_from_slice(h.as_bytes());
        out
    }

    #[test]
    fn round_trip_f64_file() {
        let dir = TestDir::new("npy");
        let p = dir.join("a.npy");
        let data: Vec<f64> = (0..12).map(|i| i as f64 * 0.37 - 1.5).collect();
        write_npy_f64(&p, 3, 4, &data).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(
            (bytes.len() - data.len() * 8) % 64,
            0,
            "header is 64-byte aligned"
        );
        let (h, w, back) = read_npy_2d(&p).unwrap();
        assert_eq!((h, w), (3, 4));
        assert_eq!(back, data);
        assert!(write_npy_f64(&p, 3, 3, &data).is_err());
    }

    #[test]
    fn f32_c_and_fortran_and_big_endian() {
        // logical array [[1, 2, 3], [4, 5, 6]]
        let c_order = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0];
        let f_order = [1.0f32, 4.0, 2.0, 5.0, 3.0, 6.0];
        let want: Vec<f64> = c_order.iter().map(|&v| v as f64).collect();
        for (major, fortran, vals) in [
            (1u8, false, c_order),
            (2, true, f_order),
            (3, true, f_order),
        ] {
            let ft = if fortran { "True" } else { "False" };
            let mut b = header_bytes(
                major,
                &format!("{{'descr': '<f4', 'fortran_order': {ft}, 'shape': (2, 3), }}"),
            );
            for v in vals {
                b.extend_from_slice(&v.to_le_bytes());
            }
            assert_eq!(
                parse_npy_2d(&b, "x.npy").unwrap(),
                (2, 3, want.clone()),
                "v{major} fortran={ft}"
            );
        }
        let mut b = header_bytes(
            1,
            "{'descr': '>f8', 'fortran_order': True, 'shape': (2, 3), }",
        );
        for v in f_order {
            b.extend_from_slice(&(v as f64).to_be_bytes());
        }
        assert_eq!(parse_npy_2d(&b, "x.npy").unwrap(), (2, 3, want.clone()));
        let mut b = header_bytes(
            1,
            "{'descr': '<u2', 'fortran_order': False, 'shape': (2, 3), }",
        );
        for v in c_order {
            b.extend_from_slice(&(v as u16).to_le_bytes());
        }
        assert_eq!(parse_npy_2d(&b, "x.npy").unwrap(), (2, 3, want.clone()));
        let mut b = header_bytes(
            1,
            "{'descr': '|u1', 'fortran_order': False, 'shape': (2, 3), }",
        );
        b.extend(c_order.iter().map(|&v| v as u8));
        assert_eq!(parse_npy_2d(&b, "x.npy").unwrap(), (2, 3, want.clone()));
        let mut b = header_bytes(
            1,
            "{'descr': '<i2', 'fortran_order': False, 'shape': (2, 3), }",
        );
        for v in c_order {
            b.extend_from_slice(&(-(v as i16)).to_le_bytes());
        }
        let neg: Vec<f64> = want.iter().map(|v| -v).collect();
        assert_eq!(parse_npy_2d(&b, "x.npy").unwrap(), (2, 3, neg));
    }

    #[test]
    fn errors_name_the_file() {
        let good = npy_f64_bytes(2, 2, &[0.0, 1.0, 2.0, 3.0]);
        let e = parse_npy_2d(&good[..good.len() - 3], "trunc.npy")
            .unwrap_err()
            .to_string();
        assert!(e.contains("trunc.npy") && e.contains("truncated"), "{e}");
        let e = parse_npy_2d(&good[..20], "short.npy")
            .unwrap_err()
            .to_string();
        assert!(e.contains("short.npy") && e.contains("truncated"), "{e}");
        let e = parse_npy_2d(b"hello world", "txt.npy")
            .unwrap_err()
            .to_string();
        assert!(e.contains("txt.npy") && e.contains("magic"), "{e}");
        let mut b = header_bytes(
            1,
            "{'descr': '<f8', 'fortran_order': False, 'shape': (4,), }",
        );
        b.extend_from_slice(&[0u8; 32]);
        let e = parse_npy_2d(&b, "one_d.npy").unwrap_err().to_string();
        assert!(e.contains("one_d.npy") && e.contains("2-D"), "{e}");
        let mut b = header_bytes(
            1,
            "{'descr': '<c16', 'fortran_order': False, 'shape': (1, 1), }",
        );
        b.extend_from_slice(&[0u8; 16]);
        let e = parse_npy_2d(&b, "cplx.npy").unwrap_err().to_string();
        assert!(e.contains("cplx.npy") && e.contains("dtype"), "{e}");
        let e = read_npy_2d(Path::new("/nonexistent/dir/missing.npy"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing.npy"), "{e}");
    }
}
