//! The `biscale library` jobs (build, merge, info, verify) as library functions the CLI calls:
//! each returns the text to print.

use super::build::{build_shard, Shard};
use super::manifest::Manifest;
use super::profile::LibraryProfile;
use super::progress::Progress;
use super::{build_all, cache_path, cache_root, finished, merge_shards, Library};
use crate::error::Result;
use std::path::{Path, PathBuf};

/// Options of `biscale library build`.
#[derive(Debug, Clone)]
pub struct BuildJob {
    pub profile: String,
    /// Output directory; default: the cache entry of the profile.
    pub out: Option<PathBuf>,
    pub cache_dir: Option<PathBuf>,
    pub shard: Shard,
    pub quiet: bool,
    pub keep_chunks: bool,
    /// Rebuild even if the directory already holds the finished library of this profile (its
    /// `manifest.json` matches the profile's hash); without it such a build does nothing and
    /// says "already built". A forced build removes the manifest first, recomputes every chunk
    /// and merges again (`--force`).
    pub force: bool,
}

/// Build a library (or one shard of it). Returns a summary.
pub fn build(job: &BuildJob) -> Result<String> {
    let force = job.force;
    let (prof, ppath) = LibraryProfile::load(&job.profile)?;
    let base = ppath.parent().map(Path::to_path_buf).unwrap_or_default();
    let dir = job
        .out
        .clone()
        .unwrap_or_else(|| cache_path(&prof, &cache_root(job.cache_dir.as_deref())));
    let progress = Progress { quiet: job.quiet };
    progress.note(&format!(
        "library build: profile '{}' ({} geometries), seed {}, into {}{}",
        prof.name,
        prof.geometry_count(),
        prof.seed,
        dir.display(),
        if job.shard.count > 1 {
            format!(", shard {}/{}", job.shard.index, job.shard.count)
        } else {
            String::new()
        }
    ));
    if !force {
        if let Some(m) = finished(&dir, &prof) {
            progress.note(&format!(
                "library: {} is already built; nothing to do",
                dir.display()
            ));
            return Ok(format!(
                "already built; nothing to do (the manifest matches profile '{}'; --force rebuilds it)\n{}",
                prof.name,
                summary(&dir, &m)
            ));
        }
    }
    if job.shard.count == 1 {
        let m = build_all(&prof, &base, &dir, &progress, job.keep_chunks, force)?;
        return Ok(summary(&dir, &m));
    }
    let rep = build_shard(&prof, &base, &dir, job.shard, force, &progress)?;
    if rep.already_built {
        return Ok(format!(
            "{} is already built; nothing to do\n",
            dir.display()
        ));
    }
    Ok(format!(
        "shard {}/{} of '{}' in {}: {} chunks built ({} geometries in {:.1} s, {} materials in {:.1} s), {} reused.\n\
         When every shard is done: biscale library merge {}\n",
        job.shard.index,
        job.shard.count,
        prof.name,
        dir.display(),
        rep.chunks_built,
        rep.geometries_built,
        rep.geometry_seconds,
        rep.materials_built,
        rep.material_seconds,
        rep.chunks_reused,
        dir.display()
    ))
}

/// Merge shards built into `dir`.
pub fn merge(dir: &Path, quiet: bool, keep_chunks: bool) -> Result<String> {
    let m = merge_shards(dir, &Progress { quiet }, keep_chunks)?;
    Ok(summary(dir, &m))
}

/// Fit (again) the geometry weights of a finished library to its light lobes
/// (`geometry/x-lobes.bsa`, [`super::lobefit`]) and write the material solver's finer
/// representatives (`material/search-*.bsa`, [`super::build::material_search_selection`]): for
/// libraries built before the merge wrote them. `material_search_energy` sets that key of the
/// library's profile first (its `profile.toml` and the manifest's profile hash are rewritten:
/// the library is then what the changed profile builds). `half_lobes` first stores `f32`
/// light-lobe records in half precision ([`super::build::convert_lobes_to_half`]) and sets the
/// profile's `geometry.lobe_precision = "half"` the same way. `pack_lobes` then stores the
/// half-precision records packed ([`super::build::convert_lobes_to_packed`]: the same numbers
/// without their zero blocks and repeated zenith nodes; the profile is unchanged, the form
/// is the files'). Rewrites the manifest.
pub fn refit(
    dir: &Path,
    material_search_energy: Option<f64>,
    half_lobes: bool,
    pack_lobes: bool,
    quiet: bool,
) -> Result<String> {
    let mut lib = Library::open(dir)?;
    let progress = Progress { quiet };
    let mut m = lib.manifest.clone();
    let mut prof = lib.profile.clone();
    if let Some(e) = material_search_energy {
        prof.compression.material_search_energy = Some(e);
    }
    if half_lobes && super::build::convert_lobes_to_half(dir, &lib, &prof, &progress, &mut m.files)?
    {
        prof.geometry.lobe_precision = super::profile::LobePrecision::Half;
    }
    if pack_lobes {
        super::build::convert_lobes_to_packed(dir, &prof, m.geometries, &progress, &mut m.files)?;
    }
    let changed = prof != lib.profile;
    if changed {
        // Parsed again, so the keys are checked as a profile's would be (and named so).
        lib.profile = LibraryProfile::parse(
            &prof.canonical(),
            "library refit: the profile with its options",
        )?;
    }
    m.build.lobe_fit = super::build::fit_lobe_weights(
        dir,
        &lib.profile,
        &lib.material_items()?,
        &progress,
        &mut m.files,
    )?;
    m.material_search =
        super::build::material_search_selection(dir, &lib.profile, &mut m.files, &progress)?;
    if m.material_search.is_none() {
        m.files.retain(|f| !f.path.starts_with("material/search-"));
    }
    // The profile, then the manifest naming its hash (two renames: a refit killed between them
    // leaves a library that `Library::open` calls inconsistent).
    if changed {
        crate::atomic_write::write_bytes(
            &dir.join("profile.toml"),
            lib.profile.canonical().as_bytes(),
        )?;
        m.profile_hash = lib.profile.hash();
    }
    m.sort_files();
    m.write(dir)?;
    Ok(summary(dir, &m))
}

