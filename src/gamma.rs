//! The library's linear form of a BVNDF: `gamma` (Eq. 3) binned on a grid of normals, at the
//! library's fixed light directions × the view nodes of a [`DirGrid`] (paper Sec. 5.2, 4.1).
//!
//! For one light `l` and one view node `v`, `gamma(n; w_l, w_v)` is the distribution of the normals
//! seen from `w_v` and lit from `w_l`, normalised by the visible projected area. With view rays
//! sampled uniformly over the base in the view's projection, every ray stands for the same share
//! `1/N` of `gamma` (the ray density already carries `(n·wo)/a_v`), so the binned column is
//! `g[l][v][b] = (1/N) Σ_rays V(hit, w_l) β_b(n_hit)`, with `β_b` the bilinear weights of the hit
//! normal on the normal grid. `fbar` is linear in it: for a material with prefiltered `F`,
//!
//! `fbar(w_l, wo) ≈ Σ_v ω_v(wo) Σ_b g[l][v][b] F(w_l, wo; kappa_b, n_b)`,
//!
//! where `ω_v` are the view grid's interpolation weights and `kappa_b` the width of a vMF matching
//! the bilinear splat at node `b` (see [`Response::new`] for where the material is averaged over
//! that splat rather than taken at the node).
//! Because the map from column to `fbar` is linear, the library can compress the columns of all
//! geometries with an SVD and pick representatives by CX (Eq. 11–12).
//!
//! The normal grid is the hemispherical octahedral map: `n ↦ (x, y) = (n_x, n_y) / (|n_x| + |n_y| +
//! n_z)` (a diamond), rotated 45° to the square `[-1, 1]²`, with `G × G` nodes at the corners of
//! `G - 1` cells.

use crate::bvndf::{cluster_normals, moments, planar_clusters, STRIDE};
use crate::dirgrid::DirGrid;
use crate::frame::{dir_from_deg, Vec3};
use crate::heightfield::Heightfield;
use crate::lightlobes::{record_len, HEAD};
use crate::material::Material;
use crate::pairs::light_directions;
use crate::prefilter::quadrature;
use crate::visibility::{ray_lattice, Visibility};
use crate::vmf::Vmf;
use rayon::prelude::*;

/// `G × G` nodes of the hemispherical octahedral map.
#[derive(Debug, Clone, PartialEq)]
pub struct NormalGrid {
    pub g: usize,
    dirs: Vec<Vec3>,
    kappas: Vec<f64>,
}

impl NormalGrid {
    pub fn new(g: usize) -> Self {
        let g = g.max(3);
        let coord = |i: usize| -1.0 + 2.0 * i as f64 / (g - 1) as f64;
        let dir = |u: f64, v: f64| {
            let (x, y) = (0.5 * (u + v), 0.5 * (u - v));
            Vec3::new(x, y, (1.0 - x.abs() - y.abs()).max(0.0)).normalized()
        };
        let mut dirs = Vec::with_capacity(g * g);
        let mut kappas = Vec::with_capacity(g * g);
        for j in 0..g {
            for i in 0..g {
                let (u, v) = (coord(i), coord(j));
                let n = dir(u, v);
                // Angular step to the neighbours (one-sided at the border).
                let h = 2.0 / (g - 1) as f64;
                let mut step = 0.0;
                let mut cnt = 0.0;
                for (du, dv) in [(h, 0.0), (-h, 0.0), (0.0, h), (0.0, -h)] {
                    let (uu, vv) = (u + du, v + dv);
                    if uu.abs() <= 1.0 + 1e-12 && vv.abs() <= 1.0 + 1e-12 {
                        step += n.dot(dir(uu, vv)).clamp(-1.0, 1.0).acos();
                        cnt += 1.0;
                    }
                }
                let step = (step / cnt).max(1e-3);
                // A tent of half-width `step` has variance step²/6 per axis; match a vMF's 1/kappa.
                kappas.push(6.0 / (step * step));
                dirs.push(n);
            }
        }
        NormalGrid { g, dirs, kappas }
    }

    pub fn len(&self) -> usize {
        self.g * self.g
    }

    pub fn is_empty(&self) -> bool {
        self.g == 0
    }

    pub fn direction(&self, b: usize) -> Vec3 {
        self.dirs[b]
    }

    /// The vMF width standing for node `b`'s bilinear splat.
    pub fn kappa(&self, b: usize) -> f64 {
        self.kappas[b]
    }

