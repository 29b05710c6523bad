//! The inverse solvers (paper Sec. 4, 6, 7): from a target look, the library geometry (material
//! fixed), the library material (geometry fixed), or both, that reproduce it.
//!
//! Every solver works in three stages, each cheaper per item and coarser than the next:
//!
//! 1. **search** over the whole library through its compressed form: `fbar` of the few
//!    representatives, combined with every item's CX weights (Eq. 12) — one small matrix product,
//!    never a pass of evaluations over the library;
//! 2. **re-rank** a pool of the best items with their own uncompressed library data (the binned
//!    BVNDF column, or the material's own prefiltered table with the fast evaluator);
//! 3. **re-evaluate** the best `K` with the fast or the exact evaluator at the same samples, and
//!    sort by that error.
//!
//! Rotations (`psi`) rotate the target instead of the geometry (Sec. 6). Errors are the relative
//! error of [`crate::sampling`].

pub mod bench;
pub mod general;
pub mod geometry;
pub mod job;
pub mod joint;
pub mod look;
pub mod material;
pub mod veds;

use crate::bvndf::{BvndfConfig, CompactBvndf};
use crate::error::Result;
use crate::exact::ExactEvaluator;
use crate::frame::{DirPair, Vec3};
use crate::heightfield::Heightfield;
use crate::material::Material;
use crate::prefilter::Prefiltered;
use crate::sampling::Samples;
use serde::Serialize;

pub use look::Look;

/// The automatic pool of the material solver for a library of `items` materials: one per 4,
/// from 64 to 1024. The pool is narrowed by coarse passes ([`geometry::narrow`]), so it costs
/// little. With the library's search selection at 99.999 % energy, 200 cases of the paper's
/// protocol found the exhaustive optimum every time at pools of 260 on the 1,040-material
/// `paper4` library (0.020 s) and of 1024 on the paper-sized material library of
/// `paper-materials` (0.047 s; `docs/solvers.md`).
pub fn auto_pool(items: usize) -> usize {
    (items / 4).clamp(64, 1024)
}

/// The automatic pool of the geometry solver for a library of `items` geometries: one per 20
/// items, from 256 to 4096. Stage 2 narrows it by coarse passes of about equal cost
/// ([`geometry::coarse_step`]), so a pool four times larger costs one pass more. With stage 1's
/// third ranking (weights refitted to the light lobes), 50 cases of the paper's protocol were
/// all within 7 % from a pool of 512 on the 10,277-geometry `paper16` library and of 2048 on
/// the 41,108-geometry `paper4` one (98 % from half those pools; `docs/solvers.md`).
pub fn auto_geometry_pool(items: usize) -> usize {
    (items / 20).clamp(256, 4096)
}

impl SolveOptions {
    /// The pool for a library of `items` materials: the one asked for, or [`auto_pool`];
    /// never below `k`.
    pub fn pool_for(&self, items: usize) -> usize {
        self.pool_or(auto_pool(items))
    }

    /// The pool for a library of `items` geometries: the one asked for, or
    /// [`auto_geometry_pool`]; never below `k`.
    pub fn geometry_pool_for(&self, items: usize) -> usize {
        self.pool_or(auto_geometry_pool(items))
    }

    /// The pool asked for, else `auto`; never below `k`.
    pub(crate) fn pool_or(&self, auto: usize) -> usize {
        if self.pool > 0 { self.pool } else { auto }.max(self.k)
    }
}

/// How the final `K` candidates are evaluated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Final {
    /// Compact BVNDF × prefiltered material (milliseconds per candidate after a build).
    Fast,
    /// The exact evaluator (the reference; about a second per candidate at 64²).
    Exact,
    /// No third stage: the item's own library data (used inside the general solver's loop).
    Library,
}

/// Settings shared by the solvers.
#[derive(Debug, Clone)]
pub struct SolveOptions {
    /// Candidates returned.
    pub k: usize,
    /// Items re-ranked with their own uncompressed data (stage 2); 0 = automatic
    /// ([`auto_pool`]).
    pub pool: usize,
    /// Geometry solver, stages 1 and 2: evaluate library geometries with their stored light
    /// lobes and the fast evaluator (the default; accurate for glossy materials), instead of
    /// their binned columns.
    pub rerank_fast: bool,
    /// Geometry solver, stage 1 with light lobes: also rank every geometry by its
    /// representatives' *binned columns* × X, and fill the pool from both rankings in turn
    /// ([`interleave`]). The two estimates fail in different places (see
    /// `docs/solvers.md`, "Two rankings"), so a geometry either ranks well is re-ranked.
    pub binned_search: bool,
    /// Geometry solver, stage 2: when the pool's best is over [`geometry::WIDEN_ABOVE`],
    /// re-rank up to this many further pools from stage 1's rankings, while each finds a
    /// geometry at under [`geometry::WIDEN_GAIN`] times the best before it (0: the pool only).
    pub widen: usize,
    /// Geometry solver: rank geometries by their error at the brightness that fits them best
    /// (within [`crate::sampling::MAX_BRIGHTNESS_SCALE`]), not at the material's own. For a
    /// material that is a guess, whose brightness the material solve after it fixes: the
    /// general solver's alternation. Candidates' errors stay the material's own.
    pub any_brightness: bool,
    /// Rotations tried by the geometry solver.
    pub psi: usize,
    /// Weight of the colour term (Eq. 13).
    pub beta: f64,
    pub final_eval: Final,
    /// Exact evaluator: view rays per cell side.
    pub exact_samples: usize,
    pub sampling: crate::sampling::SamplingConfig,
    /// Progress bar of the final exact evaluation (seconds for a few candidates). Quiet by
    /// default: `validate` and `design` run the solvers many times; `solve` shows it.
    pub progress: crate::library::progress::Progress,
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            k: 5,
            pool: 0,
            rerank_fast: true,
            binned_search: true,
            widen: geometry::WIDEN,
            any_brightness: false,
            psi: 1,
            beta: 0.0,
            final_eval: Final::Exact,
            exact_samples: 1,
            sampling: crate::sampling::SamplingConfig::default(),
            progress: crate::library::progress::Progress { quiet: true },
        }
    }
}

/// The bar of a final exact evaluation of `evaluations` sets of `samples` pairs (each pair
/// shaded from both ends), from the options' progress; hidden when the final evaluation is not
/// the exact one.
pub(crate) fn final_bar(
    opt: &SolveOptions,
    evaluations: usize,
    samples: usize,
) -> crate::library::progress::Bar {
    match opt.final_eval {
        Final::Exact => opt.progress.bar(
            (2 * evaluations * samples) as u64,
            "solve: final evaluation (exact; pairs from each end)",
        ),
        _ => crate::library::progress::Bar::hidden(),
    }
}

