//! The prefiltered material `F` of Eq. 7 and 18: the response of a material to a vMF lobe of
//! normals, tabulated so that the fast evaluator needs a few table reads per lobe.
//!
//! `F(wi, wo; kappa, mu) = ∫ f_r(n, wi, wo) (n·wi)+ rho(n; kappa, mu) dn`. Rotating the frame so that
//! `wi = (sin θh, 0, cos θh)` and `wo = (-sin θh, 0, cos θh)` (the appendix) leaves four variables:
//! `θh`, `kappa` and the lobe direction `mu'` in that frame; an isotropic BRDF is symmetric under
//! `mu'_y → -mu'_y`, so `mu'` is stored as `(θ_mu ∈ [0, pi], φ_mu ∈ [0, pi])`. Nodes: `θh`
//! uniform; kappa from 0 to 1e6 interpolated in `ln(1 + kappa)`; `θ_mu = pi u²` (dense near the
//! half vector, where glossy lobes live); `φ_mu` uniform. Interpolation is multilinear.
//!
//! Each entry is a quasi-Monte Carlo quadrature over the lobe. When the material has a glossy lobe
//! narrower than the vMF, half of the samples come from a lobe of the material's width around the
//! half vector and the two are combined with the balance heuristic (multiple importance sampling),
//! so mirror-like materials on broad normal lobes are integrated, not missed.

use crate::frame::{frame_around, Vec3};
use crate::material::Material;
use crate::store::ArrayFile;
use crate::vmf::{vmf_norm, Vmf, KAPPA_MAX};
use rayon::prelude::*;
use std::f64::consts::{FRAC_PI_2, PI};
use std::sync::Arc;

/// Table resolution and quadrature settings.
#[derive(Debug, Clone, PartialEq)]
pub struct PrefilterConfig {
    pub n_half: usize,
    pub n_theta_mu: usize,
    pub n_phi_mu: usize,
    /// Quadrature points per strategy and entry.
    pub samples: usize,
}

impl Default for PrefilterConfig {
    fn default() -> Self {
        PrefilterConfig {
            n_half: 24,
            n_theta_mu: 48,
            n_phi_mu: 13,
            samples: 96,
        }
    }
}

/// Kappa nodes (ln(1 + kappa) spacing is roughly even above 1).
pub const KAPPAS: [f64; 19] = [
    0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0, 512.0, 1024.0, 2048.0,
    4096.0, 16384.0, 65536.0, KAPPA_MAX,
];

/// Lobes at least this concentrated (width `1/sqrt(kappa)` ≤ 0.1 rad), and with `alpha² kappa`
/// at least this for every glossy lobe (width ≤ alpha / 10), are evaluated at their centre; so
/// are lobes at [`KAPPA_MAX`] (a planar cluster's delta) whatever the material's width.
pub const POINT_KAPPA: f64 = 100.0;

/// A material's prefiltered table.
#[derive(Debug, Clone)]
pub struct Prefiltered {
    pub cfg: PrefilterConfig,
    /// The material itself, for lobes so narrow that `F` is the BRDF at the lobe's centre.
    material: Material,
    /// `[i_half][i_kappa][i_theta_mu][i_phi_mu]` ([`Self::table`]).
    data: Table,
    /// `material.min_lobe_width()`, read for every lobe (the point-lobe test).
    min_width: Option<f64>,
    /// [`Self::resolves_shape`], read for every pair the fast evaluator assembles.
    resolves: bool,
    /// With [`Self::build_split`]: the glossy lobes too sharp for the table, which are left out
    /// of it and summed over facets instead, and their support radius.
    sharp: Option<(Material, f64)>,
    /// With [`Self::build_split`]: the material of the table (without the sharp lobes), which
    /// also answers for point lobes other than deltas.
    rest: Option<Material>,
}

impl Prefiltered {
    /// Whether the material has a lobe that resolves the shape of a geometry's normal
    /// distribution (any lobe but a Lambertian one): then the fast evaluator reads curved normal
    /// clusters as their sub-lobes ([`crate::bvndf::CompactBvndf::lobes`]).
    pub fn resolves_shape(&self) -> bool {
        self.resolves
    }
}

