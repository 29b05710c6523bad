//! Where a target look is compared with a candidate, and how much each comparison counts
//! (paper Sec. 6).
//!
//! Lighting directions are the library's 7 fixed lights. For each light, half of the view
//! directions are uniform over the hemisphere (a seeded, rotated Fibonacci set: every direction
//! has a chance) and half are importance-sampled by the norm of the target's angular gradient
//! (where the look changes: highlights, their edges, grazing falloff). The sampling density of a
//! view direction is the mixture `p(wo) = ½ · 1/(2π) + ½ · g(wo) / ∫ g`, with `g` the gradient
//! norm on a fixed candidate set; each sample carries the weight `w = p^(-1/4)` (Eq. 15).
//!
//! The distance between a target `t` and a candidate `f` over the samples is
//! `d(t, f) = Σ_s w_s² (t_s - f_s)²` (Eq. 14, the sum over the samples themselves: since they are
//! drawn with density `p`, it estimates `∫ p^½ (t - f)² dω`, so feature-rich regions count more,
//! but sub-linearly, and the diffuse body still counts), and the **relative error** is
//! `sqrt(d(t, f) / d(t, 0))`. Both compare `fbar` (cosine of the light included).

use crate::frame::{angles_of, dir_from_rad, rotate_z, Vec3};
use crate::rng::Rng;
use std::f64::consts::{PI, TAU};

/// Sampled direction pairs with their weights.
#[derive(Debug, Clone)]
pub struct Samples {
    /// `(light index, wo)`, in the frame of the (unrotated) geometry.
    pub pairs: Vec<(usize, Vec3)>,
    pub lights: Vec<Vec3>,
    /// `w = p^(-1/4)` per pair.
    pub weights: Vec<f64>,
}

/// Sampling settings: view directions per light, the share drawn by gradient, the seed.
#[derive(Debug, Clone, Copy)]
pub struct SamplingConfig {
    pub views_per_light: usize,
    pub gradient_share: f64,
    pub seed: u64,
}

impl Default for SamplingConfig {
    fn default() -> Self {
        SamplingConfig {
            views_per_light: 70,
            gradient_share: 0.5,
            seed: 1,
        }
    }
}

/// Fibonacci points on the upper hemisphere, uniform in solid angle, rotated by `spin`.
fn fibonacci(n: usize, spin: f64) -> Vec<Vec3> {
    (0..n)
        .map(|k| {
            let u = (k as f64 + 0.5) / n as f64;
            let theta = u.acos().min(89.0f64.to_radians());
            dir_from_rad(
                theta,
                TAU * ((k as f64 * 0.618_033_988_749_895 + spin).fract()),
            )
        })
        .collect()
}

/// Norm of the angular gradient of `f(wo)` by central differences (per radian).
fn gradient(f: &dyn Fn(Vec3) -> f64, wo: Vec3) -> f64 {
    let (theta, phi) = angles_of(wo);
    let h = 0.02;
    let t0 = (theta - h).max(0.0);
    let t1 = (theta + h).min(89.5f64.to_radians());
    let dt = (f(dir_from_rad(t1, phi)) - f(dir_from_rad(t0, phi))) / (t1 - t0).max(1e-9);
    let s = theta.sin().max(0.05);
    let dp = (f(dir_from_rad(theta, phi + h)) - f(dir_from_rad(theta, phi - h))) / (2.0 * h * s);
    let g = (dt * dt + dp * dp).sqrt();
    if g.is_finite() {
        g
    } else {
        0.0
    }
}

