//! The `forward` job: the large-scale `fbar` of one (geometry, material) pair at given direction
//! pairs, by the exact or the fast evaluator. Validates every input before any expensive work and
//! writes its CSV atomically.

use crate::bvndf::{BvndfConfig, CompactBvndf};
use crate::error::{Error, Result};
use crate::exact::ExactEvaluator;
use crate::heightfield::Heightfield;
use crate::material::{parse_material, Material};
use crate::pairs::{default_pairs, format_output, read_pairs, AnglePair};
use crate::prefilter::{PrefilterConfig, Prefiltered};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    Exact,
    Fast,
}

/// Everything the `forward` command takes.
#[derive(Debug, Clone)]
pub struct ForwardJob {
    pub geometry: String,
    pub patch_size_mm: f64,
    pub height_scale: f64,
    pub material: String,
    /// `None`: the built-in 490-pair sample set.
    pub pairs: Option<PathBuf>,
    pub method: Method,
    /// `None`: write the CSV to standard output.
    pub out: Option<PathBuf>,
    /// View rays per cell side of the exact evaluator; `None`: as many as `exact_tol` needs
    /// ([`crate::exact::fbar_to_tolerance`]).
    pub exact_samples: Option<usize>,
    /// With `exact_samples: None`, the exact method's estimated relative RMS error to reach.
    pub exact_tol: f64,
    pub bvndf: BvndfConfig,
    pub prefilter: PrefilterConfig,
    pub quiet: bool,
}

impl Default for ForwardJob {
    fn default() -> Self {
        ForwardJob {
            geometry: "bumps".into(),
            patch_size_mm: 10.0,
            height_scale: 1.0,
            material: "ggx:alpha=0.2+lambert:albedo=0.3".into(),
            pairs: None,
            method: Method::Fast,
            out: None,
            exact_samples: None,
            exact_tol: DEFAULT_EXACT_TOL,
            bvndf: BvndfConfig::forward(),
            prefilter: PrefilterConfig::default(),
            quiet: false,
        }
    }
}

/// The exact method's default tolerance on its estimated relative RMS error (0.5 %): a fifth of
/// the 1 % within which the method is held to a reference, leaving room for the reference's own.
pub const DEFAULT_EXACT_TOL: f64 = 0.005;

/// The result of a forward job.
pub struct ForwardResult {
    pub pairs: Vec<AnglePair>,
    pub fbar: Vec<f64>,
    pub csv: String,
}

/// The memory the system says is available (`MemAvailable` of `/proc/meminfo`), in bytes;
/// `None` where that is not known.
fn available_memory() -> Option<f64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024.0)
}

fn log(quiet: bool, msg: impl AsRef<str>) {
    if !quiet {
        crate::library::progress::line(&format!("biscale forward: {}", msg.as_ref()));
    }
}

/// `--out` before any work: a file path (not a directory, nor a path ending in `/`) in a
/// directory that exists (a mistyped directory is not created).
fn check_out(out: &std::path::Path) -> Result<()> {
    let name = out.display().to_string();
    if out.is_dir() || name.ends_with('/') {
        let why = if out.is_dir() {
            "is a directory"
        } else {
            "ends with '/', which names a directory"
        };
        return Err(Error::new(
            "--out",
            format!("{name} {why}; expected a CSV file path"),
        ));
    }
    match out.parent().filter(|d| !d.as_os_str().is_empty()) {
        Some(dir) if !dir.is_dir() => Err(Error::new(
            "--out",
            format!(
                "{name}: the directory {} does not exist; expected a file in an existing directory",
                dir.display()
            ),
        )),
        _ => Ok(()),
    }
}