/// One answer: a geometry (rotated by `psi_deg`), a material and its colour, with its errors.
#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    pub geometry: Option<usize>,
    pub geometry_spec: String,
    pub material: Option<usize>,
    pub material_spec: String,
    pub psi_deg: f64,
    /// Index of the colour shift (0 = the material's own colour), when a library material.
    pub colour_shift: Option<usize>,
    /// Average RGB colour `lambda` of the candidate material with its shift.
    pub colour: [f64; 3],
    /// Error from the compressed search (stage 1): in a geometry solve, the least of its
    /// rankings' that hold the candidate among their best; at the best brightness with
    /// [`SolveOptions::any_brightness`].
    pub search_error: f64,
    /// Error from the item's own library data (stage 2); at the best brightness in a geometry
    /// solve with [`SolveOptions::any_brightness`], whose candidates are in this order.
    pub rerank_error: f64,
    /// Error from the final evaluator (stage 3), always at the material's own brightness;
    /// candidates are sorted by it (but see `rerank_error`).
    pub error: f64,
    pub evaluated_by: Final,
}

/// Timings and counts of one solve, for the log and `validate`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SolveStats {
    pub search_seconds: f64,
    pub rerank_seconds: f64,
    pub final_seconds: f64,
    pub items_searched: usize,
    pub representatives: usize,
    pub notes: Vec<String>,
}

#[derive(Debug, Clone, Serialize)]
pub struct SolveResult {
    pub candidates: Vec<Candidate>,
    pub stats: SolveStats,
}

/// The pairs of a sample set as direction pairs in the geometry's frame.
pub fn dir_pairs(s: &Samples) -> Vec<DirPair> {
    s.pairs
        .iter()
        .map(|&(l, wo)| DirPair {
            wi: s.lights[l],
            wo,
        })
        .collect()
}

/// `fbar` of a compact BVNDF with a prefiltered material at every sample.
pub fn fast_values<G: crate::bvndf::LobeSource + ?Sized>(
    geo: &G,
    mat: &Prefiltered,
    s: &Samples,
) -> Vec<f64> {
    crate::fast::fbar(geo, mat, &dir_pairs(s))
}

/// The compact BVNDF the solvers use for targets and re-evaluation: the forward model's grid,
/// one vMF per cluster as in the libraries ([`BvndfConfig::library`]).
pub fn bvndf_of(hf: &Heightfield) -> CompactBvndf {
    CompactBvndf::build(hf, &BvndfConfig::library())
}

/// The samples of `look` rotated by `psi` (radians) at the library's `lights`, and the target
/// values there: the geometry rotated by `psi` seen in its own frame (Sec. 6). Drawn once per
/// look and settings ([`Look::memo`]).
pub fn rotated_samples(
    look: &Look,
    lights: &[Vec3],
    psi: f64,
    cfg: &crate::sampling::SamplingConfig,
) -> (Samples, Vec<f64>) {
    let mut key = vec![
        psi.to_bits(),
        cfg.views_per_light as u64,
        cfg.gradient_share.to_bits(),
        cfg.seed,
    ];
    key.extend(
        lights
            .iter()
            .flat_map(|l| [l.x, l.y, l.z].map(f64::to_bits)),
    );
    let v = look.memo(key, || {
        let f = look.as_fn();
        let rotated = |wi, wo| {
            f(
                crate::frame::rotate_z(wi, psi),
                crate::frame::rotate_z(wo, psi),
            )
        };
        let samples = crate::sampling::sample(lights, &rotated, cfg);
        let target = samples.values(&f, psi);
        (samples, target)
    });
    (v.0.clone(), v.1.clone())
}

/// The prefiltered table of a material: the library's stored table when it is library material
/// `index`, else built with the library's prefilter settings (0.1–0.3 s).
pub fn material_prefiltered(
    lib: &crate::library::Library,
    mat: &Material,
    index: Option<usize>,
) -> Result<Prefiltered> {
    let cfg = crate::library::build::prefilter_config(&lib.profile);
    match index {
        Some(m) => Prefiltered::from_array(
            mat,
            &cfg,
            lib.array("material/prefiltered.bsa")?,
            m,
            lib.manifest.table_len,
        ),
        None => Ok(Prefiltered::build(mat, &cfg)),
    }
}

/// View rays per view node of the light lobes built for a geometry outside the library.
pub const LIGHT_LOBE_RAYS: usize = 1024;

/// `fbar` of several materials on one geometry with the exact evaluator (shared rays).
pub fn exact_values(
    hf: &Heightfield,
    mats: &[&Material],
    s: &Samples,
    rays_per_side: usize,
    bar: &crate::library::progress::Bar,
) -> Vec<Vec<f64>> {
    ExactEvaluator::new(hf, rays_per_side)
        .with_progress(bar)
        .fbar_many(mats, &dir_pairs(s))
}

/// A value [`smallest`] ranks: the searches' errors, in `f64`, or in `f32` where a scan computes
/// them at its data's precision (the joint search).
pub trait Score: Copy {
    fn finite(self) -> bool;
    fn order(&self, other: &Self) -> std::cmp::Ordering;
    /// Whether every value of `chunk` is above `bound` (`>`, so signed zeros, NaN and equal
    /// values say no): none of them orders before it.
    fn all_above(chunk: &[Self], bound: Self) -> bool;
}

macro_rules! score_for_float {
    ($($t:ty),*) => {$(
        impl Score for $t {
            #[inline]
            fn finite(self) -> bool {
                self.is_finite()
            }
            #[inline]
            fn order(&self, other: &Self) -> std::cmp::Ordering {
                self.total_cmp(other)
            }
            #[inline]
            fn all_above(chunk: &[Self], bound: Self) -> bool {
                // Without branches, so that the test runs in vector registers.
                chunk.iter().fold(true, |a, &v| a & (v > bound))
            }
        }
    )*};
}

score_for_float!(f64, f32);

/// Indices of the `n` smallest values (ties by index), ascending.
pub fn smallest<T: Score>(errors: &[T], n: usize) -> Vec<usize> {
    if n <= SMALL_N && errors.len() > 4 * n {
        return smallest_few(errors, n);
    }
    // The n-th smallest value, found on a copy of the values (linear time, and the
    // comparisons read contiguous values rather than through indices), then one pass for the
    // indices below it and, in index order, as many equal to it as make n; only the n kept
    // are sorted.
    let finite = errors.iter().filter(|e| e.finite()).count();
    let idx: Vec<usize> = if n == 0 {
        Vec::new()
    } else if n < finite {
        let mut values: Vec<T> = errors.iter().copied().filter(|e| e.finite()).collect();
        let (before, &mut nth, _) = values.select_nth_unstable_by(n - 1, |a, b| a.order(b));
        let mut ties = n - before.iter().filter(|v| v.order(&nth).is_lt()).count();
        let mut idx = Vec::with_capacity(n);
        for (i, e) in errors.iter().enumerate() {
            if !e.finite() {
                continue;
            }
            match e.order(&nth) {
                std::cmp::Ordering::Less => idx.push(i),
                std::cmp::Ordering::Equal if ties > 0 => {
                    ties -= 1;
                    idx.push(i);
                }
                _ => {}
            }
        }
        idx
    } else {
        (0..errors.len()).filter(|&i| errors[i].finite()).collect()
    };
    // Sorted as (value, index) pairs: the comparisons read the values beside the indices
    // rather than through them (the order is total, ties by index, so unstable is exact).
    let mut keyed: Vec<(T, usize)> = idx.into_iter().map(|i| (errors[i], i)).collect();
    keyed.sort_unstable_by(|a, b| a.0.order(&b.0).then(a.1.cmp(&b.1)));
    keyed.into_iter().map(|(_, i)| i).collect()
}

