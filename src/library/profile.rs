//! Library size profiles: the TOML files in `profiles/library/` that say what a library holds
//! (which generators, textures and material models, how many of each, over which parameter
//! ranges), how finely each item is tabulated, and how hard the compression works.
//!
//! A profile is a name (a shipped file `profiles/library/<name>.toml`, see [`shipped_dirs`]) or a
//! path. Unknown keys,
//! missing keys, wrong types and out-of-range values are errors naming the file and the key.

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A parameter range `[lo, hi]`, sampled uniformly (or log-uniformly when listed in `log`).
pub type Range2 = [f64; 2];

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LibraryProfile {
    /// Profile name (written into the manifest).
    pub name: String,
    /// Seed of every random choice of the build.
    pub seed: u64,
    /// Items per chunk: the unit of resumption and of sharding.
    pub chunk: usize,
    pub geometry: GeometrySection,
    pub material: MaterialSection,
    pub compression: CompressionSection,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GeometrySection {
    /// Samples per side of every heightfield (the generators' `n`).
    pub resolution: usize,
    /// View grid of the binned BVNDF: polar and azimuthal nodes.
    pub view_theta: usize,
    pub view_phi: usize,
    /// Normal grid side `G` (G × G nodes).
    pub normal_grid: usize,
    /// View rays per view node.
    pub rays: usize,
    /// Normal clusters of each geometry's light lobes ([`crate::lightlobes`]), the per-item data
    /// the solvers re-rank with.
    #[serde(default = "default_lobe_clusters")]
    pub lobe_clusters: usize,
    /// How the light-lobe records are stored: `half` (the default: moments about each
    /// cluster's centre in `f16`, [`crate::lobecodec`], half the bytes, which a search reading
    /// records from the disk waits for) or `single` (the `f32` records). Left out of the
    /// canonical profile when `half`, so profiles and libraries from before the key keep their
    /// hashes (such libraries hold `f32` records, which are read as they are; `biscale library
    /// refit --half-lobes` converts them).
    #[serde(default, skip_serializing_if = "LobePrecision::is_half")]
    pub lobe_precision: LobePrecision,
    /// How the binned BVNDF columns are stored: `half` (the default, `f16`) or `byte` (the
    /// 8-bit float of [`crate::uf8`], within 3.1 % of each entry, half the bytes: the `paper`
    /// profile's 56 GB matrix in 28 GB). Left out of the canonical profile when `half`, so
    /// profiles and libraries from before the key keep their hashes.
    #[serde(default, skip_serializing_if = "GammaPrecision::is_half")]
    pub gamma_precision: GammaPrecision,
    #[serde(default)]
    pub family: Vec<GeometryFamily>,
}

fn default_lobe_clusters() -> usize {
    16
}

/// The stored precision of the light-lobe records (`geometry.lobe_precision`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LobePrecision {
    #[default]
    Half,
    Single,
}

impl LobePrecision {
    pub fn is_half(&self) -> bool {
        *self == LobePrecision::Half
    }
}

/// The stored precision of the binned BVNDF columns (`geometry.gamma_precision`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GammaPrecision {
    #[default]
    Half,
    Byte,
}

