//! The general solver (Sec. 4.3): geometry and material both unknown. From a start (a given
//! material, the materials of the joint search's best pairs, the library material closest to
//! the look on a flat patch, then seeded random materials; and, after those, sharper versions
//! of the first start, [`sharper_material`]), alternate the material-fixed geometry solve and the
//! geometry-fixed material solve, each returning its best, until a (geometry, rotation,
//! material) repeats or the iteration limit; several starts, until the stopping rule holds;
//! the best distinct combinations of all starts are evaluated with the final evaluator.

use super::{
    exact_values, library_heightfield, Candidate, Final, Look, SolveOptions, SolveResult,
    SolveStats,
};
use crate::bvndf::CompactBvndf;
use crate::error::{Error, Result};
use crate::heightfield::Heightfield;
use crate::library::Library;
use crate::material::{parse_material, Material};
use crate::rng::Rng;
use std::collections::hash_map::{Entry, HashMap};
use std::time::Instant;

/// Settings of the alternation.
#[derive(Debug, Clone)]
pub struct GeneralOptions {
    pub starts: usize,
    pub max_iterations: usize,
    pub seed: u64,
    /// Start from this library material (index) instead of random ones (first start only).
    pub start_material: Option<usize>,
    /// Geometries of each geometry solve that get a material solve (the best pair continues).
    pub beam: usize,
    /// Pairs of the joint search ([`super::joint`]) re-ranked with their own data (more than
    /// [`super::joint::JOINT_COARSE_KEEP`] narrowed by coarse passes first); the best pairs are
    /// candidates and their distinct materials the starts. 0 = no joint search (flat-patch and
    /// random starts).
    pub joint_pool: usize,
    /// Stopping rule: once a combination is within this relative error (library data), no
    /// further start or iteration is run (0: run them all). The visually equivalent details
    /// run them all.
    pub stop_below: f64,
}

impl Default for GeneralOptions {
    fn default() -> Self {
        GeneralOptions {
            starts: 5,
            max_iterations: 4,
            seed: 1,
            start_material: None,
            beam: 3,
            joint_pool: 1024,
            stop_below: STOP_BELOW,
        }
    }
}

/// The default stopping rule: a combination within 1 % of the look ends the search (the paper
/// finds differences below 7 % hard to notice, Fig. 12).
pub const STOP_BELOW: f64 = 0.01;