    /// Bilinear weights of unit normal `n` (`n.z >= 0`) on the grid: four `(node, weight)`.
    pub fn splat(&self, n: Vec3) -> [(usize, f64); 4] {
        let s = n.x.abs() + n.y.abs() + n.z.max(0.0);
        let (x, y) = if s > 0.0 {
            (n.x / s, n.y / s)
        } else {
            (0.0, 0.0)
        };
        let (u, v) = (x + y, x - y);
        let g1 = (self.g - 1) as f64;
        let fu = ((u + 1.0) * 0.5 * g1).clamp(0.0, g1);
        let fv = ((v + 1.0) * 0.5 * g1).clamp(0.0, g1);
        let iu = (crate::fastmath::floor(fu) as usize).min(self.g - 2);
        let iv = (crate::fastmath::floor(fv) as usize).min(self.g - 2);
        let (au, av) = (fu - iu as f64, fv - iv as f64);
        let at = |i: usize, j: usize| j * self.g + i;
        [
            (at(iu, iv), (1.0 - au) * (1.0 - av)),
            (at(iu + 1, iv), au * (1.0 - av)),
            (at(iu, iv + 1), (1.0 - au) * av),
            (at(iu + 1, iv + 1), au * av),
        ]
    }
}

/// Where the binned `gamma` of every library geometry is sampled.
#[derive(Debug, Clone, PartialEq)]
pub struct GammaLayout {
    /// The fixed light directions (the 7 of [`light_directions`]).
    pub lights: Vec<Vec3>,
    pub views: DirGrid,
    pub normals: NormalGrid,
}

impl GammaLayout {
    pub fn new(n_theta: usize, n_phi: usize, normal_grid: usize) -> Self {
        GammaLayout {
            lights: light_directions()
                .iter()
                .map(|&(t, p)| dir_from_deg(t, p))
                .collect(),
            views: DirGrid::new(n_theta, n_phi),
            normals: NormalGrid::new(normal_grid),
        }
    }

    /// Length of one geometry's column: lights × view nodes × normal nodes.
    pub fn rows(&self) -> usize {
        self.lights.len() * self.views.len() * self.normals.len()
    }

    /// The index of `wi` among the fixed lights, if it is one (to 1e-9).
    pub fn light_index(&self, wi: Vec3) -> Option<usize> {
        self.lights
            .iter()
            .position(|l| (l.x - wi.x).abs() + (l.y - wi.y).abs() + (l.z - wi.z).abs() < 1e-9)
    }

    /// The binned `gamma` of `hf`, `[light][view node][normal node]`, from about `rays` view rays
    /// per view node (a jittered lattice over the period, as in the compact BVNDF).
    pub fn column(&self, hf: &Heightfield, rays: usize) -> Vec<f32> {
        self.trace(hf, rays, 0).0
    }

