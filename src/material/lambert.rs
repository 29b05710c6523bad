//! Lambertian lobe: `f_r = albedo / pi`.

use crate::frame::Vec3;
use std::f64::consts::FRAC_1_PI;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lambert {
    pub albedo: f64,
}

impl Lambert {
    pub fn eval(&self, n: Vec3, wi: Vec3, wo: Vec3) -> f64 {
        if n.dot(wi) <= 0.0 || n.dot(wo) <= 0.0 {
            0.0
        } else {
            self.albedo * FRAC_1_PI
        }
    }
    pub fn spec(&self) -> String {
        format!("lambert:albedo={}", super::fmt_num(self.albedo))
    }
}
