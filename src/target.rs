//! Large-scale target BRDFs: what the inverse solvers try to reproduce (paper Sec. 7).
//!
//! A target is any small-scale material spec seen as a flat large-scale BRDF, an anisotropic Ward
//! (`ward:ax=0.30,ay=0.08`, which no small-scale material may be), and the edits of Sec. 7 applied
//! on top: brightness (a factor) and contrast (Eq. 16, `(f - tau) c + tau` with `tau` the mean of
//! `f_r` over the bidirectional domain, clamped at 0).

use crate::error::{show_num, Error, Result};
use crate::frame::{dir_from_rad, rotate_z, Vec3};

/// Rotate `w` by `a` radians about +y.
fn rotate_y(w: Vec3, a: f64) -> Vec3 {
    let (s, c) = a.sin_cos();
    Vec3::new(c * w.x + s * w.z, w.y, -s * w.x + c * w.z)
}
use crate::material::{parse_material, AnisoWard, Material};

#[derive(Debug, Clone)]
pub enum TargetBase {
    Flat(Material),
    AnisoWard(AnisoWard),
}

/// A target large-scale BRDF with its edits.
#[derive(Debug, Clone)]
pub struct Target {
    pub base: TargetBase,
    pub brightness: f64,
    pub contrast: f64,
    /// Mean of the base `f_r` over the bidirectional domain (for contrast).
    pub tau: f64,
    /// Angular edit `[sx, sy]`: the half-vector slopes are scaled by these (blur > 1, sharpen < 1,
    /// anisotropy when they differ); `[1, 1]` leaves the target as it is.
    pub warp: [f64; 2],
}

impl Target {
    /// Parse a target spec: any material spec, or `ward:ax=A,ay=B[,ks=K]`.
    pub fn parse(spec: &str) -> Result<Self> {
        let s = spec.trim();
        let base = if s.starts_with("ward:") && (s.contains("ax=") || s.contains("ay=")) {
            let ctx = |e: Error| e.within(format!("target '{spec}'"));
            let mut p = crate::material::Params::parse(s).map_err(ctx)?;
            let ax = p.num("ax", None, 0.0, 10.0, true).map_err(ctx)?;
            let ay = p.num("ay", None, 0.0, 10.0, true).map_err(ctx)?;
            let ks = p.num("ks", Some(1.0), 0.0, 1e6, false).map_err(ctx)?;
            p.finish("ax, ay, ks")
                .map_err(|e| e.within(format!("target '{spec}'")))?;
            TargetBase::AnisoWard(AnisoWard { ax, ay, ks })
        } else {
            TargetBase::Flat(
                parse_material(s)
                    .map_err(|e| Error::new(format!("target '{spec}'"), e.to_string()))?,
            )
        };
        let mut t = Target {
            base,
            brightness: 1.0,
            contrast: 1.0,
            tau: 0.0,
            warp: [1.0, 1.0],
        };
        t.tau = t.mean_base();
        Ok(t)
    }

    pub fn with_brightness(mut self, b: f64) -> Result<Self> {
        if !(b.is_finite() && b > 0.0 && b <= 1e6) {
            return Err(Error::new(
                "brightness",
                format!("{}: expected a factor in (0, 1e6] (1 = unchanged; a black target has no relative error to match)", show_num(b)),
            ));
        }
        self.brightness = b;
        Ok(self)
    }

    pub fn with_contrast(mut self, c: f64) -> Result<Self> {
        if !(c.is_finite() && (0.0..=1e3).contains(&c)) {
            return Err(Error::new(
                "contrast",
                format!(
                    "{}: expected a factor in [0, 1000] (1 = unchanged)",
                    show_num(c)
                ),
            ));
        }
        self.contrast = c;
        Ok(self)
    }