    /// One pass of view rays over `hf`: the binned column and, when `clusters > 0`, the record of
    /// its compact BVNDF at the lights ([`crate::lightlobes`]) with that many normal clusters.
    /// Each ray from view node `b` finds the point `b` sees; its normal is splatted into the
    /// column of every light that reaches the point, and its moments, weighted by the surface
    /// area the ray stands for, `(A_base cos theta_b / N) / (n·w_b)`, added to its cluster.
    pub fn trace(&self, hf: &Heightfield, rays: usize, clusters: usize) -> (Vec<f32>, Vec<f32>) {
        let vis = Visibility::new(hf);
        let facets = hf.facets();
        let origins = ray_lattice(hf.width(), hf.height(), rays);
        let inv = 1.0 / origins.len().max(1) as f64;
        let (nl, nv, nb) = (self.lights.len(), self.views.len(), self.normals.len());
        let kc = clusters;
        let (assign, centres, planar, area) = if kc > 0 {
            let abase = hf.base_area();
            let normals: Vec<Vec3> = facets.iter().map(|f| f.n).collect();
            let areas: Vec<f64> = facets.iter().map(|f| f.area / abase).collect();
            let (assign, centres) = cluster_normals(&normals, &areas, kc);
            let planar = planar_clusters(&normals, &assign, &centres);
            let mut area = vec![0.0; centres.len()];
            for (a, &k) in areas.iter().zip(&assign) {
                area[k as usize] += a;
            }
            (assign, centres, planar, area)
        } else {
            (Vec::new(), Vec::new(), Vec::new(), Vec::new())
        };
        // One block per view node: the column's [light][normal], the lobes' seen [cluster][3]
        // and lit [light][cluster][9].
        struct Block {
            col: Vec<f64>,
            seen: Vec<f64>,
            lit: Vec<f64>,
        }
        let light_dirs: Vec<_> = self.lights.iter().map(|w| vis.direction(*w)).collect();
        let blocks: Vec<Block> = (0..nv)
            .into_par_iter()
            .map(|v| {
                let wv = self.views.direction(v);
                let mut blk = Block {
                    col: vec![0.0f64; nl * nb],
                    seen: vec![0.0f64; kc * 3],
                    lit: vec![0.0f64; nl * kc * STRIDE],
                };
                let dv = vis.direction(wv);
                for &(u, w) in &origins {
                    let (p, f) = vis.first_hit_dir(u, w, &dv);
                    let n = facets[f].n;
                    let c = n.dot(wv);
                    if c <= 1e-9 {
                        continue;
                    }
                    let sp = self.normals.splat(n);
                    let (k, wgt, m) = if kc > 0 {
                        (assign[f] as usize, wv.z * inv / c, moments(n))
                    } else {
                        (0, 0.0, [0.0; STRIDE])
                    };
                    if kc > 0 {
                        for (s, mq) in blk.seen[k * 3..k * 3 + 3].iter_mut().zip(&m) {
                            *s += wgt * mq;
                        }
                    }
                    for (l, (wl, dl)) in self.lights.iter().zip(&light_dirs).enumerate() {
                        if n.dot(*wl) <= 0.0 || !vis.visible_dir(p.x, p.y, p.z, dl) {
                            continue;
                        }
                        let row = &mut blk.col[l * nb..(l + 1) * nb];
                        for &(b, wb) in &sp {
                            row[b] += wb * inv;
                        }
                        if kc > 0 {
                            let e = &mut blk.lit[(l * kc + k) * STRIDE..][..STRIDE];
                            for q in 0..STRIDE {
                                e[q] += wgt * m[q];
                            }
                        }
                    }
                }
                blk
            })
            .collect();
        let mut out = vec![0f32; self.rows()];
        for (v, blk) in blocks.iter().enumerate() {
            for l in 0..nl {
                let dst = (l * nv + v) * nb;
                for b in 0..nb {
                    out[dst + b] = blk.col[l * nb + b] as f32;
                }
            }
        }
        if kc == 0 {
            return (out, Vec::new());
        }
        // The record: clusters, seen, lit (see `crate::lightlobes`); unused clusters stay zero.
        let mut rec = vec![0f32; record_len(self, kc)];
        for (c, ctr) in centres.iter().enumerate() {
            let h = &mut rec[c * HEAD..(c + 1) * HEAD];
            h.copy_from_slice(&[
                ctr.x as f32,
                ctr.y as f32,
                ctr.z as f32,
                if planar[c] { 1.0 } else { 0.0 },
                area[c] as f32,
            ]);
        }
        let seen0 = kc * HEAD;
        let lit0 = seen0 + nv * kc * 3;
        for (v, blk) in blocks.iter().enumerate() {
            for (i, x) in blk.seen.iter().enumerate() {
                rec[seen0 + v * kc * 3 + i] = *x as f32;
            }
            for l in 0..nl {
                for i in 0..kc * STRIDE {
                    rec[lit0 + (l * nv + v) * kc * STRIDE + i] =
                        blk.lit[l * kc * STRIDE + i] as f32;
                }
            }
        }
        (out, rec)
    }
}

/// Quadrature points per splat-averaged node value.
const SPLAT_SAMPLES: usize = 48;

/// The linear map from a geometry column to `fbar` at a set of pairs for one material: per pair,
/// the light index, up to four `(view node, weight)` and the material's `F` at every normal node.
#[derive(Debug, Clone)]
pub struct Response {
    pub pairs: Vec<PairResponse>,
    nb: usize,
    nv: usize,
}

#[derive(Debug, Clone)]
pub struct PairResponse {
    pub light: usize,
    pub views: [(usize, f64); 4],
    pub f: Vec<f32>,
}

