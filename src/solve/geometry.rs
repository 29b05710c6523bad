//! The geometry solver (Sec. 4.1): the material is fixed; search the geometry library.
//!
//! Every rotation `psi_i` of the target gets its own samples (for stages 2 and 3). Stage 1
//! compares all rotations at one shared set, rotation 0's ([`search_errors_multi`]): evaluate
//! the representatives' `fbar` there once, with their light lobes ([`crate::lightlobes`], stored
//! in the library: nothing is rebuilt) and the material's prefiltered table, and get every
//! geometry's approximate `fbar` as representatives × CX weights (Eq. 12: `fbar` is linear in
//! the binned BVNDF the CX weights were fitted to, so any accurate evaluation of the
//! representatives may be combined), compared with each rotated target's values there. Stage 1
//! also ranks by the representatives' binned columns with the material's response (the linear
//! model the weights were fitted to) and, when the library has them, by the representatives'
//! light-lobe values with the weights refitted to them ([`crate::library::lobefit`]); the pool
//! of `pool` (geometry, rotation) pairs takes the best of the rankings in turn: where an item's
//! large weights amplify the difference between light lobes and binned columns, one ranking
//! misses it and another does not. The
//! pool's pairs are re-ranked with their own light lobes (a pool over [`COARSE_KEEP`] narrowed
//! first by coarse passes, each keeping its best quarter at a quarter of the next pass's
//! samples, [`coarse_step`]), and the best `k` geometries — each once, at its best rotation —
//! evaluated with the fast or exact evaluator. With
//! `rerank_fast = false` both stages use the binned columns instead (the material's
//! [`Response`]), for comparison.

use super::joint::RepPairs;
use super::{
    bvndf_of, dir_pairs, exact_values, fast_values, interleave, library_heightfield,
    material_prefiltered, psi_angle, rescore_share, rotated_samples, search_errors_multi, smallest,
    Candidate, Final, Look, SolveOptions, SolveResult, SolveStats,
};
use crate::error::Result;
use crate::gamma::Response;
use crate::library::build::prefilter_config;
use crate::library::GeometryLobes;
use crate::library::Library;
use crate::lightlobes::LightPairs;
use crate::material::Material;
use crate::prefilter::{PrefilterConfig, Prefiltered};
use crate::sampling::Samples;
use rayon::prelude::*;
use std::time::Instant;

struct Rotation {
    psi: f64,
    samples: Samples,
    /// The samples' pairs placed in the light-lobe table once, for every geometry.
    at: LightPairs,
    target: Vec<f64>,
    /// The material's response to binned columns (only when the search uses them).
    response: Option<Response>,
}

/// What stages 1 and 2 evaluate library geometries with. One per solve, so the size of the
/// larger variant costs nothing worth a box.
#[allow(clippy::large_enum_variant)]
enum ItemData {
    Lobes {
        lobes: GeometryLobes,
        pf: Prefiltered,
    },
    Binned(crate::library::BinnedColumns),
}

impl ItemData {
    /// `fbar` of library geometry `j` at rotation `r`'s samples.
    fn values(&self, j: usize, r: &Rotation) -> Result<Vec<f64>> {
        match (self, &r.response) {
            (ItemData::Lobes { lobes, pf }, _) => Ok(lobes.get(j)?.fbar(pf, &r.at)),
            (ItemData::Binned(gamma), Some(resp)) => gamma.respond(resp, j),
            (ItemData::Binned(gamma), None) => Err(crate::error::Error::new(
                gamma.file.path.display().to_string(),
                "internal: binned search without a material response",
            )),
        }
    }
}

/// A pooled (geometry, rotation) after stage 2.
#[derive(Debug, Clone, Copy)]
struct Reranked {
    /// The error it is ranked by: at the best brightness with
    /// [`SolveOptions::any_brightness`], else `own`.
    rank: f64,
    /// Stage 1's error.
    search: f64,
    geometry: usize,
    rotation: usize,
    /// The error at the material's own brightness.
    own: f64,
}

/// Stage 2 narrows a pool larger than this by coarse passes, each keeping its best quarter
/// (at least this many), and evaluates what is left at every sample.
pub const COARSE_KEEP: usize = 32;