    /// Angular edit (Sec. 7): blur (`s > 1`), sharpen (`s < 1`) or stretch (`sx != sy`, along x
    /// and y) the target's highlight. The BRDF at `(wi, wo)` is the original at the pair whose half
    /// vector has its slopes divided by `(sx, sy)` and the same difference angle (Rusinkiewicz's
    /// parameterisation), times the change of the half-vector density, `h'_z⁴ / (sx sy h_z⁴)`, and
    /// with the `1/(cos θi cos θo)` of the original pair swapped for that of `(wi, wo)`. For a
    /// microfacet lobe this is exactly its distribution with roughness `(sx α, sy α)`; shadowing
    /// and Fresnel are read at the warped pair. A Lambertian part is warped too, so the edit is
    /// meant for glossy targets.
    pub fn with_angular(mut self, sx: f64, sy: f64) -> Result<Self> {
        for (k, v) in [("blur x", sx), ("blur y", sy)] {
            if !(v.is_finite() && (0.01..=100.0).contains(&v)) {
                return Err(Error::new(k, format!("{}: expected a factor in [0.01, 100] (1 = unchanged, > 1 blurs, < 1 sharpens)", show_num(v))));
            }
        }
        self.warp = [sx, sy];
        self.tau = self.mean_base();
        Ok(self)
    }

    fn unwarped(&self, wi: Vec3, wo: Vec3) -> f64 {
        match &self.base {
            TargetBase::Flat(m) => m.eval(Vec3::Z, wi, wo),
            TargetBase::AnisoWard(w) => w.eval(wi, wo),
        }
    }

    fn base_brdf(&self, wi: Vec3, wo: Vec3) -> f64 {
        let [sx, sy] = self.warp;
        if sx == 1.0 && sy == 1.0 {
            return self.unwarped(wi, wo);
        }
        let s = wi + wo;
        if s.norm() < 1e-12 || wi.z <= 0.0 || wo.z <= 0.0 {
            return 0.0;
        }
        let h = s.normalized();
        let h2 = Vec3::new(h.x / sx, h.y / sy, h.z).normalized();
        // wi in the frame of h (Rz(φh) Ry(θh) maps z to h), then placed in the frame of h2.
        let (th, ph) = crate::frame::angles_of(h);
        let (th2, ph2) = crate::frame::angles_of(h2);
        let d = rotate_y(rotate_z(wi, -ph), -th);
        let wi2 = rotate_z(rotate_y(d, th2), ph2);
        let wo2 = h2 * (2.0 * h2.dot(wi2)) - wi2;
        if wi2.z <= 0.0 || wo2.z <= 0.0 {
            return 0.0;
        }
        let density = h2.z.powi(4) / (sx * sy * h.z.powi(4));
        let v = self.unwarped(wi2, wo2) * density * (wi2.z * wo2.z) / (wi.z * wo.z);
        if v.is_finite() {
            v.max(0.0)
        } else {
            0.0
        }
    }

    /// Mean of the base BRDF over pairs of directions uniform in solid angle (QMC, 64² pairs).
    fn mean_base(&self) -> f64 {
        let n = 64;
        let mut s = 0.0;
        for a in 0..n {
            let (ua, va) = (
                (a as f64 + 0.5) / n as f64,
                (a as f64 * 0.618_033_988_749_9).fract(),
            );
            let wi = dir_from_rad(ua.acos(), std::f64::consts::TAU * va);
            for b in 0..n {
                let (ub, vb) = (
                    (b as f64 + 0.5) / n as f64,
                    (b as f64 * 0.754_877_666_246_7).fract(),
                );
                let wo = dir_from_rad(ub.acos(), std::f64::consts::TAU * vb);
                s += self.base_brdf(wi, wo);
            }
        }
        s / (n * n) as f64
    }

    /// The target large-scale BRDF (without the cosine).
    pub fn brdf(&self, wi: Vec3, wo: Vec3) -> f64 {
        if wi.z <= 0.0 || wo.z <= 0.0 {
            return 0.0;
        }
        let f = self.base_brdf(wi, wo);
        let f = if self.contrast == 1.0 {
            f
        } else {
            ((f - self.tau) * self.contrast + self.tau).max(0.0)
        };
        f * self.brightness
    }

