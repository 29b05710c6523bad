//! The fast evaluator of `fbar`: a compact BVNDF (vMF lobes per direction pair, [`crate::bvndf`])
//! against a prefiltered material ([`crate::prefilter`]), Eq. 6: `fbar = Σ_j alpha_j F(wi, wo; kappa_j, mu_j)`.
//! The geometry side is any [`LobeSource`]: the full compact BVNDF, or its restriction to the
//! library's lights ([`crate::lightlobes`]). One evaluation costs one bilinear table read per cluster and one `F` read per lobe; no pass over
//! facets.

use crate::bvndf::{CompactBvndf, LobeSource};
use crate::facetrays::FacetRays;
use crate::frame::DirPair;
use crate::prefilter::{prepare, PrefilterConfig, Prefiltered, PreparedLobe};
use crate::vmf::Vmf;
use rayon::prelude::*;

/// `fbar` at one pair, reusing `scratch` for the lobes.
#[inline]
pub fn fbar_one<G: LobeSource + ?Sized>(
    geo: &G,
    mat: &Prefiltered,
    p: &DirPair,
    scratch: &mut Vec<(f64, Vmf)>,
) -> f64 {
    geo.lobes(p.wi, p.wo, mat.resolves_shape(), scratch);
    clean(mat.eval_sum(p.wi, p.wo, scratch))
}

/// A value of `fbar` as the evaluators return it: non-finite or negative sums become 0.
#[inline]
fn clean(s: f64) -> f64 {
    if s.is_finite() && s > 0.0 {
        s
    } else {
        0.0
    }
}

/// Glossy lobes narrower than this (radians) are summed over facets by [`fbar_with_facets`]
/// rather than read from the prefiltered table: below it one vMF per cluster, or its sub-lobes,
/// smooth away the spikes a triangulated curved surface gives a sharp lobe. At GGX 0.03 and
/// 0.05 the facet sum was the more accurate on fBm, dimples and weaves (equal on bumps), at 0.1
/// the table (docs/forward-model.md).
pub const FACET_WIDTH: f64 = 0.06;

/// `fbar` at every pair for a material prefiltered with [`Prefiltered::build_split`]: the
/// table's part from the lobes, plus the sharp lobes summed over the curved clusters' facets
/// ([`CompactBvndf::sharp_fbar`]). For any other table, the same as [`fbar`]. The pairs are
/// shared among the threads in blocks of [`PAIR_BLOCK`]; each pair's value is computed alone,
/// so the result does not depend on the number of threads.
pub fn fbar_with_facets(geo: &CompactBvndf, mat: &Prefiltered, pairs: &[DirPair]) -> Vec<f64> {
    // The facets' rays are prepared only for a material with sharp lobes.
    let rays = mat.sharp().map(|_| geo.facet_rays());
    pairs
        .par_chunks(PAIR_BLOCK)
        .flat_map_iter(|block| {
            let mut scratch = Vec::with_capacity(geo.clusters());
            block
                .iter()
                .map(|p| fbar_one_with_facets(geo, mat, rays.as_ref(), p, &mut scratch))
                .collect::<Vec<_>>()
        })
        .collect()
}

/// Pairs per parallel task of [`fbar_with_facets`]: a pair with sub-lobes costs tens of
/// microseconds, so a block is long enough to outweigh a task's overhead.
pub const PAIR_BLOCK: usize = 32;

/// [`fbar_with_facets`] at one pair, reusing `scratch` for the lobes. `rays`: the geometry's
/// facets prepared for rays ([`CompactBvndf::facet_rays`]) once for many pairs, read when `mat`
/// has sharp lobes; `None` prepares them at this call (a pass over the heightfield, about
/// 0.1 ms for 128²).
pub fn fbar_one_with_facets(
    geo: &CompactBvndf,
    mat: &Prefiltered,
    rays: Option<&FacetRays>,
    p: &DirPair,
    scratch: &mut Vec<(f64, Vmf)>,
) -> f64 {
    let v = fbar_one(geo, mat, p, scratch);
    let Some((sharp, radius)) = mat.sharp() else {
        return v;
    };
    let here;
    let rays = match rays {
        Some(r) => r,
        None => {
            here = geo.facet_rays();
            &here
        }
    };
    clean(v + geo.sharp_fbar(p.wi, p.wo, sharp, radius, rays))
}

/// `fbar` at every pair (a table built with [`Prefiltered::build`]; for one built with
/// [`Prefiltered::build_split`], [`fbar_with_facets`]).
pub fn fbar<G: LobeSource + ?Sized>(geo: &G, mat: &Prefiltered, pairs: &[DirPair]) -> Vec<f64> {
    debug_assert!(
        mat.sharp().is_none(),
        "a split table needs fbar_with_facets"
    );
    fbar_by(mat, pairs, None, geo.clusters(), |_, p, out| {
        geo.lobes(p.wi, p.wo, mat.resolves_shape(), out)
    })
}

