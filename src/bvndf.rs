//! The compact BVNDF of a heightfield: what the fast evaluator and the libraries store per geometry.
//!
//! The BVNDF `gamma(n; wi, wo)` of a faceted surface is a weighted set of facet normals (Eq. 3).
//! We split the facets into `K` normal clusters (area-weighted k-means on the sphere) and, for
//! every pair of nodes `(a, b)` of a hemisphere [`DirGrid`], store per cluster the first and second
//! normal moments of the jointly visible area, `G1 = Σ A n V_a V_b` and `G2 = Σ A n nᵀ V_a V_b`
//! (3 + 6 numbers). For any `(wi, wo)` the moments are interpolated bilinearly over the nodes
//! around `wi` and `wo`, then, with the exact `wo` applied afterwards:
//!
//! * the cluster's share of `gamma` is `wo·G1 / a_v(wo)` — exact for the tabulated visibility,
//!   because a facet seen from `wo` faces it, so `(n·wo)+ V = (n·wo) V`;
//! * its shape is the vMF whose mean and mean resultant length match the `(n·wo)`-weighted mean
//!   normal `G2 wo / (wo·G1)` (moment matching: visibility that selects part of a cluster, and the
//!   foreshortening that favours normals facing `wo` at grazing angles, both move the lobe);
//! * `a_v(wo)` comes from the same table on the diagonal `a = b`, so a flat patch is exact;
//! * with a fine seen table ([`crate::seen`]; `forward`'s default), each cluster's interpolated
//!   share is multiplied by a factor, and its mean normal turned, by what changes between the
//!   table's directions faster than they follow (grazing views along rows of bumps), and
//!   `a_v(wo)` comes from the fine table;
//! * a planar cluster (one normal: groove faces, walls) takes its analytic projected area
//!   `A_k (n·wo)+` times its jointly visible fraction, interpolated only over the nodes it faces,
//!   so a face turning towards `wo` between two nodes is not lost to the node it turns away from;
//! * for a material with a glossy lobe, which resolves the shape of a cluster's normal
//!   distribution (a rough surface's cluster is a broad, flat-topped patch that one vMF does not
//!   follow), a curved cluster comes instead as its sub-lobes: its whole facet distribution split
//!   by k-means into up to 16 vMFs, each weighted by its visible projected area towards `wo`
//!   (its visible fraction fitted to the cluster's 9 interpolated moments, [`crate::sublobes`]),
//!   and turned together so that their `(n·wo)`-weighted mean normal is the visible one. The
//!   libraries keep one vMF per cluster ([`BvndfConfig::library`]).
//!
//! The moments are integrated over points spread on the surface ([`crate::jointvis`],
//! [`BvndfConfig::points`]): one horizon march per azimuth at each point says which polar nodes
//! of that azimuth see it, and the pair table is a 2-D histogram of those counts per pair of
//! azimuths. Half the points are spread by area (steep facets take more, in proportion to how
//! much of a grazing view they can fill: the thin rims of walls a grazing view sees), half are
//! the first hits of rays from every node (what a view sees of a wall far taller than wide), each
//! weighted by both densities. View rays from each direction, the estimator before the points,
//! cost a march per azimuth at every hit of every direction, each serving one column. The table
//! is symmetric in `(a, b)`; only `a <= b` is stored.
//!
//! Optionally ([`BvndfConfig::seen_rays`]) a denser set of first hits without marches estimates
//! the area seen from `b`, as a control variate for the views `b` beyond 85° (which the points'
//! shares are not sized for): jointly visible = seen from `b` − hidden from `a`, the seen part
//! from the dense hits and the hidden part (seen minus jointly visible) from the points. It is
//! applied to the clusters whose every facet faces both nodes, where the hidden part is
//! occlusion by other geometry only; the estimate stays unbiased.

use crate::dirgrid::DirGrid;
use crate::facetindex::{FacetIndex, Near};
use crate::facetrays::FacetRays;
use crate::frame::Vec3;
use crate::heightfield::Heightfield;
use crate::jointvis::{joint_moments, GRAZING_DEG};
use crate::library::progress::Progress;
use crate::material::Material;
use crate::seen::{seen_moments, Correction, SeenTable};
use crate::sublobes::{cluster_shapes, Shape};
use crate::visibility::Visibility;
use crate::vmf::{kappa_from_resultant, Vmf};
use rayon::prelude::*;

/// Build settings of the compact BVNDF.
#[derive(Debug, Clone, PartialEq)]
pub struct BvndfConfig {
    pub n_theta: usize,
    pub n_phi: usize,
    /// Number of normal clusters (lobes per direction pair).
    pub clusters: usize,
    /// Points spread over the surface for the pair table ([`crate::jointvis`]), about: each
    /// point's horizon marches (one per azimuth) serve every direction.
    pub points: usize,
    /// Sub-lobes per curved cluster: its whole normal distribution split further, for materials
    /// with a glossy lobe. 1: every cluster is one vMF, as in the libraries.
    pub sub_lobes: usize,
    /// First hits per grid direction for the area seen from it (no horizon marches, by line
    /// sweeps, [`crate::visibility::Visibility::seen_facets`]): a control variate for the
    /// jointly visible moments, and the rows of the fine seen table. 0: off (the seen table
    /// too).
    pub seen_rays: usize,
    /// Azimuths of the fine table of the area seen from each direction ([`crate::seen`]), which
    /// corrects the pair table's interpolation. At most `n_phi`, or no seen rays: off.
    pub seen_phi: usize,
    /// Height bands of that table's model of joint visibility (1: the two ends independent).
    pub seen_bands: usize,
    /// The last polar node of the direction grid, in degrees; views beyond it take its data.
    /// Beyond the libraries' 88.5° the grid ends with three nodes evenly spaced in the ray
    /// slope ([`crate::dirgrid::DirGrid::to`]).
    pub last_theta_deg: f64,
}

impl Default for BvndfConfig {
    fn default() -> Self {
        BvndfConfig {
            n_theta: 10,
            n_phi: 16,
            clusters: 16,
            points: 16_384,
            sub_lobes: 16,
            seen_rays: 0,
            seen_phi: 0,
            seen_bands: 4,
            last_theta_deg: crate::dirgrid::LAST_THETA_DEG,
        }
    }
}

