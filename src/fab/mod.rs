//! Fabrication: constraint profiles, the physical scale window, millability (and printability),
//! minimum feature size, cost, and export of watertight STL / PNG heightmaps.
//!
//! The two entry points the command line calls are [`check_detail`] (is this detail makeable
//! with this profile, at what size, how far from the design, at what cost) and
//! [`export::export_detail`] (write the tile's STL, PNG heightmap and PNG scale). Profiles load
//! with [`profile::load_profile`]. See `docs/fabrication.md` for the user-facing description.

pub mod bench;
pub mod catalogue;
pub mod cost;
pub mod decimate;
pub mod export;
pub mod features;
pub mod mesh;
pub mod millability;
pub mod morph;
pub mod obj;
pub mod profile;
pub mod scale;

pub use catalogue::{Catalogue, Machine, StockMaterial, Tool, ToolKind};
pub use cost::CostReport;
pub use export::{export_detail, Decimation, ExportReport};
pub use features::FeatureReport;
pub use millability::MillReport;
pub use obj::import_obj;
pub use profile::{load_profile, FabPaths, Profile};
pub use scale::ScaleWindow;

use crate::error::{Error, Result};
use crate::heightfield::Heightfield;

/// What [`check_detail`] needs besides the detail and the profile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CheckOptions {
    /// Tile to make (x, y), mm: for costs and the machine envelope.
    pub tile_mm: (f64, f64),
    /// Use this patch size instead of picking one in the scale window.
    pub patch_mm: Option<f64>,
    /// Overrides the profile's `viewing_distance_mm` (a scene's value).
    pub viewing_distance_mm: Option<f64>,
}

/// One reason a detail cannot be made as asked.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Rejection {
    /// A short code to count rejections by: `scale_window`, `patch_outside_window`, `deviation`,
    /// `feature_size`, `reach`, `machine_z`, `envelope`.
    pub code: String,
    pub message: String,
}

/// Everything the fabrication check found for one detail and profile.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FabReport {
    pub detail: String,
    pub profile: String,
    pub feasible: bool,
    pub rejections: Vec<Rejection>,
    pub window: ScaleWindow,
    /// The patch size everything below is computed at, mm.
    pub patch_mm: f64,
    pub millability: MillReport,
    pub features: FeatureReport,
    pub cost: CostReport,
    /// The manufactured surface on the detail's grid (grid units, `cell_mm` = patch / width): rank
    /// its appearance, not the design's.
    #[serde(skip)]
    pub made: Heightfield,
}

fn reject(v: &mut Vec<Rejection>, code: &str, message: String) {
    v.push(Rejection {
        code: code.into(),
        message,
    });
}

/// Whether a `tile_mm` tile can be made with `profile` at all, whatever the detail: it fits the
/// machine's x-y envelope and, on a mill, the base leaves z travel for a relief. Checked before
/// a search ([`check_detail`] checks each detail's own height).
pub fn check_tile(profile: &Profile, tile_mm: [f64; 2]) -> Result<()> {
    use crate::error::show_num;
    let (ex, ey, ez) = profile.machine.envelope_mm();
    let small = tile_mm[0].min(tile_mm[1]);
    if small < profile.min_feature_mm {
        return Err(Error::new(
            "tile_mm",
            format!(
                "{} × {} mm is smaller than the smallest feature profile '{}' makes ({} mm); \
                 make the tile larger",
                show_num(tile_mm[0]),
                show_num(tile_mm[1]),
                profile.name,
                show_num(profile.min_feature_mm)
            ),
        ));
    }
    if tile_mm[0] > ex || tile_mm[1] > ey {
        return Err(Error::new(
            "tile_mm",
            format!(
                "{} × {} mm does not fit machine '{}' ({} × {} mm); make the tile smaller or \
                 choose another profile",
                show_num(tile_mm[0]),
                show_num(tile_mm[1]),
                profile.machine_name,
                show_num(ex),
                show_num(ey)
            ),
        ));
    }
    if matches!(profile.machine, Machine::Mill(_)) && profile.base_thickness_mm >= ez {
        return Err(Error::new(
            profile.name.clone(),
            format!(
                "base_thickness_mm = {} leaves no z travel for a relief on machine '{}' ({} mm)",
                show_num(profile.base_thickness_mm),
                profile.machine_name,
                show_num(ez)
            ),
        ));
    }
    Ok(())
}