/// Any lobe but a Lambertian one ([`Prefiltered::resolves_shape`]).
fn resolves_shape(mat: &Material) -> bool {
    mat.lobes
        .iter()
        .any(|l| !matches!(l, crate::material::Lobe::Lambert(_)))
}

/// The rotated frame `(x', y', z' = h)` of a direction pair and its half angle θh.
#[inline]
pub fn half_frame(wi: Vec3, wo: Vec3) -> Option<(Vec3, Vec3, Vec3, f64)> {
    let s = wi + wo;
    let sl = s.norm();
    if sl < 1e-12 {
        return None;
    }
    let h = s * (1.0 / sl);
    let d = wi - wo;
    let dl = d.norm();
    let x = if dl < 1e-9 {
        frame_around(h).0
    } else {
        d * (1.0 / dl)
    };
    let y = h.cross(x);
    let theta_h = 0.5 * wi.dot(wo).clamp(-1.0, 1.0).acos();
    Some((x, y, h, theta_h))
}

/// Low-discrepancy point `k` of `n` in `[0,1)²` (Fibonacci lattice).
#[inline]
fn fib(k: usize, n: usize) -> (f64, f64) {
    (
        (k as f64 + 0.5) / n as f64,
        (k as f64 * 0.618_033_988_749_894_8).fract(),
    )
}

/// `∫ f_r (n·wi)+ rho dn` by quadrature, for `wi`, `wo` in the frame where `h = z`.
pub fn quadrature(mat: &Material, wi: Vec3, wo: Vec3, lobe: &Vmf, samples: usize) -> f64 {
    let proxy = proxy_points(mat, wi, wo, lobe.kappa, samples);
    quadrature_at(
        mat,
        wi,
        wo,
        lobe,
        &local_points(lobe.kappa, samples),
        proxy.as_ref(),
    )
}

/// The Fibonacci points of a lobe of concentration `kappa`, in its own frame
/// ([`Vmf::local_sample`]).
fn local_points(kappa: f64, samples: usize) -> Vec<[f64; 3]> {
    (0..samples)
        .map(|k| {
            let (u, v) = fib(k, samples);
            Vmf::local_sample(kappa, u, v)
        })
        .collect()
}

/// When the material has a glossy lobe narrower than about twice a lobe of `kappa`, the
/// quadrature's second strategy: a vMF of the material's width around the half vector, and its
/// Fibonacci points. It depends on the directions and `kappa` only, not on the lobe's mean.
fn proxy_points(
    mat: &Material,
    wi: Vec3,
    wo: Vec3,
    kappa: f64,
    samples: usize,
) -> Option<(Vmf, Vec<Vec3>)> {
    let km = mat
        .min_lobe_width()
        .map(|a| (2.0 / (a * a)).min(KAPPA_MAX))?;
    if km <= 0.5 * kappa {
        return None;
    }
    let proxy = Vmf::new(km, (wi + wo).normalized());
    let pts = (0..samples)
        .map(|k| {
            let (u, v) = fib(k, samples);
            proxy.sample(u, v)
        })
        .collect();
    Some((proxy, pts))
}

/// [`quadrature`] with the lobe's points in its own frame (`local`, from [`local_points`]) and
/// the second strategy's points (`proxy`, from [`proxy_points`]) computed once for many lobes:
/// with a proxy, the two strategies are combined with the balance heuristic.
fn quadrature_at(
    mat: &Material,
    wi: Vec3,
    wo: Vec3,
    lobe: &Vmf,
    local: &[[f64; 3]],
    proxy: Option<&(Vmf, Vec<Vec3>)>,
) -> f64 {
    let g = |n: Vec3| {
        let c = n.dot(wi);
        if c <= 0.0 {
            0.0
        } else {
            mat.eval(n, wi, wo) * c
        }
    };
    let frame = frame_around(lobe.mu);
    let mut s = 0.0;
    match proxy {
        Some((p, pts)) => {
            // `Vmf::eval` with each lobe's normalisation computed once.
            let (nl, np) = (vmf_norm(lobe.kappa), vmf_norm(p.kappa));
            let dens = |v: &Vmf, norm: f64, n: Vec3| {
                norm * (v.kappa * (n.dot(v.mu).clamp(-1.0, 1.0) - 1.0)).exp()
            };
            for (l, &q) in local.iter().zip(pts) {
                for n in [Vmf::place(lobe.mu, frame, l), q] {
                    let pl = dens(lobe, nl, n);
                    let den = pl + dens(p, np, n);
                    if den > 0.0 {
                        s += g(n) * pl / den;
                    }
                }
            }
        }
        None => {
            for l in local {
                s += g(Vmf::place(lobe.mu, frame, l));
            }
        }
    }
    s / local.len().max(1) as f64
}