impl Response {
    /// The response of `mat` at `pairs` given as `(light index, wo)`: per normal node `b`, the
    /// value the bilinear splat of a hit normal is multiplied by. Where the material is wider
    /// than a grid step, its value at the node, `f_r(n_b) (n_b·wi)+` (the integrand is
    /// interpolated between nodes: second order, and exact for the delta-like normal
    /// distributions of flat facets). Where a glossy lobe is narrower than the node's step and
    /// the node is near the half vector, the integrand averaged over the node's splat, a vMF of
    /// width `kappa_b` ([`crate::prefilter::quadrature`], importance-sampled on the material):
    /// the splat spreads every hit normal over the node's neighbourhood, and a point value would
    /// hit or miss the narrow peak (errors of 100 % and more for GGX alpha = 0.02).
    pub fn new(layout: &GammaLayout, mat: &Material, pairs: &[(usize, Vec3)]) -> Self {
        Self::with_splat(layout, mat, pairs, &|wi, wo, lobe| {
            quadrature(mat, wi, wo, lobe, SPLAT_SAMPLES)
        })
    }

    /// [`Response::new`] with the splat averages read from the material's prefiltered table
    /// (the same integral, tabulated): about 20× faster for narrow lobes, for searches that
    /// only rank with the response.
    pub fn with_table(
        layout: &GammaLayout,
        mat: &Material,
        pf: &crate::prefilter::Prefiltered,
        pairs: &[(usize, Vec3)],
    ) -> Self {
        Self::with_splat(layout, mat, pairs, &|wi, wo, lobe| pf.eval(wi, wo, lobe))
    }

    /// The response with `splat(wi, wo, lobe)` giving the integrand averaged over a node's
    /// splat lobe where a narrow glossy lobe needs it.
    fn with_splat(
        layout: &GammaLayout,
        mat: &Material,
        pairs: &[(usize, Vec3)],
        splat: &(dyn Fn(Vec3, Vec3, &Vmf) -> f64 + Sync),
    ) -> Self {
        let nb = layout.normals.len();
        let width = mat.min_lobe_width();
        let resp = pairs
            .par_iter()
            .map(|&(l, wo)| {
                let wi = layout.lights[l];
                let h = (wi + wo).normalized();
                let f = (0..nb)
                    .map(|b| {
                        let n = layout.normals.direction(b);
                        let kb = layout.normals.kappa(b);
                        let step = (6.0 / kb).sqrt();
                        let near =
                            |w: f64| n.dot(h) > (3.0 * (step + w)).min(std::f64::consts::PI).cos();
                        let v = match width {
                            Some(w) if w < step && near(w) => splat(wi, wo, &Vmf::new(kb, n)),
                            _ => {
                                let c = n.dot(wi);
                                if c > 0.0 && n.dot(wo) > 0.0 {
                                    mat.eval(n, wi, wo) * c
                                } else {
                                    0.0
                                }
                            }
                        };
                        if v.is_finite() {
                            v as f32
                        } else {
                            0.0
                        }
                    })
                    .collect();
                PairResponse {
                    light: l,
                    views: layout.views.weights(wo),
                    f,
                }
            })
            .collect();
        Response {
            pairs: resp,
            nb,
            nv: layout.views.len(),
        }
    }

    /// `fbar` at every pair for one geometry column (`f32`, `f16` or `uf8` bytes). The
    /// column's row blocks that the pairs read (one per light and view node) are converted to
    /// `f32` once, then each pair is up to four dot products over the normal nodes.
    pub fn apply<T: ColumnElement>(&self, col: &[T]) -> Vec<f64> {
        let nb = self.nb;
        // Where each row block's `f32` copy starts in `buf` (`usize::MAX`: not converted yet),
        // indexed by block: a table, not a hash map (hashing was most of this function's time).
        let mut slot = vec![usize::MAX; col.len() / nb.max(1)];
        let mut buf: Vec<f32> = Vec::new();
        let mut block = |blk: usize, buf: &mut Vec<f32>| -> usize {
            if slot[blk] == usize::MAX {
                let at = buf.len();
                buf.resize(at + nb, 0.0);
                T::to_f32s(&col[blk * nb..(blk + 1) * nb], &mut buf[at..]);
                slot[blk] = at;
            }
            slot[blk]
        };
        let mut at = Vec::with_capacity(self.pairs.len());
        for p in &self.pairs {
            at.push(p.views.map(|(v, w)| {
                if w == 0.0 {
                    (0, 0.0)
                } else {
                    (block(p.light * self.nv + v, &mut buf), w)
                }
            }));
        }
        self.pairs
            .iter()
            .zip(&at)
            .map(|(p, views)| {
                let mut s = 0.0;
                for &(o, w) in views {
                    if w != 0.0 {
                        s += w * crate::fastmath::dot32(&buf[o..o + nb], &p.f);
                    }
                }
                s.max(0.0)
            })
            .collect()
    }
}

