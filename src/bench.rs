//! `biscale bench`: speed and accuracy tables of the forward model, printed as Markdown so that
//! `docs/` can quote them beside the command that made them.

use crate::bvndf::{BvndfConfig, CompactBvndf};
use crate::error::Result;
use crate::exact::ExactEvaluator;
use crate::fast::FACET_WIDTH;
use crate::frame::DirPair;
use crate::generators::parse_generator;
use crate::heightfield::Heightfield;
use crate::library::progress::Progress;
use crate::lightlobes::LightLobes;
use crate::material::parse_material;
use crate::pairs::{default_pairs, AnglePair};
use crate::prefilter::{PrefilterConfig, Prefiltered};
use crate::rng::Rng;
use std::time::Instant;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Median wall time of `reps` runs of `f` (seconds; at least one run), and the last result.
pub(crate) fn time<T>(reps: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    match try_time::<T, std::convert::Infallible>(reps, || Ok(f())) {
        Ok(r) => r,
        Err(never) => match never {},
    }
}

/// [`time`] of a fallible `f`: the first error ends the runs and is returned.
pub(crate) fn try_time<T, E>(
    reps: usize,
    mut f: impl FnMut() -> std::result::Result<T, E>,
) -> std::result::Result<(f64, T), E> {
    let mut run = || -> std::result::Result<(f64, T), E> {
        let t = Instant::now();
        let v = f()?;
        Ok((t.elapsed().as_secs_f64(), v))
    };
    let (t0, mut last) = run()?;
    let mut times = vec![t0];
    for _ in 1..reps {
        let (t, v) = run()?;
        times.push(t);
        last = v;
    }
    Ok((median(times), last))
}

fn geometry(spec: &str) -> Result<Heightfield> {
    parse_generator(spec)?.build()
}

fn default_dirs() -> Vec<DirPair> {
    default_pairs(70).iter().map(|p| p.dirs()).collect()
}

/// Relative RMS error of `got` against `want`: `sqrt(Σ (g - w)² / Σ w²)`.
pub fn relative_rms(got: &[f64], want: &[f64]) -> f64 {
    let num: f64 = got.iter().zip(want).map(|(g, w)| (g - w) * (g - w)).sum();
    let den: f64 = want.iter().map(|w| w * w).sum();
    if den > 0.0 {
        (num / den).sqrt()
    } else {
        num.sqrt()
    }
}

/// [`relative_rms`] over the pairs whose two directions are within 85° of the normal.
fn relative_rms_85(pairs: &[AnglePair], got: &[f64], want: &[f64]) -> f64 {
    let keep: Vec<usize> = (0..pairs.len())
        .filter(|&i| pairs[i].theta_i <= 85.0 && pairs[i].theta_o <= 85.0)
        .collect();
    let pick = |v: &[f64]| keep.iter().map(|&i| v[i]).collect::<Vec<f64>>();
    relative_rms(&pick(got), &pick(want))
}

/// The cases of `bench exact` (geometry, material): sharp and moderate glossy lobes on rough
/// and smooth surfaces, where few facets carry the sum, and a broad blend for comparison.
pub const EXACT_CASES: [(&str, &str); 5] = [
    ("fbm:n=32,amplitude=1.5,seed=4", "ggx:alpha=0.03"),
    ("fbm:n=32,amplitude=1.5,seed=4", "ggx:alpha=0.1"),
    ("fbm:n=64,amplitude=3,seed=4", "ggx:alpha=0.1"),
    (
        "bumps:n=64,count=8,radius=10,height=3,seed=2",
        "ggx:alpha=0.01",
    ),
    (
        "sine:n=64,period=8,amplitude=3.5",
        "ward:alpha=0.117+lambert:albedo=0.17",
    ),
];

