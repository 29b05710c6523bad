//! The geometry solver (Sec. 4.1): the material is fixed; search the geometry library.
//!
//! Per rotation `psi_i`: sample the target rotated by `psi_i`, build the material's response to
//! the binned BVNDF ([`crate::gamma::Response`]), apply it to the representatives' columns, and
//! get every geometry's approximate `fbar` as representatives × CX weights (Eq. 12). The best
//! `pool` (geometry, rotation) pairs are re-ranked with their own binned columns, and the best
//! `k` evaluated with the fast or exact evaluator.

use super::{
    bvndf_of, exact_values, fast_values, library_heightfield, psi_angle, quick_bvndf_of,
    search_errors, smallest, Candidate, Final, Look, SolveOptions, SolveResult, SolveStats,
};
use crate::error::Result;
use crate::gamma::Response;
use crate::library::build::prefilter_config;
use crate::library::Library;
use crate::material::Material;
use crate::prefilter::{PrefilterConfig, Prefiltered};
use crate::sampling::{sample, Samples};
use rayon::prelude::*;
use std::time::Instant;

struct Rotation {
    psi: f64,
    samples: Samples,
    target: Vec<f64>,
    response: Response,
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
    let mut stats = SolveStats::default();
    let t0 = Instant::now();
    let items = lib.geometry_items()?;
    let layout = lib.gamma_layout();
    let gamma = lib.array("geometry/gamma.bsa")?;
    let reps = lib.array("geometry/representatives.bsa")?;
    let xs = lib.array("geometry/x.bsa")?;
    let (gamma, reps, xs) = (gamma.f16s()?, reps.u32s()?, xs.f32s()?);
    let rows = layout.rows();
    let column = |j: usize| &gamma[j * rows..(j + 1) * rows];
    let f = look.as_fn();
    let rots: Vec<Rotation> = (0..opt.psi.max(1))
        .map(|i| {
            let psi = psi_angle(i, opt.psi);
            let rotated = |wi, wo| {
                f(
                    crate::frame::rotate_z(wi, psi),
                    crate::frame::rotate_z(wo, psi),
                )
            };
            let samples = sample(&layout.lights, &rotated, &opt.sampling);
            let target = samples.values(&f, psi);
            let response = Response::new(&layout, material, &samples.pairs);
            Rotation {
                psi,
                samples,
                target,
                response,
            }
        })
        .collect();
    // Stage 1: representatives × X for every geometry and rotation.
    let mut scored: Vec<(f64, usize, usize)> = Vec::new();
    for (ri, r) in rots.iter().enumerate() {
        let a: Vec<Vec<f64>> = reps
            .par_iter()
            .map(|&k| r.response.apply(column(k as usize)))
            .collect();
        let e = search_errors(&r.samples, &r.target, &a, xs, items.len());
        scored.extend(e.into_iter().enumerate().map(|(j, e)| (e, j, ri)));
    }
    stats.items_searched = items.len() * rots.len();
    stats.representatives = reps.len();
    stats.search_seconds = t0.elapsed().as_secs_f64();
    let errs: Vec<f64> = scored.iter().map(|s| s.0).collect();
    let pool = smallest(&errs, opt.pool.max(opt.k));
    // Stage 2: each pooled geometry's own data: a quick compact BVNDF with the fast evaluator,
    // or its binned column.
    let t1 = Instant::now();
    let quick_pf = if opt.rerank_fast {
        Some(Prefiltered::build(material, &prefilter_for(lib)))
    } else {
        None
    };
    let mut reranked: Vec<(f64, f64, usize, usize)> = pool
        .iter()
        .map(|&i| {
            let (se, j, ri) = scored[i];
            let r = &rots[ri];
            let v = match &quick_pf {
                Some(pf) => fast_values(
                    &quick_bvndf_of(&library_heightfield(&items[j].spec)?),
                    pf,
                    &r.samples,
                ),
                None => r.response.apply(column(j)),
            };
            Ok((r.samples.rel_error(&r.target, &v), se, j, ri))
        })
        .collect::<Result<_>>()?;
    reranked.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.2.cmp(&b.2)));
    reranked.truncate(opt.k.max(1));
    stats.rerank_seconds = t1.elapsed().as_secs_f64();
    // Stage 3: the final evaluator.
    let t2 = Instant::now();
    let pf = match opt.final_eval {
        Final::Fast => Some(
            quick_pf
                .clone()
                .unwrap_or_else(|| Prefiltered::build(material, &prefilter_for(lib))),
        ),
        Final::Exact | Final::Library => None,
    };
    let colour = crate::library::items::average_colour(material);
    let mut out: Vec<Candidate> = reranked
        .iter()
        .map(|&(re, se, j, ri)| {
            let r = &rots[ri];
            let error = match (opt.final_eval, &pf) {
                (Final::Library, _) => re,
                (_, Some(pf)) => {
                    let hf = library_heightfield(&items[j].spec)?;
                    r.samples
                        .rel_error(&r.target, &fast_values(&bvndf_of(&hf), pf, &r.samples))
                }
                _ => {
                    let hf = library_heightfield(&items[j].spec)?;
                    let v = exact_values(&hf, &[material], &r.samples, opt.exact_samples).remove(0);
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
        })
        .collect::<Result<_>>()?;
    out.sort_by(|a, b| a.error.total_cmp(&b.error));
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
