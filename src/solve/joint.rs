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
//! `y_mᵀ Q_g y_m - 2 y_mᵀ b_g + |t|²` with `Q_g = P_g W P_gᵀ` and `b_g = P_g W t`.
//!
//! The scan is dense products per block of geometries: the `R·S` weighted sample vectors
//! `fbar(rep_r, rep_s)` are first projected on their leading row-space basis (`d` of the
//! `samples` dimensions), so `P_g` for a block is `X_block · R̃` (f32); each geometry's `Q_g` and
//! `b_g` are then written as rows `Vq_g = [Q_ac (a <= c)]` and `Vl_g = [-2 b_a]`, and every
//! material's error at once is `Vq · Uqᵀ + Vl · Ulᵀ + |t|²` with `Uq_m = [y_a y_c]`,
//! `Ul_m = [y_a]`, all in f32, the CX weights' own precision (twice the f64 rate; the f64
//! products before gave the same answers, docs/solvers.md). Every rotation of the target is
//! scanned at one shared sample set (rotation 0's), so only `Vl` and the last product are per
//! rotation. On paper16 (10,277 geometries × 260 materials) this is about 4× faster than one
//! loop per geometry (docs/solvers.md gives the measurement).

use super::{
    material_prefiltered, rotated_samples, smallest, Candidate, Final, Look, SolveOptions,
};
use crate::error::{Error, Result};
use crate::library::Library;
use crate::lightlobes::LightPairs;
use crate::material::parse_material;
use crate::sampling::Samples;
use faer::Mat;
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

/// `fbar(rep_r, rep_s)` of every (geometry representative, material representative) pair at
/// the shared samples of the joint search (rotation 0's, which every rotation is scanned at). A
/// library material's values on the geometry representatives follow from its CX weights `y`
/// (Eq. 12 on the material side): `fbar(rep_r, m) ≈ Σ_s y[s] fbar(rep_r, rep_s)`, so the geometry
/// solves of the alternation need not evaluate the representatives again.
pub struct RepPairs {
    /// `[r][s][sample]`.
    rr: Vec<Vec<Vec<f64>>>,
    /// The material library's CX weights, `ks` per material.
    mx: Vec<f32>,
    ks: usize,
}

impl RepPairs {
    /// `fbar(rep_r, material)` at the shared samples, `[r][sample]`; `None` when the material is
    /// not held.
    pub fn values(&self, material: usize) -> Option<Vec<Vec<f64>>> {
        let y = self.mx.get(material * self.ks..(material + 1) * self.ks)?;
        Some(
            self.rr
                .iter()
                .map(|per_s| {
                    let np = per_s.first().map_or(0, Vec::len);
                    let mut v = vec![0.0; np];
                    for (row, &ys) in per_s.iter().zip(y) {
                        for (a, b) in v.iter_mut().zip(row) {
                            *a += ys as f64 * b;
                        }
                    }
                    v
                })
                .collect(),
        )
    }
}

/// Pairs kept per geometry from the compressed scan before the global selection (keeps memory
/// at `geometries × KEEP_PER_GEOMETRY` whatever the material library's size).
const KEEP_PER_GEOMETRY: usize = 8;

/// Share of the energy of the representative pairs' sample vectors that the scan's basis keeps
/// (the rest, a relative amplitude of about 10 % overall, is dropped from every pair's error;
/// the re-rank of stage 2 uses each pair's own data). On `paper` it keeps 69–80 of 490
/// dimensions, against 111–155 at 1 − 10⁻³ and 343–414 at 1 − 10⁻⁶: the scan's largest
/// product shrinks with it. At 1 − 10⁻² the general solver took 0.13–0.30 s less on `paper`
/// at the same or better rates (docs/solvers.md, "The joint scan in fewer dimensions"). Stage
/// 1's error through the two libraries' representatives is itself off by tens of percent (a
/// validation case's own pair scored 0.1–1.4 there), so the dropped part does not decide the
/// pool.
const BASIS_ENERGY: f64 = 1.0 - 1e-2;

