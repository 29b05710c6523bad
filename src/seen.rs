//! The area of each normal cluster seen from each direction of a fine direction grid, by height
//! band: the compact BVNDF's correction for visibility that changes faster with the direction
//! than its node-pair table resolves.
//!
//! On a tall periodic surface, what a grazing view sees changes within a few degrees of
//! azimuth: looking along a "street" between rows of bumps the view reaches their flanks, a few
//! degrees off it only their tops. The jointly visible moments of [`crate::bvndf`] are stored per
//! *pair* of nodes, so refining their grid costs its square (32 → 128 azimuths: 4 GB → 16 GB).
//! The area seen from *one* direction costs only its first hits and one row per node, so it is
//! tabulated on a grid with more azimuths ([`BvndfConfig::seen_phi`]) and used to correct the pair
//! table's interpolation ([`SeenTable::correction`]).
//!
//! The correction is a model of the jointly visible area that this table can evaluate at any
//! pair: split each cluster's facets into height bands ([`BvndfConfig::seen_bands`]) and take
//! visibility from the two ends as independent within a band,
//! `M_c(wi, wo) = Σ_h S_ch(wo) · S_ch(wi) / F_ch(wi)`, with `S_ch(w)` the projected area of
//! cluster `c`'s band `h` seen from `w` and `F_ch(w)` the projected area of its facets facing
//! `w` (so `S/F` is the band's lit fraction). The pair table's interpolated value is multiplied
//! by `M_c` at the pair over `M_c` interpolated from the pair table's nodes as the table is: the
//! table keeps what it knows at its nodes, the model carries the change between them. Heights
//! matter: what a view sees through a street between bumps lies low on their flanks, where a
//! grazing light is shadowed, so the seen area and the lit fraction move together. On the tall
//! bumps of docs/forward-model.md, between a node pair and a pair a few degrees off, the jointly
//! visible area of one cluster grew 4 % while its seen area grew 39 %; one band (independence)
//! predicted 39 %, eight bands 10 %.
//!
//! What a view between the nodes sees of a cluster also *turns* with it: a grazing view sees
//! the side of each bump that faces it. The table's 9 moments per cluster give the seen
//! `(n·wo)`-weighted mean normal at the pair and interpolated from the pair table's nodes; the
//! jointly visible mean normal is turned by the rotation between the two ([`Correction::turn`]).
//!
//! The same model, band by band, shares a cluster's jointly visible area among its facets'
//! heights where the fast method sums a sharp lobe over facets
//! ([`crate::bvndf::CompactBvndf::sharp_fbar`], [`SeenTable::band_fractions`]).
//!
//! The rows are estimated from first hits by line sweeps ([`seen_moments`],
//! [`Visibility::seen_facets`]: the rays of one vertical plane resolved in one pass down its
//! profile), `seen_rays` per direction, and also hold each cluster's 9 moments of
//! [`crate::bvndf`], which the pair table's seen-area control variate reads at its own
//! directions instead of casting the same rays again. The polar rows at 80° and beyond may cast
//! rays at every azimuth; a row nearer the zenith at most at every [`row_stride`]-th (what a
//! view sees changes with its azimuth as fast as its rays reach across the relief,
//! `tan(theta)`). Within those bounds the rows are refined adaptively ([`refine_rows`]): an
//! interval between cast azimuths is split only where its middle's seen areas are not the
//! linear interpolation of its ends', and the azimuths left out are interpolated. Fewer rays
//! make the factor noisy where the surface is
//! rough: on the tall fBm of `bench accuracy --cases 24 --seed 1` (case 15: 2.67 % without the
//! table) 1024 and 4096 first hits per direction gave 4.63 % and 3.02 % (single rays, a setting
//! since removed), one per cell 2.85 % with 8 bands and 2.64 % with 4 (the bands split a
//! cluster's hits; fewer bands, less noise). A sweep's rays share their vertical plane, so they
//! are less independent than single rays: it takes about 16 of them per cell to match one
//! single ray per cell on tall fBm, at a fraction of the cost (docs/forward-model.md, "Line
//! sweeps").
//!
//! [`BvndfConfig::seen_phi`]: crate::bvndf::BvndfConfig::seen_phi
//! [`BvndfConfig::seen_bands`]: crate::bvndf::BvndfConfig::seen_bands

use crate::bvndf::{moments, second_times, STRIDE};
use crate::dirgrid::DirGrid;
use crate::frame::{Rotation, Vec3};
use crate::library::progress::Progress;
use crate::visibility::Visibility;
use rayon::prelude::*;

