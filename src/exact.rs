//! The exact evaluator of `fbar`: the facet sum of the design notes with joint visibility.
//!
//! `fbar(wi, wo) = Σ_t A_t (n_t·wo)+ (n_t·wi)+ f_r(n_t, wi, wo) V_t(wi, wo) / a_v(wo)`, where the
//! joint visibility `V_t` of facet `t` is the fraction of its area seen from both directions.
//!
//! The sum is integrated in the view's projection, as a renderer would: parallel rays arrive from
//! `wo` on a regular `s × s` grid per cell of the base period (in the oblique projection along
//! `wo`, where every ray carries the same projected area `A_base cos(theta_o) / N`); each ray's
//! first hit ([`Visibility::first_hit`]) is the point it sees, and that point is lit if the exact
//! march towards `wi` ([`Visibility::visible`]) is clear. Then `A_t (n_t·wo)+ V_t(wo) / a_v(wo)` is
//! the share of rays that hit facet `t`, so `a_v(wo) = A_base cos(theta_o)` holds by construction,
//! and the thin visible slivers of walls at grazing view angles get rays in proportion to their
//! projected area, which a sampling of the surface itself would miss. This is the reference every
//! fast path is measured against and the re-ranking step of the solvers.
//!
//! [`ExactEvaluator::visible_projected_area`] checks the two visibility codes against each other
//! on that identity: every first hit must also pass the shadow march towards the viewer.

use crate::frame::{DirPair, Vec3};
use crate::heightfield::{Facet, Heightfield};
use crate::material::Material;
use crate::visibility::Visibility;
use rayon::prelude::*;
use std::collections::HashMap;

/// The exact evaluator for one heightfield.
pub struct ExactEvaluator<'a> {
    vis: Visibility<'a>,
    facets: Vec<Facet>,
    /// View rays per cell side.
    s: usize,
}

impl<'a> ExactEvaluator<'a> {
    /// `s` view rays per cell side (`s²` per cell of the base period); 2 is the default.
    pub fn new(hf: &'a Heightfield, s: usize) -> Self {
        ExactEvaluator {
            vis: Visibility::new(hf),
            facets: hf.facets(),
            s: s.max(1),
        }
    }

    /// Number of view rays per direction.
    pub fn rays(&self) -> usize {
        let hf = self.vis.heightfield();
        hf.width() * hf.height() * self.s * self.s
    }

    /// First hits of the view rays arriving from `wo`, as `(facet, point)` sorted by facet.
    pub fn view_hits(&self, wo: Vec3) -> Vec<(u32, Vec3)> {
        let hf = self.vis.heightfield();
        let (nx, ny) = (hf.width() * self.s, hf.height() * self.s);
        let inv = 1.0 / self.s as f64;
        // One ray per sub-cell of an `s × s` split of every cell (stratified), placed inside its
        // sub-cell by a quasi-random offset that varies with the row (for u) and the column (for
        // v). A plain regular grid would sample a straight shadow edge of grid-aligned geometry
        // at the same place in every row, so its error would not average out.
        let jitter = |k: usize, g: f64| (0.5 + k as f64 * g).fract();
        let dir = self.vis.direction(wo);
        let dir = &dir;
        let mut hits: Vec<(u32, Vec3)> = (0..ny)
            .into_par_iter()
            .flat_map_iter(|j| {
                (0..nx).map(move |i| {
                    let (p, f) = self.vis.first_hit_dir(
                        (i as f64 + jitter(j, 0.618_033_988_749_895)) * inv,
                        (j as f64 + jitter(i, 0.414_213_562_373_095)) * inv,
                        dir,
                    );
                    (f as u32, p)
                })
            })
            .collect();
        hits.sort_by_key(|h| h.0);
        hits
    }

    /// `Σ_t f_r(n_t) (n_t·wi)` over the hits lit from `wi`, divided by the ray count, for every
    /// material at once (the shadow marches are shared).
    fn shade(&self, mats: &[&Material], hits: &[(u32, Vec3)], wi: Vec3, wo: Vec3) -> Vec<f64> {
        let mut sum = vec![0.0; mats.len()];
        let dir = self.vis.direction(wi);
        let mut k = 0;
        while k < hits.len() {
            let t = hits[k].0;
            let mut end = k;
            while end < hits.len() && hits[end].0 == t {
                end += 1;
            }
            let f = &self.facets[t as usize];
            let ci = f.n.dot(wi);
            if ci > 0.0 {
                let lit = hits[k..end]
                    .iter()
                    .filter(|(_, p)| self.vis.visible_dir(p.x, p.y, p.z, &dir))
                    .count();
                if lit > 0 {
                    for (s, m) in sum.iter_mut().zip(mats) {
                        *s += lit as f64 * ci * m.eval(f.n, wi, wo);
                    }
                }
            }
            k = end;
        }
        let inv = 1.0 / hits.len().max(1) as f64;
        sum.into_iter().map(|s| s * inv).collect()
    }

