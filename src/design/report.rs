//! The design run's report: pictures per exported detail (the target and the approximation
//! rendered side by side on spheres, the heightfield, in-plane BRDF slices), `report.md`, and
//! the text summary printed at the end of the run.

use super::Summary;
use crate::error::Result;
use crate::frame::{dir_from_deg, rotate_z, DirPair, Vec3};
use crate::heightfield::Heightfield;
use crate::library::Library;
use crate::material::Material;
use crate::prefilter::Prefiltered;
use crate::solve::{bvndf_of, Look};
use std::fmt::Write as _;
use std::path::Path;

/// Write `<name>-spheres.png`, `<name>-heightfield.png` and `<name>-slices.png` into `dir`;
/// returns the slices' caption.
pub fn pictures(
    dir: &Path,
    name: &str,
    look: &Look,
    hf: &Heightfield,
    mat: &Material,
    psi_deg: f64,
    lib: &Library,
) -> Result<String> {
    let geo = bvndf_of(hf);
    let pf = Prefiltered::build(mat, &crate::solve::geometry::prefilter_for(lib));
    let psi = -psi_deg.to_radians();
    let approx = move |wi: Vec3, wo: Vec3| {
        let mut scratch = Vec::new();
        crate::fast::fbar_one(
            &geo,
            &pf,
            &DirPair {
                wi: rotate_z(wi, psi),
                wo: rotate_z(wo, psi),
            },
            &mut scratch,
        )
    };
    let target = |wi: Vec3, wo: Vec3| look.fbar(wi, wo);
    let light = dir_from_deg(45.0, 30.0);
    let size = 256;
    let colour = mat_colour(mat);
    let a = crate::render::sphere(
        &target,
        size,
        light,
        look.colour.map(norm_colour).unwrap_or(colour),
        1.0,
    );
    let b = crate::render::sphere(&approx, size, light, colour, 1.0);
    let (img, w, h) = crate::render::side_by_side(&[(&a, size), (&b, size)], 8);
    let exposure = crate::render::auto_exposure(&img);
    crate::render::write_png_rgb(
        &dir.join(format!("{name}-spheres.png")),
        &img,
        w,
        h,
        exposure,
    )?;
    crate::render::heightfield_png(&dir.join(format!("{name}-heightfield.png")), hf, 256)?;
    crate::render::brdf_slices_png(
        &dir.join(format!("{name}-slices.png")),
        &[("target", &target), ("detail", &approx)],
        &[15.0, 45.0, 70.0],
        (720, 240),
    )
}

fn norm_colour(c: [f64; 3]) -> [f64; 3] {
    let m = (c[0] + c[1] + c[2]) / 3.0;
    if m > 0.0 {
        [c[0] / m, c[1] / m, c[2] / m]
    } else {
        [1.0; 3]
    }
}

fn mat_colour(m: &Material) -> [f64; 3] {
    norm_colour(crate::library::items::average_colour(m))
}