/// Load inputs in the order cheapest first, so bad input fails before any expensive work.
pub fn load_inputs(job: &ForwardJob) -> Result<(Vec<AnglePair>, Material, Heightfield)> {
    let pairs = match &job.pairs {
        Some(p) => read_pairs(p)?,
        None => default_pairs(70),
    };
    let mat = parse_material(&job.material).map_err(|e| e.within("--material"))?;
    if !(job.patch_size_mm.is_finite() && job.patch_size_mm > 0.0) {
        return Err(Error::new(
            "--patch-size",
            format!("{} mm: expected a positive size", job.patch_size_mm),
        ));
    }
    if !(job.height_scale.is_finite() && job.height_scale >= 0.0) {
        return Err(Error::new(
            "--height-scale",
            format!("{}: expected a non-negative factor", job.height_scale),
        ));
    }
    let hf =
        crate::heightmap_io::resolve_geometry(&job.geometry, job.patch_size_mm, job.height_scale)
            .map_err(|e| e.within("--geometry"))?;
    Ok((pairs, mat, hf))
}

pub fn run(job: &ForwardJob) -> Result<ForwardResult> {
    if let Some(out) = &job.out {
        check_out(out)?;
    }
    let t0 = Instant::now();
    let (pairs, mat, hf) = load_inputs(job)?;
    let (lo, hi) = hf.min_max();
    log(
        job.quiet,
        format!(
            "geometry {} ({}×{} samples, relief {:.4} grid units, {:.4} mm) loaded in {:.1} ms",
            hf.name,
            hf.width(),
            hf.height(),
            hi - lo,
            (hi - lo) * hf.cell_mm,
            t0.elapsed().as_secs_f64() * 1e3
        ),
    );
    log(
        job.quiet,
        format!("material {}; {} direction pairs", mat.spec(), pairs.len()),
    );
    let dirs: Vec<_> = pairs.iter().map(|p| p.dirs()).collect();
    let fbar = match job.method {
        Method::Exact => {
            let t = Instant::now();
            let facets = 2 * hf.width() * hf.height();
            // Every pair is shaded from each end: seconds to minutes on a 128² map.
            let bar = crate::library::progress::Progress { quiet: job.quiet }
                .bar(2 * dirs.len() as u64, "exact: pairs (from each end)");
            let (v, how) = match job.exact_samples {
                Some(n) => {
                    let e = ExactEvaluator::new(&hf, n)
                        .with_progress(&bar)
                        .fbar_many_estimated(&[&mat], &dirs);
                    (
                        e.values,
                        format!(
                            "{n}×{n} view rays per cell from each end (--exact-samples), \
                             estimated error {:.2} %",
                            100.0 * e.noise
                        ),
                    )
                }
                None => {
                    let c = crate::exact::fbar_to_tolerance(
                        &hf,
                        &[&mat],
                        &dirs,
                        job.exact_tol,
                        Some(&bar),
                        |n, e, next| {
                            if let Some(m) = next {
                                log(
                                    job.quiet,
                                    format!(
                                        "exact: {n}×{n} rays per cell: estimated error {:.2} %, \
                                         over the {:.2} % tolerance (--exact-tol); again at \
                                         {m}×{m}, about {:.0}× the rays",
                                        100.0 * e,
                                        100.0 * job.exact_tol,
                                        (m * m) as f64 / (n * n) as f64
                                    ),
                                );
                            }
                        },
                    );
                    let over = if c.noise > job.exact_tol {
                        "; still over the tolerance at the most rays the automatic choice \
                         casts: --exact-samples up to 16 goes further"
                            .to_string()
                    } else {
                        String::new()
                    };
                    let how = format!(
                        "view rays per cell from each end and estimated error {} \
                         (tolerance {:.2} %, --exact-tol){over}",
                        c.passes_text(),
                        100.0 * job.exact_tol
                    );
                    (c.values, how)
                }
            };
            bar.finish();
            log(
                job.quiet,
                format!(
                    "exact: {facets} facets, {how}, evaluated in {:.3} s",
                    t.elapsed().as_secs_f64()
                ),
            );
            v.into_iter().next().unwrap_or_default()
        }
        Method::Fast => {
            let need = job.bvndf.peak_bytes(rayon::current_num_threads());
            if let Some(have) = available_memory() {
                if need > have {
                    return Err(Error::new(
                        "--n-theta, --n-phi, --clusters",
                        format!(
                            "the compact BVNDF of {} × {} directions and {} clusters needs about \
                             {:.1} GB and {:.1} GB is available; expected a smaller grid or \
                             fewer clusters (the default needs about {:.1} GB)",
                            job.bvndf.n_theta,
                            job.bvndf.n_phi,
                            job.bvndf.clusters,
                            need / 1e9,
                            have / 1e9,
                            BvndfConfig::forward().peak_bytes(rayon::current_num_threads()) / 1e9
                        ),
                    ));
                }
            }
            let t = Instant::now();
            let geo = CompactBvndf::build_with(
                &hf,
                &job.bvndf,
                &crate::library::progress::Progress { quiet: job.quiet },
            );
            log(
                job.quiet,
                format!(
                    "fast: compact BVNDF ({} lobes, {} directions ({} polar nodes to {:.1}°), pairs from {} surface points, {} seen rays per direction, {}, {:.2} MB) built in {:.1} ms",
                    geo.clusters,
                    geo.grid.len(),
                    geo.grid.thetas.len(),
                    geo.grid.thetas.last().map_or(0.0, |t| t.to_degrees()),
                    job.bvndf.points,
                    job.bvndf
                        .seen_rays
                        .min(crate::bvndf::SEEN_PER_CELL * hf.width() * hf.height()),
                    match &geo.seen {
                        Some(t) => format!(
                            "seen table of {} directions ({} cast) × {} height bands",
                            t.grid.len(),
                            t.cast,
                            t.bands
                        ),
                        None => "no seen table".to_string(),
                    },
                    geo.bytes() as f64 / 1e6,
                    t.elapsed().as_secs_f64() * 1e3
                ),
            );
            let t = Instant::now();
            let pre = Prefiltered::build_split(&mat, &job.prefilter, crate::fast::FACET_WIDTH);
            log(
                job.quiet,
                format!(
                    "fast: prefiltered material ({:.2} MB) built in {:.1} ms{}",
                    pre.bytes() as f64 / 1e6,
                    t.elapsed().as_secs_f64() * 1e3,
                    match pre.sharp() {
                        Some((m, r)) => format!(
                            "; its lobes narrower than {} rad ({}) are summed over the {} facet \
                             normals of the curved clusters within {:.3} rad of each half vector, \
                             those facets' visibility tested by rays (all of them up to {} facets \
                             per pair, else {} of them correcting the visibility model)",
                            crate::fast::FACET_WIDTH,
                            m.spec(),
                            geo.facets.len(),
                            r,
                            crate::facetrays::DIRECT_POINTS,
                            crate::facetrays::DIRECT_POINTS
                        ),
                        None => String::new(),
                    }
                ),
            );
            let t = Instant::now();
            let v = crate::fast::fbar_with_facets(&geo, &pre, &dirs);
            log(
                job.quiet,
                format!(
                    "fast: evaluated in {:.3} ms",
                    t.elapsed().as_secs_f64() * 1e3
                ),
            );
            v
        }
    };
    let csv = format_output(&pairs, &fbar);
    if let Some(out) = &job.out {
        crate::atomic_write::write_bytes(out, csv.as_bytes()).map_err(|e| e.within("--out"))?;
        log(job.quiet, format!("wrote {}", out.display()));
    }
    Ok(ForwardResult { pairs, fbar, csv })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The same inputs give the same bytes, for both methods (parallel work sums in fixed order).
    #[test]
    fn deterministic_output() {
        for method in [Method::Exact, Method::Fast] {
            let job = ForwardJob {
                geometry: "fbm:n=16,seed=3".into(),
                method,
                quiet: true,
                prefilter: PrefilterConfig {
                    samples: 16,
                    ..PrefilterConfig::default()
                },
                ..ForwardJob::default()
            };
            let a = run(&job).unwrap().csv;
            let b = run(&job).unwrap().csv;
            assert_eq!(a, b);
            assert!(a.starts_with("theta_i,phi_i,theta_o,phi_o,fbar,brdf\n"));
        }
    }
}
