//! The `biscale solve` job: resolve the target, open (or build) the library, run the solver the
//! fixed factors call for, and format the answer as a table or JSON. Only the library parts the
//! solver needs are read, and the log says which.

use super::general::GeneralOptions;
use super::look::{Edits, Look};
use super::{Candidate, SolveOptions, SolveResult};
use crate::error::{Error, Result};
use crate::library::progress::Progress;
use crate::library::Library;
use crate::material::parse_material;
use std::path::PathBuf;

#[derive(Debug, Clone)]
pub struct SolveJob {
    pub target: String,
    pub edits: Edits,
    pub colour: Option<[f64; 3]>,
    /// Make the target the look of a bi-scale combination: this geometry (a procedural spec or
    /// heightmap, read as `fix_geometry`) under the `target` material, by the fast forward model.
    pub target_geometry: Option<String>,
    /// Fix the material (any material spec); solve for the geometry.
    pub fix_material: Option<String>,
    /// Fix the geometry (a procedural spec or heightmap); solve for the material.
    pub fix_geometry: Option<String>,
    pub options: SolveOptions,
    pub general: GeneralOptions,
    /// Visually equivalent details: how many, and the error bound.
    pub veds: Option<(usize, f64)>,
    pub library: Option<PathBuf>,
    pub profile: String,
    pub cache_dir: Option<PathBuf>,
    pub json: bool,
    pub quiet: bool,
}

/// What a run fixes, read (and checked) before any library is opened: a material, a geometry,
/// or neither. `biscale solve` and `biscale design` both read it here and solve with it.
pub enum Fixed {
    /// The material and its spec: the geometry solver.
    Material(crate::material::Material, String),
    /// The geometry (a heightmap or OBJ file, or a procedural spec) and its spec: the material
    /// solver.
    Geometry(crate::heightfield::Heightfield, String),
    /// Neither: the general solver.
    Neither,
}

impl Fixed {
    /// Read a material spec or a geometry spec (with a heightmap's patch size and height
    /// scale); errors are placed within `labels.0` / `labels.1`.
    pub fn read(
        material: Option<&str>,
        geometry: Option<(&str, f64, f64)>,
        labels: (&str, &str),
    ) -> Result<Fixed> {
        match (material, geometry) {
            (Some(_), Some(_)) => Err(Error::new(
                format!("{} / {}", labels.0, labels.1),
                "fix at most one of them (fixing both leaves nothing to solve; use `biscale forward`)",
            )),
            (Some(m), None) => Ok(Fixed::Material(
                parse_material(m).map_err(|e| e.within(labels.0))?,
                m.to_string(),
            )),
            (None, Some((g, patch_mm, height_scale))) => Ok(Fixed::Geometry(
                crate::heightmap_io::resolve_geometry(g, patch_mm, height_scale)
                    .map_err(|e| e.within(labels.1))?,
                g.to_string(),
            )),
            (None, None) => Ok(Fixed::Neither),
        }
    }

    /// Run the solver this calls for; returns its name and its result.
    pub fn solve(
        &self,
        lib: &Library,
        look: &Look,
        opt: &SolveOptions,
        general: &GeneralOptions,
    ) -> Result<(&'static str, SolveResult)> {
        Ok(match self {
            Fixed::Material(mat, m) => (
                "geometry solver (material fixed)",
                super::geometry::solve(lib, look, mat, m, None, opt)?,
            ),
            Fixed::Geometry(hf, g) => (
                "material solver (geometry fixed)",
                super::material::solve(lib, look, hf, g, None, 0.0, opt)?,
            ),
            Fixed::Neither => (
                "general solver",
                super::general::solve(lib, look, opt, general)?,
            ),
        })
    }
}

/// The look of geometry `geometry` (a procedural spec or heightmap, 10 mm period, heights as
/// stored, as `--fix-geometry` reads it) under material `material`, by the fast forward model
/// with `biscale forward`'s default settings (the same values as `biscale forward --geometry G
/// --material M`), with a brightness edit; the other edits of Sec. 7 act on a BRDF target only.
pub fn combination_look(
    material: &str,
    geometry: &str,
    edits: Edits,
    colour: Option<[f64; 3]>,
    progress: &Progress,
) -> Result<Look> {
    if edits.contrast != 1.0 || edits.blur != [1.0, 1.0] {
        return Err(Error::new(
            "--contrast / --blur",
            "act on a BRDF target; with --target-geometry only --brightness and --colour apply",
        ));
    }
    let mat = parse_material(material)
        .map_err(|e| e.within("--target (with --target-geometry, a small-scale material)"))?;
    let hf = crate::heightmap_io::resolve_geometry(geometry, 10.0, 1.0)
        .map_err(|e| e.within("--target-geometry"))?;
    let t = std::time::Instant::now();
    let geo = crate::bvndf::CompactBvndf::build_with(
        &hf,
        &crate::bvndf::BvndfConfig::forward(),
        progress,
    );
    let pre = crate::prefilter::Prefiltered::build_split(
        &mat,
        &crate::prefilter::PrefilterConfig::default(),
        crate::fast::FACET_WIDTH,
    );
    progress.note(&format!(
        "solve: target {geometry} with {material} (fast forward model) built in {:.1} s",
        t.elapsed().as_secs_f64()
    ));
    let colour = colour.or_else(|| {
        Some(crate::library::items::average_colour(&mat).map(|c| c * edits.brightness))
    });
    Ok(Look::from_combination(
        &format!("{geometry} with {material}"),
        std::sync::Arc::new(geo),
        std::sync::Arc::new(pre),
        edits.brightness,
        colour,
    ))
}

