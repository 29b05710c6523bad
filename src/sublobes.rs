//! A curved normal cluster's shape: its facets' normal distribution split into sub-lobes, and
//! how much of each sub-lobe a direction pair sees.
//!
//! One vMF per cluster does not follow the flat-topped distribution of a rough surface's
//! cluster, which a glossy lobe resolves; so [`crate::bvndf`] reads a curved cluster as up to 16
//! vMFs, the parts of its facets found by area-weighted k-means ([`cluster_shapes`]). The table
//! holds only the cluster's jointly visible moments at a pair (`G1 = Σ A n V`, `G2 = Σ A n nᵀ V`),
//! not which of its parts are visible. A grazing view over tall bumps sees the sides of the
//! bumps that face it and not those behind, so the parts are not seen alike: each part's visible
//! fraction is fitted to the 9 tabulated moments ([`Shape::push`]): the parts' fractions closest
//! (least squares) to the fraction the whole cluster has, among those whose moments sum to the
//! tabulated ones, clamped to `[0, 1]`. Nine moments do not say which of 16 parts are seen, so
//! the fit does not single them out; it gives the parts the visible spread and mean that the
//! table holds. The parts are then weighted by their visible projected area towards `wo` and
//! turned together so that their `(n·wo)`-weighted mean normal is the tabulated one, `G2 wo`.
//!
//! Measured against the exact method (docs/forward-model.md, "Which parts of a cluster a
//! grazing view sees"): on tall surfaces under glossy lobes the fit takes up to 0.7 points off the
//! relative RMS error (the 64² tall bumps under GGX 0.2: 4.48 → 3.81 %). An exponential tilt of the parts' weights that matches only the mean
//! normal's direction (two parameters, Newton's method) was tried instead and was worse on four
//! of five surfaces (e.g. the tall fBm under Beckmann 0.2: 4.51 % against 4.00 %).

use crate::bvndf::{cluster_normals, moments, second_times, STRIDE};
use crate::frame::{Rotation, Vec3};
use crate::vmf::{kappa_from_resultant, Vmf};
use faer::linalg::solvers::Solve;
use faer::{Mat, Side};
use rayon::prelude::*;

/// The ridge of the fit, relative to the parts' moments taken in units of the cluster's
/// `Σ |Σ A n|` (so that each part's moments are about its share of the cluster, 1/16 for 16
/// parts). Small: the fit matches the tabulated moments nearly exactly, and only where the parts'
/// moments are nearly dependent (normals close together) does the ridge choose. On the tall
/// bumps of docs/forward-model.md under `ggx:alpha=0.3`, 1e-2, 1e-4, 1e-6 and 1e-8 gave 3.84,
/// 3.71, 3.03 and 2.99 % (the last two with the seen table's turn, which alone gives 3.36 %;
/// scratch runs).
const RIDGE: f64 = 1e-6;

/// One part of a cluster's normal distribution, from all its facets (visibility aside).
#[derive(Debug, Clone, PartialEq)]
pub struct SubLobe {
    /// `Σ A n` over the part's facets, in units of `A_base`.
    pub resultant: Vec3,
    /// `Σ A n nᵀ` (xx, yy, zz, xy, xz, yz).
    pub second: [f64; 6],
    /// The part's own vMF (mean direction, concentration from the mean resultant length).
    pub lobe: Vmf,
}

/// A curved cluster as its sub-lobes, with what fits their visible fractions at a pair.
#[derive(Debug, Clone, PartialEq)]
pub struct Shape {
    /// The sub-lobes (empty: the cluster is one vMF).
    pub parts: Vec<SubLobe>,
    /// `Σ |Σ A n|` over the parts: the unit of the fit's moments.
    scale: f64,
    /// Per part, its 9 moments (`Σ A n`, `Σ A n nᵀ`) over `scale`: the columns of `M`.
    columns: Vec<[f64; STRIDE]>,
    /// Per part, `(M Mᵀ + RIDGE · I)⁻¹` times its column: the fit's step for the part is this
    /// times the residual of the moments. Empty with fewer than 2 parts (no fit).
    gains: Vec<[f64; STRIDE]>,
}