/// Every combination the alternation visited, best first (library-data errors), with the
/// number of solver calls.
pub fn explore(
    lib: &Library,
    look: &Look,
    opt: &SolveOptions,
    g: &GeneralOptions,
) -> Result<(Vec<Candidate>, SolveStats)> {
    let mats = lib.material_items()?;
    if mats.is_empty() {
        return Err(Error::new(
            lib.dir.display().to_string(),
            "the library has no materials",
        ));
    }
    // The first start's geometry solves (from the joint search's best material, the likeliest
    // to be right) are the geometry solver's own, with its automatic pool; the later starts'
    // take half of it, unless a pool is asked for: the joint search has ranked every pair already.
    // On `paper16` (50 cases, the paper's protocol, 5 starts) the material solver's pool (256)
    // for every start gave 92 % within 7 %, half the geometry pool (1027) 94 % and the whole
    // one (2055) 94 % in a quarter more time; on `paper4` the whole pool for the first start
    // only gave 92 -> 94 % in 1.5 % more time (docs/solvers.md).
    // The alternation's geometry solves keep to their pools; only the last one widens
    // (below), with the best material found.
    // A start's material is a guess at the shape of the look's lobes more than at its
    // brightness (a sharp GGX with f0 0.48 where the look's has 0.27), and at the wrong
    // brightness the geometry solve ranks the right geometry far down, so the alternation's
    // geometry solves rank at the best brightness; the material solve after each fixes it.
    let inner = SolveOptions {
        final_eval: Final::Library,
        k: opt.k.max(3),
        widen: 0,
        any_brightness: true,
        ..opt.clone()
    };
    let first_geometry = SolveOptions {
        pool: opt.pool_or(super::auto_geometry_pool(lib.manifest.geometries)),
        ..inner.clone()
    };
    let later_geometry = SolveOptions {
        pool: opt.pool_or((super::auto_geometry_pool(lib.manifest.geometries) / 2).max(64)),
        ..inner.clone()
    };
    let mut rng = Rng::new(g.seed);
    let mut seen: Vec<Candidate> = Vec::new();
    let mut stats = SolveStats::default();
    // The joint search's representative pairs: the geometry solves below read their
    // representatives' values from them.
    let mut rep_pairs = None;
    // Starts: the given material; then the materials of the best pairs of the joint search;
    // then the material that best reproduces the look on a flat patch (the material solver on
    // a flat heightfield: the look as a plain BRDF); then seeded random materials; then,
    // beyond `starts`, the library materials closest to the first start sharpened by each of
    // [`SHARPEN`]'s factors, which run only while nothing found is within [`SHARPEN_ABOVE`].
    let starts = g.starts.max(1);
    let mut start_mats: Vec<usize> = g
        .start_material
        .map(|m| m.min(mats.len() - 1))
        .into_iter()
        .collect();
    if g.joint_pool > 0 {
        let t = Instant::now();
        let (scanned, pairs, reps) = super::joint::search(
            lib,
            look,
            &inner,
            g.joint_pool,
            starts,
            super::joint::MAX_OPERATIONS,
        )?;
        stats.search_seconds += t.elapsed().as_secs_f64();
        stats.items_searched += scanned;
        rep_pairs = Some(reps);
        let all = lib.manifest.geometries * mats.len() * inner.psi.max(1);
        if scanned < all {
            stats.notes.push(format!(
                "joint search: {scanned} of {all} (geometry, material, rotation) pairs: every \
                 material on a probe of the geometries, then every geometry with the materials \
                 that came closest there"
            ));
        }
        for p in &pairs {
            if start_mats.len() < starts && !start_mats.contains(&p.material) {
                start_mats.push(p.material);
            }
        }
        // Every re-ranked pair is a visited combination (the visually equivalent details walk
        // them all).
        seen.extend(super::joint::candidates(lib, look, &pairs, &inner)?);
    }
    let done =
        |seen: &[Candidate]| g.stop_below > 0.0 && seen.iter().any(|c| c.error <= g.stop_below);
    // Whether a solve found the look itself, and the stopping rule would end the search on it.
    let same_look = |found: &[Candidate]| {
        g.stop_below > 0.0 && found.iter().any(|c| c.error <= SAME_LOOK.min(g.stop_below))
    };
    let stopped = done(&seen);
    if stopped {
        stats.notes.push(format!(
            "stopped after the joint search: a combination is within {:.1} % (--stop-below)",
            100.0 * g.stop_below
        ));
        start_mats.clear();
    } else if start_mats.len() < starts {
        let (best, st) = super::material::closest_on_flat_patch(lib, look, 1, &inner)?;
        accumulate(&mut stats, &st);
        if let Some(&m) = best.first() {
            if !start_mats.contains(&m) {
                start_mats.push(m);
            }
        }
    }
    while !stopped && start_mats.len() < starts {
        start_mats.push(rng.below(mats.len() as u64) as usize);
    }
    // Sharpening factors not yet tried, in order: each becomes a start when the starts before it
    // are done and none came within `stop_below` (found only then: a flat-patch solve each).
    let mut sharpen = SHARPEN.iter().copied();
    // Solves are deterministic, so one already run (another start reaching the same material,
    // or the same geometry and rotation) is read back instead of repeated.
    let mut geometry_solves: HashMap<usize, Vec<Candidate>> = HashMap::new();
    let mut material_solves: HashMap<(usize, u64), Vec<Candidate>> = HashMap::new();
    // A geometry solve with library material `m`, through the joint search's representative
    // pairs when there are any.
    let rep_pairs = rep_pairs;
    let geometry_solve = |m: usize, o: &SolveOptions| -> Result<SolveResult> {
        let mat: Material = parse_material(&mats[m].spec)?;
        super::geometry::solve_with(
            lib,
            look,
            &mat,
            &mats[m].spec,
            Some(m),
            o,
            rep_pairs.as_ref(),
        )
    };
    // A material solve on a candidate's geometry at its rotation.
    let material_solve = |c: &Candidate| -> Result<SolveResult> {
        let hf = library_heightfield(&c.geometry_spec)?;
        super::material::solve(
            lib,
            look,
            &hf,
            &c.geometry_spec,
            c.geometry,
            c.psi_deg,
            &inner,
        )
    };
    let mut s = 0;
    loop {
        if stopped {
            break;
        }
        if done(&seen) {
            stats.notes.push(format!(
                "stopped before start {s}: a combination is within {:.1} % (--stop-below)",
                100.0 * g.stop_below
            ));
            break;
        }
        if s == start_mats.len() {
            // The sharper starts rescue a search that found nothing visually equivalent; with
            // a combination within the bound they only refine it, at the cost of a start
            // each (the visually equivalent details, `stop_below` 0, run them all).
            if g.stop_below > 0.0 && seen.iter().any(|c| c.error <= SHARPEN_ABOVE) {
                stats.notes.push(format!(
                    "no sharper starts: a combination is within {:.0} %",
                    100.0 * SHARPEN_ABOVE
                ));
                break;
            }
            // Optional: a material whose sharpened look cannot be made (a MERL file that is
            // gone since the build) ends the starts, and the log says why.
            let Some(factor) = sharpen.next() else { break };
            match sharper_material(lib, &mats[start_mats[0]].spec, factor, &inner) {
                Ok((m, st)) => {
                    accumulate(&mut stats, &st);
                    match m {
                        Some(m) if !start_mats.contains(&m) => {
                            start_mats.push(m);
                            stats.notes.push(format!(
                                "start {s}: {}, the library material closest to the first \
                                 start's sharpened (lobe widths x {factor})",
                                mats[m].spec
                            ));
                        }
                        _ => stats.notes.push(format!(
                            "no new start from the first start's sharpened (lobe widths x \
                             {factor}): its closest library material is a start already"
                        )),
                    }
                }
                Err(e) => {
                    stats.notes.push(format!("no sharper start: {e}"));
                    break;
                }
            }
            continue;
        }
        let mut m = start_mats[s];
        let mut last: Option<(usize, i64, usize)> = None;
        let mut ended = false;
        for _ in 0..g.max_iterations.max(1) {
            if let Entry::Vacant(slot) = geometry_solves.entry(m) {
                let gr = geometry_solve(
                    m,
                    if s == 0 {
                        &first_geometry
                    } else {
                        &later_geometry
                    },
                )?;
                accumulate(&mut stats, &gr.stats);
                seen.extend(gr.candidates.iter().cloned());
                slot.insert(gr.candidates);
            }
            let geometries = geometry_solves[&m].clone();
            // Beam: the material solve on each of the best `beam` geometries; the best pair
            // found continues the alternation. A combination that is the look itself
            // ([`SAME_LOOK`]) ends the beam (and then the search): nothing after it could be
            // told from it.
            let mut best: Option<(Candidate, Candidate)> = None;
            let beam = if same_look(&geometries) {
                0
            } else {
                g.beam.max(1)
            };
            for cand in geometries.iter().take(beam) {
                let j = cand.geometry.unwrap_or(0);
                let key = (j, cand.psi_deg.to_bits());
                if let Entry::Vacant(slot) = material_solves.entry(key) {
                    let mr = material_solve(cand)?;
                    accumulate(&mut stats, &mr.stats);
                    seen.extend(mr.candidates.iter().cloned());
                    slot.insert(mr.candidates);
                }
                if let Some(bm) = material_solves[&key].first() {
                    if best.as_ref().is_none_or(|b| bm.error < b.1.error) {
                        best = Some((cand.clone(), bm.clone()));
                    }
                }
                if same_look(&material_solves[&key]) {
                    break;
                }
            }
            if same_look(&seen) {
                stats.notes.push(format!(
                    "stopped in start {s}: a combination is within {:.2} % (the look itself)",
                    100.0 * SAME_LOOK
                ));
                ended = true;
                break;
            }
            let Some((best_g, best_m)) = best else {
                break;
            };
            let j = best_g.geometry.unwrap_or(0);
            let key = (
                j,
                best_g.psi_deg.round() as i64,
                best_m.material.unwrap_or(0),
            );
            if last == Some(key) {
                stats.notes.push(format!("start {s}: converged"));
                break;
            }
            // The stopping rule holds within a start too: an iteration that found a
            // combination within the bound ends the search.
            if done(&seen) {
                stats.notes.push(format!(
                    "stopped in start {s}: a combination is within {:.1} % (--stop-below)",
                    100.0 * g.stop_below
                ));
                ended = true;
                break;
            }
            last = Some(key);
            m = best_m.material.unwrap_or(m);
        }
        if ended {
            break;
        }
        s += 1;
    }
    // When nothing came within the geometry solver's widening bound, the best combination's
    // material gets one more geometry solve, the first start's, with its pool widened
    // ([`SolveOptions::widen`]), and its best geometry a material solve: with a sharp material
    // the right geometry can rank past a pool, and the alternation's solves do not widen. When
    // that material solve makes another material the best and still nothing is within the
    // visually equivalent bound, that material gets the same ([`LAST_SOLVES`]).
    let mut last_materials: Vec<usize> = Vec::new();
    for round in 0..LAST_SOLVES {
        let bound = if round == 0 {
            super::geometry::WIDEN_ABOVE
        } else {
            super::job::MATCH_BOUND
        };
        let best = seen.iter().min_by(|a, b| a.error.total_cmp(&b.error));
        let Some(m) = best
            .filter(|c| opt.widen > 0 && c.error > bound)
            .and_then(|c| c.material)
            .filter(|m| !last_materials.contains(m))
        else {
            break;
        };
        last_materials.push(m);
        let gr = geometry_solve(
            m,
            &SolveOptions {
                widen: opt.widen,
                any_brightness: false,
                ..first_geometry.clone()
            },
        )?;
        accumulate(&mut stats, &gr.stats);
        let widened = gr
            .stats
            .notes
            .iter()
            .find(|n| n.starts_with("geometry pool"));
        stats.notes.push(format!(
            "{} geometry solve with the best material so far ({}): {}",
            if round == 0 { "a last" } else { "another last" },
            mats[m].spec,
            widened.map_or("the best of its pool was within the widening bound", |n| n
                .as_str())
        ));
        if let Some(c) = gr.candidates.first() {
            let j = c.geometry.unwrap_or(0);
            if !material_solves.contains_key(&(j, c.psi_deg.to_bits())) {
                let mr = material_solve(c)?;
                accumulate(&mut stats, &mr.stats);
                seen.extend(mr.candidates);
            }
        }
        seen.extend(gr.candidates);
    }
    // Distinct combinations, best first: a (geometry, material) pair once, at its best rotation.
    seen.sort_by(|a, b| a.error.total_cmp(&b.error));
    let mut uniq: Vec<Candidate> = Vec::new();
    for c in seen {
        if !uniq
            .iter()
            .any(|u| u.geometry == c.geometry && u.material == c.material)
        {
            uniq.push(c);
        }
    }
    Ok((uniq, stats))
}

