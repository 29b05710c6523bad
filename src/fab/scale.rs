//! The physical scale window of a detail. BVNDFs are scale-free, so the patch size (the side of
//! one period along x, in mm) is free; fabrication and viewing bound it:
//!
//! Lower bounds (the detail must be large enough to be made):
//! - **process**: the smallest patch size at which the made surface
//!   ([`super::millability::simulate`]) stays within `max_deviation_frac` × relief of the design.
//!   Scaling a surface up by `s` is the same as shrinking the tool by `1/s`, and a closing by a
//!   smaller ball (disc) is never higher than by a larger one, so the relative deviation falls as
//!   the patch grows; the bound is found by bisection on log(patch size) to 2 %. The search never
//!   goes below a patch of twice the tool (or printer XY) diameter.
//! - **features**: the narrowest valley or ridge ([`super::features`], measured at the same
//!   tolerance) must be at least `min_feature_mm`.
//! - **mesh**: the tile's mesh, one vertex per sample of the surface, must have at most
//!   [`super::mesh::MAX_MESH_SAMPLES`] vertices.
//!
//! Upper bounds (the detail must stay small enough):
//! - **viewing**: one period (its longer side) must subtend at most `max_period_arcmin` at the
//!   viewing distance `D`: `period <= D · tan(max_period_arcmin / 60 °)`. With the shipped 1
//!   arc minute (the eye's acuity) and `D` = 2 m that is 0.58 mm. A flat detail has no period
//!   to see and no such bound.
//! - **reach**: the relief must not exceed the tool's flute length (mills) or the build height
//!   minus the base (printers), and base + relief must fit the mill's z travel.
//! - **tile**: the tile must hold at least one whole period (a flat detail has none).
//!
//! The size picked is the geometric mean of the bounds (equal ratio margin to both), or the
//! lower bound when there is no upper bound (a flat detail). An empty interval rejects the detail with a
//! reason naming both binding bounds.

use super::catalogue::Machine;
use super::features::FeatureWidths;
use super::mesh::MAX_MESH_SAMPLES;
use super::millability::simulate;
use super::profile::Profile;
use crate::error::Result;
use crate::heightfield::Heightfield;

/// One bound of the window.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Bound {
    /// "process", "features", "mesh", "viewing", "tile", "reach" or "machine_z".
    pub name: String,
    pub patch_mm: f64,
    pub why: String,
}

/// The allowed interval of patch sizes and the size picked inside it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ScaleWindow {
    pub lower: Vec<Bound>,
    pub upper: Vec<Bound>,
    /// The binding bounds: the largest lower bound (0 if none) and the smallest upper bound.
    pub lo_mm: f64,
    pub hi_mm: f64,
    /// The patch size picked (none when the window is empty).
    pub chosen_mm: Option<f64>,
    pub rejection: Option<String>,
}

fn relative_ok(hf: &Heightfield, s: f64, profile: &Profile, relief_g: f64) -> Result<bool> {
    let sim = simulate(hf, s, profile)?;
    let relief = relief_g * s / hf.width() as f64;
    Ok(sim.report.max_deviation_mm <= profile.max_deviation_frac * relief)
}

/// The process diameter: tool (or the mill's step when larger), SLA pixel or FDM nozzle (mm).
pub fn process_diameter_mm(profile: &Profile) -> f64 {
    match (&profile.machine, &profile.tool) {
        (Machine::Sla(s), _) => s.xy_resolution_mm,
        (Machine::Fdm(f), _) => f.nozzle_mm,
        // A mill cannot place a feature finer than its smallest step, whatever the tool.
        (Machine::Mill(m), Some(t)) => t.diameter_mm.max(m.resolution_mm),
        (Machine::Mill(_), None) => 0.0,
    }
}

