//! Small-scale materials: isotropic BRDFs `f_r(n, wi, wo)` evaluated for any facet normal `n`,
//! as a single spectrally averaged channel (what the solvers use) plus an RGB colour.
//!
//! A [`Material`] is a sum of lobes; each lobe is one model in its own module. Every model is
//! written with dot products only, so a facet with normal `n` needs no local frame. Every model
//! returns 0 when `n·wi <= 0` or `n·wo <= 0`, and never NaN or inf for unit inputs.

mod lambert;
mod merl;
mod microfacet;
mod phong;
mod spec;
mod ward;

pub use merl::MerlBrdf;
pub use microfacet::{Distribution, Microfacet, Shadowing};
pub(crate) use spec::round_sig4;
pub(crate) use spec::Params;
pub use spec::{
    map_path_terms, param_scaled, parse_material, spec_params, spec_scaled, MATERIAL_GRAMMAR,
};
pub use ward::{AnisoWard, Ward};

use crate::frame::Vec3;
use std::sync::Arc;

pub use lambert::Lambert;
pub use phong::BlinnPhong;

/// One additive term of a material.
#[derive(Debug, Clone)]
pub enum Lobe {
    Lambert(Lambert),
    Microfacet(Microfacet),
    Ward(Ward),
    Blinn(BlinnPhong),
    Merl(Arc<MerlBrdf>),
}

impl Lobe {
    /// Single-channel `f_r` for a facet with unit normal `n`.
    pub fn eval(&self, n: Vec3, wi: Vec3, wo: Vec3) -> f64 {
        match self {
            Lobe::Lambert(l) => l.eval(n, wi, wo),
            Lobe::Microfacet(m) => m.eval(n, wi, wo),
            Lobe::Ward(w) => w.eval(n, wi, wo),
            Lobe::Blinn(b) => b.eval(n, wi, wo),
            Lobe::Merl(m) => m.eval(n, wi, wo),
        }
    }

    /// RGB value of the lobe (only measured data has its own colour; analytic lobes are grey).
    pub fn eval_rgb(&self, n: Vec3, wi: Vec3, wo: Vec3) -> [f64; 3] {
        match self {
            Lobe::Merl(m) => m.eval_rgb(n, wi, wo),
            other => [other.eval(n, wi, wo); 3],
        }
    }

    /// Canonical spec of the lobe, parameters included.
    pub fn spec(&self) -> String {
        match self {
            Lobe::Lambert(l) => l.spec(),
            Lobe::Microfacet(m) => m.spec(),
            Lobe::Ward(w) => w.spec(),
            Lobe::Blinn(b) => b.spec(),
            Lobe::Merl(m) => m.path.clone(),
        }
    }

    /// A width in normal space (radians) below which the lobe behaves like a mirror, used to
    /// choose quadrature; `None` for smooth (diffuse or measured) lobes.
    pub fn lobe_width(&self) -> Option<f64> {
        match self {
            Lobe::Lambert(_) | Lobe::Merl(_) => None,
            Lobe::Microfacet(m) => Some(m.alpha),
            Lobe::Ward(w) => Some(w.alpha),
            Lobe::Blinn(b) => Some((2.0 / (b.n + 2.0)).sqrt()),
        }
    }

    /// The angle between a facet normal and the half vector beyond which a glossy lobe is
    /// negligible: `D` below 1e-6 of its peak for GGX (30 α; the tail beyond holds about
    /// `α² / (30 α)² ≈ 0.1 %` of the lobe), below `e^-36` for Beckmann, Cook–Torrance and Ward
    /// (6 α), below `e^-18` for Blinn–Phong (`6 / sqrt(n)`). `None` for smooth lobes.
    pub fn support_radius(&self) -> Option<f64> {
        let r = match self {
            Lobe::Lambert(_) | Lobe::Merl(_) => return None,
            Lobe::Microfacet(m) => match m.dist {
                Distribution::Ggx => 30.0 * m.alpha,
                Distribution::Beckmann => 6.0 * m.alpha,
            },
            Lobe::Ward(w) => 6.0 * w.alpha,
            Lobe::Blinn(b) => 6.0 / b.n.max(1.0).sqrt(),
        };
        Some(r.min(std::f64::consts::FRAC_PI_2))
    }
}

