//! The jointly visible fraction of single facets, by rays: what the fast evaluator's facet sum
//! for sharp glossy lobes ([`crate::bvndf::CompactBvndf::sharp_fbar`]) tests directly when few
//! facets meet a lobe.
//!
//! A lobe narrower than about 0.01 rad meets only a few facets of a rough surface at a pair
//! (13 per pair on average on a 128² fBm under Ward 0.0034), and `fbar` is then their sum: which
//! of those few facets the light reaches and the view sees decides it, and an average over the
//! facet's sub-lobe part and height band cannot. Each facet is tested at the centroids of an
//! `s × s` subdivision ([`crate::heightfield::Facet::stratified_points`]), from both ends of
//! the pair, the same test as the exact evaluator's shadow rays ([`Visibility::visible_dir`]).
//!
//! A broader lobe meets thousands of facets, too many to test at every pair; there the facet
//! sum takes a model's fraction per facet and the rays correct it at a sample
//! ([`FacetRays::visible_sum`]).

use crate::facetindex::Near;
use crate::frame::Vec3;
use crate::heightfield::Heightfield;
use crate::visibility::{Direction, Visibility};

/// The facets [`FacetRays::visible_sum`] tests at one pair: every facet a lobe meets when there
/// are no more (at up to twice as many points), else one point each of this many. The cost is
/// up to two rays per point (about 2 × 512 per pair: evaluating 490 pairs of a sharp GGX 0.03 lobe on a 64² bumps
/// map takes 116–134 ms instead of 36–42 ms); with 64, 128 and 256 samples a broad sharp lobe's
/// error went 5.6, 3.4 and 2.6 % against 1.4 % at 512 (docs/forward-model.md).
pub const DIRECT_POINTS: usize = 512;

/// The side `s` of the `s × s` points at which [`FacetRays::visible_sum`] tests one of `count`
/// facets (at most [`DIRECT_POINTS`]) whose term is `term` of the sum `total`: as large as an
/// even share of the budget allows, or as the facet's share `DIRECT_POINTS · term / total`
/// allows where that is larger; from 1 to 4.
fn side_for(count: usize, term: f64, total: f64) -> usize {
    let even = (DIRECT_POINTS / count.max(1)) as f64;
    let own = DIRECT_POINTS as f64 * term / total;
    (even.max(own).sqrt().floor() as usize).clamp(1, 4)
}

/// A point index in `0..16` scrambled from a facet and a sample number
/// ([`FacetRays::joint_one`]): deterministic, and uncorrelated with where the facet lies in the
/// period (a multiplicative hash).
fn pick(facet: u32, k: u32) -> usize {
    let h =
        (facet.wrapping_mul(0x9E37_79B1) ^ k.wrapping_mul(0x85EB_CA6B)).wrapping_mul(0xC2B2_AE35);
    (h >> 28) as usize
}

/// A heightfield prepared for facet visibility tests.
pub struct FacetRays<'a> {
    vis: Visibility<'a>,
}

impl FacetRays<'static> {
    /// Holding its heightfield (for a model that outlives the one it was built from).
    pub fn owned(hf: Heightfield) -> Self {
        FacetRays {
            vis: Visibility::owned(hf),
        }
    }
}

/// Both ends of a pair, prepared once for every facet tested at it.
pub struct Ends {
    wi: Direction,
    wo: Direction,
}

impl<'a> FacetRays<'a> {
    pub fn new(hf: &'a Heightfield) -> Self {
        FacetRays {
            vis: Visibility::new(hf),
        }
    }

    /// The pair `(wi, wo)` (both above the horizon) prepared for [`Self::joint`].
    pub fn ends(&self, wi: Vec3, wo: Vec3) -> Ends {
        Ends {
            wi: self.vis.direction(wi),
            wo: self.vis.direction(wo),
        }
    }

    /// The fraction of facet `facet`'s `side²` stratified points (one of its centroids with
    /// `side = 1`) seen from `wo` and lit from `wi`. `scratch` holds the points.
    pub fn joint(&self, facet: u32, side: usize, ends: &Ends, scratch: &mut Vec<Vec3>) -> f64 {
        scratch.clear();
        self.vis
            .heightfield()
            .facet(facet as usize)
            .stratified_points_into(side, scratch);
        let seen = scratch
            .iter()
            .filter(|p| self.seen_and_lit(p, ends))
            .count();
        seen as f64 / scratch.len().max(1) as f64
    }

