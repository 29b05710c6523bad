//! `biscale validate`: the paper's Table 1 protocol on a library, and error against run time.
//!
//! Each case draws a library geometry `g*` and material `m*` (seeded) and makes the target the
//! look of that combination under the fast forward model (compact BVNDF × prefiltered table, at
//! any direction pair). Each solver then runs with the other factor fixed to the truth (geometry
//! solver: `m*` fixed; material solver: `g*` fixed) or with both unknown (general solver), and we
//! record whether its best answer is within 7 % relative error, whether it is the original item
//! ("exact recovery"), whether it is within 1 % of the original's look, and its run time. The
//! solvers rank the library by its data and, by default, re-evaluate their best `K` with the
//! target's own model and answer the best of those (stage 3, as `biscale solve` does with the
//! exact evaluator; `--final-eval library` answers by library data alone), all timed; the
//! answer's error is then verified with the target's model (untimed). For the geometry and
//! material solvers, an **exhaustive scan** of the same library — every item with its own light
//! lobes or table, no representatives; geometries at every rotation the solver tries; its best
//! `K` through the same stage 3 — runs on the same cases, so the gap between the compressed
//! search and the best the library can offer is visible. With `library_targets` the target is
//! instead the combination as the library itself holds it (its light lobes and table) and
//! answers are judged with that data: the paper's own protocol, where the library's model is
//! the only one. The sweep varies the accuracy knobs of the geometry solver and prints error
//! and time per setting, and can plot them as a PNG.

use crate::error::{Error, Result};
use crate::fast::fbar_one;
use crate::frame::Vec3;
use crate::library::Library;
use crate::material::parse_material;
use crate::prefilter::Prefiltered;
use crate::rng::Rng;
use crate::solve::general::GeneralOptions;
use crate::solve::{
    bvndf_of, library_heightfield, material_prefiltered, rotated_samples, Candidate, Final, Look,
    SolveOptions,
};
use rayon::prelude::*;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

#[derive(Debug, Clone)]
pub struct ValidateJob {
    pub cases: usize,
    pub seed: u64,
    pub options: SolveOptions,
    pub general: GeneralOptions,
    /// Also sweep the geometry solver's knobs.
    pub sweep: bool,
    /// Write the sweep as a PNG plot.
    pub plot: Option<PathBuf>,
    pub quiet: bool,
    /// Targets are the combinations as the library itself represents them (their stored light
    /// lobes and tables), and answers are judged with the same data: the paper's protocol,
    /// where the library's model is the only one. Otherwise targets come from the full forward
    /// model and answers are verified with it.
    pub library_targets: bool,
    /// Which solvers run (each with its exhaustive scan where it has one); empty: all three.
    pub solvers: Vec<Solver>,
    /// Run the exhaustive scans beside the geometry and material solvers (seconds per case on
    /// a large library).
    pub exhaustive: bool,
}

/// A solver `validate` can run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Solver {
    /// Material fixed to the truth.
    Geometry,
    /// Geometry fixed to the truth.
    Material,
    /// Both unknown.
    General,
}

impl ValidateJob {
    fn runs(&self, s: Solver) -> bool {
        self.solvers.is_empty() || self.solvers.contains(&s)
    }
}

/// One library combination as a target look as the library represents it: the geometry's
/// stored light lobes with the material's stored table. Defined at the library's lights only
/// (targets cannot be rotated).
pub fn library_look(lib: &Library, g: usize, m: usize) -> Result<Look> {
    let gi = lib.geometry_items()?;
    let mi = lib.material_items()?;
    let lobes = lib.geometry_lobes()?;
    // A bad record fails here, not inside the look; a packed record is indexed once, not at
    // every direction the look is read at.
    lobes.get(g)?;
    let index = lobes.index(g)?;
    let mat = parse_material(&mi[m].spec)?;
    let pf = material_prefiltered(lib, &mat, Some(m))?;
    let colour = crate::library::items::average_colour(&mat);
    Ok(Look::from_fn(
        &format!("{} with {} (library data)", gi[g].spec, mi[m].spec),
        move |wi: Vec3, wo: Vec3| {
            let mut scratch = Vec::new();
            lobes.get_indexed(g, index.as_ref()).map_or(0.0, |l| {
                fbar_one(&l, &pf, &crate::frame::DirPair { wi, wo }, &mut scratch)
            })
        },
        Some(colour),
    ))
}