/// Up to this many, [`smallest`] keeps a sorted list of the best so far, so that most values
/// cost one comparison (the joint search takes the best 8 of every geometry's materials).
const SMALL_N: usize = 32;

/// Values per chunk [`smallest_few`] tests at once.
const FEW_CHUNK: usize = 16;

/// [`smallest`] for small `n`: one pass, the best so far kept sorted; a value enters only if it
/// beats the last kept (ties by index, and indices ascend, so an equal value never does).
fn smallest_few<T: Score>(errors: &[T], n: usize) -> Vec<usize> {
    let mut best: Vec<(T, usize)> = Vec::with_capacity(n + 1);
    if n == 0 {
        return Vec::new();
    }
    // Once `n` are kept, a chunk whose every value is above the last kept is passed over
    // whole: most of a long list's chunks are.
    for (c, chunk) in errors.chunks(FEW_CHUNK).enumerate() {
        if best.len() == n {
            if let Some(&(last, _)) = best.last() {
                if T::all_above(chunk, last) {
                    continue;
                }
            }
        }
        for (k, &e) in chunk.iter().enumerate() {
            if !e.finite() {
                continue;
            }
            if best.len() == n {
                match best.last() {
                    Some(&(last, _)) if e.order(&last).is_lt() => {}
                    _ => continue,
                }
            }
            let at = best.partition_point(|&(v, _)| v.order(&e).is_le());
            best.insert(at, (e, c * FEW_CHUNK + k));
            best.truncate(n);
        }
    }
    best.into_iter().map(|(_, i)| i).collect()
}

/// The first `n` distinct entries of `rankings` taken in turn (`r0[0]`, `r1[0]`, …, `r0[1]`,
/// …; a ranking that runs out drops out): their union, each contributing its best, when none
/// can be trusted alone.
pub fn interleave(rankings: &[&[usize]], n: usize) -> Vec<usize> {
    // Entries are indices: which were taken is a flag per index up to the largest.
    let top = rankings
        .iter()
        .flat_map(|r| r.iter())
        .max()
        .map_or(0, |&m| m + 1);
    let mut seen = vec![false; top];
    let mut out = Vec::with_capacity(n);
    let longest = rankings.iter().map(|r| r.len()).max().unwrap_or(0);
    for i in 0..longest {
        for r in rankings {
            if out.len() == n {
                return out;
            }
            if let Some(&x) = r.get(i) {
                if !std::mem::replace(&mut seen[x], true) {
                    out.push(x);
                }
            }
        }
    }
    out
}

/// Weighted `A X` errors for every item: `t` target values, `a` the representatives' values per
/// sample (`[k][sample]`), `x` item-major CX weights (`[item][k]`). Returns relative errors.
///
/// An item's error compares the target with its reconstruction `A x` clamped at zero (`fbar` is
/// never negative). Computing it costs `samples × k` per item; on a paper-sized library that is
/// 60× the memory-bandwidth limit (`biscale bench scan`). So every item is first scored without
/// the clamp through the Gram form — with `A_w = diag(w) A`, `t_w = diag(w) t`, the squared
/// error is `|t_w|² − 2 xᵀ (A_wᵀ t_w) + xᵀ (A_wᵀ A_w) x`, `k² + k` operations per item — and
/// the best `rescore` of those get the clamped error. Clamping can only lower an error (the
/// target is never negative), so the rest keep an upper bound. A library of at most `rescore`
/// items gets the clamped error for every item. A solve shares [`SEARCH_RESCORE`] among its
/// searches (one per rotation). Items are processed
/// in blocks of [`SEARCH_BLOCK`] (in parallel), so memory stays `O(samples × block)` whatever
/// the library's size.
pub fn search_errors(
    s: &Samples,
    t: &[f64],
    a: &[Vec<f64>],
    x: &[f32],
    items: usize,
    rescore: usize,
) -> Vec<f64> {
    search_errors_multi(
        s,
        std::slice::from_ref(&t.to_vec()),
        a,
        x,
        items,
        rescore,
        items,
        false,
    )
    .pop()
    .unwrap_or_default()
}

