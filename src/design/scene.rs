//! Scenes: what a `biscale design` run is asked to make. A scene is a TOML file (or the built-in
//! default): the target look and its edits, what is fixed, the fabrication profile, the tile
//! size, the viewing distance and how many details to export. Unknown keys, wrong types and
//! out-of-range values are errors naming the file and the key.

use crate::error::{Error, Result};
use crate::tomlfile::exact_len;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The built-in default scene: the paper's anisotropic Ward target (Fig. 7) with a fixed glossy
/// metal, milled with a 1 mm ball-nose in aluminium, as a facade panel seen from 40 m (at 2 m a
/// 1 mm tool's smallest period, about 10 mm, would subtend far more than one arc minute). The
/// metal is modelled by Ward's BRDF like the target: a microfacet metal (GGX with Fresnel) is far
/// brighter at grazing angles than any Ward lobe, which no geometry corrects (its best default
/// design was 56 % off, with bumps; the Ward metal's is 37 %, with grooves along the long axis).
pub const DEFAULT_SCENE: &str = r#"# The built-in default scene of `biscale design`.
name = "aniso-ward-panel"
target = "ward:ax=0.30,ay=0.08"
fixed_material = "ward:alpha=0.08"
profile = "cnc-ball1-aluminium"
tile_mm = [50.0, 50.0]
viewing_distance_mm = 40000.0
details = 2
candidates = 40
psi = 4
library_profile = "default"
decimate_max_error_mm = 0.005
"#;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Names the output directory `outputs/<name>/`.
    pub name: String,
    /// Target look: a material spec, `ward:ax=..,ay=..`, or a MERL `.binary` path.
    pub target: String,
    #[serde(default = "one")]
    pub brightness: f64,
    #[serde(default = "one")]
    pub contrast: f64,
    /// Angular edit of the target: `[sx, sy]` blur (> 1) or sharpen (< 1) of the highlight along
    /// x and y (different values stretch it).
    #[serde(default = "unit_blur", deserialize_with = "exact_len::array2")]
    pub blur: [f64; 2],
    /// Target colour `[r, g, b]` (average fbar per channel), optional.
    #[serde(default, deserialize_with = "exact_len::option_array3")]
    pub colour: Option<[f64; 3]>,
    /// Fix the small-scale material (a spec): solve for the geometry only.
    #[serde(default)]
    pub fixed_material: Option<String>,
    /// Fix the geometry (a procedural spec or heightmap path): solve for the material only.
    #[serde(default)]
    pub fixed_geometry: Option<String>,
    /// A heightmap `fixed_geometry`'s period along x in mm and the factor on its stored values
    /// (heights in mm), as `forward`'s `--patch-size` and `--height-scale` (defaults 10 and 1).
    /// Only the relief's proportion to the period matters to the look; the size the detail is
    /// made at is chosen by the scale window.
    #[serde(default)]
    pub heightmap_patch_mm: Option<f64>,
    #[serde(default)]
    pub heightmap_height_scale: Option<f64>,
    /// Fabrication profile: a shipped name (`profiles/fabrication/`) or a path.
    pub profile: String,
    /// Physical tile to make, `[x, y]` in mm.
    #[serde(deserialize_with = "exact_len::array2")]
    pub tile_mm: [f64; 2],
    /// Distance the surface is seen from, mm (overrides the profile's).
    #[serde(default)]
    pub viewing_distance_mm: Option<f64>,
    /// Details to export (0: rank and report only; no mesh is built).
    #[serde(default = "two")]
    pub details: usize,
    /// Candidates the solver returns for the fabrication stage to check (the best-looking are
    /// often unmakeable: many are needed to find makeable ones).
    #[serde(default = "forty")]
    pub candidates: usize,
    /// Rotations of the geometry tried.
    #[serde(default = "four")]
    pub psi: usize,
    /// Library profile (`tiny`, `default`, `paper` or a path); built on first use.
    #[serde(default = "default_lib")]
    pub library_profile: String,
    /// Weight of the cost in the ranking: score = appearance error (fraction) + cost_weight ×
    /// the profile's weighted cost (currency units).
    #[serde(default = "cost_weight")]
    pub cost_weight: f64,
    /// Decimate each exported solid to this height error (mm), and/or to a triangle budget.
    #[serde(default)]
    pub decimate_max_error_mm: Option<f64>,
    #[serde(default)]
    pub triangle_budget: Option<usize>,
    /// Refine this many of the best details continuously (relief amplitude, rotation, the
    /// generator's shape parameters, and the material's parameters when it is not fixed; NLopt
    /// COBYLA, the profile's limits as constraints); 0 turns refinement off.
    #[serde(default = "one_usize")]
    pub refine: usize,
    /// Objective evaluations per refined detail (each simulates the tool and builds a quick BVNDF).
    #[serde(default = "twenty")]
    pub refine_evaluations: u32,
    /// Seed of the solver's random starts and sampling.
    #[serde(default = "seed")]
    pub seed: u64,
}

