//! `biscale bench library-speed` and `biscale bench library-accuracy`: what one library item costs
//! to precompute (and what a whole profile would cost on this machine), and how well `fbar`
//! reconstructed from the representatives (Eq. 12) matches the exact evaluator.

use super::build::{gamma_layout, geometry_data, lobe_bytes, prefilter_config};
use super::items::{geometry_items, material_items};
use super::profile::LibraryProfile;
use super::progress::Progress;
use super::Library;
use crate::error::{Error, Result};
use crate::exact::ExactEvaluator;
use crate::frame::{dir_from_deg, DirPair, Vec3};
use crate::gamma::Response;
use crate::generators::parse_generator;
use crate::material::{parse_material, Material};
use crate::prefilter::Prefiltered;
use crate::rng::Rng;
use rayon::prelude::*;
use std::path::Path;
use std::time::Instant;

fn quantiles(mut v: Vec<f64>) -> (f64, f64, f64) {
    if v.is_empty() {
        return (f64::NAN, f64::NAN, f64::NAN);
    }
    v.sort_by(f64::total_cmp);
    let q = |f: f64| v[((v.len() - 1) as f64 * f).round() as usize];
    (q(0.5), q(0.9), v[v.len() - 1])
}

/// Time `sample` geometries and `sample / 4` materials of `profile`, spread over its families,
/// and extrapolate the whole profile's precompute on this machine.
pub fn speed(profile: &str, sample: usize, progress: &Progress) -> Result<String> {
    let (prof, path) = LibraryProfile::load(profile)?;
    let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
    let geos = geometry_items(&prof, &base)?;
    let mats = material_items(&prof, &base)?;
    let layout = gamma_layout(&prof);
    let pick = |n: usize, k: usize| -> Vec<usize> {
        (0..k.min(n)).map(|i| i * n / k.min(n).max(1)).collect()
    };
    // Items in parallel, as `library build` runs them (one item's serial parts, generating the
    // heightfield and clustering its normals, would otherwise leave a core idle).
    let t = Instant::now();
    let bar = progress.bar(
        pick(geos.len(), sample).len() as u64,
        "bench library-speed: geometries",
    );
    pick(geos.len(), sample)
        .par_iter()
        .map(|&i| {
            let r = geometry_data(&geos[i], &layout, &prof)
                .and_then(|(_, lobes)| lobe_bytes(&geos[i], &layout, &prof, &lobes))
                .map(|_| ());
            bar.inc(1);
            r
        })
        .collect::<Result<Vec<()>>>()?;
    bar.finish();
    let ng = pick(geos.len(), sample).len().max(1);
    let tg = t.elapsed().as_secs_f64() / ng as f64;
    let pcfg = prefilter_config(&prof);
    let msample = pick(mats.len(), (sample / 4).max(2));
    let t = Instant::now();
    msample
        .par_iter()
        .map(|&i| parse_material(&mats[i].spec).map(|m| drop(Prefiltered::build(&m, &pcfg))))
        .collect::<Result<Vec<()>>>()?;
    let tm = t.elapsed().as_secs_f64() / msample.len().max(1) as f64;
    let threads = rayon::current_num_threads();
    let gamma_mb = (layout.rows() * prof.geometry.gamma_precision.dtype().size()) as f64 / 1e6;
    let (k, record) = (
        prof.geometry.lobe_clusters,
        crate::lightlobes::record_len(&layout, prof.geometry.lobe_clusters),
    );
    let lobes_mb = match prof.geometry.lobe_precision {
        super::profile::LobePrecision::Single => record * 4,
        super::profile::LobePrecision::Half => {
            k * crate::lightlobes::HEAD * 4 + crate::lobecodec::half_len(record, k) * 2
        }
    } as f64
        / 1e6;
    let table_mb = super::build::table_len(&prof) as f64 * 4.0 / 1e6;
    let total = tg * geos.len() as f64 + tm * mats.len() as f64;
    Ok(format!(
        "Precompute of profile '{}' on {threads} threads (items in parallel, as in `library build`):\n\n\
         | item | sampled | wall time per item | items in profile | extrapolated | stored per item |\n\
         |---|---|---|---|---|---|\n\
         | geometry ({}² heights, {} lights × {} views × {}² normals + {} light-lobe clusters, {} rays/view) | {ng} | {:.1} ms | {} | {:.1} min | {:.2} + {:.2} MB |\n\
         | material (prefiltered F, {} entries × {} samples) | {} | {:.1} ms | {} | {:.1} min | {:.2} MB |\n\n\
         Extrapolated precompute (before the merge): {:.1} min; geometry matrix {:.1} GB, light lobes {:.1} GB, material matrix {:.2} GB.\n",
        prof.name,
        prof.geometry.resolution,
        layout.lights.len(),
        layout.views.len(),
        prof.geometry.normal_grid,
        prof.geometry.lobe_clusters,
        prof.geometry.rays,
        tg * 1e3,
        geos.len(),
        tg * geos.len() as f64 / 60.0,
        gamma_mb,
        lobes_mb,
        super::build::table_len(&prof),
        pcfg.samples,
        msample.len(),
        tm * 1e3,
        mats.len(),
        tm * mats.len() as f64 / 60.0,
        table_mb,
        total / 60.0,
        gamma_mb * geos.len() as f64 / 1e3,
        lobes_mb * geos.len() as f64 / 1e3,
        table_mb * mats.len() as f64 / 1e3,
    ))
}