impl BvndfConfig {
    /// The `forward` command's default: 25 polar nodes, the libraries' spacing of 24 to 88.5°
    /// but its last two, then three to 89.9° ([`crate::dirgrid::DirGrid::to`]: views between
    /// 88.5° and the horizon were 18–415 % off with the last node at 88.5°), and 40 azimuths
    /// (grazing views on
    /// grooves: 16 polar nodes left tall sine grooves at 3.3 % up to 85°; at grazing views over
    /// tall bumps, 32 azimuths left 3.1 % up to 85°, 40 give 2.5 %; 40 keep the axes and the
    /// diagonals as nodes), 32 normal clusters
    /// (visibility that selects part of a rough surface's normals), 262,144 surface points for
    /// the pair table (half by area, half first hits from the grid's directions; past 65,536
    /// the tallest surfaces gain a few tenths of a point), 65,536 first hits per direction for
    /// the area seen from it (a control variate for the views beyond 85°, `seen_rays`; line
    /// sweeps make them cheap), and the fine seen table on 520 azimuths (13 per pair-table
    /// azimuth; `seen_phi` is rounded up to a multiple of `n_phi`) (tall surfaces at
    /// grazing views, [`crate::seen`]) (docs/forward-model.md, "Points on the surface" and
    /// "Line sweeps").
    pub fn forward() -> Self {
        BvndfConfig {
            n_theta: 25,
            n_phi: 40,
            clusters: 32,
            points: 262_144,
            seen_rays: 65_536,
            seen_phi: 512,
            last_theta_deg: 89.9,
            ..BvndfConfig::default()
        }
    }

    /// About the most memory, in bytes, that [`CompactBvndf::build`] holds at once with these
    /// settings on `threads` threads: the pair table twice (the points' per-cluster tables,
    /// then the interleaved one), one histogram per thread ([`crate::jointvis`]) and the fine
    /// seen table. The facets and points are not counted (tens of MB at 128²).
    pub fn peak_bytes(&self, threads: usize) -> f64 {
        let nt = self.n_theta.max(2) as f64;
        let np = self.n_phi.max(3) as f64;
        let nodes = nt * np;
        let kc = self.clusters.max(1) as f64;
        let table = nodes * (nodes + 1.0) / 2.0 * kc * STRIDE as f64 * 4.0;
        let hist = threads.max(1) as f64
            * (np * (np + 1.0) / 2.0)
            * (nt + 2.0).powi(2)
            * STRIDE as f64
            * 8.0;
        let seen = if self.seen_rays > 0 && self.seen_phi > self.n_phi {
            let phi = (self.seen_phi.div_ceil(self.n_phi.max(3)) * self.n_phi.max(3)) as f64;
            nt * phi * kc * (STRIDE + 6 * self.seen_bands) as f64 * 4.0
        } else {
            0.0
        };
        2.0 * table + hist + seen
    }

    /// The representation the libraries store ([`crate::lightlobes`]): one vMF per cluster. Looks
    /// that are compared with library items (the solvers' targets and re-evaluations) use it, so
    /// that a library combination reproduces its own look.
    pub fn library() -> Self {
        BvndfConfig {
            sub_lobes: 1,
            ..BvndfConfig::default()
        }
    }
}

/// The most seen rays per heightmap cell and direction: more no longer pays on tall fBm (a
/// sweep's rays share their vertical plane; 16 per cell on a 64² map gave 3.72 %, 4 per cell
/// 3.98 %, docs/forward-model.md "Line sweeps"), and a small map would sweep for nothing.
pub const SEEN_PER_CELL: usize = 16;

/// Floats stored per (node pair, cluster).
pub(crate) const STRIDE: usize = 9;

/// The compact BVNDF of one geometry.
#[derive(Debug, Clone, PartialEq)]
pub struct CompactBvndf {
    pub grid: DirGrid,
    pub clusters: usize,
    /// `[pair(a <= b)][cluster][G1 (x, y, z), G2 (xx, yy, zz, xy, xz, yz)]`, areas in units of `A_base`.
    pub table: Vec<f32>,
    /// The cluster centres (unit mean normals of each whole cluster).
    pub centres: Vec<Vec3>,
    /// Clusters whose facets all share one normal (planar walls, groove faces): their lobe is a
    /// delta at the centre, whatever rounding the `f32` moments carry.
    pub planar: Vec<bool>,
    /// Area of each cluster in units of `A_base`.
    pub cluster_area: Vec<f64>,
    /// Per curved cluster, its whole normal distribution split into sub-lobes, with what fits
    /// their visible fractions at a pair (empty for planar clusters and with `sub_lobes = 1`).
    pub shapes: Vec<Shape>,
    /// The curved clusters' facets by normal direction, for glossy lobes too sharp for the
    /// prefiltered table ([`Self::sharp_fbar`]).
    pub facets: FacetIndex,
    /// `Σ A n` of each cluster's facets, in units of `A_base`.
    pub resultants: Vec<Vec3>,
    /// The area of each cluster seen from each direction of a grid with more azimuths, by
    /// height band, which corrects the pair table's interpolation ([`crate::seen`]; `None`
    /// with `seen_phi` off).
    pub seen: Option<SeenTable>,
    /// Per cluster, `Σ A n` of its facets by sub-lobe part and height band
    /// (`[part · bands + band]`; one part for a cluster without sub-lobes), for
    /// [`Self::visible_fractions`].
    pub part_bands: Vec<Vec<Vec3>>,
    /// Height bands of `part_bands` (the fine seen table's; 1 without it).
    pub bands: usize,
    /// The heightfield itself, whose facets the sharp-lobe facet sum tests by rays
    /// ([`Self::sharp_fbar`], [`FacetRays`]).
    pub relief: Heightfield,
}

/// The index of the node pair `(a, b)` (either order) in the table's pair order.
#[inline]
pub(crate) fn pair_index(a: usize, b: usize) -> usize {
    let (lo, hi) = if a <= b { (a, b) } else { (b, a) };
    hi * (hi + 1) / 2 + lo
}

/// Area-weighted spherical k-means of unit normals; deterministic (farthest-point start).
/// Returns the cluster of every normal and the centres.
pub fn cluster_normals(normals: &[Vec3], weights: &[f64], k: usize) -> (Vec<u16>, Vec<Vec3>) {
    let k = k.max(1).min(normals.len().max(1));
    let mean = normals
        .iter()
        .zip(weights)
        .fold(Vec3::default(), |a, (n, w)| a + *n * *w)
        .normalized();
    let mut centres: Vec<Vec3> = Vec::with_capacity(k);
    // Farthest-point initialisation from the mean normal.
    let first = normals
        .iter()
        .enumerate()
        .min_by(|a, b| b.1.dot(mean).total_cmp(&a.1.dot(mean)))
        .map(|(i, _)| i)
        .unwrap_or(0);
    centres.push(normals.get(first).copied().unwrap_or(Vec3::Z));
    while centres.len() < k {
        let mut far = (0usize, f64::INFINITY);
        for (i, n) in normals.iter().enumerate() {
            let best = centres
                .iter()
                .map(|c| c.dot(*n))
                .fold(f64::NEG_INFINITY, f64::max);
            if best < far.1 {
                far = (i, best);
            }
        }
        if far.1 > 1.0 - 1e-12 {
            break; // fewer distinct normals than clusters
        }
        centres.push(normals[far.0]);
    }
    let mut assign = vec![0u16; normals.len()];
    for _ in 0..12 {
        assign
            .par_iter_mut()
            .zip(normals.par_iter())
            .for_each(|(a, n)| {
                let mut best = (0usize, f64::NEG_INFINITY);
                for (ci, c) in centres.iter().enumerate() {
                    let d = c.dot(*n);
                    if d > best.1 {
                        best = (ci, d);
                    }
                }
                *a = best.0 as u16;
            });
        let mut sums = vec![Vec3::default(); centres.len()];
        for ((n, w), a) in normals.iter().zip(weights).zip(&assign) {
            sums[*a as usize] = sums[*a as usize] + *n * *w;
        }
        let mut moved = 0.0f64;
        for (c, s) in centres.iter_mut().zip(sums) {
            if s.norm() > 0.0 {
                let nc = s.normalized();
                moved = moved.max(1.0 - nc.dot(*c));
                *c = nc;
            }
        }
        if moved < 1e-12 {
            break;
        }
    }
    (assign, centres)
}