fn one() -> f64 {
    1.0
}
fn unit_blur() -> [f64; 2] {
    [1.0, 1.0]
}
fn one_usize() -> usize {
    1
}
fn twenty() -> u32 {
    20
}
fn two() -> usize {
    2
}
fn four() -> usize {
    4
}
fn forty() -> usize {
    40
}
fn seed() -> u64 {
    1
}
fn default_lib() -> String {
    "default".into()
}
fn cost_weight() -> f64 {
    0.001
}

/// The longest scene name: its output directory's hidden working name,
/// `.NAME.partial-PID`, must fit the 255 bytes of a file name.
pub const MAX_NAME: usize = 200;

impl Scene {
    /// Parse and validate scene text; `ctx` names the file in errors.
    pub fn parse(text: &str, ctx: &str) -> Result<Self> {
        let s: Scene = crate::tomlfile::parse(Path::new(ctx), text)?;
        s.validate().map_err(|e| e.within(ctx))?;
        Ok(s)
    }

    /// Read a scene file; its relative paths are taken relative to its directory
    /// ([`Scene::resolve_paths`]).
    pub fn load(path: &Path) -> Result<Self> {
        let text =
            std::fs::read_to_string(path).map_err(|e| Error::io(path, "read the scene", e))?;
        let mut s = Self::parse(&text, &path.display().to_string())?;
        s.resolve_paths(path.parent().unwrap_or(Path::new("")));
        Ok(s)
    }

    /// Make the scene's relative paths — a fabrication or library profile given as a path, a
    /// heightmap `fixed_geometry` or the image of a `texture:file=PATH` one, a MERL file in
    /// `target` or `fixed_material` — relative to
    /// `dir` (the scene file's directory), so a scene runs the same from any working
    /// directory. A relative path that exists only from the working directory is kept as it is.
    pub fn resolve_paths(&mut self, dir: &Path) {
        let under = |v: &str| -> String {
            let p = Path::new(v);
            let there = dir.join(p);
            if p.is_absolute() || dir.as_os_str().is_empty() || (p.exists() && !there.exists()) {
                v.to_string()
            } else {
                there.display().to_string()
            }
        };
        if crate::fab::profile::is_path(&self.profile) {
            self.profile = under(&self.profile);
        }
        if crate::library::profile::is_path(&self.library_profile) {
            self.library_profile = under(&self.library_profile);
        }
        if let Some(g) = &mut self.fixed_geometry {
            if crate::heightmap_io::is_heightmap_file(g) {
                *g = under(g);
            } else {
                *g = crate::generators::map_file_key(g, under);
            }
        }
        self.target = crate::material::map_path_terms(&self.target, under);
        if let Some(m) = &mut self.fixed_material {
            *m = crate::material::map_path_terms(m, under);
        }
    }

    pub fn builtin() -> Result<Self> {
        Self::parse(DEFAULT_SCENE, "built-in default scene")
    }