/// Floats per (node, cluster, band) in [`SeenTable::banded`]: `Σ A n` seen, `Σ A n` facing.
const BAND_STRIDE: usize = 6;

/// The seen area of every cluster and height band at every node of a fine grid.
#[derive(Debug, Clone, PartialEq)]
pub struct SeenTable {
    pub grid: DirGrid,
    pub clusters: usize,
    pub bands: usize,
    /// `[node][cluster][STRIDE]`: the 9 moments of each cluster's seen area, in units of
    /// `A_base`.
    pub moments: Vec<f32>,
    /// `[node][cluster][band][BAND_STRIDE]`: per height band, `Σ A n` over the area seen from
    /// the node (`S`, in units of `A_base`) and over its facets facing the node (`F`). Kept as
    /// vectors, so that both project on the actual direction: on the tall bumps the same model
    /// from the nodes' own projected areas (two scalars, an earlier form not kept) gave 3.45 %
    /// instead of 3.31 % (8 bands).
    pub banded: Vec<f32>,
    /// How many of the nodes cast rays ([`refine_rows`]); the others are interpolated.
    pub cast: usize,
}

/// What the first hits from `w` see, per cluster (facet `f` in cluster `assign[f]`, `kc`
/// clusters): `Σ A n` and `Σ A n nᵀ` over the seen area, and, when `band` (per facet) is given,
/// `Σ A n` over the seen area of each of `nb` bands (`[cluster][band]`). About `rays` first
/// hits, by line sweeps ([`Visibility::seen_facets`]; each ray carries the projected area
/// `w.z / rays`, in units of `A_base`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn seen_moments(
    vis: &Visibility,
    normals: &[Vec3],
    assign: &[u16],
    kc: usize,
    band: &[u8],
    nb: usize,
    w: Vec3,
    rays: usize,
) -> (Vec<[f64; STRIDE]>, Vec<Vec3>) {
    let mut out = vec![[0.0f64; STRIDE]; kc];
    let mut banded = vec![Vec3::default(); if band.is_empty() { 0 } else { kc * nb }];
    if w.z <= 0.0 || rays == 0 {
        return (out, banded);
    }
    // Hits are counted per facet during the sweeps and weighted afterwards, once per facet hit:
    // the sweeps' inner loop only counts.
    let mut hits = vec![0u32; normals.len()];
    let n = vis.seen_facets(&vis.direction(w), rays, |f| hits[f] += 1);
    for (f, &count) in hits.iter().enumerate() {
        if count == 0 {
            continue;
        }
        let nf = normals[f];
        let c = nf.dot(w);
        if c <= 1e-9 {
            continue;
        }
        let k = assign[f] as usize;
        let m = moments(nf);
        let x = count as f64 / c;
        let e = &mut out[k];
        for q in 0..STRIDE {
            e[q] += m[q] * x;
        }
        if let Some(&h) = band.get(f) {
            let b = &mut banded[k * nb + h as usize];
            *b = *b + nf * x;
        }
    }
    let per_ray = w.z / n as f64;
    out.iter_mut().flatten().for_each(|x| *x *= per_ray);
    banded.iter_mut().for_each(|b| *b = *b * per_ray);
    (out, banded)
}

/// The height band of every facet (of `nb`, at most 255, evenly between the lowest and the
/// highest centroid `centroid_z`).
pub(crate) fn facet_bands(centroid_z: &[f64], nb: usize) -> Vec<u8> {
    let nb = nb.clamp(1, 255);
    let (z0, z1) = centroid_z
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &z| {
            (a.min(z), b.max(z))
        });
    centroid_z.iter().map(|&z| band_of(z, z0, z1, nb)).collect()
}

/// The height band (of `nb` between `z0` and `z1`) of a facet's centroid.
fn band_of(z: f64, z0: f64, z1: f64, nb: usize) -> u8 {
    if !(z1 > z0) {
        return 0;
    }
    (((z - z0) / (z1 - z0) * nb as f64) as usize).min(nb - 1) as u8
}

/// Views at or above this polar angle may cast rays at every azimuth of the fine table.
const FULL_THETA_DEG: f64 = 80.0;

/// Of `ratio` fine azimuths per pair-table azimuth, every how many a polar row at `theta` casts
/// rays: the largest divisor of `ratio` at most `tan(80°) / tan(theta)`. What a view sees
/// changes with its azimuth about as fast as the horizontal reach of its rays, `tan(theta)`
/// times the relief, so a row nearer the zenith needs proportionally fewer azimuths.
pub(crate) fn row_stride(theta: f64, ratio: usize) -> usize {
    let want = FULL_THETA_DEG.to_radians().tan() / theta.tan();
    (1..=ratio.max(1))
        .rev()
        .find(|s| ratio.is_multiple_of(*s) && (*s as f64) <= want)
        .unwrap_or(1)
}