impl CompactBvndf {
    /// Build the compact BVNDF of `hf`: cluster the facet normals, integrate the pair table over
    /// points on the surface (about [`BvndfConfig::points`]; at each point one horizon march per
    /// azimuth gives its visibility from every node at once, [`crate::jointvis`]), and, with
    /// [`BvndfConfig::seen_rays`], correct the views beyond 85° with the dense first hits and
    /// build the fine seen table.
    pub fn build(hf: &Heightfield, cfg: &BvndfConfig) -> Self {
        Self::build_with(hf, cfg, &Progress { quiet: true })
    }

    /// [`CompactBvndf::build`], with progress bars (rate and time left) for its long steps:
    /// the fine seen table's first hits (its refining rounds added to the bar as they start)
    /// and the surface points' horizon marches. The table is the same whatever `progress` says.
    pub fn build_with(hf: &Heightfield, cfg: &BvndfConfig, progress: &Progress) -> Self {
        let grid = DirGrid::to(cfg.n_theta, cfg.n_phi, cfg.last_theta_deg);
        let facets = hf.facets();
        let abase = hf.base_area();
        let normals: Vec<Vec3> = facets.iter().map(|f| f.n).collect();
        let areas: Vec<f64> = facets.iter().map(|f| f.area / abase).collect();
        let (assign, centres) = cluster_normals(&normals, &areas, cfg.clusters);
        let kc = centres.len();
        let np = grid.n_phi;
        let vis = Visibility::new(hf);
        let n_nodes = grid.len();
        // First hits per direction for the seen areas (line sweeps), at most SEEN_PER_CELL per
        // cell.
        let seen_count =
            Some(cfg.seen_rays.min(SEEN_PER_CELL * hf.width() * hf.height())).filter(|&r| r > 0);
        // The fine grid has a whole multiple of the pair grid's azimuths, so it holds its nodes.
        let centroid_z: Vec<f64> = facets
            .iter()
            .map(|f| (f.v[0].z + f.v[1].z + f.v[2].z) / 3.0)
            .collect();
        let seen_table = seen_count.filter(|_| cfg.seen_phi > np).map(|rays| {
            SeenTable::build(
                &vis,
                &normals,
                &areas,
                &centroid_z,
                &assign,
                kc,
                cfg.seen_bands,
                DirGrid::to(
                    cfg.n_theta,
                    cfg.seen_phi.div_ceil(np) * np,
                    cfg.last_theta_deg,
                ),
                cfg.seen_phi.div_ceil(np),
                rays,
                progress,
            )
        });
        let joint = joint_moments(
            &vis, &facets, abase, &assign, kc, &grid, cfg.points, progress,
        );
        let n_pairs = n_nodes * (n_nodes + 1) / 2;
        let mut table = vec![0f32; n_pairs * kc * STRIDE];
        table
            .par_chunks_mut(kc * STRIDE)
            .enumerate()
            .for_each(|(pi, out)| {
                for (c, e) in out.chunks_exact_mut(STRIDE).enumerate() {
                    e.copy_from_slice(&joint.pairs[c][pi * STRIDE..][..STRIDE]);
                }
            });
        if let Some(big) = seen_count {
            // Control variate for the views more grazing than the points were spread for
            // (GRAZING_DEG): jointly visible = seen from b - occluded towards a. The seen part
            // comes from the dense first hits (the fine seen table's row at b when there is one:
            // the same rays), the occluded part from the points (their seen minus their jointly
            // visible moments). Only for clusters whose every facet faces both a and b, where
            // the occluded part is occlusion by other geometry. Nearer the zenith the points
            // alone are the better estimate (1.02 % against 1.25 % with 8192 seen rays on a
            // rough fBm, `forward_fast.rs`).
            let dirs: Vec<Vec3> = (0..n_nodes).map(|a| grid.direction(a)).collect();
            let mut min_dot = vec![f64::INFINITY; kc * n_nodes];
            for (n, &k) in normals.iter().zip(&assign) {
                let row = &mut min_dot[k as usize * n_nodes..][..n_nodes];
                for (m, d) in row.iter_mut().zip(&dirs) {
                    *m = m.min(n.dot(*d));
                }
            }
            let faces = |k: usize, a: usize| min_dot[k * n_nodes + a] > 1e-9;
            // Nodes are ordered by polar angle, so the grazing ones are the last rows.
            let first = np
                * grid
                    .thetas
                    .iter()
                    .take_while(|&&t| t <= GRAZING_DEG.to_radians())
                    .count();
            let rows: Vec<Vec<[f64; STRIDE]>> = (first..n_nodes)
                .into_par_iter()
                .map(|b| match &seen_table {
                    Some(t) => t.moments_at(t.node_of(&grid, b)),
                    None => seen_moments(&vis, &normals, &assign, kc, &[], 1, dirs[b], big).0,
                })
                .collect();
            for (b, row) in (first..n_nodes).zip(&rows) {
                for a in 0..=b {
                    let pi = pair_index(a, b);
                    for k in (0..kc).filter(|&k| faces(k, a) && faces(k, b)) {
                        let e = &mut table[(pi * kc + k) * STRIDE..][..STRIDE];
                        for q in 0..STRIDE {
                            e[q] = (e[q] as f64 + row[k][q] - joint.seen[b][k][q]) as f32;
                        }
                    }
                }
            }
        }
        let planar = planar_clusters(&normals, &assign, &centres);
        let mut cluster_area = vec![0.0; kc];
        for (a, &k) in areas.iter().zip(&assign) {
            cluster_area[k as usize] += a;
        }
        let (shapes, part) = cluster_shapes(&normals, &areas, &assign, &planar, cfg.sub_lobes);
        // Each facet's height band, as the fine seen table splits its clusters (one without it).
        let bands = seen_table.as_ref().map_or(1, |t| t.bands);
        let band = if bands > 1 {
            crate::seen::facet_bands(&centroid_z, bands)
        } else {
            vec![0; facets.len()]
        };
        let mut part_bands: Vec<Vec<Vec3>> = shapes
            .iter()
            .map(|sh| vec![Vec3::default(); sh.parts.len().max(1) * bands])
            .collect();
        for i in 0..facets.len() {
            let p = crate::sublobes::part_row(part[i]);
            let e = &mut part_bands[assign[i] as usize][p * bands + band[i] as usize];
            *e = *e + normals[i] * areas[i];
        }
        let mut resultants = vec![Vec3::default(); kc];
        for ((n, a), &k) in normals.iter().zip(&areas).zip(&assign) {
            resultants[k as usize] = resultants[k as usize] + *n * *a;
        }
        // A cluster whose normals all but coincide comes as a delta (KAPPA_MAX), which a split
        // table evaluates with the whole material, sharp lobes included: like a planar cluster,
        // it stays out of the facet sum.
        let delta = |k: usize| {
            cluster_area[k] > 0.0
                && kappa_from_resultant((resultants[k].norm() / cluster_area[k]).min(1.0))
                    >= crate::vmf::KAPPA_MAX
        };
        let facets = FacetIndex::build(&normals, &areas, &assign, &part, &band, |k| {
            !planar[k] && !delta(k)
        });
        CompactBvndf {
            grid,
            clusters: kc,
            table,
            centres,
            planar,
            cluster_area,
            shapes,
            facets,
            resultants,
            seen: seen_table,
            part_bands,
            bands,
            relief: hf.clone(),
        }
    }