/// Relative RMS of `got` against `want`.
fn rel(got: &[f64], want: &[f64]) -> f64 {
    crate::bench::relative_rms(got, want)
}

/// For `geometries` random library geometries × `materials_per` random library materials each:
/// `fbar` at 7 lights × 10 views from (a) the exact evaluator, (b) the geometry's own binned
/// column, (c) the representatives' columns combined with the geometry's CX weights (Eq. 12),
/// (d) the geometry's own light lobes ([`crate::lightlobes`]) with the material's stored table,
/// (e) the representatives' light lobes combined with the CX weights (what the geometry search
/// computes), and (e) against (d): the search index's own error.
pub fn accuracy(
    dir: &Path,
    geometries: usize,
    materials_per: usize,
    seed: u64,
    progress: &Progress,
) -> Result<String> {
    let lib = Library::open(dir)?;
    let items = lib.geometry_items()?;
    let mats = lib.material_items()?;
    let layout = lib.gamma_layout();
    let gamma = lib.binned_columns()?;
    let reps = lib.array("geometry/representatives.bsa")?;
    let xs = lib.array("geometry/x.bsa")?;
    let (reps, xs) = (reps.u32s()?, xs.f32s()?);
    let c = reps.len();
    if items.is_empty() || mats.is_empty() {
        return Err(Error::new(
            dir.display().to_string(),
            "the library is empty",
        ));
    }
    let rep_cols: Vec<Vec<f32>> = reps
        .iter()
        .map(|&k| gamma.column(k as usize))
        .collect::<Result<_>>()?;
    let views: Vec<Vec3> = (0..10)
        .map(|k| {
            let u = (k as f64 + 0.5) / 10.0;
            dir_from_deg(
                u.acos().to_degrees().min(80.0),
                360.0 * (k as f64 * 0.618_034).fract(),
            )
        })
        .collect();
    let pairs: Vec<(usize, Vec3)> = (0..layout.lights.len())
        .flat_map(|l| views.iter().map(move |&v| (l, v)))
        .collect();
    let dirs: Vec<DirPair> = pairs
        .iter()
        .map(|&(l, wo)| DirPair {
            wi: layout.lights[l],
            wo,
        })
        .collect();
    let mut rng = Rng::new(seed);
    // Errors by material class: every glossy lobe at least NARROW wide, or not.
    const NARROW: f64 = 0.15;
    let (mut e_bin, mut e_cmp, mut e_rec) = (Vec::new(), Vec::new(), Vec::new());
    let (mut w_bin, mut w_rec) = (Vec::new(), Vec::new());
    let (mut e_lob, mut e_lrec, mut w_lob) = (Vec::new(), Vec::new(), Vec::new());
    let mut e_idx = Vec::new();
    let lobes = lib.geometry_lobes()?;
    let mat_index: Vec<usize> = (0..geometries * materials_per)
        .map(|_| rng.below(mats.len() as u64) as usize)
        .collect();
    let mut picks = mat_index.chunks(materials_per.max(1));
    let t = Instant::now();
    let bar = progress.bar(geometries as u64, "bench library-accuracy: geometries");
    for _ in 0..geometries {
        let j = rng.below(items.len() as u64) as usize;
        let hf = parse_generator(&items[j].spec)?.build()?;
        let idx = picks.next().unwrap_or(&[]);
        let chosen: Vec<Material> = idx
            .iter()
            .map(|&m| parse_material(&mats[m].spec))
            .collect::<Result<_>>()?;
        let refs: Vec<&Material> = chosen.iter().collect();
        let exact = ExactEvaluator::new(&hf, 2).fbar_many(&refs, &dirs);
        let own = gamma.column(j)?;
        let own_lobes = lobes.get(j)?;
        for ((m, ex), &mi) in chosen.iter().zip(&exact).zip(idx) {
            let pf = crate::solve::material_prefiltered(&lib, m, Some(mi))?;
            let lob = crate::fast::fbar(&own_lobes, &pf, &dirs);
            let mut lrec = vec![0.0; pairs.len()];
            for (k, &r) in reps.iter().enumerate() {
                let w = xs[j * c + k] as f64;
                if w != 0.0 {
                    let v = crate::fast::fbar(&lobes.get(r as usize)?, &pf, &dirs);
                    for (a, b) in lrec.iter_mut().zip(v) {
                        *a += w * b;
                    }
                }
            }
            let lrec: Vec<f64> = lrec.into_iter().map(|v| v.max(0.0)).collect();
            e_lob.push(rel(&lob, ex));
            e_lrec.push(rel(&lrec, ex));
            e_idx.push(rel(&lrec, &lob));
            let resp = Response::new(&layout, m, &pairs);
            let bin = resp.apply(&own);
            let mut rec = vec![0.0; pairs.len()];
            for (k, rc) in rep_cols.iter().enumerate() {
                let w = xs[j * c + k] as f64;
                if w != 0.0 {
                    for (r, v) in rec.iter_mut().zip(resp.apply(rc)) {
                        *r += w * v;
                    }
                }
            }
            let rec: Vec<f64> = rec.into_iter().map(|v| v.max(0.0)).collect();
            e_bin.push(rel(&bin, ex));
            e_cmp.push(rel(&rec, &bin));
            e_rec.push(rel(&rec, ex));
            if m.min_lobe_width().is_none_or(|w| w >= NARROW) {
                w_bin.push(rel(&bin, ex));
                w_rec.push(rel(&rec, ex));
                w_lob.push(rel(&lob, ex));
            }
        }
        bar.inc(1);
    }
    bar.finish();
    let n = e_bin.len();
    let row = |name: &str, v: Vec<f64>| {
        let within = v.iter().filter(|&&e| e <= 0.05).count() as f64 / v.len().max(1) as f64;
        let (q50, q90, max) = quantiles(v);
        format!(
            "| {name} | {:.2} % | {:.2} % | {:.2} % | {:.0} % |\n",
            q50 * 100.0,
            q90 * 100.0,
            max * 100.0,
            within * 100.0
        )
    };
    Ok(format!(
        "Library {} ('{}': {} geometries, {} representatives): {n} (geometry, material) cases, {} pairs each \
         (7 lights × 10 views to 80°), exact evaluator with 2×2 rays per cell; {:.0} s.\n\n\
         | relative RMS of fbar | median | 90th pct | max | cases ≤ 5 % |\n|---|---|---|---|---|\n{}{}{}{}{}{}{}{}{}",
        dir.display(),
        lib.manifest.profile,
        items.len(),
        c,
        pairs.len(),
        t.elapsed().as_secs_f64(),
        row("binned BVNDF vs exact", e_bin),
        row("representatives (Eq. 12) vs binned", e_cmp),
        row("representatives (Eq. 12) vs exact", e_rec),
        row(&format!("binned vs exact, glossy lobes ≥ {NARROW} rad ({} cases)", w_bin.len()), w_bin),
        row("representatives vs exact, same cases", w_rec),
        row("light lobes vs exact", e_lob),
        row("representatives' light lobes (Eq. 12) vs exact", e_lrec),
        row("light lobes vs exact, glossy lobes ≥ 0.15 rad", w_lob),
        row("representatives' light lobes (Eq. 12) vs the item's light lobes", e_idx),
    ))
}