impl Shape {
    /// The shape of `parts`, with the fit's gains computed once here (`faer`'s Cholesky).
    pub fn new(parts: Vec<SubLobe>) -> Self {
        let scale: f64 = parts.iter().map(|p| p.resultant.norm()).sum();
        let columns: Vec<[f64; STRIDE]> = if scale > 0.0 {
            parts
                .iter()
                .map(|p| {
                    let r = p.resultant;
                    let mut c = [r.x, r.y, r.z, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
                    c[3..].copy_from_slice(&p.second);
                    c.map(|x| x / scale)
                })
                .collect()
        } else {
            Vec::new()
        };
        let gains = if parts.len() < 2 || columns.is_empty() {
            Vec::new()
        } else {
            gains_of(&columns)
        };
        Shape {
            parts,
            scale,
            columns,
            gains,
        }
    }

    /// The same parts weighted by their projected area towards `wo` alone, without the fit of
    /// their visible fractions (the sub-lobes as they were read before it: a comparison).
    pub fn unfitted(&self) -> Self {
        Shape {
            gains: Vec::new(),
            ..self.clone()
        }
    }

    /// Bytes of the sub-lobes and the fit's columns and gains.
    pub fn bytes(&self) -> usize {
        self.parts.len() * std::mem::size_of::<SubLobe>()
            + (self.columns.len() + self.gains.len()) * STRIDE * 8
            + 8
    }

    /// Whether the cluster has no sub-lobes.
    pub fn is_empty(&self) -> bool {
        self.parts.is_empty()
    }

    /// Each part's visible fraction at a pair whose interpolated jointly visible moments are
    /// `g` (module doc): 0 for the parts that do not face `wo`; the whole cluster's fraction
    /// (`wo·G1` over the facing parts' projected area) where there is no fit.
    pub(crate) fn visible(&self, wo: Vec3, g: &[f64; STRIDE], fraction: &mut Vec<f64>) {
        // First each part's projected area towards wo, then its fraction.
        fraction.clear();
        fraction.extend(self.parts.iter().map(|p| p.resultant.dot(wo).max(0.0)));
        let facing: f64 = fraction.iter().sum();
        if !(facing > 0.0) {
            return;
        }
        let seen = wo.x * g[0] + wo.y * g[1] + wo.z * g[2];
        let t = (seen / facing).clamp(0.0, 1.0);
        if self.gains.is_empty() {
            for f in fraction.iter_mut().filter(|f| **f > 0.0) {
                *f = t;
            }
            return;
        }
        // The residual of the uniform fraction, then the least-squares step that removes it.
        let mut r: [f64; STRIDE] = std::array::from_fn(|k| g[k] / self.scale);
        for (c, &a) in self.columns.iter().zip(fraction.iter()) {
            if a > 0.0 {
                for k in 0..STRIDE {
                    r[k] -= t * c[k];
                }
            }
        }
        let mut fitted = 0.0;
        for (f, gain) in fraction.iter_mut().zip(&self.gains) {
            let area = *f;
            if area > 0.0 {
                let step: f64 = (0..STRIDE).map(|k| gain[k] * r[k]).sum();
                let v = (t + step).clamp(0.0, 1.0);
                *f = if v.is_finite() { v } else { t };
                fitted += *f * area;
            }
        }
        if !(fitted > 0.0) {
            // Nothing left visible: keep the whole cluster's fraction.
            for (f, p) in fraction.iter_mut().zip(&self.parts) {
                *f = if p.resultant.dot(wo) > 0.0 { t } else { 0.0 };
            }
        }
    }

    /// The cluster as its sub-lobes at a pair: each weighted by its fitted visible projected
    /// area towards `wo` ([`Self::visible`], from the interpolated moments `g`), the whole set
    /// turned so that its `(n·wo)`-weighted mean normal is `m`, the weights summing to the
    /// cluster's `share`. False (nothing pushed) when no sub-lobe faces `wo`.
    pub(crate) fn push(
        &self,
        wo: Vec3,
        m: Vec3,
        g: &[f64; STRIDE],
        share: f64,
        out: &mut Vec<(f64, Vmf)>,
    ) -> bool {
        let mut fraction = Vec::with_capacity(self.parts.len());
        self.visible(wo, g, &mut fraction);
        let start = out.len();
        let mut total = 0.0;
        let mut pred = Vec3::default();
        for (s, &f) in self.parts.iter().zip(&fraction) {
            let w = s.resultant.dot(wo) * f;
            if w > 0.0 {
                pred = pred + second_times(&s.second, wo) * f;
                total += w;
                out.push((w, s.lobe));
            }
        }
        if !(total > 0.0) || !(pred.norm() > 0.0) {
            out.truncate(start);
            return false;
        }
        let turn = Rotation::between(pred.normalized(), m.normalized());
        for (w, l) in &mut out[start..] {
            *w *= share / total;
            *l = Vmf::new(l.kappa, turn.apply(l.mu));
        }
        true
    }
}

/// Per column `c_i` of `M`, `(M Mᵀ + RIDGE · I)⁻¹ c_i` (`faer`'s Cholesky of the 9 × 9 matrix);
/// empty if it fails or is not finite.
fn gains_of(columns: &[[f64; STRIDE]]) -> Vec<[f64; STRIDE]> {
    let mut a = Mat::<f64>::zeros(STRIDE, STRIDE);
    for c in columns {
        for p in 0..STRIDE {
            for q in 0..STRIDE {
                a[(p, q)] += c[p] * c[q];
            }
        }
    }
    for p in 0..STRIDE {
        a[(p, p)] += RIDGE;
    }
    let Ok(llt) = a.llt(Side::Lower) else {
        return Vec::new();
    };
    let mut m = Mat::<f64>::zeros(STRIDE, columns.len());
    for (j, c) in columns.iter().enumerate() {
        for p in 0..STRIDE {
            m[(p, j)] = c[p];
        }
    }
    let x = llt.solve(m);
    let gains: Vec<[f64; STRIDE]> = (0..columns.len())
        .map(|j| std::array::from_fn(|p| x[(p, j)]))
        .collect();
    if gains.iter().flatten().all(|v| v.is_finite()) {
        gains
    } else {
        Vec::new()
    }
}

/// The sub-lobes of every curved cluster: at most `s` of them, by area-weighted k-means within
/// the cluster; and each facet's part, an index into its cluster's [`Shape::parts`]
/// ([`NO_PART`] for a facet of a cluster without sub-lobes).
pub(crate) fn cluster_shapes(
    normals: &[Vec3],
    areas: &[f64],
    assign: &[u16],
    planar: &[bool],
    s: usize,
) -> (Vec<Shape>, Vec<u16>) {
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); planar.len()];
    for (i, &k) in assign.iter().enumerate() {
        members[k as usize].push(i);
    }
    let split: Vec<(Shape, Vec<u16>)> = members
        .par_iter()
        .zip(planar)
        .map(|(idx, &flat)| {
            if flat || s < 2 || idx.is_empty() {
                return (Shape::new(Vec::new()), vec![NO_PART; idx.len()]);
            }
            let n: Vec<Vec3> = idx.iter().map(|&i| normals[i]).collect();
            let a: Vec<f64> = idx.iter().map(|&i| areas[i]).collect();
            let (sa, sc) = cluster_normals(&n, &a, s);
            // The k-means groups kept as parts (those with a resultant), numbered in order.
            let mut number = vec![NO_PART; sc.len()];
            let mut parts = Vec::new();
            for (k, slot) in number.iter_mut().enumerate() {
                let part = part_of(
                    n.iter()
                        .zip(&a)
                        .zip(&sa)
                        .filter(|(_, &j)| j as usize == k)
                        .map(|((nn, aa), _)| (*nn, *aa)),
                );
                if part.resultant.norm() > 0.0 {
                    *slot = parts.len() as u16;
                    parts.push(part);
                }
            }
            let of_facet = sa.iter().map(|&j| number[j as usize]).collect();
            (Shape::new(parts), of_facet)
        })
        .collect();
    let mut part = vec![NO_PART; normals.len()];
    for (idx, (_, of_facet)) in members.iter().zip(&split) {
        for (&i, &p) in idx.iter().zip(of_facet) {
            part[i] = p;
        }
    }
    (split.into_iter().map(|(sh, _)| sh).collect(), part)
}