/// [`search_errors`] for several targets at the same samples (one per rotation of the target,
/// read at one shared sample set): `[target][item]`. Everything that does not depend on the
/// target is computed once — the Gram matrix, each item's quadratic term `xᵀ Q x`, and the
/// reconstruction `A x` of every rescored item — so `T` targets cost little more than one. Each
/// target's best `rescore` (by the Gram form) are rescored, and every item rescored for one
/// target gets its clamped error for all; a library of at most `rescore × T` items gets the
/// clamped error everywhere. With `any_brightness` each error is taken at the brightness that
/// fits best ([`crate::sampling::scaled_rel_error`]): the terms are the same.
///
/// Only the best `keep` entries over all targets (and each target's best `rescore`) need be
/// exact. For one target, when those are few ([`PRUNE_SHARE`]) and the Gram matrix has a
/// factor, every item is first bounded from below by the factor's first band
/// ([`gram_bounds`]); the items with the best bounds (half as many again) are scored, and any
/// other only when its bound is under the `keep`-th best error found among them. Every other
/// item holds its bound, which is above the errors of the best `keep` (and `rescore`): ranking
/// the result gives the same best entries as scoring every item. (With several targets the
/// selections over every entry cost more than the bounds save: every item is scored.)
/// `keep = items × targets` scores every item.
#[allow(clippy::too_many_arguments)]
pub fn search_errors_multi(
    s: &Samples,
    ts: &[Vec<f64>],
    a: &[Vec<f64>],
    x: &[f32],
    items: usize,
    rescore: usize,
    keep: usize,
    any_brightness: bool,
) -> Vec<Vec<f64>> {
    use faer::Mat;
    use rayon::prelude::*;
    let (np, c) = (s.weights.len(), a.len());
    if c == 0 {
        return vec![vec![f64::INFINITY; items]; ts.len()];
    }
    let aw = Mat::<f64>::from_fn(np, c, |p, k| a[k][p] * s.weights[p]);
    let aw32 = Mat::<f32>::from_fn(np, c, |p, k| aw[(p, k)] as f32);
    let tws: Vec<Vec<f64>> = ts
        .iter()
        .map(|t| t.iter().zip(&s.weights).map(|(t, w)| t * w).collect())
        .collect();
    let n2s: Vec<f64> = tws
        .iter()
        .map(|tw| tw.iter().map(|v| v * v).sum())
        .collect();
    let rel = |n2: f64, lin: f64, quad: f64| {
        crate::sampling::scaled_rel_error(n2, lin, quad, any_brightness)
    };
    let nt = ts.len();
    // Blocks of `n` items each, `[target][item in block]` flattened target-major, joined into
    // `[target][item]` in the blocks' order.
    fn join(nt: usize, blocks: Vec<(usize, Vec<f64>)>) -> Vec<Vec<f64>> {
        let mut out: Vec<Vec<f64>> = vec![Vec::new(); nt];
        for (n, b) in &blocks {
            for (ti, o) in out.iter_mut().enumerate() {
                o.extend_from_slice(&b[ti * n..(ti + 1) * n]);
            }
        }
        out
    }
    // The clamped error of the items `ids` for every target, `[target][position in ids]`: one
    // reconstruction per item serves all targets. The reconstruction and its error sums run in
    // `f32`, the CX weights' own precision (twice the `f64` rate, and the sums in vector
    // registers): their rounding is about 1e-7 of `|t|²`, far below the 1e-4 of a 1 % error.
    let tws32: Vec<Vec<f32>> = tws
        .iter()
        .map(|tw| tw.iter().map(|&v| v as f32).collect())
        .collect();
    let clamped = |ids: &[usize]| -> Vec<Vec<f64>> {
        let blocks: Vec<(usize, Vec<f64>)> = ids
            .par_chunks(RESCORE_BLOCK)
            .map(|chunk| {
                let n = chunk.len();
                let xm = Mat::<f32>::from_fn(c, n, |k, j| x[chunk[j] * c + k]);
                let mut prod = &aw32 * &xm;
                let mut out = vec![0.0; nt * n];
                for j in 0..n {
                    let col = prod.col_as_slice_mut(j);
                    for v in col.iter_mut() {
                        *v = v.max(0.0);
                    }
                    let col = &*col;
                    // The clamped reconstruction's own terms; at brightness 1 the squared
                    // difference is summed directly (no cancellation near an exact match).
                    let quad = if any_brightness {
                        crate::fastmath::dot32(col, col)
                    } else {
                        0.0
                    };
                    for (ti, (tw, &n2)) in tws32.iter().zip(&n2s).enumerate() {
                        out[ti * n + j] = if any_brightness {
                            rel(n2, crate::fastmath::dot32(tw, col), quad)
                        } else if n2 > 0.0 {
                            (crate::fastmath::dist2_32(tw, col) / n2).sqrt()
                        } else {
                            f64::INFINITY
                        };
                    }
                }
                (n, out)
            })
            .collect();
        join(nt, blocks)
    };
    if items <= rescore.saturating_mul(nt) {
        return clamped(&(0..items).collect::<Vec<_>>());
    }
    // The Gram product runs in f32, the weights' own precision (twice the f64 rate); its
    // rounding only decides which items are rescored, in f64, below. Through the Gram
    // matrix's Cholesky factor when it has one ([`gram_factor`]): `xᵀ Q x = |R x|²`, and `R`
    // is triangular, so the product needs a little over half the operations
    // ([`triangular_times`]).
    let q = aw.transpose() * &aw;
    let factor = gram_factor(q.as_ref());
    let q = Mat::<f32>::from_fn(c, c, |i, j| q[(i, j)] as f32);
    // The targets' cross terms `A_wᵀ t_w`, one row per target: every item's linear terms are
    // one product per block, in `f32` as the quadratic terms (one dot product per item and
    // target before: at psi 8 they cost more than the Gram product).
    let bm = Mat::<f32>::from_fn(nt, c, |ti, k| {
        (0..np).map(|p| aw[(p, k)] * tws[ti][p]).sum::<f64>() as f32
    });
    // The Gram scores of a block of items whose weights `xb` are column-major `c × n` (read in
    // place for a run of the library, copied for a gathered set), `[target][item in block]`.
    let score = |xb: &[f32]| -> Vec<f64> {
        let n = xb.len() / c;
        let xm = faer::MatRef::from_column_major_slice(xb, c, n);
        // `R X` band by band, or `Q X` without a factor; the quadratic term is `|R x|²`, or
        // `xᵀ (Q x)`.
        let (prod, factored) = match &factor {
            Some(r) => (triangular_times(r.as_ref(), xm), true),
            None => (&q * xm, false),
        };
        let mut lins = Mat::<f32>::zeros(nt, n);
        faer::linalg::matmul::matmul(
            lins.as_mut(),
            faer::Accum::Replace,
            bm.as_ref(),
            xm,
            1.0f32,
            faer::Par::Seq,
        );
        let mut out = vec![0.0; nt * n];
        for (j, xj) in xb.chunks_exact(c).enumerate() {
            let col = prod.col_as_slice(j);
            let quad = if factored {
                crate::fastmath::dot(col, col)
            } else {
                crate::fastmath::dot(xj, col)
            };
            for (ti, &n2) in n2s.iter().enumerate() {
                out[ti * n + j] = rel(n2, lins[(ti, j)] as f64, quad);
            }
        }
        out
    };
    // Subnormal products (a small weight times a small cross term) are flushed: computed, they
    // made some scans 10× slower (`fastmath::without_subnormals`).
    let scored = |ids: &[usize]| -> Vec<Vec<f64>> {
        let blocks: Vec<(usize, Vec<f64>)> = ids
            .par_chunks(SEARCH_BLOCK)
            .map(|chunk| {
                let mut xb = Vec::with_capacity(chunk.len() * c);
                for &j in chunk {
                    xb.extend_from_slice(&x[j * c..(j + 1) * c]);
                }
                let e = crate::fastmath::without_subnormals(|| score(&xb));
                (chunk.len(), e)
            })
            .collect();
        join(nt, blocks)
    };
    let bounds = match (&factor, n2s.as_slice()) {
        (Some(r), &[n2]) if !any_brightness && prunes(items, keep, rescore) => {
            gram_bounds(r.as_ref(), &bm, n2, x, items)
        }
        _ => None,
    };
    let mut errors = match bounds {
        // Every item's bound from the factor's first band; the entries with the best bounds
        // give a threshold, and only the other items whose bound is under it are scored.
        Some(mut errors) => {
            let put = |ids: &[usize], errors: &mut [f64]| {
                for (&j, v) in ids.iter().zip(scored(ids).remove(0)) {
                    errors[j] = v;
                }
            };
            let mut ids = smallest(&errors, keep.max(rescore).saturating_mul(3) / 2);
            ids.sort_unstable();
            put(&ids, &mut errors);
            // The `keep`-th best error among the scored items is at least the `keep`-th best
            // of all (the `rescore`-th likewise): an item whose bound is over it is not among
            // the best.
            let limit = kth_smallest(ids.iter().map(|&j| errors[j]).collect(), keep.max(rescore))
                .powi(2)
                + BOUND_MARGIN;
            // (Not a number only from weights that are not: then every item is scored.)
            let limit = if limit.is_nan() { f64::INFINITY } else { limit };
            let mut done = vec![false; items];
            for &j in &ids {
                done[j] = true;
            }
            let rest: Vec<usize> = (0..items)
                .filter(|&j| !done[j] && errors[j] * errors[j] <= limit)
                .collect();
            put(&rest, &mut errors);
            vec![errors]
        }
        None => {
            let starts: Vec<usize> = (0..items).step_by(SEARCH_BLOCK).collect();
            let blocks: Vec<(usize, Vec<f64>)> = starts
                .par_iter()
                .map(|&j0| {
                    let n = SEARCH_BLOCK.min(items - j0);
                    let xb = &x[j0 * c..(j0 + n) * c];
                    (n, crate::fastmath::without_subnormals(|| score(xb)))
                })
                .collect();
            join(nt, blocks)
        }
    };
    let mut best: Vec<usize> = errors.iter().flat_map(|e| smallest(e, rescore)).collect();
    best.sort_unstable();
    best.dedup();
    let exact = clamped(&best);
    for (ti, e) in exact.into_iter().enumerate() {
        for (&j, v) in best.iter().zip(e) {
            errors[ti][j] = v;
        }
    }
    errors
}