/// One library combination as a target look (fast forward model).
fn combo_look(lib: &Library, g: usize, m: usize) -> Result<Look> {
    let gi = lib.geometry_items()?;
    let mi = lib.material_items()?;
    let hf = library_heightfield(&gi[g].spec)?;
    let geo = Arc::new(bvndf_of(&hf));
    let mat = parse_material(&mi[m].spec)?;
    let pf = Arc::new(Prefiltered::build(
        &mat,
        &crate::solve::geometry::prefilter_for(lib),
    ));
    let colour = crate::library::items::average_colour(&mat);
    Ok(Look::from_combination(
        &format!("{} with {}", gi[g].spec, mi[m].spec),
        geo,
        pf,
        1.0,
        Some(colour),
    ))
}

#[derive(Default, Clone)]
struct Tally {
    n: usize,
    within7: usize,
    recovered: usize,
    within1: usize,
    times: Vec<f64>,
    errors: Vec<f64>,
    /// Per case, the solver's own stage times (search, re-rank, final evaluation), when it
    /// reports them.
    stages: Vec<[f64; 3]>,
    /// Cases with an exhaustive scan beside the solver, and those where the solver's answer was
    /// the scan's optimum or no worse ([`as_good`]).
    compared: usize,
    optimum: usize,
}

impl Tally {
    fn add(&mut self, err: f64, recovered: bool, secs: f64) {
        self.n += 1;
        self.within7 += (err <= crate::solve::job::MATCH_BOUND) as usize;
        self.within1 += (err <= 0.01) as usize;
        self.recovered += recovered as usize;
        self.times.push(secs);
        self.errors.push(err);
    }
    fn pct(&self, k: usize) -> f64 {
        100.0 * k as f64 / self.n.max(1) as f64
    }
    /// Count one case's solver answer against the exhaustive scan's on the same case; the
    /// log names a case where the solver did worse.
    fn compare(&mut self, solver: &Answer, scan: &Answer, case: usize, name: &str, quiet: bool) {
        self.compared += 1;
        let found = as_good(solver, scan);
        self.optimum += found as usize;
        if !found && !quiet {
            let show = |a: &Answer| {
                a.0.as_ref().map_or("none".to_string(), |c| {
                    format!(
                        "geometry {:?} material {:?} psi {:.0} at {:.2} %",
                        c.geometry,
                        c.material,
                        c.psi_deg,
                        a.1 * 100.0
                    )
                })
            };
            crate::library::progress::line(&format!(
                "validate: case {case}: {name} did not find the exhaustive optimum: answer {}, scan {}",
                show(solver),
                show(scan)
            ));
        }
    }
    fn q(v: &[f64], f: f64) -> f64 {
        if v.is_empty() {
            return f64::NAN;
        }
        let mut v = v.to_vec();
        v.sort_by(f64::total_cmp);
        v[((v.len() - 1) as f64 * f).round() as usize]
    }
}

/// A case's answer: the best candidate and its verified error.
type Answer = (Option<Candidate>, f64);

/// Whether a solver's answer found the exhaustive scan's optimum: the same item at the same rotation,
/// or a verified error no larger (to rounding: both errors are sums over the same samples).
fn as_good(solver: &Answer, scan: &Answer) -> bool {
    let same = match (&solver.0, &scan.0) {
        (Some(a), Some(b)) => {
            a.geometry == b.geometry && a.material == b.material && a.psi_deg == b.psi_deg
        }
        _ => false,
    };
    same || solver.1 <= scan.1 * (1.0 + 1e-9) + 1e-12
}