/// A small-scale material: a sum of lobes and a colour multiplier whose channel mean is 1.
#[derive(Debug, Clone)]
pub struct Material {
    pub lobes: Vec<Lobe>,
    /// RGB multiplier with mean 1; measured lobes carry their own colour on top.
    pub color: [f64; 3],
}

impl Material {
    pub fn new(lobes: Vec<Lobe>) -> Self {
        Material {
            lobes,
            color: [1.0; 3],
        }
    }

    /// Single-channel (spectrally averaged) `f_r(n, wi, wo)`.
    pub fn eval(&self, n: Vec3, wi: Vec3, wo: Vec3) -> f64 {
        if n.dot(wi) <= 0.0 || n.dot(wo) <= 0.0 {
            return 0.0;
        }
        self.lobes.iter().map(|l| l.eval(n, wi, wo)).sum()
    }

    /// RGB `f_r(n, wi, wo)`.
    pub fn eval_rgb(&self, n: Vec3, wi: Vec3, wo: Vec3) -> [f64; 3] {
        let mut out = [0.0; 3];
        if n.dot(wi) <= 0.0 || n.dot(wo) <= 0.0 {
            return out;
        }
        for l in &self.lobes {
            let v = l.eval_rgb(n, wi, wo);
            for c in 0..3 {
                out[c] += v[c] * self.color[c];
            }
        }
        out
    }

    /// Canonical spec (`lobe+lobe`), parseable by [`parse_material`].
    pub fn spec(&self) -> String {
        let s: Vec<String> = self.lobes.iter().map(|l| l.spec()).collect();
        let mut s = s.join("+");
        if self.color != [1.0; 3] {
            s.push_str(&format!(
                ",rgb={}:{}:{}",
                fmt_num(self.color[0]),
                fmt_num(self.color[1]),
                fmt_num(self.color[2])
            ));
        }
        s
    }

    /// The material split into its lobes at least `width` wide (and smooth ones) and its glossy
    /// lobes narrower than `width`, each part with this material's colour. Either may have no
    /// lobes.
    pub fn split_by_width(&self, width: f64) -> (Material, Material) {
        let (sharp, rest): (Vec<Lobe>, Vec<Lobe>) = self
            .lobes
            .iter()
            .cloned()
            .partition(|l| l.lobe_width().is_some_and(|w| w < width));
        (
            Material {
                lobes: rest,
                color: self.color,
            },
            Material {
                lobes: sharp,
                color: self.color,
            },
        )
    }

    /// The narrowest glossy lobe width (radians), if any lobe is glossy.
    pub fn min_lobe_width(&self) -> Option<f64> {
        self.lobes
            .iter()
            .filter_map(|l| l.lobe_width())
            .reduce(f64::min)
    }
}

/// Shortest decimal that round-trips, for canonical specs: in exponent form beyond 1e15 and
/// below 1e-9 ([`crate::error::show_num`]), where the plain form runs to hundreds of digits.
pub(crate) fn fmt_num(v: f64) -> String {
    crate::error::show_num(v)
}

/// `(n·wi, n·wo, n·h, wi·h)` for unit inputs, with `h` the normalised half vector; `None` when
/// either cosine is not positive or the half vector degenerates (`wi = -wo`).
#[inline]
pub(crate) fn half_terms(n: Vec3, wi: Vec3, wo: Vec3) -> Option<(f64, f64, f64, f64)> {
    let ci = n.dot(wi);
    let co = n.dot(wo);
    if ci <= 0.0 || co <= 0.0 {
        return None;
    }
    let hs = wi + wo;
    let len = hs.norm();
    if len < 1e-12 {
        return None;
    }
    let h = hs * (1.0 / len);
    Some((
        ci,
        co,
        n.dot(h).clamp(-1.0, 1.0),
        wi.dot(h).clamp(-1.0, 1.0),
    ))
}

/// Schlick's Fresnel approximation; `f0 = 1` gives exactly 1 (no Fresnel).
#[inline]
pub(crate) fn schlick(f0: f64, cos_d: f64) -> f64 {
    let m = (1.0 - cos_d).clamp(0.0, 1.0);
    let m2 = m * m;
    f0 + (1.0 - f0) * m2 * m2 * m
}