/// The exact method's own error table: at the 490 default pairs, for each (geometry,
/// material) case, the estimate of its error ([`crate::exact::Estimated::noise`]) and its
/// error against the method at `reference` rays per cell side, at 2 × 2 rays and with the
/// automatic choice ([`crate::exact::fbar_to_tolerance`] at `tol`, `forward`'s default), with
/// the times.
pub fn exact(
    cases: &[(String, String)],
    reference: usize,
    tol: f64,
    progress: &Progress,
) -> Result<String> {
    let bar = progress.bar(cases.len() as u64, "bench exact: cases");
    let pairs = default_pairs(70);
    let dirs: Vec<DirPair> = pairs.iter().map(|p| p.dirs()).collect();
    // Every case is read before any is computed, so a bad one fails at once.
    let inputs = cases
        .iter()
        .map(|(gs, ms)| {
            Ok((
                gs,
                ms,
                crate::heightmap_io::resolve_geometry(gs, 10.0, 1.0)
                    .map_err(|e| e.within("--case"))?,
                parse_material(ms).map_err(|e| e.within("--case"))?,
            ))
        })
        .collect::<Result<Vec<_>>>()?;
    let mut rows = String::new();
    for (gs, ms, hf, mat) in inputs {
        let truth = ExactEvaluator::new(&hf, reference).fbar(&mat, &dirs);
        let t = Instant::now();
        let fixed = ExactEvaluator::new(&hf, 2).fbar_many_estimated(&[&mat], &dirs);
        let fixed_s = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let auto = crate::exact::fbar_to_tolerance(&hf, &[&mat], &dirs, tol, None, |_, _, _| {});
        let auto_s = t.elapsed().as_secs_f64();
        let errors = |v: &[f64]| {
            format!(
                "{:.2} % / {:.2} %",
                100.0 * relative_rms(v, &truth),
                100.0 * relative_rms_85(&pairs, v, &truth)
            )
        };
        rows.push_str(&format!(
            "| `{gs}` | `{ms}` | {:.2} % | {} | {fixed_s:.2} s | {} | {} | {auto_s:.2} s |\n",
            100.0 * fixed.noise,
            errors(&fixed.values[0]),
            auto.passes_text(),
            errors(&auto.values[0]),
        ));
        bar.inc(1);
    }
    bar.finish();
    Ok(format!(
        "The exact method's error against itself at {reference}×{reference} view rays per cell \
         (relative RMS over the 490 default pairs / over those up to 85°), at 2×2 rays and with \
         the automatic choice of `forward` (tolerance {:.2} % on the estimated error)\n\n\
         | geometry | material | 2×2: estimated | 2×2: error all / ≤ 85° | 2×2: time | automatic: rays and estimate per pass | automatic: error all / ≤ 85° | automatic: time |\n\
         |---|---|---|---|---|---|---|---|\n{rows}",
        100.0 * tol
    ))
}