/// Geometries whose coordinates are computed together (one matrix product).
const GEOMETRY_BLOCK: usize = 256;

/// A joint pool larger than this is narrowed by coarse passes before the pairs left are
/// evaluated at every sample. At 32 rather than 512 (the passes then at 16, 30 and 122
/// samples, and 32 pairs at every sample: an eighth of the evaluations) the general solver
/// took 0.3–0.6 s less per case on `paper` at the same rates within 7 % and 1 %, and one
/// recovery fewer in 120 cases (docs/solvers.md, "A narrower joint pool"). The re-ranked
/// pairs start the alternation; stage 1's pairs of further materials are added when the
/// starts want more materials than these hold.
pub const JOINT_COARSE_KEEP: usize = 32;

/// Multiply-adds the pair scan may spend: 250 times the default library's scan (730 geometries
/// × 160 materials × `13² + 13` = 2 × 10⁷). A paper-sized library (164,431 geometries × 4,101
/// distinct BRDFs) would need thousands of times the default's, so there only the materials
/// that come closest to the look on a probe of the geometries ([`MATERIAL_PROBE`]) are paired
/// with every geometry: 144 of 4,168 on `paper`. With the probe, 36, 72, 144, 289 and 578
/// materials gave the same rates on 120 cases of `paper` but for one case lost at 36, and the
/// scan's time grows with them (docs/solvers.md, "The joint scan's materials from
/// a probe of the geometries").
pub const MAX_OPERATIONS: f64 = 5e9;

/// At most this many geometries (every `n`-th of the library, so that each family and amplitude
/// is among them: 4,011 on `paper`) on which every material is scored to choose the materials
/// of a scan that cannot pair them all: each material's best relative error there ranks it. On
/// `paper`, under the budget of 10¹⁰ then (289 of 4,168 materials paired), the original
/// material of a validation case was among those chosen in 23 of 40 cases, against 10 of 40
/// when they were the materials closest to the look on a flat patch (the look taken as a plain
/// BRDF: a material sharper than the look, which a rough geometry blurs, ranks far down there);
/// every 20th, 40th or 80th geometry gave the same rates (docs/solvers.md, "The joint scan's
/// materials from a probe of the geometries").
pub const MATERIAL_PROBE: usize = 4096;

/// Fewest geometries of the probe, whatever the budget: a library of so many materials that the
/// budget pays for fewer than [`MATERIAL_PROBE`] geometries with each is probed on fewer, down to
/// this many (on `paper` the budget pays for 5,712).
pub const MIN_PROBE: usize = 256;

/// Fewest materials the pair scan pairs with every geometry, whatever the budget.
pub const MIN_MATERIALS: usize = 4;