/// How much [`sharper_material`] narrows the first start's highlight for each extra start (the
/// angular edit of Sec. 7: lobe widths times 0.7, 0.4, then 0.25). On `paper4` (50 cases, the
/// paper's protocol) 0.4 alone found one of the three misses of the starts without it, and 0.25
/// after it one more, a GGX 0.024 on a rough texture that the first start (GGX 0.105) and 0.4's
/// (GGX 0.050) left at 12.3 %. 0.7, tried first, found a Cook–Torrance 0.030 on cracks (100
/// cases of seed 2) that the first start (0.051) and 0.4's (a GGX 0.021) left at 7.9 %
/// (`docs/solvers.md`).
pub const SHARPEN: [f64; 3] = [0.7, 0.4, 0.25];

/// Widened geometry solves at the end of the search, each with the best material so far
/// (see [`explore`]): the first when nothing is within 1 %, the second only when the first's
/// material solve made another material the best and nothing is within 7 %. On `paper4` (seed
/// 1, case 3: U-grooves under a Cook–Torrance 0.057 with a Lambertian lobe) the first, with a
/// Beckmann 0.051, found a geometry whose material solve gave the target's material at 10.6 %,
/// and the second, with that material, the target's geometry (`docs/solvers.md`).
pub const LAST_SOLVES: usize = 2;

