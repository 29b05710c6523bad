//! The exact evaluator of `fbar`: the facet sum of the design notes with joint visibility.
//!
//! `fbar(wi, wo) = Σ_t A_t (n_t·wo)+ (n_t·wi)+ f_r(n_t, wi, wo) V_t(wi, wo) / a_v(wo)`, where the
//! joint visibility `V_t` of facet `t` is the fraction of its area seen from both directions,
//! integrated with `s²` stratified points per facet (the centroids of its `s × s` subdivision),
//! each tested with the exact ray march of [`crate::visibility`]. `a_v(wo)` is the visible
//! projected area found by the same points, so a flat patch is exact and the identity
//! `a_v(wo) = A_base cos(theta_o)` checks the visibility code. This is the reference every fast
//! path is measured against and the re-ranking step of the solvers.

use crate::frame::{DirPair, Vec3};
use crate::heightfield::{Facet, Heightfield};
use crate::material::Material;
use crate::visibility::Visibility;
use rayon::prelude::*;
use std::collections::HashMap;

/// Pairs are evaluated in chunks so that the cached visibility masks stay small.
const PAIR_CHUNK: usize = 512;

/// A stratified surface point with the facet it lies on.
#[derive(Debug, Clone, Copy)]
pub struct SurfacePoint {
    pub p: Vec3,
    pub facet: u32,
}

/// Surface points of a heightfield: `s²` per facet, contiguous per facet.
pub fn surface_points(facets: &[Facet], s: usize) -> Vec<SurfacePoint> {
    let s = s.max(1);
    let inv = 1.0 / s as f64;
    let mut out = Vec::with_capacity(facets.len() * s * s);
    for (t, f) in facets.iter().enumerate() {
        let [a, b, c] = f.v;
        let (e1, e2) = (b - a, c - a);
        let mut push = |u: f64, v: f64| {
            out.push(SurfacePoint {
                p: a + e1 * u + e2 * v,
                facet: t as u32,
            })
        };
        for i in 0..s {
            for j in 0..s - i {
                push((i as f64 + 1.0 / 3.0) * inv, (j as f64 + 1.0 / 3.0) * inv);
                if i + j + 1 < s {
                    push((i as f64 + 2.0 / 3.0) * inv, (j as f64 + 2.0 / 3.0) * inv);
                }
            }
        }
    }
    out
}

/// The exact evaluator for one heightfield.
pub struct ExactEvaluator<'a> {
    vis: Visibility<'a>,
    facets: Vec<Facet>,
    points: Vec<SurfacePoint>,
    /// Points per facet (`s²`).
    per_facet: usize,
}

/// A bit mask over surface points.
type Mask = Vec<u64>;

impl<'a> ExactEvaluator<'a> {
    /// `s` points per facet side (`s²` per facet); 2 is the default reference quality.
    pub fn new(hf: &'a Heightfield, s: usize) -> Self {
        let facets = hf.facets();
        let points = surface_points(&facets, s);
        ExactEvaluator {
            vis: Visibility::new(hf),
            facets,
            points,
            per_facet: s.max(1) * s.max(1),
        }
    }

    pub fn facets(&self) -> &[Facet] {
        &self.facets
    }

    /// Which surface points see `w` (false for back-facing facets).
    pub fn mask(&self, w: Vec3) -> Mask {
        let n = self.points.len();
        let mut mask = vec![0u64; n.div_ceil(64)];
        mask.par_chunks_mut(16).enumerate().for_each(|(ci, words)| {
            for (wi, word) in words.iter_mut().enumerate() {
                let base = (ci * 16 + wi) * 64;
                let mut bits = 0u64;
                for k in 0..64 {
                    let idx = base + k;
                    if idx >= n {
                        break;
                    }
                    let sp = self.points[idx];
                    if self.facets[sp.facet as usize].n.dot(w) <= 0.0 {
                        continue;
                    }
                    if self.vis.visible(sp.p.x, sp.p.y, sp.p.z, w) {
                        bits |= 1 << k;
                    }
                }
                *word = bits;
            }
        });
        mask
    }

    /// Visible projected area `a_v(w) = Σ A (n·w)+ V(w)` in grid units², from the surface points.
    pub fn visible_projected_area(&self, w: Vec3) -> f64 {
        let m = self.mask(w);
        self.projected_area_of(&m, w)
    }

    fn projected_area_of(&self, m: &Mask, w: Vec3) -> f64 {
        let mut total = 0.0;
        for (t, f) in self.facets.iter().enumerate() {
            let c = self.count(m, None, t);
            if c > 0 {
                total += f.area * f.n.dot(w) * c as f64;
            }
        }
        total / self.per_facet as f64
    }