    /// The geometry's heightfield prepared for the sharp-lobe facet sum's rays
    /// ([`Self::sharp_fbar`]).
    pub fn facet_rays(&self) -> FacetRays<'_> {
        FacetRays::new(&self.relief)
    }

    /// Bytes of the stored representation (the table, the centres, the sub-lobes, the facet
    /// index, the fine seen table and the heightfield).
    pub fn bytes(&self) -> usize {
        self.table.len() * 4
            + self.seen.as_ref().map_or(0, SeenTable::bytes)
            + self.centres.len() * 49
            + self.shapes.iter().map(Shape::bytes).sum::<usize>()
            + self.facets.bytes()
            + self.part_bands.iter().map(|v| v.len() * 24).sum::<usize>()
            + self.relief.samples().len() * 8
    }

    #[inline]
    fn entry(&self, a: usize, b: usize, c: usize) -> &[f32] {
        &self.table[(pair_index(a, b) * self.clusters + c) * STRIDE..][..STRIDE]
    }

    /// `a_v(wo)` (in units of `A_base`) from the table's diagonal, interpolated with `wo`'s node
    /// weights `wb`.
    fn visible_area(&self, wo: Vec3, wb: &[(usize, f64)]) -> f64 {
        let mut diag = 0.0;
        for &(b, vb) in wb {
            if vb == 0.0 {
                continue;
            }
            for c in 0..self.clusters {
                diag += vb * self.seen_at(wo, b, c);
            }
        }
        diag
    }

    /// `w·G1` of cluster `c` on the table's diagonal at node `b`: its projected area seen from
    /// `b`, towards `w`.
    #[inline]
    fn seen_at(&self, w: Vec3, b: usize, c: usize) -> f64 {
        let e = self.entry(b, b, c);
        w.x * e[0] as f64 + w.y * e[1] as f64 + w.z * e[2] as f64
    }

    /// The fine seen table's correction at the pair `(wi, wo)` (node weights `wa`, `wb`), or
    /// `None` without one.
    fn correction(
        &self,
        wi: Vec3,
        wo: Vec3,
        wa: &[(usize, f64)],
        wb: &[(usize, f64)],
    ) -> Option<Correction> {
        let t = self.seen.as_ref()?;
        Some(t.correction(&self.grid, wi, wo, wa, wb))
    }

    /// The part of `fbar(wi, wo)` that the glossy lobes of `sharp` (too narrow for the
    /// prefiltered table) add on the curved clusters, summed over their facets within `radius`
    /// of the half vector ([`FacetIndex::near`]):
    /// `Σ_f ρ_f A_f (n_f·wo)+ (n_f·wi)+ f_sharp(n_f, wi, wo) / a_v(wo)`, the exact evaluator's
    /// facet sum (`a_v(wo) = A_base cos(theta_o)`, the identity), with `ρ_f` the facet's jointly
    /// visible fraction:
    ///
    /// * where those facets are few, tested by rays from `rays` (the
    ///   geometry's heightfield, [`Self::relief`]; [`FacetRays::visible_sum`]);
    /// * otherwise from the model, the fraction of the facet's sub-lobe part and height band
    ///   ([`Self::visible_fractions`]: its cluster's tabulated visible projected area towards
    ///   `wo`, shared among the parts as the sub-lobes' fit shares it and among the bands as the
    ///   fine seen table's band model does), corrected by the rays at a sample of the facets.
    ///
    /// (docs/forward-model.md, "Few facets under a sharp lobe: tested by rays".)
    /// Planar clusters (and curved ones whose normals all but coincide) are not included: their
    /// lobe is a delta, which the table's material answers at its centre, sharp lobes included.
    pub fn sharp_fbar(
        &self,
        wi: Vec3,
        wo: Vec3,
        sharp: &Material,
        radius: f64,
        rays: &FacetRays,
    ) -> f64 {
        if wi.z <= 0.0 || wo.z <= 0.0 || sharp.lobes.is_empty() || self.facets.is_empty() {
            return 0.0;
        }
        let h = (wi + wo).normalized();
        // Each facing entry with its term `A (n·wo) (n·wi) f_sharp`.
        let mut near = Vec::new();
        self.facets.near(h, radius, |e| {
            let (ci, co) = (e.n.dot(wi), e.n.dot(wo));
            if ci <= 0.0 || co <= 0.0 {
                return;
            }
            let t = e.area * co * ci * sharp.eval(e.n, wi, wo);
            if t > 0.0 {
                near.push((t, e));
            }
        });
        if near.is_empty() {
            return 0.0;
        }
        let ends = rays.ends(wi, wo);
        // The visibility model, set up only where the rays ask for it: the pair table's and
        // the fine seen table's weights and the correction, then each cluster's fractions.
        let mut model: Option<ModelAt> = None;
        let s = rays.visible_sum(&near, &ends, |e: &Near| {
            let m = model.get_or_insert_with(|| {
                let (wa, wb) = (self.grid.weights(wi), self.grid.weights(wo));
                let correction = self.correction(wi, wo, &wa, &wb);
                let fine = self
                    .seen
                    .as_ref()
                    .filter(|_| self.bands > 1)
                    .map(|t| (t.node_weights(wi), t.node_weights(wo)));
                ModelAt {
                    wa,
                    wb,
                    correction,
                    fine,
                    clusters: vec![None; self.clusters],
                }
            });
            let c = e.cluster;
            let (wa, wb, correction, fine) = (&m.wa, &m.wb, &m.correction, &m.fine);
            m.clusters[c]
                .get_or_insert_with(|| {
                    let g = blend(wa, wb, |na, b| self.entry(na, b, c));
                    self.visible_fractions(c, (wi, wo), &g, correction.as_ref(), fine.as_ref())
                })
                .of(e.part, e.band)
        });
        // `a_v(wo) = A_base cos(theta_o)`, exactly (the areas are in units of `A_base`): the
        // rays' sum is exact, and the tabulated `a_v` is off by up to 44 % at 89°.
        let v = s / wo.z;
        if v.is_finite() {
            v.max(0.0)
        } else {
            0.0
        }
    }

    /// The jointly visible fraction of cluster `c`'s facets at a pair `(wi, wo)` whose
    /// interpolated moments are `g`: the cluster's seen area towards `wo` (rescaled by the fine
    /// seen table) over its facets' projected area; for a cluster with sub-lobes, each part's
    /// own fraction, the sub-lobes' fit ([`Shape::visible`]) scaled so that the parts' seen
    /// areas sum to the cluster's (a part that does not face `wo` keeps the whole cluster's
    /// fraction); and with the fine seen table's height bands, each (part, band)'s, which also
    /// keeps each band's share of the seen area as the band model gives it
    /// ([`share_by_bands`]).
    ///
    /// `fine`: the fine seen table's interpolation weights of `wi` and `wo`
    /// ([`SeenTable::node_weights`]); `None`: by part only.
    fn visible_fractions(
        &self,
        c: usize,
        (wi, wo): (Vec3, Vec3),
        g: &[f64; STRIDE],
        correction: Option<&Correction>,
        fine: Option<&FineWeights>,
    ) -> Visible {
        let seen = wo.x * g[0] + wo.y * g[1] + wo.z * g[2];
        let seen = correction.map_or(seen, |k| k.area(c, seen));
        let shape = self.shapes.get(c).filter(|sh| !sh.is_empty());
        let facing = match shape {
            Some(sh) => sh.parts.iter().map(|p| p.resultant.dot(wo).max(0.0)).sum(),
            None => self.resultants[c].dot(wo).max(0.0),
        };
        let whole = if facing > 0.0 {
            (seen / facing).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let mut parts = Vec::new();
        if let Some(sh) = shape.filter(|_| whole > 0.0) {
            sh.visible(wo, g, &mut parts);
            let fitted: f64 = parts
                .iter()
                .zip(&sh.parts)
                .map(|(f, p)| f * p.resultant.dot(wo).max(0.0))
                .sum();
            if fitted > 0.0 && seen > 0.0 {
                let k = seen / fitted;
                for (f, p) in parts.iter_mut().zip(&sh.parts) {
                    *f = if p.resultant.dot(wo) > 0.0 {
                        (*f * k).clamp(0.0, 1.0)
                    } else {
                        whole
                    };
                }
            } else {
                parts.clear();
            }
        }
        let table = match (&self.seen, fine) {
            (Some(t), Some((fa, fb))) if self.bands > 1 && whole > 0.0 => {
                let mut bands = Vec::new();
                t.band_fractions((wi, fa), (wo, fb), c, &mut bands);
                let one = [whole];
                let fp: &[f64] = if parts.is_empty() { &one } else { &parts };
                share_by_bands(&self.part_bands[c], fp, &bands, seen, whole, wo)
            }
            _ => Vec::new(),
        };
        Visible {
            whole,
            parts,
            table,
            bands: self.bands,
        }
    }

    /// The lobes of `gamma(·; wi, wo)`: `(weight, vMF)` per cluster, weights summing to at most 1.
    /// Empty when `wo` is at or below the horizon. `split`: curved clusters come as their
    /// sub-lobes, for materials whose lobes resolve a cluster's shape
    /// ([`crate::prefilter::Prefiltered::resolves_shape`]); otherwise one vMF per cluster.
    pub fn lobes(&self, wi: Vec3, wo: Vec3, split: bool, out: &mut Vec<(f64, Vmf)>) {
        out.clear();
        if wi.z <= 0.0 || wo.z <= 0.0 {
            return;
        }
        let wa = self.grid.weights(wi);
        let wb = self.grid.weights(wo);
        let entry = |a: usize, b: usize, c: usize| -> &[f32] { self.entry(a, b, c) };
        let correction = self.correction(wi, wo, &wa, &wb);
        let diag = correction
            .as_ref()
            .map_or_else(|| self.visible_area(wo, &wb), |k| k.diag);
        let clusters = Clusters {
            centres: &self.centres,
            planar: &self.planar,
            area: &self.cluster_area,
            shapes: &self.shapes,
            split,
        };
        let dir = |n: usize| self.grid.direction(n);
        assemble_lobes(
            &clusters,
            wi,
            wo,
            &wa,
            dir,
            &wb,
            dir,
            &entry,
            |c| blend(&wa, &wb, |a, b| entry(a, b, c)),
            correction.as_ref(),
            diag,
            out,
        );
    }
}

