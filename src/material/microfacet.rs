//! Microfacet lobes: GGX and Beckmann with separable Smith masking and Schlick Fresnel, and
//! Cook–Torrance (Beckmann `m`, Schlick `F0`, V-cavity masking).
//!
//! `f_r = ks · D(h) · G · F(wi·h) / (4 (n·wi)(n·wo))`. With `f0 = 1`, `ks = 1` the GGX and Beckmann
//! lobes equal Mitsuba 3's `roughconductor` with `material = "none"` (Mitsuba's `eval` returns
//! `f_r · cos(theta)` of its sampled direction): the same `D`, the same separable Smith `G1`
//! (exact for GGX, the rational approximation for Beckmann) with the same side test
//! `(v·h)(v·n) > 0`.

use super::{fmt_num, half_terms, schlick};
use crate::frame::Vec3;
use std::f64::consts::FRAC_1_PI;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Distribution {
    Ggx,
    Beckmann,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shadowing {
    /// Separable Smith `G1(wi) G1(wo)` of the distribution.
    Smith,
    /// Cook–Torrance V-cavity `min(1, 2 (n·h)(n·wo)/(wo·h), 2 (n·h)(n·wi)/(wi·h))`.
    VCavity,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Microfacet {
    pub dist: Distribution,
    pub shadowing: Shadowing,
    /// Roughness (GGX alpha, Beckmann alpha = Cook–Torrance m).
    pub alpha: f64,
    pub f0: f64,
    pub ks: f64,
}

impl Microfacet {
    /// Normal distribution `D(cos theta_h)`, normalised so `∫ D(h) (h·n) dh = 1`.
    #[inline]
    pub fn d(&self, cos_h: f64) -> f64 {
        if cos_h <= 0.0 {
            return 0.0;
        }
        let a2 = self.alpha * self.alpha;
        let c2 = cos_h * cos_h;
        match self.dist {
            Distribution::Ggx => {
                // a² / (pi (c²(a²-1) + 1)²), written to stay accurate for tiny alpha:
                // c²(a²-1)+1 = s² + c² a² with s² = 1 - c².
                let s2 = (1.0 - c2).max(0.0);
                let den = s2 + c2 * a2;
                if den <= 0.0 {
                    return FRAC_1_PI / a2;
                }
                a2 * FRAC_1_PI / (den * den)
            }
            Distribution::Beckmann => {
                let tan2 = (1.0 - c2).max(0.0) / c2;
                let e = crate::fastmath::exp(-tan2 / a2);
                if e == 0.0 {
                    return 0.0;
                }
                e * FRAC_1_PI / (a2 * c2 * c2)
            }
        }
    }

    /// Smith `G1` for direction `v` with `cos_v = n·v`, `cos_vh = v·h`.
    #[inline]
    pub fn g1(&self, cos_v: f64, cos_vh: f64) -> f64 {
        if cos_vh * cos_v <= 0.0 {
            return 0.0;
        }
        let c2 = (cos_v * cos_v).min(1.0);
        let tan2 = (1.0 - c2).max(0.0) / c2;
        if tan2 == 0.0 {
            return 1.0;
        }
        let a2 = self.alpha * self.alpha;
        match self.dist {
            Distribution::Ggx => 2.0 / (1.0 + (1.0 + a2 * tan2).sqrt()),
            Distribution::Beckmann => {
                let a = 1.0 / (self.alpha * tan2.sqrt());
                if a >= 1.6 {
                    1.0
                } else {
                    let a_sqr = a * a;
                    (3.535 * a + 2.181 * a_sqr) / (1.0 + 2.276 * a + 2.577 * a_sqr)
                }
            }
        }
    }

    pub fn eval(&self, n: Vec3, wi: Vec3, wo: Vec3) -> f64 {
        let Some((ci, co, ch, cd)) = half_terms(n, wi, wo) else {
            return 0.0;
        };
        let d = self.d(ch);
        if d == 0.0 {
            return 0.0;
        }
        let g = match self.shadowing {
            Shadowing::Smith => self.g1(ci, cd) * self.g1(co, cd),
            Shadowing::VCavity => {
                if cd <= 0.0 {
                    0.0
                } else {
                    (2.0 * ch * co / cd).min(2.0 * ch * ci / cd).min(1.0)
                }
            }
        };
        self.ks * d * g * schlick(self.f0, cd) / (4.0 * ci * co)
    }

    pub fn spec(&self) -> String {
        match (self.dist, self.shadowing) {
            (Distribution::Beckmann, Shadowing::VCavity) => {
                format!(
                    "ct:m={},f0={},ks={}",
                    fmt_num(self.alpha),
                    fmt_num(self.f0),
                    fmt_num(self.ks)
                )
            }
            (d, _) => format!(
                "{}:alpha={},f0={},ks={}",
                if d == Distribution::Ggx {
                    "ggx"
                } else {
                    "beckmann"
                },
                fmt_num(self.alpha),
                fmt_num(self.f0),
                fmt_num(self.ks)
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::dir_from_deg;

    fn mf(dist: Distribution, alpha: f64) -> Microfacet {
        Microfacet {
            dist,
            shadowing: Shadowing::Smith,
            alpha,
            f0: 1.0,
            ks: 1.0,
        }
    }

    /// ∫ D(h)(h·n) dω_h = 1, by quadrature in cos theta.
    #[test]
    fn ndf_normalised() {
        for dist in [Distribution::Ggx, Distribution::Beckmann] {
            for alpha in [0.05, 0.2, 0.6] {
                let m = mf(dist, alpha);
                let nsteps = 200_000;
                let mut s = 0.0;
                for i in 0..nsteps {
                    let t = (i as f64 + 0.5) / nsteps as f64 * std::f64::consts::FRAC_PI_2;
                    s += m.d(t.cos()) * t.cos() * t.sin();
                }
                s *= std::f64::consts::TAU * std::f64::consts::FRAC_PI_2 / nsteps as f64;
                assert!((s - 1.0).abs() < 2e-3, "{dist:?} {alpha}: {s}");
            }
        }
    }

    /// A value computed by hand from Mitsuba 3's roughconductor formulas (material = none):
    /// GGX alpha 0.2, wi = (30°, 0°), wo = (40°, 180°), n = z.
    #[test]
    fn ggx_matches_hand_computed_mitsuba_value() {
        let m = mf(Distribution::Ggx, 0.2);
        let wi = dir_from_deg(30.0, 0.0);
        let wo = dir_from_deg(40.0, 180.0);
        let h = (wi + wo).normalized();
        let a2: f64 = 0.04;
        let c = h.z;
        let d = a2 / (std::f64::consts::PI * (c * c * (a2 - 1.0) + 1.0).powi(2));
        let g1 = |v: Vec3| {
            let t2 = (1.0 - v.z * v.z) / (v.z * v.z);
            2.0 / (1.0 + (1.0 + a2 * t2).sqrt())
        };
        let want = d * g1(wi) * g1(wo) / (4.0 * wi.z * wo.z);
        let got = m.eval(Vec3::Z, wi, wo);
        assert!((got / want - 1.0).abs() < 1e-12, "{got} {want}");
    }

    #[test]
    fn tiny_alpha_is_finite() {
        for dist in [Distribution::Ggx, Distribution::Beckmann] {
            let m = mf(dist, 1e-3);
            let wi = dir_from_deg(30.0, 0.0);
            let wo = dir_from_deg(30.0, 180.0);
            let v = m.eval(Vec3::Z, wi, wo);
            assert!(v.is_finite() && v > 0.0);
            let v2 = m.eval(Vec3::Z, wi, dir_from_deg(89.9, 180.0));
            assert!(v2.is_finite());
        }
    }
}
