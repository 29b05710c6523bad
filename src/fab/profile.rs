//! Fabrication profiles (`profiles/fabrication/*.toml`): which machine, tool and material a shop
//! uses, and the limits and cost weights of the fabrication stage. A profile names catalogue
//! entries (`machine = "mill-3axis"`, `tool = "ball-1mm"`, `material = "aluminium-6061"`, see
//! [`super::catalogue`]) and may start from another profile with `extends = "NAME"` (a shipped
//! name or a path relative to the extending file), overriding any keys it sets.
//!
//! Lookup: [`FabPaths::for_scene`] takes `constraints/` (with its `tools.toml`) and
//! `profiles/fabrication/` from the scene's directory, else from the working directory, else the
//! shipped ones at the crate root (`CARGO_MANIFEST_DIR`); a profile name not found in a user's
//! own `profiles/fabrication/` is looked up among the shipped ones next. [`FabPaths::new`] fixes
//! the base directory.

use super::catalogue::{lookup, Catalogue, Machine, StockMaterial, Tool};
use crate::error::{Error, Result};
use crate::tomlfile::{non_negative, parse, positive, read_text};
use serde::Deserialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Where catalogues and shipped profiles live.
#[derive(Debug, Clone, PartialEq)]
pub struct FabPaths {
    pub constraints: PathBuf,
    pub profiles: PathBuf,
    /// Where a profile name that `profiles` lacks is looked up next (the shipped profiles, when
    /// `profiles` is a user's own directory).
    pub fallback_profiles: Option<PathBuf>,
}

impl FabPaths {
    /// `BASE/constraints` and `BASE/profiles/fabrication`.
    pub fn new(base: &Path) -> FabPaths {
        FabPaths {
            constraints: base.join("constraints"),
            profiles: base.join("profiles").join("fabrication"),
            fallback_profiles: None,
        }
    }

    /// [`Self::for_scene`] without a scene: the working directory's, else the shipped ones.
    pub fn default_paths() -> FabPaths {
        Self::for_scene(None)
    }

    /// Each from the scene's directory if it has it (`constraints/tools.toml`,
    /// `profiles/fabrication/`), else from the working directory, else from the crate root (a
    /// shop's own catalogue next to the shipped profiles, or its own profiles with the shipped
    /// catalogue). So a scene moved with its `constraints/` reads the same catalogue from any
    /// working directory. Shipped profile names stay reachable from a user's own profiles
    /// directory.
    pub fn for_scene(scene_dir: Option<&Path>) -> FabPaths {
        let shipped = FabPaths::new(Path::new(env!("CARGO_MANIFEST_DIR")));
        let bases: Vec<FabPaths> = scene_dir
            .map(FabPaths::new)
            .into_iter()
            .chain(std::iter::once(FabPaths::new(Path::new("."))))
            .collect();
        let constraints = bases
            .iter()
            .map(|b| b.constraints.clone())
            .find(|c| c.join("tools.toml").is_file())
            .unwrap_or_else(|| shipped.constraints.clone());
        let own = bases
            .iter()
            .map(|b| b.profiles.clone())
            .find(|p| p.is_dir());
        FabPaths {
            constraints,
            fallback_profiles: own.as_ref().map(|_| shipped.profiles.clone()),
            profiles: own.unwrap_or(shipped.profiles),
        }
    }
    /// Names of the profiles in `profiles` (file stems), sorted.
    pub fn shipped_profiles(&self) -> Result<Vec<String>> {
        profile_names(&self.profiles)
    }
}

/// Names of the profiles in `dir` (file stems), sorted.
fn profile_names(dir: &Path) -> Result<Vec<String>> {
    let rd =
        std::fs::read_dir(dir).map_err(|e| Error::io(dir, "list the profiles directory", e))?;
    let mut v: Vec<String> = rd
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .filter_map(|p| p.file_stem().map(|s| s.to_string_lossy().into_owned()))
        .collect();
    v.sort();
    Ok(v)
}