/// Whether a scan of `items` items for one target, of which the best `keep` (and the best
/// `rescore`) must be exact, is worth bounding first: when those are at most a
/// [`PRUNE_SHARE`]th of the items.
fn prunes(items: usize, keep: usize, rescore: usize) -> bool {
    keep.max(rescore).saturating_mul(PRUNE_SHARE) <= items
}

/// [`search_errors_multi`] bounds every item before scoring it when the items it must score
/// exactly are at most this share of all (one in four).
pub const PRUNE_SHARE: usize = 4;

/// Added to the squared threshold (relative) of [`search_errors_multi`]'s bounds: the bound and
/// the score sum in different orders, in `f32`, which round at about 1e-7 of the magnitudes
/// summed, so an item is passed over only when its bound is clearly over the threshold.
pub const BOUND_MARGIN: f64 = 1e-4;

/// Lower bounds on every item's relative Gram error. With `R` the factor (`Rᵀ R = Q`) and `z` the
/// solution of `Rᵀ z = b` (`b = A_wᵀ t_w`, the row `bm`), the squared error
/// `|t_w|² − 2 bᵀ x + |R x|²` is `|R x − z|² + |t_w|² − |z|²`: a sum of squares, one per row of
/// `R`, plus a constant. The first [`GRAM_BAND`] rows — the representatives CX picked first,
/// which carry most of the energy — cost about a quarter of `|R x|²` and bound the rest from
/// below. `None` when `z` is not finite.
fn gram_bounds(
    r: faer::MatRef<'_, f32>,
    bm: &faer::Mat<f32>,
    n2: f64,
    x: &[f32],
    items: usize,
) -> Option<Vec<f64>> {
    use rayon::prelude::*;
    let c = r.nrows();
    let h = GRAM_BAND.min(c);
    // Forward substitution in `f64` on the `f32` factor the scores use, so that the identity
    // holds for it; `R x`'s rows are the reconstruction's coordinates in an orthonormal basis of
    // the representatives' span and `z` the target's projection's, so `|z|² ≤ |t_w|²`.
    let mut z = vec![0.0f64; c];
    for i in 0..c {
        let v: f64 = (0..i).map(|k| r[(k, i)] as f64 * z[k]).sum();
        z[i] = (bm[(0, i)] as f64 - v) / r[(i, i)] as f64;
    }
    if !(n2 > 0.0) || z.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let rest = n2 - z.iter().map(|v| v * v).sum::<f64>();
    let z32: Vec<f32> = z[..h].iter().map(|&v| v as f32).collect();
    let band = r.subrows(0, h);
    let starts: Vec<usize> = (0..items).step_by(SEARCH_BLOCK).collect();
    let blocks: Vec<Vec<f64>> = starts
        .par_iter()
        .map(|&j0| {
            let n = SEARCH_BLOCK.min(items - j0);
            let xm = faer::MatRef::from_column_major_slice(&x[j0 * c..(j0 + n) * c], c, n);
            let mut y = faer::Mat::<f32>::zeros(h, n);
            crate::fastmath::without_subnormals(|| {
                faer::linalg::matmul::matmul(
                    y.as_mut(),
                    faer::Accum::Replace,
                    band,
                    xm,
                    1.0f32,
                    faer::Par::Seq,
                )
            });
            (0..n)
                .map(|j| {
                    let part = crate::fastmath::dist2_32(y.col_as_slice(j), &z32);
                    ((part + rest).max(0.0) / n2).sqrt()
                })
                .collect()
        })
        .collect();
    Some(blocks.concat())
}

/// The `k`-th smallest of `values` (from 1), infinite when there are fewer.
fn kth_smallest(mut values: Vec<f64>, k: usize) -> f64 {
    if k == 0 || k > values.len() {
        return f64::INFINITY;
    }
    *values.select_nth_unstable_by(k - 1, f64::total_cmp).1
}

/// The upper Cholesky factor `R` (`Q = Rᵀ R`, in `f32`) of a search's Gram matrix `q`, with
/// a ridge of [`GRAM_RIDGE`] of its largest diagonal entry so that a Gram matrix of dependent
/// representatives has one too; `None` when `q` is zero, not finite, or has no factor even so
/// (the scan then uses `q` itself). The ridge adds `GRAM_RIDGE · max Q_ii · |x|²` to an item's
/// quadratic term, far below the `f32` product's rounding.
fn gram_factor(q: faer::MatRef<'_, f64>) -> Option<faer::Mat<f32>> {
    let c = q.nrows();
    let scale = (0..c).map(|i| q[(i, i)]).fold(0.0, f64::max);
    if !(scale > 0.0 && scale.is_finite()) {
        return None;
    }
    let mut qr = q.to_owned();
    for i in 0..c {
        qr[(i, i)] += GRAM_RIDGE * scale;
    }
    let llt = qr.llt(faer::Side::Lower).ok()?;
    let l = llt.L();
    let r = faer::Mat::<f32>::from_fn(c, c, |i, j| if j >= i { l[(j, i)] as f32 } else { 0.0 });
    let finite = (0..c).all(|j| r.col_as_slice(j).iter().all(|v| v.is_finite()));
    finite.then_some(r)
}

/// The ridge of [`gram_factor`], relative to the Gram matrix's largest diagonal entry.
pub const GRAM_RIDGE: f64 = 1e-10;

/// Rows per band of [`triangular_times`].
const GRAM_BAND: usize = 16;

/// `R X` for an upper triangular `R` (`c × c`) and a block of weights `X` (`c × n`): a band of
/// `R`'s rows is zero left of its first row, so it multiplies only the rows of `X` from there
/// on. With bands of [`GRAM_BAND`] rows that is 58 % of a full product's operations at 101
/// representatives, each band one dense product (faer, sequential: the blocks run in parallel).
fn triangular_times(r: faer::MatRef<'_, f32>, x: faer::MatRef<'_, f32>) -> faer::Mat<f32> {
    let (c, n) = (r.nrows(), x.ncols());
    let mut y = faer::Mat::<f32>::zeros(c, n);
    for r0 in (0..c).step_by(GRAM_BAND) {
        let h = GRAM_BAND.min(c - r0);
        faer::linalg::matmul::matmul(
            y.as_mut().subrows_mut(r0, h),
            faer::Accum::Replace,
            r.submatrix(r0, r0, h, c - r0),
            x.subrows(r0, c - r0),
            1.0f32,
            faer::Par::Seq,
        );
    }
    y
}

/// Items of one solve's compressed search that get the clamped error, shared among its
/// rotations (see [`search_errors`]).
pub const SEARCH_RESCORE: usize = 4096;

/// The `rescore` of each of a solve's `searches` (one per rotation): an equal share of
/// [`SEARCH_RESCORE`], never fewer than the `pool` the solve keeps (the pool is one over all
/// rotations, so the shares together cover it).
pub fn rescore_share(searches: usize, pool: usize) -> usize {
    (SEARCH_RESCORE / searches.max(1)).max(pool)
}