/// The best geometry by an exhaustive scan of every library geometry's own light lobes (material
/// fixed, no representatives, no pool) at every rotation the solver tries (`opt.psi`, each at
/// its own samples, as the solver's stage 2 compares them), as a candidate for verification.
pub fn exhaustive_geometry(
    lib: &Library,
    look: &Look,
    m: usize,
    opt: &SolveOptions,
) -> Result<Candidate> {
    Ok(exhaustive_geometries(lib, look, m, opt, 1)?.remove(0))
}

/// The `k` best geometries of [`exhaustive_geometry`]'s scan, each at its best rotation (the
/// first rotation wins ties), best first; at least one.
fn exhaustive_geometries(
    lib: &Library,
    look: &Look,
    m: usize,
    opt: &SolveOptions,
    k: usize,
) -> Result<Vec<Candidate>> {
    let mi = lib.material_items()?;
    let gi = lib.geometry_items()?;
    let mat = parse_material(&mi[m].spec)?;
    let pf = material_prefiltered(lib, &mat, Some(m))?;
    let lobes = lib.geometry_lobes()?;
    // Each geometry's best (error, rotation) over the rotations.
    let mut best = vec![(f64::INFINITY, 0.0); lib.manifest.geometries];
    for i in 0..opt.psi.max(1) {
        let psi = crate::solve::psi_angle(i, opt.psi);
        let (s, t) = rotated_samples(look, &lib.gamma_layout().lights, psi, &opt.sampling);
        let at = crate::lightlobes::LightPairs::new(&lobes.layout, crate::solve::dir_pairs(&s));
        let errs: Vec<f64> = (0..lib.manifest.geometries)
            .into_par_iter()
            .map(|j| Ok(s.rel_error(&t, &lobes.get(j)?.fbar(&pf, &at))))
            .collect::<Result<_>>()?;
        for (b, e) in best.iter_mut().zip(errs) {
            if e < b.0 {
                *b = (e, psi);
            }
        }
    }
    let errs: Vec<f64> = best.iter().map(|b| b.0).collect();
    Ok(top(&errs, k)
        .into_iter()
        .map(|(j, e)| Candidate {
            psi_deg: best.get(j).map_or(0.0, |b| b.1).to_degrees(),
            ..candidate(&gi[j].spec, Some(j), &mi[m].spec, Some(m), e)
        })
        .collect())
}

/// The `k` best materials by an exhaustive scan of every library table (geometry fixed, its
/// stored light lobes), best first; at least one.
fn exhaustive_materials(
    lib: &Library,
    look: &Look,
    g: usize,
    opt: &SolveOptions,
    k: usize,
) -> Result<Vec<Candidate>> {
    let gi = lib.geometry_items()?;
    let mi = lib.material_items()?;
    let lobes = lib.geometry_lobes()?;
    let (s, t) = rotated_samples(look, &lib.gamma_layout().lights, 0.0, &opt.sampling);
    // The geometry is fixed: its lobes at the samples are assembled once for every material.
    let geo = crate::fast::FixedLobes::new(&lobes.get(g)?, &crate::solve::dir_pairs(&s));
    let errs: Vec<f64> = (0..mi.len())
        .into_par_iter()
        .map(|m| {
            let pf = material_prefiltered(lib, &parse_material(&mi[m].spec)?, Some(m))?;
            Ok(s.rel_error(&t, &geo.fbar(&pf)))
        })
        .collect::<Result<_>>()?;
    Ok(top(&errs, k)
        .into_iter()
        .map(|(m, e)| candidate(&gi[g].spec, Some(g), &mi[m].spec, Some(m), e))
        .collect())
}

/// An exhaustive scan's answer as the solvers give theirs: its best `opt.k` re-evaluated with
/// the final evaluator, the best of them (stage 3); with [`Final::Library`] its best by library
/// data.
fn exhaustive_answer(
    lib: &Library,
    look: &Look,
    opt: &SolveOptions,
    scan: &dyn Fn(usize) -> Result<Vec<Candidate>>,
) -> Result<Candidate> {
    let k = if opt.final_eval == Final::Library {
        1
    } else {
        opt.k.max(1)
    };
    let cands = crate::solve::general::finalize(lib, look, scan(k)?, opt)?;
    cands
        .into_iter()
        .next()
        .ok_or_else(|| Error::new("validate", "an exhaustive scan of an empty library"))
}