/// A resolved, validated profile.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Profile {
    /// The name it was loaded by (file stem).
    pub name: String,
    /// The files read, the profile first, then what it extends.
    pub files: Vec<PathBuf>,
    /// The catalogue files its machine, tool and material come from.
    pub catalogues: Vec<PathBuf>,
    pub description: String,
    pub machine_name: String,
    pub machine: Machine,
    /// The cutter (mills only).
    pub tool: Option<Tool>,
    pub material: StockMaterial,
    /// Raster stepover of the finishing pass (mills only).
    pub stepover_mm: Option<f64>,
    pub base_thickness_mm: f64,
    /// Thinnest ridge or valley the process makes reliably.
    pub min_feature_mm: f64,
    /// Largest accepted deviation of the made surface, as a fraction of the relief (peak to valley).
    pub max_deviation_frac: f64,
    pub viewing_distance_mm: f64,
    /// Largest angle one period may subtend at the viewing distance.
    pub max_period_arcmin: f64,
    /// Weight of one currency unit of material in the total cost.
    pub weight_material: f64,
    /// Weight of one hour of machine time in the total cost.
    pub weight_time_per_h: f64,
}

#[derive(Deserialize, Default, Clone)]
#[serde(deny_unknown_fields)]
struct Raw {
    extends: Option<String>,
    description: Option<String>,
    machine: Option<String>,
    tool: Option<String>,
    material: Option<String>,
    stepover_mm: Option<f64>,
    base_thickness_mm: Option<f64>,
    min_feature_mm: Option<f64>,
    max_deviation_frac: Option<f64>,
    viewing_distance_mm: Option<f64>,
    max_period_arcmin: Option<f64>,
    weight_material: Option<f64>,
    weight_time_per_h: Option<f64>,
}

/// Child keys override parent keys; `from` records which file set each key.
macro_rules! merge {
    ($child:expr, $parent:expr, $from:expr, $file:expr; $($f:ident),*) => {
        $(
            if $child.$f.is_none() {
                $child.$f = $parent.$f.clone();
            } else {
                $from.insert(stringify!($f), $file.clone());
            }
        )*
    };
}

/// Whether a profile reference is a path (else a shipped profile's name).
pub fn is_path(spec: &str) -> bool {
    spec.ends_with(".toml") || spec.contains('/') || spec.contains('\\')
}

fn resolve_spec(spec: &str, rel_to: Option<&Path>, paths: &FabPaths) -> Result<PathBuf> {
    if is_path(spec) {
        let p = Path::new(spec);
        let p = match rel_to {
            Some(dir) if p.is_relative() => dir.join(p),
            _ => p.to_path_buf(),
        };
        if p.is_dir() {
            return Err(Error::new(
                spec,
                format!(
                    "{} is a directory; expected a profile file (.toml)",
                    p.display()
                ),
            ));
        }
        if !p.is_file() {
            return Err(Error::new(
                spec,
                format!("no such profile file ({})", p.display()),
            ));
        }
        return Ok(p);
    }
    for dir in std::iter::once(&paths.profiles).chain(paths.fallback_profiles.as_ref()) {
        let p = dir.join(format!("{spec}.toml"));
        if p.is_file() {
            return Ok(p);
        }
    }
    let mut known = paths.shipped_profiles().unwrap_or_default();
    if let Some(f) = &paths.fallback_profiles {
        known.extend(profile_names(f).unwrap_or_default());
    }
    let known = known.join(", ");
    Err(Error::new(
        spec,
        format!(
            "no shipped profile of this name in {} (known: {known}); give a path ending in .toml for your own",
            paths.profiles.display()
        ),
    ))
}