    fn validate(&self) -> Result<()> {
        if self.name.is_empty()
            || !self
                .name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
            || self.name.starts_with('.')
        {
            return Err(Error::new("name", format!("'{}': expected letters, digits, '-', '_' or '.' (it names the output directory)", self.name)));
        }
        // The hidden `.NAME.partial-PID` directory must fit a file name (255 bytes).
        if self.name.len() > MAX_NAME {
            return Err(Error::new(
                "name",
                format!(
                    "{} characters: expected at most {MAX_NAME} (it names the output directory)",
                    self.name.len()
                ),
            ));
        }
        for (k, v) in [
            ("tile_mm[0]", self.tile_mm[0]),
            ("tile_mm[1]", self.tile_mm[1]),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::new(
                    k,
                    format!("expected a positive size in mm, got {v}"),
                ));
            }
        }
        if let Some(d) = self.viewing_distance_mm {
            if !(d.is_finite() && d > 0.0) {
                return Err(Error::new(
                    "viewing_distance_mm",
                    format!("expected a positive distance in mm, got {d}"),
                ));
            }
        }
        for (k, v) in [
            ("brightness", self.brightness),
            ("contrast", self.contrast),
            ("cost_weight", self.cost_weight),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(Error::new(k, format!("expected a number >= 0, got {v}")));
            }
        }
        if self.fixed_material.is_some() && self.fixed_geometry.is_some() {
            return Err(Error::new(
                "fixed_material / fixed_geometry",
                "fix at most one of them",
            ));
        }
        for (k, v) in [
            ("heightmap_patch_mm", self.heightmap_patch_mm),
            ("heightmap_height_scale", self.heightmap_height_scale),
        ] {
            let Some(v) = v else { continue };
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::new(
                    k,
                    format!("expected a positive number, got {v}"),
                ));
            }
            if !self
                .fixed_geometry
                .as_deref()
                .is_some_and(crate::heightmap_io::is_heightmap_file)
            {
                return Err(Error::new(
                    k,
                    "applies to a heightmap file given as `fixed_geometry` (.npy, .png or .obj); \
                     procedural geometries set their heights in their spec",
                ));
            }
            let obj = self
                .fixed_geometry
                .as_deref()
                .is_some_and(|g| g.trim().to_ascii_lowercase().ends_with(".obj"));
            if obj && k == "heightmap_patch_mm" {
                return Err(Error::new(
                    k,
                    "an .obj carries its own size (its x-y bounding rectangle is the period)",
                ));
            }
        }
        // Whole-number keys: each in a range a run can use (a huge `candidates` would allocate
        // its pool before the library caps it; `psi` is rotations of a full turn).
        for (k, v, lo, hi) in [
            ("candidates", self.candidates, 1, 100_000),
            ("psi", self.psi, 1, 360),
            ("details", self.details, 0, 1000),
            ("refine", self.refine, 0, 1000),
            (
                "refine_evaluations",
                self.refine_evaluations as usize,
                0,
                100_000,
            ),
        ] {
            if !(lo..=hi).contains(&v) {
                return Err(Error::new(
                    k,
                    format!("expected a whole number from {lo} to {hi}, got {v}"),
                ));
            }
        }
        if let Some(b) = self.triangle_budget {
            if b < 12 {
                return Err(Error::new(
                    "triangle_budget",
                    format!("expected at least 12 (the fewest triangles of a closed box), got {b}"),
                ));
            }
        }
        if let Some(e) = self.decimate_max_error_mm {
            if !(e.is_finite() && e > 0.0) {
                return Err(Error::new(
                    "decimate_max_error_mm",
                    format!("expected a positive height error in mm, got {e}"),
                ));
            }
        }
        if let Some(c) = self.colour {
            crate::solve::look::check_colour("colour", c)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_paths_are_taken_against_the_scene_directory() {
        let mut s = Scene::builtin().unwrap();
        s.fixed_geometry = Some("texture:file=tex/wood.png,patch=1".into());
        s.resolve_paths(Path::new("/scenes"));
        assert_eq!(
            s.fixed_geometry.as_deref(),
            Some("texture:file=/scenes/tex/wood.png,patch=1")
        );
        s.fixed_geometry = Some("maps/relief.npy".into());
        s.resolve_paths(Path::new("/scenes"));
        assert_eq!(s.fixed_geometry.as_deref(), Some("/scenes/maps/relief.npy"));
        s.fixed_geometry = Some("bumps:n=32".into());
        s.resolve_paths(Path::new("/scenes"));
        assert_eq!(s.fixed_geometry.as_deref(), Some("bumps:n=32"));
    }

    #[test]
    fn builtin_parses_and_bad_scenes_name_the_key() {
        let s = Scene::builtin().unwrap();
        assert_eq!(s.details, 2);
        let e = Scene::parse(&DEFAULT_SCENE.replace("details", "detials"), "s.toml")
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("s.toml") && e.contains("detials"), "{e}");
        let e = Scene::parse(
            &DEFAULT_SCENE.replace("[50.0, 50.0]", "[50.0, -5.0]"),
            "s.toml",
        )
        .err()
        .unwrap()
        .to_string();
        assert!(e.contains("tile_mm[1]"), "{e}");
        let long = format!("name = \"{}\"", "n".repeat(MAX_NAME + 1));
        let e = Scene::parse(
            &DEFAULT_SCENE.replace("name = \"aniso-ward-panel\"", &long),
            "s.toml",
        )
        .err()
        .unwrap()
        .to_string();
        assert!(e.contains("name") && e.contains("at most"), "{e}");
        let e = Scene::parse(
            &DEFAULT_SCENE.replace("details = 2", "details = \"two\""),
            "s.toml",
        )
        .err()
        .unwrap()
        .to_string();
        assert!(e.contains("s.toml") && e.contains("details"), "{e}");
        // Whole numbers out of range name their key (a huge `candidates` used to abort on an
        // allocation of terabytes).
        for (from, to, key) in [
            ("candidates = 40", "candidates = 100000000000", "candidates"),
            ("psi = 4", "psi = 0", "psi"),
            ("psi = 4", "psi = 100000", "psi"),
        ] {
            let e = Scene::parse(&DEFAULT_SCENE.replace(from, to), "s.toml")
                .err()
                .unwrap()
                .to_string();
            assert!(e.contains("s.toml") && e.contains(key), "{to}: {e}");
        }
        let e = Scene::parse(&format!("{DEFAULT_SCENE}\ntriangle_budget = 1\n"), "s.toml")
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("triangle_budget"), "{e}");
        // A black target colour has no scale for the relative error: refused, as by `solve`.
        let e = Scene::parse(
            &format!("{DEFAULT_SCENE}\ncolour = [0.0, 0.0, 0.0]\n"),
            "s.toml",
        )
        .err()
        .unwrap()
        .to_string();
        assert!(
            e.contains("s.toml") && e.contains("colour") && e.contains("not all 0"),
            "{e}"
        );
    }
}