/// A combination within this relative error (library data) is the look itself: with the
/// stopping rule on, the alternation's iteration that found it ends there, without the rest of
/// its beam's material solves (each 0.03 s on `paper`). In the paper's protocol (targets that
/// are library combinations) the original scores 0 by library data (to rounding); against the full
/// forward model no library combination comes near it, so the rule never applies there.
pub const SAME_LOOK: f64 = 1e-4;

/// The sharper starts ([`SHARPEN`]) run only while no combination is within this relative
/// error: the visually equivalent bound ([`super::job::MATCH_BOUND`], 7 %).
pub const SHARPEN_ABOVE: f64 = super::job::MATCH_BOUND;

/// The library material closest, on a flat patch, to `spec` (an analytic material: defined at
/// every pair) with its highlight narrowed by `factor` (one of [`SHARPEN`]): a start for the alternation that
/// leaves the blur to the geometry. From a material rougher than the look's own, the
/// alternation finds smooth geometries and stays there: a glossy material on a rough geometry
/// was answered with a rougher material of the same family on a smoother one
/// (`docs/solvers.md`).
fn sharper_material(
    lib: &Library,
    spec: &str,
    factor: f64,
    opt: &SolveOptions,
) -> Result<(Option<usize>, SolveStats)> {
    let edits = super::look::Edits {
        blur: [factor, factor],
        ..Default::default()
    };
    let look = Look::from_spec(spec, edits, None)?;
    let (best, st) = super::material::closest_on_flat_patch(lib, &look, 1, opt)?;
    Ok((best.first().copied(), st))
}

