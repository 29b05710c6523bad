//! The physical scale window of a detail. BVNDFs are scale-free, so the patch size (the side of
//! one period along x, in mm) is free; fabrication and viewing bound it:
//!
//! Lower bounds (the detail must be large enough to be made):
//! - **process**: the smallest patch size at which the made surface
//!   ([`super::millability::simulate`]) stays within `max_deviation_frac` × relief of the design.
//!   Scaling a surface up by `s` is the same as shrinking the tool by `1/s`, and a closing by a
//!   smaller ball (disc) is never higher than by a larger one, so the relative deviation falls as
//!   the patch grows; the bound is bracketed by halving the patch, then narrowed to 2 % by a
//!   log–log secant guess and a probe beside it ([`Bracket::narrow`]), which keeps the bracket
//!   (refused below, admitted above) as bisection does in fewer simulations. The search never
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

/// The made surface's deviation at patch size `s` against the allowed one: `(max deviation,
/// max_deviation_frac × relief)`, both in mm; the size is admissible when the first is at most
/// the second.
fn deviation_at(hf: &Heightfield, s: f64, profile: &Profile, relief_g: f64) -> Result<(f64, f64)> {
    let sim = simulate(hf, s, profile)?;
    let relief = relief_g * s / hf.width() as f64;
    Ok((
        sim.report.max_deviation_mm,
        profile.max_deviation_frac * relief,
    ))
}

/// The process bound's search: the made surface's relative deviation `r(s)` (deviation over
/// the allowed one, [`deviation_at`]) at the two ends of a bracket, `lo` refused and `hi`
/// admitted, narrowed to a ratio of [`BRACKET`].
struct Bracket {
    lo: f64,
    hi: f64,
    r_lo: f64,
    r_hi: f64,
}

/// The process bound is found to this ratio of patch sizes (2 %).
const BRACKET: f64 = 1.02;

/// The relative deviation the search's guesses aim at ([`Bracket::narrow`]).
const AIM: f64 = 0.995;

impl Bracket {
    /// Narrow to [`BRACKET`]. The relative deviation falls about as a power of the patch size
    /// (a tool shrinking against the surface), so the size where it crosses 1 is first guessed
    /// on the line through the two ends in log–log (aiming at [`AIM`]), and the guess is
    /// followed by a probe 1.99 % to its other side, which closes the bracket when the guess was
    /// within 2 % (two simulations where halving the ratio of sizes each time takes five or
    /// six). Two such
    /// rounds at most; then the geometric midpoint. Either way the invariant holds (`lo`
    /// refused, `hi` admitted), so the bound is as exact as bisection's.
    fn narrow(mut self, mut admitted: impl FnMut(f64) -> Result<(bool, f64)>) -> Result<Self> {
        let mut guesses = 0;
        while self.hi / self.lo > BRACKET {
            let (llo, lhi) = (self.lo.ln(), self.hi.ln());
            let secant = guesses < 2
                && self.r_lo.is_finite()
                && self.r_lo > 1.0
                && self.r_hi > 0.0
                && self.r_hi <= 1.0;
            let mid = if secant {
                guesses += 1;
                // Aimed a little inside the admitted side (relative deviation 0.995), so that
                // the guess is usually admitted and becomes the bound, within about 0.5 % of the
                // crossing, and the probe below it closes the bracket.
                let (a, b) = (self.r_lo.ln(), self.r_hi.ln());
                let t = if a > b { (a - AIM.ln()) / (a - b) } else { 0.5 };
                // Strictly inside, so that every step narrows the bracket.
                (llo + t.clamp(0.02, 0.98) * (lhi - llo)).exp()
            } else {
                (self.lo * self.hi).sqrt()
            };
            let ok = self.step(mid, &mut admitted)?;
            if secant && self.hi / self.lo > BRACKET {
                let probe = if ok {
                    self.hi / (BRACKET - 1e-4)
                } else {
                    self.lo * (BRACKET - 1e-4)
                };
                if probe > self.lo && probe < self.hi {
                    self.step(probe, &mut admitted)?;
                }
            }
        }
        Ok(self)
    }

    fn step(
        &mut self,
        s: f64,
        admitted: &mut impl FnMut(f64) -> Result<(bool, f64)>,
    ) -> Result<bool> {
        let (ok, r) = admitted(s)?;
        if ok {
            (self.hi, self.r_hi) = (s, r);
        } else {
            (self.lo, self.r_lo) = (s, r);
        }
        Ok(ok)
    }
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
    // Whether size `s` is admitted, and its relative deviation (for the search's guesses).
    let admitted = |s: f64| -> Result<(bool, f64)> {
        let (dev, allowed) = deviation_at(hf, s, profile, relief_g)?;
        Ok((dev <= allowed, dev / allowed))
    };
    let mut hi = floor.max(hf.width() as f64 * d);
    let mut doublings = 0;
    let mut r_hi;
    loop {
        let (ok, r) = admitted(hi)?;
        r_hi = r;
        if ok {
            break;
        }
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
    let r_lo;
    loop {
        if lo <= floor {
            lo = floor;
            let (ok, r) = admitted(lo)?;
            if ok {
                return Ok(Some(Bound {
                    name: "process".into(),
                    patch_mm: floor,
                    why: format!("a patch must be at least twice the {d} mm process diameter"),
                }));
            }
            r_lo = r;
            break;
        }
        let (ok, r) = admitted(lo)?;
        if !ok {
            r_lo = r;
            break;
        }
        (hi, r_hi) = (lo, r);
        lo /= 2.0;
    }
    let b = Bracket { lo, hi, r_lo, r_hi }.narrow(admitted)?;
    Ok(Some(Bound {
        name: "process".into(),
        patch_mm: b.hi,
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