/// Elements of a stored geometry column: converted to `f32` a row block at a time.
pub trait ColumnElement: Copy {
    fn to_f32s(src: &[Self], dst: &mut [f32]);
}

impl ColumnElement for f32 {
    fn to_f32s(src: &[f32], dst: &mut [f32]) {
        dst.copy_from_slice(src);
    }
}

impl ColumnElement for half::f16 {
    fn to_f32s(src: &[half::f16], dst: &mut [f32]) {
        use half::slice::HalfFloatSliceExt;
        src.convert_to_f32_slice(dst);
    }
}

/// A byte of a column is a [`crate::uf8`] value (the only bytes a column holds).
impl ColumnElement for u8 {
    fn to_f32s(src: &[u8], dst: &mut [f32]) {
        crate::uf8::decode_into(src, dst);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::exact::ExactEvaluator;
    use crate::frame::DirPair;
    use crate::generators::parse_generator;
    use crate::material::parse_material;

    #[test]
    fn splat_weights_sum_to_one_and_hit_nodes_exactly() {
        let ng = NormalGrid::new(12);
        for b in [0, 5, 66, 143] {
            let n = ng.direction(b);
            let sp = ng.splat(n);
            let s: f64 = sp.iter().map(|x| x.1).sum();
            assert!((s - 1.0).abs() < 1e-12);
            let top = sp.iter().max_by(|a, b| a.1.total_cmp(&b.1)).unwrap();
            assert_eq!(top.0, b);
            assert!(top.1 > 1.0 - 1e-9, "node {b}: {sp:?}");
        }
    }

    #[test]
    fn flat_patch_column_is_the_visible_share_and_fbar_is_exact() {
        let lay = GammaLayout::new(6, 8, 9);
        let hf = Heightfield::flat(16, 16);
        let col = lay.column(&hf, 64);
        // Every view node of every light: all mass at the pole node, total 1.
        let nb = lay.normals.len();
        let pole = lay.normals.splat(Vec3::Z)[0].0;
        for blk in col.chunks(nb) {
            assert!((blk[pole] - 1.0).abs() < 1e-6);
        }
        let mat = parse_material("ggx:alpha=0.3+lambert:albedo=0.2").unwrap();
        let wo = dir_from_deg(40.0, 200.0);
        let r = Response::new(&lay, &mat, &[(2, wo)]);
        let got = r.apply(&col)[0];
        let wi = lay.lights[2];
        let want = mat.eval(Vec3::Z, wi, wo) * wi.z;
        assert!((got - want).abs() < 1e-6 * want, "{got} vs {want}");
    }

    #[test]
    fn binned_gamma_tracks_the_exact_evaluator_on_rough_geometry() {
        let lay = GammaLayout::new(10, 16, 20);
        let hf = parse_generator("bumps:n=48,count=6,radius=8,height=3,seed=2")
            .unwrap()
            .build()
            .unwrap();
        let col = lay.column(&hf, 1024);
        let mat = parse_material("ggx:alpha=0.4+lambert:albedo=0.1").unwrap();
        let pairs: Vec<(usize, Vec3)> = (0..7)
            .flat_map(|l| {
                [(30.0, 10.0), (55.0, 130.0), (70.0, 250.0)]
                    .into_iter()
                    .map(move |(t, p)| (l, dir_from_deg(t, p)))
            })
            .collect();
        let resp = Response::new(&lay, &mat, &pairs);
        let got = resp.apply(&col);
        // The column stored in bytes (`uf8`) gives its decoded column's numbers exactly.
        let bytes = crate::uf8::encode_all(&col);
        let mut decoded = vec![0f32; bytes.len()];
        crate::uf8::decode_into(&bytes, &mut decoded);
        assert_eq!(resp.apply(&bytes), resp.apply(&decoded));
        let ex = ExactEvaluator::new(&hf, 3);
        let dp: Vec<DirPair> = pairs
            .iter()
            .map(|&(l, wo)| DirPair {
                wi: lay.lights[l],
                wo,
            })
            .collect();
        let want = ex.fbar(&mat, &dp);
        let rel = crate::bench::relative_rms(&got, &want);
        assert!(rel < 0.05, "binned gamma vs exact: {rel}");
    }
}
