//! `biscale design`: the main job. From a scene (a target look, what is fixed, a fabrication
//! profile, a tile size, a viewing distance), find library details that reproduce the look,
//! check each against the profile (scale window, millability, feature size, cost), evaluate the
//! appearance of the surface the tool would actually leave, rank by that plus the weighted cost,
//! and export the best as watertight STL, 16-bit PNG heightmaps, `summary.json` and a report.
//!
//! Only what the scene needs is loaded: a scene that fixes the material never reads the material
//! library; a scene that exports nothing never builds a mesh. The log says what was read and
//! built. Output goes to `outputs/<scene>/`, assembled in a temporary directory and renamed into
//! place, so a failed run leaves no half-written output; an existing output is replaced only
//! with `--force`.

pub mod refine;
pub mod report;
pub mod scene;

use crate::error::{Error, Result};
use crate::fab::{
    check_detail, export_detail, load_profile, CheckOptions, Decimation, FabPaths, FabReport,
};
use crate::heightfield::Heightfield;
use crate::library::progress::Progress;
use crate::material::{parse_material, Material};
use crate::prefilter::Prefiltered;
use crate::solve::job::Fixed;
use crate::solve::look::Edits;
use crate::solve::{fast_values, Candidate, Final, Look, SolveOptions};
use scene::Scene;
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Options of a design run besides the scene.
#[derive(Debug, Clone)]
pub struct DesignJob {
    /// Scene file; `None` runs the built-in default.
    pub scene: Option<PathBuf>,
    /// Parent of the output directory (`outputs/`).
    pub outputs: PathBuf,
    pub force: bool,
    /// Library directory; default: the cached build of the scene's `library_profile`.
    pub library: Option<PathBuf>,
    pub cache_dir: Option<PathBuf>,
    pub quiet: bool,
}

/// One ranked detail in `summary.json`.
#[derive(Debug, Clone, Serialize)]
pub struct DetailSummary {
    pub rank: usize,
    pub geometry: String,
    pub material: String,
    pub rotation_deg: f64,
    pub colour: [f64; 3],
    pub stl: Option<String>,
    pub heightmap_png: Option<String>,
    pub heightmap_scale: Option<String>,
    pub patch_mm: f64,
    pub tile_mm: [f64; 2],
    pub tool: Option<String>,
    pub process: String,
    pub max_deviation_mm: f64,
    pub rms_deviation_mm: f64,
    pub min_feature_mm: Option<f64>,
    pub cost: crate::fab::CostReport,
    /// Relative appearance error of the designed surface and of the manufactured one (fast
    /// evaluator at the solver's samples).
    pub appearance_error_design: f64,
    pub appearance_error_made: f64,
    /// The score ranked by: error_made + cost_weight × weighted cost.
    pub score: f64,
    /// Continuous refinement (amplitude scale, rotation), when asked for.
    pub refinement: Option<refine::Refined>,
    /// The tile actually made, `[x, y]` mm: `tile_mm` rounded down to whole samples of the
    /// surface (exported details only).
    pub tile_made_mm: Option<[f64; 2]>,
    pub triangles: Option<usize>,
    pub triangles_full: Option<usize>,
    pub mesh_height_error_mm: Option<f64>,
    /// Whether the mesh met every decimation limit asked for (`triangle_budget`, and with it
    /// `decimate_max_error_mm`).
    pub budget_met: Option<bool>,
    /// The caption of `detail-N-slices.png` (which curve is which, the axes), for the report.
    #[serde(skip)]
    pub slices_caption: Option<String>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub scene: Scene,
    /// The profile's name, and the profile as resolved (every file read, machine, tool with its
    /// diameter, stock, limits, weights): what an independent check of the export needs.
    pub profile: String,
    pub fabrication_profile: crate::fab::Profile,
    pub library: String,
    pub mode: String,
    pub candidates_checked: usize,
    /// Distinct candidate geometries rejected; `rejected` counts reasons (a geometry can fail
    /// several checks, so its counts may add up to more).
    pub candidates_rejected: usize,
    pub rejected: BTreeMap<String, usize>,
    pub rejections: Vec<(String, String, String)>,
    pub details: Vec<DetailSummary>,
    pub log: Vec<String>,
}