    /// Number of points of facet `t` set in `a` (and in `b`, if given).
    #[inline]
    fn count(&self, a: &Mask, b: Option<&Mask>, t: usize) -> u32 {
        let lo = t * self.per_facet;
        let hi = lo + self.per_facet;
        let mut c = 0;
        let mut i = lo;
        while i < hi {
            let word = i / 64;
            let bit = i % 64;
            let take = (64 - bit).min(hi - i);
            let sel = if take == 64 {
                u64::MAX
            } else {
                ((1u64 << take) - 1) << bit
            };
            let mut v = a[word] & sel;
            if let Some(b) = b {
                v &= b[word];
            }
            c += v.count_ones();
            i += take;
        }
        c
    }

    /// `fbar` (cosine of the light direction included) at every pair. Pairs with a direction at or
    /// below the horizon give 0.
    pub fn fbar(&self, mat: &Material, pairs: &[DirPair]) -> Vec<f64> {
        let mut out = Vec::with_capacity(pairs.len());
        for chunk in pairs.chunks(PAIR_CHUNK) {
            // Distinct directions of the chunk, masks computed once each.
            let mut dirs: Vec<Vec3> = Vec::new();
            let mut index: HashMap<[u64; 3], usize> = HashMap::new();
            let mut idx_of = |w: Vec3, dirs: &mut Vec<Vec3>| {
                let key = [w.x.to_bits(), w.y.to_bits(), w.z.to_bits()];
                *index.entry(key).or_insert_with(|| {
                    dirs.push(w);
                    dirs.len() - 1
                })
            };
            let ids: Vec<(usize, usize)> = chunk
                .iter()
                .map(|p| (idx_of(p.wi, &mut dirs), idx_of(p.wo, &mut dirs)))
                .collect();
            let masks: Vec<Mask> = dirs
                .iter()
                .map(|&w| if w.z > 0.0 { self.mask(w) } else { Vec::new() })
                .collect();
            let av: Vec<f64> = dirs
                .iter()
                .zip(&masks)
                .map(|(&w, m)| {
                    if w.z > 0.0 {
                        self.projected_area_of(m, w)
                    } else {
                        0.0
                    }
                })
                .collect();
            let vals: Vec<f64> = chunk
                .par_iter()
                .zip(ids.par_iter())
                .map(|(pair, &(ii, io))| {
                    if pair.wi.z <= 0.0 || pair.wo.z <= 0.0 || av[io] <= 0.0 {
                        return 0.0;
                    }
                    let (mi, mo) = (&masks[ii], &masks[io]);
                    let mut sum = 0.0;
                    for (t, f) in self.facets.iter().enumerate() {
                        let ci = f.n.dot(pair.wi);
                        let co = f.n.dot(pair.wo);
                        if ci <= 0.0 || co <= 0.0 {
                            continue;
                        }
                        let c = self.count(mi, Some(mo), t);
                        if c == 0 {
                            continue;
                        }
                        sum += f.area * c as f64 * co * ci * mat.eval(f.n, pair.wi, pair.wo);
                    }
                    let v = sum / self.per_facet as f64 / av[io];
                    if v.is_finite() {
                        v
                    } else {
                        0.0
                    }
                })
                .collect();
            out.extend(vals);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::dir_from_deg;
    use crate::material::parse_material;

    #[test]
    fn point_counts_and_weights() {
        let hf = Heightfield::flat(3, 3);
        let f = hf.facets();
        for s in 1..5 {
            let pts = surface_points(&f, s);
            assert_eq!(pts.len(), f.len() * s * s);
            // every point lies inside its facet's xy footprint
            for sp in &pts {
                let fa = &f[sp.facet as usize];
                let (mnx, mxx) =
                    fa.v.iter()
                        .fold((9.0f64, -9.0f64), |(a, b), v| (a.min(v.x), b.max(v.x)));
                assert!(sp.p.x > mnx && sp.p.x < mxx);
            }
        }
    }

    #[test]
    fn flat_patch_is_brdf_times_cosine() {
        let hf = Heightfield::flat(4, 4);
        let ev = ExactEvaluator::new(&hf, 2);
        let m = parse_material("ggx:alpha=0.3+lambert:albedo=0.2").unwrap();
        let pairs = [
            DirPair {
                wi: dir_from_deg(30.0, 10.0),
                wo: dir_from_deg(60.0, 200.0),
            },
            DirPair {
                wi: dir_from_deg(89.9, 0.0),
                wo: dir_from_deg(89.9, 180.0),
            },
        ];
        let got = ev.fbar(&m, &pairs);
        for (p, g) in pairs.iter().zip(got) {
            let want = m.eval(Vec3::Z, p.wi, p.wo) * p.wi.z;
            assert!((g / want - 1.0).abs() < 1e-9, "{g} {want}");
        }
    }
}