/// Sample the pairs for a target `fbar(wi, wo)` (seen in the geometry's frame).
pub fn sample(
    lights: &[Vec3],
    target: &(dyn Fn(Vec3, Vec3) -> f64 + Sync),
    cfg: &SamplingConfig,
) -> Samples {
    let mut rng = Rng::new(cfg.seed);
    let n = cfg.views_per_light.max(2);
    let n_grad = ((n as f64 * cfg.gradient_share.clamp(0.0, 1.0)).round() as usize).min(n);
    let n_uni = n - n_grad;
    // Candidate set for the gradient density; each candidate owns 2π/M steradians.
    const M: usize = 1024;
    let cands = fibonacci(M, 0.0);
    let mut pairs = Vec::with_capacity(n * lights.len());
    let mut weights = Vec::with_capacity(n * lights.len());
    for (l, &wi) in lights.iter().enumerate() {
        let f = |wo: Vec3| target(wi, wo);
        let g: Vec<f64> = cands.iter().map(|&c| gradient(&f, c)).collect();
        let gsum: f64 = g.iter().sum();
        let mean_g = gsum / M as f64;
        // Density of a direction: uniform half plus the gradient half (density g / ∫g, where
        // ∫g ≈ mean_g · 2π).
        let share = if gsum > 0.0 {
            cfg.gradient_share.clamp(0.0, 1.0)
        } else {
            0.0
        };
        let density = |gw: f64| {
            let grad = if mean_g > 0.0 {
                gw / (mean_g * TAU)
            } else {
                0.0
            };
            (1.0 - share) / TAU + share * grad
        };
        let mut views: Vec<Vec3> =
            fibonacci(n_uni + if share == 0.0 { n_grad } else { 0 }, rng.uniform());
        if share > 0.0 {
            // Systematic resampling of the candidates by g, jittered inside each candidate's cell.
            let mut cdf = Vec::with_capacity(M);
            let mut acc = 0.0;
            for x in &g {
                acc += x / gsum;
                cdf.push(acc);
            }
            let u0 = rng.uniform();
            let mut k = 0;
            for s in 0..n_grad {
                let u = (s as f64 + u0) / n_grad as f64;
                while k + 1 < M && cdf[k] < u {
                    k += 1;
                }
                let (t, p) = angles_of(cands[k]);
                let cell = (2.0 * PI / M as f64).sqrt() * 0.5;
                let jt = (t + (rng.uniform() - 0.5) * cell).clamp(0.0, 89.0f64.to_radians());
                let jp = p + (rng.uniform() - 0.5) * cell / t.sin().max(0.05);
                views.push(dir_from_rad(jt, jp));
            }
        }
        for wo in views {
            let p = density(gradient(&f, wo)).max(1e-6);
            pairs.push((l, wo));
            weights.push(p.powf(-0.25));
        }
    }
    Samples {
        pairs,
        lights: lights.to_vec(),
        weights,
    }
}

/// How far the brightness of a guessed material may be off when errors are taken at the best
/// brightness ([`scaled_rel_error`]): scales in `[1/4, 4]`. A library's specular materials span
/// Fresnel `f0` from 0.02 to 0.97; the general solver's starts are within a few times of the
/// look's brightness, and a wider range lets nearly black geometries (deep grooves at grazing
/// views) pass for bright ones.
pub const MAX_BRIGHTNESS_SCALE: f64 = 4.0;

/// The relative error `sqrt(|t − s f|² / |t|²)` (weighted) from `n2 = |t|²`, `lin = ⟨t, f⟩` and
/// `quad = |f|²`: at `s = 1`, or, when `any_brightness`, at the `s` in `[1/MAX_BRIGHTNESS_SCALE,
/// MAX_BRIGHTNESS_SCALE]` that minimises it (`lin / quad`, clamped): the error of `f`'s shape,
/// whatever its brightness. Infinite for a black target.
pub fn scaled_rel_error(n2: f64, lin: f64, quad: f64, any_brightness: bool) -> f64 {
    let s = if any_brightness && quad > 0.0 {
        (lin / quad).clamp(1.0 / MAX_BRIGHTNESS_SCALE, MAX_BRIGHTNESS_SCALE)
    } else {
        1.0
    };
    if n2 > 0.0 {
        ((n2 - 2.0 * s * lin + s * s * quad).max(0.0) / n2).sqrt()
    } else {
        f64::INFINITY
    }
}

impl Samples {
    /// Every `step`-th pair (from the first) with its weight, and the same entries of `t`: a
    /// coarse version of the set, for ranking many candidates before evaluating the best at
    /// every pair.
    pub fn every(&self, step: usize, t: &[f64]) -> (Samples, Vec<f64>) {
        let step = step.max(1);
        let s = Samples {
            pairs: self.pairs.iter().step_by(step).copied().collect(),
            lights: self.lights.clone(),
            weights: self.weights.iter().step_by(step).copied().collect(),
        };
        (s, t.iter().step_by(step).copied().collect())
    }

    /// The target's values at the samples, with the geometry rotated by `psi` about the normal
    /// (the target is read at the pairs rotated by `psi`, Sec. 6).
    pub fn values(&self, target: &(dyn Fn(Vec3, Vec3) -> f64 + Sync), psi: f64) -> Vec<f64> {
        self.pairs
            .iter()
            .map(|&(l, wo)| {
                let v = target(rotate_z(self.lights[l], psi), rotate_z(wo, psi));
                if v.is_finite() {
                    v.max(0.0)
                } else {
                    0.0
                }
            })
            .collect()
    }

    /// `d(t, 0) = Σ w² t²`.
    pub fn norm2(&self, t: &[f64]) -> f64 {
        t.iter()
            .zip(&self.weights)
            .map(|(t, w)| w * w * t * t)
            .sum()
    }