/// How the design job measures the appearance error of a heightfield (designed, milled or
/// refined): its light lobes ([`crate::lightlobes`]) at the library's lights, where every sample
/// lies, with the material's prefiltered table. `rays` view rays per view node.
pub struct Appraiser {
    pub layout: crate::gamma::GammaLayout,
    pub rays: usize,
    pub clusters: usize,
}

impl Appraiser {
    /// Relative error of `hf` with `pf`, rotated by `psi_deg`, against the look.
    pub fn error(
        &self,
        look: &Look,
        hf: &Heightfield,
        pf: &Prefiltered,
        psi_deg: f64,
        opt: &SolveOptions,
    ) -> f64 {
        let (s, t) = crate::solve::rotated_samples(
            look,
            &self.layout.lights,
            psi_deg.to_radians(),
            &opt.sampling,
        );
        let geo = crate::lightlobes::LightLobes::build(&self.layout, hf, self.rays, self.clusters);
        s.rel_error(&t, &fast_values(&geo, pf, &s))
    }
}

/// Run the design job; returns the text summary printed to standard output.
pub fn run(job: &DesignJob) -> Result<String> {
    let t0 = Instant::now();
    let progress = Progress { quiet: job.quiet };
    let mut log: Vec<String> = Vec::new();
    let note = |s: String, log: &mut Vec<String>| {
        progress.note(&format!("design: {s}"));
        log.push(s);
    };
    let scene = match &job.scene {
        Some(p) => Scene::load(p)?,
        None => Scene::builtin()?,
    };
    // Every input is read and checked before any work (and before the output check, so that
    // a bad scene is reported as such): the profile, the target, what is fixed.
    let ctx = |key: &str| match &job.scene {
        Some(p) => format!("{}: key `{key}`", p.display()),
        None => format!("built-in scene: key `{key}`"),
    };
    let scene_dir = job.scene.as_deref().and_then(Path::parent);
    let profile = load_profile(&scene.profile, &FabPaths::for_scene(scene_dir))
        .map_err(|e| e.within(ctx("profile")))?;
    let edits = Edits {
        brightness: scene.brightness,
        contrast: scene.contrast,
        blur: scene.blur,
    };
    let look =
        Look::from_spec(&scene.target, edits, scene.colour).map_err(|e| e.within(ctx("target")))?;
    look.check_not_black()
        .map_err(|e| e.within(ctx("target")))?;
    let fixed = Fixed::read(
        scene.fixed_material.as_deref(),
        scene.fixed_geometry.as_deref().map(|g| {
            (
                g,
                scene.heightmap_patch_mm.unwrap_or(10.0),
                scene.heightmap_height_scale.unwrap_or(1.0),
            )
        }),
        (&ctx("fixed_material"), &ctx("fixed_geometry")),
    )?;
    let fixed_hf = match &fixed {
        Fixed::Geometry(hf, _) => Some(hf.clone()),
        _ => None,
    };
    // Checked even when `--library` names the library to use: a mistyped key is a mistake in
    // the scene whichever library the run reads.
    crate::library::profile::LibraryProfile::load(&scene.library_profile).map_err(|e| {
        // The loader names its input as the command line does (`--profile`); here it is the
        // scene's key.
        if e.context == "--profile" {
            Error::new(ctx("library_profile"), e.message)
        } else {
            e.within(ctx("library_profile"))
        }
    })?;
    crate::fab::check_tile(&profile, scene.tile_mm).map_err(|e| {
        if e.context == "tile_mm" {
            Error::new(ctx("tile_mm"), e.message)
        } else {
            e
        }
    })?;
    crate::atomic_write::check_output_dir(&job.outputs, "--outputs")?;
    let out_dir = job.outputs.join(&scene.name);
    if out_dir.exists() && !job.force {
        return Err(Error::new(
            out_dir.display().to_string(),
            "already exists; pass --force to replace it, or rename the scene",
        ));
    }
    remove_stale(&job.outputs, &scene.name);
    note(
        format!(
            "scene '{}': target {}, profile {}, tile {}×{} mm",
            scene.name, scene.target, profile.name, scene.tile_mm[0], scene.tile_mm[1]
        ),
        &mut log,
    );
    let lib = crate::solve::job::open_library(
        &job.library,
        &scene.library_profile,
        &job.cache_dir,
        &progress,
    )?;
    let opt = SolveOptions {
        k: scene.candidates,
        // The pool counts (geometry, rotation) pairs; the solver keeps each geometry once, so
        // `candidates` different geometries need up to `candidates × psi` pairs.
        pool: (scene.candidates * scene.psi.max(1))
            .max(crate::solve::auto_geometry_pool(lib.manifest.geometries)),
        psi: scene.psi,
        // The fabrication stage evaluates the designed and the made surface of every feasible
        // candidate with the fast evaluator; a third solver stage would repeat that.
        final_eval: Final::Library,
        sampling: crate::sampling::SamplingConfig {
            seed: scene.seed,
            ..Default::default()
        },
        ..SolveOptions::default()
    };
    let general = crate::solve::general::GeneralOptions {
        seed: scene.seed,
        ..Default::default()
    };
    let (mode, result) = fixed.solve(&lib, &look, &opt, &general)?;
    note(
        format!(
            "{mode}: {} candidates in {:.1} s; library {} read: {}",
            result.candidates.len(),
            t0.elapsed().as_secs_f64(),
            lib.dir.display(),
            lib.reads().join(", ")
        ),
        &mut log,
    );

    // Fabrication stage: check every candidate, evaluate the made surface, rank.
    let eye = Appraiser {
        layout: lib.gamma_layout(),
        rays: crate::solve::LIGHT_LOBE_RAYS,
        clusters: lib.profile.geometry.lobe_clusters,
    };
    let mut rejected: BTreeMap<String, usize> = BTreeMap::new();
    let mut rejections = Vec::new();
    let mut ranked: Vec<(f64, Candidate, FabReport, f64, f64, Heightfield, Material)> = Vec::new();
    let mut prefiltered: BTreeMap<String, Prefiltered> = BTreeMap::new();
    // One fabrication check per distinct geometry (its rotations share it; a rejected geometry
    // is counted once).
    let mut specs: Vec<String> = Vec::new();
    for c in &result.candidates {
        if !specs.contains(&c.geometry_spec) {
            specs.push(c.geometry_spec.clone());
        }
    }
    let t1 = Instant::now();
    // One bar over the checks and then the appraisals: two steps per geometry, the second
    // counted as done at once for a geometry the check rejects (so the bar never goes back).
    let bar = progress.bar(
        2 * specs.len() as u64,
        "design: fabrication check and appraisal",
    );
    let checks: Vec<(Heightfield, FabReport)> = {
        use rayon::prelude::*;
        specs
            .par_iter()
            .map(|spec| {
                let hf = match &fixed_hf {
                    Some(h) => h.clone(),
                    None => crate::solve::library_heightfield(spec)?,
                };
                let rep = check_detail(
                    &hf,
                    &profile,
                    &CheckOptions {
                        tile_mm: (scene.tile_mm[0], scene.tile_mm[1]),
                        patch_mm: None,
                        viewing_distance_mm: scene.viewing_distance_mm,
                    },
                )?;
                bar.inc(1);
                Ok((hf, rep))
            })
            .collect::<Result<_>>()?
    };
    let checked: BTreeMap<String, (Heightfield, FabReport)> =
        specs.into_iter().zip(checks).collect();
    let mut counted: std::collections::BTreeSet<String> = Default::default();
    let mut candidates_rejected = 0;
    let mut feasible = Vec::new();
    for c in &result.candidates {
        // One detail per geometry: its best rotation (candidates come best first).
        if !counted.insert(c.geometry_spec.clone()) {
            continue;
        }
        let (hf, rep) = checked[&c.geometry_spec].clone();
        if !rep.feasible {
            candidates_rejected += 1;
            for r in &rep.rejections {
                *rejected.entry(r.code.clone()).or_default() += 1;
                rejections.push((c.geometry_spec.clone(), r.code.clone(), r.message.clone()));
            }
            continue;
        }
        let mat = parse_material(&c.material_spec)?;
        if !prefiltered.contains_key(&c.material_spec) {
            let pf = crate::solve::material_prefiltered(&lib, &mat, c.material)?;
            prefiltered.insert(c.material_spec.clone(), pf);
        }
        feasible.push((c, hf, rep, mat));
    }
    // The designed and the made surface of each feasible detail, appraised in parallel (each
    // builds its own light lobes; the values do not depend on the number of threads).
    bar.inc((checked.len() - feasible.len()) as u64);
    let appraised: Vec<(f64, f64)> = {
        use rayon::prelude::*;
        feasible
            .par_iter()
            .map(|(c, hf, rep, _)| {
                let pf = &prefiltered[&c.material_spec];
                let e_design = eye.error(&look, hf, pf, c.psi_deg, &opt);
                let e_made = eye.error(&look, &rep.made, pf, c.psi_deg, &opt);
                bar.inc(1);
                (e_design, e_made)
            })
            .collect()
    };
    bar.finish();
    for ((c, hf, rep, mat), (e_design, e_made)) in feasible.into_iter().zip(appraised) {
        let score = e_made + scene.cost_weight * rep.cost.total;
        ranked.push((score, c.clone(), rep, e_design, e_made, hf, mat));
    }
    ranked.sort_by(|a, b| a.0.total_cmp(&b.0));
    note(
        format!(
            "fabrication: {} candidates ({} distinct geometries) checked in {:.1} s, {} feasible, rejected by reason: {:?}",
            result.candidates.len(),
            checked.len(),
            t1.elapsed().as_secs_f64(),
            ranked.len(),
            rejected
        ),
        &mut log,
    );
    // Continuous refinement of the best few: amplitude, rotation, shape and (when the scene
    // leaves it free) material parameters, under the profile's limits.
    let mut refined_by_spec: BTreeMap<String, refine::Refined> = BTreeMap::new();
    let t2 = Instant::now();
    let prefilter_cfg = crate::library::build::prefilter_config(&lib.profile);
    for entry in ranked.iter_mut().take(scene.refine) {
        let (score, c, rep, e_design, e_made, hf, mat) = entry;
        let pf = prefiltered[&c.material_spec].clone();
        let subject = refine::Subject {
            hf,
            // A geometry the scene fixes keeps its shape; a library item's generator is refined.
            generator: match fixed_hf {
                Some(_) => None,
                None => crate::generators::parse_generator(&c.geometry_spec).ok(),
            },
            material: match scene.fixed_material {
                Some(_) => None,
                None => Some(c.material_spec.clone()),
            },
            pf: &pf,
            prefilter: prefilter_cfg.clone(),
            psi0_deg: c.psi_deg,
            relief_fixed: fixed_hf.is_some(),
        };
        let r = refine::refine(
            &look,
            &subject,
            rep.patch_mm,
            &profile,
            &opt,
            &eye,
            scene.refine_evaluations,
        )?;
        if r.accepted {
            let base = match &r.geometry_spec {
                Some(g) => crate::solve::library_heightfield(g)?,
                None => hf.clone(),
            };
            let hf2 = base.scaled(r.scale);
            let rep2 = check_detail(
                &hf2,
                &profile,
                &CheckOptions {
                    tile_mm: (scene.tile_mm[0], scene.tile_mm[1]),
                    patch_mm: Some(rep.patch_mm),
                    viewing_distance_mm: scene.viewing_distance_mm,
                },
            )?;
            if rep2.feasible {
                if let Some(m) = &r.material_spec {
                    let m2 = parse_material(m)?;
                    prefiltered.insert(m.clone(), Prefiltered::build(&m2, &prefilter_cfg));
                    c.material_spec = m.clone();
                    // No longer a library material: no index, no colour shift.
                    c.material = None;
                    c.colour_shift = None;
                    *mat = m2;
                }
                let pf2 = &prefiltered[&c.material_spec];
                c.psi_deg = r.psi_deg;
                let spec = r.geometry_spec.as_deref().unwrap_or(&c.geometry_spec);
                c.geometry_spec = if r.scale == 1.0 {
                    spec.to_string()
                } else {
                    format!("{spec} (heights × {:.3})", r.scale)
                };
                *e_design = eye.error(&look, &hf2, pf2, c.psi_deg, &opt);
                *e_made = eye.error(&look, &rep2.made, pf2, c.psi_deg, &opt);
                *score = *e_made + scene.cost_weight * rep2.cost.total;
                *hf = hf2;
                *rep = rep2;
            }
        }
        refined_by_spec.insert(c.geometry_spec.clone(), r);
    }
    if scene.refine > 0 && !ranked.is_empty() {
        ranked.sort_by(|a, b| a.0.total_cmp(&b.0));
        let what = match (&fixed_hf, &scene.fixed_material) {
            (Some(_), _) => "rotation and the material's parameters (the geometry is fixed)",
            (None, Some(_)) => "relief, rotation and shape (the material is fixed)",
            (None, None) => "relief, rotation, shape and the material's parameters",
        };
        note(
            format!(
                "refinement (NLopt COBYLA: {what}): {} in {:.1} s: {}",
                refined_by_spec.len(),
                t2.elapsed().as_secs_f64(),
                refined_by_spec
                    .iter()
                    .map(|(g, r)| {
                        let budget = if r.max_evaluations > scene.refine_evaluations {
                            format!(
                                "; refine_evaluations = {} raised to {}, one more than the \
                                 variables, which COBYLA needs to start",
                                scene.refine_evaluations, r.max_evaluations
                            )
                        } else {
                            String::new()
                        };
                        format!(
                            "{g}: {:.1} % -> {:.1} % ({}, {} evaluations{budget})",
                            r.error_before * 100.0,
                            r.error_after * 100.0,
                            r.status,
                            r.evaluations
                        )
                    })
                    .collect::<Vec<_>>()
                    .join("; ")
            ),
            &mut log,
        );
    }
    let refined: BTreeMap<usize, refine::Refined> = ranked
        .iter()
        .enumerate()
        .filter_map(|(i, e)| {
            refined_by_spec
                .get(&e.1.geometry_spec)
                .map(|r| (i + 1, r.clone()))
        })
        .collect();

    // Export into a temporary directory, then rename into place.
    let tmp = job
        .outputs
        .join(format!(".{}.partial-{}", scene.name, std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).map_err(|e| Error::io(&tmp, "create the output directory", e))?;
    // Removed if the run is interrupted before the output is complete; not while it is being
    // moved into place (`install`), where the previous output is briefly set aside.
    let registered = crate::interrupt::register(&tmp);
    let outcome = (|| -> Result<Vec<DetailSummary>> {
        let mut details = Vec::new();
        let n_export = scene.details.min(ranked.len());
        if n_export == 0 {
            let why = if scene.details == 0 {
                "the scene asks for details = 0"
            } else {
                "no candidate is feasible"
            };
            note(
                format!("no detail exported ({why}): no mesh built"),
                &mut log,
            );
        }
        for (i, (score, c, rep, e_d, e_m, hf, mat)) in ranked.iter().enumerate() {
            let rank = i + 1;
            let export = if i < n_export {
                let name = format!("detail-{rank}");
                let dec = match (scene.decimate_max_error_mm, scene.triangle_budget) {
                    (Some(e), Some(b)) => Some(Decimation::Both {
                        max_error_mm: e,
                        budget: b,
                    }),
                    (None, Some(b)) => Some(Decimation::TriangleBudget(b)),
                    (Some(e), None) => Some(Decimation::MaxErrorMm(e)),
                    _ => None,
                };
                let t = Instant::now();
                let ex = export_detail(
                    hf,
                    &profile,
                    rep.patch_mm,
                    (scene.tile_mm[0], scene.tile_mm[1]),
                    &tmp,
                    &name,
                    dec,
                )?;
                note(
                    format!(
                        "{name}: tile made {:.3} × {:.3} mm (whole samples of {:.4} mm), {} triangles ({} before decimation, height error {:.4} mm), built and checked in {:.2} s",
                        ex.tile_x_mm,
                        ex.tile_y_mm,
                        ex.sample_mm,
                        ex.triangles,
                        ex.triangles_full,
                        ex.max_height_error_mm,
                        t.elapsed().as_secs_f64()
                    ),
                    &mut log,
                );
                if !ex.budget_met {
                    let why = match (scene.decimate_max_error_mm, scene.triangle_budget) {
                        // The budget fits, at a larger error than asked for.
                        (Some(e), Some(b)) if ex.triangles <= b => format!(
                            "within decimate_max_error_mm = {e} mm the mesh has more than \
                             triangle_budget = {b} triangles; the budget was kept, at a height \
                             error of {:.4} mm",
                            ex.max_height_error_mm
                        ),
                        (_, b) => format!(
                            "no mesh of this tile fits triangle_budget = {} (the coarsest has {})",
                            b.unwrap_or(0),
                            ex.triangles
                        ),
                    };
                    note(format!("{name}: warning: {why}"), &mut log);
                }
                let allowed = profile.max_deviation_frac * rep.millability.relief_mm;
                if ex.max_height_error_mm > allowed {
                    note(
                        format!(
                            "{name}: warning: the mesh's height error ({:.4} mm) exceeds what the \
                             profile allows the made surface ({:.4} mm: max_deviation_frac {} of \
                             the {:.4} mm relief); the appearance errors are those of the \
                             undecimated surface",
                            ex.max_height_error_mm,
                            allowed,
                            profile.max_deviation_frac,
                            rep.millability.relief_mm
                        ),
                        &mut log,
                    );
                }
                let caption = report::pictures(&tmp, &name, &look, hf, mat, c.psi_deg, &lib)?;
                Some((ex, caption))
            } else {
                None
            };
            let (export, slices_caption) = match export {
                Some((e, c)) => (Some(e), Some(c)),
                None => (None, None),
            };
            let rel = |p: &Path| p.file_name().map(|n| n.to_string_lossy().into_owned());
            details.push(DetailSummary {
                rank,
                geometry: c.geometry_spec.clone(),
                material: c.material_spec.clone(),
                rotation_deg: signed_degrees(c.psi_deg),
                colour: c.colour,
                stl: export.as_ref().and_then(|e| rel(&e.stl)),
                heightmap_png: export.as_ref().and_then(|e| rel(&e.png)),
                heightmap_scale: export.as_ref().and_then(|e| rel(&e.png_scale)),
                patch_mm: rep.patch_mm,
                tile_mm: scene.tile_mm,
                tool: profile.tool.as_ref().map(|t| t.name.clone()),
                process: rep.millability.process.clone(),
                max_deviation_mm: rep.millability.max_deviation_mm,
                rms_deviation_mm: rep.millability.rms_deviation_mm,
                min_feature_mm: rep.features.min_feature_mm,
                cost: rep.cost.clone(),
                appearance_error_design: *e_d,
                appearance_error_made: *e_m,
                score: *score,
                refinement: refined.get(&rank).cloned(),
                tile_made_mm: export.as_ref().map(|e| [e.tile_x_mm, e.tile_y_mm]),
                triangles: export.as_ref().map(|e| e.triangles),
                triangles_full: export.as_ref().map(|e| e.triangles_full),
                mesh_height_error_mm: export.as_ref().map(|e| e.max_height_error_mm),
                budget_met: export.as_ref().map(|e| e.budget_met),
                slices_caption,
            });
        }
        Ok(details)
    })();
    let details = match outcome {
        Ok(d) => d,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e);
        }
    };
    let summary = Summary {
        scene: scene.clone(),
        profile: profile.name.clone(),
        fabrication_profile: profile.clone(),
        library: lib.dir.display().to_string(),
        mode: mode.into(),
        candidates_checked: result.candidates.len(),
        candidates_rejected,
        rejected,
        rejections,
        details,
        log: log.clone(),
    };
    let finish = || -> Result<()> {
        let json = serde_json::to_string_pretty(&summary)
            .map_err(|e| Error::new("summary.json", e.to_string()))?;
        crate::atomic_write::write_bytes(&tmp.join("summary.json"), json.as_bytes())?;
        report::write_markdown(&tmp, &summary)?;
        drop(registered);
        install(&tmp, &out_dir)
    };
    if let Err(e) = finish() {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(e);
    }
    Ok(report::text(&summary, &out_dir, t0.elapsed().as_secs_f64()))
}