/// Score every pair through the representatives (stage 1), re-rank the best `pool` pairs with
/// their own light lobes and prefiltered tables (stage 2), and with them stage 1's best pair of
/// each further material while the re-ranked pairs hold fewer than `materials_wanted`
/// materials (the general solver's starts). Returns the number of pairs scanned,
/// the re-ranked pool, best first, and the representative pairs' values. When scoring every
/// pair would cost more than `max_operations` multiply-adds, only the materials that come
/// closest to the look on a probe of [`MATERIAL_PROBE`] geometries are paired, as many as the
/// budget allows (at least [`MIN_MATERIALS`]).
pub fn search(
    lib: &Library,
    look: &Look,
    opt: &SolveOptions,
    pool: usize,
    materials_wanted: usize,
    max_operations: f64,
) -> Result<(usize, Vec<Pair>, RepPairs)> {
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
    // The pairs' values are built from the representatives' light lobes: their weights are
    // the ones refitted to the light lobes when the library has them (`library::lobefit`;
    // on `paper4`, 50 cases of the paper's protocol, 82 → 92 % within 7 %).
    let gx = lib.geometry_lobe_weights()?;
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
    let n_scan = affordable.max(MIN_MATERIALS).min(mitems.len());
    let all_materials: Vec<usize> = (0..mitems.len()).collect();
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
    let nqq = ks * (ks + 1) / 2;
    let mut kept: Vec<Pair> = Vec::new();
    // Pairs scored: the probe's (below) and the scan's.
    let mut scanned = 0;
    // Every rotation is scanned at one shared sample set, rotation 0's (as the geometry solver's
    // stage 1): the representative pairs, their basis and each geometry's quadratic form do not
    // depend on the target, so only the linear term is computed per rotation. Stage 2 below
    // compares each pair at its rotation's own samples.
    let (s0, t0) = &rots[0];
    let at0 = LightPairs::new(&lobes.layout, super::dir_pairs(s0));
    let np = at0.pairs.len();
    // fbar(rep_r, rep_s) at the samples: [r][s][p].
    let rr: Vec<Vec<Vec<f64>>> = greps
        .par_iter()
        .map(|&r| {
            let fixed = lobes.get(r as usize)?.fixed(&at0);
            Ok(rep_tables.iter().map(|pf| fixed.fbar(pf)).collect())
        })
        .collect::<Result<_>>()?;
    let rep_pairs = RepPairs {
        rr,
        mx: mx.to_vec(),
        ks,
    };
    let rr = &rep_pairs.rr;
    // The weighted targets of the rotations worth scanning (a black target has no error scale).
    let f = look.as_fn();
    let targets: Vec<(usize, Vec<f64>, f64)> = (0..rots.len())
        .filter_map(|ri| {
            let t = if ri == 0 {
                t0.clone()
            } else {
                s0.values(&f, super::psi_angle(ri, opt.psi))
            };
            let tw: Vec<f64> = t.iter().zip(&s0.weights).map(|(t, w)| t * w).collect();
            let n2: f64 = tw.iter().map(|v| v * v).sum();
            (n2 > 0.0).then_some((ri, tw, n2))
        })
        .collect();
    // Every pair's weighted values are a combination of the kr·ks rows rr[r][s]: project them on
    // their row space's leading basis (d ≪ np dimensions), so the scan below runs in d
    // dimensions. A target's part outside the basis only adds a constant.
    let rows = Mat::from_fn(kr * ks, np, |i, p| rr[i / ks][i % ks][p] * s0.weights[p]);
    // Err: every representative is black at these samples; nothing to scan.
    if let (Ok(basis), false) = (
        crate::lowrank::row_basis(rows.clone(), BASIS_ENERGY),
        targets.is_empty(),
    ) {
        let d = basis.ncols();
        // The rows in the basis, (kr·ks) × d; then [r][s·d + k]: representative r's
        // material-representative rows. In f32, the CX weights' own precision (twice the f64
        // rate); an error is about 1e-6 of |t|², far below the differences the scan ranks by,
        // and stage 2 rescoring is in f64.
        let reduced = &rows * &basis;
        let rt = Mat::<f32>::from_fn(kr, ks * d, |r, j| reduced[(r * ks + j / d, j % d)] as f32);
        let twrs: Vec<Vec<f32>> = targets
            .iter()
            .map(|(_, tw, _)| {
                (0..d)
                    .map(|k| (0..np).map(|p| basis[(p, k)] * tw[p]).sum::<f64>() as f32)
                    .collect()
            })
            .collect();
        // Each material's side of the quadratic form: the products y_a y_c (×2 off the
        // diagonal), and y_a; one row per material.
        let material_terms = |materials: &[usize]| -> (Mat<f32>, Mat<f32>) {
            let y_of = |k: usize| &mx[materials[k] * ks..(materials[k] + 1) * ks];
            (
                Mat::<f32>::from_fn(materials.len(), nqq, |k, j| upper_term(y_of(k), ks, j)),
                Mat::<f32>::from_fn(materials.len(), ks, |k, j| y_of(k)[j]),
            )
        };
        // One block of geometries `gs` with the materials of `(uq, ul)`: each target's
        // (rotation's) `|t - f|² - |t|²` (which ranks as the error does), materials ×
        // geometries.
        let block_errors = |gs: &[usize], uq: &Mat<f32>, ul: &Mat<f32>| -> Vec<Mat<f32>> {
            // P for the block's geometries at once, one row per geometry: Xᵀ · rt,
            // geometries × (ks·d), so that entry (a, k) of every geometry's P is one contiguous
            // column and the terms below run down the block's geometries in vector registers.
            let n = gs.len();
            let x = Mat::from_fn(n, kr, |i, r| gx[gs[i] * kr + r]);
            let mut p = Mat::<f32>::zeros(n, ks * d);
            faer::linalg::matmul::matmul(
                p.as_mut(),
                faer::Accum::Replace,
                x.as_ref(),
                rt.as_ref(),
                1.0,
                faer::Par::Seq,
            );
            // Each geometry's quadratic form in the materials' coordinates, one column per
            // term: [Q_ac (a <= c)] once (Q = P Pᵀ, its Gram matrix), [-2 b_a] per rotation;
            // then every material's error at once, Eᵀ = Uq Vqᵀ + Ul Vlᵀ + |t|², one
            // contiguous column per geometry.
            let col = |a: usize, k: usize| p.col_as_slice(a * d + k);
            let mut vq = Mat::<f32>::zeros(n, nqq);
            for j in 0..nqq {
                let (a, c) = upper_pair(ks, j);
                let out = vq.col_as_slice_mut(j);
                for k in 0..d {
                    for ((o, &pa), &pc) in out.iter_mut().zip(col(a, k)).zip(col(c, k)) {
                        *o += pa * pc;
                    }
                }
            }
            let mut eq = Mat::<f32>::zeros(uq.nrows(), n);
            faer::linalg::matmul::matmul(
                eq.as_mut(),
                faer::Accum::Replace,
                uq.as_ref(),
                vq.as_ref().transpose(),
                1.0,
                faer::Par::Seq,
            );
            // Each rotation's errors, materials × geometries.
            twrs.iter()
                .enumerate()
                .map(|(ti, twr)| {
                    let mut vl = Mat::<f32>::zeros(n, ks);
                    for a in 0..ks {
                        let out = vl.col_as_slice_mut(a);
                        for (k, &t) in twr.iter().enumerate() {
                            for (o, &pa) in out.iter_mut().zip(col(a, k)) {
                                *o += pa * t;
                            }
                        }
                        for o in out.iter_mut() {
                            *o *= -2.0;
                        }
                    }
                    // The quadratic terms serve every rotation: the last one takes them.
                    let mut e = if ti + 1 == targets.len() {
                        std::mem::replace(&mut eq, Mat::new())
                    } else {
                        eq.clone()
                    };
                    faer::linalg::matmul::matmul(
                        e.as_mut(),
                        faer::Accum::Add,
                        ul.as_ref(),
                        vl.as_ref().transpose(),
                        1.0,
                        faer::Par::Seq,
                    );
                    e
                })
                .collect()
        };
        // Subnormal products are flushed (`fastmath::without_subnormals`).
        let errors_of = |gs: &[usize], uq: &Mat<f32>, ul: &Mat<f32>| {
            crate::fastmath::without_subnormals(|| block_errors(gs, uq, ul))
        };
        // The materials paired with every geometry: all of them when the budget allows, else
        // the `n_scan` that come closest to the look on a probe of MATERIAL_PROBE geometries
        // spread over the library (every material with each; a material's score is its best
        // relative error there). The probe keeps to the budget as well: a library of very many
        // materials is probed on fewer geometries (at least MIN_PROBE).
        let materials = if n_scan >= mitems.len() {
            all_materials
        } else {
            let size = (max_operations / (mitems.len() as f64 * per_pair)).floor() as usize;
            let size = size.clamp(MIN_PROBE, MATERIAL_PROBE);
            let stride = gitems.div_ceil(size).max(1);
            let probe: Vec<usize> = (0..gitems).step_by(stride).collect();
            let (uq, ul) = material_terms(&all_materials);
            let best = probe
                .par_chunks(GEOMETRY_BLOCK)
                .map(|gs| {
                    let mut best = vec![f64::INFINITY; mitems.len()];
                    for ((_, _, n2), e) in targets.iter().zip(errors_of(gs, &uq, &ul)) {
                        for i in 0..gs.len() {
                            for (b, &v) in best.iter_mut().zip(e.col_as_slice(i)) {
                                *b = b.min((n2 + v as f64) / n2);
                            }
                        }
                    }
                    best
                })
                .reduce(
                    || vec![f64::INFINITY; mitems.len()],
                    |a, b| a.iter().zip(&b).map(|(a, b)| a.min(*b)).collect(),
                );
            scanned += probe.len() * mitems.len() * rots.len();
            smallest(&best, n_scan)
        };
        let (uq, ul) = material_terms(&materials);
        // One block of geometries: every material's error for each, the best kept.
        let scan_geometries = |gs: &[usize]| -> Vec<Pair> {
            let es = errors_of(gs, &uq, &ul);
            let mut out = Vec::with_capacity(gs.len() * KEEP_PER_GEOMETRY * targets.len());
            for (i, &g) in gs.iter().enumerate() {
                let first = out.len();
                for ((ri, _, n2), e) in targets.iter().zip(&es) {
                    // `|t - f|² - |t|²` ranks as the error does; the root only for the kept.
                    let col = e.col_as_slice(i);
                    out.extend(smallest(col, KEEP_PER_GEOMETRY).into_iter().map(|k| {
                        let err = ((n2 + col[k] as f64).max(0.0) / n2).sqrt();
                        Pair {
                            error: err,
                            search_error: err,
                            geometry: g,
                            material: materials[k],
                            rotation: *ri,
                        }
                    }));
                }
                // One rotation per (geometry, material), its best (below): rotations of a
                // nearly isotropic geometry score alike and would fill the pool with copies of
                // one pair. Sorted geometry by geometry, the blocks' pairs come out in the
                // order one sort of them all would give; that sort, after the scan and on one
                // processor, took 0.09–0.12 s per case on `paper`.
                out[first..].sort_by(|a, b| {
                    a.material
                        .cmp(&b.material)
                        .then(a.error.total_cmp(&b.error))
                        .then(a.rotation.cmp(&b.rotation))
                });
            }
            out.dedup_by_key(|p| (p.geometry, p.material));
            out
        };
        let geometries: Vec<usize> = (0..gitems).collect();
        let best: Vec<Vec<Pair>> = geometries
            .par_chunks(GEOMETRY_BLOCK)
            .map(scan_geometries)
            .collect();
        kept.extend(best.into_iter().flatten());
        scanned += gitems * materials.len() * rots.len();
    }
    // `kept` is in (geometry, material) order, each pair once.
    let errs: Vec<f64> = kept.iter().map(|p| p.error).collect();
    let chosen: Vec<Pair> = smallest(&errs, pool.max(1))
        .into_iter()
        .map(|i| kept[i])
        .collect();
    // Stage 2: each chosen pair with its own data; the lobes of a (geometry, rotation) are
    // assembled once, the tables of a material read once. A pool over JOINT_COARSE_KEEP is
    // narrowed first by coarse passes, as the geometry solver's ([`super::geometry::coarse_step`]).
    // Each chosen pair's error at `at`'s samples (per rotation), in `chosen`'s order.
    let rerank = |chosen: &[Pair], at: &[(Samples, Vec<f64>, LightPairs)]| -> Result<Vec<Pair>> {
        let mut by_geo: HashMap<(usize, usize), Vec<(usize, usize)>> = HashMap::new();
        for (i, p) in chosen.iter().enumerate() {
            by_geo
                .entry((p.geometry, p.rotation))
                .or_default()
                .push((i, p.material));
        }
        // ((geometry, rotation), [(index in `chosen`, material)]).
        type Group = ((usize, usize), Vec<(usize, usize)>);
        let mut groups: Vec<Group> = by_geo.into_iter().collect();
        groups.sort_by_key(|(k, _)| *k);
        let mut geometries: Vec<usize> = groups.iter().map(|((g, _), _)| *g).collect();
        geometries.dedup();
        lobes.will_need(&geometries);
        let errs: Vec<Vec<(usize, f64)>> = groups
            .par_iter()
            .map(|((g, ri), ms)| {
                let (s, t, lp) = &at[*ri];
                let fixed = lobes.get(*g)?.fixed(lp);
                ms.iter()
                    .map(|&(i, m)| {
                        let pf =
                            material_prefiltered(lib, &parse_material(&mitems[m].spec)?, Some(m))?;
                        Ok((i, s.rel_error(t, &fixed.fbar(&pf))))
                    })
                    .collect::<Result<Vec<_>>>()
            })
            .collect::<Result<_>>()?;
        let mut out = chosen.to_vec();
        for (i, e) in errs.into_iter().flatten() {
            out[i].error = e;
        }
        Ok(out)
    };
    let at_every = |step: usize| -> Vec<(Samples, Vec<f64>, LightPairs)> {
        rots.iter()
            .enumerate()
            .map(|(ri, (s, t))| {
                let psi = super::psi_angle(ri, opt.psi);
                super::coarse_at(&lobes.layout, s, t, look, psi, step)
            })
            .collect()
    };
    // The pool in stage 1's order, before the coarse passes.
    let by_search = chosen.clone();
    let mut chosen =
        super::geometry::narrow(chosen, JOINT_COARSE_KEEP, s0.pairs.len(), |pool, step| {
            Ok(rerank(pool, &at_every(step))?
                .iter()
                .map(|p| p.error)
                .collect())
        })?;
    // The narrowed pool may hold pairs of fewer materials than the starts want (its pairs
    // often share one material): the best pair by stage 1 of each further material is
    // re-ranked too, so that the starts are the joint search's materials, not random ones.
    let mut held: std::collections::HashSet<usize> = chosen.iter().map(|p| p.material).collect();
    for p in &by_search {
        if held.len() >= materials_wanted {
            break;
        }
        if held.insert(p.material) {
            chosen.push(*p);
        }
    }
    let mut reranked = rerank(&chosen, &at_every(1))?;
    reranked.sort_by(|a, b| {
        a.error
            .total_cmp(&b.error)
            .then(a.geometry.cmp(&b.geometry))
            .then(a.material.cmp(&b.material))
            .then(a.rotation.cmp(&b.rotation))
    });
    Ok((scanned, reranked, rep_pairs))
}

