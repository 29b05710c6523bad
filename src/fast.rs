//! The fast evaluator of `fbar`: a compact BVNDF (vMF lobes per direction pair, [`crate::bvndf`])
//! against a prefiltered material ([`crate::prefilter`]), Eq. 6: `fbar = Σ_j alpha_j F(wi, wo; kappa_j, mu_j)`.
//! The geometry side is any [`LobeSource`]: the full compact BVNDF, or its restriction to the
//! library's lights ([`crate::lightlobes`]). One evaluation costs one bilinear table read per cluster and one `F` read per lobe; no pass over
//! facets.

use crate::bvndf::LobeSource;
use crate::frame::DirPair;
use crate::prefilter::Prefiltered;
use crate::vmf::Vmf;

/// `fbar` at one pair, reusing `scratch` for the lobes.
#[inline]
pub fn fbar_one<G: LobeSource + ?Sized>(
    geo: &G,
    mat: &Prefiltered,
    p: &DirPair,
    scratch: &mut Vec<(f64, Vmf)>,
) -> f64 {
    geo.lobes(p.wi, p.wo, scratch);
    let mut s = 0.0;
    for (w, lobe) in scratch.iter() {
        s += w * mat.eval(p.wi, p.wo, lobe);
    }
    if s.is_finite() && s > 0.0 {
        s
    } else {
        0.0
    }
}

/// `fbar` at every pair.
pub fn fbar<G: LobeSource + ?Sized>(geo: &G, mat: &Prefiltered, pairs: &[DirPair]) -> Vec<f64> {
    let mut scratch = Vec::with_capacity(geo.clusters());
    pairs
        .iter()
        .map(|p| fbar_one(geo, mat, p, &mut scratch))
        .collect()
}
