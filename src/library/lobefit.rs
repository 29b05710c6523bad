//! CX weights refitted to what the geometry search evaluates: the representatives' light lobes.
//!
//! The CX weights `X` of [`super::build`] are fitted to the binned BVNDF columns (Eq. 11). The
//! geometry solver's stage 1 combines them with the representatives' `fbar` from their *light
//! lobes* (Eq. 12), which are far more accurate than the binned columns for narrow material lobes
//! — and differ from them most where the weights are large: under the paper's protocol on
//! `paper4` (41,108 geometries), tall or rough surfaces under sharp materials ranked past the
//! 4,096th in both of stage 1's rankings (`docs/solvers.md`). Here each geometry's weights are
//! fitted again in the space the search works in: the `fbar` of its own light lobes at fixed
//! probe pairs under the library's representative materials (every library material is close
//! to a combination of them, Sec. 4.2), against the same values of the geometry
//! representatives; a least squares pulled towards the binned fit, which keeps the weights where
//! the probes say little. The result, `geometry/x-lobes.bsa`, has the shape of `x.bsa` and gives
//! the solver's stage 1 a third ranking.
//!
//! Probes: every library light with 48 view directions uniform over the hemisphere and 16 in a
//! 20° cap around its mirror direction (where narrow lobes put their highlights); each
//! material's values scaled to unit RMS over the representatives, so that every material counts
//! alike. Twice as many views gave the same rates on `paper4` and one case in 50 more on
//! `paper16`, at twice the cost.

use super::GeometryLobes;
use crate::error::{Error, Result};
use crate::frame::{dir_from_rad, DirPair, Vec3};
use crate::gamma::GammaLayout;
use crate::lightlobes::{LightLobes, LightPairs};
use crate::prefilter::Prefiltered;
use faer::Mat;
use rayon::prelude::*;

/// Uniform probe views per light, and views in the cap around its mirror direction.
const UNIFORM_VIEWS: usize = 48;
const MIRROR_VIEWS: usize = 16;
const MIRROR_CAP_DEG: f64 = 20.0;

/// Weight of the prior (the binned fit), relative to the mean diagonal of `Φ_Cᵀ Φ_C`.
const PRIOR: f64 = 1e-3;

/// The probe pairs (placed in the light-lobe table once) and the probe materials' tables.
pub struct Probes {
    at: LightPairs,
    tables: Vec<Prefiltered>,
}

impl Probes {
    /// The probe pairs with the given materials' tables.
    pub fn with_tables(layout: &GammaLayout, tables: Vec<Prefiltered>) -> Self {
        let golden = 0.618_033_988_749_895;
        let mut pairs = Vec::new();
        for &wi in &layout.lights {
            for k in 0..UNIFORM_VIEWS {
                let u = (k as f64 + 0.5) / UNIFORM_VIEWS as f64;
                let theta = u.acos().min(88f64.to_radians());
                pairs.push(DirPair {
                    wi,
                    wo: dir_from_rad(theta, std::f64::consts::TAU * (k as f64 * golden).fract()),
                });
            }
            // A cap around the mirror direction (-wi.x, -wi.y, wi.z), uniform in solid angle.
            let m = Vec3::new(-wi.x, -wi.y, wi.z);
            let (t, b) = tangent_frame(m);
            let c0 = MIRROR_CAP_DEG.to_radians().cos();
            for k in 0..MIRROR_VIEWS {
                let u = (k as f64 + 0.5) / MIRROR_VIEWS as f64;
                let ct = 1.0 - u * (1.0 - c0);
                let st = (1.0 - ct * ct).max(0.0).sqrt();
                let ph = std::f64::consts::TAU * (k as f64 * golden).fract();
                let w = m * ct + t * (st * ph.cos()) + b * (st * ph.sin());
                if w.z > 0.02 {
                    pairs.push(DirPair {
                        wi,
                        wo: w.normalized(),
                    });
                }
            }
        }
        Probes {
            at: LightPairs::new(layout, pairs),
            tables,
        }
    }

