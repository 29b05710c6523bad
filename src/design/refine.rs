//! Continuous refinement of a chosen detail with NLopt (COBYLA): the library is discrete, so the
//! best detail is tuned continuously — its relief amplitude, its rotation, the continuous shape
//! parameters of its procedural generator, and the analytic parameters of its material when the
//! scene leaves the material free — with the fabrication profile's limits as nonlinear inequality
//! constraints, and the appearance of the *milled* surface as the objective.
//!
//! Variables, in order:
//! - `scale` (multiplies the heights, 0.5–1.5; held at 1 when the scene fixes the geometry);
//! - the rotation `psi` (±45° around the solver's);
//! - one factor (0.6–1.6) per shape parameter of the generator
//!   ([`crate::generators::Generator::shape_params`]: periods, widths, radii, … — not counts or
//!   seeds, and not the amplitude key, which `scale` covers);
//! - one factor (0.5–2) per numeric parameter of the material
//!   ([`crate::material::spec_params`]: roughness, exponent, `f0`, Lambertian albedo, …; fractions
//!   are clamped to 1).
//!
//! Constraints (each `≤ 0`): milled-vs-design deviation minus `max_deviation_frac` × relief, and
//! relief minus the tool's reach. The patch size stays the one the scale window chose. Each
//! evaluation builds the geometry, simulates the tool and builds the milled surface's light lobes
//! at a quarter of the rays (and, when a material parameter moved, the material's prefiltered
//! table); the error before and after are both measured that way, and the refined detail is kept
//! only if it is feasible and better.

use super::Appraiser;
use crate::error::Result;
use crate::fab::{millability::simulate, Profile};
use crate::generators::Generator;
use crate::heightfield::Heightfield;
use crate::material::{param_scaled, parse_material, round_sig4, spec_params, spec_scaled};
use crate::prefilter::{PrefilterConfig, Prefiltered};
use crate::solve::{Look, SolveOptions};
use nlopt::{Algorithm, Nlopt, Target};
use serde::Serialize;
use std::cell::{Cell, RefCell};

/// Objective value of a point that cannot be built or simulated.
const PENALTY: f64 = 1e3;

/// What is refined: the detail as the solver and the fabrication stage left it.
pub struct Subject<'a> {
    /// The designed heightfield (grid units).
    pub hf: &'a Heightfield,
    /// Its procedural generator, when it has one and the scene does not fix the geometry: its
    /// shape parameters are refined too.
    pub generator: Option<Generator>,
    /// The material's spec, when the scene leaves the material free: its analytic parameters
    /// are refined too.
    pub material: Option<String>,
    /// The material's prefiltered table as it stands.
    pub pf: &'a Prefiltered,
    /// The prefilter settings for a changed material (the library's).
    pub prefilter: PrefilterConfig,
    pub psi0_deg: f64,
    /// The scene fixes the geometry: its relief is kept (`scale` stays 1); only the rotation
    /// and a free material move.
    pub relief_fixed: bool,
}

/// One refined parameter: its name (`scale`, `psi_deg`, a generator key, or `material.KEY`
/// with the term's index for sums), its value before and after.
#[derive(Debug, Clone, Serialize)]
pub struct Change {
    pub name: String,
    pub before: f64,
    pub after: f64,
}

/// What refinement did to one detail.
#[derive(Debug, Clone, Serialize)]
pub struct Refined {
    pub scale: f64,
    pub psi_deg: f64,
    /// The refined generator's spec (before the relief `scale`), when a shape parameter was
    /// refined and accepted.
    pub geometry_spec: Option<String>,
    /// The refined material's spec, when a material parameter was refined and accepted.
    pub material_spec: Option<String>,
    /// Every variable, before and after (after = before when not accepted).
    pub changes: Vec<Change>,
    /// Appearance error of the milled surface (quick light lobes) before and after.
    pub error_before: f64,
    pub error_after: f64,
    pub evaluations: usize,
    /// The evaluation budget: the scene's `refine_evaluations`, or one more than the variables
    /// when that is larger (COBYLA needs as many to start).
    pub max_evaluations: u32,
    /// Whether the refined detail replaced the original (it must be feasible and better).
    pub accepted: bool,
    pub status: String,
}

