//! Reading the TOML files users write (library profiles, scenes, fabrication catalogues and
//! profiles) with messages a user can act on.
//!
//! Files are parsed with serde into structs marked `deny_unknown_fields`. A toml/serde error only
//! carries a byte span and a message such as `invalid type: string "x", expected f64`; this
//! module turns it into `FILE: [section] key `k` (line N): expected a number, got string "x"` by
//! reading the key and the enclosing `[section]` from the source line the span points at.

use crate::error::{Error, Result};
use serde::de::DeserializeOwned;
use std::path::Path;

/// Read `path` as UTF-8 text; the error names the file.
pub fn read_text(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| Error::io(path, "read", e))
}

/// Parse `src` (the text of `path`) into `T`, mapping any error to one naming the file, the
/// section, the key and what was expected.
pub fn parse<T: DeserializeOwned>(path: &Path, src: &str) -> Result<T> {
    toml::from_str::<T>(src).map_err(|e| map_error(path, src, e.message(), e.span()))
}

/// The key named in backticks after `prefix` in a serde message (`unknown field `x``).
fn backticked(msg: &str, prefix: &str) -> Option<String> {
    let rest = msg.strip_prefix(prefix)?;
    let rest = rest.strip_prefix('`')?;
    rest.find('`').map(|end| rest[..end].to_string())
}

/// The key assigned on a `key = value` line, if the line is one.
fn key_of_line(line: &str) -> Option<String> {
    let t = line.trim_start();
    let eq = t.find('=')?;
    let k = t[..eq].trim().trim_matches('"');
    if k.is_empty() || k.starts_with('[') || k.starts_with('#') {
        None
    } else {
        Some(k.to_string())
    }
}

/// Serde's type words rewritten for a user ("f64" → "a number").
fn plain(msg: &str) -> String {
    msg.replace("expected f64", "expected a number")
        .replace(
            "expected u32",
            "expected a whole number from 0 to 4294967295",
        )
        // The key's own range, where it has one, is checked once the type is right.
        .replace("expected u64", "expected a whole number (0 or more)")
        .replace("expected usize", "expected a whole number (0 or more)")
}

fn map_error(path: &Path, src: &str, msg: &str, span: Option<std::ops::Range<usize>>) -> Error {
    let file = path.display().to_string();
    let start = span.as_ref().map(|s| s.start.min(src.len())).unwrap_or(0);
    let line_no = src[..start].matches('\n').count() + 1;
    let line = src.lines().nth(line_no - 1).unwrap_or("");
    let section = src[..start]
        .lines()
        .rev()
        .map(str::trim)
        .find(|l| l.starts_with('[') && l.contains(']'))
        .map(|l| l.trim_matches(|c| c == '[' || c == ']').to_string());
    let where_ = match &section {
        Some(s) => format!("[{s}] "),
        None => String::new(),
    };
    if let Some(k) = backticked(msg, "unknown field ") {
        let known = msg.split_once("expected ").map(|x| x.1).unwrap_or("");
        // An unquoted header with a dot (`[ball-0.5mm]`) nests a table named after the part
        // behind the dot, which the error then reports as an unknown key, sometimes with no
        // position: find that header.
        let dotted = src
            .lines()
            .enumerate()
            .map(|(i, l)| (i + 1, l.trim()))
            .find(|(_, l)| {
                l.starts_with('[') && !l.contains('"') && l.ends_with(&format!(".{k}]"))
            });
        if let Some((n, l)) = dotted {
            let s = l.trim_matches(|c| c == '[' || c == ']');
            return Error::new(
                file,
                format!(
                    "[{s}] (line {n}): a dot in a table name nests tables, so `{k}` is read as a \
                     key of [{}]; write [\"{s}\"] for one name with a dot",
                    s.rsplit_once('.').map(|x| x.0).unwrap_or(s)
                ),
            );
        }
        let hint = match &section {
            Some(s) if s.contains('.') && !s.contains('"') => {
                format!(" (a dot in [{s}] nests tables: write [\"{s}\"] for one name with a dot)")
            }
            _ => String::new(),
        };
        return Error::new(
            file,
            format!("{where_}unknown key `{k}` (line {line_no}); the keys allowed here are {known}{hint}"),
        );
    }
    if let Some(k) = backticked(msg, "missing field ") {
        return Error::new(file, format!("{where_}missing key `{k}`"));
    }
    if msg.starts_with("duplicate key") || span.is_none() {
        return Error::new(file, format!("{where_}line {line_no}: {}", plain(msg)));
    }
    match key_of_line(line) {
        Some(k) => Error::new(
            file,
            format!("{where_}key `{k}` (line {line_no}): {}", plain(msg)),
        ),
        None => Error::new(file, format!("line {line_no}: {}", plain(msg))),
    }
}