/// Items per block of the compressed search.
pub const SEARCH_BLOCK: usize = 4096;

/// Items per block of the clamped rescoring: a block's reconstruction (`samples × block` f64,
/// 1 MB at 490 samples) stays in the processor's cache between the product that writes it and
/// the error loop that reads it; at [`SEARCH_BLOCK`] it was 16 MB.
pub const RESCORE_BLOCK: usize = 256;

/// Rotation `i` of `psi` in radians.
pub fn psi_angle(i: usize, psi: usize) -> f64 {
    std::f64::consts::TAU * i as f64 / psi.max(1) as f64
}

/// A coarse pass's samples: every `step`-th of the samples `s` (`t`: the target values there),
/// their pairs placed in the light-lobe table of `layout`, and the target's values at them.
/// With `step` 1 these are `s` and `t`. Coarser, each sample's view is moved to the nearest
/// view node of the table ([`crate::lightlobes::LightPairs::snapped`]), where a record is read
/// at one node instead of interpolated over up to four, and `look` (rotated by `psi`) is read
/// there: a coarse pass only ranks, and its samples need not be the solve's own.
pub fn coarse_at(
    layout: &crate::gamma::GammaLayout,
    s: &Samples,
    t: &[f64],
    look: &Look,
    psi: f64,
    step: usize,
) -> (Samples, Vec<f64>, crate::lightlobes::LightPairs) {
    let (mut s, t) = s.every(step, t);
    if step <= 1 {
        let at = crate::lightlobes::LightPairs::new(layout, dir_pairs(&s));
        return (s, t, at);
    }
    let at = crate::lightlobes::LightPairs::snapped(layout, dir_pairs(&s));
    for (p, q) in s.pairs.iter_mut().zip(&at.pairs) {
        p.1 = q.wo;
    }
    let t = s.values(&look.as_fn(), psi);
    (s, t, at)
}

/// The heightfield of a library geometry item.
pub fn library_heightfield(spec: &str) -> Result<Heightfield> {
    crate::generators::parse_generator(spec)?.build()
}

