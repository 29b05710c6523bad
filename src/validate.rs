//! `biscale validate`: the paper's Table 1 protocol on a library, and error against run time.
//!
//! Each case draws a library geometry `g*` and material `m*` (seeded) and makes the target the
//! look of that combination under the fast forward model (compact BVNDF × prefiltered table, at
//! any direction pair). Each solver then runs with the other factor fixed to the truth (geometry
//! solver: `m*` fixed; material solver: `g*` fixed) or with both unknown (general solver), and we
//! record whether its best answer is within 7 % relative error, whether it is the original item
//! ("exact recovery"), whether it is within 1 % of the original's look, and its run time. For
//! the geometry and material solvers, an **exhaustive scan** of the same library — every item
//! with its own uncompressed data, no representatives — runs on the same cases, so the gap
//! between the compressed search and the best the library can offer is visible. The sweep varies
//! the accuracy knobs of the geometry solver and prints error and time per setting, and can plot
//! them as a PNG.

use crate::error::{Error, Result};
use crate::fast::fbar_one;
use crate::frame::Vec3;
use crate::gamma::Response;
use crate::library::Library;
use crate::material::parse_material;
use crate::prefilter::Prefiltered;
use crate::rng::Rng;
use crate::solve::general::GeneralOptions;
use crate::solve::{bvndf_of, fast_values, library_heightfield, Final, Look, SolveOptions};
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
    Ok(Look::from_fn(
        &format!("{} with {}", gi[g].spec, mi[m].spec),
        move |wi: Vec3, wo: Vec3| {
            let mut scratch = Vec::with_capacity(geo.clusters);
            fbar_one(&geo, &pf, &crate::frame::DirPair { wi, wo }, &mut scratch)
        },
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
}

impl Tally {
    fn add(&mut self, err: f64, recovered: bool, secs: f64) {
        self.n += 1;
        self.within7 += (err <= 0.07) as usize;
        self.within1 += (err <= 0.01) as usize;
        self.recovered += recovered as usize;
        self.times.push(secs);
        self.errors.push(err);
    }
    fn pct(&self, k: usize) -> f64 {
        100.0 * k as f64 / self.n.max(1) as f64
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

/// The best geometry by an exhaustive scan of every library column (material fixed).
fn exhaustive_geometry(
    lib: &Library,
    look: &Look,
    m: usize,
    opt: &SolveOptions,
) -> Result<(usize, f64)> {
    let mi = lib.material_items()?;
    let mat = parse_material(&mi[m].spec)?;
    let layout = lib.gamma_layout();
    let f = look.as_fn();
    let s = crate::sampling::sample(&layout.lights, &f, &opt.sampling);
    let t = s.values(&f, 0.0);
    let resp = Response::new(&layout, &mat, &s.pairs);
    let gamma = lib.array("geometry/gamma.bsa")?;
    let gamma = gamma.f16s()?;
    let rows = layout.rows();
    use rayon::prelude::*;
    let errs: Vec<f64> = (0..lib.manifest.geometries)
        .into_par_iter()
        .map(|j| s.rel_error(&t, &resp.apply(&gamma[j * rows..(j + 1) * rows])))
        .collect();
    let best = crate::solve::smallest(&errs, 1)
        .first()
        .copied()
        .unwrap_or(0);
    let gi = lib.geometry_items()?;
    let pf = Prefiltered::build(&mat, &crate::solve::geometry::prefilter_for(lib));
    let v = fast_values(&bvndf_of(&library_heightfield(&gi[best].spec)?), &pf, &s);
    Ok((best, s.rel_error(&t, &v)))
}

/// The best material by an exhaustive scan of every library table (geometry fixed).
fn exhaustive_material(
    lib: &Library,
    look: &Look,
    g: usize,
    opt: &SolveOptions,
) -> Result<(usize, f64)> {
    let gi = lib.geometry_items()?;
    let mi = lib.material_items()?;
    let hf = library_heightfield(&gi[g].spec)?;
    let geo = bvndf_of(&hf);
    let f = look.as_fn();
    let s = crate::sampling::sample(&lib.gamma_layout().lights, &f, &opt.sampling);
    let t = s.values(&f, 0.0);
    let cfg = crate::solve::geometry::prefilter_for(lib);
    let tlen = lib.manifest.table_len;
    let tables = lib.array("material/prefiltered.bsa")?;
    let tables = tables.f32s()?;
    use rayon::prelude::*;
    let errs: Vec<f64> = (0..mi.len())
        .into_par_iter()
        .map(|m| {
            let mat = parse_material(&mi[m].spec)?;
            let pf =
                Prefiltered::from_table(&mat, &cfg, tables[m * tlen..(m + 1) * tlen].to_vec())?;
            Ok(s.rel_error(&t, &fast_values(&geo, &pf, &s)))
        })
        .collect::<Result<_>>()?;
    let best = crate::solve::smallest(&errs, 1)
        .first()
        .copied()
        .unwrap_or(0);
    Ok((best, errs[best]))
}

pub fn run(lib: &Library, job: &ValidateJob) -> Result<String> {
    let (ng, nm) = (lib.manifest.geometries, lib.manifest.materials);
    if ng == 0 || nm == 0 {
        return Err(Error::new(
            lib.dir.display().to_string(),
            "the library is empty",
        ));
    }
    let mi = lib.material_items()?;
    let gi = lib.geometry_items()?;
    let mut rng = Rng::new(job.seed);
    let opt = SolveOptions {
        final_eval: if job.options.final_eval == Final::Exact {
            Final::Fast
        } else {
            job.options.final_eval
        },
        ..job.options.clone()
    };
    let (mut tg, mut tm, mut tgen, mut eg, mut em) = (
        Tally::default(),
        Tally::default(),
        Tally::default(),
        Tally::default(),
        Tally::default(),
    );
    let t_all = Instant::now();
    for c in 0..job.cases {
        let (g, m) = (rng.below(ng as u64) as usize, rng.below(nm as u64) as usize);
        let look = combo_look(lib, g, m)?;
        let mat = parse_material(&mi[m].spec)?;
        let t = Instant::now();
        let r = crate::solve::geometry::solve(lib, &look, &mat, &mi[m].spec, Some(m), &opt)?;
        let best = r.candidates.first();
        tg.add(
            best.map_or(f64::INFINITY, |b| b.error),
            best.and_then(|b| b.geometry) == Some(g),
            t.elapsed().as_secs_f64(),
        );
        let t = Instant::now();
        let (bj, be) = exhaustive_geometry(lib, &look, m, &opt)?;
        eg.add(be, bj == g, t.elapsed().as_secs_f64());
        let hf = library_heightfield(&gi[g].spec)?;
        let t = Instant::now();
        let r = crate::solve::material::solve(lib, &look, &hf, &gi[g].spec, Some(g), 0.0, &opt)?;
        let best = r.candidates.first();
        tm.add(
            best.map_or(f64::INFINITY, |b| b.error),
            best.and_then(|b| b.material) == Some(m),
            t.elapsed().as_secs_f64(),
        );
        let t = Instant::now();
        let (bm, be) = exhaustive_material(lib, &look, g, &opt)?;
        em.add(be, bm == m, t.elapsed().as_secs_f64());
        let t = Instant::now();
        let r = crate::solve::general::solve(lib, &look, &opt, &job.general)?;
        let best = r.candidates.first();
        tgen.add(
            best.map_or(f64::INFINITY, |b| b.error),
            best.is_some_and(|b| b.geometry == Some(g) && b.material == Some(m)),
            t.elapsed().as_secs_f64(),
        );
        if !job.quiet {
            eprintln!(
                "validate: case {}/{} done ({:.0} s)",
                c + 1,
                job.cases,
                t_all.elapsed().as_secs_f64()
            );
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
    let mut out = format!(
        "Library {} ('{}': {} geometries, {} materials; {} / {} representatives), {} cases, seed {}; \
         targets and final evaluation: fast forward model; psi = {}, pool = {}, K = {}, {} starts.\n\n\
         | solver | cases | within 7 % | exact recovery | within 1 % | median time | 95th pct time | median error |\n\
         |---|---|---|---|---|---|---|---|\n",
        lib.dir.display(),
        lib.manifest.profile,
        ng,
        nm,
        lib.manifest.geometry.representatives,
        lib.manifest.material.representatives,
        job.cases,
        job.seed,
        opt.psi,
        opt.pool,
        opt.k,
        job.general.starts
    );
    out += &row("geometry (material fixed)", &tg);
    out += &row("  exhaustive scan, same cases", &eg);
    out += &row("material (geometry fixed)", &tm);
    out += &row("  exhaustive scan, same cases", &em);
    out += &row("general (both unknown)", &tgen);
    if job.sweep {
        out += &sweep(lib, job)?;
    }
    Ok(out)
}

/// Error against run time of the geometry solver over its knobs (pool re-ranked, psi, final).
fn sweep(lib: &Library, job: &ValidateJob) -> Result<String> {
    let mi = lib.material_items()?;
    let (ng, nm) = (lib.manifest.geometries, lib.manifest.materials);
    // (pool, psi, re-rank with the fast evaluator, final evaluation)
    let settings: Vec<(usize, usize, bool, Final)> = vec![
        (1, 1, false, Final::Library),
        (20, 1, false, Final::Library),
        (80, 1, false, Final::Library),
        (4, 1, true, Final::Library),
        (16, 1, true, Final::Library),
        (16, 1, true, Final::Fast),
        (16, 4, true, Final::Fast),
    ];
    let mut rng = Rng::new(job.seed ^ 0x5eed);
    let cases: Vec<(usize, usize)> = (0..job.cases)
        .map(|_| (rng.below(ng as u64) as usize, rng.below(nm as u64) as usize))
        .collect();
    let looks: Vec<Look> = cases
        .iter()
        .map(|&(g, m)| combo_look(lib, g, m))
        .collect::<Result<_>>()?;
    let mut out = String::from("\nError against run time (geometry solver, same cases):\n\n| re-ranked pool | re-rank by | psi | final | median error | within 7 % | recovery | median time |\n|---|---|---|---|---|---|---|---|\n");
    let mut points = Vec::new();
    for &(pool, psi, rerank_fast, fin) in &settings {
        let opt = SolveOptions {
            pool,
            psi,
            rerank_fast,
            final_eval: fin,
            k: 1,
            ..job.options.clone()
        };
        let mut t = Tally::default();
        for (&(g, m), look) in cases.iter().zip(&looks) {
            let mat = parse_material(&mi[m].spec)?;
            let s = Instant::now();
            let r = crate::solve::geometry::solve(lib, look, &mat, &mi[m].spec, Some(m), &opt)?;
            let b = r.candidates.first();
            t.add(
                b.map_or(f64::INFINITY, |b| b.error),
                b.and_then(|b| b.geometry) == Some(g),
                s.elapsed().as_secs_f64(),
            );
        }
        let (me, mt) = (Tally::q(&t.errors, 0.5), Tally::q(&t.times, 0.5));
        points.push((mt, me));
        let by = if rerank_fast {
            "quick BVNDF + fast"
        } else {
            "binned column"
        };
        out += &format!(
            "| {pool} | {by} | {psi} | {fin:?} | {:.2} % | {:.1} % | {:.1} % | {:.3} s |\n",
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