/// One cast row of the fine table: a node's 9 moments per cluster (concatenated) and its seen
/// `Σ A n` per cluster and band.
type Row = (Vec<f64>, Vec<Vec3>);

/// How far, as a share of the area seen from a direction (`a_v`), a cast row may be from the
/// linear interpolation of its neighbours in the row, in every cluster's band, for the
/// azimuths between them to be interpolated rather than cast ([`refine_rows`]).
const SMOOTH_TOL: f64 = 0.002;

/// The rows of the fine table that are cast, by adaptive refinement in azimuth: every
/// pair-table azimuth (every `ratio`-th) first, then, in each polar row, the middle of every
/// interval whose ends are further apart than the row's [`row_stride`]; an interval whose
/// middle agrees with the linear interpolation of its ends to [`SMOOTH_TOL`] is not split
/// further (what a view sees there changes linearly with its azimuth, as on grooves and walls),
/// the others are split in two. `cast` computes rows, in parallel, for a list of nodes. Returns
/// the row of every cast node.
fn refine_rows(
    grid: &DirGrid,
    ratio: usize,
    cast: &dyn Fn(&[usize]) -> Vec<Row>,
) -> Vec<Option<Row>> {
    let np = grid.n_phi;
    let ratio = ratio.max(1);
    let strides: Vec<usize> = grid.thetas.iter().map(|&t| row_stride(t, ratio)).collect();
    let mut rows: Vec<Option<Row>> = vec![None; grid.len()];
    let first: Vec<usize> = (0..grid.len())
        .filter(|b| (b % np).is_multiple_of(ratio))
        .collect();
    for (&b, r) in first.iter().zip(cast(&first)) {
        rows[b] = Some(r);
    }
    // Intervals `(polar row, first azimuth, length)` still to split; lengths are multiples of
    // the row's stride.
    let mut todo: Vec<(usize, usize, usize)> = (0..grid.thetas.len())
        .filter(|&it| ratio >= 2 * strides[it])
        .flat_map(|it| (0..np).step_by(ratio).map(move |j| (it, j, ratio)))
        .collect();
    while !todo.is_empty() {
        let mid = |&(it, j, s): &(usize, usize, usize)| j + (s / strides[it] / 2) * strides[it];
        let nodes: Vec<usize> = todo.iter().map(|iv| grid.node(iv.0, mid(iv))).collect();
        let new = cast(&nodes);
        let mut next = Vec::new();
        for (iv, (&b, r)) in todo.iter().zip(nodes.iter().zip(new)) {
            let (it, j, s) = *iv;
            let m = mid(iv);
            let t = (m - j) as f64 / s as f64;
            let ends = (
                rows[grid.node(it, j)].as_ref(),
                rows[grid.node(it, (j + s) % np)].as_ref(),
            );
            let linear = match ends {
                (Some(a), Some(c)) => agrees(&r.1, &a.1, &c.1, t, grid.direction(b)),
                _ => false,
            };
            rows[b] = Some(r);
            if !linear {
                for (j0, len) in [(j, m - j), (m, j + s - m)] {
                    if len >= 2 * strides[it] {
                        next.push((it, j0, len));
                    }
                }
            }
        }
        todo = next;
    }
    rows
}

/// Whether the seen sums `mid` (per cluster and band) agree with `(1 - t) a + t c` to
/// [`SMOOTH_TOL`] of the area seen from `w`, projected on `w`.
fn agrees(mid: &[Vec3], a: &[Vec3], c: &[Vec3], t: f64, w: Vec3) -> bool {
    let area: f64 = mid.iter().map(|x| x.dot(w)).sum();
    if !(area > 0.0) {
        return false;
    }
    let tol = SMOOTH_TOL * area;
    mid.iter()
        .zip(a.iter().zip(c))
        .all(|(m, (a, c))| ((*a * (1.0 - t) + *c * t).dot(w) - m.dot(w)).abs() <= tol)
}

/// Node weights as the grid gives them, without the zero ones.
fn weights(grid: &DirGrid, w: Vec3) -> impl Iterator<Item = (usize, f64)> {
    grid.weights(w).into_iter().filter(|x| x.1 != 0.0)
}