    /// `fbar` of the target: its BRDF times `cos(theta_i)`.
    pub fn fbar(&self, wi: Vec3, wo: Vec3) -> f64 {
        self.brdf(wi, wo) * wi.z.max(0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angular_edits_blur_sharpen_and_stretch_a_microfacet_highlight() {
        // Blurring GGX(0.1) by 2 gives GGX(0.2) up to shadowing and Fresnel read at the warped
        // pair: compare on the highlight (where D dominates) in and out of the plane.
        let blurred = Target::parse("ggx:alpha=0.1")
            .unwrap()
            .with_angular(2.0, 2.0)
            .unwrap();
        let wide = Target::parse("ggx:alpha=0.2").unwrap();
        let stretched = Target::parse("ward:alpha=0.1")
            .unwrap()
            .with_angular(3.0, 0.8)
            .unwrap();
        let aniso = Target::parse("ward:ax=0.3,ay=0.08").unwrap();
        let wi = dir_from_rad(0.5, 0.0);
        for (t, p) in [
            (0.5, std::f64::consts::PI),
            (0.6, 3.0),
            (0.4, 3.3),
            (0.55, 2.9),
        ] {
            let wo = dir_from_rad(t, p);
            let (a, b) = (blurred.brdf(wi, wo), wide.brdf(wi, wo));
            assert!((a - b).abs() < 0.05 * b, "blur: {a} vs {b} at ({t}, {p})");
            let (a, b) = (stretched.brdf(wi, wo), aniso.brdf(wi, wo));
            assert!((a - b).abs() < 0.2 * b, "stretch: {a} vs {b} at ({t}, {p})");
        }
        // Unit factors change nothing; bad factors are errors.
        let same = Target::parse("ggx:alpha=0.1")
            .unwrap()
            .with_angular(1.0, 1.0)
            .unwrap();
        let plain = Target::parse("ggx:alpha=0.1").unwrap();
        assert_eq!(
            same.brdf(wi, dir_from_rad(0.5, 3.0)),
            plain.brdf(wi, dir_from_rad(0.5, 3.0))
        );
        assert!(plain.with_angular(0.0, 1.0).is_err());
    }
    use crate::frame::dir_from_deg;

    #[test]
    fn aniso_ward_rotates_by_ninety_degrees() {
        let a = Target::parse("ward:ax=0.30,ay=0.08").unwrap();
        let b = Target::parse("ward:ax=0.08,ay=0.30").unwrap();
        let (wi, wo) = (dir_from_deg(30.0, 20.0), dir_from_deg(45.0, 230.0));
        let r = |w: Vec3| crate::frame::rotate_z(w, std::f64::consts::FRAC_PI_2);
        assert!((a.brdf(wi, wo) - b.brdf(r(wi), r(wo))).abs() < 1e-9 * a.brdf(wi, wo));
    }

    #[test]
    fn contrast_zero_is_constant_and_errors_are_named() {
        let t = Target::parse("blinn:n=60+lambert:albedo=0.3")
            .unwrap()
            .with_contrast(0.0)
            .unwrap();
        let v1 = t.brdf(dir_from_deg(10.0, 0.0), dir_from_deg(10.0, 180.0));
        let v2 = t.brdf(dir_from_deg(60.0, 0.0), dir_from_deg(20.0, 90.0));
        assert!((v1 - v2).abs() < 1e-12 && v1 > 0.0);
        assert!(Target::parse("ward:ax=-1,ay=0.1")
            .unwrap_err()
            .to_string()
            .contains("ax"));
        assert!(Target::parse("nope:x=1")
            .unwrap_err()
            .to_string()
            .contains("target 'nope:x=1'"));
    }
}