/// The generator with its shape parameters multiplied by `x[2..2 + shape.len()]`.
fn generator_at(g: &Generator, shape: &[(&'static str, f64)], x: &[f64]) -> Result<Generator> {
    let mut g = g.clone();
    for (i, (k, v)) in shape.iter().enumerate() {
        g = g.with_param(k, &format!("{}", round_sig4(v * x[2 + i])))?;
    }
    Ok(g)
}

/// The geometry at `x` (before the relief scale): the refined generator's, or the subject's
/// heightfield when it has no shape parameters.
fn shape_at(s: &Subject, shape: &[(&'static str, f64)], x: &[f64]) -> Result<Heightfield> {
    match &s.generator {
        Some(g) if !shape.is_empty() => generator_at(g, shape, x)?.build(),
        _ => Ok(s.hf.clone()),
    }
}

/// Refine `subject` (milled at `patch_mm` with `profile`) against `look`.
#[allow(clippy::too_many_arguments)]
pub fn refine(
    look: &Look,
    subject: &Subject,
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
    let shape: Vec<(&'static str, f64)> = match &subject.generator {
        Some(g) => g.shape_params(),
        None => Vec::new(),
    };
    let mat_params = match &subject.material {
        Some(m) => spec_params(m),
        None => Vec::new(),
    };
    let (ns, nm) = (shape.len(), mat_params.len());
    let n = 2 + ns + nm;
    // The material's table at `x`, rebuilt only when its parameters moved.
    let cache: RefCell<Option<(String, Prefiltered)>> = RefCell::new(None);
    let with_pf = |x: &[f64], f: &dyn Fn(&Prefiltered) -> f64| -> f64 {
        let Some(m) = &subject.material else {
            return f(subject.pf);
        };
        if nm == 0 || x[2 + ns..].iter().all(|v| *v == 1.0) {
            return f(subject.pf);
        }
        let spec = spec_scaled(m, &x[2 + ns..]);
        if cache.borrow().as_ref().is_none_or(|(s, _)| *s != spec) {
            let Ok(mat) = parse_material(&spec) else {
                return PENALTY;
            };
            *cache.borrow_mut() = Some((spec, Prefiltered::build(&mat, &subject.prefilter)));
        }
        match cache.borrow().as_ref() {
            Some((_, pf)) => f(pf),
            None => PENALTY,
        }
    };
    let error_at = |x: &[f64]| -> f64 {
        let Ok(hf) = shape_at(subject, &shape, x) else {
            return PENALTY;
        };
        match simulate(&hf.scaled(x[0]), patch_mm, profile) {
            Ok(sim) => with_pf(x, &|pf| {
                let e = quick.error(look, &sim.made, pf, x[1], opt);
                if e.is_finite() {
                    e
                } else {
                    PENALTY
                }
            }),
            Err(_) => PENALTY,
        }
    };
    let evals = Cell::new(0usize);
    let objective = |x: &[f64], _g: Option<&mut [f64]>, _: &mut ()| -> f64 {
        evals.set(evals.get() + 1);
        error_at(x)
    };
    let deviation = |x: &[f64], _g: Option<&mut [f64]>, _: &mut ()| -> f64 {
        let Ok(hf) = shape_at(subject, &shape, x) else {
            return PENALTY;
        };
        match simulate(&hf.scaled(x[0]), patch_mm, profile) {
            Ok(s) => s.report.max_deviation_mm - profile.max_deviation_frac * s.report.relief_mm,
            Err(_) => PENALTY,
        }
    };
    let relief = |x: &[f64], _g: Option<&mut [f64]>, _: &mut ()| -> f64 {
        let Ok(hf) = shape_at(subject, &shape, x) else {
            return PENALTY;
        };
        let (lo, hi) = hf.min_max();
        (hi - lo) * x[0] * patch_mm / hf.width() as f64 - reach.min(1e9)
    };
    let psi0 = subject.psi0_deg;
    let mut x0 = vec![1.0; n];
    x0[1] = psi0;
    let (mut lo, mut hi, mut step) = (vec![0.5; n], vec![1.5; n], vec![0.15; n]);
    (lo[1], hi[1], step[1]) = (psi0 - 45.0, psi0 + 45.0, 15.0);
    if subject.relief_fixed {
        // NLopt fixes a variable whose bounds are equal.
        (lo[0], hi[0]) = (1.0, 1.0);
    }
    for i in 2..2 + ns {
        (lo[i], hi[i]) = (0.6, 1.6);
    }
    for i in 2 + ns..n {
        (lo[i], hi[i], step[i]) = (0.5, 2.0, 0.2);
    }
    let max_evaluations = max_evals.max(n as u32 + 1);
    let before = error_at(&x0);
    let mut opt_ = Nlopt::new(Algorithm::Cobyla, n, objective, Target::Minimize, ());
    let mut status = String::new();
    let setup = [
        opt_.set_lower_bounds(&lo),
        opt_.set_upper_bounds(&hi),
        opt_.add_inequality_constraint(deviation, (), 1e-4),
        opt_.add_inequality_constraint(relief, (), 1e-4),
        opt_.set_maxeval(max_evaluations),
        opt_.set_xtol_rel(1e-3),
        opt_.set_initial_step(&step),
    ];
    if let Some(e) = setup.iter().find(|r| r.is_err()) {
        status = format!("setup failed: {e:?}");
    }
    let mut x = x0.clone();
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
    if !accepted {
        x = x0.clone();
    }
    let mut changes = vec![
        Change {
            name: "scale".into(),
            before: 1.0,
            after: x[0],
        },
        Change {
            name: "psi_deg".into(),
            before: psi0,
            after: x[1],
        },
    ];
    for (i, (k, v)) in shape.iter().enumerate() {
        changes.push(Change {
            name: k.to_string(),
            before: *v,
            after: round_sig4(v * x[2 + i]),
        });
    }
    for (i, (t, k, v)) in mat_params.iter().enumerate() {
        changes.push(Change {
            name: format!("material.{t}.{k}"),
            before: *v,
            after: param_scaled(k, *v, x[2 + ns + i]),
        });
    }
    let moved = |r: std::ops::Range<usize>| x[r].iter().any(|v| *v != 1.0);
    let geometry_spec = match &subject.generator {
        Some(g) if accepted && moved(2..2 + ns) => Some(generator_at(g, &shape, &x)?.name()),
        _ => None,
    };
    let material_spec = match &subject.material {
        Some(m) if accepted && moved(2 + ns..n) => Some(spec_scaled(m, &x[2 + ns..])),
        _ => None,
    };
    Ok(Refined {
        scale: x[0],
        psi_deg: x[1],
        geometry_spec,
        material_spec,
        changes,
        error_before: before,
        error_after: if accepted { after } else { before },
        evaluations: evals.get(),
        max_evaluations,
        accepted,
        status,
    })
}