/// Check `hf` against `profile`: scale window → made surface and its deviation → feature sizes
/// → cost of one tile. Infeasible details are not errors: they come back with `feasible = false`
/// and one [`Rejection`] per reason. Errors are for bad options only.
pub fn check_detail(hf: &Heightfield, profile: &Profile, opts: &CheckOptions) -> Result<FabReport> {
    let (tx, ty) = opts.tile_mm;
    for (v, what) in [(tx, "tile x"), (ty, "tile y")] {
        if !(v.is_finite() && v > 0.0) {
            return Err(Error::new(
                what,
                format!("must be a positive number of mm, got {v}"),
            ));
        }
    }
    let distance = opts
        .viewing_distance_mm
        .unwrap_or(profile.viewing_distance_mm);
    if !(distance.is_finite() && distance > 0.0) {
        return Err(Error::new(
            "viewing distance",
            format!("must be a positive number of mm, got {distance}"),
        ));
    }
    let feats = features::measure(hf, profile.max_deviation_frac);
    let window = scale::scale_window(hf, profile, &feats, distance, (tx, ty))?;
    let mut rej = Vec::new();
    if let Some(r) = &window.rejection {
        reject(&mut rej, "scale_window", r.clone());
    }
    let patch_mm = match opts.patch_mm {
        Some(p) => {
            if !(p.is_finite() && p > 0.0) {
                return Err(Error::new(
                    "patch size",
                    format!("must be a positive number of mm, got {p}"),
                ));
            }
            if window.rejection.is_none() && (p < window.lo_mm * 0.999 || p > window.hi_mm * 1.001)
            {
                reject(
                    &mut rej,
                    "patch_outside_window",
                    format!(
                        "patch {p} mm is outside the allowed {:.3}–{:.3} mm",
                        window.lo_mm, window.hi_mm
                    ),
                );
            }
            p
        }
        None => window
            .chosen_mm
            .unwrap_or(if window.lo_mm.is_finite() && window.lo_mm > 0.0 {
                window.lo_mm
            } else {
                window.hi_mm.max(1e-3)
            }),
    };
    let sim = millability::simulate(hf, patch_mm, profile)?;
    let m = &sim.report;
    if m.max_deviation_mm > profile.max_deviation_frac * m.relief_mm + 1e-12 {
        reject(
            &mut rej,
            "deviation",
            format!(
                "at a {patch_mm:.2} mm patch the made surface deviates up to {:.4} mm, more than {} of the {:.4} mm relief",
                m.max_deviation_mm, profile.max_deviation_frac, m.relief_mm
            ),
        );
    }
    if m.relief_mm > m.reach_mm {
        reject(
            &mut rej,
            "reach",
            format!(
                "at a {patch_mm:.2} mm patch the relief, {:.3} mm, exceeds the {:.3} mm reach",
                m.relief_mm, m.reach_mm
            ),
        );
    }
    let (ex, ey, ez) = profile.machine.envelope_mm();
    if let Machine::Mill(_) = profile.machine {
        if profile.base_thickness_mm + m.relief_mm > ez {
            reject(
                &mut rej,
                "machine_z",
                format!(
                    "part height {:.3} mm exceeds the {ez} mm z travel",
                    profile.base_thickness_mm + m.relief_mm
                ),
            );
        }
    }
    if tx > ex || ty > ey {
        reject(
            &mut rej,
            "envelope",
            format!("tile {tx} × {ty} mm exceeds the machine's {ex} × {ey} mm"),
        );
    }
    let features = feats.at_patch(hf.width(), patch_mm);
    if let Some(f) = features.min_feature_mm {
        if f < profile.min_feature_mm {
            reject(
                &mut rej,
                "feature_size",
                format!(
                    "narrowest feature {f:.3} mm is below the {} mm limit",
                    profile.min_feature_mm
                ),
            );
        }
    }
    // The cost of the tile made (whole samples, as the export makes it), not of the request.
    let cost = cost::tile_cost(
        profile,
        &sim.made_fine,
        mesh::made_tile_mm(hf, patch_mm, tx),
        mesh::made_tile_mm(hf, patch_mm, ty),
    );
    Ok(FabReport {
        detail: hf.name.clone(),
        profile: profile.name.clone(),
        feasible: rej.is_empty(),
        rejections: rej,
        window,
        patch_mm,
        millability: sim.report,
        features,
        cost,
        made: sim.made,
    })
}
