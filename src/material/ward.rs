//! Ward lobes. Isotropic Ward is a small-scale material:
//! `f_r = ks · exp(-tan²θh / α²) / (4 π α² sqrt(cosθi cosθo))`.
//! Anisotropic Ward `(ax, ay)` (Ward 1992) is a large-scale *target* only (small-scale materials are
//! isotropic); it lives here beside its isotropic form and is used by `crate::target`.

use super::{fmt_num, half_terms};
use crate::frame::Vec3;
use std::f64::consts::PI;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ward {
    pub alpha: f64,
    pub ks: f64,
}

impl Ward {
    pub fn eval(&self, n: Vec3, wi: Vec3, wo: Vec3) -> f64 {
        let Some((ci, co, ch, _)) = half_terms(n, wi, wo) else {
            return 0.0;
        };
        if ch <= 0.0 {
            return 0.0;
        }
        let a2 = self.alpha * self.alpha;
        let c2 = ch * ch;
        let tan2 = (1.0 - c2).max(0.0) / c2;
        let e = crate::fastmath::exp(-tan2 / a2);
        if e == 0.0 {
            return 0.0;
        }
        self.ks * e / (4.0 * PI * a2 * (ci * co).sqrt())
    }
    pub fn spec(&self) -> String {
        format!("ward:alpha={},ks={}", fmt_num(self.alpha), fmt_num(self.ks))
    }
}

/// Anisotropic Ward in the macro frame (normal +z, `ax` along +x, `ay` along +y).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnisoWard {
    pub ax: f64,
    pub ay: f64,
    pub ks: f64,
}

impl AnisoWard {
    /// `f_r(wi, wo)` for the macro normal +z.
    pub fn eval(&self, wi: Vec3, wo: Vec3) -> f64 {
        if wi.z <= 0.0 || wo.z <= 0.0 {
            return 0.0;
        }
        let h = wi + wo;
        if h.z <= 0.0 {
            return 0.0;
        }
        let ex = (h.x / (self.ax * h.z)).powi(2) + (h.y / (self.ay * h.z)).powi(2);
        let e = crate::fastmath::exp(-ex);
        if e == 0.0 {
            return 0.0;
        }
        self.ks * e / (4.0 * PI * self.ax * self.ay * (wi.z * wo.z).sqrt())
    }
    pub fn spec(&self) -> String {
        format!(
            "ward:ax={},ay={},ks={}",
            fmt_num(self.ax),
            fmt_num(self.ay),
            fmt_num(self.ks)
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::dir_from_deg;

    #[test]
    fn aniso_equals_iso_when_equal() {
        let iso = Ward {
            alpha: 0.2,
            ks: 1.0,
        };
        let an = AnisoWard {
            ax: 0.2,
            ay: 0.2,
            ks: 1.0,
        };
        for &(ti, pi, to, po) in &[
            (10.0, 0.0, 20.0, 170.0),
            (60.0, 30.0, 45.0, 250.0),
            (85.0, 0.0, 85.0, 180.0),
        ] {
            let (wi, wo) = (dir_from_deg(ti, pi), dir_from_deg(to, po));
            let a = iso.eval(Vec3::Z, wi, wo);
            let b = an.eval(wi, wo);
            assert!((a - b).abs() <= 1e-12 * a.max(1e-300), "{a} {b}");
        }
    }
}