/// Entry `j` of a material's row of the scan's quadratic form: the products `y_a y_c` for
/// `a <= c` (doubled off the diagonal, so the row dotted with the upper triangle of a symmetric
/// `Q` is `yᵀ Q y`), then `y_a`.
fn upper_term(y: &[f32], ks: usize, j: usize) -> f32 {
    let mut col = 0;
    for a in 0..ks {
        for c in a..ks {
            if col == j {
                let f = if a == c { 1.0 } else { 2.0 };
                return f * y[a] * y[c];
            }
            col += 1;
        }
    }
    y[j - col]
}

/// The `(a, c)`, `a <= c`, of entry `j` of the upper triangle of a `ks × ks` matrix, row-major.
fn upper_pair(ks: usize, j: usize) -> (usize, usize) {
    let mut col = 0;
    for a in 0..ks {
        if j < col + ks - a {
            return (a, a + j - col);
        }
        col += ks - a;
    }
    (ks - 1, ks - 1)
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn upper_pair_walks_the_upper_triangle_as_upper_term_does() {
        let ks = 5;
        // y = powers of two: y_a y_c identifies (a, c).
        let y: Vec<f32> = (0..ks).map(|a| (1u32 << a) as f32).collect();
        for j in 0..ks * (ks + 1) / 2 {
            let (a, c) = upper_pair(ks, j);
            assert!(a <= c && c < ks);
            let f = if a == c { 1.0 } else { 2.0 };
            assert_eq!(upper_term(&y, ks, j), f * y[a] * y[c], "entry {j}");
        }
    }
}