/// A unit vector's components, for logs.
pub fn fmt_dir(w: Vec3) -> String {
    let (t, p) = crate::frame::angles_of(w);
    format!("({:.1}°, {:.1}°)", t.to_degrees(), p.to_degrees())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::Vec3;

    #[test]
    fn coarse_passes_compare_at_view_nodes_and_the_last_at_the_solves_samples() {
        let layout = crate::gamma::GammaLayout::new(10, 16, 16);
        let look = Look::from_spec("ggx:alpha=0.2", look::Edits::default(), None).unwrap();
        let pairs: Vec<(usize, Vec3)> = (0..40)
            .map(|k| {
                let (t, p) = ((5 + 2 * k) as f64, (37 * k) as f64);
                (k % 7, crate::frame::dir_from_deg(t, p))
            })
            .collect();
        let s = Samples {
            weights: (0..40).map(|k| 1.0 + k as f64 / 40.0).collect(),
            pairs,
            lights: layout.lights.clone(),
        };
        let psi = 0.3;
        let t = s.values(&look.as_fn(), psi);
        // Every sample: the solve's own samples and values.
        let (s1, t1, _) = coarse_at(&layout, &s, &t, &look, psi, 1);
        assert_eq!(
            (s1.pairs, s1.weights, t1),
            (s.pairs.clone(), s.weights.clone(), t)
        );
        // Every 4th: the views at grid nodes, the weights kept, the look read there.
        let (s4, t4, at) = coarse_at(&layout, &s, &s.values(&look.as_fn(), psi), &look, psi, 4);
        assert_eq!(s4.pairs.len(), 10);
        assert_eq!(
            s4.weights,
            s.weights.iter().step_by(4).copied().collect::<Vec<_>>()
        );
        for (k, &(l, wo)) in s4.pairs.iter().enumerate() {
            assert_eq!(l, s.pairs[4 * k].0);
            assert!((0..layout.views.len()).any(|b| layout.views.direction(b) == wo));
            assert_eq!(at.pairs[k].wo, wo);
        }
        assert_eq!(t4, s4.values(&look.as_fn(), psi));
        assert_ne!(
            t4,
            s.values(&look.as_fn(), psi)
                .into_iter()
                .step_by(4)
                .collect::<Vec<_>>()
        );
    }

    #[test]
    fn the_automatic_pool_grows_with_the_library_and_an_asked_pool_wins() {
        assert_eq!(auto_pool(29), 64);
        assert_eq!(auto_pool(192), 64);
        assert_eq!(auto_pool(1_040), 260);
        assert_eq!(auto_pool(4_168), 1024);
        assert_eq!(auto_geometry_pool(200), 256);
        assert_eq!(auto_geometry_pool(800), 256);
        assert_eq!(auto_geometry_pool(10_277), 513);
        assert_eq!(auto_geometry_pool(41_108), 2055);
        assert_eq!(auto_geometry_pool(164_431), 4096);
        let auto = SolveOptions::default();
        assert_eq!(auto.pool_for(1_040), 260);
        assert_eq!(auto.geometry_pool_for(10_277), 513);
        let asked = SolveOptions {
            pool: 16,
            k: 20,
            ..Default::default()
        };
        assert_eq!(asked.pool_for(10_277), 20, "never below k");
        assert_eq!(asked.geometry_pool_for(10_277), 20, "never below k");
    }

    #[test]
    fn coarse_passes_cost_alike_and_keep_enough_samples() {
        use geometry::{coarse_step, COARSE_KEEP, COARSE_MIN_SAMPLES};
        // 128 → 32: one pass at every 4th sample.
        assert_eq!(coarse_step(128, COARSE_KEEP, 490), 4);
        // 512 → 128 → 32: every 16th, then every 4th.
        assert_eq!(coarse_step(512, COARSE_KEEP, 490), 16);
        // paper16's 2055 → 513 → 128 → 32 would start at every 64th sample: never under
        // COARSE_MIN_SAMPLES samples.
        assert_eq!(
            coarse_step(2055, COARSE_KEEP, 490),
            490 / COARSE_MIN_SAMPLES
        );
        assert_eq!(coarse_step(513, COARSE_KEEP, 490), 16);
        // A pool just over the floor: one pass to the floor.
        assert_eq!(coarse_step(40, COARSE_KEEP, 490), 4);
        // Nothing to narrow, or too few samples to thin.
        assert_eq!(coarse_step(32, COARSE_KEEP, 490), 1);
        assert_eq!(coarse_step(1024, COARSE_KEEP, 20), 1);
    }

    #[test]
    fn narrowing_evaluates_passes_at_the_same_samples_once() {
        use geometry::{coarse_step, narrow, COARSE_KEEP, COARSE_STEP};
        // Errors with many ties, different at every step.
        let err = |i: usize, step: usize| ((i * 7919 + step * 31) % 1000) as f64;
        let calls = std::cell::RefCell::new(Vec::new());
        let got = narrow(
            (0..4096).collect(),
            COARSE_KEEP,
            490,
            |p: &[usize], step| {
                calls.borrow_mut().push((p.len(), step));
                Ok(p.iter().map(|&i| err(i, step)).collect())
            },
        )
        .unwrap();
        // 4096 → 1024 → 256 → 64 → 32: the first two passes both at every 30th sample (held
        // at COARSE_MIN_SAMPLES), evaluated once.
        assert_eq!(*calls.borrow(), vec![(4096, 30), (256, 16), (64, 4)]);
        // The same entries in the same order as evaluating every pass.
        let mut naive: Vec<usize> = (0..4096).collect();
        while naive.len() > COARSE_KEEP {
            let step = coarse_step(naive.len(), COARSE_KEEP, 490);
            let e: Vec<f64> = naive.iter().map(|&i| err(i, step)).collect();
            let keep = (naive.len() / COARSE_STEP).max(COARSE_KEEP);
            naive = smallest(&e, keep).into_iter().map(|i| naive[i]).collect();
        }
        assert_eq!(got, naive);
    }

    #[test]
    fn smallest_keeps_the_n_best_in_order_with_ties_by_index() {
        let e = [0.5, f64::NAN, 0.1, 0.3, 0.1, f64::INFINITY, 0.2, 0.3];
        assert_eq!(smallest(&e, 3), vec![2, 4, 6]);
        assert_eq!(smallest(&e, 5), vec![2, 4, 6, 3, 7]);
        assert_eq!(smallest(&e, 100), vec![2, 4, 6, 3, 7, 0]);
        assert!(smallest(&e, 0).is_empty());
        let mut r = crate::rng::Rng::new(8);
        let big: Vec<f64> = (0..5000).map(|_| (r.below(50) as f64) / 7.0).collect();
        let mut want: Vec<usize> = (0..big.len()).collect();
        want.sort_by(|&a, &b| big[a].total_cmp(&big[b]).then(a.cmp(&b)));
        want.truncate(300);
        assert_eq!(smallest(&big, 300), want);
        // Both paths, the one pass for small n and the n-th value's for larger n (many ties,
        // signed zeros, NaN and infinities), give what sorting every index gives.
        let odd = [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, -0.0, 0.0];
        for seed in 0..20 {
            let mut r = crate::rng::Rng::new(seed);
            let v: Vec<f64> = (0..1040)
                .map(|_| match r.below(40) {
                    k @ 0..=4 => odd[k as usize],
                    k => (k as f64) / 9.0 - 1.0,
                })
                .collect();
            let mut all: Vec<usize> = (0..v.len()).filter(|&i| v[i].is_finite()).collect();
            all.sort_by(|&a, &b| v[a].total_cmp(&v[b]).then(a.cmp(&b)));
            for n in [1, 8, 32, 33, 100, 700] {
                assert_eq!(smallest(&v, n), all[..n], "seed {seed}, n {n}");
            }
        }
    }

    #[test]
    fn interleave_takes_both_rankings_in_turn_without_repeats() {
        assert_eq!(
            interleave(&[&[3, 1, 4, 5], &[1, 9, 2]], 5),
            vec![3, 1, 9, 4, 2]
        );
        // A shorter ranking runs out; the longer one fills the rest.
        assert_eq!(interleave(&[&[7], &[8, 9, 10]], 4), vec![7, 8, 9, 10]);
        assert_eq!(
            interleave(&[&[1, 2], &[3], &[4, 5]], 5),
            vec![1, 3, 4, 2, 5]
        );
        assert_eq!(interleave(&[&[1, 2], &[2, 1]], 10), vec![1, 2]);
        assert!(interleave(&[&[], &[]], 3).is_empty());
    }

    /// A random compressed search drawn with `seed`: `np` samples with weights, `targets`
    /// targets, `c` representatives' values and `items` items' CX weights (some negative).
    #[allow(clippy::type_complexity)]
    fn random_search(
        seed: u64,
        np: usize,
        targets: usize,
        c: usize,
        items: usize,
    ) -> (Samples, Vec<Vec<f64>>, Vec<Vec<f64>>, Vec<f32>) {
        let mut rng = crate::rng::Rng::new(seed);
        let s = Samples {
            pairs: (0..np).map(|_| (0, Vec3::Z)).collect(),
            lights: vec![Vec3::Z],
            weights: (0..np).map(|_| rng.range(0.5, 2.0)).collect(),
        };
        let ts = (0..targets)
            .map(|_| (0..np).map(|_| rng.uniform()).collect())
            .collect();
        let a = (0..c)
            .map(|_| (0..np).map(|_| rng.uniform()).collect())
            .collect();
        let x = (0..items * c)
            .map(|_| rng.range(-0.5, 1.0) as f32)
            .collect();
        (s, ts, a, x)
    }

    #[test]
    fn search_errors_multi_serves_every_target_as_a_search_of_its_own_would() {
        let items = SEARCH_BLOCK + 11;
        let (s, ts, a, x) = random_search(5, 16, 3, 4, items);
        // Small budget: Gram bounds, each target's best rescored, rescored items exact for all.
        let rescore = 100;
        let multi = search_errors_multi(&s, &ts, &a, &x, items, rescore, items * 3, false);
        assert_eq!(multi.len(), ts.len());
        for (t, m) in ts.iter().zip(&multi) {
            let one = search_errors(&s, t, &a, &x, items, rescore);
            for j in 0..items {
                // Never above its own search's value (up to the f32 Gram bound's rounding);
                // equal wherever that search rescored.
                assert!(m[j] <= one[j] + 1e-5, "item {j}: {} > {}", m[j], one[j]);
            }
            for j in smallest(&one, rescore) {
                assert!((m[j] - one[j]).abs() < 1e-12, "item {j}");
            }
        }
        // A budget covering the library: clamped everywhere, as one search of each.
        let all = search_errors_multi(&s, &ts, &a, &x, 200, 100, 600, false);
        for (t, m) in ts.iter().zip(&all) {
            let one = search_errors(&s, t, &a, &x, 200, 200);
            assert!(m.iter().zip(&one).all(|(p, q)| (p - q).abs() < 1e-12));
        }
    }

    #[test]
    fn a_bounded_scan_ranks_its_best_entries_as_a_full_scan_does() {
        // 40 representatives: the bounds read the first 16 rows of the factor, the scores all.
        let items = 3 * SEARCH_BLOCK + 7;
        let (keep, rescore) = (300, 60);
        assert!(prunes(items, keep, rescore));
        let (s, ts, a, x) = random_search(11, 64, 3, 40, items);
        let one = std::slice::from_ref(&ts[0]);
        let f = search_errors_multi(&s, one, &a, &x, items, rescore, items, false).remove(0);
        let p = search_errors_multi(&s, one, &a, &x, items, rescore, keep, false).remove(0);
        // The same best items, with the same errors (up to the f32 products' order).
        let best = smallest(&f, keep);
        assert_eq!(smallest(&p, keep), best);
        assert_eq!(smallest(&p, rescore), smallest(&f, rescore));
        for &j in &best {
            assert!((p[j] - f[j]).abs() < 1e-6, "item {j}: {} vs {}", p[j], f[j]);
        }
        // Every other item holds its error or a bound below it, above the best; most are
        // bounds (the items passed over).
        let worst = best.iter().map(|&j| f[j]).fold(0.0, f64::max);
        let mut bounded = 0;
        for (j, (&pv, &fv)) in p.iter().zip(&f).enumerate() {
            assert!(pv <= fv + 1e-6, "item {j}: bound {pv} over error {fv}");
            if !best.contains(&j) {
                assert!(pv > worst, "item {j}: {pv} not above the best ({worst})");
            }
            bounded += usize::from(pv < fv - 1e-6);
        }
        assert!(bounded > items / 2, "{bounded} bounds");
        // Several targets: every item scored, whatever `keep`.
        let full = search_errors_multi(&s, &ts, &a, &x, items, rescore, 3 * items, false);
        let part = search_errors_multi(&s, &ts, &a, &x, items, rescore, keep, false);
        assert_eq!(full, part);
    }

    #[test]
    fn any_brightness_search_errors_fit_the_brightness_within_its_range() {
        let (np, c, items) = (16, 4, SEARCH_BLOCK + 5);
        let (s, _, a, x) = random_search(7, np, 1, c, items);
        let j = 3;
        // Item j's clamped reconstruction, scaled by `f`.
        let scaled = |f: f64| -> Vec<f64> {
            (0..np)
                .map(|p| {
                    let v: f64 = (0..c).map(|k| a[k][p] * x[j * c + k] as f64).sum();
                    f * v.max(0.0)
                })
                .collect()
        };
        // Every item rescored (clamped): at a third of the brightness the item fits exactly;
        // at an eighth the scale stops at a quarter, twice the target (error 1).
        for (f, want) in [(1.0 / 3.0, 0.0), (1.0 / 8.0, 1.0)] {
            let t = scaled(f);
            // Every item scored and rescored, at brightness 1 or at the best.
            let all = |anyb| {
                let ts = std::slice::from_ref(&t);
                search_errors_multi(&s, ts, &a, &x, items, items, items, anyb).remove(0)
            };
            let (one, any) = (all(false), all(true));
            assert!((any[j] - want).abs() < 1e-6, "{f}: {}", any[j]);
            assert!((one[j] - (1.0 / f - 1.0)).abs() < 1e-6, "{f}: {}", one[j]);
            // Brightness 1 is one of the scales tried: never worse (up to the f32 sums'
            // rounding, about 1e-7).
            assert!(any.iter().zip(&one).all(|(p, q)| *p <= q + 1e-6));
        }
        // Through the Gram bound too (a small rescore): item j ranks first.
        let t = scaled(0.5);
        let any = search_errors_multi(&s, &[t], &a, &x, items, 10, items, true).remove(0);
        assert_eq!(smallest(&any, 1), vec![j]);
    }

    #[test]
    fn the_banded_gram_factor_gives_each_items_quadratic_term() {
        // 70 representatives: three bands (32, 32, 6), one a copy of another (a Gram matrix
        // without an exact factor; the ridge gives it one).
        let (np, c, n) = (120, 70, 9);
        let (_, _, mut a, x) = random_search(5, np, 1, c, n);
        a[69] = a[3].clone();
        let aw = faer::Mat::<f64>::from_fn(np, c, |p, k| a[k][p]);
        let q = aw.transpose() * &aw;
        let r = gram_factor(q.as_ref()).expect("a factor");
        let y = triangular_times(r.as_ref(), faer::MatRef::from_column_major_slice(&x, c, n));
        for j in 0..n {
            let xj = &x[j * c..(j + 1) * c];
            let want: f64 = (0..c)
                .flat_map(|i| (0..c).map(move |k| (i, k)))
                .map(|(i, k)| xj[i] as f64 * q[(i, k)] * xj[k] as f64)
                .sum();
            let got = crate::fastmath::dot(y.col_as_slice(j), y.col_as_slice(j));
            // f32 products over 70 terms: relative rounding about 1e-6.
            assert!(
                (got - want).abs() < 1e-5 * want,
                "item {j}: {got} vs {want}"
            );
        }
        // A zero or non-finite Gram matrix has no factor: the scan then uses it as it is.
        assert!(gram_factor(faer::Mat::<f64>::zeros(4, 4).as_ref()).is_none());
        let mut bad = q.clone();
        bad[(0, 0)] = f64::NAN;
        assert!(gram_factor(bad.as_ref()).is_none());
    }

    #[test]
    fn search_errors_are_clamped_for_the_best_and_bounded_for_the_rest() {
        let (np, c, items) = (20, 3, SEARCH_BLOCK + 37);
        let (s, ts, a, x) = random_search(3, np, 1, c, items);
        let t = ts[0].clone();
        // Item j's reconstruction, unclamped and clamped at zero.
        let recon = |j: usize| -> (Vec<f64>, Vec<f64>) {
            let f: Vec<f64> = (0..np)
                .map(|p| (0..c).map(|k| a[k][p] * x[j * c + k] as f64).sum::<f64>())
                .collect();
            let clamped = f.iter().map(|v| v.max(0.0)).collect();
            (f, clamped)
        };
        let e = search_errors(&s, &t, &a, &x, items, SEARCH_RESCORE);
        assert_eq!(e.len(), items);
        // Each item has its clamped error (up to the f32 reconstruction's rounding, about 1e-7)
        // or, outside the best SEARCH_RESCORE, the unclamped one from the f32 Gram product: an
        // upper bound up to f32 rounding.
        let mut rescored = 0;
        for (j, &ej) in e.iter().enumerate() {
            let (f, clamped) = recon(j);
            let (ec, eu) = (s.rel_error(&t, &clamped), s.rel_error(&t, &f));
            if (ej - ec).abs() < 1e-6 {
                rescored += 1;
            } else {
                assert!((ej - eu).abs() < 1e-5, "item {j}: {ej} vs {ec} / {eu}");
            }
            assert!(ej >= ec - 1e-5, "item {j}");
        }
        assert!(rescored >= SEARCH_RESCORE, "{rescored}");
        // A smaller share rescores fewer: the items it leaves hold the (larger) Gram bound.
        let share = rescore_share(8, 64);
        assert_eq!(share, SEARCH_RESCORE / 8);
        assert_eq!(rescore_share(1000, 64), 64);
        let e8 = search_errors(&s, &t, &a, &x, items, share);
        let clamped_now = (0..items)
            .filter(|&j| (e8[j] - s.rel_error(&t, &recon(j).1)).abs() < 1e-6)
            .count();
        assert!(
            clamped_now >= share && clamped_now < rescored,
            "{clamped_now} {rescored}"
        );
        assert!((0..items).all(|j| e8[j] >= e[j] - 1e-5));
        // A library within SEARCH_RESCORE items gets the clamped error everywhere, and some of
        // these items do reconstruct below zero somewhere (so the clamp is exercised).
        let small = search_errors(&s, &t, &a, &x, 100, SEARCH_RESCORE);
        assert!((0..100).any(|j| recon(j).0.iter().any(|v| *v < 0.0)));
        for (j, &sj) in small.iter().enumerate() {
            let f = recon(j).1;
            assert!((sj - s.rel_error(&t, &f)).abs() < 1e-6, "item {j}");
        }
    }
}