fn accumulate(s: &mut SolveStats, o: &SolveStats) {
    s.search_seconds += o.search_seconds;
    s.rerank_seconds += o.rerank_seconds;
    s.items_searched += o.items_searched;
    s.representatives = s.representatives.max(o.representatives);
}

/// Evaluate candidates (geometry, rotation, material) with the final evaluator at the samples
/// of the look, and sort them.
pub fn finalize(
    lib: &Library,
    look: &Look,
    mut cands: Vec<Candidate>,
    opt: &SolveOptions,
) -> Result<Vec<Candidate>> {
    if opt.final_eval == Final::Library {
        return Ok(cands);
    }
    let lights = lib.gamma_layout().lights;
    // Each geometry's heightfield, and for the fast evaluator its compact BVNDF, built once for
    // the candidates that share it.
    let mut built: HashMap<String, (Heightfield, Option<CompactBvndf>)> = HashMap::new();
    let sampled: Vec<_> = cands
        .iter()
        .map(|c| super::rotated_samples(look, &lights, c.psi_deg.to_radians(), &opt.sampling))
        .collect();
    let bar = super::final_bar(
        opt,
        cands.len(),
        sampled.first().map_or(0, |s| s.0.pairs.len()),
    );
    for (c, (samples, target)) in cands.iter_mut().zip(sampled) {
        let (hf, full) = match built.entry(c.geometry_spec.clone()) {
            Entry::Occupied(e) => e.into_mut(),
            Entry::Vacant(e) => e.insert((library_heightfield(&c.geometry_spec)?, None)),
        };
        let mat = parse_material(&c.material_spec)?;
        let v = match opt.final_eval {
            Final::Fast => {
                let pf = super::material_prefiltered(lib, &mat, c.material)?;
                let full = full.get_or_insert_with(|| super::bvndf_of(hf));
                super::fast_values(full, &pf, &samples)
            }
            _ => exact_values(hf, &[&mat], &samples, opt.exact_samples, &bar).remove(0),
        };
        c.error = samples.rel_error(&target, &v);
        c.evaluated_by = opt.final_eval;
    }
    bar.finish();
    cands.sort_by(|a, b| a.error.total_cmp(&b.error));
    Ok(cands)
}

/// The general solver: explore, then evaluate the best `k` distinct combinations.
pub fn solve(
    lib: &Library,
    look: &Look,
    opt: &SolveOptions,
    g: &GeneralOptions,
) -> Result<SolveResult> {
    let (mut cands, mut stats) = explore(lib, look, opt, g)?;
    cands.truncate(opt.k.max(1));
    let t = Instant::now();
    let cands = finalize(lib, look, cands, opt)?;
    stats.final_seconds = t.elapsed().as_secs_f64();
    Ok(SolveResult {
        candidates: cands,
        stats,
    })
}
