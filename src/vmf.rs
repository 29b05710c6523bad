//! von Mises–Fisher lobes on the unit sphere (paper Eq. 4–5), evaluated without overflow.
//!
//! `rho(n; kappa, mu) = kappa / (4 pi sinh kappa) · exp(kappa n·mu)` is never evaluated as written:
//! it is `kappa / (2 pi (1 - exp(-2 kappa))) · exp(kappa (n·mu - 1))`, with `-expm1(-2 kappa)` and
//! the limit `1/(4 pi)` as kappa → 0. Lobes with kappa of 1e4–1e6 (mirror-like facets) are normal
//! input.

use crate::frame::{frame_around, Vec3};
use std::f64::consts::{PI, TAU};

/// Largest concentration used anywhere: a lobe of angular width ~1e-3 rad.
pub const KAPPA_MAX: f64 = 1e6;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Vmf {
    pub kappa: f64,
    /// Unit mean direction.
    pub mu: Vec3,
}

/// Normalisation `kappa / (2 pi (1 - exp(-2 kappa)))`, i.e. the density at `n = mu`.
#[inline]
pub fn vmf_norm(kappa: f64) -> f64 {
    if kappa < 1e-6 {
        // kappa/(2 pi (2 kappa - 2 kappa² + ...)) → (1 + kappa)/(4 pi)
        (1.0 + kappa) / (4.0 * PI)
    } else {
        kappa / (TAU * (-(-2.0 * kappa).exp_m1()))
    }
}

impl Vmf {
    pub fn new(kappa: f64, mu: Vec3) -> Self {
        Vmf {
            kappa: kappa.clamp(0.0, KAPPA_MAX),
            mu,
        }
    }

    /// Density at unit `n`.
    #[inline]
    pub fn eval(&self, n: Vec3) -> f64 {
        let c = n.dot(self.mu).clamp(-1.0, 1.0);
        vmf_norm(self.kappa) * crate::fastmath::exp(self.kappa * (c - 1.0))
    }

    /// `cos` of the angle to `mu` for uniform `u` in `[0, 1)` (inverse CDF, stable for all kappa).
    #[inline]
    pub fn sample_cos(kappa: f64, u: f64) -> f64 {
        if kappa < 1e-6 {
            return 1.0 - 2.0 * u;
        }
        // w = 1 + ln(1 - u (1 - exp(-2 kappa))) / kappa
        let w = 1.0 + (-u * (-(-2.0 * kappa).exp_m1())).ln_1p() / kappa;
        w.clamp(-1.0, 1.0)
    }

    /// A direction distributed by this lobe for uniform `(u, v)` in `[0, 1)²`.
    pub fn sample(&self, u: f64, v: f64) -> Vec3 {
        Self::place(
            self.mu,
            frame_around(self.mu),
            &Self::local_sample(self.kappa, u, v),
        )
    }

    /// [`Vmf::sample`] in the lobe's own frame (`mu` along z): `[s cos φ, s sin φ, w]`. It
    /// depends on `kappa` only, so a quadrature over many lobes of one `kappa` computes it once.
    #[inline]
    pub fn local_sample(kappa: f64, u: f64, v: f64) -> [f64; 3] {
        let w = Self::sample_cos(kappa, u);
        let s = (1.0 - w * w).max(0.0).sqrt();
        let (sp, cp) = (TAU * v).sin_cos();
        [s * cp, s * sp, w]
    }

    /// A local sample placed around unit `mu` with `frame = frame_around(mu)`.
    #[inline]
    pub fn place(mu: Vec3, (t, b): (Vec3, Vec3), l: &[f64; 3]) -> Vec3 {
        (t * l[0] + b * l[1] + mu * l[2]).normalized()
    }
}

/// Mean resultant length `A(kappa) = coth(kappa) - 1/kappa` of a 3-D vMF.
pub fn mean_resultant(kappa: f64) -> f64 {
    if kappa < 1e-4 {
        kappa / 3.0
    } else if kappa > 50.0 {
        1.0 - 1.0 / kappa
    } else {
        1.0 / kappa.tanh() - 1.0 / kappa
    }
}

/// The kappa whose mean resultant length is `r` in `[0, 1]` (Banerjee et al. 2005 start, then
/// Newton), clamped to `[0, KAPPA_MAX]`.
pub fn kappa_from_resultant(r: f64) -> f64 {
    if !(r > 0.0) {
        return 0.0;
    }
    if r >= 1.0 - 1.0 / KAPPA_MAX {
        return KAPPA_MAX;
    }
    let mut k = r * (3.0 - r * r) / (1.0 - r * r);
    for _ in 0..4 {
        if k > 50.0 {
            // A(k) = 1 - 1/k exactly to double precision here.
            k = 1.0 / (1.0 - r);
            break;
        }
        let a = mean_resultant(k);
        let sh = k.sinh();
        let da = 1.0 / (k * k) - 1.0 / (sh * sh);
        if !(da > 0.0) {
            break;
        }
        let step = (a - r) / da;
        k = (k - step).max(k * 0.1);
    }
    k.clamp(0.0, KAPPA_MAX)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::dir_from_deg;

    /// Integrates to 1 and never overflows, for kappa from 1e-8 to 1e6.
    #[test]
    fn normalised_and_finite_over_the_whole_range() {
        for &k in &[1e-8, 1e-3, 0.5, 3.0, 50.0, 1e3, 1e4, 1e6] {
            let l = Vmf::new(k, Vec3::Z);
            // integrate in cos theta around mu with a grid fine enough for the lobe width
            let n = 400_000;
            let mut s = 0.0;
            let width = (10.0 / k).min(2.0);
            for i in 0..n {
                let c = 1.0 - width * (i as f64 + 0.5) / n as f64;
                let v = l.eval(crate::frame::Vec3::new(
                    (1.0 - c * c).max(0.0).sqrt(),
                    0.0,
                    c,
                ));
                assert!(v.is_finite());
                s += v;
            }
            s *= TAU * width / n as f64;
            assert!(
                (s - 1.0).abs() < 1e-3 || k > 5e5 && (s - 1.0).abs() < 1e-2,
                "kappa {k}: {s}"
            );
            let far = l.eval(dir_from_deg(179.0, 0.0));
            assert!(far.is_finite() && far >= 0.0);
        }
    }

    #[test]
    fn resultant_round_trip() {
        for &k in &[1e-3, 0.3, 2.0, 10.0, 80.0, 1e4] {
            let r = mean_resultant(k);
            let k2 = kappa_from_resultant(r);
            assert!((k2 / k - 1.0).abs() < 1e-4, "{k} {k2}");
        }
    }

    #[test]
    fn resultant_inverts_to_nine_digits_across_the_newton_range() {
        // Up to the closed form beyond 50.
        for i in 0..=400 {
            let k = 0.05 * 1.02f64.powi(i);
            if k > 49.0 {
                break;
            }
            let k2 = kappa_from_resultant(mean_resultant(k));
            assert!((k2 / k - 1.0).abs() < 1e-9, "{k} {k2}");
        }
    }

    #[test]
    fn sampling_matches_mean() {
        let l = Vmf::new(5.0, dir_from_deg(30.0, 40.0));
        let n = 20_000;
        let mut m = Vec3::default();
        for i in 0..n {
            let u = (i as f64 + 0.5) / n as f64;
            let v = (i as f64 * 0.618_033_988_749_895).fract();
            m = m + l.sample(u, v);
        }
        let r = (m * (1.0 / n as f64)).dot(l.mu);
        assert!((r - mean_resultant(5.0)).abs() < 1e-3, "{r}");
    }
}