/// The indices and values of the `k` smallest finite errors, smallest first (ties by index);
/// index 0 with an infinite error if none is finite.
fn top(errs: &[f64], k: usize) -> Vec<(usize, f64)> {
    let idx = crate::solve::smallest(errs, k.max(1));
    if idx.is_empty() {
        return vec![(0, f64::INFINITY)];
    }
    idx.into_iter()
        .map(|i| (i, errs.get(i).copied().unwrap_or(f64::INFINITY)))
        .collect()
}

/// A (geometry, material) answer at rotation 0.
fn candidate(gs: &str, g: Option<usize>, ms: &str, m: Option<usize>, error: f64) -> Candidate {
    Candidate {
        geometry: g,
        geometry_spec: gs.to_string(),
        material: m,
        material_spec: ms.to_string(),
        psi_deg: 0.0,
        colour_shift: None,
        colour: [0.0; 3],
        search_error: error,
        rerank_error: error,
        error,
        evaluated_by: Final::Library,
    }
}

/// The error of an answer under the model that made the target (the full compact BVNDF with the
/// material's prefiltered table, at the rotated target's samples, the ones the solvers fit). The original
/// combination at rotation 0 is the target itself: its error is 0 by construction, not computed.
/// With `library_targets` the library's data made the target, and the answer's error from
/// that data (what the solver computed) is its error.
fn verified(
    lib: &Library,
    look: &Look,
    c: Option<&Candidate>,
    truth: (usize, usize),
    opt: &SolveOptions,
    library_targets: bool,
) -> Result<f64> {
    let Some(c) = c else {
        return Ok(f64::INFINITY);
    };
    if c.geometry == Some(truth.0) && c.material == Some(truth.1) && c.psi_deg == 0.0 {
        return Ok(0.0);
    }
    if library_targets {
        return Ok(c.error);
    }
    let o = SolveOptions {
        final_eval: Final::Fast,
        ..opt.clone()
    };
    let v = crate::solve::general::finalize(lib, look, vec![c.clone()], &o)?;
    Ok(v.first().map_or(f64::INFINITY, |c| c.error))
}

/// A timed solver's answer: its best candidate and its stage times (search, re-rank, final
/// evaluation).
type SolverAnswer = (Option<Candidate>, Option<[f64; 3]>);