/// A prefiltered table's entries: its own, or one material's byte range of a library's mapped
/// array, read in place (the map lives as long as the `Arc`).
#[derive(Clone)]
enum Table {
    Owned(Vec<f32>),
    Mapped {
        file: Arc<ArrayFile>,
        start: usize,
        end: usize,
    },
}

impl std::fmt::Debug for Table {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Table::Owned(v) => write!(f, "Owned({} entries)", v.len()),
            Table::Mapped { file, start, end } => {
                write!(f, "Mapped({}, bytes {start}..{end})", file.path.display())
            }
        }
    }
}

impl Table {
    #[inline]
    fn entries(&self) -> &[f32] {
        match self {
            Table::Owned(v) => v,
            // The range and its alignment were checked when the table was made
            // ([`Prefiltered::from_array`]); the empty slice is never reached.
            Table::Mapped { file, start, end } => file
                .bytes()
                .get(*start..*end)
                .and_then(|b| bytemuck::try_cast_slice(b).ok())
                .unwrap_or(&[]),
        }
    }
}

impl Prefiltered {
    pub fn build(mat: &Material, cfg: &PrefilterConfig) -> Self {
        let (nh, nk, nt, np) = (cfg.n_half, KAPPAS.len(), cfg.n_theta_mu, cfg.n_phi_mu);
        let data: Vec<f32> = (0..nh * nk)
            .into_par_iter()
            .flat_map_iter(|hk| {
                let (ih, ik) = (hk / nk, hk % nk);
                let th = Self::half_node(nh, ih);
                let wi = Vec3::new(th.sin(), 0.0, th.cos());
                let wo = Vec3::new(-th.sin(), 0.0, th.cos());
                let kappa = KAPPAS[ik];
                // The points of every entry of this (θh, kappa): computed once.
                let local = local_points(Vmf::new(kappa, Vec3::Z).kappa, cfg.samples);
                let proxy = proxy_points(mat, wi, wo, kappa, cfg.samples);
                (0..nt * np).map(move |tp| {
                    let (it, ip) = (tp / np, tp % np);
                    let tm = Self::theta_mu_node(nt, it);
                    let pm = PI * ip as f64 / (np - 1) as f64;
                    let mu = Vec3::new(tm.sin() * pm.cos(), tm.sin() * pm.sin(), tm.cos());
                    let v =
                        quadrature_at(mat, wi, wo, &Vmf::new(kappa, mu), &local, proxy.as_ref());
                    if v.is_finite() {
                        v as f32
                    } else {
                        0.0
                    }
                })
            })
            .collect();
        Prefiltered {
            cfg: cfg.clone(),
            material: mat.clone(),
            data: Table::Owned(data),
            min_width: mat.min_lobe_width(),
            resolves: resolves_shape(mat),
            sharp: None,
            rest: None,
        }
    }

    /// As [`Self::build`], but the material's glossy lobes narrower than `width` radians are
    /// left out of the table and kept apart ([`Self::sharp`]), for an evaluator that sums them
    /// over the geometry's facets ([`crate::fast::fbar_with_facets`]). A delta lobe (a planar
    /// cluster) still gets the whole material at its centre. Without such lobes, the same as
    /// [`Self::build`].
    pub fn build_split(mat: &Material, cfg: &PrefilterConfig, width: f64) -> Self {
        let (rest, sharp) = mat.split_by_width(width);
        if sharp.lobes.is_empty() {
            return Self::build(mat, cfg);
        }
        let radius = sharp
            .lobes
            .iter()
            .filter_map(|l| l.support_radius())
            .fold(0.0, f64::max);
        let data = if rest.lobes.is_empty() {
            Table::Owned(vec![
                0.0;
                cfg.n_half
                    * KAPPAS.len()
                    * cfg.n_theta_mu
                    * cfg.n_phi_mu
            ])
        } else {
            Self::build(&rest, cfg).data
        };
        Prefiltered {
            cfg: cfg.clone(),
            material: mat.clone(),
            data,
            min_width: rest.min_lobe_width(),
            resolves: resolves_shape(&rest),
            sharp: Some((sharp, radius)),
            rest: Some(rest),
        }
    }

