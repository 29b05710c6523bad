//! MERL measured BRDFs (Matusik et al. 2003) from their `.binary` files.
//!
//! Format: three little-endian `i32` dimensions (90, 90, 180), then `3 × 90 × 90 × 180` `f64` in
//! channel-major order (red, green, blue), scaled by 1/1500, 1.15/1500, 1.66/1500. The half-angle
//! index is `sqrt(theta_h / (pi/2)) · 90`, the difference angles are linear; negative values mark
//! missing measurements and are read as 0. The single channel used by the solvers is the mean of
//! the three scaled channels.

use crate::error::{Error, Result};
use crate::frame::{frame_around, Vec3};
use std::f64::consts::{FRAC_PI_2, PI};
use std::path::Path;

const N_TH: usize = 90;
const N_TD: usize = 90;
const N_PD: usize = 180;
const SCALE: [f64; 3] = [1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0];
/// The largest BRDF value (per steradian, once scaled) a measured file may hold: above the
/// analytic models' peaks at their sharpest accepted settings (GGX `alpha = 0.001` at normal
/// incidence: `1 / (4 pi alpha²)`, about 8e4), far below what overflows the single-precision
/// tables built from it (1e12 per value passed the old check, and solve then found nothing).
pub const MAX_VALUE: f64 = 1e6;

/// A measured BRDF held in memory (f32 per channel: 11.7 MB).
#[derive(Debug, Clone)]
pub struct MerlBrdf {
    pub path: String,
    /// `[channel][index]`, already scaled, missing values replaced by 0.
    data: [Vec<f32>; 3],
}