#[inline]
fn dot(w: Vec3, e: &[f32]) -> f64 {
    w.x * e[0] as f64 + w.y * e[1] as f64 + w.z * e[2] as f64
}

impl SeenTable {
    /// The table on `grid` for clusters `assign` (`kc` of them) and `bands` height bands of the
    /// facets' centroids (`centroid_z`), about `rays` first hits at every node. `grid` has a
    /// whole multiple `ratio` of the pair table's azimuths; each polar row casts rays at the
    /// azimuths [`refine_rows`] picks (at most every [`row_stride`]-th) and interpolates the
    /// seen sums between them linearly in azimuth (the facing sums are exact at every node).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn build(
        vis: &Visibility,
        normals: &[Vec3],
        areas: &[f64],
        centroid_z: &[f64],
        assign: &[u16],
        kc: usize,
        bands: usize,
        grid: DirGrid,
        ratio: usize,
        rays: usize,
        progress: &Progress,
    ) -> Self {
        let nb = bands.clamp(1, 255);
        let band = facet_bands(centroid_z, nb);
        let np = grid.n_phi;
        // One bar over the directions cast: the first round's (every `ratio`-th azimuth), then
        // each refining round's added as it starts (where the seen sums are not linear).
        let first = grid.thetas.len() * np.div_ceil(ratio.max(1));
        let bar = progress.bar(first as u64, "compact BVNDF: seen areas (directions)");
        let rounds = std::sync::atomic::AtomicUsize::new(0);
        let cast = |nodes: &[usize]| -> Vec<Row> {
            if rounds.fetch_add(1, std::sync::atomic::Ordering::Relaxed) > 0 {
                bar.inc_length(nodes.len() as u64);
            }
            nodes
                .par_iter()
                .map(|&b| {
                    let (m, seen) =
                        seen_moments(vis, normals, assign, kc, &band, nb, grid.direction(b), rays);
                    bar.inc(1);
                    (m.concat(), seen)
                })
                .collect()
        };
        let rows = refine_rows(&grid, ratio, &cast);
        bar.finish();
        let n_cast = rows.iter().filter(|r| r.is_some()).count();
        // Per node, the cast azimuths of its row on either side (the node itself if cast).
        let (mut before, mut after) = (vec![0usize; grid.len()], vec![0usize; grid.len()]);
        for it in 0..grid.thetas.len() {
            let on = |j: usize| rows[grid.node(it, j % np)].is_some();
            for j in 0..np {
                let back = (0..np).find(|&d| on(j + np - d)).unwrap_or(0);
                let ahead = (0..np).find(|&d| on(j + d)).unwrap_or(0);
                before[grid.node(it, j)] = (j + np - back) % np;
                after[grid.node(it, j)] = j + ahead;
            }
        }
        let per_node: Vec<(Vec<f32>, Vec<f32>)> = (0..grid.len())
            .into_par_iter()
            .map(|b| {
                let w = grid.direction(b);
                let (it, j) = (b / np, b % np);
                let (j0, j1) = (before[b], after[b]);
                let span = (j1 + np - j0) % np;
                let t = if span == 0 {
                    0.0
                } else {
                    ((j + np - j0) % np) as f64 / span as f64
                };
                let ends = [
                    (&rows[grid.node(it, j0)], 1.0 - t),
                    (&rows[grid.node(it, j1 % np)], t),
                ];
                let mut m = vec![0.0f64; kc * STRIDE];
                let mut seen = vec![Vec3::default(); kc * nb];
                for (row, v) in ends.iter().filter(|e| e.1 != 0.0) {
                    if let Some((rm, rs)) = row {
                        m.iter_mut().zip(rm).for_each(|(x, y)| *x += v * y);
                        seen.iter_mut().zip(rs).for_each(|(x, y)| *x = *x + *y * *v);
                    }
                }
                let mut facing = vec![Vec3::default(); kc * nb];
                for (f, n) in normals.iter().enumerate() {
                    if n.dot(w) > 0.0 {
                        let e = &mut facing[assign[f] as usize * nb + band[f] as usize];
                        *e = *e + *n * areas[f];
                    }
                }
                let banded = seen
                    .iter()
                    .zip(&facing)
                    .flat_map(|(s, f)| [s.x, s.y, s.z, f.x, f.y, f.z].map(|x| x as f32))
                    .collect();
                (m.iter().map(|&x| x as f32).collect(), banded)
            })
            .collect();
        let (moments, banded): (Vec<Vec<f32>>, Vec<Vec<f32>>) = per_node.into_iter().unzip();
        SeenTable {
            grid,
            clusters: kc,
            bands: nb,
            moments: moments.concat(),
            banded: banded.concat(),
            cast: n_cast,
        }
    }

    /// The 9 moments of every cluster's seen area at node `b`.
    pub(crate) fn moments_at(&self, b: usize) -> Vec<[f64; STRIDE]> {
        self.moments[b * self.clusters * STRIDE..][..self.clusters * STRIDE]
            .chunks_exact(STRIDE)
            .map(|e| std::array::from_fn(|q| e[q] as f64))
            .collect()
    }

    /// The bands of every cluster at node `b`: `[cluster][band][BAND_STRIDE]`.
    #[inline]
    fn bands_at(&self, b: usize) -> &[f32] {
        let n = self.clusters * self.bands * BAND_STRIDE;
        &self.banded[b * n..][..n]
    }

    /// The node of this grid at the direction of node `b` of `coarse`, the pair table's grid
    /// (this grid has its polar nodes and a whole multiple of its azimuths).
    #[inline]
    pub(crate) fn node_of(&self, coarse: &DirGrid, b: usize) -> usize {
        let np = coarse.n_phi;
        self.grid.node(b / np, (b % np) * (self.grid.n_phi / np))
    }

    /// Bytes of the table.
    pub fn bytes(&self) -> usize {
        (self.moments.len() + self.banded.len()) * 4
    }

    /// The model's two ends interpolated over `(node, weight)` pairs of this grid, per cluster
    /// and band: `seen[c·bands + h]`, the projected area towards `wo` seen from the view's nodes
    /// `b_nodes`, and `lit[...]`, the lit fraction towards `wi` (seen over facing, per node) from
    /// the light's nodes `a_nodes`.
    fn ends(
        &self,
        (wi, a_nodes): (Vec3, &[(usize, f64)]),
        (wo, b_nodes): (Vec3, &[(usize, f64)]),
        seen: &mut [f64],
        lit: &mut [f64],
    ) {
        seen.iter_mut().for_each(|x| *x = 0.0);
        lit.iter_mut().for_each(|x| *x = 0.0);
        for &(b, v) in b_nodes {
            for (s, e) in seen
                .iter_mut()
                .zip(self.bands_at(b).chunks_exact(BAND_STRIDE))
            {
                *s += v * dot(wo, e);
            }
        }
        for &(a, u) in a_nodes {
            for (l, e) in lit
                .iter_mut()
                .zip(self.bands_at(a).chunks_exact(BAND_STRIDE))
            {
                let facing = dot(wi, &e[3..]);
                if facing > 0.0 {
                    *l += u * (dot(wi, e) / facing).clamp(0.0, 1.0);
                }
            }
        }
    }

    /// The interpolation weights of `w` on this grid, for [`Self::band_fractions`].
    pub(crate) fn node_weights(&self, w: Vec3) -> Vec<(usize, f64)> {
        weights(&self.grid, w).collect()
    }

    /// Per height band of cluster `c`, its jointly visible fraction at `(wi, wo)` in the band
    /// model (the fraction of its facets facing `wo` that `wo` sees, times the fraction of
    /// those facing `wi` that `wi` lights, each interpolated on this grid with the weights
    /// `fa` of `wi` and `fb` of `wo`, [`Self::node_weights`]), into `out`.
    pub(crate) fn band_fractions(
        &self,
        (wi, fa): (Vec3, &[(usize, f64)]),
        (wo, fb): (Vec3, &[(usize, f64)]),
        c: usize,
        out: &mut Vec<f64>,
    ) {
        out.clear();
        out.resize(self.bands, 0.0);
        let at = |b: usize, h: usize| &self.bands_at(b)[(c * self.bands + h) * BAND_STRIDE..];
        let (mut seen, mut facing) = (vec![0.0; self.bands], vec![0.0; self.bands]);
        for &(b, v) in fb {
            for (h, (s, f)) in seen.iter_mut().zip(facing.iter_mut()).enumerate() {
                let e = at(b, h);
                *s += v * dot(wo, e);
                *f += v * dot(wo, &e[3..]);
            }
        }
        let mut lit = vec![0.0; self.bands];
        for &(a, u) in fa {
            for (h, l) in lit.iter_mut().enumerate() {
                let e = at(a, h);
                let facing = dot(wi, &e[3..]);
                if facing > 0.0 {
                    *l += u * (dot(wi, e) / facing).clamp(0.0, 1.0);
                }
            }
        }
        for (((o, s), f), l) in out.iter_mut().zip(&seen).zip(&facing).zip(&lit) {
            let sigma = if *f > 0.0 {
                (s / f).clamp(0.0, 1.0)
            } else {
                0.0
            };
            *o = sigma * l;
        }
    }

    /// The correction of the pair table (grid `coarse`) at `(wi, wo)`, whose interpolation
    /// weights over `coarse` are `wa`, `wb` ([`Correction`]).
    pub fn correction(
        &self,
        coarse: &DirGrid,
        wi: Vec3,
        wo: Vec3,
        wa: &[(usize, f64)],
        wb: &[(usize, f64)],
    ) -> Correction {
        let fa: Vec<(usize, f64)> = weights(&self.grid, wi).collect();
        let fb: Vec<(usize, f64)> = weights(&self.grid, wo).collect();
        let on_fine = |ws: &[(usize, f64)]| -> Vec<(usize, f64)> {
            ws.iter()
                .filter(|x| x.1 != 0.0)
                .map(|&(b, v)| (self.node_of(coarse, b), v))
                .collect()
        };
        let (ca, cb) = (on_fine(wa), on_fine(wb));
        let n = self.clusters * self.bands;
        let (mut s_fine, mut l_fine) = (vec![0.0; n], vec![0.0; n]);
        let (mut s_nodes, mut l_nodes) = (vec![0.0; n], vec![0.0; n]);
        self.ends((wi, &fa), (wo, &fb), &mut s_fine, &mut l_fine);
        self.ends((wi, &ca), (wo, &cb), &mut s_nodes, &mut l_nodes);
        let model = |s: &[f64], l: &[f64]| -> f64 { s.iter().zip(l).map(|(s, l)| s * l).sum() };
        // The (n·wo)-weighted seen normal `G2 wo` of cluster `c`, interpolated over `nodes`.
        let seen_mean = |nodes: &[(usize, f64)], c: usize| -> Vec3 {
            let mut m = Vec3::default();
            for &(b, v) in nodes {
                let e = &self.moments[(b * self.clusters + c) * STRIDE..][3..STRIDE];
                let q: [f64; 6] = std::array::from_fn(|k| e[k] as f64);
                m = m + second_times(&q, wo) * v;
            }
            m
        };
        let mut out = Correction {
            factor: vec![1.0; self.clusters],
            seen: vec![0.0; self.clusters],
            turn: vec![Rotation::between(Vec3::Z, Vec3::Z); self.clusters],
            diag: 0.0,
        };
        for c in 0..self.clusters {
            let band = c * self.bands..(c + 1) * self.bands;
            let fine = model(&s_fine[band.clone()], &l_fine[band.clone()]);
            let interpolated = model(&s_nodes[band.clone()], &l_nodes[band.clone()]);
            if interpolated > 1e-12 && fine.is_finite() {
                out.factor[c] = fine / interpolated;
            }
            out.seen[c] = s_fine[band].iter().sum::<f64>();
            out.diag += out.seen[c];
            let (m_fine, m_nodes) = (seen_mean(&fb, c), seen_mean(&cb, c));
            if m_fine.norm() > 0.0 && m_nodes.norm() > 0.0 {
                out.turn[c] = Rotation::between(m_nodes.normalized(), m_fine.normalized());
            }
        }
        out
    }
}

