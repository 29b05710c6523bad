//! The joint search of the general solver: every (geometry, material, rotation) of the library
//! scored at once through both libraries' representatives, then the best pairs re-ranked with
//! their own library data. It replaces random starts: the alternation of [`super::general`]
//! starts from the best pairs found here.
//!
//! `fbar` is linear in the geometry's BVNDF and in the material's BRDF, so with the CX weights
//! `x_g` (geometry) and `y_m` (material) every pair's values are
//! `fbar(g, m) ≈ Σ_r Σ_s x_g[r] y_m[s] fbar(rep_r, rep_s)` (Eq. 12 applied on both sides).
//! Per geometry, `P_g = Σ_r x_g[r] fbar(rep_r, ·)` is an `S × samples` matrix (`S` material
//! representatives); with sample weights `w`, the weighted error of material `m` is
//! `y_mᵀ Q_g y_m - 2 y_mᵀ b_g + |t|²` with `Q_g = P_g W P_gᵀ` and `b_g = P_g W t`: `S² + S`
//! operations per pair, so the whole product of the two libraries is scanned in well under a
//! second on the default library.

use super::{
    material_prefiltered, rotated_samples, smallest, Candidate, Final, Look, SolveOptions,
};
use crate::error::{Error, Result};
use crate::fast::FixedLobes;
use crate::library::Library;
use crate::material::parse_material;
use rayon::prelude::*;
use std::collections::HashMap;

/// One scored pair: relative error, geometry, material, rotation index.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pair {
    /// Relative error from the pair's own library data (after [`search`]'s re-rank).
    pub error: f64,
    /// Relative error through the representatives (stage 1).
    pub search_error: f64,
    pub geometry: usize,
    pub material: usize,
    pub rotation: usize,
}

/// Pairs kept per geometry from the compressed scan before the global selection (keeps memory
/// at `geometries × KEEP_PER_GEOMETRY` whatever the material library's size).
const KEEP_PER_GEOMETRY: usize = 8;

/// Multiply-adds the pair scan may spend: 500 times the default library's scan (730 geometries
/// × 160 materials × `13² + 13` = 2 × 10⁷). A paper-sized library (164,431 geometries × 4,101
/// distinct BRDFs) would need thousands of times the default's, so there only the materials
/// closest to the look on a flat patch are paired with every geometry.
pub const MAX_OPERATIONS: f64 = 1e10;

/// Fewest materials the pair scan pairs with every geometry, whatever the budget.
pub const MIN_MATERIALS: usize = 4;