    /// Values per geometry: probe materials × probe pairs.
    pub fn len(&self) -> usize {
        self.tables.len() * self.at.pairs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// One geometry's `fbar` at every probe pair for every probe material (material-major).
    pub fn values(&self, lobes: &LightLobes) -> Vec<f64> {
        let fixed = lobes.fixed(&self.at);
        self.tables.iter().flat_map(|t| fixed.fbar(t)).collect()
    }
}

/// Two unit vectors completing `n` to an orthonormal frame.
fn tangent_frame(n: Vec3) -> (Vec3, Vec3) {
    let a = if n.x.abs() < 0.9 {
        Vec3::new(1.0, 0.0, 0.0)
    } else {
        Vec3::new(0.0, 1.0, 0.0)
    };
    let t = a.cross(n).normalized();
    (t, n.cross(t))
}

/// Refitted weights `[geometries][representatives]` (the layout of `x.bsa`) for the light-lobe
/// records in `lobes` and the representatives `reps`, probed with the materials `tables`:
/// per geometry `j`, `x = argmin |Φ_C x − Φ_j|² + μ |x − x0_j|²` with `Φ` the probe values
/// (each material's block scaled to unit RMS over the representatives), `x0` the binned fit
/// (`x.bsa`, the prior where the probes say little) and `μ = PRIOR ×` the mean diagonal of
/// `Φ_Cᵀ Φ_C`. `progress(n)` is called as each block of `n` geometries finishes.
pub fn fit(
    lobes: &GeometryLobes,
    tables: Vec<Prefiltered>,
    reps: &[usize],
    x0: &[f32],
    progress: &(dyn Fn(usize) + Sync),
) -> Result<Vec<f32>> {
    let n = lobes.len();
    let probes = Probes::with_tables(&lobes.layout, tables);
    let (p, r) = (probes.len(), reps.len());
    if r == 0 || n == 0 || probes.is_empty() {
        return Ok(x0.to_vec());
    }
    if x0.len() != n * r {
        return Err(Error::new(
            lobes.path().display().to_string(),
            format!(
                "{} prior weights for {n} geometries × {r} representatives",
                x0.len()
            ),
        ));
    }
    let per = probes.at.pairs.len();
    // The representatives' probe values, and each probe material's scale.
    let cols: Vec<Vec<f64>> = reps
        .par_iter()
        .map(|&k| Ok(probes.values(&lobes.read(k)?)))
        .collect::<Result<_>>()?;
    let scale: Vec<f64> = (0..probes.tables.len())
        .map(|m| {
            let ss: f64 = cols
                .iter()
                .map(|c| c[m * per..(m + 1) * per].iter().map(|v| v * v).sum::<f64>())
                .sum();
            let rms = (ss / (per * r) as f64).sqrt();
            if rms > 0.0 && rms.is_finite() {
                1.0 / rms
            } else {
                0.0
            }
        })
        .collect();
    let scaled = |v: &mut [f64]| {
        for (i, x) in v.iter_mut().enumerate() {
            *x *= scale[i / per];
        }
    };
    let mut c = Mat::<f64>::zeros(p, r);
    for (k, col) in cols.iter().enumerate() {
        let mut col = col.clone();
        scaled(&mut col);
        for (i, v) in col.iter().enumerate() {
            c[(i, k)] = *v;
        }
    }
    // (Φ_Cᵀ Φ_C + μ I)⁻¹ once; per geometry, its product with Φ_Cᵀ Φ_j + μ x0_j.
    let ct = c.transpose().to_owned();
    let g = crate::lowrank::reconstruct(ct.as_ref(), c.as_ref());
    let mu = PRIOR * (0..r).map(|i| g[(i, i)]).sum::<f64>() / r as f64;
    let inv = crate::lowrank::ridge_inverse(g.as_ref(), mu)?;
    let m = crate::lowrank::reconstruct(inv.as_ref(), ct.as_ref());
    const BLOCK: usize = 64;
    let blocks: Vec<std::ops::Range<usize>> = (0..n)
        .step_by(BLOCK)
        .map(|s| s..(s + BLOCK).min(n))
        .collect();
    let parts: Vec<Vec<f32>> = blocks
        .par_iter()
        .map(|b| {
            let mut v = Mat::<f64>::zeros(p, b.len());
            for (jj, j) in b.clone().enumerate() {
                let mut col = probes.values(&lobes.read(j)?);
                scaled(&mut col);
                for (i, x) in col.iter().enumerate() {
                    v[(i, jj)] = *x;
                }
            }
            let fit = crate::lowrank::reconstruct(m.as_ref(), v.as_ref());
            let mut out = Vec::with_capacity(b.len() * r);
            for (jj, j) in b.clone().enumerate() {
                let prior = crate::lowrank::reconstruct(
                    inv.as_ref(),
                    Mat::<f64>::from_fn(r, 1, |k, _| mu * x0[j * r + k] as f64).as_ref(),
                );
                for k in 0..r {
                    let w = fit[(k, jj)] + prior[(k, 0)];
                    if !w.is_finite() {
                        return Err(Error::new(
                            lobes.path().display().to_string(),
                            format!("geometry {j}: a refitted weight is not finite"),
                        ));
                    }
                    out.push(w as f32);
                }
            }
            progress(b.len());
            Ok(out)
        })
        .collect::<Result<_>>()?;
    Ok(parts.concat())
}