pub fn run(lib: &Library, job: &ValidateJob) -> Result<String> {
    let (ng, nm) = (lib.manifest.geometries, lib.manifest.materials);
    if ng == 0 || nm == 0 {
        return Err(Error::new(
            lib.dir.display().to_string(),
            "the library is empty",
        ));
    }
    if job.library_targets && (job.options.psi > 1 || job.sweep) {
        return Err(Error::new(
            "validate --library-targets",
            "the library's light lobes are defined at its own lights only, so its targets \
             cannot be rotated: use --psi 1 and no --sweep or --plot",
        ));
    }
    if job.library_targets && job.options.final_eval != Final::Library {
        return Err(Error::new(
            "validate --library-targets",
            "the paper's protocol judges answers with the library's own data, so a final \
             evaluation with the forward model has nothing to be judged by: use --final-eval \
             library (the default) with --library-targets",
        ));
    }
    if let Some(p) = &job.plot {
        let dir = p.parent().unwrap_or(std::path::Path::new(""));
        crate::atomic_write::check_output_dir(dir, "--plot")?;
        if p.is_dir() {
            return Err(Error::new(
                "--plot",
                format!("{} is a directory; expected a PNG file name", p.display()),
            ));
        }
    }
    let mi = lib.material_items()?;
    let gi = lib.geometry_items()?;
    let mut rng = Rng::new(job.seed);
    // The solvers answer from library data, or re-evaluate their best K with the final
    // evaluator (timed); the answer is then verified against the target's own model at the
    // samples the solvers fit (untimed).
    let opt = job.options.clone();
    let (mut tg, mut tm, mut tgen, mut eg, mut em) = (
        Tally::default(),
        Tally::default(),
        Tally::default(),
        Tally::default(),
        Tally::default(),
    );
    let t_all = Instant::now();
    let mut sampling_secs = Vec::new();
    for c in 0..job.cases {
        let (g, m) = (rng.below(ng as u64) as usize, rng.below(nm as u64) as usize);
        let look = if job.library_targets {
            library_look(lib, g, m)?
        } else {
            combo_look(lib, g, m)?
        };
        let mat = parse_material(&mi[m].spec)?;
        // The target is discretised once per rotation before the solvers are timed (as in the
        // paper's timings); the cost depends on the target, not on the solver.
        let t = Instant::now();
        let lights = lib.gamma_layout().lights;
        for i in 0..opt.psi.max(1) {
            let psi = crate::solve::psi_angle(i, opt.psi);
            rotated_samples(&look, &lights, psi, &opt.sampling);
        }
        sampling_secs.push(t.elapsed().as_secs_f64());
        // Run one solver (timed), verify its answer (untimed), count it, and name a miss.
        let run = |tally: &mut Tally,
                   name: &str,
                   solve: &dyn Fn() -> Result<SolverAnswer>,
                   recovered: &dyn Fn(&Candidate) -> bool|
         -> Result<Answer> {
            let t = Instant::now();
            let (best, stages) = solve()?;
            let secs = t.elapsed().as_secs_f64();
            let err = verified(lib, &look, best.as_ref(), (g, m), &opt, job.library_targets)?;
            tally.add(err, best.as_ref().is_some_and(recovered), secs);
            tally.stages.extend(stages);
            if err > crate::solve::job::MATCH_BOUND && !job.quiet {
                crate::library::progress::line(&format!(
                    "validate: case {}: {name} missed 7 %: {} (geometry {g} '{}', material {m} '{}'), answer {}",
                    c + 1,
                    if err.is_finite() { format!("{:.2} %", err * 100.0) } else { "no answer".into() },
                    gi[g].spec,
                    mi[m].spec,
                    best.as_ref().map_or("none".to_string(), |b| format!(
                        "geometry {:?} material {:?} psi {:.0}",
                        b.geometry, b.material, b.psi_deg
                    )),
                ));
            }
            Ok((best, err))
        };
        // The best candidate, and the solver's stage times.
        let first = |r: crate::solve::SolveResult| {
            let stages = [
                r.stats.search_seconds,
                r.stats.rerank_seconds,
                r.stats.final_seconds,
            ];
            (r.candidates.into_iter().next(), Some(stages))
        };
        let is_g = |b: &Candidate| b.geometry == Some(g);
        let is_m = |b: &Candidate| b.material == Some(m);
        // A solver, then (with the scans) its exhaustive scan through the same stage 3, and
        // whether the solver found the scan's optimum.
        let with_scan = |tally: &mut Tally,
                         scans: &mut Tally,
                         name: &str,
                         solve: &dyn Fn() -> Result<SolverAnswer>,
                         scan: &dyn Fn(usize) -> Result<Vec<Candidate>>,
                         recovered: &dyn Fn(&Candidate) -> bool|
         -> Result<()> {
            let solver = run(tally, &format!("{name} solver"), solve, recovered)?;
            if job.exhaustive {
                let scan = run(
                    scans,
                    &format!("{name} exhaustive scan"),
                    &|| exhaustive_answer(lib, &look, &opt, scan).map(|c| (Some(c), None)),
                    recovered,
                )?;
                tally.compare(&solver, &scan, c + 1, &format!("{name} solver"), job.quiet);
            }
            Ok(())
        };
        if job.runs(Solver::Geometry) {
            with_scan(
                &mut tg,
                &mut eg,
                "geometry",
                &|| {
                    crate::solve::geometry::solve(lib, &look, &mat, &mi[m].spec, Some(m), &opt)
                        .map(first)
                },
                &|k| exhaustive_geometries(lib, &look, m, &opt, k),
                &is_g,
            )?;
        }
        if job.runs(Solver::Material) {
            let hf = library_heightfield(&gi[g].spec)?;
            with_scan(
                &mut tm,
                &mut em,
                "material",
                &|| {
                    crate::solve::material::solve(lib, &look, &hf, &gi[g].spec, Some(g), 0.0, &opt)
                        .map(first)
                },
                &|k| exhaustive_materials(lib, &look, g, &opt, k),
                &is_m,
            )?;
        }
        if job.runs(Solver::General) {
            run(
                &mut tgen,
                "general solver",
                &|| crate::solve::general::solve(lib, &look, &opt, &job.general).map(first),
                &|b| is_g(b) && is_m(b),
            )?;
        }
        if !job.quiet {
            let (done, secs) = (c + 1, t_all.elapsed().as_secs_f64());
            crate::library::progress::line(&format!(
                "validate: case {done}/{} done ({}, {:.2} cases/s, about {} left)",
                job.cases,
                crate::library::progress::fmt_secs(secs),
                done as f64 / secs.max(1e-9),
                crate::library::progress::fmt_secs(secs / done as f64 * (job.cases - done) as f64)
            ));
        }
    }
    let row = |name: &str, t: &Tally| {
        format!(
            "| {name} | {} | {:.1} % | {:.1} % | {:.1} % | {:.3} s | {:.3} s | {:.2} % |\n",
            t.n,
            t.pct(t.within7),
            t.pct(t.recovered),
            t.pct(t.within1),
            Tally::q(&t.times, 0.5),
            Tally::q(&t.times, 0.95),
            Tally::q(&t.errors, 0.5) * 100.0
        )
    };
    let protocol = if job.library_targets {
        "targets: the combinations as the library represents them (its light lobes and tables: \
         the paper's protocol); solvers answer from library data (timed) and are judged with it"
    } else {
        let answer = match opt.final_eval {
            Final::Library => "solvers answer from library data (timed)",
            Final::Fast => {
                "solvers and exhaustive scans re-evaluate their best K with the fast forward \
                 model and answer the best (timed, stage 3)"
            }
            Final::Exact => {
                "solvers and exhaustive scans re-evaluate their best K with the exact evaluator \
                 and answer the best (timed, stage 3)"
            }
        };
        &format!(
            "targets: fast forward model; {answer}, the answer's error is then verified with the \
             target's model at its samples (untimed)"
        )
    };
    let mut out = format!(
        "Library {} ('{}': {} geometries, {} materials; {} / {}{} representatives), {} cases, seed {}; \
         {protocol}; psi = {}, pool = {} geometries / {} materials, K = {}, {} starts.\n\n\
         | solver | cases | within 7 % | exact recovery | within 1 % | median time | 95th pct time | median error |\n\
         |---|---|---|---|---|---|---|---|\n",
        lib.dir.display(),
        lib.manifest.profile,
        ng,
        nm,
        lib.manifest.geometry.representatives,
        lib.manifest.material.representatives,
        lib.manifest
            .material_search
            .as_ref()
            .map(|r| format!(" (the material solver's search: {})", r.representatives))
            .unwrap_or_default(),
        job.cases,
        job.seed,
        opt.psi,
        opt.geometry_pool_for(ng),
        opt.pool_for(nm),
        opt.k,
        job.general.starts
    );
    if job.runs(Solver::Geometry) {
        out += &row("geometry (material fixed)", &tg);
        if job.exhaustive {
            out += &row("  exhaustive scan, same cases", &eg);
        }
    }
    if job.runs(Solver::Material) {
        out += &row("material (geometry fixed)", &tm);
        if job.exhaustive {
            out += &row("  exhaustive scan, same cases", &em);
        }
    }
    if job.runs(Solver::General) {
        out += &row("general (both unknown)", &tgen);
    }
    let found: Vec<String> = [("geometry", &tg), ("material", &tm)]
        .iter()
        .filter(|(_, t)| t.compared > 0)
        .map(|(name, t)| {
            format!(
                "{name} {} of {} ({:.1} %)",
                t.optimum,
                t.compared,
                100.0 * t.optimum as f64 / t.compared as f64
            )
        })
        .collect();
    if !found.is_empty() {
        out += &format!(
            "\nExhaustive optimum found (the solver's answer is the exhaustive scan's, or its \
             verified error is no larger): {}.\n",
            found.join(", ")
        );
    }
    let stages: Vec<String> = [("geometry", &tg), ("material", &tm), ("general", &tgen)]
        .iter()
        .filter(|(_, t)| !t.stages.is_empty())
        .map(|(name, t)| {
            let stage =
                |i: usize| Tally::q(&t.stages.iter().map(|s| s[i]).collect::<Vec<_>>(), 0.5);
            if opt.final_eval == Final::Library {
                format!("{name} {:.3} / {:.3} s", stage(0), stage(1))
            } else {
                format!(
                    "{name} {:.3} / {:.3} / {:.3} s",
                    stage(0),
                    stage(1),
                    stage(2)
                )
            }
        })
        .collect();
    if !stages.is_empty() {
        out += &format!(
            "\nMedian stage times inside the times above, search (stage 1: the compressed \
             libraries through their representatives) / re-rank (stage 2: the pool with each \
             item's own data, coarse passes included){}: {} (the general solver's summed over \
             its joint search and its solves).\n",
            if opt.final_eval == Final::Library {
                ""
            } else {
                " / final evaluation (stage 3: the best K)"
            },
            stages.join(", ")
        );
    }
    out += &format!(
        "\nDrawing each target's samples (7 lights × {} views, gradient importance; not in the times above): median {:.3} s.\n",
        opt.sampling.views_per_light,
        Tally::q(&sampling_secs, 0.5)
    );
    if job.sweep {
        out += &sweep(lib, job)?;
    }
    Ok(out)
}