/// Score every pair through the representatives (stage 1), re-rank the best `pool` pairs with
/// their own light lobes and prefiltered tables (stage 2). Returns the number of pairs scanned
/// and the re-ranked pool, best first. When scoring every pair would cost more than
/// `max_operations` multiply-adds, only the materials that best reproduce the look on a flat
/// patch (the material solver's ranking) are paired, as many as the budget allows (at least
/// [`MIN_MATERIALS`]).
pub fn search(
    lib: &Library,
    look: &Look,
    opt: &SolveOptions,
    pool: usize,
    max_operations: f64,
) -> Result<(usize, Vec<Pair>)> {
    let gitems = lib.geometry_items()?.len();
    let mitems = lib.material_items()?;
    if gitems == 0 || mitems.is_empty() {
        return Err(Error::new(
            lib.dir.display().to_string(),
            "the library has no geometries or no materials",
        ));
    }
    let lobes = lib.geometry_lobes()?;
    let layout = lib.gamma_layout();
    let greps = lib.array("geometry/representatives.bsa")?;
    let gx = lib.array("geometry/x.bsa")?;
    let mreps = lib.array("material/representatives.bsa")?;
    let mx = lib.array("material/x.bsa")?;
    let (greps, gx, mreps, mx) = (greps.u32s()?, gx.f32s()?, mreps.u32s()?, mx.f32s()?);
    let (kr, ks) = (greps.len(), mreps.len());
    if kr == 0 || ks == 0 || gx.len() != gitems * kr || mx.len() != mitems.len() * ks {
        return Err(Error::new(
            lib.dir.display().to_string(),
            "representatives and CX weights do not match the item counts",
        ));
    }
    let per_pair = (ks * ks + ks) as f64;
    let rotations = opt.psi.max(1) as f64;
    let affordable = (max_operations / (gitems as f64 * rotations * per_pair)).floor() as usize;
    let materials: Vec<usize> = if affordable >= mitems.len() {
        (0..mitems.len()).collect()
    } else {
        let n = affordable.max(MIN_MATERIALS).min(mitems.len());
        super::material::closest_on_flat_patch(lib, look, n, opt)?.0
    };
    let rep_tables: Vec<_> = mreps
        .iter()
        .map(|&s| {
            let s = s as usize;
            material_prefiltered(lib, &parse_material(&mitems[s].spec)?, Some(s))
        })
        .collect::<Result<_>>()?;
    let rots: Vec<_> = (0..opt.psi.max(1))
        .map(|i| {
            let psi = super::psi_angle(i, opt.psi);
            rotated_samples(look, &layout.lights, psi, &opt.sampling)
        })
        .collect();
    let mut kept: Vec<Pair> = Vec::new();
    for (ri, (s, t)) in rots.iter().enumerate() {
        let pairs = super::dir_pairs(s);
        let np = pairs.len();
        // fbar(rep_r, rep_s) at the samples, weighted: [r][s][p].
        let rr: Vec<Vec<Vec<f64>>> = greps
            .par_iter()
            .map(|&r| {
                let fixed = FixedLobes::new(&lobes.get(r as usize)?, &pairs);
                Ok(rep_tables
                    .iter()
                    .map(|pf| {
                        fixed
                            .fbar(pf)
                            .iter()
                            .zip(&s.weights)
                            .map(|(v, w)| v * w)
                            .collect()
                    })
                    .collect())
            })
            .collect::<Result<_>>()?;
        let tw: Vec<f64> = t.iter().zip(&s.weights).map(|(t, w)| t * w).collect();
        let n2: f64 = tw.iter().map(|v| v * v).sum();
        if !(n2 > 0.0) {
            continue;
        }
        let best: Vec<Vec<Pair>> = (0..gitems)
            .into_par_iter()
            .map(|g| {
                let x = &gx[g * kr..(g + 1) * kr];
                // P_g (weighted), S × np.
                let mut p = vec![0.0f64; ks * np];
                for (r, &xr) in x.iter().enumerate() {
                    if xr == 0.0 {
                        continue;
                    }
                    for (si, row) in rr[r].iter().enumerate() {
                        let dst = &mut p[si * np..(si + 1) * np];
                        for (d, v) in dst.iter_mut().zip(row) {
                            *d += xr as f64 * v;
                        }
                    }
                }
                let mut q = vec![0.0f64; ks * ks];
                let mut b = vec![0.0f64; ks];
                for i in 0..ks {
                    let pi = &p[i * np..(i + 1) * np];
                    b[i] = pi.iter().zip(&tw).map(|(a, c)| a * c).sum();
                    for j in i..ks {
                        let v: f64 = pi
                            .iter()
                            .zip(&p[j * np..(j + 1) * np])
                            .map(|(a, c)| a * c)
                            .sum();
                        q[i * ks + j] = v;
                        q[j * ks + i] = v;
                    }
                }
                let errs: Vec<f64> = materials
                    .iter()
                    .map(|&m| {
                        let y = &mx[m * ks..(m + 1) * ks];
                        let mut d = n2;
                        for i in 0..ks {
                            let yi = y[i] as f64;
                            d -= 2.0 * yi * b[i];
                            for j in 0..ks {
                                d += yi * q[i * ks + j] * y[j] as f64;
                            }
                        }
                        (d.max(0.0) / n2).sqrt()
                    })
                    .collect();
                smallest(&errs, KEEP_PER_GEOMETRY)
                    .into_iter()
                    .map(|i| Pair {
                        error: errs[i],
                        search_error: errs[i],
                        geometry: g,
                        material: materials[i],
                        rotation: ri,
                    })
                    .collect()
            })
            .collect();
        kept.extend(best.into_iter().flatten());
    }
    let scanned = gitems * materials.len() * rots.len();
    // One rotation per (geometry, material): its best. (Rotations of a nearly isotropic geometry
    // score alike and would fill the pool with copies of one pair.)
    kept.sort_by(|a, b| {
        (a.geometry, a.material)
            .cmp(&(b.geometry, b.material))
            .then(a.error.total_cmp(&b.error))
            .then(a.rotation.cmp(&b.rotation))
    });
    kept.dedup_by_key(|p| (p.geometry, p.material));
    let errs: Vec<f64> = kept.iter().map(|p| p.error).collect();
    let chosen: Vec<Pair> = smallest(&errs, pool.max(1))
        .into_iter()
        .map(|i| kept[i])
        .collect();
    // Stage 2: each chosen pair with its own data; the lobes of a (geometry, rotation) are
    // assembled once, the tables of a material read once.
    let mut by_geo: HashMap<(usize, usize), Vec<(usize, f64)>> = HashMap::new();
    for p in &chosen {
        by_geo
            .entry((p.geometry, p.rotation))
            .or_default()
            .push((p.material, p.search_error));
    }
    let groups: Vec<((usize, usize), Vec<(usize, f64)>)> = {
        let mut v: Vec<_> = by_geo.into_iter().collect();
        v.sort_by_key(|(k, _)| *k);
        v
    };
    let mut reranked: Vec<Pair> = groups
        .par_iter()
        .map(|((g, ri), ms)| {
            let (s, t) = &rots[*ri];
            let fixed = FixedLobes::new(&lobes.get(*g)?, &super::dir_pairs(s));
            ms.iter()
                .map(|&(m, search_error)| {
                    let pf = material_prefiltered(lib, &parse_material(&mitems[m].spec)?, Some(m))?;
                    Ok(Pair {
                        error: s.rel_error(t, &fixed.fbar(&pf)),
                        search_error,
                        geometry: *g,
                        material: m,
                        rotation: *ri,
                    })
                })
                .collect::<Result<Vec<_>>>()
        })
        .collect::<Result<Vec<_>>>()?
        .into_iter()
        .flatten()
        .collect();
    reranked.sort_by(|a, b| {
        a.error
            .total_cmp(&b.error)
            .then(a.geometry.cmp(&b.geometry))
            .then(a.material.cmp(&b.material))
            .then(a.rotation.cmp(&b.rotation))
    });
    Ok((scanned, reranked))
}