/// An angle in degrees as the equal one in (-180°, 180°] (a tile's mounting rotation).
fn signed_degrees(a: f64) -> f64 {
    let r = a.rem_euclid(360.0);
    if r > 180.0 {
        r - 360.0
    } else {
        r
    }
}

/// Remove the temporary directories (`.NAME.partial-PID`) that runs of scene `name` left in
/// `outputs` when they were killed (their process is gone). Only where `/proc` tells which
/// processes run; elsewhere they are left for the user.
fn remove_stale(outputs: &Path, name: &str) {
    let proc_ = Path::new("/proc");
    if !proc_.join("self").exists() {
        return;
    }
    let prefix = format!(".{name}.partial-");
    let Ok(entries) = std::fs::read_dir(outputs) else {
        return;
    };
    for e in entries.flatten() {
        let file = e.file_name();
        let Some(pid) = file.to_str().and_then(|f| f.strip_prefix(&prefix)) else {
            continue;
        };
        if pid.parse::<u32>().is_ok() && !proc_.join(pid).exists() {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// Move the finished temporary directory to `out`, replacing an older output only after the new
/// one is complete.
fn install(tmp: &Path, out: &Path) -> Result<()> {
    let old = out.with_file_name(format!(
        ".{}.old-{}",
        out.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        std::process::id()
    ));
    let had_old = out.exists();
    if had_old {
        std::fs::rename(out, &old)
            .map_err(|e| Error::io(out, "move the previous output aside", e))?;
    }
    if let Err(e) = std::fs::rename(tmp, out) {
        if had_old {
            let _ = std::fs::rename(&old, out);
        }
        return Err(Error::io(out, "move the finished output into place", e));
    }
    if had_old {
        // The previous output may have been a directory or (with --force) a plain file.
        let _ = if old.is_dir() {
            std::fs::remove_dir_all(&old)
        } else {
            std::fs::remove_file(&old)
        };
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn install_replaces_an_old_output_directory_or_file_and_leaves_no_backup() {
        let d = crate::testdir::TestDir::new("design-install");
        for old_is_file in [false, true] {
            let (tmp, out) = (d.join(".scene.partial-1"), d.join("scene"));
            std::fs::create_dir_all(&tmp).unwrap();
            std::fs::write(tmp.join("report.md"), "new").unwrap();
            if old_is_file {
                std::fs::write(&out, "an old file").unwrap();
            } else {
                std::fs::create_dir_all(&out).unwrap();
                std::fs::write(out.join("report.md"), "old").unwrap();
            }
            install(&tmp, &out).unwrap();
            assert_eq!(
                std::fs::read_to_string(out.join("report.md")).unwrap(),
                "new"
            );
            let left: Vec<_> = std::fs::read_dir(&*d)
                .unwrap()
                .map(|e| e.unwrap().file_name())
                .collect();
            assert_eq!(left, ["scene"], "old_is_file = {old_is_file}");
            std::fs::remove_dir_all(&out).unwrap();
        }
    }
}