/// The part of a facet whose cluster has no sub-lobes.
pub(crate) const NO_PART: u16 = u16::MAX;

/// The row of part `part` in a per-part table of its cluster (`[part · bands + band]`, one row
/// for a cluster without sub-lobes): [`NO_PART`] is row 0.
#[inline]
pub(crate) fn part_row(part: u16) -> usize {
    if part == NO_PART {
        0
    } else {
        part as usize
    }
}

/// The moments and vMF of a set of `(normal, area)`.
fn part_of(facets: impl Iterator<Item = (Vec3, f64)>) -> SubLobe {
    let mut o = SubLobe {
        resultant: Vec3::default(),
        second: [0.0; 6],
        lobe: Vmf::new(0.0, Vec3::Z),
    };
    let mut mass = 0.0;
    for (n, a) in facets {
        o.resultant = o.resultant + n * a;
        let m = moments(n);
        for q in 0..6 {
            o.second[q] += a * m[3 + q];
        }
        mass += a;
    }
    let len = o.resultant.norm();
    if mass > 0.0 && len > 0.0 {
        o.lobe = Vmf::new(
            kappa_from_resultant((len / mass).min(1.0)),
            o.resultant * (1.0 / len),
        );
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::dir_from_deg;

    /// A cluster of normals on a cone of half-angle 40° about the zenith, split into 16 parts
    /// (facets of equal area every 3° of polar angle and 10° of azimuth).
    fn cone() -> Shape {
        let mut normals = Vec::new();
        for t in (1..=40).step_by(3) {
            for p in (0..360).step_by(10) {
                normals.push(dir_from_deg(t as f64, p as f64));
            }
        }
        let areas = vec![1.0 / normals.len() as f64; normals.len()];
        let assign = vec![0u16; normals.len()];
        cluster_shapes(&normals, &areas, &assign, &[false], 16)
            .0
            .remove(0)
    }

    fn moments_of(parts: &[&SubLobe]) -> [f64; STRIDE] {
        let mut g = [0.0; STRIDE];
        for p in parts {
            g[0] += p.resultant.x;
            g[1] += p.resultant.y;
            g[2] += p.resultant.z;
            for k in 0..6 {
                g[3 + k] += p.second[k];
            }
        }
        g
    }

    /// Wholly visible, every part keeps its whole projected area: the fit changes nothing.
    #[test]
    fn a_wholly_visible_cluster_keeps_its_parts_weights() {
        let shape = cone();
        assert_eq!(shape.parts.len(), 16);
        let wo = dir_from_deg(30.0, 20.0);
        let all: Vec<&SubLobe> = shape.parts.iter().collect();
        let mut fraction = Vec::new();
        shape.visible(wo, &moments_of(&all), &mut fraction);
        for f in &fraction {
            assert!((f - 1.0).abs() < 1e-6, "{fraction:?}");
        }
    }

    /// A view that sees only the parts of a cluster tilted towards it (the side of a bump
    /// facing a grazing view): the fitted fractions stay in `[0, 1]`, their moments come much
    /// closer to the tabulated ones than one fraction for the whole cluster does (0.15 of its
    /// residual when this test was written), and the pushed sub-lobes carry the cluster's whole
    /// share.
    #[test]
    fn fitted_fractions_follow_the_tabulated_moments() {
        let shape = cone();
        let wo = dir_from_deg(60.0, 0.0);
        let seen: Vec<&SubLobe> = shape.parts.iter().filter(|p| p.resultant.x > 0.0).collect();
        let g = moments_of(&seen);
        let residual = |fraction: &[f64]| -> f64 {
            let mut r = g;
            for (p, f) in shape.parts.iter().zip(fraction) {
                let m = moments_of(&[p]);
                for k in 0..STRIDE {
                    r[k] -= f * m[k];
                }
            }
            r.iter().map(|x| x * x).sum::<f64>().sqrt()
        };
        let mut fraction = Vec::new();
        shape.visible(wo, &g, &mut fraction);
        assert!(
            fraction.iter().all(|f| (0.0..=1.0).contains(f)),
            "{fraction:?}"
        );
        let facing: f64 = shape
            .parts
            .iter()
            .map(|p| p.resultant.dot(wo).max(0.0))
            .sum();
        let t = (wo.x * g[0] + wo.y * g[1] + wo.z * g[2]) / facing;
        let uniform: Vec<f64> = shape
            .parts
            .iter()
            .map(|p| if p.resultant.dot(wo) > 0.0 { t } else { 0.0 })
            .collect();
        let (fit, one) = (residual(&fraction), residual(&uniform));
        assert!(fit < 0.25 * one, "fitted {fit}, one fraction {one}");
        let mut out = Vec::new();
        assert!(shape.push(wo, second_times(&g[3..], wo), &g, 0.7, &mut out));
        let total: f64 = out.iter().map(|l| l.0).sum();
        assert!((total - 0.7).abs() < 1e-9, "{total}");
    }
}