/// Open the library a job names: a directory, or the cached build of a profile.
pub fn open_library(
    library: &Option<PathBuf>,
    profile: &str,
    cache: &Option<PathBuf>,
    progress: &Progress,
) -> Result<Library> {
    match library {
        Some(d) => Library::open(d),
        None => crate::library::ensure(profile, cache.as_deref(), progress),
    }
}

pub fn run(job: &SolveJob) -> Result<String> {
    let progress = Progress { quiet: job.quiet };
    // What is fixed is read before the target's model is built and the library is opened (or
    // built): bad input fails first.
    let fixed = Fixed::read(
        job.fix_material.as_deref(),
        job.fix_geometry.as_deref().map(|g| (g, 10.0, 1.0)),
        ("--fix-material", "--fix-geometry"),
    )?;
    let look = match &job.target_geometry {
        None => {
            Look::from_spec(&job.target, job.edits, job.colour).map_err(|e| e.within("--target"))?
        }
        Some(g) => combination_look(&job.target, g, job.edits, job.colour, &progress)?,
    };
    look.check_not_black().map_err(|e| e.within("--target"))?;
    let lib = open_library(&job.library, &job.profile, &job.cache_dir, &progress)?;
    // The final exact evaluation shows a bar here (the solvers' default is quiet).
    let options = SolveOptions {
        progress,
        ..job.options.clone()
    };
    let (mode, result) = match (&fixed, job.veds) {
        (Fixed::Neither, Some((n, bound))) => (
            "visually equivalent details",
            super::veds::solve(&lib, &look, &options, &job.general, n, bound, 0.98)?,
        ),
        _ => fixed.solve(&lib, &look, &options, &job.general)?,
    };
    progress.note(&format!(
        "solve: {mode}; library {} ('{}'); read: {}",
        lib.dir.display(),
        lib.manifest.profile,
        lib.reads().join(", ")
    ));
    let s = &result.stats;
    progress.note(&format!(
        "solve: search {:.3} s over {} items via {} representatives, re-rank {:.3} s, final {:.3} s",
        s.search_seconds, s.items_searched, s.representatives, s.rerank_seconds, s.final_seconds
    ));
    for n in &s.notes {
        progress.note(&format!("solve: {n}"));
    }
    if result.candidates.is_empty() {
        // Every combination's error was undefined (not finite): a failure, not an empty answer.
        return Err(Error::new(
            "--target",
            format!(
                "'{}': the {mode} found no combination with a finite error against this target \
                 (expected a target whose values are finite and of a reflectance's size)",
                look.name
            ),
        ));
    }
    if job.json {
        #[derive(serde::Serialize)]
        struct Out<'a> {
            target: &'a str,
            mode: &'a str,
            library: String,
            result: &'a SolveResult,
        }
        return serde_json::to_string_pretty(&Out {
            target: &look.name,
            mode,
            library: lib.dir.display().to_string(),
            result: &result,
        })
        .map(|s| s + "\n")
        .map_err(|e| Error::new("--json", e.to_string()));
    }
    Ok(table(&look.name, mode, &result.candidates))
}

/// A readable table of candidates.
pub fn table(target: &str, mode: &str, cands: &[Candidate]) -> String {
    let mut s = format!("target: {target}\nmode: {mode}\n\n| # | error | geometry | rotation | material | colour | search / re-rank error |\n|---|---|---|---|---|---|---|\n");
    for (i, c) in cands.iter().enumerate() {
        s.push_str(&format!(
            "| {} | {:.2} % ({:?}) | {} | {:.1}° | {} | {:.3}, {:.3}, {:.3}{} | {:.2} % / {:.2} % |\n",
            i + 1,
            c.error * 100.0,
            c.evaluated_by,
            c.geometry_spec,
            c.psi_deg,
            c.material_spec,
            c.colour[0],
            c.colour[1],
            c.colour[2],
            c.colour_shift.map(|s| format!(" (shift {s})")).unwrap_or_default(),
            c.search_error * 100.0,
            c.rerank_error * 100.0
        ));
    }
    if let Some(best) = cands.first().filter(|c| c.error > MATCH_BOUND) {
        s.push_str(&format!(
            "\nNo match: the best answer is {:.1} % from the target, over the {:.0} % within which a \
             look counts as reproduced (paper Table 1). Nothing in this library{} comes closer; \
             the table shows how far each answer is.\n",
            best.error * 100.0,
            MATCH_BOUND * 100.0,
            if mode.contains("fixed") {
                " with what is fixed"
            } else {
                ""
            }
        ));
    }
    s
}

/// The relative error within which a look counts as reproduced (the paper's Table 1 threshold,
/// and `validate`'s "within 7 %").
pub const MATCH_BOUND: f64 = 0.07;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::{Candidate, Final};

    fn cand(err: f64) -> Candidate {
        Candidate {
            geometry: None,
            geometry_spec: "flat:n=16".into(),
            material: None,
            material_spec: "lambert:albedo=0.5".into(),
            psi_deg: 0.0,
            colour_shift: None,
            colour: [0.5; 3],
            search_error: err,
            rerank_error: err,
            error: err,
            evaluated_by: Final::Exact,
        }
    }

    #[test]
    fn the_table_says_when_nothing_matches() {
        let t = table(
            "ggx:alpha=0.001",
            "geometry solver (material fixed)",
            &[cand(0.9999), cand(1.2)],
        );
        assert!(
            t.contains("No match: the best answer is 100.0 % from the target")
                && t.contains("with what is fixed"),
            "{t}"
        );
        let ok = table("ggx:alpha=0.2", "general solver", &[cand(0.02)]);
        assert!(!ok.contains("No match"), "{ok}");
    }
}