fn process_bound(hf: &Heightfield, profile: &Profile, relief_g: f64) -> Result<Option<Bound>> {
    if relief_g <= 0.0 {
        return Ok(None);
    }
    let d = process_diameter_mm(profile);
    let floor = 2.0 * d;
    let mut hi = floor.max(hf.width() as f64 * d);
    let mut doublings = 0;
    while !relative_ok(hf, hi, profile, relief_g)? {
        hi *= 2.0;
        doublings += 1;
        if doublings > 12 {
            return Ok(Some(Bound {
                name: "process".into(),
                patch_mm: f64::INFINITY,
                why: format!(
                    "the made surface stays more than {} of the relief from the design at every size up to {hi:.0} mm",
                    profile.max_deviation_frac
                ),
            }));
        }
    }
    let mut lo = hi / 2.0;
    loop {
        if lo <= floor {
            lo = floor;
            if relative_ok(hf, lo, profile, relief_g)? {
                return Ok(Some(Bound {
                    name: "process".into(),
                    patch_mm: floor,
                    why: format!("a patch must be at least twice the {d} mm process diameter"),
                }));
            }
            break;
        }
        if !relative_ok(hf, lo, profile, relief_g)? {
            break;
        }
        hi = lo;
        lo /= 2.0;
    }
    while hi / lo > 1.02 {
        let mid = (lo * hi).sqrt();
        if relative_ok(hf, mid, profile, relief_g)? {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    Ok(Some(Bound {
        name: "process".into(),
        patch_mm: hi,
        why: format!(
            "below it the made surface ({} mm tool/resolution) deviates more than {} of the relief",
            d, profile.max_deviation_frac
        ),
    }))
}

/// The scale window of `hf` for `profile` viewed from `viewing_distance_mm`, exported as a
/// tile of `tile_mm`.
pub fn scale_window(
    hf: &Heightfield,
    profile: &Profile,
    features: &FeatureWidths,
    viewing_distance_mm: f64,
    tile_mm: (f64, f64),
) -> Result<ScaleWindow> {
    let w = hf.width() as f64;
    let (zlo, zhi) = hf.min_max();
    let relief_g = zhi - zlo;
    let mut lower = Vec::new();
    if let Some(b) = process_bound(hf, profile, relief_g)? {
        lower.push(b);
    }
    if let Some(m) = features.min_cells() {
        lower.push(Bound {
            name: "features".into(),
            patch_mm: profile.min_feature_mm * w / m,
            why: format!(
                "the narrowest feature is {m:.2} samples of {w}; it must be at least {} mm",
                profile.min_feature_mm
            ),
        });
    }
    // The tile's mesh has one vertex per sample of the surface (`patch / width` apart).
    let (tx, ty) = tile_mm;
    lower.push(Bound {
        name: "mesh".into(),
        patch_mm: w * (tx * ty / MAX_MESH_SAMPLES).sqrt() * (1.0 + 1e-3),
        why: format!(
            "the {} × {} mm tile's mesh must have at most {} million samples",
            crate::error::show_num(tx),
            crate::error::show_num(ty),
            MAX_MESH_SAMPLES / 1e6
        ),
    });
    let mut upper = Vec::new();
    // A tile that does not hold one whole period does not show the detail's large-scale look
    // (a flat detail has no period).
    if relief_g > 0.0 {
        upper.push(Bound {
            name: "tile".into(),
            patch_mm: tx.min(ty),
            why: format!(
                "the {} × {} mm tile must hold at least one period",
                crate::error::show_num(tx),
                crate::error::show_num(ty)
            ),
        });
    }
    let theta = (profile.max_period_arcmin / 60.0).to_radians();
    let side = hf.width().max(hf.height()) as f64;
    // A flat detail has no period to see.
    if relief_g > 0.0 {
        upper.push(Bound {
            name: "viewing".into(),
            patch_mm: viewing_distance_mm * theta.tan() * w / side,
            why: format!(
                "one period must subtend at most {} arc minute(s) at {viewing_distance_mm} mm",
                profile.max_period_arcmin
            ),
        });
    }
    if relief_g > 0.0 {
        let reach = match (&profile.machine, &profile.tool) {
            (Machine::Mill(_), Some(t)) => t.flute_length_mm,
            (m, _) => m.envelope_mm().2 - profile.base_thickness_mm,
        };
        upper.push(Bound {
            name: "reach".into(),
            patch_mm: reach.max(0.0) * w / relief_g,
            why: format!("the relief must not exceed the {reach} mm reach"),
        });
        if let Machine::Mill(m) = &profile.machine {
            let z = m.travel_z_mm - profile.base_thickness_mm;
            upper.push(Bound {
                name: "machine_z".into(),
                patch_mm: z.max(0.0) * w / relief_g,
                why: format!("base + relief must fit the {} mm z travel", m.travel_z_mm),
            });
        }
    }
    let lo_b = lower
        .iter()
        .max_by(|a, b| a.patch_mm.total_cmp(&b.patch_mm));
    let hi_b = upper
        .iter()
        .min_by(|a, b| a.patch_mm.total_cmp(&b.patch_mm));
    let lo_mm = lo_b.map(|b| b.patch_mm).unwrap_or(0.0);
    let hi_mm = hi_b.map(|b| b.patch_mm).unwrap_or(f64::INFINITY);
    let (chosen_mm, rejection) = if lo_mm <= hi_mm && hi_mm > 0.0 && lo_mm.is_finite() {
        let c = if lo_mm > 0.0 && hi_mm.is_finite() {
            (lo_mm * hi_mm).sqrt()
        } else if hi_mm.is_finite() {
            hi_mm
        } else {
            lo_mm
        };
        (Some(c), None)
    } else {
        let l = lo_b
            .map(|b| format!("{} ({})", fmt_mm(b.patch_mm), b.why))
            .unwrap_or_default();
        let h = hi_b
            .map(|b| format!("{} ({})", fmt_mm(b.patch_mm), b.why))
            .unwrap_or_default();
        (
            None,
            Some(format!(
                "no patch size fits: it must be at least {l} and at most {h}"
            )),
        )
    };
    Ok(ScaleWindow {
        lower,
        upper,
        lo_mm,
        hi_mm,
        chosen_mm,
        rejection,
    })
}

fn fmt_mm(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.3} mm")
    } else {
        "unbounded".into()
    }
}
