//! Minimum feature size: the narrowest valley and the narrowest ridge of a detail.
//!
//! Definition. With a tolerance `t` (a height), the **valley width** is the diameter of the
//! largest flat disc that can be lowered into every valley without the closing by that disc
//! raising the surface anywhere by more than `t`; equivalently, valleys are measured across at
//! height `t` above their floor (a groove with a flat floor measures its floor width plus the
//! part of its walls within `t`; a V groove of half-angle `a` measures `2 t tan a`). The
//! **ridge width** is the same for the opening (ridges measured `t` below their crest). The
//! minimum feature size is the smaller of the two. Only features up to half the period are
//! searched (disc radius up to a quarter of the period): a surface with no valley (ridge)
//! narrower than that reports none for it.
//!
//! Discretisation. Discs are digital discs of integer radius `m` samples (offsets with
//! `dx² + dy² <= m²`); the closing is monotone in `m`, so the first `m*` whose closing changes the
//! surface by more than `t` is found by bisection. A disc of radius `m* − 1` (extent `2m* − 2`
//! samples) still fits and one of radius `m*` (extent `2m*`) does not; the width reported is the
//! midpoint, `2m* − 1` samples, to within one sample. The narrower of the two, when narrow, is
//! measured again on the triangulated surface sampled finer (as far as [`MAX_SIDE`] allows): 4×
//! for `m* < 4` (widths up to 7 samples, resolution 1/4 sample), 2× for `m* <= 8` (resolution
//! 1/2 sample, under 7 % of such widths).
//!
//! Widths are computed in grid units (scale-free, with `t` a fraction of the relief) and scale
//! with the patch size: [`FeatureWidths::at_patch`] gives millimetres.

use super::morph::{flat_close_cells, flat_open_cells, Grid};
use crate::heightfield::Heightfield;

/// Longest side of the refined grid used for narrow features.
pub const MAX_SIDE: usize = 512;

/// Narrowest valley and ridge in grid units of the heightfield.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct FeatureWidths {
    pub valley_cells: Option<f64>,
    pub ridge_cells: Option<f64>,
    /// Uncertainty of each width (grid units).
    pub valley_resolution_cells: f64,
    pub ridge_resolution_cells: f64,
    /// The height tolerance `t` (grid units).
    pub tol_cells: f64,
}

/// The same at a physical patch size, in millimetres.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct FeatureReport {
    pub valley_mm: Option<f64>,
    pub ridge_mm: Option<f64>,
    /// The smaller of the two (none when the surface has neither).
    pub min_feature_mm: Option<f64>,
    /// Uncertainty of `min_feature_mm`.
    pub resolution_mm: f64,
    pub tol_mm: f64,
}

impl FeatureWidths {
    /// Widths at patch size `patch_mm` for a heightfield `w` samples wide.
    pub fn at_patch(&self, w: usize, patch_mm: f64) -> FeatureReport {
        let c = patch_mm / w as f64;
        let valley_mm = self.valley_cells.map(|v| v * c);
        let ridge_mm = self.ridge_cells.map(|v| v * c);
        let (min_feature_mm, res) = match (valley_mm, ridge_mm) {
            (Some(a), Some(b)) if b < a => (Some(b), self.ridge_resolution_cells),
            (Some(a), _) => (Some(a), self.valley_resolution_cells),
            (None, b) => (b, self.ridge_resolution_cells),
        };
        FeatureReport {
            valley_mm,
            ridge_mm,
            min_feature_mm,
            resolution_mm: res * c,
            tol_mm: self.tol_cells * c,
        }
    }

    /// The smaller of the valley and ridge widths (grid units).
    pub fn min_cells(&self) -> Option<f64> {
        match (self.valley_cells, self.ridge_cells) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }
}

/// Does the closing (valleys) or opening (ridges) by a disc of radius `m` change `g` by more
/// than `tol` anywhere?
fn changes(g: &Grid, m: usize, tol: f64, valleys: bool) -> bool {
    if m == 0 {
        return false;
    }
    let r = m as f64;
    let out = if valleys {
        flat_close_cells(g.w, g.h, &g.z, r)
    } else {
        flat_open_cells(g.w, g.h, &g.z, r)
    };
    out.iter().zip(&g.z).any(|(a, b)| (a - b).abs() > tol)
}

/// Smallest `m` in `(lo, hi]` with `changes`, given `!changes(lo)`; `None` if not even `hi`.
fn first_change(g: &Grid, mut lo: usize, mut hi: usize, tol: f64, valleys: bool) -> Option<usize> {
    if !changes(g, hi, tol, valleys) {
        return None;
    }
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if changes(g, mid, tol, valleys) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    Some(hi)
}

/// First `m` at which the closing (valleys) or opening (ridges) changes the coarse grid.
fn coarse_first(g: &Grid, tol: f64, valleys: bool) -> Option<usize> {
    first_change(g, 0, (g.w.max(g.h) / 4).max(1), tol, valleys)
}

/// The width `2m − 1` samples, remeasured on a finer grid when narrow (`m <= 8`).
fn refined_width(hf: &Heightfield, m: usize, tol: f64, valleys: bool) -> (f64, f64) {
    let w = hf.width();
    let want = if m < 4 { 4 } else { 2 };
    let k = (MAX_SIDE / w.max(hf.height())).clamp(1, want);
    if m > 8 || k == 1 {
        return ((2 * m - 1) as f64, 1.0);
    }
    let fine = Grid::from_heightfield(hf, w as f64, k);
    let mut lo = (k * (m - 1)).saturating_sub(k);
    while lo > 0 && changes(&fine, lo, tol, valleys) {
        lo /= 2;
    }
    match first_change(&fine, lo, k * m + k, tol, valleys) {
        Some(mf) => ((2 * mf - 1) as f64 / k as f64, 1.0 / k as f64),
        None => ((2 * m - 1) as f64, 1.0),
    }
}

/// Narrowest valley and ridge of `hf`, with tolerance `tol_frac` × relief (peak to valley).
pub fn measure(hf: &Heightfield, tol_frac: f64) -> FeatureWidths {
    let (lo, hi) = hf.min_max();
    let tol = tol_frac * (hi - lo);
    let coarse = Grid::from_heightfield(hf, hf.width() as f64, 1);
    let mv = coarse_first(&coarse, tol, true);
    let mr = coarse_first(&coarse, tol, false);
    // Only the narrower of the two (both when tied) is remeasured finely: it is the one the
    // limits are compared with; the other keeps the coarse resolution of one sample.
    let narrowest = match (mv, mr) {
        (Some(a), Some(b)) => a.min(b),
        (Some(a), None) | (None, Some(a)) => a,
        (None, None) => 0,
    };
    let one = |m: Option<usize>, valleys: bool| -> (Option<f64>, f64) {
        match m {
            None => (None, 1.0),
            Some(m) if m == narrowest => {
                let (wd, r) = refined_width(hf, m, tol, valleys);
                (Some(wd), r)
            }
            Some(m) => (Some((2 * m - 1) as f64), 1.0),
        }
    };
    let (valley, vr) = one(mv, true);
    let (ridge, rr) = one(mr, false);
    FeatureWidths {
        valley_cells: valley,
        ridge_cells: ridge,
        valley_resolution_cells: vr,
        ridge_resolution_cells: rr,
        tol_cells: tol,
    }
}