/// Error against run time of the geometry solver over its knobs (pool re-ranked, psi, final).
fn sweep(lib: &Library, job: &ValidateJob) -> Result<String> {
    let mi = lib.material_items()?;
    let (ng, nm) = (lib.manifest.geometries, lib.manifest.materials);
    // (pool, further pools re-ranked when the best is over 1 % (`SolveOptions::widen`), psi,
    // re-rank with light lobes (else binned columns), stage 1 also ranks by binned columns,
    // final evaluation, candidates it re-evaluates)
    let settings: Vec<(usize, usize, usize, bool, bool, Final, usize)> = vec![
        (1, 0, 1, false, false, Final::Library, 1),
        (64, 0, 1, false, false, Final::Library, 1),
        (1, 0, 1, true, false, Final::Library, 1),
        (4, 0, 1, true, false, Final::Library, 1),
        (16, 0, 1, true, false, Final::Library, 1),
        (64, 0, 1, true, false, Final::Library, 1),
        (256, 0, 1, true, false, Final::Library, 1),
        (16, 0, 1, true, true, Final::Library, 1),
        (64, 0, 1, true, true, Final::Library, 1),
        (64, 3, 1, true, true, Final::Library, 1),
        (256, 0, 1, true, true, Final::Library, 1),
        (256, 3, 1, true, true, Final::Library, 1),
        (1024, 0, 1, true, true, Final::Library, 1),
        (4096, 0, 1, true, true, Final::Library, 1),
        (256, 0, 4, true, true, Final::Library, 1),
        (256, 0, 1, true, true, Final::Fast, 3),
        (256, 0, 1, true, true, Final::Fast, 8),
    ];
    let mut rng = Rng::new(job.seed ^ 0x5eed);
    let cases: Vec<(usize, usize)> = (0..job.cases)
        .map(|_| (rng.below(ng as u64) as usize, rng.below(nm as u64) as usize))
        .collect();
    let looks: Vec<Look> = cases
        .iter()
        .map(|&(g, m)| combo_look(lib, g, m))
        .collect::<Result<_>>()?;
    let mut out = String::from("\nError against run time (geometry solver, same cases; errors verified with the target's model):\n\n| re-ranked pool | widened | stage 1 / stage 2 by | psi | final | median error | within 7 % | recovery | median time |\n|---|---|---|---|---|---|---|---|---|\n");
    let mut points = Vec::new();
    let t_all = Instant::now();
    for (i, &(pool, widen, psi, rerank_fast, binned_search, fin, k)) in settings.iter().enumerate()
    {
        let opt = SolveOptions {
            pool,
            widen,
            psi,
            rerank_fast,
            binned_search,
            final_eval: fin,
            k,
            ..job.options.clone()
        };
        let mut t = Tally::default();
        for (&(g, m), look) in cases.iter().zip(&looks) {
            let mat = parse_material(&mi[m].spec)?;
            let s = Instant::now();
            let r = crate::solve::geometry::solve(lib, look, &mat, &mi[m].spec, Some(m), &opt)?;
            let secs = s.elapsed().as_secs_f64();
            let b = r.candidates.first();
            t.add(
                verified(lib, look, b, (g, m), &opt, false)?,
                b.and_then(|b| b.geometry) == Some(g),
                secs,
            );
        }
        let (me, mt) = (Tally::q(&t.errors, 0.5), Tally::q(&t.times, 0.5));
        points.push((mt, me));
        if !job.quiet {
            let (done, secs) = (i + 1, t_all.elapsed().as_secs_f64());
            crate::library::progress::line(&format!(
                "validate: sweep setting {done}/{} done ({}, about {} left)",
                settings.len(),
                crate::library::progress::fmt_secs(secs),
                crate::library::progress::fmt_secs(
                    secs / done as f64 * (settings.len() - done) as f64
                )
            ));
        }
        let by = match (rerank_fast, binned_search) {
            (false, _) => "binned / binned",
            (true, false) => "lobes / lobes",
            (true, true) => "lobes + binned / lobes",
        };
        out += &format!(
            "| {pool} | {} | {by} | {psi} | {} | {:.2} % | {:.1} % | {:.1} % | {:.3} s |\n",
            if widen > 0 {
                format!("up to {widen}× more")
            } else {
                "no".to_string()
            },
            match fin {
                Final::Library => "library".to_string(),
                Final::Fast => format!("fast, best {k}"),
                Final::Exact => format!("exact, best {k}"),
            },
            me * 100.0,
            t.pct(t.within7),
            t.pct(t.recovered),
            mt
        );
    }
    if let Some(p) = &job.plot {
        let caption =
            crate::plot::scatter_png(p, &points, "median time (s)", "median relative error")?;
        out += &format!("\nPlot {caption}\n");
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn answer(g: usize, psi: f64, err: f64) -> Answer {
        let mut c = candidate("g", Some(g), "m", Some(0), err);
        c.psi_deg = psi;
        (Some(c), err)
    }

    #[test]
    fn a_scan_keeps_its_k_best_finite_errors_best_first() {
        let errs = [0.3, f64::NAN, 0.1, 0.2, 0.1, f64::INFINITY];
        assert_eq!(top(&errs, 3), vec![(2, 0.1), (4, 0.1), (3, 0.2)]);
        // More asked than finite: the finite ones.
        assert_eq!(top(&errs, 10).len(), 4);
        // Nothing finite: one answer, infinitely far.
        let none = top(&[f64::NAN, f64::INFINITY], 2);
        assert_eq!(none.len(), 1);
        assert_eq!(none[0].0, 0);
        assert!(none[0].1.is_infinite());
    }

    #[test]
    fn the_exhaustive_optimum_is_found_by_the_same_item_or_an_answer_no_worse() {
        let scan = answer(7, 0.0, 0.05);
        // The same item, whatever its verified error.
        assert!(as_good(&answer(7, 0.0, 0.05), &scan));
        // Another item (or a rotation) that is no worse, to rounding.
        assert!(as_good(&answer(3, 0.0, 0.04), &scan));
        assert!(as_good(&answer(3, 45.0, 0.05 * (1.0 + 1e-12)), &scan));
        assert!(as_good(&answer(3, 0.0, 0.0), &answer(7, 0.0, 0.0)));
        // Worse, or no answer.
        assert!(!as_good(&answer(3, 0.0, 0.051), &scan));
        assert!(!as_good(&answer(7, 90.0, 0.06), &scan));
        assert!(!as_good(&(None, f64::INFINITY), &scan));
    }
}