    /// The lobes left out of the table by [`Self::build_split`], and their support radius.
    pub fn sharp(&self) -> Option<(&Material, f64)> {
        self.sharp.as_ref().map(|(m, r)| (m, *r))
    }

    /// A prefiltered material from a stored table (a library column) and the material it was
    /// built from (needed for narrow lobes, which are evaluated at their centre).
    pub fn from_table(
        mat: &Material,
        cfg: &PrefilterConfig,
        data: Vec<f32>,
    ) -> crate::error::Result<Self> {
        Self::with_table(mat, cfg, Table::Owned(data))
    }

    /// [`Self::from_table`] for material `index` of a library's `material/prefiltered.bsa`
    /// (`f32`, tables of `len` entries one after the other), read in place rather than copied
    /// out of the map: a solve reads up to a thousand materials' tables, 153 KB each at the
    /// paper's settings. A material past the last is an error naming the file.
    pub fn from_array(
        mat: &Material,
        cfg: &PrefilterConfig,
        file: Arc<ArrayFile>,
        index: usize,
        len: usize,
    ) -> crate::error::Result<Self> {
        let (start, end) = (index * len * 4, (index + 1) * len * 4);
        let table = file
            .f32s()?
            .get(index * len..(index + 1) * len)
            .map(|_| Table::Mapped {
                file: file.clone(),
                start,
                end,
            })
            .ok_or_else(|| {
                crate::error::Error::new(
                    file.path.display().to_string(),
                    format!("no material {index}"),
                )
            })?;
        Self::with_table(mat, cfg, table)
    }

    fn with_table(
        mat: &Material,
        cfg: &PrefilterConfig,
        data: Table,
    ) -> crate::error::Result<Self> {
        let want = cfg.n_half * KAPPAS.len() * cfg.n_theta_mu * cfg.n_phi_mu;
        if data.entries().len() != want {
            return Err(crate::error::Error::new(
                "prefiltered table",
                format!("{} entries, the settings need {want}", data.entries().len()),
            ));
        }
        Ok(Prefiltered {
            cfg: cfg.clone(),
            material: mat.clone(),
            data,
            min_width: mat.min_lobe_width(),
            resolves: resolves_shape(mat),
            sharp: None,
            rest: None,
        })
    }

    /// The table's entries, `[i_half][i_kappa][i_theta_mu][i_phi_mu]`.
    pub fn table(&self) -> &[f32] {
        self.data.entries()
    }

    fn half_node(nh: usize, i: usize) -> f64 {
        FRAC_PI_2 * i as f64 / (nh - 1) as f64
    }
    fn theta_mu_node(nt: usize, i: usize) -> f64 {
        let u = i as f64 / (nt - 1) as f64;
        PI * u * u
    }

    pub fn bytes(&self) -> usize {
        self.table().len() * 4
    }

    /// `F(wi, wo; lobe)`: for a lobe narrower than a tenth of a radian and than a tenth of every
    /// glossy lobe of the material ([`POINT_KAPPA`]), and for a delta ([`KAPPA_MAX`]: a planar
    /// cluster, such as a flat patch, under a material sharper than any table node resolves, as
    /// GGX `alpha = 0.001`), the material at the lobe's centre, `f_r(mu) (mu·wi)+` — exact in
    /// the limit, exact for a flat patch, and free of the table's interpolation across the
    /// `n·wo = 0` cutoff, which a narrow lobe of nearly edge-on facets sits on (smooth dimples:
    /// 8 % → 0.3 % against the exact method); otherwise multilinear interpolation of the table.
    pub fn eval(&self, wi: Vec3, wo: Vec3, lobe: &Vmf) -> f64 {
        self.eval_sum(wi, wo, std::slice::from_ref(&(1.0, *lobe)))
    }