/// The fine seen table's correction of the pair table at one pair ([`SeenTable::correction`]):
/// per cluster, how its interpolated jointly visible area and mean normal change between the
/// pair table's nodes.
#[derive(Debug, Clone)]
pub struct Correction {
    /// The band model's value at the pair over its value interpolated from the pair table's
    /// nodes (1 where that is 0: nothing to rescale).
    pub factor: Vec<f64>,
    /// The cluster's projected area seen from `wo` in the fine table: a factor may not raise a
    /// jointly visible area above it. Where the model is nearly 0 at the nodes and not at the
    /// pair (a cluster shadowed at every node around a pair, lit at the pair) the factor can be
    /// in the thousands; the bound keeps the rescaled area possible. It does not lower what the
    /// pair table gives: the table's interpolated value and the fine table's scatter about each
    /// other where nearly all of a cluster is seen and lit, and capping the result itself at
    /// the seen area took 2–3 % off every pair near the zenith.
    pub seen: Vec<f64>,
    /// The rotation from the cluster's `(n·wo)`-weighted *seen* mean normal interpolated from
    /// the pair table's nodes to the same at the pair in the fine table: what a view between
    /// the nodes sees of a cluster turns with it (the side of a bump facing a grazing view),
    /// and the jointly visible mean normal is turned the same way.
    pub turn: Vec<Rotation>,
    /// `a_v(wo)` from the fine table.
    pub diag: f64,
}