/// Scored pairs as solver candidates (colour: each material's best colour shift for the look).
pub fn candidates(
    lib: &Library,
    look: &Look,
    pairs: &[Pair],
    opt: &SolveOptions,
) -> Result<Vec<Candidate>> {
    let gi = lib.geometry_items()?;
    let mi = lib.material_items()?;
    let colours = lib.array("material/colour.bsa")?;
    let shifts = lib.array("material/colour-shifts.bsa")?;
    let (colours, shifts) = (colours.f32s()?, shifts.f32s()?);
    let ns = lib.manifest.colours_per_material * 3;
    Ok(pairs
        .iter()
        .map(|p| {
            let m = p.material;
            let (shift, colour, _) = super::material::best_colour(
                [colours[3 * m], colours[3 * m + 1], colours[3 * m + 2]],
                &shifts[m * ns..(m + 1) * ns],
                look.colour,
            );
            Candidate {
                geometry: Some(p.geometry),
                geometry_spec: gi[p.geometry].spec.clone(),
                material: Some(m),
                material_spec: mi[m].spec.clone(),
                psi_deg: super::psi_angle(p.rotation, opt.psi).to_degrees(),
                colour_shift: Some(shift),
                colour,
                search_error: p.search_error,
                rerank_error: p.error,
                error: p.error,
                evaluated_by: Final::Library,
            }
        })
        .collect())
}
