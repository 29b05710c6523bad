//! The material solver (Sec. 4.2): the geometry is fixed; search the material library.
//!
//! The geometry's light lobes ([`crate::lightlobes`]: the library's stored record for a library
//! geometry, else built once from its heightfield) give, at every sample, a few vMF lobes; `fbar` of a material is
//! then `Σ_c w_c F(κ_c, μ_c)` of its prefiltered table (Eq. 6). That is evaluated for the
//! representative materials only; every material's value is representatives × CX weights. The
//! representatives are the library's finer search selection (`material/search-*.bsa`) when it
//! has one, else its CX representatives. The score adds the colour term of Eq. 13:
//! `(1 - β) e² + β |λ̂ - λ|² / |λ̂|²` with `e` the relative error and `λ` the material's average
//! colour under its best colour shift.

use super::geometry::{narrow, COARSE_KEEP};
use super::{
    exact_values, fast_values, rotated_samples, search_errors, smallest, Candidate, Final, Look,
    SolveOptions, SolveResult, SolveStats, LIGHT_LOBE_RAYS, SEARCH_RESCORE,
};
use crate::bvndf::LobeSource;
use crate::error::Result;
use crate::heightfield::Heightfield;
use crate::library::Library;
use crate::lightlobes::LightLobes;
use crate::material::{parse_material, Material};
use crate::prefilter::Prefiltered;
use rayon::prelude::*;
use std::time::Instant;

/// The best colour shift of material `m` for a target colour: `(shift index, colour, distance²
/// relative to |λ̂|²)`.
pub(super) fn best_colour(
    base: [f32; 3],
    shifts: &[f32],
    target: Option<[f64; 3]>,
) -> (usize, [f64; 3], f64) {
    let own = [base[0] as f64, base[1] as f64, base[2] as f64];
    let Some(t) = target else {
        return (0, own, 0.0);
    };
    let tn: f64 = t.iter().map(|x| x * x).sum::<f64>().max(1e-12);
    let mut best = (0, own, f64::INFINITY);
    for (s, c) in shifts.chunks(3).enumerate() {
        let col = [
            own[0] * c[0] as f64,
            own[1] * c[1] as f64,
            own[2] * c[2] as f64,
        ];
        let d: f64 = (0..3).map(|i| (col[i] - t[i]).powi(2)).sum::<f64>() / tn;
        if d < best.2 {
            best = (s, col, d);
        }
    }
    best
}