impl Correction {
    /// Cluster `c`'s jointly visible projected area `v`, interpolated in the pair table,
    /// rescaled: `min(v · factor, max(v, seen))`.
    #[inline]
    pub fn area(&self, c: usize, v: f64) -> f64 {
        (v * self.factor[c]).min(v.max(self.seen[c]))
    }

    /// Cluster `c`'s interpolated `(n·wo)`-weighted jointly visible normal `m`, turned.
    #[inline]
    pub fn mean(&self, c: usize, m: Vec3) -> Vec3 {
        let len = m.norm();
        if len > 0.0 {
            self.turn[c].apply(m) * len
        } else {
            m
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::bvndf::{BvndfConfig, CompactBvndf};
    use crate::dirgrid::DirGrid;
    use crate::frame::{dir_from_deg, Vec3};
    use crate::generators::parse_generator;
    use crate::seen::{refine_rows, row_stride, Row};

    fn table_of(spec: &str) -> CompactBvndf {
        let hf = parse_generator(spec).unwrap().build().unwrap();
        CompactBvndf::build(
            &hf,
            &BvndfConfig {
                n_theta: 8,
                n_phi: 8,
                clusters: 8,
                points: 4096,
                seen_rays: 1024,
                seen_phi: 32,
                ..BvndfConfig::default()
            },
        )
    }

    /// At a pair of the pair table's nodes the model's value and its interpolation are the same
    /// rows, so nothing is rescaled; and the seen areas add up to `a_v(wo) = cos(theta_o)` there
    /// (every first hit faces its ray).
    #[test]
    fn rows_nearer_the_zenith_cast_at_fewer_azimuths() {
        // Every grazing row casts at every azimuth, the zenith's at the pair table's only, and
        // a stride always divides the ratio (the pair table's azimuths are always cast).
        for ratio in [1, 4, 6, 16] {
            assert_eq!(row_stride(0.0, ratio), ratio);
            assert_eq!(row_stride(80f64.to_radians(), ratio), 1);
            assert_eq!(row_stride(88.5f64.to_radians(), ratio), 1);
            let mut last = ratio;
            for d in 0..=88 {
                let s = row_stride((d as f64).to_radians(), ratio);
                assert!(ratio % s == 0 && s <= last, "{ratio} {d}: {s}");
                last = s;
            }
        }
    }

    /// Adaptive refinement: where the seen sums change linearly with the azimuth one level of
    /// middles is cast and found to agree, so the rest is interpolated; near a kink the row is
    /// split down to its stride; the pair table's azimuths are always cast.
    #[test]
    fn rows_are_refined_only_where_they_bend() {
        let grid = DirGrid::new(6, 128);
        let ratio = 16;
        // One cluster and band whose seen `Σ A n` points up and whose size, as a function of
        // azimuth, is a triangle wave with its corners at the pair table's azimuths (every 45°,
        // so linear between them), plus, in the grazing rows only, a ramp from 95° to 105°.
        let value = |b: usize| -> f64 {
            let w = grid.direction(b);
            let x = (b % grid.n_phi) as f64 * 8.0 / grid.n_phi as f64;
            let f = x.fract();
            let tri = if (x.floor() as usize).is_multiple_of(2) {
                f
            } else {
                1.0 - f
            };
            let phi = x * 45.0;
            let ramp = if w.z < 0.2 {
                0.3 * (phi - 95.0).clamp(0.0, 10.0) / 10.0
            } else {
                0.0
            };
            0.5 + tri + ramp
        };
        let cast = |nodes: &[usize]| -> Vec<Row> {
            nodes
                .iter()
                .map(|&b| (Vec::new(), vec![Vec3::Z * value(b)]))
                .collect()
        };
        let rows = refine_rows(&grid, ratio, &cast);
        let np = grid.n_phi;
        for it in 0..grid.thetas.len() {
            let cast_at: Vec<usize> = (0..np)
                .filter(|&j| rows[grid.node(it, j)].is_some())
                .collect();
            assert!((0..np).step_by(ratio).all(|j| cast_at.contains(&j)));
            let stride = row_stride(grid.thetas[it], ratio);
            if grid.direction(grid.node(it, 0)).z >= 0.2 {
                // Linear everywhere: the pair table's azimuths and one middle per interval
                // (where the row's stride allows one).
                let want = if stride * 2 <= ratio {
                    2 * np / ratio
                } else {
                    np / ratio
                };
                assert_eq!(cast_at.len(), want, "row {it}: {cast_at:?}");
            } else {
                // The ramp's corners (azimuths 33.8 and 37.3 of 128) are resolved to the row's
                // stride.
                assert_eq!(stride, 1);
                assert!(
                    [33, 34, 37, 38].iter().all(|j| cast_at.contains(j)),
                    "row {it}: {cast_at:?}"
                );
                assert!(cast_at.len() < np / 2, "row {it}: {cast_at:?}");
            }
        }
    }

    #[test]
    fn at_the_pair_tables_nodes_nothing_is_rescaled() {
        let geo = table_of("bumps:n=32,count=13,radius=8.245,height=5.546,seed=7");
        let t = geo.seen.as_ref().unwrap();
        assert_eq!(t.grid.n_phi, 32);
        for (a, b) in [(9, 60), (20, 43), (63, 63), (50, 17)] {
            let (wi, wo) = (geo.grid.direction(a), geo.grid.direction(b));
            let k = t.correction(&geo.grid, wi, wo, &[(a, 1.0)], &[(b, 1.0)]);
            assert!(
                (k.diag - wo.z).abs() < 1e-5 * wo.z,
                "{} vs {}",
                k.diag,
                wo.z
            );
            for f in &k.factor {
                assert!((f - 1.0).abs() < 1e-12, "nodes {a}, {b}: {:?}", k.factor);
            }
            let m = Vec3::new(0.3, -0.2, 0.9);
            for c in 0..geo.clusters {
                assert!(
                    (k.mean(c, m) - m).norm() < 1e-12,
                    "nodes {a}, {b}: {:?}",
                    k.turn
                );
            }
        }
    }

    /// The rescaled lobes' weights sum to at most about 1 (`gamma` is a distribution over the
    /// visible normals) at every pair of a dense sweep on a tall rough surface, where some
    /// clusters are shadowed at every node around a pair and lit at the pair: there the factor
    /// alone is in the thousands (a 64² fBm of amplitude 24 gave `fbar` 9× the exact method's
    /// before the factor was bounded by the cluster's seen area; this sweep's sum reached 18.6).
    /// Bounded, it reaches 1.03: the pair table's interpolated areas and the fine table's seen
    /// areas come from different rays and scatter by a few percent on this coarse build.
    #[test]
    fn rescaled_weights_stay_a_distribution() {
        let geo = table_of("fbm:n=32,octaves=4,amplitude=12,seed=7");
        let mut lobes = Vec::new();
        let mut worst: f64 = 0.0;
        for ti in (0..=85).step_by(5) {
            for to in (0..=85).step_by(5) {
                for po in (0..360).step_by(7) {
                    let wi = dir_from_deg(ti as f64 + 0.37, 90.0);
                    let wo = dir_from_deg(to as f64 + 0.61, po as f64 + 0.29);
                    geo.lobes(wi, wo, true, &mut lobes);
                    let total: f64 = lobes.iter().map(|l| l.0).sum();
                    worst = worst.max(total);
                }
            }
        }
        assert!(worst < 1.1, "lobe weights sum to {worst}");
    }

    /// Between the nodes, the factors and `a_v(wo)` stay finite and non-negative at every
    /// direction, down to the horizon.
    #[test]
    fn factors_are_finite_everywhere() {
        let geo = table_of("bricks:n=32,length=16,height=8,mortar=2,depth=6");
        let t = geo.seen.as_ref().unwrap();
        for (ti, pi, to, po) in [
            (0.0, 0.0, 89.9, 13.0),
            (89.9, 91.0, 89.9, 271.0),
            (45.0, 7.0, 88.9, 187.3),
            (89.0, 44.0, 0.0, 0.0),
        ] {
            let (wi, wo) = (dir_from_deg(ti, pi), dir_from_deg(to, po));
            let (wa, wb) = (geo.grid.weights(wi), geo.grid.weights(wo));
            let k = t.correction(&geo.grid, wi, wo, &wa, &wb);
            assert!(k.diag.is_finite() && k.diag >= 0.0, "{}", k.diag);
            assert!(
                k.factor.iter().all(|f| f.is_finite() && *f >= 0.0),
                "{:?}",
                k.factor
            );
            let m = Vec3::new(0.3, -0.2, 0.9);
            assert!((0..geo.clusters).all(|c| {
                let t = k.mean(c, m);
                t.x.is_finite() && t.y.is_finite() && t.z.is_finite()
            }));
        }
    }
}