/// Anything that gives the lobes of `gamma(·; wi, wo)` (the full compact BVNDF, or its
/// restriction to the library's lights, [`crate::lightlobes::LightLobes`]).
pub trait LobeSource {
    /// `(weight, vMF)` per normal cluster, or with `split` per sub-lobe of the curved clusters
    /// where the source keeps them ([`CompactBvndf::lobes`]); empty where `gamma` is not defined.
    fn lobes(&self, wi: Vec3, wo: Vec3, split: bool, out: &mut Vec<(f64, Vmf)>);
    /// Lobes at most (scratch capacity).
    fn clusters(&self) -> usize;
}

impl LobeSource for CompactBvndf {
    fn lobes(&self, wi: Vec3, wo: Vec3, split: bool, out: &mut Vec<(f64, Vmf)>) {
        CompactBvndf::lobes(self, wi, wo, split, out)
    }
    fn clusters(&self) -> usize {
        self.shapes
            .iter()
            .map(|s| s.parts.len().max(1))
            .sum::<usize>()
            .max(self.clusters)
    }
}

/// The per-cluster data lobes are assembled from.
pub(crate) struct Clusters<'a> {
    pub centres: &'a [Vec3],
    pub planar: &'a [bool],
    pub area: &'a [f64],
    /// Per cluster, its sub-lobes (empty: one vMF).
    pub shapes: &'a [Shape],
    /// Whether curved clusters come as their sub-lobes.
    pub split: bool,
}