    /// `Σ w F(wi, wo; lobe)` over the weighted lobes of one pair ([`Self::eval`] for each),
    /// with the pair's half-vector frame computed once.
    pub fn eval_sum(&self, wi: Vec3, wo: Vec3, lobes: &[(f64, Vmf)]) -> f64 {
        let mut frame = None;
        let mut s = 0.0;
        // The lobes' table coordinates are found LANES at a time ([`coords_lanes`]), for the
        // chunks that have a lobe read from the table; the sum runs in the lobes' order.
        for chunk in lobes.chunks(LANES) {
            let coords = if chunk.iter().all(|(_, l)| self.is_point(l)) {
                None
            } else {
                (*frame.get_or_insert_with(|| half_frame(wi, wo)))
                    .map(|f| coords_lanes(&self.cfg, f, chunk))
            };
            for (k, (w, lobe)) in chunk.iter().enumerate() {
                s += w * self.lobe_value(wi, lobe, || coords.as_ref().map(|c| c[k]), wo);
            }
        }
        s
    }

    /// `Σ w F` over lobes whose table coordinates were found once ([`prepare`]) for a table of
    /// the same settings: equal to [`Self::eval_sum`] on the same lobes, without the per-lobe
    /// trigonometry. Evaluating many materials on one geometry's lobes (the material solver,
    /// the joint search) pays for the coordinates once.
    pub fn eval_prepared(&self, wi: Vec3, wo: Vec3, lobes: &[PreparedLobe]) -> f64 {
        lobes
            .iter()
            .map(|p| p.weight * self.lobe_value(wi, &p.lobe, || p.coords, wo))
            .sum()
    }

    /// Whether `lobe` is evaluated at its centre for this material ([`POINT_KAPPA`]).
    #[inline]
    fn is_point(&self, lobe: &Vmf) -> bool {
        lobe.kappa >= KAPPA_MAX
            || (lobe.kappa >= POINT_KAPPA
                && self
                    .min_width
                    .is_none_or(|a| a * a * lobe.kappa >= POINT_KAPPA))
    }

    /// One lobe's `F`: at its centre when it is a point for this material, else from the table
    /// at `coords` (none: the pair has no half-vector frame, and the lobe contributes nothing).
    #[inline]
    fn lobe_value(
        &self,
        wi: Vec3,
        lobe: &Vmf,
        coords: impl FnOnce() -> Option<TableCoords>,
        wo: Vec3,
    ) -> f64 {
        if self.is_point(lobe) {
            let c = lobe.mu.dot(wi);
            // A delta (planar cluster) sees the whole material; other point lobes the table's.
            let m = match &self.rest {
                Some(rest) if lobe.kappa < KAPPA_MAX => rest,
                _ => &self.material,
            };
            return if c > 0.0 {
                m.eval(lobe.mu, wi, wo) * c
            } else {
                0.0
            };
        }
        coords().map_or(0.0, |c| self.eval_coords(&c))
    }

    /// Interpolated entry for half angle `th`, `kappa` and unit `mu` in the half-vector frame.
    pub fn eval_local(&self, th: f64, kappa: f64, mu: Vec3) -> f64 {
        self.eval_coords(&local_coords(&self.cfg, th, kappa, mu))
    }

    /// The multilinear interpolation of the table at `c`.
    fn eval_coords(&self, c: &TableCoords) -> f64 {
        let (nk, nt, np) = (KAPPAS.len(), self.cfg.n_theta_mu, self.cfg.n_phi_mu);
        let data = self.table();
        let mut s = 0.0;
        for (dh, ah) in [(0, 1.0 - c.wh), (1, c.wh)] {
            if ah == 0.0 {
                continue;
            }
            for (dk, ak) in [(0, 1.0 - c.wk), (1, c.wk)] {
                if ak == 0.0 {
                    continue;
                }
                let base = ((c.ih + dh) * nk + c.ik + dk) * nt;
                for (dt, at) in [(0, 1.0 - c.wt), (1, c.wt)] {
                    if at == 0.0 {
                        continue;
                    }
                    let row = (base + c.it + dt) * np + c.ip;
                    let v = data[row] as f64 * (1.0 - c.wp) + data[row + 1] as f64 * c.wp;
                    s += ah * ak * at * v;
                }
            }
        }
        s
    }
}