/// Stage 2 re-ranks further pools ([`SolveOptions::widen`]) while its best is over this relative
/// error: 1 %, the general solver's stopping rule ([`super::general::STOP_BELOW`]).
pub const WIDEN_ABOVE: f64 = super::general::STOP_BELOW;

/// A further pool is kept only when its best is below this fraction of the best before it
/// (half): a geometry that halves the error is a different answer, a smaller gain is within
/// what the library's data and the full forward model disagree by for sharp materials.
pub const WIDEN_GAIN: f64 = 0.5;

/// Further pools stage 2 may re-rank by default: the pool at most four times over.
pub const WIDEN: usize = 3;

/// Each coarse pass keeps a quarter of the pool, and uses a quarter of the next pass's samples.
pub const COARSE_STEP: usize = 4;

/// The fewest samples a coarse pass compares at (about 16: at most every 30th of 490).
pub const COARSE_MIN_SAMPLES: usize = 16;

/// The sample stride of the coarse pass over a pool of `n` (narrowed to `floor` in the end) at
/// `samples` samples: `COARSE_STEP` to the number of passes still to run, so that every pass
/// costs about the same (a quarter of the items at four times the samples), but never fewer
/// than [`COARSE_MIN_SAMPLES`] samples.
pub fn coarse_step(n: usize, floor: usize, samples: usize) -> usize {
    let (mut n, mut step) = (n, 1);
    // The passes still to run, each keeping a quarter (at least `floor`), as the solver does.
    while n > floor.max(1) {
        n = (n / COARSE_STEP).max(floor.max(1));
        step *= COARSE_STEP;
    }
    step.min((samples / COARSE_MIN_SAMPLES).max(1))
}

/// Narrow `pool` to at most `floor` entries by coarse passes over `samples` samples:
/// `errors(pool, step)` gives each entry's error (in `pool`'s order) at every `step`-th
/// sample, and each pass keeps the best quarter (at least `floor`). A pass whose samples are
/// the pass before's (both held at [`COARSE_MIN_SAMPLES`]) is not evaluated again: its errors
/// are the kept entries' own from before, and it keeps their best quarter, the same entries in
/// the same order.
pub fn narrow<T: Copy>(
    mut pool: Vec<T>,
    floor: usize,
    samples: usize,
    errors: impl Fn(&[T], usize) -> Result<Vec<f64>>,
) -> Result<Vec<T>> {
    let floor = floor.max(1);
    // The last pass's step and its kept entries' errors, in `pool`'s order.
    let mut last: Option<(usize, Vec<f64>)> = None;
    while pool.len() > floor {
        let step = coarse_step(pool.len(), floor, samples);
        let errs = match last.take() {
            Some((s, errs)) if s == step => errs,
            _ => errors(&pool, step)?,
        };
        let keep = (pool.len() / COARSE_STEP).max(floor);
        let best = smallest(&errs, keep);
        pool = best.iter().map(|&i| pool[i]).collect();
        last = Some((step, best.iter().map(|&i| errs[i]).collect()));
    }
    Ok(pool)
}

/// Solve for the geometry with `material` fixed. `material_label` names it in the results.
pub fn solve(
    lib: &Library,
    look: &Look,
    material: &Material,
    material_label: &str,
    material_index: Option<usize>,
    opt: &SolveOptions,
) -> Result<SolveResult> {
    solve_with(
        lib,
        look,
        material,
        material_label,
        material_index,
        opt,
        None,
    )
}