impl GammaPrecision {
    pub fn is_half(&self) -> bool {
        *self == GammaPrecision::Half
    }
    /// The array element type of `geometry/gamma.bsa`.
    pub fn dtype(self) -> crate::store::Dtype {
        match self {
            GammaPrecision::Half => crate::store::Dtype::F16,
            GammaPrecision::Byte => crate::store::Dtype::UF8,
        }
    }
    /// A binned column in this precision, as the array's bytes.
    pub fn encode(self, col: &[f32]) -> Vec<u8> {
        match self {
            GammaPrecision::Half => {
                let h: Vec<half::f16> = col.iter().map(|&v| half::f16::from_f32(v)).collect();
                bytemuck::cast_slice(&h).to_vec()
            }
            GammaPrecision::Byte => crate::uf8::encode_all(col),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GeometryFamily {
    /// A generator name of `biscale forward --help` (`vgroove`, `bricks`, ..., `texture`).
    pub generator: String,
    /// Items drawn from this family.
    pub count: usize,
    /// Parameter ranges; integer parameters (`count`, `cells`, `octaves`, `patch`) are rounded.
    #[serde(default, deserialize_with = "crate::tomlfile::exact_len::ranges")]
    pub params: BTreeMap<String, Range2>,
    /// Parameters sampled log-uniformly.
    #[serde(default)]
    pub log: Vec<String>,
    /// Texture families: use the built-in procedural textures.
    #[serde(default)]
    pub builtin_textures: bool,
    /// Texture families: directories of PNG images (relative ones are taken against the profile
    /// file's directory and stored absolute).
    #[serde(default)]
    pub texture_dirs: Vec<PathBuf>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MaterialSection {
    /// Prefiltered table resolution and quadrature samples per entry.
    pub prefilter: PrefilterSection,
    /// Colour-shifted variants per distinct BRDF (besides its own colour).
    pub colours: usize,
    /// Lambertian albedos mixed into every analytic lobe (0 = the pure lobe).
    pub lambert: Vec<f64>,
    /// Directories of MERL `.binary` files (relative ones are taken against the profile file's
    /// directory and stored absolute).
    #[serde(default)]
    pub merl_dirs: Vec<PathBuf>,
    #[serde(default)]
    pub family: Vec<MaterialFamily>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrefilterSection {
    pub n_half: usize,
    pub n_theta_mu: usize,
    pub n_phi_mu: usize,
    pub samples: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MaterialFamily {
    /// A lobe model of the material grammar: `ggx`, `beckmann`, `ct`, `ward`, `blinn`, or
    /// `lambert` (pure matte materials, `params = { albedo = [lo, hi] }`, not mixed with
    /// `material.lambert`).
    pub model: String,
    /// Distinct parameter draws (each mixed with every `lambert` albedo).
    pub count: usize,
    #[serde(default, deserialize_with = "crate::tomlfile::exact_len::ranges")]
    pub params: BTreeMap<String, Range2>,
    #[serde(default)]
    pub log: Vec<String>,
}

fn initial_rank() -> usize {
    64
}
fn is_initial_rank(v: &usize) -> bool {
    *v == 64
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CompressionSection {
    /// Energy kept by the material SVD (paper: 0.999).
    pub material_energy: f64,
    /// Energy kept by a second, finer selection of material representatives that only the
    /// material solver's search reads (`material/search-*.bsa`); absent: none, and the material
    /// solver searches through the representatives above. The shipped profiles keep 0.99999:
    /// at 0.999 the paper's 14 representatives rank sharp materials on rough surfaces poorly
    /// (docs/solvers.md), while the joint search's cost grows with the square of the
    /// representatives it combines, so it keeps the coarser set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material_search_energy: Option<f64>,
    /// Energy kept by the geometry randomized SVD (paper: 0.99).
    pub geometry_energy: f64,
    /// CX relative error threshold (paper: 0.015).
    pub cx_error: f64,
    /// `pivoted-qr` (deterministic) or `leverage` (Drineas et al. 2008).
    pub cx_method: String,
    pub oversample: usize,
    pub power_iters: usize,
    pub max_rank: usize,
    /// Columns per streamed chunk of the randomized SVD.
    pub stream_chunk: usize,
    /// Rank the randomized SVD's first sketch is sized for (a good guess saves a restart).
    #[serde(default = "initial_rank", skip_serializing_if = "is_initial_rank")]
    pub initial_rank: usize,
    /// Geometries (evenly spaced) on which the randomized SVD finds the geometry basis; every
    /// geometry is then projected on it in one pass (`lowrank::RsvdConfig::pilot`). Absent: the
    /// randomized SVD runs on all geometries (`2 + 2 power_iters` passes over the matrix).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub geometry_pilot: Option<usize>,
}

/// Most entries of one item's table (a geometry's binned column or light-lobe record, a
/// material's prefiltered table): 64 MB in `f32`.
const MAX_ENTRIES: usize = 1 << 24;

/// Most items of one kind in a profile (the paper's library has 164,431 geometries).
const MAX_ITEMS: usize = 100_000_000;

/// Where shipped library profiles are looked for, in order (the first holding `NAME.toml` wins):
/// `profiles/library/` of the source tree this binary was built from, `./profiles/library/`
/// under the current directory, and next to the executable: `<exe dir>/profiles/library/`, then
/// `profiles/library/` two directories above it (the checkout of a `target/release/biscale`).
pub fn shipped_dirs() -> Vec<PathBuf> {
    let mut dirs = vec![Path::new(env!("CARGO_MANIFEST_DIR")).join("profiles/library")];
    if let Ok(cwd) = std::env::current_dir() {
        dirs.push(cwd.join("profiles/library"));
    }
    if let Some(exe_dir) = std::env::current_exe()
        .ok()
        .and_then(|e| e.parent().map(Path::to_path_buf))
    {
        dirs.push(exe_dir.join("profiles/library"));
        if let Some(up2) = exe_dir.parent().and_then(Path::parent) {
            dirs.push(up2.join("profiles/library"));
        }
    }
    let mut out: Vec<PathBuf> = Vec::new();
    for d in dirs {
        if !out.contains(&d) {
            out.push(d);
        }
    }
    out
}

/// The first of `dirs` holding `NAME.toml`; the error lists every place looked at.
pub fn find_shipped(name: &str, dirs: &[PathBuf]) -> Result<PathBuf> {
    let file = format!("{name}.toml");
    if let Some(f) = dirs.iter().map(|d| d.join(&file)).find(|f| f.is_file()) {
        return Ok(f);
    }
    let names = names_in(dirs);
    Err(Error::new(
        "--profile",
        format!(
            "no library profile '{name}': looked for {file} in {} (shipped profiles found: {}); \
             or give a path to a .toml file",
            dirs.iter()
                .map(|d| d.display().to_string())
                .collect::<Vec<_>>()
                .join(", "),
            if names.is_empty() {
                "none".to_string()
            } else {
                names.join(", ")
            }
        ),
    ))
}

fn names_in(dirs: &[PathBuf]) -> Vec<String> {
    let mut v: Vec<String> = dirs
        .iter()
        .filter_map(|d| std::fs::read_dir(d).ok())
        .flat_map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter_map(|e| {
                    let p = e.path();
                    (p.extension()? == "toml")
                        .then(|| p.file_stem().map(|s| s.to_string_lossy().into_owned()))
                        .flatten()
                })
                .collect::<Vec<_>>()
        })
        .collect();
    v.sort();
    v.dedup();
    v
}

/// Names of the shipped library profiles (over every place [`shipped_dirs`] lists).
pub fn shipped_names() -> Vec<String> {
    names_in(&shipped_dirs())
}

/// `d` made absolute: relative paths are taken against `base` (itself made absolute against
/// the current directory).
fn absolute_dir(d: &Path, base: &Path, ctx: &str) -> Result<PathBuf> {
    let joined = if d.is_absolute() {
        d.to_path_buf()
    } else {
        base.join(d)
    };
    std::path::absolute(&joined)
        .map_err(|e| Error::io(&joined, "make the path absolute", e).within(ctx))
}

/// Whether a library profile reference is a path (a `.toml` file or more than one path
/// component), else a shipped profile's name.
pub fn is_path(name_or_path: &str) -> bool {
    let p = Path::new(name_or_path);
    p.extension().is_some_and(|e| e == "toml") || p.components().count() > 1 || p.is_file()
}

impl LibraryProfile {
    /// Load a profile by shipped name (`tiny`, `default`, `paper`) or by path ([`is_path`]).
    /// Relative `texture_dirs` and `merl_dirs` are resolved against the profile file's
    /// directory here, once, so the profile (and the `profile.toml` a build stores) holds
    /// absolute paths.
    pub fn load(name_or_path: &str) -> Result<(Self, PathBuf)> {
        let p = Path::new(name_or_path);
        let path = if is_path(name_or_path) {
            p.to_path_buf()
        } else {
            find_shipped(name_or_path, &shipped_dirs())?
        };
        let text = std::fs::read_to_string(&path)
            .map_err(|e| Error::io(&path, "read the library profile", e))?;
        let ctx = path.display().to_string();
        let mut prof = Self::parse(&text, &ctx)?;
        let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
        prof.resolve_dirs(&base).map_err(|e| e.within(&ctx))?;
        Ok((prof, path))
    }

    /// Make every relative `texture_dirs` / `merl_dirs` entry absolute, against `base` (the
    /// profile file's directory). Absolute entries are kept as they are.
    pub fn resolve_dirs(&mut self, base: &Path) -> Result<()> {
        for (i, f) in self.geometry.family.iter_mut().enumerate() {
            for d in f.texture_dirs.iter_mut() {
                *d = absolute_dir(
                    d,
                    base,
                    format!("geometry.family[{i}].texture_dirs").as_str(),
                )?;
            }
        }
        for d in self.material.merl_dirs.iter_mut() {
            *d = absolute_dir(d, base, "material.merl_dirs")?;
        }
        Ok(())
    }

    /// Whether every `texture_dirs` / `merl_dirs` entry is absolute.
    pub fn dirs_are_absolute(&self) -> bool {
        self.geometry
            .family
            .iter()
            .flat_map(|f| &f.texture_dirs)
            .chain(&self.material.merl_dirs)
            .all(|d| d.is_absolute())
    }

    /// Parse and validate profile text; `ctx` names the file in errors.
    pub fn parse(text: &str, ctx: &str) -> Result<Self> {
        let prof: LibraryProfile = crate::tomlfile::parse(Path::new(ctx), text)?;
        prof.validate().map_err(|e| e.within(ctx))?;
        Ok(prof)
    }

    fn validate(&self) -> Result<()> {
        let name_ok = !self.name.is_empty()
            && self.name.len() <= 64
            && !self.name.starts_with('.')
            && self
                .name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'));
        if !name_ok {
            return Err(Error::new(
                "name",
                format!(
                    "expected 1 to 64 letters, digits, '-', '_' or '.' (not first), got {:?}: \
                     the name becomes a directory of the cache",
                    self.name
                ),
            ));
        }
        // Bounds keep a typo from asking for terabytes: each is far beyond what a build on
        // one machine or a cluster can use.
        let pos = |key: &str, v: usize, min: usize, max: usize| {
            if v < min || v > max {
                Err(Error::new(
                    key,
                    format!("expected an integer in [{min}, {max}], got {v}"),
                ))
            } else {
                Ok(())
            }
        };
        pos("chunk", self.chunk, 1, 1 << 16)?;
        let g = &self.geometry;
        pos("geometry.resolution", g.resolution, 8, 2048)?;
        pos("geometry.view_theta", g.view_theta, 2, 64)?;
        pos("geometry.view_phi", g.view_phi, 3, 128)?;
        pos("geometry.normal_grid", g.normal_grid, 3, 64)?;
        pos("geometry.rays", g.rays, 1, 1 << 20)?;
        pos("geometry.lobe_clusters", g.lobe_clusters, 1, 64)?;
        // One geometry's binned column (f16) and light-lobe record (in floats, whatever their
        // precision), as GammaLayout and lightlobes::record_len size them for the 7 lights.
        let views = g.view_theta * g.view_phi;
        let column = 7 * views * g.normal_grid * g.normal_grid;
        let record = g.lobe_clusters * (5 + views * 3 + 7 * views * 9);
        if column > MAX_ENTRIES || record > MAX_ENTRIES {
            return Err(Error::new(
                "geometry",
                format!(
                    "view_theta × view_phi × normal_grid² and lobe_clusters make {column} binned \
                     entries and a {record}-float light-lobe record per geometry; at most \
                     {MAX_ENTRIES} each"
                ),
            ));
        }
        let count = |families: usize, total: usize, key: &str| {
            if total > MAX_ITEMS {
                Err(Error::new(
                    key,
                    format!(
                        "the {families} families' counts add up to {total}; at most {MAX_ITEMS}"
                    ),
                ))
            } else {
                Ok(())
            }
        };
        count(g.family.len(), self.geometry_count(), "geometry.family")?;
        count(
            self.material.family.len(),
            self.material
                .family
                .iter()
                .map(|f| f.count.saturating_mul(self.material.lambert.len().max(1)))
                .fold(0usize, usize::saturating_add),
            "material.family",
        )?;
        for (i, f) in g.family.iter().enumerate() {
            let key = format!("geometry.family[{i}]");
            let names: Vec<&str> = crate::generators::list().iter().map(|x| x.0).collect();
            if !names.contains(&f.generator.as_str()) {
                return Err(Error::new(
                    format!("{key}.generator"),
                    format!(
                        "unknown generator '{}' (expected one of: {})",
                        f.generator,
                        names.join(", ")
                    ),
                ));
            }
            check_ranges(&key, &f.params, &f.log)?;
            if f.generator == "texture" && !f.builtin_textures && f.texture_dirs.is_empty() {
                return Err(Error::new(
                    key,
                    "a texture family needs builtin_textures = true or texture_dirs = [...]",
                ));
            }
        }
        let m = &self.material;
        pos("material.prefilter.n_half", m.prefilter.n_half, 2, 256)?;
        pos(
            "material.prefilter.n_theta_mu",
            m.prefilter.n_theta_mu,
            2,
            512,
        )?;
        pos("material.prefilter.n_phi_mu", m.prefilter.n_phi_mu, 2, 256)?;
        pos(
            "material.prefilter.samples",
            m.prefilter.samples,
            1,
            1 << 16,
        )?;
        let table = m.prefilter.n_half
            * crate::prefilter::KAPPAS.len()
            * m.prefilter.n_theta_mu
            * m.prefilter.n_phi_mu;
        if table > MAX_ENTRIES {
            return Err(Error::new(
                "material.prefilter",
                format!(
                    "n_half × {} kappas × n_theta_mu × n_phi_mu = {table} entries per material; \
                     at most {MAX_ENTRIES}",
                    crate::prefilter::KAPPAS.len()
                ),
            ));
        }
        pos("material.colours", m.colours, 0, 1 << 16)?;
        for (i, a) in m.lambert.iter().enumerate() {
            if !(0.0..=1.0).contains(a) {
                return Err(Error::new(
                    format!("material.lambert[{i}]"),
                    format!("expected an albedo in [0, 1], got {a}"),
                ));
            }
        }
        if m.lambert.is_empty() {
            return Err(Error::new(
                "material.lambert",
                "expected at least one albedo (0 for the pure lobes)",
            ));
        }
        for (i, f) in m.family.iter().enumerate() {
            let key = format!("material.family[{i}]");
            const MODELS: [&str; 6] = ["ggx", "beckmann", "ct", "ward", "blinn", "lambert"];
            if !MODELS.contains(&f.model.as_str()) {
                return Err(Error::new(
                    format!("{key}.model"),
                    format!(
                        "unknown model '{}' (expected one of: {})",
                        f.model,
                        MODELS.join(", ")
                    ),
                ));
            }
            check_ranges(&key, &f.params, &f.log)?;
        }
        let c = &self.compression;
        for (k, v) in [
            ("compression.material_energy", c.material_energy),
            ("compression.geometry_energy", c.geometry_energy),
        ] {
            if !(v > 0.0 && v <= 1.0) {
                return Err(Error::new(
                    k,
                    format!("expected a fraction in (0, 1], got {v}"),
                ));
            }
        }
        if let Some(v) = c.material_search_energy {
            if !(v >= c.material_energy && v <= 1.0) {
                return Err(Error::new(
                    "compression.material_search_energy",
                    format!(
                        "expected a fraction in [material_energy = {}, 1], got {v}",
                        c.material_energy
                    ),
                ));
            }
        }
        if !(c.cx_error > 0.0 && c.cx_error < 1.0) {
            return Err(Error::new(
                "compression.cx_error",
                format!("expected a fraction in (0, 1), got {}", c.cx_error),
            ));
        }
        if c.cx_method != "pivoted-qr" && c.cx_method != "leverage" {
            return Err(Error::new(
                "compression.cx_method",
                format!(
                    "expected \"pivoted-qr\" or \"leverage\", got \"{}\"",
                    c.cx_method
                ),
            ));
        }
        pos("compression.max_rank", c.max_rank, 1, 100_000)?;
        pos("compression.stream_chunk", c.stream_chunk, 1, 1 << 20)?;
        pos("compression.oversample", c.oversample, 0, 4096)?;
        pos("compression.power_iters", c.power_iters, 0, 64)?;
        pos("compression.initial_rank", c.initial_rank, 1, 100_000)?;
        if let Some(p) = c.geometry_pilot {
            pos("compression.geometry_pilot", p, 1, MAX_ITEMS)?;
        }
        // Every family's range ends make valid items now, before any directory is touched
        // (a draw between them is then valid too, for the generators' and materials' bounds).
        crate::library::items::check_range_ends(self)
    }

    /// Number of geometry items.
    pub fn geometry_count(&self) -> usize {
        self.geometry.family.iter().map(|f| f.count).sum()
    }

    /// Canonical TOML of the profile (stored in the library; its hash names the cache entry).
    pub fn canonical(&self) -> String {
        toml::to_string(self).unwrap_or_default()
    }

    /// Short hash of the canonical profile.
    pub fn hash(&self) -> String {
        format!(
            "{:016x}",
            xxhash_rust::xxh3::xxh3_64(self.canonical().as_bytes())
        )
    }
}

fn check_ranges(key: &str, params: &BTreeMap<String, Range2>, log: &[String]) -> Result<()> {
    for (k, [lo, hi]) in params {
        if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
            return Err(Error::new(
                format!("{key}.params.{k}"),
                format!("expected [lo, hi] with lo <= hi, got [{lo}, {hi}]"),
            ));
        }
    }
    for k in log {
        match params.get(k) {
            Some([lo, _]) if *lo > 0.0 => {}
            Some(_) => {
                return Err(Error::new(
                    format!("{key}.log"),
                    format!("'{k}' is log-sampled, so its range must be > 0"),
                ))
            }
            None => {
                return Err(Error::new(
                    format!("{key}.log"),
                    format!("'{k}' has no range in params"),
                ))
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testdir::TestDir;

    #[test]
    fn shipped_profiles_load() {
        for n in [
            "tiny",
            "default",
            "paper16",
            "paper4",
            "paper2",
            "paper-materials",
            "paper",
        ] {
            let (p, _) = LibraryProfile::load(n).unwrap();
            assert_eq!(p.name, n);
            assert!(p.geometry_count() > 0);
        }
        let (paper, _) = LibraryProfile::load("paper").unwrap();
        assert!(
            paper.geometry_count() >= 164_431,
            "{}",
            paper.geometry_count()
        );
        // `paper-materials` has the paper's material library, draw for draw.
        let (pm, _) = LibraryProfile::load("paper-materials").unwrap();
        assert_eq!(pm.material, paper.material);
        // The same compression, but for the geometry pilot: its geometries are few.
        assert_eq!(
            pm.compression,
            CompressionSection {
                geometry_pilot: None,
                ..paper.compression.clone()
            }
        );
        assert_eq!(pm.geometry.family.len(), paper.geometry.family.len());
        // The paper's library and its fractions keep their binned columns in one byte (to fit
        // on one machine's disk); the smaller profiles in half precision.
        for n in ["paper", "paper2", "paper4"] {
            let (p, _) = LibraryProfile::load(n).unwrap();
            assert_eq!(p.geometry.gamma_precision, GammaPrecision::Byte, "{n}");
            assert!(p.canonical().contains("gamma_precision = \"byte\""), "{n}");
        }
        for n in ["tiny", "default", "paper16"] {
            let (p, _) = LibraryProfile::load(n).unwrap();
            assert_eq!(p.geometry.gamma_precision, GammaPrecision::Half, "{n}");
            assert!(!p.canonical().contains("gamma_precision"), "{n}");
        }
    }

    #[test]
    fn bad_profiles_name_the_key() {
        let (tiny, path) = LibraryProfile::load("tiny").unwrap();
        let text = std::fs::read_to_string(path).unwrap();
        let e = LibraryProfile::parse(&text.replace("chunk =", "chunkk ="), "p.toml")
            .err()
            .unwrap();
        assert!(
            e.to_string().contains("p.toml") && e.to_string().contains("chunkk"),
            "{e}"
        );
        let e = LibraryProfile::parse(&text.replace("normal_grid = ", "normal_grid = -"), "p.toml")
            .err()
            .unwrap();
        assert!(e.to_string().contains("p.toml"), "{e}");
        let quarter = text.replace(
            "[geometry]\n",
            "[geometry]\ngamma_precision = \"quarter\"\n",
        );
        let e = LibraryProfile::parse(&quarter, "p.toml").err().unwrap();
        assert!(
            e.to_string().contains("p.toml") && e.to_string().contains("gamma_precision"),
            "{e}"
        );
        let bad = tiny
            .canonical()
            .replace("cx_method = \"pivoted-qr\"", "cx_method = \"svd\"");
        let e = LibraryProfile::parse(&bad, "p.toml").err().unwrap();
        assert!(e.to_string().contains("compression.cx_method"), "{e}");
        let e = LibraryProfile::load("huge").err().unwrap();
        assert!(e.to_string().contains("tiny"), "{e}");
        assert!(e.to_string().contains("huge.toml"), "{e}");
        for d in shipped_dirs() {
            assert!(e.to_string().contains(&d.display().to_string()), "{e}");
        }
    }

    #[test]
    fn bad_sizes_names_and_range_ends_fail_when_the_profile_is_read() {
        let (tiny, _) = LibraryProfile::load("tiny").unwrap();
        let text = tiny.canonical();
        let err_all = |edits: &[(&str, &str)]| {
            let mut t = text.clone();
            for (from, to) in edits {
                assert!(t.contains(from), "{from}");
                t = t.replacen(from, to, 1);
            }
            LibraryProfile::parse(&t, "p.toml")
                .err()
                .map(|e| e.to_string())
                .unwrap_or_default()
        };
        let err = |from: &str, to: &str| err_all(&[(from, to)]);
        // Sizes that would ask for terabytes (or hang) are refused, naming the key.
        let e = err("normal_grid = 12", "normal_grid = 100000");
        assert!(
            e.contains("p.toml") && e.contains("geometry.normal_grid"),
            "{e}"
        );
        let e = err("colours = 8", "colours = 100000000000");
        assert!(e.contains("material.colours"), "{e}");
        let e = err_all(&[
            ("view_theta = 8", "view_theta = 64"),
            ("normal_grid = 12", "normal_grid = 64"),
        ]);
        assert!(e.contains("geometry") && e.contains("entries"), "{e}");
        // The name becomes a cache directory: no path separators.
        let e = err("name = \"tiny\"", "name = \"../../evil\"");
        assert!(e.contains("p.toml: name:"), "{e}");
        assert!(err("name = \"tiny\"", "name = \"\"").contains("name:"));
        // A range end a generator or a model refuses, or a mistyped key, fails now.
        let e = err("period = [4.0, 32.0]", "period = [0.0, 32.0]");
        assert!(
            e.contains("geometry.family[0].params")
                && e.contains("low end")
                && e.contains("period"),
            "{e}"
        );
        let e = err("period = [4.0, 32.0]", "periodd = [4.0, 32.0]");
        assert!(e.contains("unknown key 'periodd'"), "{e}");
        let e = err("f0 = [0.04, 1.0]", "f0 = [0.04, 1.5]");
        assert!(
            e.contains("material.family[0].params") && e.contains("high end") && e.contains("f0"),
            "{e}"
        );
        // The shipped profile itself is fine.
        assert!(LibraryProfile::parse(&text, "p.toml").is_ok());
    }

    #[test]
    fn shipped_lookup_takes_the_first_directory_holding_the_name() {
        let root = TestDir::new("shipped");
        let (a, b, c) = (root.join("a"), root.join("b"), root.join("c"));
        for d in [&a, &b, &c] {
            std::fs::create_dir_all(d).unwrap();
        }
        std::fs::write(b.join("x.toml"), "b").unwrap();
        std::fs::write(c.join("x.toml"), "c").unwrap();
        std::fs::write(c.join("y.toml"), "c").unwrap();
        let dirs = vec![a.clone(), b.clone(), c.clone()];
        assert_eq!(find_shipped("x", &dirs).unwrap(), b.join("x.toml"));
        assert_eq!(find_shipped("y", &dirs).unwrap(), c.join("y.toml"));
        let e = find_shipped("z", &dirs).err().unwrap().to_string();
        for d in &dirs {
            assert!(e.contains(&d.display().to_string()), "{e}");
        }
        assert!(e.contains("z.toml") && e.contains("x, y"), "{e}");
        // The current directory and the executable's surroundings are searched too.
        let all = shipped_dirs();
        let cwd = std::env::current_dir().unwrap().join("profiles/library");
        assert!(all.contains(&cwd), "{all:?}");
        let exe = std::env::current_exe().unwrap();
        let exe_dir = exe.parent().unwrap();
        let up2 = exe_dir.parent().unwrap().parent().unwrap();
        assert!(all.contains(&up2.join("profiles/library")), "{all:?}");
    }

    #[test]
    fn relative_dirs_become_absolute_against_the_profile_file() {
        let (mut p, _) = LibraryProfile::load("tiny").unwrap();
        assert!(p.dirs_are_absolute());
        let h = p.hash();
        p.resolve_dirs(Path::new("/elsewhere")).unwrap();
        assert_eq!(p.hash(), h, "profiles without directories keep their hash");
        p.material.merl_dirs = vec!["merl".into(), "/abs/merl".into()];
        p.geometry.family[0].texture_dirs = vec!["../tex".into()];
        assert!(!p.dirs_are_absolute());
        p.resolve_dirs(Path::new("/data/profiles")).unwrap();
        assert!(p.dirs_are_absolute());
        assert_eq!(
            p.material.merl_dirs,
            vec![
                PathBuf::from("/data/profiles/merl"),
                PathBuf::from("/abs/merl")
            ]
        );
        assert!(p.canonical().contains("/data/profiles/merl"));
    }
}