/// The moments of one cluster interpolated over the nodes: `Σ_a Σ_b ua vb entry(a, b)`, in that
/// order (callers that blend several clusters at once must add in the same order to get the
/// same bits).
#[inline]
pub(crate) fn blend<'t>(
    wa: &[(usize, f64)],
    wb: &[(usize, f64)],
    entry: impl Fn(usize, usize) -> &'t [f32],
) -> [f64; STRIDE] {
    let mut a = [0.0f64; STRIDE];
    for &(b, vb) in wb {
        if vb == 0.0 {
            continue;
        }
        for &(na, ua) in wa {
            let w = ua * vb;
            if w == 0.0 {
                continue;
            }
            let e = entry(na, b);
            for q in 0..STRIDE {
                a[q] += w * e[q] as f64;
            }
        }
    }
    a
}

/// Turn tabulated moments into lobes (shared by every table layout). `wa`, `wb`: interpolation
/// weights of `wi` and `wo` over the table's light-side and view-side nodes, with their
/// directions `a_dir`, `b_dir`; `entry(a, b, c)`: the 9 moments of cluster `c` at `(a, b)`;
/// `blended(c)`: those of a non-planar cluster interpolated over the nodes, equal to [`blend`]
/// of `entry` (a table whose clusters lie side by side can blend them all in one pass over
/// memory, [`crate::lightlobes`]); `diag`: the visible projected area `a_v(wo)` from the same
/// table.
///
/// * a cluster's share of `gamma` is `wo·G1 / a_v(wo)`, its shape the vMF whose mean and mean
///   resultant length match the `(n·wo)`-weighted mean normal `G2 wo / (wo·G1)`;
/// * a planar cluster takes its analytic projected area `A_k (n·wo)+` times its jointly visible
///   fraction, interpolated only over the nodes it faces.
#[allow(clippy::too_many_arguments)]
pub(crate) fn assemble_lobes<'t, M: ClusterMoments>(
    cl: &Clusters,
    wi: Vec3,
    wo: Vec3,
    wa: &[(usize, f64)],
    a_dir: impl Fn(usize) -> Vec3,
    wb: &[(usize, f64)],
    b_dir: impl Fn(usize) -> Vec3,
    entry: &impl Fn(usize, usize, usize) -> &'t [f32],
    blended: impl Fn(usize) -> M,
    correction: Option<&Correction>,
    diag: f64,
    out: &mut Vec<(f64, Vmf)>,
) {
    out.clear();
    if !(diag > 0.0) {
        return;
    }
    for c in 0..cl.centres.len() {
        if cl.planar[c] {
            // A planar cluster's share is its analytic projected area times its jointly
            // visible fraction, interpolated only over the nodes where it faces both
            // directions (a facet facing a node carries no information about shadowing).
            let n = cl.centres[c];
            let (ci, co) = (n.dot(wi), n.dot(wo));
            let area = cl.area[c];
            if ci <= 0.0 || co <= 0.0 || !(area > 0.0) {
                continue;
            }
            let (mut rs, mut ws) = (0.0, 0.0);
            for &(b, vb) in wb {
                let wbv = b_dir(b);
                let cb = n.dot(wbv);
                if vb == 0.0 || cb <= 1e-9 {
                    continue;
                }
                for &(na, ua) in wa {
                    if ua == 0.0 || n.dot(a_dir(na)) <= 1e-9 {
                        continue;
                    }
                    let e = entry(na, b, c);
                    let g = wbv.x * e[0] as f64 + wbv.y * e[1] as f64 + wbv.z * e[2] as f64;
                    rs += ua * vb * (g / (area * cb)).clamp(0.0, 1.0);
                    ws += ua * vb;
                }
            }
            if ws > 0.0 {
                let v = area * co * rs / ws;
                out.push((
                    correction.map_or(v, |k| k.area(c, v)) / diag,
                    Vmf::new(crate::vmf::KAPPA_MAX, n),
                ));
                continue;
            }
        }
        if cl.planar[c] {
            let a = blend(wa, wb, |na, b| entry(na, b, c));
            push_cluster(cl, c, wo, &a, correction, diag, out);
        } else {
            push_cluster(cl, c, wo, &blended(c), correction, diag, out);
        }
    }
}

/// A cluster's moments `G1` and `G2` as [`assemble_lobes`] reads them: the 9 numbers in the
/// macro frame (`[f64; STRIDE]`), or another form that gives the same two products
/// ([`crate::lobecodec::Local`]).
pub(crate) trait ClusterMoments {
    /// `wo·G1`, the cluster's projected area.
    fn projected(&self, wo: Vec3) -> f64;
    /// `G2 wo`, the `(n·wo)`-weighted normal moment.
    fn second(&self, wo: Vec3) -> Vec3;
    /// `(G1, G2 as xx, yy, zz, xy, xz, yz)` in the macro frame.
    fn global(&self) -> [f64; STRIDE];
}

impl ClusterMoments for [f64; STRIDE] {
    #[inline]
    fn projected(&self, wo: Vec3) -> f64 {
        wo.x * self[0] + wo.y * self[1] + wo.z * self[2]
    }
    #[inline]
    fn second(&self, wo: Vec3) -> Vec3 {
        second_times(&self[3..], wo)
    }
    #[inline]
    fn global(&self) -> [f64; STRIDE] {
        *self
    }
}

/// The lobe (or sub-lobes) of cluster `c` from its moments `a`, appended to `out`
/// ([`assemble_lobes`]).
#[inline]
fn push_cluster(
    cl: &Clusters,
    c: usize,
    wo: Vec3,
    a: &impl ClusterMoments,
    correction: Option<&Correction>,
    diag: f64,
    out: &mut Vec<(f64, Vmf)>,
) {
    let tabulated = a.projected(wo);
    if !(tabulated > 0.0) {
        return;
    }
    // The lobe's shape comes from the tabulated moments; its share is rescaled and its
    // mean normal turned by the fine seen table.
    let mass = correction.map_or(tabulated, |k| k.area(c, tabulated));
    if !(mass > 0.0) {
        return;
    }
    // (n·wo)-weighted normal moment G2 wo.
    let m = a.second(wo);
    let m = match correction {
        Some(k) if !cl.planar[c] => k.mean(c, m),
        _ => m,
    };
    let len = m.norm();
    if !(len > 0.0) {
        return;
    }
    if let Some(shape) = cl.shapes.get(c).filter(|s| cl.split && s.parts.len() > 1) {
        if shape.push(wo, m, &a.global(), mass / diag, out) {
            return;
        }
    }
    let lobe = if cl.planar[c] {
        Vmf::new(crate::vmf::KAPPA_MAX, cl.centres[c])
    } else {
        Vmf::new(
            kappa_from_resultant((len / tabulated).min(1.0)),
            m * (1.0 / len),
        )
    };
    out.push((mass / diag, lobe));
}

