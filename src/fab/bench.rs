//! `biscale`-style timing tables of the fabrication stage (Markdown, like `crate::bench`): the
//! milling simulation of a 128² detail, the full [`super::check_detail`], and
//! [`super::export_detail`] of 50 × 50 mm tiles. Timings are printed, never asserted.

use super::export::{export_detail, Decimation};
use super::profile::Profile;
use super::{check_detail, millability, CheckOptions};
use crate::bench::try_time;
use crate::error::Result;
use crate::generators::parse_generator;
use std::path::PathBuf;

/// A scratch directory removed when dropped, so an early return (`?`) or a panic leaves nothing
/// behind either.
struct Scratch(PathBuf);

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Milling simulation and check of 128² generators with `profile` (a mill profile gives the
/// tool), then exports of 50 × 50 mm tiles.
pub fn bench_fab(profile: &Profile, reps: usize) -> Result<String> {
    let threads = rayon::current_num_threads();
    let mut out = format!(
        "Fabrication speed ({threads} threads, median of {reps}, profile {})\n\n\
         | geometry (128²) | patch | simulation grid | simulate | check_detail |\n|---|---|---|---|---|\n",
        profile.name
    );
    for spec in ["bumps", "vgroove", "fbm"] {
        let hf = parse_generator(spec)?.build()?;
        for patch in [10.0, 40.0] {
            let (ts, sim) = try_time(reps, || millability::simulate(&hf, patch, profile))?;
            let opts = CheckOptions {
                tile_mm: (50.0, 50.0),
                patch_mm: None,
                viewing_distance_mm: Some(1e6),
            };
            let (tc, _) = try_time(reps, || check_detail(&hf, profile, &opts))?;
            let side = 128 * sim.report.refine;
            out.push_str(&format!(
                "| {spec} | {patch} mm | {side}² | {:.1} ms | {:.0} ms |\n",
                ts * 1e3,
                tc * 1e3
            ));
        }
    }
    let dir =
        Scratch(std::env::temp_dir().join(format!("biscale-fab-bench-{}", std::process::id())));
    out.push_str(
        "\n| geometry (128²) | patch | tile samples | decimation | triangles (full → written) | max error | export |\n|---|---|---|---|---|---|---|\n",
    );
    for spec in ["bumps", "vgroove", "fbm"] {
        let hf = parse_generator(spec)?.build()?;
        for (patch, dec) in [
            (10.0, None),
            (10.0, Some(Decimation::MaxErrorMm(0.01))),
            (10.0, Some(Decimation::TriangleBudget(30_000))),
            (5.0, None),
            (5.0, Some(Decimation::MaxErrorMm(0.01))),
        ] {
            let (t, r) = try_time(1, || {
                export_detail(&hf, profile, patch, (50.0, 50.0), &dir.0, "bench", dec)
            })?;
            out.push_str(&format!(
                "| {spec} | {patch} mm | {}² | {} | {} → {} | {:.4} mm | {:.2} s |\n",
                (r.tile_x_mm / r.sample_mm).round() as usize + 1,
                match dec {
                    None => "none".to_string(),
                    Some(Decimation::MaxErrorMm(e)) => format!("≤ {e} mm"),
                    Some(Decimation::TriangleBudget(n)) => format!("≤ {n} triangles"),
                    Some(Decimation::Both {
                        max_error_mm,
                        budget,
                    }) => format!("≤ {max_error_mm} mm, ≤ {budget} triangles"),
                },
                r.triangles_full,
                r.triangles,
                r.max_height_error_mm,
                t
            ));
        }
    }
    Ok(out)
}
