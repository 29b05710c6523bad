//! Blinn–Phong lobe with the energy-conserving normalisation of Akenine-Möller et al.
//! (Real-Time Rendering): `f_r = ks (n + 8) / (8 pi) · (n·h)^n`.

use super::{fmt_num, half_terms};
use crate::frame::Vec3;
use std::f64::consts::PI;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlinnPhong {
    /// Exponent, `n >= 0`.
    pub n: f64,
    pub ks: f64,
}

impl BlinnPhong {
    pub fn eval(&self, n: Vec3, wi: Vec3, wo: Vec3) -> f64 {
        let Some((_, _, ch, _)) = half_terms(n, wi, wo) else {
            return 0.0;
        };
        if ch <= 0.0 {
            return 0.0;
        }
        // exp(n ln c) underflows cleanly to 0 for huge exponents.
        self.ks * (self.n + 8.0) / (8.0 * PI) * (self.n * ch.ln()).exp()
    }
    pub fn spec(&self) -> String {
        format!("blinn:n={},ks={}", fmt_num(self.n), fmt_num(self.ks))
    }
}
