//! What the machine makes of a heightfield at a physical size, and how far that is from the design.
//!
//! **Mills (3-axis).** The cutter is dropped onto the surface at every sample position (periodic);
//! the surface left is the lower envelope of all tool positions, i.e. the morphological closing
//! of the height function by the tool's tip: a ball of radius `d/2` for a ball-nose cutter, a
//! flat disc of diameter `d` for a flat-end cutter (valleys narrower than the tool fill up; the
//! cylinder above the tip never touches a single-valued surface first). A heightfield has no
//! undercuts by construction; meshes with overhangs are rejected on import ([`super::obj`]).
//!
//! **Printers.** XY: opening then closing by a flat disc whose diameter is the printer's XY
//! resolution (SLA pixel) or nozzle width (FDM): ridges and valleys narrower than that vanish.
//! Z: heights above the lowest point are rounded to whole layers.
//!
//! Both are computed on the triangulated surface sampled `k` times finer than the heightfield
//! (`k` from [`super::morph::refine_factor`]: spacing at most a sixteenth of the tool radius, or of
//! the printer's XY radius, with the refined side capped at [`MAX_SIDE`] samples); the surface a
//! drop cutter makes between samples is therefore resolved to about `(spacing)² / (2 r)`.
//! Deviation = made − design at every refined sample (for a mill always >= 0): its maximum and
//! its root mean square, in mm.

use super::catalogue::{Machine, Tool, ToolKind};
use super::morph::{self, Grid};
use super::profile::Profile;
use crate::error::Result;
use crate::heightfield::Heightfield;

/// Longest side of the refined grid the simulations use.
pub const MAX_SIDE: usize = 512;

/// The made surface and its deviation from the design.
#[derive(Debug, Clone, serde::Serialize)]
pub struct MillReport {
    /// "mill", "sla" or "fdm".
    pub process: String,
    pub patch_mm: f64,
    /// Spacing of the samples the simulation used (mm) and the refinement factor.
    pub sample_mm: f64,
    pub refine: usize,
    /// Largest |made − design| (mm).
    pub max_deviation_mm: f64,
    /// Root mean square of made − design over the period (mm).
    pub rms_deviation_mm: f64,
    /// Peak-to-valley height of the design (mm).
    pub relief_mm: f64,
    /// The deepest relief the process reaches: the tool's flute length (mills) or the build
    /// height minus the base (printers), in mm.
    pub reach_mm: f64,
    /// Cusp height between finishing passes of a ball-nose at the profile's stepover,
    /// `r − sqrt(r² − (s/2)²)`; reported separately, not in the deviation (mills only).
    pub scallop_mm: Option<f64>,
}

/// A simulation result: the report, and the made surface on the heightfield's own grid (for the
/// appearance of the manufactured surface) and on the refined grid (for costs).
#[derive(Debug, Clone)]
pub struct Simulated {
    pub report: MillReport,
    /// The made surface at the heightfield's resolution, heights in grid units, `cell_mm` set.
    pub made: Heightfield,
    /// The made surface on the refined grid, heights in mm.
    pub made_fine: Grid,
}

fn deviation(design: &[f64], made: &[f64]) -> (f64, f64) {
    let n = design.len().max(1) as f64;
    let (mut mx, mut ss) = (0.0f64, 0.0f64);
    for (d, m) in design.iter().zip(made) {
        let e = m - d;
        mx = mx.max(e.abs());
        ss += e * e;
    }
    (mx, (ss / n).sqrt())
}

#[allow(clippy::too_many_arguments)]
fn finish(
    hf: &Heightfield,
    design: &Grid,
    made: Vec<f64>,
    k: usize,
    process: &str,
    patch_mm: f64,
    reach_mm: f64,
    scallop_mm: Option<f64>,
) -> Result<Simulated> {
    let (max_d, rms_d) = deviation(&design.z, &made);
    let (lo, hi) = design.min_max();
    let made_fine = design.with_z(made);
    let made = made_fine.subsample(k, &format!("{} (made by {process})", hf.name))?;
    Ok(Simulated {
        report: MillReport {
            process: process.to_string(),
            patch_mm,
            sample_mm: design.cell_mm,
            refine: k,
            max_deviation_mm: max_d,
            rms_deviation_mm: rms_d,
            relief_mm: hi - lo,
            reach_mm,
            scallop_mm,
        },
        made,
        made_fine,
    })
}