/// Load a profile by shipped name (`cnc-ball1-aluminium`) or path, following `extends`.
pub fn load_profile(spec: &str, paths: &FabPaths) -> Result<Profile> {
    let top = resolve_spec(spec, None, paths)?;
    let mut chain: Vec<PathBuf> = Vec::new();
    let mut raws: Vec<Raw> = Vec::new();
    let mut cur = top.clone();
    loop {
        let canon = cur.canonicalize().map_err(|e| Error::io(&cur, "open", e))?;
        if let Some(i) = chain
            .iter()
            .position(|c| c.canonicalize().ok().as_ref() == Some(&canon))
        {
            let cycle: Vec<String> = chain[i..]
                .iter()
                .chain(std::iter::once(&cur))
                .map(|p| p.display().to_string())
                .collect();
            return Err(Error::new(
                chain[chain.len() - 1].display().to_string(),
                format!("key `extends` makes a cycle: {}", cycle.join(" → ")),
            ));
        }
        let raw: Raw = parse(&cur, &read_text(&cur)?)?;
        let next = raw.extends.clone();
        chain.push(cur.clone());
        raws.push(raw);
        match next {
            None => break,
            Some(n) => {
                let dir = cur.parent().map(Path::to_path_buf);
                cur = resolve_spec(&n, dir.as_deref(), paths).map_err(|e| {
                    e.within(format!(
                        "{}: key `extends`",
                        chain[chain.len() - 1].display()
                    ))
                })?;
            }
        }
    }
    // Merge from the root of the chain down to the profile itself.
    let mut from: BTreeMap<&'static str, PathBuf> = BTreeMap::new();
    let mut merged = Raw::default();
    for (raw, file) in raws.iter().zip(&chain).rev() {
        let mut r = raw.clone();
        merge!(r, merged, from, file; description, machine, tool, material, stepover_mm,
               base_thickness_mm, min_feature_mm, max_deviation_frac, viewing_distance_mm,
               max_period_arcmin, weight_material, weight_time_per_h);
        merged = r;
    }
    let cat = Catalogue::load(&paths.constraints)?;
    let name = top
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    build(name, chain, merged, &from, &cat)
}