/// Where a lobe falls in a table of given settings: the lower node and the weight of the upper
/// one along each axis (half angle, kappa, `θ_mu`, `φ_mu`). It depends on the lobe, the pair
/// and the settings, not on the material.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TableCoords {
    ih: usize,
    ik: usize,
    it: usize,
    ip: usize,
    wh: f64,
    wk: f64,
    wt: f64,
    wp: f64,
}

/// A weighted lobe of one pair with its table coordinates, ready for many materials.
#[derive(Debug, Clone, Copy)]
pub struct PreparedLobe {
    pub weight: f64,
    pub lobe: Vmf,
    coords: Option<TableCoords>,
}

/// The lobes of pair `(wi, wo)` with their coordinates in tables of settings `cfg`.
pub fn prepare(
    cfg: &PrefilterConfig,
    wi: Vec3,
    wo: Vec3,
    lobes: &[(f64, Vmf)],
) -> Vec<PreparedLobe> {
    let frame = half_frame(wi, wo);
    lobes
        .chunks(LANES)
        .flat_map(|chunk| {
            let coords = frame.map(|f| coords_lanes(cfg, f, chunk));
            chunk
                .iter()
                .enumerate()
                .map(move |(k, &(weight, lobe))| PreparedLobe {
                    weight,
                    lobe,
                    coords: coords.as_ref().map(|c| c[k]),
                })
        })
        .collect()
}

/// Lobes whose table coordinates are found together ([`coords_soa`]).
pub const LANES: usize = 8;

/// The table coordinates of up to [`LANES`] lobes of one pair (half-vector frame `f`), found
/// together by [`coords_soa`]. Entries past `lobes.len()` are meaningless.
fn coords_lanes(
    cfg: &PrefilterConfig,
    f: (Vec3, Vec3, Vec3, f64),
    lobes: &[(f64, Vmf)],
) -> [TableCoords; LANES] {
    let (x, y, h, th) = f;
    // Unused lanes hold kappa 0 and mu 0.
    let (mut kap, mut mx, mut my, mut mz) =
        ([0.0; LANES], [0.0; LANES], [0.0; LANES], [0.0; LANES]);
    for (k, (_, l)) in lobes.iter().take(LANES).enumerate() {
        kap[k] = l.kappa;
        mx[k] = l.mu.dot(x);
        my[k] = l.mu.dot(y).abs();
        mz[k] = l.mu.dot(h);
    }
    coords_soa(cfg, th, &kap, [&mx, &my, &mz])
}

/// The coordinates of half angle `th`, `kappa` and unit `mu` (half-vector frame).
fn local_coords(cfg: &PrefilterConfig, th: f64, kappa: f64, mu: Vec3) -> TableCoords {
    let lane = |v: f64| std::array::from_fn(|k| if k == 0 { v } else { 0.0 });
    coords_soa(
        cfg,
        th,
        &lane(kappa),
        [&lane(mu.x), &lane(mu.y), &lane(mu.z)],
    )[0]
}

