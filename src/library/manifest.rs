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
    pub passes: usize,
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
}

impl Manifest {
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