/// `report.md`: the ranking, the rejections, and the pictures of each exported detail.
pub fn write_markdown(dir: &Path, s: &Summary) -> Result<()> {
    let mut r = String::new();
    let _ = writeln!(r, "# Design report: {}\n", s.scene.name);
    let _ = writeln!(
        r,
        "Target `{}`; {}; profile `{}`; tile {} × {} mm; library `{}`.\n",
        s.scene.target, s.mode, s.profile, s.scene.tile_mm[0], s.scene.tile_mm[1], s.library
    );
    let _ = writeln!(r, "{}\n", rejected_line(s));
    if let Some(note) = match_note(s) {
        let _ = writeln!(r, "**{note}**\n");
    }
    let _ = writeln!(r, "| rank | geometry | material | rotation | patch | max / RMS deviation | min feature | error designed → made | cost | STL |\n|---|---|---|---|---|---|---|---|---|---|");
    for d in &s.details {
        let _ = writeln!(
            r,
            "| {} | `{}` | `{}` | {:.0}° | {:.2} mm | {:.3} / {:.3} mm | {} | {:.1} % → {:.1} % | {:.2} {} + {:.2} h | {} |",
            d.rank,
            d.geometry,
            d.material,
            d.rotation_deg,
            d.patch_mm,
            d.max_deviation_mm,
            d.rms_deviation_mm,
            d.min_feature_mm.map(|m| format!("{m:.3} mm")).unwrap_or_else(|| "–".into()),
            d.appearance_error_design * 100.0,
            d.appearance_error_made * 100.0,
            d.cost.material_cost,
            d.cost.currency,
            d.cost.time_h,
            d.stl.clone().unwrap_or_else(|| "not exported".into())
        );
    }
    for d in s.details.iter().filter(|d| d.stl.is_some()) {
        let n = format!("detail-{}", d.rank);
        let _ = writeln!(
            r,
            "\n## {n}\n\nTarget (left) and this detail (right), rendered as large-scale BRDFs on spheres:\n\n![{n} spheres]({n}-spheres.png)\n\n\
             One period of the heightfield: ![{n} heightfield]({n}-heightfield.png)\n\n\
             {}: ![{n} slices]({n}-slices.png)\n\n\
             Tile made: {} (whole samples of the surface). Mount the tile rotated by {:.0}° about its normal relative to the design frame. Files: `{}`, `{}` (scale: `{}`).",
            d.slices_caption
                .as_deref()
                .unwrap_or("In-plane BRDF slices")
                .trim_end_matches('.'),
            d.tile_made_mm
                .map(|[x, y]| format!("{x:.3} × {y:.3} mm"))
                .unwrap_or_else(|| "–".into()),
            d.rotation_deg,
            d.stl.clone().unwrap_or_default(),
            d.heightmap_png.clone().unwrap_or_default(),
            d.heightmap_scale.clone().unwrap_or_default()
        );
    }
    if !s.rejections.is_empty() {
        let _ = writeln!(r, "\n## Rejected candidates\n");
        for (g, code, msg) in &s.rejections {
            let _ = writeln!(r, "- `{g}`: {code}: {msg}");
        }
    }
    crate::atomic_write::write_bytes(&dir.join("report.md"), r.as_bytes())
}

/// The text printed at the end of a run.
pub fn text(s: &Summary, out: &Path, secs: f64) -> String {
    let mut t = format!(
        "design '{}' → {} ({:.1} s)\n",
        s.scene.name,
        out.display(),
        secs
    );
    for d in &s.details {
        let _ = writeln!(
            t,
            "  #{} {} | {} | patch {:.2} mm | deviation {:.3} mm max | error {:.1} % designed, {:.1} % made | {}",
            d.rank,
            d.geometry,
            d.material,
            d.patch_mm,
            d.max_deviation_mm,
            d.appearance_error_design * 100.0,
            d.appearance_error_made * 100.0,
            d.stl.clone().unwrap_or_else(|| "(not exported)".into())
        );
    }
    if let Some(note) = match_note(s) {
        let _ = writeln!(t, "  {note}");
    }
    let _ = writeln!(
        t,
        "  {}; report: {}",
        rejected_line(s),
        out.join("report.md").display()
    );
    t
}

/// How many candidates were checked and rejected, and for what.
fn rejected_line(s: &Summary) -> String {
    if s.candidates_rejected == 0 {
        return format!("{} candidates checked, none rejected", s.candidates_checked);
    }
    let reasons: Vec<String> = s.rejected.iter().map(|(k, n)| format!("{k} {n}")).collect();
    format!(
        "{} candidates checked, {} {} rejected (by reason, a geometry may fail several: {})",
        s.candidates_checked,
        s.candidates_rejected,
        if s.candidates_rejected == 1 {
            "geometry"
        } else {
            "geometries"
        },
        reasons.join(", ")
    )
}

/// When even the best detail is not visually equivalent to the target (the paper's 7 %), a
/// line saying so, as `biscale solve` does.
fn match_note(s: &Summary) -> Option<String> {
    let bound = crate::solve::job::MATCH_BOUND;
    let best = s
        .details
        .iter()
        .map(|d| d.appearance_error_made)
        .fold(f64::INFINITY, f64::min);
    if s.details.is_empty() {
        return Some(
            "No detail is makeable with this profile: see the rejected candidates.".into(),
        );
    }
    (best > bound).then(|| {
        format!(
            "No match: the best made detail is {:.1} % from the target, over the {:.0} % within \
             which a look counts as reproduced (paper Table 1): the solver found nothing closer \
             {}that this profile can make.",
            best * 100.0,
            bound * 100.0,
            if s.mode.contains("fixed") {
                "with what the scene fixes "
            } else {
                ""
            }
        )
    })
}