    pub fn facets(&self) -> &[Facet] {
        &self.facets
    }

    /// Visible projected area `a_v(w)` in grid units² as the *shadow test* sees it: the share of
    /// the view rays from `w` whose first hit also passes the shadow march towards `w`, times
    /// `A_base cos(theta)`. The first-hit cast and the shadow march are independent codes over the
    /// same surface; they agree exactly when both are right, so this equals `A_base cos(theta)`
    /// (the identity of the design notes) unless one of them has a bug.
    pub fn visible_projected_area(&self, w: Vec3) -> f64 {
        if w.z <= 0.0 {
            return 0.0;
        }
        let hits = self.view_hits(w);
        let dir = self.vis.direction(w);
        let seen = hits
            .par_iter()
            .filter(|(_, p)| self.vis.visible_dir(p.x, p.y, p.z, &dir))
            .count();
        let hf = self.vis.heightfield();
        hf.base_area() * w.z * seen as f64 / hits.len().max(1) as f64
    }

    /// `fbar` (cosine of the light direction included) at every pair; 0 for a direction at or
    /// below the horizon. The integral is estimated from both ends — rays from `wo` shaded
    /// towards `wi`, and rays from `wi` shaded towards `wo` (an estimate of `fbar(wo, wi)`, turned
    /// into one of `fbar(wi, wo)` by reciprocity, `· cos(theta_i) / cos(theta_o)`) — and the two
    /// are averaged: half the variance where few rays see a lit area (both directions grazing),
    /// and a result reciprocal by construction. [`Self::fbar_one_sided`] gives either estimate.
    pub fn fbar(&self, mat: &Material, pairs: &[DirPair]) -> Vec<f64> {
        self.fbar_many(&[mat], pairs).pop().unwrap_or_default()
    }

    /// [`Self::fbar`] for several materials on the same rays and shadow marches: `[material][pair]`.
    pub fn fbar_many(&self, mats: &[&Material], pairs: &[DirPair]) -> Vec<Vec<f64>> {
        let a = self.fbar_one_sided_many(mats, pairs);
        let swapped: Vec<DirPair> = pairs
            .iter()
            .map(|p| DirPair { wi: p.wo, wo: p.wi })
            .collect();
        let b = self.fbar_one_sided_many(mats, &swapped);
        a.iter()
            .zip(&b)
            .map(|(a, b)| {
                pairs
                    .iter()
                    .zip(a.iter().zip(b))
                    .map(|(p, (x, y))| {
                        if p.wi.z <= 0.0 || p.wo.z <= 0.0 {
                            return 0.0;
                        }
                        let v = 0.5 * (x + y * p.wi.z / p.wo.z);
                        if v.is_finite() {
                            v
                        } else {
                            0.0
                        }
                    })
                    .collect()
            })
            .collect()
    }

    /// The one-sided estimate of `fbar`: rays from `wo` only, shaded towards `wi`. Pairs sharing
    /// a view direction share its rays.
    pub fn fbar_one_sided(&self, mat: &Material, pairs: &[DirPair]) -> Vec<f64> {
        self.fbar_one_sided_many(&[mat], pairs)
            .pop()
            .unwrap_or_default()
    }

    /// [`Self::fbar_one_sided`] for several materials: `[material][pair]`.
    pub fn fbar_one_sided_many(&self, mats: &[&Material], pairs: &[DirPair]) -> Vec<Vec<f64>> {
        // Group the pairs by view direction.
        let mut groups: HashMap<[u64; 3], Vec<usize>> = HashMap::new();
        let mut order: Vec<[u64; 3]> = Vec::new();
        for (k, p) in pairs.iter().enumerate() {
            let key = [p.wo.x.to_bits(), p.wo.y.to_bits(), p.wo.z.to_bits()];
            groups
                .entry(key)
                .or_insert_with(|| {
                    order.push(key);
                    Vec::new()
                })
                .push(k);
        }
        let results: Vec<Vec<(usize, Vec<f64>)>> = order
            .par_iter()
            .map(|key| {
                let idx = &groups[key];
                let wo = pairs[idx[0]].wo;
                if wo.z <= 0.0 {
                    return idx.iter().map(|&k| (k, vec![0.0; mats.len()])).collect();
                }
                let hits = self.view_hits(wo);
                idx.iter()
                    .map(|&k| {
                        let wi = pairs[k].wi;
                        let v = if wi.z > 0.0 {
                            self.shade(mats, &hits, wi, wo)
                        } else {
                            vec![0.0; mats.len()]
                        };
                        (
                            k,
                            v.into_iter()
                                .map(|x| if x.is_finite() { x } else { 0.0 })
                                .collect(),
                        )
                    })
                    .collect()
            })
            .collect();
        let mut out = vec![vec![0.0; pairs.len()]; mats.len()];
        for (k, v) in results.into_iter().flatten() {
            for (m, x) in v.into_iter().enumerate() {
                out[m][k] = x;
            }
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
