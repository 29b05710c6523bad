//! Direction-pair files (`theta_i,phi_i,theta_o,phi_o` in degrees, design-notes frame), the
//! `forward` output CSV, and the default quasi-random sample set.

use crate::error::{Error, Result};
use crate::frame::{dir_from_deg, DirPair};
use std::path::Path;

pub const PAIRS_HEADER: &str = "theta_i,phi_i,theta_o,phi_o";

/// One row of a pairs file, in degrees as given.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnglePair {
    pub theta_i: f64,
    pub phi_i: f64,
    pub theta_o: f64,
    pub phi_o: f64,
}

impl AnglePair {
    pub fn dirs(&self) -> DirPair {
        DirPair {
            wi: dir_from_deg(self.theta_i, self.phi_i),
            wo: dir_from_deg(self.theta_o, self.phi_o),
        }
    }
}

/// Parse pairs CSV text; `name` is used in messages.
pub fn parse_pairs(text: &str, name: &str) -> Result<Vec<AnglePair>> {
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let Some((_, header)) = lines.next() else {
        return Err(Error::new(
            name,
            format!("empty file; expected the header '{PAIRS_HEADER}'"),
        ));
    };
    let cols: Vec<String> = header
        .split(',')
        .map(|c| c.trim().trim_start_matches('\u{feff}').to_string())
        .collect();
    if cols.join(",") != PAIRS_HEADER {
        return Err(Error::new(
            format!("{name} line 1"),
            format!("header is '{}', expected '{PAIRS_HEADER}'", header.trim()),
        ));
    }
    let names = ["theta_i", "phi_i", "theta_o", "phi_o"];
    let mut out = Vec::new();
    for (ln, line) in lines {
        let fields: Vec<&str> = line.split(',').map(|f| f.trim()).collect();
        let at = format!("{name} line {}", ln + 1);
        if fields.len() != 4 {
            return Err(Error::new(
                at,
                format!("{} fields, expected 4 ({PAIRS_HEADER})", fields.len()),
            ));
        }
        let mut v = [0.0; 4];
        for k in 0..4 {
            let x: f64 = fields[k].parse().map_err(|_| {
                Error::new(
                    &at,
                    format!("{} = '{}' is not a number (degrees)", names[k], fields[k]),
                )
            })?;
            if !x.is_finite() {
                return Err(Error::new(
                    &at,
                    format!("{} = {x}, expected a finite angle in degrees", names[k]),
                ));
            }
            if k % 2 == 0 && !(0.0..90.0).contains(&x) {
                return Err(Error::new(
                    &at,
                    format!(
                        "{} = {x}°, expected 0 <= theta < 90 (directions must be above the surface)",
                        names[k]
                    ),
                ));
            }
            v[k] = x;
        }
        out.push(AnglePair {
            theta_i: v[0],
            phi_i: v[1],
            theta_o: v[2],
            phi_o: v[3],
        });
    }
    if out.is_empty() {
        return Err(Error::new(name, "no direction pairs after the header"));
    }
    Ok(out)
}

pub fn read_pairs(path: &Path) -> Result<Vec<AnglePair>> {
    let text =
        std::fs::read_to_string(path).map_err(|e| Error::io(path, "read the pairs file", e))?;
    parse_pairs(&text, &path.display().to_string())
}

/// The `forward` output: the four angle columns, `fbar` and `brdf = fbar / cos(theta_i)`.
pub fn format_output(pairs: &[AnglePair], fbar: &[f64]) -> String {
    let mut s = String::with_capacity(64 * pairs.len());
    s.push_str(PAIRS_HEADER);
    s.push_str(",fbar,brdf\n");
    for (p, f) in pairs.iter().zip(fbar) {
        let f = if f.is_finite() && *f > 0.0 { *f } else { 0.0 };
        let c = p.theta_i.to_radians().cos();
        let brdf = if c > 0.0 { f / c } else { 0.0 };
        s.push_str(&format!(
            "{},{},{},{},{:.9e},{:.9e}\n",
            p.theta_i, p.phi_i, p.theta_o, p.phi_o, f, brdf
        ));
    }
    s
}

/// The default sample set: 7 quasi-random light directions and, for each, `per_light` view
/// directions, uniform in solid angle over the hemisphere (paper Sec. 6 uses 7 × 70 = 490).
pub fn default_pairs(per_light: usize) -> Vec<AnglePair> {
    let lights = light_directions();
    let mut out = Vec::with_capacity(7 * per_light);
    for (l, &(ti, pi)) in lights.iter().enumerate() {
        for k in 0..per_light {
            // Fibonacci points on the hemisphere, rotated per light so the sets differ.
            let u = (k as f64 + 0.5) / per_light as f64;
            let v = (k as f64 * 0.618_033_988_749_894_8 + l as f64 * 0.137).fract();
            let theta_o = u.acos().to_degrees().min(89.0);
            out.push(AnglePair {
                theta_i: ti,
                phi_i: pi,
                theta_o,
                phi_o: 360.0 * v,
            });
        }
    }
    out
}

/// The 7 fixed light directions (degrees), quasi-random over the hemisphere (Hammersley points,
/// uniform in solid angle, theta capped at 80°).
pub fn light_directions() -> [(f64, f64); 7] {
    let mut out = [(0.0, 0.0); 7];
    for (k, o) in out.iter_mut().enumerate() {
        let u = (k as f64 + 0.5) / 7.0;
        // base-2 radical inverse of k for the azimuth
        let mut r = 0.0;
        let (mut f, mut n) = (0.5, k + 1);
        while n > 0 {
            r += f * (n & 1) as f64;
            n >>= 1;
            f *= 0.5;
        }
        *o = ((1.0 - u).acos().to_degrees().min(80.0), 360.0 * r);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_rejects() {
        let ok = parse_pairs(
            "theta_i,phi_i,theta_o,phi_o\n30,0,40,180\n\n89.9, 10 ,0,0\n",
            "p.csv",
        )
        .unwrap();
        assert_eq!(ok.len(), 2);
        let e = parse_pairs("theta_i,phi_i,theta_out,phi_o\n30,0,40,180\n", "p.csv")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("p.csv line 1") && e.contains("expected 'theta_i,phi_i,theta_o,phi_o'"),
            "{e}"
        );
        let e = parse_pairs("theta_i,phi_i,theta_o,phi_o\n30,0,95,180\n", "p.csv")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 2") && e.contains("theta_o = 95"), "{e}");
        let e = parse_pairs("theta_i,phi_i,theta_o,phi_o\n30,x,5,180\n", "p.csv")
            .unwrap_err()
            .to_string();
        assert!(e.contains("phi_i = 'x'"), "{e}");
        assert!(parse_pairs("theta_i,phi_i,theta_o,phi_o\n", "p.csv").is_err());
        assert!(parse_pairs("theta_i,phi_i,theta_o,phi_o\n1,2,3\n", "p.csv").is_err());
    }

    #[test]
    fn default_set_has_490_pairs_above_the_horizon() {
        let p = default_pairs(70);
        assert_eq!(p.len(), 490);
        assert!(p.iter().all(|a| a.theta_i < 90.0 && a.theta_o < 90.0));
    }
}
