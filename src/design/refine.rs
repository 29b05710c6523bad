//! Continuous refinement of a chosen detail with NLopt (COBYLA): the library is discrete, so the
//! best detail's relief amplitude and rotation are tuned continuously, with the fabrication
//! profile's limits as nonlinear inequality constraints, and the appearance of the *milled*
//! surface as the objective.
//!
//! Variables: `scale` (multiplies the heights, 0.5–1.5) and the rotation `psi` (±45° around the
//! solver's). Constraints (each `≤ 0`): milled-vs-design deviation minus `max_deviation_frac` ×
//! relief, and relief minus the tool's reach. The patch size stays the one the scale window chose.
//! Each evaluation simulates the tool and builds a quick compact BVNDF of the milled surface; the
//! error before and after are both measured that way, and the refined detail is kept only if it
//! is better.

use super::Appraiser;
use crate::error::Result;
use crate::fab::{millability::simulate, Profile};
use crate::heightfield::Heightfield;
use crate::prefilter::Prefiltered;
use crate::solve::{Look, SolveOptions};
use nlopt::{Algorithm, Nlopt, Target};
use serde::Serialize;
use std::cell::Cell;

/// What refinement did to one detail.
#[derive(Debug, Clone, Serialize)]
pub struct Refined {
    pub scale: f64,
    pub psi_deg: f64,
    /// Appearance error of the milled surface (quick BVNDF) before and after.
    pub error_before: f64,
    pub error_after: f64,
    pub evaluations: usize,
    /// Whether the refined detail replaced the original (it must be feasible and better).
    pub accepted: bool,
    pub status: String,
}

/// Refine `hf` (milled at `patch_mm` with `profile`) seen with `pf` against `look`.
#[allow(clippy::too_many_arguments)]
pub fn refine(
    look: &Look,
    hf: &Heightfield,
    pf: &Prefiltered,
    psi0_deg: f64,
    patch_mm: f64,
    profile: &Profile,
    opt: &SolveOptions,
    eye: &Appraiser,
    max_evals: u32,
) -> Result<Refined> {
    let reach = profile
        .tool
        .as_ref()
        .map(|t| t.flute_length_mm)
        .unwrap_or(f64::INFINITY);
    // A quarter of the rays inside the loop: the error is measured again at full rays when the
    // refined detail is accepted.
    let quick = Appraiser {
        rays: (eye.rays / 4).max(1),
        clusters: eye.clusters,
        layout: eye.layout.clone(),
    };
    let error_at = |x: &[f64]| -> f64 {
        match simulate(&hf.scaled(x[0]), patch_mm, profile) {
            Ok(sim) => {
                let e = quick.error(look, &sim.made, pf, x[1], opt);
                if e.is_finite() {
                    e
                } else {
                    1e3
                }
            }
            Err(_) => 1e3,
        }
    };
    let evals = Cell::new(0usize);
    let objective = |x: &[f64], _g: Option<&mut [f64]>, _: &mut ()| -> f64 {
        evals.set(evals.get() + 1);
        error_at(x)
    };
    let deviation = |x: &[f64], _g: Option<&mut [f64]>, _: &mut ()| -> f64 {
        match simulate(&hf.scaled(x[0]), patch_mm, profile) {
            Ok(s) => s.report.max_deviation_mm - profile.max_deviation_frac * s.report.relief_mm,
            Err(_) => 1e3,
        }
    };
    let relief = |x: &[f64], _g: Option<&mut [f64]>, _: &mut ()| -> f64 {
        let (lo, hi) = hf.min_max();
        (hi - lo) * x[0] * patch_mm / hf.width() as f64 - reach.min(1e9)
    };
    let x0 = [1.0, psi0_deg];
    let before = error_at(&x0);
    let mut opt_ = Nlopt::new(Algorithm::Cobyla, 2, objective, Target::Minimize, ());
    let mut status = String::new();
    let setup = [
        opt_.set_lower_bounds(&[0.5, psi0_deg - 45.0]),
        opt_.set_upper_bounds(&[1.5, psi0_deg + 45.0]),
        opt_.add_inequality_constraint(deviation, (), 1e-4),
        opt_.add_inequality_constraint(relief, (), 1e-4),
        opt_.set_maxeval(max_evals.max(2)),
        opt_.set_xtol_rel(1e-3),
        opt_.set_initial_step(&[0.15, 15.0]),
    ];
    if let Some(e) = setup.iter().find(|r| r.is_err()) {
        status = format!("setup failed: {e:?}");
    }
    let mut x = x0;
    let result = if status.is_empty() {
        Some(opt_.optimize(&mut x))
    } else {
        None
    };
    if let Some(r) = &result {
        status = match r {
            Ok((s, _)) => format!("{s:?}"),
            Err((f, _)) => format!("{f:?}"),
        };
    }
    let after = error_at(&x);
    let feasible = deviation(&x, None, &mut ()) <= 1e-4 && relief(&x, None, &mut ()) <= 1e-4;
    let accepted = feasible && after < before;
    Ok(Refined {
        scale: if accepted { x[0] } else { 1.0 },
        psi_deg: if accepted { x[1] } else { psi0_deg },
        error_before: before,
        error_after: if accepted { after } else { before },
        evaluations: evals.get(),
        accepted,
        status,
    })
}