/// The table coordinates at half angle `th` of [`LANES`] lobes given by their `kappa` and the
/// components `mu = [x, y, z]` of their unit directions in the half-vector frame, lane by lane
/// in branch-free loops that the compiler runs in vector registers (`fastmath::ln_1p_select`;
/// the `kappa` node is a count of the nodes below; the floors of clamped, non-negative
/// coordinates are truncations). Found one lobe at a time, with branches, each lobe was a long
/// chain of dependent scalar operations (`ln_1p`, `acos`, `atan2`, a search over the `kappa`
/// nodes): a quarter of a geometry solve's processor time (`perf record` of `biscale validate …
/// --solvers geometry`). The values are the same bit for bit (the same operations in the same
/// order; tests).
fn coords_soa(
    cfg: &PrefilterConfig,
    th: f64,
    kap: &[f64; LANES],
    mu: [&[f64; LANES]; 3],
) -> [TableCoords; LANES] {
    let (nh, nk, nt, np) = (cfg.n_half, KAPPAS.len(), cfg.n_theta_mu, cfg.n_phi_mu);
    let lkn = &*LN_KAPPAS;
    let [mx, my, mz] = mu;
    let fh = (th / FRAC_PI_2 * (nh - 1) as f64).clamp(0.0, (nh - 1) as f64);
    let (ih, wh) = split_lane(fh, nh);
    let mut lk = [0.0; LANES];
    for k in 0..LANES {
        lk[k] = crate::fastmath::ln_1p_select(kap[k].clamp(0.0, KAPPA_MAX));
    }
    // The last node at or below `lk` (at most the last but one), counted: the nodes increase.
    let mut ik = [0usize; LANES];
    for &node in &lkn[1..nk - 1] {
        for k in 0..LANES {
            ik[k] += (lk[k] >= node) as usize;
        }
    }
    let (mut ft, mut fp) = ([0.0; LANES], [0.0; LANES]);
    for k in 0..LANES {
        let tm = crate::fastmath::acos(mz[k]);
        ft[k] = ((tm / PI).sqrt() * (nt - 1) as f64).clamp(0.0, (nt - 1) as f64);
        let pm = crate::fastmath::atan2_upper(my[k].abs(), mx[k]);
        fp[k] = (pm / PI * (np - 1) as f64).clamp(0.0, (np - 1) as f64);
    }
    std::array::from_fn(|k| {
        let ik = ik[k].min(nk - 2);
        let wk = ((lk[k] - lkn[ik]) / (lkn[ik + 1] - lkn[ik])).clamp(0.0, 1.0);
        let (it, wt) = split_lane(ft[k], nt);
        let (ip, wp) = split_lane(fp[k], np);
        TableCoords {
            ih,
            ik,
            it,
            ip,
            wh,
            wk,
            wt,
            wp,
        }
    })
}

/// The lower node and the weight of the upper one for a coordinate `f` clamped to `[0, n - 1]`
/// (NaN: node 0, weight NaN): the floor of a non-negative number is its truncation.
#[inline]
fn split_lane(f: f64, n: usize) -> (usize, f64) {
    let i = (f as i32 as usize).min(n - 2);
    (i, f - i as f64)
}

