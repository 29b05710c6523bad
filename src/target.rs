//! Large-scale target BRDFs: what the inverse solvers try to reproduce (paper Sec. 7).
//!
//! A target is any small-scale material spec seen as a flat large-scale BRDF, an anisotropic Ward
//! (`ward:ax=0.30,ay=0.08`, which no small-scale material may be), and the edits of Sec. 7 applied
//! on top: brightness (a factor) and contrast (Eq. 16, `(f - tau) c + tau` with `tau` the mean of
//! `f_r` over the bidirectional domain, clamped at 0).

use crate::error::{Error, Result};
use crate::frame::{dir_from_rad, Vec3};
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
        };
        t.tau = t.mean_base();
        Ok(t)
    }

    pub fn with_brightness(mut self, b: f64) -> Result<Self> {
        if !(b.is_finite() && b >= 0.0) {
            return Err(Error::new(
                "brightness",
                format!("{b}: expected a non-negative factor"),
            ));
        }
        self.brightness = b;
        Ok(self)
    }

    pub fn with_contrast(mut self, c: f64) -> Result<Self> {
        if !(c.is_finite() && c >= 0.0) {
            return Err(Error::new(
                "contrast",
                format!("{c}: expected a non-negative factor (1 = unchanged)"),
            ));
        }
        self.contrast = c;
        Ok(self)
    }

    fn base_brdf(&self, wi: Vec3, wo: Vec3) -> f64 {
        match &self.base {
            TargetBase::Flat(m) => m.eval(Vec3::Z, wi, wo),
            TargetBase::AnisoWard(w) => w.eval(wi, wo),
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