/// The fine seen table's interpolation weights of a pair's two ends, `wi` then `wo`
/// ([`SeenTable::node_weights`]).
type FineWeights = (Vec<(usize, f64)>, Vec<(usize, f64)>);

/// What the sharp-lobe facet sum's visibility model needs at one pair
/// ([`CompactBvndf::sharp_fbar`]): the pair table's interpolation weights of `wi` and `wo`,
/// the fine seen table's correction and its own weights of both ends, and each cluster's
/// fractions once found.
struct ModelAt {
    wa: [(usize, f64); 4],
    wb: [(usize, f64); 4],
    correction: Option<Correction>,
    fine: Option<FineWeights>,
    clusters: Vec<Option<Visible>>,
}

/// The jointly visible fraction of one cluster's facets at a pair
/// ([`CompactBvndf::visible_fractions`]).
#[derive(Clone)]
struct Visible {
    /// The whole cluster's.
    whole: f64,
    /// Each sub-lobe's (empty: the whole cluster's for every facet).
    parts: Vec<f64>,
    /// Each (part, height band)'s, `[part · bands + band]` (empty: by part only).
    table: Vec<f64>,
    bands: usize,
}

impl Visible {
    /// The fraction of a facet of sub-lobe `part` (or [`crate::sublobes::NO_PART`]) and height
    /// band `band`.
    #[inline]
    fn of(&self, part: u16, band: u8) -> f64 {
        let p = crate::sublobes::part_row(part);
        if let Some(&r) = self.table.get(p * self.bands + band as usize) {
            return r;
        }
        self.parts.get(part as usize).copied().unwrap_or(self.whole)
    }
}

/// The most iterations of [`share_by_bands`]' proportional fitting.
const BAND_FIT_ROUNDS: usize = 16;

/// One cluster's jointly visible fraction per (part, height band), `[part · bands + band]`:
/// the table closest to uniform (iterative proportional fitting, a product of a factor per part
/// and one per band) whose seen areas towards `wo` add up, per part, to what the sub-lobes' fit
/// gives (`parts`: its fractions, or the cluster's `whole` fraction for one part) and, per band,
/// to what the band model gives (`bands`: per band, its jointly visible fraction), both scaled
/// to the cluster's seen area `seen`; each at most 1, the area that the cells held at 1 lose
/// given back to the others in proportion (docs/forward-model.md: seed 2's sharp cases,
/// median 0.81 → 0.36 %, max 9.11 → 9.04 % up to 85°).
/// `pb`: the facets' `Σ A n` per (part, band). Empty when a margin is empty.
fn share_by_bands(
    pb: &[Vec3],
    parts: &[f64],
    bands: &[f64],
    seen: f64,
    whole: f64,
    wo: Vec3,
) -> Vec<f64> {
    let nb = bands.len();
    let np = parts.len();
    if nb == 0 || pb.len() != np * nb || !(seen > 0.0) {
        return Vec::new();
    }
    let area: Vec<f64> = pb.iter().map(|r| r.dot(wo).max(0.0)).collect();
    let row = |p: usize| -> f64 { area[p * nb..][..nb].iter().sum() };
    let col = |h: usize| -> f64 { (0..np).map(|p| area[p * nb + h]).sum() };
    let scaled = |v: Vec<f64>| -> Option<Vec<f64>> {
        let t: f64 = v.iter().sum();
        (t > 0.0).then(|| v.iter().map(|x| x * seen / t).collect())
    };
    let (Some(pt), Some(bt)) = (
        scaled((0..np).map(|p| parts[p] * row(p)).collect()),
        scaled((0..nb).map(|h| bands[h] * col(h)).collect()),
    ) else {
        return Vec::new();
    };
    let mut r = vec![1.0f64; np * nb];
    for _ in 0..BAND_FIT_ROUNDS {
        // Until the bands' shares hold to 1e-6 after a round (most pairs: a few rounds).
        let mut moved = 0.0f64;
        for h in 0..nb {
            let s: f64 = (0..np).map(|p| r[p * nb + h] * area[p * nb + h]).sum();
            if s > 0.0 {
                let k = bt[h] / s;
                moved = moved.max((k - 1.0).abs());
                (0..np).for_each(|p| r[p * nb + h] *= k);
            }
        }
        if moved < 1e-6 {
            break;
        }
        for p in 0..np {
            let s: f64 = (0..nb).map(|h| r[p * nb + h] * area[p * nb + h]).sum();
            if s > 0.0 {
                let k = pt[p] / s;
                r[p * nb..][..nb].iter_mut().for_each(|x| *x *= k);
            }
        }
    }
    for p in 0..np {
        let facing = row(p) > 0.0;
        for x in &mut r[p * nb..][..nb] {
            *x = if facing && x.is_finite() {
                x.clamp(0.0, 1.0)
            } else {
                whole
            };
        }
    }
    // The cells held at 1 lose area the cluster has seen: the others take it back, in
    // proportion, while some are under 1.
    for _ in 0..4 {
        let (mut full, mut open) = (0.0, 0.0);
        for (x, a) in r.iter().zip(&area) {
            if *x >= 1.0 {
                full += a;
            } else {
                open += x * a;
            }
        }
        let want = seen - full;
        if !(open > 0.0) || want <= open * (1.0 + 1e-9) {
            break;
        }
        let k = want / open;
        for x in r.iter_mut().filter(|x| **x < 1.0) {
            *x = (*x * k).min(1.0);
        }
    }
    r
}

/// `Q w` for the symmetric matrix `Q` stored as `(xx, yy, zz, xy, xz, yz)`.
#[inline]
pub(crate) fn second_times(q: &[f64], w: Vec3) -> Vec3 {
    Vec3::new(
        q[0] * w.x + q[3] * w.y + q[4] * w.z,
        q[3] * w.x + q[1] * w.y + q[5] * w.z,
        q[4] * w.x + q[5] * w.y + q[2] * w.z,
    )
}

/// The 9 moments of one hit normal: `n` and the upper triangle of `n nᵀ`.
#[inline]
pub(crate) fn moments(n: Vec3) -> [f64; STRIDE] {
    [
        n.x,
        n.y,
        n.z,
        n.x * n.x,
        n.y * n.y,
        n.z * n.z,
        n.x * n.y,
        n.x * n.z,
        n.y * n.z,
    ]
}