fn build(
    name: String,
    chain: Vec<PathBuf>,
    r: Raw,
    from: &BTreeMap<&'static str, PathBuf>,
    cat: &Catalogue,
) -> Result<Profile> {
    let top = chain[0].clone();
    let file_of = |k: &str| from.get(k).cloned().unwrap_or_else(|| top.clone());
    let via = if chain.len() > 1 {
        " (in this file or the profiles it extends)".to_string()
    } else {
        String::new()
    };
    let need = |k: &str, v: Option<f64>, what: &str| -> Result<f64> {
        v.ok_or_else(|| {
            Error::new(
                top.display().to_string(),
                format!("missing key `{k}`{via} (expected {what})"),
            )
        })
    };
    let need_s = |k: &str, v: Option<String>, what: &str| -> Result<String> {
        v.ok_or_else(|| {
            Error::new(
                top.display().to_string(),
                format!("missing key `{k}`{via} (expected {what})"),
            )
        })
    };
    let pos = |k: &str, v: f64, unit: &str| positive(&file_of(k), "", k, v, unit);
    let nonneg = |k: &str, v: f64, unit: &str| non_negative(&file_of(k), "", k, v, unit);
    let in_key = |k: &str, e: Error| {
        Error::new(
            file_of(k).display().to_string(),
            format!("key `{k}`: {}", e.message),
        )
    };

    let machine_name = need_s("machine", r.machine.clone(), "a machine of machines.toml")?;
    let machine = lookup(
        &cat.machines,
        "machine",
        &machine_name,
        &cat.dir.join("machines.toml"),
    )
    .map_err(|e| in_key("machine", e))?
    .clone();
    let is_mill = matches!(machine, Machine::Mill(_));
    // A mill-only key that a profile up the chain set before a profile further down changed the
    // machine to a printer belongs to the machine it replaced: it is dropped, not an error (a
    // profile cannot unset a key it inherits). Set in the same file as the printer, or below
    // it, it is the user's mistake and stays an error.
    let depth = |k: &str| chain.iter().position(|c| *c == file_of(k));
    let stale = |k: &str| !is_mill && depth(k) > depth("machine");
    let mut r = r;
    if stale("tool") {
        r.tool = None;
    }
    if stale("stepover_mm") {
        r.stepover_mm = None;
    }
    let tool = match (&r.tool, is_mill) {
        (Some(t), true) => Some(
            lookup(&cat.tools, "tool", t, &cat.dir.join("tools.toml"))
                .map_err(|e| in_key("tool", e))?
                .clone(),
        ),
        (None, true) => {
            need_s("tool", None, "a tool of tools.toml, e.g. \"ball-1mm\"")?;
            None
        }
        (Some(_), false) => {
            return Err(Error::new(
                file_of("tool").display().to_string(),
                format!(
                    "key `tool` does not apply to a {} printer (remove it)",
                    machine.kind()
                ),
            ))
        }
        (None, false) => None,
    };
    let material_name = need_s(
        "material",
        r.material.clone(),
        "a material of materials.toml",
    )?;
    let material = lookup(
        &cat.materials,
        "material",
        &material_name,
        &cat.dir.join("materials.toml"),
    )
    .map_err(|e| in_key("material", e))?
    .clone();
    if !material.processes.iter().any(|p| p == machine.kind()) {
        return Err(Error::new(
            file_of("material").display().to_string(),
            format!(
                "key `material`: \"{material_name}\" is not worked by a {} (it is for {})",
                machine.kind(),
                material.processes.join(", ")
            ),
        ));
    }
    let stepover_mm = match (r.stepover_mm, &tool) {
        (Some(s), Some(t)) => {
            let s = pos("stepover_mm", s, "mm")?;
            if s > t.diameter_mm {
                return Err(Error::new(
                    file_of("stepover_mm").display().to_string(),
                    format!(
                        "key `stepover_mm` = {s} is wider than the tool ({} mm); expected at most the tool diameter",
                        t.diameter_mm
                    ),
                ));
            }
            Some(s)
        }
        (None, Some(_)) => Some(need(
            "stepover_mm",
            None,
            "the finishing raster stepover in mm",
        )?),
        (Some(_), None) => {
            return Err(Error::new(
                file_of("stepover_mm").display().to_string(),
                "key `stepover_mm` applies to mills only (remove it)",
            ))
        }
        (None, None) => None,
    };
    let frac = need(
        "max_deviation_frac",
        r.max_deviation_frac,
        "a fraction of the relief in (0, 1]",
    )?;
    if !(frac > 0.0 && frac <= 1.0) {
        return Err(Error::new(
            file_of("max_deviation_frac").display().to_string(),
            format!(
                "key `max_deviation_frac` must be in (0, 1] (a fraction of the relief), got {frac}"
            ),
        ));
    }
    Ok(Profile {
        name,
        description: r.description.clone().unwrap_or_default(),
        machine_name,
        machine,
        tool,
        material,
        stepover_mm,
        base_thickness_mm: pos(
            "base_thickness_mm",
            need("base_thickness_mm", r.base_thickness_mm, "a number of mm")?,
            "mm",
        )?,
        min_feature_mm: pos(
            "min_feature_mm",
            need("min_feature_mm", r.min_feature_mm, "a number of mm")?,
            "mm",
        )?,
        max_deviation_frac: frac,
        viewing_distance_mm: pos(
            "viewing_distance_mm",
            need(
                "viewing_distance_mm",
                r.viewing_distance_mm,
                "a number of mm",
            )?,
            "mm",
        )?,
        max_period_arcmin: pos(
            "max_period_arcmin",
            need(
                "max_period_arcmin",
                r.max_period_arcmin,
                "an angle in arc minutes",
            )?,
            "arc minutes",
        )?,
        weight_material: nonneg(
            "weight_material",
            need(
                "weight_material",
                r.weight_material,
                "a weight >= 0 per currency unit",
            )?,
            "per currency unit",
        )?,
        weight_time_per_h: nonneg(
            "weight_time_per_h",
            need(
                "weight_time_per_h",
                r.weight_time_per_h,
                "a weight >= 0 per hour",
            )?,
            "per hour",
        )?,
        files: chain,
        catalogues: ["tools.toml", "machines.toml", "materials.toml"]
            .iter()
            .map(|f| cat.dir.join(f))
            .collect(),
    })
}