    /// Whether one of facet `facet`'s 16 stratified points (`side = 4`), the one [`pick`] gives
    /// for `(facet, k)`, is seen from `wo` and lit from `wi`: 1 or 0. Where a facet is tested at
    /// one point only, a point spread over the facets in this way, rather than the centroid of
    /// each, keeps its answer a fraction of the facets' *area* on average (on a weave, whose
    /// facets repeat from period to period, the centroids are all seen or all hidden together:
    /// under Ward 0.014 5.1 % from the exact method up to 85°, docs/forward-model.md).
    pub fn joint_one(&self, facet: u32, k: u32, ends: &Ends, scratch: &mut Vec<Vec3>) -> f64 {
        scratch.clear();
        self.vis
            .heightfield()
            .facet(facet as usize)
            .stratified_points_into(4, scratch);
        let p = scratch[pick(facet, k) % scratch.len()];
        self.seen_and_lit(&p, ends) as u8 as f64
    }

    /// Whether point `p` is seen from the pair's `wo` and lit from its `wi` (the exact method's
    /// shadow test, from both ends).
    fn seen_and_lit(&self, p: &Vec3, ends: &Ends) -> bool {
        self.vis.visible_dir(p.x, p.y, p.z, &ends.wo)
            && self.vis.visible_dir(p.x, p.y, p.z, &ends.wi)
    }

    /// Facet `facet`'s jointly visible fraction as [`Self::visible_sum`] tests every facet:
    /// at its `side × side` points ([`Self::joint`]), or with `side = 1` at one point spread
    /// over the facets ([`Self::joint_one`]).
    pub fn tested(&self, facet: u32, side: usize, ends: &Ends, scratch: &mut Vec<Vec3>) -> f64 {
        match side {
            0 | 1 => self.joint_one(facet, 0, ends, scratch),
            _ => self.joint(facet, side, ends, scratch),
        }
    }