/// A finite number `> 0`, or an error naming the file, section and key.
pub fn positive(file: &Path, section: &str, key: &str, v: f64, unit: &str) -> Result<f64> {
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(Error::new(
            file.display().to_string(),
            format!("{section}key `{key}` must be a positive number of {unit}, got {v}"),
        ))
    }
}

/// A finite number `>= 0`, or an error naming the file, section and key.
pub fn non_negative(file: &Path, section: &str, key: &str, v: f64, unit: &str) -> Result<f64> {
    if v.is_finite() && v >= 0.0 {
        Ok(v)
    } else {
        Err(Error::new(
            file.display().to_string(),
            format!("{section}key `{key}` must be a number >= 0 ({unit}), got {v}"),
        ))
    }
}

/// A required key of a section: `Some(v)`, or an error naming the file, section and key.
pub fn required<T>(file: &Path, section: &str, key: &str, v: Option<T>, what: &str) -> Result<T> {
    v.ok_or_else(|| {
        Error::new(
            file.display().to_string(),
            format!("{section}missing key `{key}` (expected {what})"),
        )
    })
}

/// Fixed-length arrays of numbers for `#[serde(deserialize_with = ...)]`. TOML's deserializer
/// fills a `[f64; N]` from the first `N` elements of a longer array and drops the rest; these
/// refuse any other length (`invalid length 3, expected an array of 2 numbers`).
pub mod exact_len {
    use serde::de::{Deserializer, Error};
    use serde::Deserialize;
    use std::collections::BTreeMap;

    fn fixed<const N: usize, E: Error>(v: Vec<f64>) -> std::result::Result<[f64; N], E> {
        let n = v.len();
        v.try_into()
            .map_err(|_| E::invalid_length(n, &format!("an array of {N} numbers").as_str()))
    }

    pub fn array2<'de, D: Deserializer<'de>>(d: D) -> std::result::Result<[f64; 2], D::Error> {
        fixed(Vec::deserialize(d)?)
    }

    pub fn option_array3<'de, D: Deserializer<'de>>(
        d: D,
    ) -> std::result::Result<Option<[f64; 3]>, D::Error> {
        Option::<Vec<f64>>::deserialize(d)?.map(fixed).transpose()
    }

    /// A table of `name = [lo, hi]` ranges.
    pub fn ranges<'de, D: Deserializer<'de>>(
        d: D,
    ) -> std::result::Result<BTreeMap<String, [f64; 2]>, D::Error> {
        BTreeMap::<String, Vec<f64>>::deserialize(d)?
            .into_iter()
            .map(|(k, v)| {
                let n = v.len();
                let r: [f64; 2] = v.try_into().map_err(|_| {
                    D::Error::invalid_length(n, &format!("`{k}` = [low, high], 2 numbers").as_str())
                })?;
                Ok((k, r))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Deserialize, Debug)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct T {
        a_mm: Option<f64>,
        name: Option<String>,
    }

    #[test]
    fn messages_name_key_and_line() {
        let p = Path::new("x.toml");
        let e = parse::<T>(p, "name = \"q\"\na_mm = \"wide\"\n").unwrap_err();
        let s = e.to_string();
        assert!(
            s.contains("x.toml") && s.contains("`a_mm`") && s.contains("line 2"),
            "{s}"
        );
        assert!(s.contains("expected a number"), "{s}");
        let s = parse::<T>(p, "a_mn = 3\n").unwrap_err().to_string();
        assert!(
            s.contains("unknown key `a_mn`") && s.contains("`a_mm`"),
            "{s}"
        );
    }

    #[derive(Deserialize, Debug)]
    #[allow(dead_code)]
    struct A {
        #[serde(deserialize_with = "exact_len::array2")]
        tile_mm: [f64; 2],
        #[serde(default, deserialize_with = "exact_len::option_array3")]
        colour: Option<[f64; 3]>,
    }

    #[test]
    fn fixed_arrays_refuse_other_lengths() {
        let p = Path::new("x.toml");
        let a = parse::<A>(p, "tile_mm = [1, 2]\n").unwrap();
        assert_eq!((a.tile_mm, a.colour), ([1.0, 2.0], None));
        for (src, key) in [
            ("tile_mm = [1, 2, 3]\n", "tile_mm"),
            ("tile_mm = [1]\n", "tile_mm"),
            ("tile_mm = [1, 2]\ncolour = [1, 2, 3, 4]\n", "colour"),
        ] {
            let s = parse::<A>(p, src).unwrap_err().to_string();
            assert!(
                s.contains(key) && s.contains("invalid length"),
                "{src}: {s}"
            );
        }
    }
}