/// Speed table: compact BVNDF build of 128² geometries, prefiltered material build, and one
/// evaluation of the 490 default pairs by each method; also the compact BVNDF at the 7 lights
/// only (the `default` library's light lobes), its evaluation of the same pairs (all lit from
/// those lights) and its error against the exact method beside `forward`'s default build's.
pub fn speed(reps: usize, progress: &Progress) -> Result<String> {
    let threads = rayon::current_num_threads();
    let bar = progress.bar(9, "bench speed: 5 surfaces, then 4 materials");
    let dirs = default_dirs();
    let mut out = format!(
        "Forward model speed ({threads} threads; median of {reps}; 490 pairs = 7 lights × 70 views)\n\n\
         | geometry (128²) | BVNDF build | BVNDF size | fast 490 pairs | fast, one vMF per cluster | BVNDF build, `forward`'s default | fast 490 pairs, `forward`'s default | exact 490 pairs (s=2) | light lobes build | light lobes size | light lobes, 490 pairs | error: light lobes / `forward`'s default |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    );
    let mat = parse_material("ggx:alpha=0.2+lambert:albedo=0.3")?;
    let pre = Prefiltered::build(&mat, &PrefilterConfig::default());
    // The compact BVNDF at the 7 lights only, as the `default` library builds and stores it
    // (its view grid, rays and clusters): the 490 pairs are lit from those lights.
    let (lp, _) = crate::library::profile::LibraryProfile::load("default")?;
    let layout = crate::library::build::gamma_layout(&lp);
    let (rays, clusters) = (lp.geometry.rays, lp.geometry.lobe_clusters);
    for spec in ["bumps", "vgroove", "fbm", "bricks", "weave"] {
        let hf = geometry(spec)?;
        let cfg = BvndfConfig::default();
        let (tb, geo) = time(reps, || CompactBvndf::build(&hf, &cfg));
        let (tf, _) = time(reps.max(20), || crate::fast::fbar(&geo, &pre, &dirs));
        // The libraries' representation (no sub-lobes), for the cost of the sub-lobes.
        let coarse = CompactBvndf::build(&hf, &BvndfConfig::library());
        let (tc, _) = time(reps.max(20), || crate::fast::fbar(&coarse, &pre, &dirs));
        // The `forward` command's default build (finer grid, seen-area control variate).
        let (tw, fwd) = time(reps.min(3), || {
            CompactBvndf::build(&hf, &BvndfConfig::forward())
        });
        let (tfw, vfw) = time(reps.max(20), || crate::fast::fbar(&fwd, &pre, &dirs));
        let ev = ExactEvaluator::new(&hf, 2);
        let (te, exact) = time(1, || ev.fbar(&mat, &dirs));
        let (tl, lobes) = time(reps, || LightLobes::build(&layout, &hf, rays, clusters));
        let (tlf, vl) = time(reps.max(20), || crate::fast::fbar(&lobes, &pre, &dirs));
        out.push_str(&format!(
            "| {spec} | {:.1} ms | {:.2} MB | {:.3} ms | {:.3} ms | {:.1} ms | {:.3} ms | {:.2} s \
             | {:.1} ms | {:.2} MB | {:.3} ms | {:.2} % / {:.2} % |\n",
            tb * 1e3,
            geo.bytes() as f64 / 1e6,
            tf * 1e3,
            tc * 1e3,
            tw * 1e3,
            tfw * 1e3,
            te,
            tl * 1e3,
            lobes.bytes() as f64 / 1e6,
            tlf * 1e3,
            100.0 * relative_rms(&vl, &exact),
            100.0 * relative_rms(&vfw, &exact),
        ));
        bar.inc(1);
    }
    out.push_str("\n| material | prefiltered F build | F size |\n|---|---|---|\n");
    for spec in [
        "lambert:albedo=0.5",
        "ggx:alpha=0.2+lambert:albedo=0.3",
        "blinn:n=60+lambert:albedo=0.2",
        "ct:m=0.19,f0=0.23",
    ] {
        let m = parse_material(spec)?;
        let (tp, p) = time(reps.min(3), || {
            Prefiltered::build(&m, &PrefilterConfig::default())
        });
        out.push_str(&format!(
            "| {spec} | {:.1} ms | {:.2} MB |\n",
            tp * 1e3,
            p.bytes() as f64 / 1e6
        ));
        bar.inc(1);
    }
    bar.finish();
    Ok(out)
}

/// A random geometry spec for the accuracy table.
fn random_geometry(r: &mut Rng) -> String {
    let seed = r.below(1_000_000);
    match r.below(8) {
        0 => format!(
            "bumps:count={},radius={:.1},height={:.1},seed={seed}",
            4 + r.below(20),
            r.range(5.0, 20.0),
            r.range(1.0, 8.0)
        ),
        1 => format!(
            "vgroove:period={},depth={:.1}",
            [8, 16, 32][r.below(3) as usize],
            r.range(1.0, 10.0)
        ),
        2 => format!(
            "sine:period={},amplitude={:.1}",
            [16, 32, 64][r.below(3) as usize],
            r.range(0.5, 8.0)
        ),
        3 => format!(
            "fbm:octaves={},amplitude={:.1},seed={seed}",
            2 + r.below(5),
            r.range(1.0, 12.0)
        ),
        4 => format!("bricks:depth={:.1}", r.range(1.0, 8.0)),
        5 => format!(
            "dimples:count={},radius={:.1},height={:.1},seed={seed}",
            4 + r.below(20),
            r.range(5.0, 20.0),
            r.range(1.0, 8.0)
        ),
        6 => format!(
            "pyramids:period={},height={:.1}",
            [16, 32][r.below(2) as usize],
            r.range(2.0, 12.0)
        ),
        _ => format!(
            "weave:period={},height={:.1}",
            [16, 32][r.below(2) as usize],
            r.range(1.0, 6.0)
        ),
    }
}

/// A random material whose glossy lobe is sharp (width log-uniform in 0.002–0.06 rad, the
/// range the fast method sums over facets), alone or with a Lambertian lobe.
fn random_sharp_material(r: &mut Rng) -> String {
    let kd = r.range(0.05, 0.6);
    let w = (r.range(0.002f64.ln(), 0.06f64.ln())).exp();
    match r.below(5) {
        0 => format!("ggx:alpha={w:.4}"),
        1 => format!("beckmann:alpha={w:.4},f0={:.2}", r.range(0.04, 1.0)),
        2 => format!("ggx:alpha={w:.4}+lambert:albedo={kd:.2}"),
        3 => format!("ward:alpha={w:.4}+lambert:albedo={kd:.2}"),
        _ => format!("blinn:n={:.0}+lambert:albedo={kd:.2}", 2.0 / (w * w) - 2.0),
    }
}

/// A random material spec for the accuracy table.
fn random_material(r: &mut Rng) -> String {
    let kd = r.range(0.05, 0.6);
    match r.below(7) {
        0 => format!("lambert:albedo={kd:.2}"),
        1 => format!("ggx:alpha={:.3}", r.range(0.08, 0.6)),
        2 => format!(
            "beckmann:alpha={:.3},f0={:.2}",
            r.range(0.08, 0.6),
            r.range(0.04, 1.0)
        ),
        3 => format!("ggx:alpha={:.3}+lambert:albedo={kd:.2}", r.range(0.08, 0.6)),
        4 => format!(
            "ward:alpha={:.3}+lambert:albedo={kd:.2}",
            r.range(0.08, 0.5)
        ),
        5 => format!("blinn:n={:.0}+lambert:albedo={kd:.2}", r.range(10.0, 300.0)),
        _ => format!(
            "ct:m={:.3},f0={:.2}+lambert:albedo={kd:.2}",
            r.range(0.1, 0.5),
            r.range(0.04, 0.9)
        ),
    }
}

/// What `bench accuracy` draws and how it checks.
#[derive(Debug, Clone)]
pub struct AccuracyOptions {
    /// Draw sharp materials ([`random_sharp_material`]) instead of the usual ones.
    pub sharp: bool,
    /// View rays per cell side of the exact reference (2 is where `forward` starts).
    pub exact_samples: usize,
    /// Instead, the reference's rays chosen for this estimated error
    /// ([`crate::exact::fbar_to_tolerance`], as `forward` does).
    pub exact_tol: Option<f64>,
}

impl Default for AccuracyOptions {
    fn default() -> Self {
        AccuracyOptions {
            sharp: false,
            exact_samples: 2,
            exact_tol: None,
        }
    }
}

/// Accuracy table: relative RMS error of the fast evaluator against the exact one (`s` view rays
/// per cell side, `opt.exact_samples`) at the 490 default pairs, for `cases` random (geometry,
/// material) pairs drawn with `seed` (sharp materials with `opt.sharp`), the fast method's
/// compact BVNDF built with `cfg`.
pub fn accuracy(
    cases: usize,
    seed: u64,
    cfg: &BvndfConfig,
    opt: &AccuracyOptions,
    progress: &Progress,
) -> Result<String> {
    let bar = progress.bar(cases as u64, "bench accuracy: cases (exact and fast)");
    let pairs = default_pairs(70);
    let dirs: Vec<DirPair> = pairs.iter().map(|p| p.dirs()).collect();
    let mut errs85 = Vec::new();
    let mut r = Rng::new(seed);
    let mut rows = String::new();
    let mut errs = Vec::new();
    let mut build_s = 0.0;
    for c in 0..cases {
        let gs = random_geometry(&mut r);
        let ms = if opt.sharp {
            random_sharp_material(&mut r)
        } else {
            random_material(&mut r)
        };
        let hf = geometry(&gs)?;
        let mat = parse_material(&ms)?;
        // The reference, with its own estimated error (a share of the fast method's error
        // below is the reference's).
        let (exact, samples, noise) = match opt.exact_tol {
            Some(tol) => {
                let c =
                    crate::exact::fbar_to_tolerance(&hf, &[&mat], &dirs, tol, None, |_, _, _| {});
                (c.values, c.samples, c.noise)
            }
            None => {
                let n = opt.exact_samples;
                let e = ExactEvaluator::new(&hf, n).fbar_many_estimated(&[&mat], &dirs);
                (e.values, n, e.noise)
            }
        };
        let exact = exact.into_iter().next().unwrap_or_default();
        let t = Instant::now();
        let geo = CompactBvndf::build(&hf, cfg);
        build_s += t.elapsed().as_secs_f64();
        let pre = Prefiltered::build_split(&mat, &PrefilterConfig::default(), FACET_WIDTH);
        let fast = crate::fast::fbar_with_facets(&geo, &pre, &dirs);
        let e = relative_rms(&fast, &exact);
        let e85 = relative_rms_85(&pairs, &fast, &exact);
        errs.push(e);
        errs85.push(e85);
        rows.push_str(&format!(
            "| {c} | `{gs}` | `{ms}` | {:.2} % | {:.2} % | {samples}×{samples}, {:.2} % |\n",
            100.0 * e,
            100.0 * e85,
            100.0 * noise
        ));
        bar.inc(1);
    }
    bar.finish();
    let reference = match opt.exact_tol {
        Some(t) => format!(
            "view rays per cell from both ends chosen for an estimated error within {:.2} %",
            100.0 * t
        ),
        None => format!(
            "{0}×{0} view rays per cell from both ends",
            opt.exact_samples
        ),
    };
    let sharp = if opt.sharp {
        "; sharp materials: glossy widths 0.002–0.06 rad"
    } else {
        ""
    };
    let summary = |name: &str, errs: &[f64]| {
        let mut sorted = errs.to_vec();
        sorted.sort_by(f64::total_cmp);
        let q = |f: f64| sorted[((sorted.len() - 1) as f64 * f).round() as usize];
        format!(
            "| {name} | {:.2} % | {:.2} % | {:.2} % | {:.0} % |\n",
            100.0 * q(0.5),
            100.0 * q(0.9),
            100.0 * q(1.0),
            100.0 * errs.iter().filter(|e| **e <= 0.03).count() as f64 / errs.len() as f64
        )
    };
    Ok(format!(
        "Fast vs exact evaluator (exact: {reference}{sharp}): relative RMS error over \
         the 490 default pairs, {cases} random cases, seed {seed}; compact BVNDF: {} × {} grid, {} \
         surface points for the pairs (+ {} seen rays per direction), {} clusters, {} sub-lobes, {}; its builds took {build_s:.1} s in all \
         ({:.3} s per geometry)\n\n\
         | pairs | median | 90th percentile | max | cases ≤ 3 % |\n|---|---|---|---|---|\n{}{}\n\
         | case | geometry | material | all pairs | theta ≤ 85° | exact: rays per cell, its estimated error |\n|---|---|---|---|---|---|\n{rows}",
        cfg.n_theta,
        cfg.n_phi,
        cfg.points,
        cfg.seen_rays,
        cfg.clusters,
        cfg.sub_lobes,
        if cfg.seen_phi > cfg.n_phi {
            format!(
                "seen table {} azimuths × {} height bands",
                cfg.seen_phi.div_ceil(cfg.n_phi) * cfg.n_phi,
                cfg.seen_bands
            )
        } else {
            "no seen table".to_string()
        },
        build_s / cases as f64,
        summary("all 490 (theta to 89°)", &errs),
        summary("theta_i, theta_o ≤ 85°", &errs85),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_runs_at_least_once_and_try_time_stops_at_the_first_error() {
        let mut calls = 0;
        let (t, v) = time(0, || {
            calls += 1;
            calls
        });
        assert_eq!((calls, v), (1, 1));
        assert!(t >= 0.0 && t.is_finite());
        let (_, v) = time(3, || {
            calls += 1;
            calls
        });
        assert_eq!(v, 4);
        let mut runs = 0;
        let r: std::result::Result<(f64, ()), String> = try_time(5, || {
            runs += 1;
            if runs == 2 {
                Err(format!("run {runs}"))
            } else {
                Ok(())
            }
        });
        assert_eq!(r.err().as_deref(), Some("run 2"));
        assert_eq!(runs, 2);
    }

    #[test]
    fn sharp_random_materials_parse_and_go_to_the_facet_sum() {
        let mut r = Rng::new(7);
        for _ in 0..50 {
            let spec = random_sharp_material(&mut r);
            let m = parse_material(&spec).unwrap();
            let w = m.min_lobe_width().unwrap();
            assert!((0.0019..0.0601).contains(&w), "{spec}: width {w}");
            let (_, sharp) = m.split_by_width(FACET_WIDTH);
            assert_eq!(sharp.lobes.len(), 1, "{spec}");
        }
    }

    #[test]
    fn the_exact_table_has_a_row_per_case_and_reads_every_case_first() {
        let quiet = Progress { quiet: true };
        let case = |g: &str, m: &str| (g.to_string(), m.to_string());
        let t = exact(
            &[case("vgroove:n=8,period=4", "lambert:albedo=0.5")],
            3,
            0.005,
            &quiet,
        )
        .unwrap();
        let rows: Vec<&str> = t.lines().filter(|l| l.starts_with("| `")).collect();
        assert_eq!(rows.len(), 1, "{t}");
        assert!(
            rows[0].contains("`vgroove:n=8,period=4`") && rows[0].contains("2×2: "),
            "{t}"
        );
        assert!(!t.contains("NaN"), "{t}");
        // The bad second case fails before the first is computed.
        let e = exact(
            &[
                case("fbm:n=256,seed=1", "ggx:alpha=0.01"),
                case("flat", "ggx:alpha=-1"),
            ],
            64,
            0.005,
            &quiet,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("--case") && e.contains("alpha"), "{e}");
    }
}