/// [`solve`], with the representatives' values taken from a joint search's representative pairs
/// when the material is a library material (stage 1 then evaluates nothing; stages 2 and 3 use
/// the material's own table as always). The joint search's shared samples are rotation 0's, as
/// stage 1's here, when both use the same sampling settings.
pub fn solve_with(
    lib: &Library,
    look: &Look,
    material: &Material,
    material_label: &str,
    material_index: Option<usize>,
    opt: &SolveOptions,
    reps_values: Option<&RepPairs>,
) -> Result<SolveResult> {
    let mut stats = SolveStats::default();
    let t0 = Instant::now();
    let items = lib.geometry_items()?;
    let layout = lib.gamma_layout();
    let reps = lib.array("geometry/representatives.bsa")?;
    let xs = lib.array("geometry/x.bsa")?;
    // The weights refitted to the light lobes (`library::lobefit`), when the library has them:
    // the third ranking of stage 1.
    let xl = lib
        .has("geometry/x-lobes.bsa")
        .then(|| lib.array("geometry/x-lobes.bsa"));
    let xl = xl.transpose()?;
    let (reps, xs) = (reps.u32s()?, xs.f32s()?);
    let xl = xl.as_ref().map(|f| f.f32s()).transpose()?;
    // The item data of stages 1 and 2: light lobes with the material's prefiltered table, or
    // (`rerank_fast = false`, for comparison) binned columns with the material's response.
    let data = if opt.rerank_fast {
        ItemData::Lobes {
            lobes: lib.geometry_lobes()?,
            pf: material_prefiltered(lib, material, material_index)?,
        }
    } else {
        ItemData::Binned(lib.binned_columns()?)
    };
    let rots: Vec<Rotation> = (0..opt.psi.max(1))
        .map(|i| {
            let psi = psi_angle(i, opt.psi);
            let (samples, target) = rotated_samples(look, &layout.lights, psi, &opt.sampling);
            let response = match data {
                ItemData::Binned(_) => Some(Response::new(&layout, material, &samples.pairs)),
                ItemData::Lobes { .. } => None,
            };
            Rotation {
                psi,
                at: LightPairs::new(&layout, dir_pairs(&samples)),
                samples,
                target,
                response,
            }
        })
        .collect();
    // Stage 1: representatives' `fbar` × X for every geometry and rotation (Eq. 12), every
    // rotation compared at one shared sample set, rotation 0's: the representatives' values,
    // the material's response and each item's Gram term are then computed once, and a
    // rotation adds only its target values and one dot product per item. Stage 2 compares
    // at each rotation's own samples.
    let shared = &rots[0].samples;
    let targets: Vec<Vec<f64>> = rots
        .iter()
        .enumerate()
        .map(|(ri, r)| {
            if ri == 0 {
                r.target.clone()
            } else {
                shared.values(&look.as_fn(), r.psi)
            }
        })
        .collect();
    let pool_size = opt.geometry_pool_for(items.len());
    // Stages 1 and 2 rank at the best brightness when asked; the candidates' errors are at the
    // material's own.
    let anyb = opt.any_brightness;
    let rescore = rescore_share(rots.len(), pool_size);
    // The representatives' values at the shared samples: from the joint search's
    // representative pairs when given (and drawn with the same settings: as many samples),
    // else evaluated representative by representative.
    let a: Vec<Vec<f64>> = match (reps_values, material_index, &data) {
        (Some(rp), Some(m), ItemData::Lobes { .. }) => rp.values(m),
        _ => None,
    }
    .filter(|v| v.iter().all(|r| r.len() == shared.pairs.len()))
    .map_or_else(
        || {
            reps.par_iter()
                .map(|&k| data.values(k as usize, &rots[0]))
                .collect::<Result<Vec<_>>>()
        },
        Ok,
    )?;
    // The rankings reach as deep as the widened pools may go; the first `pool_size` of their
    // interleaving are the pool either way (each ranking is a prefix of a deeper one).
    let depth = pool_size.saturating_mul(1 + opt.widen);
    let n = items.len();
    // The three rankings run side by side: each scan's serial parts (the selections, the
    // material's response) overlap the others' products.
    // Each ranking's errors, rotation-major (entry `ri · n + j` is item `j` at rotation `ri`):
    // exact for its best `depth` entries, elsewhere a bound above them (`search_errors_multi`).
    let (first, (binned, refit)) = rayon::join(
        || search_errors_multi(shared, &targets, &a, xs, n, rescore, depth, anyb).concat(),
        || {
            rayon::join(
                // The second ranking: the representatives' binned columns with the material's
                // response, the linear model the CX weights were fitted to (same (rotation,
                // item) layout).
                || -> Result<Option<Vec<f64>>> {
                    let (ItemData::Lobes { pf, .. }, true) = (&data, opt.binned_search) else {
                        return Ok(None);
                    };
                    let gamma = lib.binned_columns()?;
                    let resp = Response::with_table(&layout, material, pf, &shared.pairs);
                    let b: Vec<Vec<f64>> = reps
                        .par_iter()
                        .map(|&k| gamma.respond(&resp, k as usize))
                        .collect::<Result<_>>()?;
                    Ok(Some(
                        search_errors_multi(shared, &targets, &b, xs, n, rescore, depth, anyb)
                            .concat(),
                    ))
                },
                // The third: the representatives' light-lobe values with the weights refitted
                // to them.
                || match (&data, xl) {
                    (ItemData::Lobes { .. }, Some(xl)) => Some(
                        search_errors_multi(shared, &targets, &a, xl, n, rescore, depth, anyb)
                            .concat(),
                    ),
                    _ => None,
                },
            )
        },
    );
    let errors: Vec<Vec<f64>> = std::iter::once(first).chain(binned?).chain(refit).collect();
    let rankings: Vec<Vec<usize>> = errors.par_iter().map(|e| smallest(e, depth)).collect();
    // An entry's stage-1 error: the least of the rankings' that hold it among their best (every
    // pooled entry is among some ranking's best).
    let mut stage1 = vec![f64::INFINITY; n * rots.len()];
    for (e, r) in errors.iter().zip(&rankings) {
        for &i in r {
            stage1[i] = stage1[i].min(e[i]);
        }
    }
    let scored = |i: usize| (stage1[i], i % n, i / n);
    let refs: Vec<&[usize]> = rankings.iter().map(|r| r.as_slice()).collect();
    let order = interleave(&refs, depth);
    stats.items_searched = items.len() * rots.len();
    stats.representatives = reps.len();
    stats.search_seconds = t0.elapsed().as_secs_f64();
    // Stage 2: each pooled geometry's own data.
    let t1 = Instant::now();
    // A large pool is narrowed by successive coarse passes (each ranks the pool at every
    // `step`-th sample and keeps its best quarter), until at most COARSE_KEEP are left for
    // every sample — or `k` per rotation: the pool holds (geometry, rotation) pairs and the
    // answers are `k` different geometries, which up to `k × psi` pairs may take.
    let rerank = |pool: &[usize]| -> Result<Vec<Reranked>> {
        let pool = match &data {
            ItemData::Lobes { lobes, pf } => {
                // The pool's records, asked for at once: from a library larger than memory
                // the disk then serves them together rather than one fault at a time.
                let js: Vec<usize> = pool.iter().map(|&i| scored(i).1).collect();
                lobes.will_need(&js);
                narrow(
                    pool.to_vec(),
                    COARSE_KEEP.max(opt.k * rots.len()),
                    rots[0].samples.pairs.len(),
                    |pool, step| {
                        let coarse: Vec<_> = rots
                            .iter()
                            .map(|r| {
                                super::coarse_at(&layout, &r.samples, &r.target, look, r.psi, step)
                            })
                            .collect();
                        pool.par_iter()
                            .map(|&i| {
                                let (_, j, ri) = scored(i);
                                let (s, t, at) = &coarse[ri];
                                Ok(s.rel_error_scaled(t, &lobes.get(j)?.fbar(pf, at), anyb))
                            })
                            .collect()
                    },
                )?
            }
            ItemData::Binned { .. } => pool.to_vec(),
        };
        pool.par_iter()
            .map(|&i| {
                let (se, j, ri) = scored(i);
                let r = &rots[ri];
                let v = data.values(j, r)?;
                let own = r.samples.rel_error(&r.target, &v);
                let ranked = if anyb {
                    r.samples.rel_error_scaled(&r.target, &v, true)
                } else {
                    own
                };
                Ok(Reranked {
                    rank: ranked,
                    search: se,
                    geometry: j,
                    rotation: ri,
                    own,
                })
            })
            .collect()
    };
    let best_of = |r: &[Reranked]| r.iter().map(|x| x.rank).fold(f64::INFINITY, f64::min);
    let extent =
        |e: usize| &order[(e * pool_size).min(order.len())..((e + 1) * pool_size).min(order.len())];
    let mut reranked = rerank(extent(0))?;
    // Widening: the next pools of the rankings while the best is not yet close and each further
    // pool found a decisively better geometry (a sharp material's reconstruction from the
    // representatives can rank the right geometry past the pool). A pool that does not is
    // dropped whole: a small gain is within what the library's data and the full model
    // disagree by, and taking it would trade the pool's answer for a worse one.
    let mut best = best_of(&reranked);
    let (mut extents, mut widened) = (1, 1);
    while best > WIDEN_ABOVE && extents <= opt.widen && !extent(extents).is_empty() {
        let more = rerank(extent(extents))?;
        let b = best_of(&more);
        extents += 1;
        if b >= best * WIDEN_GAIN {
            break;
        }
        widened = extents;
        reranked.extend(more);
        best = b;
    }
    if widened > 1 {
        stats.notes.push(format!(
            "geometry pool widened to {} (the best of the first {pool_size} was over {:.0} %; \
             a further pool's best was under {:.0} % of it)",
            (widened * pool_size).min(order.len()),
            100.0 * WIDEN_ABOVE,
            100.0 * WIDEN_GAIN
        ));
    } else if extents > 1 {
        stats.notes.push(format!(
            "geometry pool not widened: the next {pool_size} held nothing better than {:.0} % of \
             the pool's best",
            100.0 * WIDEN_GAIN
        ));
    }
    reranked.sort_by(|a, b| a.rank.total_cmp(&b.rank).then(a.geometry.cmp(&b.geometry)));
    // Each geometry once, at its best rotation: the K answers are K different geometries.
    let mut seen = std::collections::HashSet::new();
    reranked.retain(|r| seen.insert(r.geometry));
    reranked.truncate(opt.k.max(1));
    stats.rerank_seconds = t1.elapsed().as_secs_f64();
    // Stage 3: the final evaluator.
    let t2 = Instant::now();
    let colour = crate::library::items::average_colour(material);
    let bar = super::final_bar(
        opt,
        reranked.len(),
        rots.first().map_or(0, |r| r.samples.pairs.len()),
    );
    let mut out: Vec<Candidate> = reranked
        .par_iter()
        .map(
            |&Reranked {
                 rank: re,
                 search: se,
                 geometry: j,
                 rotation: ri,
                 own,
             }| {
                let r = &rots[ri];
                let error = match opt.final_eval {
                    Final::Library => own,
                    Final::Fast => {
                        let hf = library_heightfield(&items[j].spec)?;
                        let pf = match &data {
                            ItemData::Lobes { pf, .. } => pf.clone(),
                            ItemData::Binned { .. } => {
                                material_prefiltered(lib, material, material_index)?
                            }
                        };
                        r.samples
                            .rel_error(&r.target, &fast_values(&bvndf_of(&hf), &pf, &r.samples))
                    }
                    Final::Exact => {
                        let hf = library_heightfield(&items[j].spec)?;
                        let v = exact_values(&hf, &[material], &r.samples, opt.exact_samples, &bar)
                            .remove(0);
                        r.samples.rel_error(&r.target, &v)
                    }
                };
                Ok(Candidate {
                    geometry: Some(j),
                    geometry_spec: items[j].spec.clone(),
                    material: material_index,
                    material_spec: material_label.to_string(),
                    psi_deg: r.psi.to_degrees(),
                    colour_shift: None,
                    colour,
                    search_error: se,
                    rerank_error: re,
                    error,
                    evaluated_by: opt.final_eval,
                })
            },
        )
        .collect::<Result<_>>()?;
    bar.finish();
    // At the best brightness the order is stage 2's: the errors at the material's own
    // brightness are the answers' errors, not their ranking.
    if !anyb {
        out.sort_by(|a, b| a.error.total_cmp(&b.error));
    }
    stats.final_seconds = t2.elapsed().as_secs_f64();
    Ok(SolveResult {
        candidates: out,
        stats,
    })
}

/// The library's prefilter settings (cheap enough to build per solve).
pub fn prefilter_for(lib: &Library) -> PrefilterConfig {
    prefilter_config(&lib.profile)
}