/// Solve for the material on the fixed geometry `hf` (rotated by `psi_deg`: the samples are read
/// in the rotated frame). `geometry_label` names it in the results. With `geometry_index`, `hf`
/// is that library geometry and its stored light lobes are used; without, they are built from
/// `hf` ([`LIGHT_LOBE_RAYS`] rays per view node).
pub fn solve(
    lib: &Library,
    look: &Look,
    hf: &Heightfield,
    geometry_label: &str,
    geometry_index: Option<usize>,
    psi_deg: f64,
    opt: &SolveOptions,
) -> Result<SolveResult> {
    let mut stats = SolveStats::default();
    let t0 = Instant::now();
    let items = lib.material_items()?;
    // The finer selection for this search when the library has one (the coarse set serves the
    // joint search, whose cost grows with its square).
    let prefix = if lib.has("material/search-x.bsa") {
        "material/search-"
    } else {
        "material/"
    };
    let reps = lib.array(&format!("{prefix}representatives.bsa"))?;
    let xs = lib.array(&format!("{prefix}x.bsa"))?;
    let colours = lib.array("material/colour.bsa")?;
    let shifts = lib.array("material/colour-shifts.bsa")?;
    let (reps, xs, colours, shifts) = (reps.u32s()?, xs.f32s()?, colours.f32s()?, shifts.f32s()?);
    let ns = lib.manifest.colours_per_material * 3;
    let layout = lib.gamma_layout();
    let (samples, target) =
        rotated_samples(look, &layout.lights, psi_deg.to_radians(), &opt.sampling);
    let stored;
    let geo: Box<dyn LobeSource + Sync> = match geometry_index {
        Some(j) => {
            stored = lib.geometry_lobes()?;
            Box::new(stored.get(j)?)
        }
        None => Box::new(LightLobes::build(
            &layout,
            hf,
            LIGHT_LOBE_RAYS,
            lib.profile.geometry.lobe_clusters,
        )),
    };
    // The geometry is fixed: its lobes at the samples are assembled once for every material.
    let fixed = crate::fast::FixedLobes::new(geo.as_ref(), &super::dir_pairs(&samples));
    let prefiltered = |m: usize| -> Result<Prefiltered> {
        super::material_prefiltered(lib, &parse_material(&items[m].spec)?, Some(m))
    };
    let a: Vec<Vec<f64>> = reps
        .par_iter()
        .map(|&k| Ok(fixed.fbar(&prefiltered(k as usize)?)))
        .collect::<Result<_>>()?;
    let e = search_errors(&samples, &target, &a, xs, items.len(), SEARCH_RESCORE);
    let beta = opt.beta.clamp(0.0, 1.0);
    let score = |m: usize, e: f64| {
        let (s, col, d) = best_colour(
            [colours[3 * m], colours[3 * m + 1], colours[3 * m + 2]],
            &shifts[m * ns..(m + 1) * ns],
            look.colour,
        );
        ((1.0 - beta) * e * e + beta * d, s, col)
    };
    let scores: Vec<f64> = e.iter().enumerate().map(|(m, &e)| score(m, e).0).collect();
    stats.items_searched = items.len();
    stats.representatives = reps.len();
    stats.search_seconds = t0.elapsed().as_secs_f64();
    // Stage 2: each pooled material's own table.
    let t1 = Instant::now();
    // The compressed search ranks sharp materials on rough surfaces poorly (the 14 CX
    // representatives of `paper4`: originals past the 64th, some past the 520th; the 25 of the
    // search selection at 99.999 %: none past the 260th in 200 cases), so the pool is large
    // (`auto_pool`) and narrowed first by the geometry solver's coarse passes (each ranks by
    // the score at every `step`-th sample and keeps its best quarter), which makes it cheap.
    let pool = smallest(&scores, opt.pool_for(items.len()));
    let pool = narrow(
        pool,
        COARSE_KEEP.max(opt.k),
        samples.pairs.len(),
        |pool, step| {
            let (s, t) = samples.every(step, &target);
            let f = fixed.every(step);
            pool.par_iter()
                .map(|&m| Ok(score(m, s.rel_error(&t, &f.fbar(&prefiltered(m)?))).0))
                .collect()
        },
    )?;
    let mut reranked: Vec<(f64, f64, usize)> = pool
        .par_iter()
        .map(|&m| {
            let v = fixed.fbar(&prefiltered(m)?);
            let re = samples.rel_error(&target, &v);
            Ok((score(m, re).0, re, m))
        })
        .collect::<Result<_>>()?;
    reranked.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.2.cmp(&b.2)));
    reranked.truncate(opt.k.max(1));
    stats.rerank_seconds = t1.elapsed().as_secs_f64();
    // Stage 3.
    let t2 = Instant::now();
    let mats: Vec<Material> = reranked
        .iter()
        .map(|r| parse_material(&items[r.2].spec))
        .collect::<Result<_>>()?;
    let finals: Vec<Vec<f64>> = match opt.final_eval {
        Final::Library => Vec::new(),
        Final::Exact => {
            // Every material is shaded on the same rays: one count per pair and end.
            let refs: Vec<&Material> = mats.iter().collect();
            let bar = super::final_bar(opt, 1, samples.pairs.len());
            let v = exact_values(hf, &refs, &samples, opt.exact_samples, &bar);
            bar.finish();
            v
        }
        Final::Fast => {
            // The forward model's full compact BVNDF, as the other solvers' fast final stage.
            let full = super::bvndf_of(hf);
            reranked
                .iter()
                .map(|r| Ok(fast_values(&full, &prefiltered(r.2)?, &samples)))
                .collect::<Result<_>>()?
        }
    };
    let mut out: Vec<(f64, Candidate)> = reranked
        .iter()
        .enumerate()
        .map(|(i, &(_, re, m))| {
            let err = finals
                .get(i)
                .map(|v| samples.rel_error(&target, v))
                .unwrap_or(re);
            let (sc, s, col) = score(m, err);
            (
                sc,
                Candidate {
                    geometry: geometry_index,
                    geometry_spec: geometry_label.to_string(),
                    material: Some(m),
                    material_spec: items[m].spec.clone(),
                    psi_deg,
                    colour_shift: Some(s),
                    colour: col,
                    search_error: e[m],
                    rerank_error: re,
                    error: err,
                    evaluated_by: opt.final_eval,
                },
            )
        })
        .collect();
    // Sorted by the Eq. 13 score (the error alone when beta = 0).
    out.sort_by(|a, b| a.0.total_cmp(&b.0));
    let out: Vec<Candidate> = out.into_iter().map(|x| x.1).collect();
    stats.final_seconds = t2.elapsed().as_secs_f64();
    Ok(SolveResult {
        candidates: out,
        stats,
    })
}

/// The `n` library materials that best reproduce the look on a flat patch (the look taken as a
/// plain BRDF), best first, with the solve's statistics: a start of the general solver when the
/// joint search's pairs hold too few materials.
pub fn closest_on_flat_patch(
    lib: &Library,
    look: &Look,
    n: usize,
    opt: &SolveOptions,
) -> Result<(Vec<usize>, SolveStats)> {
    let flat = Heightfield::flat(16, 16);
    let o = SolveOptions {
        k: n.max(1),
        pool: opt.pool_for(lib.manifest.materials).max(n),
        final_eval: Final::Library,
        ..opt.clone()
    };
    let r = solve(lib, look, &flat, "flat", None, 0.0, &o)?;
    Ok((
        r.candidates.iter().filter_map(|c| c.material).collect(),
        r.stats,
    ))
}