    /// [`Samples::rel_error`] of `f` scaled by the factor in `[1/MAX_BRIGHTNESS_SCALE,
    /// MAX_BRIGHTNESS_SCALE]` that brings it closest to `t` when `any_brightness` (a guessed
    /// material's brightness is the next material solve's to fix, [`scaled_rel_error`]), else
    /// of `f` itself.
    pub fn rel_error_scaled(&self, t: &[f64], f: &[f64], any_brightness: bool) -> f64 {
        if !any_brightness {
            return self.rel_error(t, f);
        }
        let (mut n2, mut lin, mut quad) = (0.0, 0.0, 0.0);
        for ((t, f), w) in t.iter().zip(f).zip(&self.weights) {
            let w2 = w * w;
            n2 += w2 * t * t;
            lin += w2 * t * f;
            quad += w2 * f * f;
        }
        scaled_rel_error(n2, lin, quad, true)
    }

    /// Relative error `sqrt(d(t, f) / d(t, 0))`.
    pub fn rel_error(&self, t: &[f64], f: &[f64]) -> f64 {
        let n = self.norm2(t);
        let d: f64 = t
            .iter()
            .zip(f)
            .zip(&self.weights)
            .map(|((t, f), w)| w * w * (t - f) * (t - f))
            .sum();
        if n > 0.0 {
            (d / n).sqrt()
        } else if d > 0.0 {
            f64::INFINITY
        } else {
            0.0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::target::Target;

    #[test]
    fn errors_at_the_best_brightness_fit_a_scaled_copy_within_the_range() {
        let s = Samples {
            pairs: vec![(0, Vec3::Z); 3],
            lights: vec![Vec3::Z],
            weights: vec![1.0, 0.5, 2.0],
        };
        let t = [1.0, 2.0, 0.5];
        let f = |k: f64| t.iter().map(|v| k * v).collect::<Vec<_>>();
        assert_eq!(
            s.rel_error_scaled(&t, &f(2.0), false),
            s.rel_error(&t, &f(2.0))
        );
        assert!((s.rel_error(&t, &f(2.0)) - 1.0).abs() < 1e-12);
        // Twice as bright: fitted exactly; ten times: the scale stops at 4 (2.5x the target).
        assert!(s.rel_error_scaled(&t, &f(2.0), true) < 1e-7);
        assert!((s.rel_error_scaled(&t, &f(10.0), true) - 1.5).abs() < 1e-12);
        // A different shape keeps an error; a black target has no scale.
        assert!(s.rel_error_scaled(&t, &[2.0, 1.0, 0.5], true) > 0.1);
        assert_eq!(scaled_rel_error(0.0, 0.0, 1.0, true), f64::INFINITY);
    }

    #[test]
    fn every_keeps_each_steps_pair_with_its_weight_and_target_value() {
        let s = Samples {
            pairs: (0..10).map(|i| (i % 2, Vec3::new(0.0, 0.0, 1.0))).collect(),
            lights: vec![Vec3::Z, Vec3::Z],
            weights: (0..10).map(|i| i as f64).collect(),
        };
        let t: Vec<f64> = (0..10).map(|i| 10.0 * i as f64).collect();
        let (c, ct) = s.every(4, &t);
        assert_eq!(c.weights, vec![0.0, 4.0, 8.0]);
        assert_eq!(ct, vec![0.0, 40.0, 80.0]);
        assert_eq!(c.pairs.len(), 3);
        assert_eq!(c.lights.len(), 2);
        assert_eq!(s.every(0, &t).1, t, "a step of 0 keeps every pair");
    }

    #[test]
    fn samples_concentrate_on_the_highlight_and_weights_follow_the_density() {
        let t = Target::parse("ggx:alpha=0.1+lambert:albedo=0.2").unwrap();
        let f = |wi: Vec3, wo: Vec3| t.fbar(wi, wo);
        let lights = vec![crate::frame::dir_from_deg(40.0, 0.0)];
        let s = sample(&lights, &f, &SamplingConfig::default());
        assert_eq!(s.pairs.len(), 70);
        // Mirror direction of the light.
        let mirror = crate::frame::dir_from_deg(40.0, 180.0);
        let near = s
            .pairs
            .iter()
            .filter(|(_, wo)| wo.dot(mirror) > 0.9)
            .count();
        // Uniform sampling would put about 70 · (1 - 0.9) = 7 there.
        assert!(near > 12, "{near} samples near the highlight");
        let (wmin, wmax) = s
            .weights
            .iter()
            .fold((f64::MAX, 0.0f64), |a, &w| (a.0.min(w), a.1.max(w)));
        assert!(wmin > 0.0 && wmax > wmin && wmax.is_finite());
        // Deterministic.
        let s2 = sample(&lights, &f, &SamplingConfig::default());
        assert_eq!(s.pairs.len(), s2.pairs.len());
        assert!(s.pairs.iter().zip(&s2.pairs).all(|(a, b)| a.1 == b.1));
        // The error is 0 against itself and 1 against nothing.
        let v = s.values(&f, 0.0);
        assert_eq!(s.rel_error(&v, &v), 0.0);
        assert!((s.rel_error(&v, &vec![0.0; v.len()]) - 1.0).abs() < 1e-12);
    }
}