/// Call `f` with every index below `n`, in `order` when given (a permutation), else ascending.
fn visit(n: usize, order: Option<&[usize]>, f: impl FnMut(usize)) {
    match order {
        Some(order) => order.iter().copied().for_each(f),
        None => (0..n).for_each(f),
    }
}

/// `fbar` at every pair, with pair `i`'s lobes (about `clusters` of them) put in `out` by
/// `lobes(i, pair, out)`. The pairs are visited in `order` (a permutation of their indices;
/// `None`: as given), which changes no value, only the order in which `lobes` reads its data.
pub fn fbar_by(
    mat: &Prefiltered,
    pairs: &[DirPair],
    order: Option<&[usize]>,
    clusters: usize,
    mut lobes: impl FnMut(usize, &DirPair, &mut Vec<(f64, Vmf)>),
) -> Vec<f64> {
    let mut scratch = Vec::with_capacity(clusters);
    let mut out = vec![0.0; pairs.len()];
    visit(pairs.len(), order, |i| {
        let p = &pairs[i];
        lobes(i, p, &mut scratch);
        out[i] = clean(mat.eval_sum(p.wi, p.wo, &scratch));
    });
    out
}

/// The lobes of one geometry at a fixed set of pairs, assembled once: evaluating many materials
/// on the same geometry (the material solver) then costs only the `F` reads. One vMF per
/// cluster (no sub-lobes: they depend on the material), as in the libraries.
pub struct FixedLobes {
    pairs: Vec<DirPair>,
    lobes: Vec<Vec<(f64, Vmf)>>,
    /// The lobes with their table coordinates, for the settings of the first table evaluated.
    prepared: std::sync::OnceLock<(PrefilterConfig, Vec<Vec<PreparedLobe>>)>,
}

impl FixedLobes {
    pub fn new<G: LobeSource + ?Sized>(geo: &G, pairs: &[DirPair]) -> Self {
        Self::by(pairs, None, geo.clusters(), |_, p, l| {
            geo.lobes(p.wi, p.wo, false, l)
        })
    }

    /// The lobes at `pairs`, pair `i`'s (about `clusters` of them) put in `out` by
    /// `lobes(i, pair, out)`, the pairs visited in `order` (as [`fbar_by`]).
    pub fn by(
        pairs: &[DirPair],
        order: Option<&[usize]>,
        clusters: usize,
        mut lobes: impl FnMut(usize, &DirPair, &mut Vec<(f64, Vmf)>),
    ) -> Self {
        let mut all = vec![Vec::new(); pairs.len()];
        visit(pairs.len(), order, |i| {
            let mut l = Vec::with_capacity(clusters);
            lobes(i, &pairs[i], &mut l);
            all[i] = l;
        });
        let lobes = all;
        FixedLobes {
            pairs: pairs.to_vec(),
            lobes,
            prepared: std::sync::OnceLock::new(),
        }
    }

    /// The same lobes at every `step`-th pair from the first (a coarse pass's pairs, as
    /// [`crate::sampling::Samples::every`] picks them), with their table coordinates when
    /// they were found already.
    pub fn every(&self, step: usize) -> FixedLobes {
        let step = step.max(1);
        let prepared = std::sync::OnceLock::new();
        if let Some((cfg, p)) = self.prepared.get() {
            let _ = prepared.set((cfg.clone(), p.iter().step_by(step).cloned().collect()));
        }
        FixedLobes {
            pairs: self.pairs.iter().step_by(step).copied().collect(),
            lobes: self.lobes.iter().step_by(step).cloned().collect(),
            prepared,
        }
    }

    /// `fbar` of `mat` at every pair; equal to [`fbar`] on the geometry. The lobes' table
    /// coordinates are found on the first call and reused by every later table of the same
    /// settings.
    pub fn fbar(&self, mat: &Prefiltered) -> Vec<f64> {
        let (cfg, prepared) = self.prepared.get_or_init(|| {
            let prep = self
                .pairs
                .iter()
                .zip(&self.lobes)
                .map(|(p, l)| prepare(&mat.cfg, p.wi, p.wo, l))
                .collect();
            (mat.cfg.clone(), prep)
        });
        if *cfg == mat.cfg {
            self.pairs
                .iter()
                .zip(prepared)
                .map(|(p, l)| clean(mat.eval_prepared(p.wi, p.wo, l)))
                .collect()
        } else {
            self.pairs
                .iter()
                .zip(&self.lobes)
                .map(|(p, l)| clean(mat.eval_sum(p.wi, p.wo, l)))
                .collect()
        }
    }
}