/// `ln(1 + kappa)` at the kappa nodes.
static LN_KAPPAS: std::sync::LazyLock<Vec<f64>> =
    std::sync::LazyLock::new(|| KAPPAS.iter().map(|k| k.ln_1p()).collect());

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::dir_from_deg;
    use crate::material::parse_material;

    #[test]
    fn sharp_lobe_at_normal_gives_brdf_times_cosine() {
        let m = parse_material("ggx:alpha=0.3+lambert:albedo=0.4").unwrap();
        let (wi, wo) = (dir_from_deg(30.0, 0.0), dir_from_deg(50.0, 150.0));
        let want = m.eval(Vec3::Z, wi, wo) * wi.z;
        let q = quadrature(&m, wi, wo, &Vmf::new(KAPPA_MAX, Vec3::Z), 64);
        assert!((q / want - 1.0).abs() < 1e-3, "{q} {want}");
        let t = Prefiltered::build(
            &m,
            &PrefilterConfig {
                samples: 32,
                ..Default::default()
            },
        );
        let f = t.eval(wi, wo, &Vmf::new(KAPPA_MAX, Vec3::Z));
        assert!((f / want - 1.0).abs() < 0.03, "{f} {want}");
    }

    #[test]
    fn prepared_lobes_give_the_same_sum_as_eval_sum() {
        let cfg = PrefilterConfig {
            n_half: 6,
            n_theta_mu: 8,
            n_phi_mu: 5,
            samples: 8,
        };
        let lobes = [
            (0.5, Vmf::new(3.0, dir_from_deg(20.0, 40.0))),
            (0.3, Vmf::new(500.0, dir_from_deg(5.0, 200.0))),
            (0.2, Vmf::new(KAPPA_MAX, Vec3::Z)),
        ];
        for spec in ["ggx:alpha=0.02", "blinn:n=60+lambert:albedo=0.2"] {
            let t = Prefiltered::build(&parse_material(spec).unwrap(), &cfg);
            for (wi, wo) in [
                (dir_from_deg(30.0, 0.0), dir_from_deg(50.0, 150.0)),
                (dir_from_deg(40.0, 10.0), dir_from_deg(40.0, 190.0)),
                (dir_from_deg(0.0, 0.0), dir_from_deg(0.0, 0.0)),
            ] {
                let want = t.eval_sum(wi, wo, &lobes);
                let got = t.eval_prepared(wi, wo, &prepare(&cfg, wi, wo, &lobes));
                assert_eq!(got.to_bits(), want.to_bits(), "{spec}");
            }
        }
    }

    /// The coordinates of one lobe as they were found before `coords_soa`: with branches, one
    /// operation after another. `(node, weight)` per axis: half angle, kappa, `θ_mu`, `φ_mu`.
    fn one_lobe_reference(
        cfg: &PrefilterConfig,
        th: f64,
        kappa: f64,
        mu: Vec3,
    ) -> [(usize, f64); 4] {
        let (nh, nk, nt, np) = (cfg.n_half, KAPPAS.len(), cfg.n_theta_mu, cfg.n_phi_mu);
        let lkn = &*LN_KAPPAS;
        let split = |f: f64, n: usize| {
            let i = (crate::fastmath::floor(f) as usize).min(n - 2);
            (i, f - i as f64)
        };
        let lk = crate::fastmath::ln_1p(kappa.clamp(0.0, KAPPA_MAX));
        let mut ik = 0;
        while ik + 2 < nk && lk >= lkn[ik + 1] {
            ik += 1;
        }
        let tm = crate::fastmath::acos(mu.z);
        let pm = crate::fastmath::atan2_upper(mu.y.abs(), mu.x);
        [
            split(
                (th / FRAC_PI_2 * (nh - 1) as f64).clamp(0.0, (nh - 1) as f64),
                nh,
            ),
            (
                ik,
                ((lk - lkn[ik]) / (lkn[ik + 1] - lkn[ik])).clamp(0.0, 1.0),
            ),
            split(
                ((tm / PI).sqrt() * (nt - 1) as f64).clamp(0.0, (nt - 1) as f64),
                nt,
            ),
            split((pm / PI * (np - 1) as f64).clamp(0.0, (np - 1) as f64), np),
        ]
    }

    #[test]
    fn coordinates_found_in_lanes_equal_those_found_one_lobe_at_a_time() {
        let cfg = PrefilterConfig::default();
        let mut rng = crate::rng::Rng::new(7);
        let mut dir = |up: bool| {
            let v = Vec3::new(rng.normal(), rng.normal(), rng.normal()).normalized();
            if up && v.z < 0.0 {
                Vec3::new(v.x, v.y, -v.z)
            } else {
                v
            }
        };
        // Kappas from 0 through the nodes' range to the cap, and beyond it.
        let kappas = [
            0.0, 1e-9, 5e-5, 1e-4, 0.25, 0.3, 1.0, 7.5, 4096.0, 3e4, 1e6, KAPPA_MAX, 1e9,
        ];
        for n in [1usize, 3, 8, 9, 16, 17, 32] {
            for _ in 0..50 {
                let (wi, wo) = (dir(true), dir(true));
                let lobes: Vec<(f64, Vmf)> = (0..n)
                    .map(|i| {
                        (
                            1.0,
                            Vmf::new(kappas[(i * 5 + n) % kappas.len()], dir(false)),
                        )
                    })
                    .collect();
                let Some(f) = half_frame(wi, wo) else {
                    continue;
                };
                let (x, y, h, th) = f;
                for chunk in lobes.chunks(LANES) {
                    let got = coords_lanes(&cfg, f, chunk);
                    for (k, (_, l)) in chunk.iter().enumerate() {
                        let mu = Vec3::new(l.mu.dot(x), l.mu.dot(y).abs(), l.mu.dot(h));
                        let c = &got[k];
                        let lanes = [(c.ih, c.wh), (c.ik, c.wk), (c.it, c.wt), (c.ip, c.wp)];
                        let want = one_lobe_reference(&cfg, th, l.kappa, mu);
                        let bits = |a: [(usize, f64); 4]| a.map(|(i, w)| (i, w.to_bits()));
                        assert_eq!(bits(lanes), bits(want), "{l:?}");
                        assert_eq!(*c, local_coords(&cfg, th, l.kappa, mu));
                    }
                }
            }
        }
    }
}