/// Describe a library.
pub fn info(dir: &Path) -> Result<String> {
    let lib = Library::open(dir)?;
    Ok(summary(dir, &lib.manifest))
}

/// Check every file of a library against its manifest.
pub fn verify(dir: &Path) -> Result<String> {
    let mut lib = Library::open(dir)?;
    let n = lib.verify_all()?;
    Ok(format!(
        "{}: {n} files match their checksums\n",
        dir.display()
    ))
}

fn summary(dir: &Path, m: &Manifest) -> String {
    let bytes: u64 = m.files.iter().map(|f| f.bytes).sum();
    let b = &m.build;
    let mut s = format!(
        "library {} (profile '{}', seed {}, biscale {}): {:.1} MB\n\
         | part | items | rows per item | SVD rank | energy kept | passes | representatives | CX error | total error |\n\
         |---|---|---|---|---|---|---|---|---|\n",
        dir.display(),
        m.profile,
        m.seed,
        m.tool_version,
        bytes as f64 / 1e6
    );
    let parts = [
        Some(("geometry", m.geometries, m.gamma_rows, &m.geometry)),
        Some(("material", m.materials, m.table_len, &m.material)),
        m.material_search
            .as_ref()
            .map(|c| ("material (solver's search)", m.materials, m.table_len, c)),
    ];
    for (name, n, rows, c) in parts.into_iter().flatten() {
        let passes = match (c.pilot_columns, c.pilot_passes) {
            (Some(cols), Some(pp)) => format!("{} (+ {pp} over a pilot of {cols})", c.passes),
            _ => c.passes.to_string(),
        };
        s.push_str(&format!(
            "| {name} | {n} | {rows} | {} | {:.4} | {passes} | {} ({}) | {:.4} | {:.4} |\n",
            c.rank, c.energy_kept, c.representatives, c.method, c.cx_rel_error, c.total_rel_error
        ));
    }
    let items = if b.shards_merged > 0 {
        format!(
            "geometries {:.1} s, materials {:.1} s (the sum of {} shard records; the shards ran elsewhere)",
            b.geometry_seconds, b.material_seconds, b.shards_merged
        )
    } else if b.shards_in_process == 0 && b.geometry_seconds == 0.0 && b.material_seconds == 0.0 {
        "geometries and materials not recorded (shards built without time records)".to_string()
    } else {
        format!(
            "geometries {:.1} s, materials {:.1} s",
            b.geometry_seconds, b.material_seconds
        )
    };
    let total = if b.shards_in_process == 0 {
        "merge total"
    } else {
        "total"
    };
    s.push_str(&format!(
        "colours: {} per distinct material ({} effective materials)\n\
         build: {items}, join {:.1} s, colours {:.1} s, compression {:.1} s, \
         light-lobe weights {:.1} s; {total} {:.1} s on {} threads; peak memory {:.0} MiB\n",
        m.colours_per_material,
        m.materials * m.colours_per_material,
        b.assemble,
        b.colours,
        b.compress,
        b.lobe_fit,
        b.total_seconds,
        b.threads,
        b.peak_rss_mib
    ));
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testdir::TestDir;

    #[test]
    fn building_a_finished_library_does_nothing_unless_forced() {
        let tmp = TestDir::new("cmd-build");
        // Not made here: the build makes it.
        let dir = tmp.join("lib");
        let mut job = BuildJob {
            profile: "tiny".into(),
            out: Some(dir.clone()),
            cache_dir: None,
            shard: Shard::ALL,
            quiet: true,
            keep_chunks: false,
            force: false,
        };
        let first = build(&job).unwrap();
        assert!(!first.contains("already built"), "{first}");
        let manifest = std::fs::read(dir.join("manifest.json")).unwrap();
        let again = build(&job).unwrap();
        assert!(again.starts_with("already built; nothing to do"), "{again}");
        job.shard = Shard { index: 2, count: 3 };
        let shard = build(&job).unwrap();
        assert!(shard.contains("already built"), "{shard}");
        assert_eq!(std::fs::read(dir.join("manifest.json")).unwrap(), manifest);
        assert!(!dir.join("chunks").exists());
        job.shard = Shard::ALL;
        job.force = true;
        let forced = build(&job).unwrap();
        assert!(!forced.contains("already built"), "{forced}");
        assert_ne!(std::fs::read(dir.join("manifest.json")).unwrap(), manifest);
    }
}