impl MerlBrdf {
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, "read the MERL file", e))?;
        Self::from_bytes(&bytes, &path.display().to_string())
    }

    pub fn from_bytes(bytes: &[u8], name: &str) -> Result<Self> {
        if bytes.len() < 12 {
            return Err(Error::new(
                name,
                "not a MERL .binary file: shorter than its 12-byte header",
            ));
        }
        let dim = |i: usize| {
            i32::from_le_bytes([
                bytes[4 * i],
                bytes[4 * i + 1],
                bytes[4 * i + 2],
                bytes[4 * i + 3],
            ])
        };
        let dims = [dim(0), dim(1), dim(2)];
        if dims != [N_TH as i32, N_TD as i32, N_PD as i32] {
            return Err(Error::new(
                name,
                format!("not a MERL .binary file: dimensions {dims:?}, expected [90, 90, 180]"),
            ));
        }
        let n = N_TH * N_TD * N_PD;
        let want = 12 + 3 * n * 8;
        if bytes.len() != want {
            return Err(Error::new(
                name,
                format!(
                    "truncated or padded MERL file: {} bytes, expected {want}",
                    bytes.len()
                ),
            ));
        }
        let mut data: [Vec<f32>; 3] = [
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
        ];
        for (c, ch) in data.iter_mut().enumerate() {
            for i in 0..n {
                let o = 12 + 8 * (c * n + i);
                let mut b = [0u8; 8];
                b.copy_from_slice(&bytes[o..o + 8]);
                let v = f64::from_le_bytes(b);
                if !v.is_finite() {
                    return Err(Error::new(
                        name,
                        format!("value {i} of channel {c} is {v}, expected a finite number"),
                    ));
                }
                let x = if v < 0.0 { 0.0 } else { v * SCALE[c] };
                if x > MAX_VALUE {
                    return Err(Error::new(
                        name,
                        format!(
                            "value {i} of channel {c} is {v:e}, {x:.3e} per steradian once scaled: \
                             too large for a reflectance (expected at most {MAX_VALUE:e})"
                        ),
                    ));
                }
                let x = x as f32;
                ch.push(x);
            }
        }
        if data.iter().all(|ch| ch.iter().all(|&x| x <= 0.0)) {
            return Err(Error::new(
                name,
                "every value is zero or negative (MERL marks missing measurements with negative \
                 values): no reflectance to read",
            ));
        }
        Ok(MerlBrdf {
            path: name.to_string(),
            data,
        })
    }

    /// Table index for a configuration with `n` as the facet normal.
    fn index(n: Vec3, wi: Vec3, wo: Vec3) -> Option<usize> {
        if n.dot(wi) <= 0.0 || n.dot(wo) <= 0.0 {
            return None;
        }
        let (t, b) = frame_around(n);
        let to_local = |v: Vec3| Vec3::new(v.dot(t), v.dot(b), v.dot(n));
        let (li, lo) = (to_local(wi), to_local(wo));
        let hs = li + lo;
        if hs.norm() < 1e-12 {
            return None;
        }
        let h = hs.normalized();
        let theta_h = h.z.clamp(-1.0, 1.0).acos();
        let phi_h = h.y.atan2(h.x);
        // diff vector: rotate wi by -phi_h about z, then by -theta_h about y.
        let (sp, cp) = (-phi_h).sin_cos();
        let r1 = Vec3::new(cp * li.x - sp * li.y, sp * li.x + cp * li.y, li.z);
        let (st, ct) = (-theta_h).sin_cos();
        let d = Vec3::new(ct * r1.x + st * r1.z, r1.y, -st * r1.x + ct * r1.z);
        let theta_d = d.z.clamp(-1.0, 1.0).acos();
        // phi_d modulo pi (reciprocity); a value within rounding of pi is 0, so that swapping wi
        // and wo (which adds pi) lands in the same bin.
        let mut phi_d = d.y.atan2(d.x).rem_euclid(PI);
        if PI - phi_d < 1e-9 {
            phi_d = 0.0;
        }
        let th = {
            let v = (theta_h / FRAC_PI_2).max(0.0).sqrt() * N_TH as f64;
            (v as usize).min(N_TH - 1)
        };
        let td = ((theta_d / FRAC_PI_2 * N_TD as f64) as usize).min(N_TD - 1);
        let pd = ((phi_d / PI * N_PD as f64) as usize).min(N_PD - 1);
        Some(pd + td * N_PD + th * N_PD * N_TD)
    }

    /// RGB value. The table is indexed from both `(wi, wo)` and `(wo, wi)`: they name the same bin
    /// except where an angle falls on a bin edge, and there the two bins are averaged, so the
    /// lookup is exactly reciprocal like the measured reflectance it stands for.
    pub fn eval_rgb(&self, n: Vec3, wi: Vec3, wo: Vec3) -> [f64; 3] {
        let at = |i: usize| {
            [
                self.data[0][i] as f64,
                self.data[1][i] as f64,
                self.data[2][i] as f64,
            ]
        };
        match (Self::index(n, wi, wo), Self::index(n, wo, wi)) {
            (Some(a), Some(b)) if a == b => at(a),
            (Some(a), Some(b)) => {
                let (x, y) = (at(a), at(b));
                [
                    0.5 * (x[0] + y[0]),
                    0.5 * (x[1] + y[1]),
                    0.5 * (x[2] + y[2]),
                ]
            }
            _ => [0.0; 3],
        }
    }

    pub fn eval(&self, n: Vec3, wi: Vec3, wo: Vec3) -> f64 {
        let c = self.eval_rgb(n, wi, wo);
        (c[0] + c[1] + c[2]) / 3.0
    }

    /// Write a MERL file whose every entry is produced by `f(theta_h_index, theta_d_index,
    /// phi_d_index, channel)` before scaling (for tests and examples).
    pub fn write_synthetic(
        path: &Path,
        f: impl Fn(usize, usize, usize, usize) -> f64,
    ) -> Result<()> {
        let n = N_TH * N_TD * N_PD;
        let mut out = Vec::with_capacity(12 + 24 * n);
        for d in [N_TH, N_TD, N_PD] {
            out.extend_from_slice(&(d as i32).to_le_bytes());
        }
        for c in 0..3 {
            for th in 0..N_TH {
                for td in 0..N_TD {
                    for pd in 0..N_PD {
                        out.extend_from_slice(&f(th, td, pd, c).to_le_bytes());
                    }
                }
            }
        }
        crate::atomic_write::write_bytes(path, &out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::dir_from_deg;
    use crate::testdir::TestDir;

    #[test]
    fn constant_file_reads_back_and_rejects_bad_headers() {
        let dir = TestDir::new("merl");
        let p = dir.join("const.binary");
        // 1500/pi in the red channel gives exactly 1/pi after scaling.
        MerlBrdf::write_synthetic(&p, |_, _, _, c| if c == 0 { 1500.0 / PI } else { -1.0 })
            .unwrap();
        let m = MerlBrdf::load(&p).unwrap();
        let v = m.eval_rgb(Vec3::Z, dir_from_deg(30.0, 10.0), dir_from_deg(50.0, 200.0));
        assert!((v[0] - 1.0 / PI).abs() < 1e-6 && v[1] == 0.0 && v[2] == 0.0);
        assert_eq!(
            m.eval(Vec3::Z, dir_from_deg(30.0, 0.0), dir_from_deg(95.0, 0.0)),
            0.0
        );
        let bytes = std::fs::read(&p).unwrap();
        let e = MerlBrdf::from_bytes(&bytes[..1000], "cut.binary").unwrap_err();
        assert!(e.to_string().contains("cut.binary") && e.to_string().contains("truncated"));
        let mut bad = bytes.clone();
        bad[0] = 7;
        assert!(MerlBrdf::from_bytes(&bad, "b")
            .unwrap_err()
            .to_string()
            .contains("dimensions"));
        // Every measurement missing, or a value no reflectance has: refused, naming the file.
        let none = dir.join("none.binary");
        MerlBrdf::write_synthetic(&none, |_, _, _, _| -1.0).unwrap();
        let e = MerlBrdf::load(&none).unwrap_err().to_string();
        assert!(
            e.contains("none.binary") && e.contains("zero or negative"),
            "{e}"
        );
        let huge = dir.join("huge.binary");
        MerlBrdf::write_synthetic(&huge, |th, _, _, _| if th == 3 { 1e300 } else { 1.0 }).unwrap();
        let e = MerlBrdf::load(&huge).unwrap_err().to_string();
        assert!(e.contains("huge.binary") && e.contains("too large"), "{e}");
        // Finite in single precision, but far beyond any reflectance: refused too (before,
        // solve and design went on and found nothing).
        MerlBrdf::write_synthetic(&huge, |_, _, _, _| 1e12).unwrap();
        let e = MerlBrdf::load(&huge).unwrap_err().to_string();
        assert!(
            e.contains("huge.binary") && e.contains("at most 1e6"),
            "{e}"
        );
    }
}