/// Which facets form planar clusters: every facet normal equals its centre (to 1e-12).
pub(crate) fn planar_clusters(normals: &[Vec3], assign: &[u16], centres: &[Vec3]) -> Vec<bool> {
    let mut planar = vec![true; centres.len()];
    for (n, &k) in normals.iter().zip(assign) {
        if n.dot(centres[k as usize]) < 1.0 - 1e-12 {
            planar[k as usize] = false;
        }
    }
    planar
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::dir_from_deg;

    #[test]
    fn flat_patch_is_one_sharp_lobe() {
        let hf = Heightfield::flat(8, 8);
        let b = CompactBvndf::build(&hf, &BvndfConfig::default());
        let mut l = Vec::new();
        b.lobes(
            dir_from_deg(30.0, 20.0),
            dir_from_deg(80.0, 250.0),
            true,
            &mut l,
        );
        let total: f64 = l.iter().map(|x| x.0).sum();
        assert!((total - 1.0).abs() < 1e-6, "{l:?}");
        assert!(l.iter().all(|x| x.1.mu.z > 0.999999 && x.1.kappa >= 1e5));
    }

    /// Each facet's part of its cluster is the one whose moments hold it, and at a pair the
    /// parts' fractions share the cluster's seen area (each at most 1).
    #[test]
    fn parts_share_their_clusters_seen_area() {
        let hf = crate::generators::parse_generator("bumps:n=32,count=5,radius=7,height=4,seed=3")
            .unwrap()
            .build()
            .unwrap();
        let cfg = BvndfConfig {
            points: 4096,
            ..BvndfConfig::default()
        };
        let b = CompactBvndf::build(&hf, &cfg);
        let facets = hf.facets();
        let abase = hf.base_area();
        let normals: Vec<Vec3> = facets.iter().map(|f| f.n).collect();
        let areas: Vec<f64> = facets.iter().map(|f| f.area / abase).collect();
        let (assign, _) = cluster_normals(&normals, &areas, cfg.clusters);
        let planar = planar_clusters(&normals, &assign, &b.centres);
        let (shapes, part) = cluster_shapes(&normals, &areas, &assign, &planar, cfg.sub_lobes);
        assert_eq!(shapes, b.shapes);
        let mut sums = vec![Vec::new(); b.clusters];
        for (c, sh) in shapes.iter().enumerate() {
            sums[c] = vec![Vec3::default(); sh.parts.len()];
        }
        for (i, (&k, &p)) in assign.iter().zip(&part).enumerate() {
            let (k, p) = (k as usize, p as usize);
            if shapes[k].is_empty() {
                assert_eq!(p, crate::sublobes::NO_PART as usize);
            } else {
                sums[k][p] = sums[k][p] + normals[i] * areas[i];
            }
        }
        let mut checked = 0;
        for (c, sh) in shapes.iter().enumerate() {
            for (got, want) in sums[c].iter().zip(&sh.parts) {
                assert!((*got - want.resultant).norm() < 1e-9 * (1.0 + want.resultant.norm()));
            }
            for (wi, wo) in [
                (dir_from_deg(20.0, 10.0), dir_from_deg(60.0, 200.0)),
                (dir_from_deg(70.0, 90.0), dir_from_deg(80.0, 300.0)),
            ] {
                let (wa, wb) = (b.grid.weights(wi), b.grid.weights(wo));
                let g = blend(&wa, &wb, |na, nb| b.entry(na, nb, c));
                let v = b.visible_fractions(c, (wi, wo), &g, None, None);
                assert!(v
                    .parts
                    .iter()
                    .chain([&v.whole])
                    .all(|f| (0.0..=1.0).contains(f)));
                if v.parts.is_empty() || v.parts.contains(&1.0) {
                    continue;
                }
                let seen = wo.x * g[0] + wo.y * g[1] + wo.z * g[2];
                let shared: f64 = v
                    .parts
                    .iter()
                    .zip(&sh.parts)
                    .filter(|(_, p)| p.resultant.dot(wo) > 0.0)
                    .map(|(f, p)| f * p.resultant.dot(wo))
                    .sum();
                assert!(
                    (shared - seen).abs() <= 1e-9 * seen.max(1e-12),
                    "{shared} {seen}"
                );
                checked += 1;
            }
        }
        assert!(checked > 4, "{checked} pairs of curved clusters checked");
    }

    /// The table by part and band keeps both margins: each part's seen area as the sub-lobes'
    /// fit gives it and each band's as the band model gives it, both scaled to the cluster's.
    #[test]
    fn parts_by_bands_keep_both_margins() {
        let wo = dir_from_deg(50.0, 30.0);
        // 3 parts × 4 bands of facets all facing wo, with unequal areas.
        let pb: Vec<Vec3> = (0..12)
            .map(|i| wo * (0.02 + 0.01 * ((i * 7) % 5) as f64))
            .collect();
        let parts = [0.6, 0.3, 0.45];
        let bands = [0.2, 0.4, 0.5, 0.7];
        let seen = 0.05;
        let r = share_by_bands(&pb, &parts, &bands, seen, 0.4, wo);
        assert_eq!(r.len(), 12);
        let area = |i: usize| pb[i].dot(wo);
        let row = |p: usize| (0..4).map(|h| area(p * 4 + h)).sum::<f64>();
        let col = |h: usize| (0..3).map(|p| area(p * 4 + h)).sum::<f64>();
        let pt: Vec<f64> = (0..3).map(|p| parts[p] * row(p)).collect();
        let bt: Vec<f64> = (0..4).map(|h| bands[h] * col(h)).collect();
        let (ps, bs): (f64, f64) = (pt.iter().sum(), bt.iter().sum());
        assert!(r.iter().all(|x| (0.0..1.0).contains(x)), "{r:?}");
        let total: f64 = (0..12).map(|i| r[i] * area(i)).sum();
        assert!((total - seen).abs() < 1e-5 * seen, "{total}");
        for p in 0..3 {
            let got: f64 = (0..4).map(|h| r[p * 4 + h] * area(p * 4 + h)).sum();
            assert!((got - pt[p] * seen / ps).abs() < 1e-5 * seen, "part {p}");
        }
        // The fit stops once a round moves the bands' shares by under 1e-6.
        for h in 0..4 {
            let got: f64 = (0..3).map(|p| r[p * 4 + h] * area(p * 4 + h)).sum();
            assert!((got - bt[h] * seen / bs).abs() < 1e-5 * seen, "band {h}");
        }
        // A margin that is all zero leaves the table empty (by part only).
        assert!(share_by_bands(&pb, &parts, &[0.0; 4], seen, 0.4, wo).is_empty());
        // Where the fit asks more than all of a cell, the cell is held at 1 and the others
        // take the rest of the cluster's seen area.
        let total_area: f64 = (0..12).map(area).sum();
        let seen = 0.8 * total_area;
        let r = share_by_bands(&pb, &parts, &[0.05, 0.05, 0.05, 1.0], seen, 0.8, wo);
        assert!(
            r.iter().all(|x| (0.0..=1.0).contains(x)) && r.contains(&1.0),
            "{r:?}"
        );
        let total: f64 = (0..12).map(|i| r[i] * area(i)).sum();
        assert!((total - seen).abs() < 1e-9 * seen, "{total} vs {seen}");
    }
}