    /// `Σ_e t_e ρ_e` over index entries `near` (each with its term `t_e`) at a pair `ends`,
    /// `ρ_e` the jointly visible fraction of the entry's facets:
    ///
    /// * when the entries have at most [`DIRECT_POINTS`] facets, by rays: each facet at
    ///   `s × s` points, `s` as large as an even share of the budget allows or, for a facet
    ///   whose term is a larger share of the sum, as that share allows, at most 4; at one point
    ///   spread over the facets when `s = 1` ([`Self::tested`]). At most twice
    ///   [`DIRECT_POINTS`] points in all;
    /// * otherwise `model(e)`'s fraction, corrected by the rays at one point each
    ///   ([`Self::joint_one`]) of [`DIRECT_POINTS`] facets drawn in proportion to their terms
    ///   (systematic sampling in the entries' order, a facet of an entry by where the sample
    ///   falls in it): the difference estimator `Σ t ρ_model + (W / T) Σ_k (v_k − ρ_model,k)`,
    ///   `W = Σ t`, `T` samples. Its expectation is the rays' sum whatever the model; the better
    ///   the model, the less noise.
    ///
    /// The order of `near` is the order of the sum (deterministic).
    pub fn visible_sum(
        &self,
        near: &[(f64, Near)],
        ends: &Ends,
        mut model: impl FnMut(&Near) -> f64,
    ) -> f64 {
        let mut points = Vec::new();
        let count: usize = near.iter().map(|(_, e)| e.facets.len()).sum();
        if count == 0 {
            return 0.0;
        }
        let total: f64 = near.iter().map(|(t, _)| t).sum();
        if count <= DIRECT_POINTS {
            return near
                .iter()
                .map(|(t, e)| {
                    let side = side_for(count, t / e.facets.len() as f64, total);
                    let seen: f64 = e
                        .facets
                        .iter()
                        .map(|&f| self.tested(f, side, ends, &mut points))
                        .sum();
                    t * seen / e.facets.len() as f64
                })
                .sum();
        }
        let step = total / DIRECT_POINTS as f64;
        let (mut sum, mut diff) = (0.0, 0.0);
        let (mut before, mut k) = (0.0, 0usize);
        for (t, e) in near {
            let r = model(e);
            sum += t * r;
            // The samples `(k + 1/2) · step` that fall in this entry.
            let after = before + t;
            while k < DIRECT_POINTS && (k as f64 + 0.5) * step < after {
                let at = ((k as f64 + 0.5) * step - before) / t;
                let i = ((at * e.facets.len() as f64) as usize).min(e.facets.len() - 1);
                diff += self.joint_one(e.facets[i], k as u32, ends, &mut points) - r;
                k += 1;
            }
            before = after;
        }
        sum + step * diff
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::dir_from_deg;
    use crate::generators::parse_generator;

    /// Every point of a flat patch sees every direction; a facet in a V-groove's shadowed wall
    /// is dark from a grazing light across the groove and lit from one along it.
    #[test]
    fn flat_points_see_everything_and_groove_walls_shadow() {
        let flat = Heightfield::flat(8, 8);
        let rays = FacetRays::new(&flat);
        let ends = rays.ends(dir_from_deg(89.0, 10.0), dir_from_deg(85.0, 200.0));
        let mut scratch = Vec::new();
        for f in [0u32, 7, 127] {
            assert_eq!(rays.joint(f, 3, &ends, &mut scratch), 1.0);
            assert_eq!(scratch.len(), 9);
        }
        let hf = parse_generator("vgroove:n=16,period=16,depth=8")
            .unwrap()
            .build()
            .unwrap();
        let rays = FacetRays::owned(hf.clone());
        // A facet near the bottom of the groove facing -x (normal with n.x < 0).
        let f = (0..hf.width() * hf.height() * 2)
            .find(|&i| {
                let t = hf.facet(i);
                t.n.x < -0.3 && t.v.iter().all(|v| v.z < hf.min_max().0 + 2.0)
            })
            .unwrap() as u32;
        let wo = dir_from_deg(0.0, 0.0);
        // A light low from -x (beyond the wall's rim) is blocked by the groove's other wall;
        // from straight above it is lit.
        let low = rays.ends(dir_from_deg(80.0, 180.0), wo);
        let high = rays.ends(dir_from_deg(0.0, 0.0), wo);
        assert_eq!(rays.joint(f, 2, &low, &mut scratch), 0.0);
        assert_eq!(rays.joint(f, 2, &high, &mut scratch), 1.0);
    }

    /// Few facets: the sum is the rays' own, whatever the model. Many: the sample's correction
    /// brings even a constant model (every facet half visible) near the rays' sum over every
    /// facet's 4 × 4 points.
    #[test]
    fn the_sum_is_the_rays_and_a_sample_corrects_any_model() {
        use crate::facetindex::FacetIndex;
        let hf = parse_generator("bumps:n=64,count=8,radius=10,height=6,seed=2")
            .unwrap()
            .build()
            .unwrap();
        let facets = hf.facets();
        let normals: Vec<Vec3> = facets.iter().map(|f| f.n).collect();
        let areas: Vec<f64> = facets.iter().map(|f| f.area / hf.base_area()).collect();
        let zeros = vec![0u16; facets.len()];
        let ix = FacetIndex::build(
            &normals,
            &areas,
            &zeros,
            &zeros,
            &vec![0; facets.len()],
            |_| true,
        );
        let rays = FacetRays::new(&hf);
        let mut scratch = Vec::new();
        let (mut corrected, mut constant, mut checked) = (0.0, 0.0, 0);
        for (ti, pi, to, po) in [
            (30.0, 0.0, 40.0, 170.0),
            (60.0, 45.0, 70.0, 200.0),
            (75.0, 300.0, 20.0, 90.0),
            (80.0, 10.0, 82.0, 180.0),
            (70.0, 90.0, 84.0, 300.0),
        ] {
            let (wi, wo) = (dir_from_deg(ti, pi), dir_from_deg(to, po));
            let h = (wi + wo).normalized();
            let ends = rays.ends(wi, wo);
            for radius in [0.02, 0.3, 0.6] {
                let mut near = Vec::new();
                ix.near(h, radius, |e| {
                    let t = e.area * e.n.dot(wi).max(0.0) * e.n.dot(wo).max(0.0);
                    if t > 0.0 {
                        near.push((t, e));
                    }
                });
                let count: usize = near.iter().map(|(_, e)| e.facets.len()).sum();
                let got = rays.visible_sum(&near, &ends, |_| 0.5);
                let total: f64 = near.iter().map(|(t, _)| t).sum();
                // Every facet tested as `visible_sum` tests it, at the side `side(term)`.
                let mut every = |side: &dyn Fn(f64) -> usize| -> f64 {
                    near.iter()
                        .map(|(t, e)| {
                            let s = side(t / e.facets.len() as f64);
                            t * e
                                .facets
                                .iter()
                                .map(|&f| rays.tested(f, s, &ends, &mut scratch))
                                .sum::<f64>()
                                / e.facets.len() as f64
                        })
                        .sum()
                };
                if count <= DIRECT_POINTS {
                    assert_eq!(got, every(&|term| side_for(count, term, total)));
                    continue;
                }
                // Every facet's seen and lit area at 4 × 4 points.
                let rays_all = every(&|_| 4);
                let half: f64 = near.iter().map(|(t, _)| 0.5 * t).sum();
                corrected += ((got - rays_all) / rays_all).powi(2);
                constant += ((half - rays_all) / rays_all).powi(2);
                checked += 1;
            }
        }
        assert!(checked >= 2, "{checked} pairs with many facets");
        let (corrected, constant) = (
            (corrected / checked as f64).sqrt(),
            (constant / checked as f64).sqrt(),
        );
        eprintln!("{checked} pairs with many facets: corrected {corrected:.4}, constant model {constant:.4}");
        // 512 binary samples at p = 1/2 leave sqrt(1/4 / 512) / (1/2) = 4.4 % of noise at most
        // (1.03 % here over 6 pairs, against 39.7 % for the constant model uncorrected).
        assert!(
            corrected < 0.045 && corrected < 0.2 * constant,
            "{corrected} vs {constant}"
        );
    }
}