/// Heights `v` in whole steps of `step` mm above `lo`, each to the nearest step: a printer's
/// layers.
fn in_steps(v: &[f64], lo: f64, step: f64) -> Vec<f64> {
    v.iter()
        .map(|v| lo + ((v - lo) / step).round() * step)
        .collect()
}

/// Tool-centre heights `v` raised to whole steps of `step` mm above `lo`: a mill whose z moves
/// in steps stops at the first step that does not cut into the design.
fn up_to_steps(v: &[f64], lo: f64, step: f64) -> Vec<f64> {
    v.iter()
        .map(|v| lo + ((v - lo) / step - 1e-9).ceil() * step)
        .collect()
}

/// The surface a cutter leaves on `hf` at patch size `patch_mm` (z positioned exactly).
pub fn mill(
    hf: &Heightfield,
    patch_mm: f64,
    tool: &Tool,
    stepover_mm: Option<f64>,
) -> Result<Simulated> {
    mill_in_steps(hf, patch_mm, tool, stepover_mm, None)
}

/// [`mill`] on a machine whose z moves in steps of `resolution_mm` (the catalogue's
/// `resolution_mm`): the tool's heights at every position (the dilation of the design by the
/// tool) are raised to whole steps above the design's lowest point before the surface the tool
/// leaves (the erosion) is taken, so the part is never cut below the design.
pub fn mill_in_steps(
    hf: &Heightfield,
    patch_mm: f64,
    tool: &Tool,
    stepover_mm: Option<f64>,
    resolution_mm: Option<f64>,
) -> Result<Simulated> {
    let r = 0.5 * tool.diameter_mm;
    let k = morph::refine_factor(hf, patch_mm, r, MAX_SIDE);
    let g = Grid::from_heightfield(hf, patch_mm, k);
    let steps = |c: Vec<f64>| match resolution_mm {
        Some(step) if step > 0.0 => up_to_steps(&c, g.min_max().0, step),
        _ => c,
    };
    let made = match tool.kind {
        ToolKind::Ball => morph::ball_erode(&g, &steps(morph::ball_dilate(&g, &g.z, r)), r),
        ToolKind::Flat => {
            let rc = r / g.cell_mm;
            let centres = steps(morph::flat_dilate_cells(g.w, g.h, &g.z, rc));
            morph::flat_erode_cells(g.w, g.h, &centres, rc)
        }
    };
    let scallop = match (tool.kind, stepover_mm) {
        (ToolKind::Ball, Some(s)) => {
            let half = (0.5 * s).min(r);
            Some(r - (r * r - half * half).sqrt())
        }
        (ToolKind::Flat, Some(_)) => Some(0.0),
        _ => None,
    };
    finish(
        hf,
        &g,
        made,
        k,
        "mill",
        patch_mm,
        tool.flute_length_mm,
        scallop,
    )
}

/// The surface a printer with XY resolution `xy_mm` and layer `layer_mm` makes of `hf`.
pub fn print(
    hf: &Heightfield,
    patch_mm: f64,
    xy_mm: f64,
    layer_mm: f64,
    process: &str,
    reach_mm: f64,
) -> Result<Simulated> {
    let r = 0.5 * xy_mm;
    let k = morph::refine_factor(hf, patch_mm, r, MAX_SIDE);
    let g = Grid::from_heightfield(hf, patch_mm, k);
    let rc = r / g.cell_mm;
    let xy = morph::flat_close_cells(g.w, g.h, &morph::flat_open_cells(g.w, g.h, &g.z, rc), rc);
    let made = in_steps(&xy, g.min_max().0, layer_mm);
    finish(hf, &g, made, k, process, patch_mm, reach_mm, None)
}

/// Simulate the profile's process on `hf` at patch size `patch_mm`.
pub fn simulate(hf: &Heightfield, patch_mm: f64, profile: &Profile) -> Result<Simulated> {
    let base = profile.base_thickness_mm;
    match (&profile.machine, &profile.tool) {
        (Machine::Mill(m), Some(t)) => {
            mill_in_steps(hf, patch_mm, t, profile.stepover_mm, Some(m.resolution_mm))
        }
        (Machine::Mill(_), None) => Err(crate::error::Error::new(
            profile.name.clone(),
            "a mill profile needs a tool",
        )),
        (Machine::Sla(s), _) => print(
            hf,
            patch_mm,
            s.xy_resolution_mm,
            s.z_resolution_mm,
            "sla",
            s.build_z_mm - base,
        ),
        (Machine::Fdm(f), _) => print(
            hf,
            patch_mm,
            f.nozzle_mm,
            f.layer_mm,
            "fdm",
            f.build_z_mm - base,
        ),
    }
}
