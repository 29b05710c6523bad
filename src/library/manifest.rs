//! The library manifest (`manifest.json`): format version, tool version, profile and seed, item
//! counts, array shapes, compression results, every file with its checksum, and the build's times
//! and peak memory. It is written last, so its presence marks a complete library.

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

pub const MANIFEST_VERSION: u32 = 3;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub format: String,
    pub version: u32,
    pub tool_version: String,
    pub profile: String,
    pub profile_hash: String,
    pub seed: u64,
    pub geometries: usize,
    pub materials: usize,
    pub colours_per_material: usize,
    /// Length of one geometry's binned BVNDF column.
    pub gamma_rows: usize,
    /// Length of one material's prefiltered table.
    pub table_len: usize,
    pub material: CompressionReport,
    /// The material solver's finer selection (`material/search-*.bsa`), when the profile asks
    /// for one (`compression.material_search_energy`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material_search: Option<CompressionReport>,
    pub geometry: CompressionReport,
    pub files: Vec<ArrayEntry>,
    /// Times and memory of the build (the only part that differs between identical builds).
    pub build: StageTimes,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArrayEntry {
    pub path: String,
    pub checksum: String,
    pub bytes: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CompressionReport {
    pub rank: usize,
    pub energy_kept: f64,
    /// Full passes over the matrix.
    pub passes: usize,
    /// Columns of the pilot the geometry basis was found on (`compression.geometry_pilot`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pilot_columns: Option<usize>,
    /// Passes over the pilot's columns.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pilot_passes: Option<usize>,
    pub representatives: usize,
    /// CX error on the compressed coordinates.
    pub cx_rel_error: f64,
    /// Relative Frobenius error of the whole chain against the uncompressed matrix.
    pub total_rel_error: f64,
    pub method: String,
    pub svd_seconds: f64,
    pub cx_seconds: f64,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StageTimes {
    pub geometry_seconds: f64,
    pub material_seconds: f64,
    pub assemble: f64,
    pub colours: f64,
    pub compress: f64,
    /// Fitting the geometry weights to the light lobes (`geometry/x-lobes.bsa`).
    #[serde(default)]
    pub lobe_fit: f64,
    pub total_seconds: f64,
    pub threads: usize,
    pub peak_rss_mib: f64,
    /// Shards that built chunks in this process (1 for a one-process build; 0 when merged
    /// separately).
    pub shards_in_process: usize,
    /// Shard records ([`ShardTimes`]) a separate merge found and summed into
    /// `geometry_seconds` / `material_seconds` (0 for a one-process build).
    #[serde(default)]
    pub shards_merged: usize,
}

/// What one shard of a sharded build spent, kept beside its chunks as
/// `chunks/shard-I-of-N.json` so that `library merge`, often run in another process or on
/// another node, can report the build's item times. A resumed shard adds to its record.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShardTimes {
    pub geometry_seconds: f64,
    pub material_seconds: f64,
    pub geometries_built: usize,
    pub materials_built: usize,
    /// Runs of this shard that built or reused chunks (more than 1 after a resume).
    pub runs: usize,
}

impl ShardTimes {
    fn path(dir: &Path, index: usize, count: usize) -> std::path::PathBuf {
        dir.join("chunks")
            .join(format!("shard-{index}-of-{count}.json"))
    }

    /// Add one run's times to shard `index` of `count`'s record in `dir` (written atomically).
    /// An unreadable earlier record is replaced: the times are a report, not library data.
    pub fn record(dir: &Path, index: usize, count: usize, run: &ShardTimes) -> Result<()> {
        let p = Self::path(dir, index, count);
        let mut t: ShardTimes = std::fs::read_to_string(&p)
            .ok()
            .and_then(|s| serde_json::from_str(&s).ok())
            .unwrap_or_default();
        t.geometry_seconds += run.geometry_seconds;
        t.material_seconds += run.material_seconds;
        t.geometries_built += run.geometries_built;
        t.materials_built += run.materials_built;
        t.runs += 1;
        let text = serde_json::to_string_pretty(&t)
            .map_err(|e| Error::new(p.display().to_string(), format!("cannot encode: {e}")))?;
        crate::atomic_write::write_bytes(&p, text.as_bytes())
    }

    /// The shard records in `dir/chunks`, sorted.
    fn paths(dir: &Path) -> Vec<std::path::PathBuf> {
        let Ok(rd) = std::fs::read_dir(dir.join("chunks")) else {
            return Vec::new();
        };
        let mut paths: Vec<_> = rd
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with("shard-") && n.ends_with(".json"))
            })
            .collect();
        paths.sort();
        paths
    }

    /// Remove every shard record of `dir` (once their times are taken into a build's).
    pub fn remove_all(dir: &Path) {
        for p in Self::paths(dir) {
            let _ = std::fs::remove_file(p);
        }
    }

    /// The sum of every shard record in `dir/chunks` and how many there were. Records that do
    /// not parse are skipped and named in the returned list.
    pub fn collect(dir: &Path) -> (ShardTimes, usize, Vec<String>) {
        let mut sum = ShardTimes::default();
        let (mut n, mut bad) = (0, Vec::new());
        for p in Self::paths(dir) {
            match std::fs::read_to_string(&p)
                .ok()
                .and_then(|s| serde_json::from_str::<ShardTimes>(&s).ok())
            {
                Some(t) => {
                    sum.geometry_seconds += t.geometry_seconds;
                    sum.material_seconds += t.material_seconds;
                    sum.geometries_built += t.geometries_built;
                    sum.materials_built += t.materials_built;
                    sum.runs += t.runs;
                    n += 1;
                }
                None => bad.push(p.display().to_string()),
            }
        }
        (sum, n, bad)
    }
}

impl Manifest {
    /// List the files by path (so a library the merge wrote and one a refit completed list
    /// them alike).
    pub fn sort_files(&mut self) {
        self.files.sort_by(|a, b| a.path.cmp(&b.path));
    }

    pub fn write(&self, dir: &Path) -> Result<()> {
        let text = serde_json::to_string_pretty(self)
            .map_err(|e| Error::new("manifest.json", format!("cannot encode: {e}")))?;
        crate::atomic_write::write_bytes(&dir.join("manifest.json"), text.as_bytes())
    }

    pub fn read(dir: &Path) -> Result<Self> {
        let p = dir.join("manifest.json");
        let text = std::fs::read_to_string(&p).map_err(|e| {
            Error::io(
                &p,
                "read the library manifest (an incomplete build? run `biscale library merge`)",
                e,
            )
        })?;
        let m: Manifest = serde_json::from_str(&text)
            .map_err(|e| Error::new(p.display().to_string(), format!("corrupted manifest: {e}")))?;
        if m.format != "biscale-library" || m.version != MANIFEST_VERSION {
            return Err(Error::new(
                p.display().to_string(),
                format!(
                    "library format '{}' version {} (this biscale {} reads biscale-library version {MANIFEST_VERSION}); rebuild it",
                    m.format, m.version, env!("CARGO_PKG_VERSION")
                ),
            ));
        }
        Ok(m)
    }
}
