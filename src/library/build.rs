//! Building a library: items are computed in chunks (the unit of resumption and of sharding),
//! then merged into whole arrays and compressed.
//!
//! A build claims the directory (writes or checks `profile.toml`, with relative texture and MERL
//! directories made absolute). A one-process build ([`build_joined`]) appends its chunks in order
//! straight to the joined arrays (resumable [`PartialArray`]s), so nothing is written twice. A
//! shard ([`build_shard`]; `--shard i/N` takes chunks `k ≡ i mod N`) writes chunk files,
//! skipping chunks already on disk whose checksum holds, so a killed build resumes where it
//! stopped and shards can run on different machines over a shared directory. A directory that
//! already holds the finished library of the profile is left alone unless forced.
//! `merge` takes the arrays a one-process build wrote, or checks that every chunk is present and
//! joins them into `geometry/gamma.bsa`, `geometry/lobes.bsa` and `material/prefiltered.bsa`
//! (removing each chunk once joined; a verified joined array of a merge that stopped stands for
//! its chunks, in the build and in the merge, so a stopped merge resumes after its last join),
//! compresses both (material: SVD of the Gram matrix; geometry: streaming randomized SVD), picks
//! representatives by CX, and writes `manifest.json` last: a directory with a manifest is a
//! complete library. Every item depends only on the profile, the seed and its index, and every
//! reduction has a fixed order, so the same profile and seed give byte-identical array files
//! whether built in one process or in shards.

use super::items::{
    average_colour, colour_shifts, geometry_items, material_items, GeometryItem, MaterialItem,
};
use super::manifest::{
    ArrayEntry, CompressionReport, Manifest, ShardTimes, StageTimes, MANIFEST_VERSION,
};
use super::profile::{LibraryProfile, LobePrecision};
use super::progress::{Bar, Progress, Stages};
use crate::error::{Error, Result};
use crate::gamma::GammaLayout;
use crate::generators::parse_generator;
use crate::lightlobes::record_len;
use crate::lowrank::{cx, rsvd_streaming_with, svd_gram, BlockSource, CxMethod, RsvdConfig};
use crate::material::parse_material;
use crate::prefilter::{PrefilterConfig, Prefiltered};
use crate::store::{f32_bytes, write_array, ArrayFile, ArrayWriter, Dtype, Expect, PartialArray};
use faer::reborrow::ReborrowMut;
use faer::{Mat, MatMut};
use rayon::prelude::*;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Which part of the chunk list a process builds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

impl Shard {
    pub const ALL: Shard = Shard { index: 0, count: 1 };

    /// Parse `i/N` (0-based `i < N`).
    pub fn parse(s: &str) -> Result<Self> {
        let bad = || {
            Error::new(
                "--shard",
                format!("'{s}': expected i/N with 0 <= i < N, e.g. 0/4"),
            )
        };
        let (a, b) = s.split_once('/').ok_or_else(bad)?;
        let (index, count): (usize, usize) = (
            a.trim().parse().map_err(|_| bad())?,
            b.trim().parse().map_err(|_| bad())?,
        );
        if count == 0 || index >= count {
            return Err(bad());
        }
        Ok(Shard { index, count })
    }
}

/// The settings derived from a profile that fix the arrays' shapes.
pub fn gamma_layout(p: &LibraryProfile) -> GammaLayout {
    GammaLayout::new(
        p.geometry.view_theta,
        p.geometry.view_phi,
        p.geometry.normal_grid,
    )
}

pub fn prefilter_config(p: &LibraryProfile) -> PrefilterConfig {
    let s = &p.material.prefilter;
    PrefilterConfig {
        n_half: s.n_half,
        n_theta_mu: s.n_theta_mu,
        n_phi_mu: s.n_phi_mu,
        samples: s.samples,
    }
}

/// Entries of one material's prefiltered table.
pub fn table_len(p: &LibraryProfile) -> usize {
    let s = &p.material.prefilter;
    s.n_half * crate::prefilter::KAPPAS.len() * s.n_theta_mu * s.n_phi_mu
}

fn chunk_path(dir: &Path, kind: &str, k: usize) -> PathBuf {
    dir.join("chunks").join(format!("{kind}-{k:06}.bsa"))
}

/// Check or create `profile.toml`: a directory holds one profile's library. Creates `dir` if
/// needed, and nothing else. The file is created exclusively, so of several processes claiming an
/// empty directory at once exactly one writes it and the others compare against it.
fn claim_dir(dir: &Path, prof: &LibraryProfile) -> Result<()> {
    // A file where the directory should be, or a directory that cannot be written, is named as
    // such (not as a profile.toml that cannot be read).
    crate::atomic_write::check_output_dir(dir, "library directory")?;
    let path = dir.join("profile.toml");
    let canon = prof.canonical();
    let old = match std::fs::read_to_string(&path) {
        Ok(old) => old,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            if crate::atomic_write::create_exclusive(&path, canon.as_bytes())? {
                return Ok(());
            }
            std::fs::read_to_string(&path)
                .map_err(|e| Error::io(&path, "read the library's profile", e))?
        }
        Err(e) => return Err(Error::io(&path, "read the library's profile", e)),
    };
    if old == canon {
        return Ok(());
    }
    Err(Error::new(
        path.display().to_string(),
        format!(
            "this directory holds a library of another profile (or seed); expected profile '{}' \
             with hash {} — use another --out directory or remove this one",
            prof.name,
            prof.hash()
        ),
    ))
}

/// What a shard build did.
#[derive(Debug, Clone)]
pub struct BuildReport {
    /// The directory already held the finished library of this profile: nothing was done.
    pub already_built: bool,
    pub chunks_built: usize,
    pub chunks_reused: usize,
    pub geometry_seconds: f64,
    pub material_seconds: f64,
    pub geometries_built: usize,
    pub materials_built: usize,
    /// Arrays this build wrote whole ([`build_joined`]) and their checksums, which [`merge`]
    /// then takes without reading them again.
    pub joined: Vec<(&'static str, String)>,
}

/// Build this shard's chunks in `dir` (resuming: valid chunks are kept). A shard of several
/// adds its times to `chunks/shard-I-of-N.json` ([`ShardTimes`]) for the merge's manifest.
///
/// Relative `texture_dirs` / `merl_dirs` of `prof` are resolved against `base` (the profile
/// file's directory) before `profile.toml` is written, so the stored profile holds absolute
/// paths and the merge finds the same files. If `dir` already holds the finished library of this
/// profile (see [`super::finished`]), nothing is done and the report says `already_built`,
/// unless `force` is set: then the manifest is removed (the directory is no longer a complete
/// library) and the chunks are built again.
pub fn build_shard(
    prof: &LibraryProfile,
    base: &Path,
    dir: &Path,
    shard: Shard,
    force: bool,
    progress: &Progress,
) -> Result<BuildReport> {
    let rep = build(prof, base, dir, shard, force, progress, false)?;
    if shard.count > 1 && !rep.already_built {
        ShardTimes::record(
            dir,
            shard.index,
            shard.count,
            &ShardTimes {
                geometry_seconds: rep.geometry_seconds,
                material_seconds: rep.material_seconds,
                geometries_built: rep.geometries_built,
                materials_built: rep.materials_built,
                runs: 1,
            },
        )?;
    }
    Ok(rep)
}

/// Build every item in this process straight into the joined arrays (`geometry/gamma.bsa`,
/// `geometry/lobes.bsa`, `material/prefiltered.bsa`), chunk after chunk, so no byte is written
/// twice and the merge has nothing to join. Each array grows in a [`PartialArray`], whose log
/// makes the build resumable as chunk files do: a killed build continues after the last chunk
/// whose data checks out. Chunk files already in `dir` (from shards, or an earlier build that
/// kept them) are copied in instead of being built again, and removed once their array is
/// finished. The arrays are byte for byte those a merge of the same chunks joins. The report
/// lists each array written with its checksum, for [`merge`]. Otherwise as [`build_shard`].
pub fn build_joined(
    prof: &LibraryProfile,
    base: &Path,
    dir: &Path,
    force: bool,
    progress: &Progress,
) -> Result<BuildReport> {
    build(prof, base, dir, Shard::ALL, force, progress, true)
}

fn build(
    prof: &LibraryProfile,
    base: &Path,
    dir: &Path,
    shard: Shard,
    force: bool,
    progress: &Progress,
    stream: bool,
) -> Result<BuildReport> {
    let mut resolved = prof.clone();
    resolved.resolve_dirs(base)?;
    let prof = &resolved;
    let mut rep = BuildReport {
        already_built: false,
        chunks_built: 0,
        chunks_reused: 0,
        geometry_seconds: 0.0,
        material_seconds: 0.0,
        geometries_built: 0,
        materials_built: 0,
        joined: Vec::new(),
    };
    if !force && super::finished(dir, prof).is_some() {
        progress.note(&format!(
            "library: {} is already built; nothing to do",
            dir.display()
        ));
        rep.already_built = true;
        return Ok(rep);
    }
    // Claim the directory first, so a refused build leaves nothing behind.
    claim_dir(dir, prof)?;
    let manifest = dir.join("manifest.json");
    if manifest.exists() {
        progress.note(&format!(
            "library: removing {} ({}); the library is rebuilt",
            manifest.display(),
            if force {
                "forced rebuild"
            } else {
                "it does not describe a complete library of this profile"
            }
        ));
        std::fs::remove_file(&manifest)
            .map_err(|e| Error::io(&manifest, "remove the old manifest", e))?;
    }
    let geos = geometry_items(prof, base)?;
    let mats = material_items(prof, base)?;
    let parts = parts(prof, geos.len(), mats.len());
    // The geometry parts (binned columns and light lobes) and the materials' tables, last.
    let (geometry_parts, table) = parts.split_at(parts.len() - 1);
    let geometry_parts: Vec<&Part> = geometry_parts.iter().collect();
    if force {
        // The joined arrays of an earlier merge would stand in for chunks (see `build_chunks`),
        // and an earlier build's partial arrays would be resumed.
        for p in &parts {
            let path = dir.join(p.joined);
            if path.exists() {
                std::fs::remove_file(&path)
                    .map_err(|e| Error::io(&path, "remove the old joined array", e))?;
            }
            PartialArray::discard(&path)?;
        }
    }
    if !stream {
        std::fs::create_dir_all(dir.join("chunks"))
            .map_err(|e| Error::io(&dir.join("chunks"), "create the chunk directory", e))?;
    }
    let layout = gamma_layout(prof);
    let pcfg = prefilter_config(prof);
    let chunk = prof.chunk;
    let mine = |n: usize| -> Vec<usize> {
        (0..n.div_ceil(chunk))
            .filter(|k| k % shard.count == shard.index)
            .collect()
    };
    let (n, secs) = build_chunks(
        dir,
        &geometry_parts,
        &geos,
        chunk,
        &mine,
        progress,
        "geometries (binned BVNDF and light lobes)",
        &mut rep,
        stream,
        |it| {
            let (col, lobes) = geometry_data(it, &layout, prof)?;
            let mut out = vec![col];
            out.extend(lobe_bytes(it, &layout, prof, &lobes)?);
            Ok(out)
        },
    )?;
    rep.geometries_built = n;
    rep.geometry_seconds = secs;
    let (n, secs) = build_chunks(
        dir,
        &[&table[0]],
        &mats,
        chunk,
        &mine,
        progress,
        "materials (prefiltered F)",
        &mut rep,
        stream,
        |it| {
            let m = parse_material(&it.spec)
                .map_err(|e| e.within(format!("material item {}", it.index)))?;
            Ok(vec![
                f32_bytes(Prefiltered::build(&m, &pcfg).table()).to_vec()
            ])
        },
    )?;
    rep.materials_built = n;
    rep.material_seconds = secs;
    if stream {
        // Chunks of earlier shards were copied in (and removed); their time records go with
        // them into this build's times.
        let (shards, _, _) = ShardTimes::collect(dir);
        rep.geometry_seconds += shards.geometry_seconds;
        rep.material_seconds += shards.material_seconds;
        ShardTimes::remove_all(dir);
    }
    Ok(rep)
}

/// Build this shard's missing chunks of one item kind: items in parallel within a chunk
/// (`item_bytes` returns one byte vector per part). A part whose verified joined array is
/// already there (a merge stopped after joining it, or an earlier joined build) needs nothing.
///
/// Without `stream`, each chunk is written atomically as one array file per part, and a chunk
/// is missing when one of its parts has neither a valid chunk file (header, shape and checksum)
/// nor a valid joined array. With `stream` (one process, every chunk), the parts still missing
/// grow as [`PartialArray`]s, resumed after the chunks they already hold; a chunk whose files
/// are all valid is copied in rather than built, and its files are removed when the arrays are
/// finished. Returns the items built and the seconds spent.
#[allow(clippy::too_many_arguments)]
fn build_chunks<T: Sync>(
    dir: &Path,
    outputs: &[&Part],
    items: &[T],
    chunk: usize,
    mine: &dyn Fn(usize) -> Vec<usize>,
    progress: &Progress,
    what: &str,
    rep: &mut BuildReport,
    stream: bool,
    item_bytes: impl Fn(&T) -> Result<Vec<Vec<u8>>> + Sync,
) -> Result<(usize, f64)> {
    let size = |k: usize| chunk.min(items.len() - k * chunk);
    let joined: Vec<bool> = outputs.iter().map(|o| o.open_joined(dir).is_ok()).collect();
    if joined.iter().any(|&j| j) {
        let names: Vec<&str> = outputs
            .iter()
            .zip(&joined)
            .filter(|(_, &j)| j)
            .map(|(o, _)| o.joined)
            .collect();
        progress.note(&format!(
            "library: {} already joined (checksums hold); their chunks are not needed",
            names.join(", ")
        ));
    }
    let all = mine(items.len());
    // The parts this build writes: every part for chunk files, the unjoined ones when streaming.
    let open: Vec<usize> = (0..outputs.len())
        .filter(|&i| !stream || !joined[i])
        .collect();
    let mut writers = Vec::new();
    let todo: Vec<usize> = if stream {
        for (o, _) in outputs.iter().zip(&joined).filter(|(_, &j)| j) {
            // A finished array's log, if a build stopped between its rename and the log's removal.
            PartialArray::discard(&dir.join(o.joined))?;
        }
        if open.is_empty() {
            rep.chunks_reused += all.len();
            return Ok((0, 0.0));
        }
        let array = |i: usize, keep: usize| {
            let o = outputs[i];
            PartialArray::open(
                &dir.join(o.joined),
                o.name,
                o.dtype,
                &[o.items, o.len],
                keep,
            )
        };
        // Resume after the chunks every part holds, checked against its log.
        let mut keep = usize::MAX;
        for &i in &open {
            let o = outputs[i];
            keep = keep.min(PartialArray::logged_units(
                &dir.join(o.joined),
                o.name,
                o.dtype,
                &[o.items, o.len],
            )?);
        }
        writers = loop {
            let ws = open
                .iter()
                .map(|&i| array(i, keep))
                .collect::<Result<Vec<_>>>()?;
            let good = ws.iter().map(|w| w.units()).min().unwrap_or(0);
            if ws.iter().all(|w| w.units() == good) {
                break ws;
            }
            keep = good;
        };
        let start = writers[0].units();
        if start > 0 {
            let names: Vec<&str> = open.iter().map(|&i| outputs[i].joined).collect();
            progress.note(&format!(
                "library: resuming {} after {start} of {} chunks (their data checked against the log)",
                names.join(", "),
                all.len()
            ));
        }
        rep.chunks_reused += start;
        all[start..].to_vec()
    } else {
        all.iter()
            .copied()
            .filter(|&k| {
                outputs
                    .iter()
                    .zip(&joined)
                    .any(|(o, &j)| !j && o.open_chunk(dir, chunk, k, true).is_err())
            })
            .collect()
    };
    if !stream {
        rep.chunks_reused += all.len() - todo.len();
    }
    let bar = progress.bar(todo.iter().map(|&k| size(k)).sum::<usize>() as u64, what);
    let t = Instant::now();
    let mut built = 0;
    // Chunk files of this kind copied into the streamed arrays, removed once those are finished.
    let mut copied = Vec::new();
    let writers = std::sync::Mutex::new(writers);
    // Each chunk's bytes are written (joined, checksummed) by a thread of their own while the
    // next chunk is computed: one chunk in flight, in order, so memory stays two chunks.
    std::thread::scope(|scope| -> Result<()> {
        let join = |h: std::thread::ScopedJoinHandle<'_, Result<()>>| {
            h.join().unwrap_or_else(|_| {
                Err(Error::new(
                    dir.display().to_string(),
                    "the thread writing a chunk stopped unexpectedly",
                ))
            })
        };
        let mut pending = None;
        for &k in &todo {
            // One byte vector per part of `open`, per item (or one for the whole chunk).
            let reuse = stream.then(|| {
                open.iter()
                    .map(|&i| outputs[i].open_chunk(dir, chunk, k, true))
                    .collect::<Result<Vec<_>>>()
                    .ok()
            });
            let cols: Vec<Vec<Vec<u8>>> = match reuse.flatten() {
                Some(files) => {
                    let bytes = files.iter().map(|f| f.bytes().to_vec()).collect();
                    copied.extend(files.into_iter().map(|f| f.path));
                    bar.inc(size(k) as u64);
                    rep.chunks_reused += 1;
                    vec![bytes]
                }
                None => {
                    let part = &items[k * chunk..k * chunk + size(k)];
                    let cols = part
                        .par_iter()
                        .map(|it| {
                            let mut b = item_bytes(it)?;
                            bar.inc(1);
                            if stream {
                                b = open.iter().map(|&i| std::mem::take(&mut b[i])).collect();
                            }
                            Ok(b)
                        })
                        .collect::<Result<_>>()?;
                    rep.chunks_built += 1;
                    built += part.len();
                    cols
                }
            };
            if let Some(h) = pending.take() {
                join(h)?;
            }
            let (n, writers, open) = (size(k), &writers, &open);
            pending = Some(scope.spawn(move || -> Result<()> {
                for (slot, &i) in open.iter().enumerate() {
                    let mut bytes = Vec::with_capacity(cols.iter().map(|c| c[slot].len()).sum());
                    for c in &cols {
                        bytes.extend_from_slice(&c[slot]);
                    }
                    if stream {
                        let mut ws = writers.lock().map_err(|_| {
                            Error::new(dir.display().to_string(), "a chunk writer failed")
                        })?;
                        ws[slot].append(&bytes)?;
                    } else {
                        let o = outputs[i];
                        write_array(
                            &chunk_path(dir, o.kind, k),
                            o.chunk_name,
                            o.dtype,
                            &[n, o.len],
                            &bytes,
                        )?;
                    }
                }
                Ok(())
            }));
        }
        match pending {
            Some(h) => join(h),
            None => Ok(()),
        }
    })?;
    let writers = writers
        .into_inner()
        .map_err(|_| Error::new(dir.display().to_string(), "a chunk writer failed"))?;
    for (w, &i) in writers.into_iter().zip(&open) {
        let sum = w.finish()?;
        rep.joined.push((outputs[i].joined, sum));
    }
    for p in copied {
        std::fs::remove_file(&p).map_err(|e| Error::io(&p, "remove the joined chunk", e))?;
    }
    bar.finish();
    Ok((built, t.elapsed().as_secs_f64()))
}

/// One geometry item's library data, from one pass of view rays: the bytes of its binned BVNDF
/// column in the profile's `gamma_precision` and its light-lobe record ([`crate::lightlobes`]).
pub fn geometry_data(
    it: &GeometryItem,
    layout: &GammaLayout,
    prof: &LibraryProfile,
) -> Result<(Vec<u8>, Vec<f32>)> {
    let hf = parse_generator(&it.spec)
        .and_then(|g| g.build())
        .map_err(|e| e.within(format!("geometry item {}", it.index)))?;
    let (col, lobes) = layout.trace(&hf, prof.geometry.rays, prof.geometry.lobe_clusters);
    Ok((prof.geometry.gamma_precision.encode(&col), lobes))
}

/// The stored form of a geometry's light-lobe record `lobes`, one byte vector per light-lobe
/// part of [`parts`]: the record (`single`), or its cluster headers and its moments in half
/// precision ([`crate::lobecodec`], `half`).
pub fn lobe_bytes(
    it: &GeometryItem,
    layout: &GammaLayout,
    prof: &LibraryProfile,
    lobes: &[f32],
) -> Result<Vec<Vec<u8>>> {
    match prof.geometry.lobe_precision {
        LobePrecision::Single => Ok(vec![f32_bytes(lobes).to_vec()]),
        LobePrecision::Half => {
            let k = prof.geometry.lobe_clusters;
            let (head, body) =
                crate::lobecodec::encode(lobes, k, layout.views.len()).ok_or_else(|| {
                    Error::new(
                        format!("geometry item {} ({})", it.index, it.spec),
                        "a light-lobe moment is beyond half precision's range (an area over \
                         65,504 times the base area: a surface too tall for the library); use \
                         geometry.lobe_precision = \"single\" in the profile",
                    )
                })?;
            Ok(vec![
                f32_bytes(&head).to_vec(),
                bytemuck::cast_slice(&body).to_vec(),
            ])
        }
    }
}

/// A library array read as the matrix `B` whose column `j` is item `j` (items stored row-major,
/// one item after another).
pub struct ItemMatrix<'a> {
    file: &'a ArrayFile,
    items: usize,
    len: usize,
    /// Per-item factors applied to the columns as they are read (none: the stored values).
    scale: Option<Vec<f64>>,
}

impl<'a> ItemMatrix<'a> {
    pub fn new(file: &'a ArrayFile) -> Self {
        let s = &file.header.shape;
        ItemMatrix {
            file,
            items: s[0],
            len: s.get(1).copied().unwrap_or(1),
            scale: None,
        }
    }

    /// Each item's column norm (one parallel pass over the file).
    pub fn column_norms(&self) -> Result<Vec<f64>> {
        let rows = self.len;
        (0..self.items)
            .into_par_iter()
            .map(|j| {
                let mut col = Mat::<f64>::zeros(rows, 1);
                self.read_block(0..rows, j..j + 1, col.as_mut())?;
                Ok((0..rows).map(|i| col[(i, 0)].powi(2)).sum::<f64>().sqrt())
            })
            .collect()
    }

    /// The same matrix with column `j` multiplied by `scale[j]`.
    pub fn scaled(mut self, scale: Vec<f64>) -> Self {
        self.scale = Some(scale);
        self
    }

    /// Every column scaled to unit norm (an all-zero column stays zero), and the norms.
    pub fn unit_columns(self) -> Result<(Self, Vec<f64>)> {
        let norms = self.column_norms()?;
        let inv = norms
            .iter()
            .map(|&v| if v > 0.0 { 1.0 / v } else { 0.0 })
            .collect();
        Ok((self.scaled(inv), norms))
    }
}

/// An element type the library matrices are read into: converted from the stored half or
/// single precision slice to slice (vectorised; element by element, half's f16 conversion was
/// a call per value and 70 % of a default library build), or from `uf8` bytes through their
/// table of values ([`crate::uf8::decode_into`]).
trait ReadElement: Copy + Default + std::ops::MulAssign + From<f32> {
    fn from_f16s(src: &[half::f16], dst: &mut [Self]);
    fn from_f32s(src: &[f32], dst: &mut [Self]);
    fn from_f64(v: f64) -> Self;
}

impl ReadElement for f64 {
    fn from_f16s(src: &[half::f16], dst: &mut [f64]) {
        use half::slice::HalfFloatSliceExt;
        src.convert_to_f64_slice(dst)
    }
    fn from_f32s(src: &[f32], dst: &mut [f64]) {
        for (o, v) in dst.iter_mut().zip(src) {
            *o = *v as f64;
        }
    }
    fn from_f64(v: f64) -> f64 {
        v
    }
}

impl ReadElement for f32 {
    fn from_f16s(src: &[half::f16], dst: &mut [f32]) {
        use half::slice::HalfFloatSliceExt;
        src.convert_to_f32_slice(dst)
    }
    fn from_f32s(src: &[f32], dst: &mut [f32]) {
        dst.copy_from_slice(src)
    }
    fn from_f64(v: f64) -> f32 {
        v as f32
    }
}

impl ItemMatrix<'_> {
    /// Fill `out` with block `(rows, cols)`. Each item's rows are contiguous in the file and
    /// each column of `out` is (for the matrices the solvers and the SVD allocate) contiguous in
    /// memory, so columns convert slice to slice.
    fn read_into<T: ReadElement>(
        &self,
        rows: Range<usize>,
        cols: Range<usize>,
        mut out: MatMut<'_, T>,
    ) -> Result<()> {
        let mut buf = Vec::new();
        let mut put = |jj: usize, fill: &mut dyn FnMut(&mut [T])| match out
            .rb_mut()
            .col_mut(jj)
            .try_as_col_major_mut()
        {
            Some(c) => fill(c.as_slice_mut()),
            None => {
                buf.resize(rows.len(), T::default());
                fill(&mut buf);
                for (ii, v) in buf.iter().enumerate() {
                    out[(ii, jj)] = *v;
                }
            }
        };
        // Positioned reads, not the map: a pass over a matrix larger than memory would
        // otherwise keep every page it read resident (`ArrayFile::read_data`).
        let size = self.file.header.dtype.size();
        let at = |j: usize| (j * self.len + rows.start) * size;
        let mut err = None;
        match self.file.header.dtype {
            Dtype::UF8 => {
                let mut src = vec![0u8; rows.len()];
                for (jj, j) in cols.clone().enumerate() {
                    if let Err(e) = self.file.read_data(at(j), &mut src) {
                        err = Some(e);
                        break;
                    }
                    put(jj, &mut |dst| crate::uf8::decode_into(&src, dst));
                }
            }
            Dtype::F16 => {
                let mut src = vec![half::f16::ZERO; rows.len()];
                for (jj, j) in cols.clone().enumerate() {
                    if let Err(e) = self
                        .file
                        .read_data(at(j), bytemuck::cast_slice_mut(&mut src))
                    {
                        err = Some(e);
                        break;
                    }
                    put(jj, &mut |dst| T::from_f16s(&src, dst));
                }
            }
            Dtype::F32 => {
                let mut src = vec![0f32; rows.len()];
                for (jj, j) in cols.clone().enumerate() {
                    if let Err(e) = self
                        .file
                        .read_data(at(j), bytemuck::cast_slice_mut(&mut src))
                    {
                        err = Some(e);
                        break;
                    }
                    put(jj, &mut |dst| T::from_f32s(&src, dst));
                }
            }
            d => {
                return Err(Error::new(
                    self.file.path.display().to_string(),
                    format!("{d:?} is not a matrix type"),
                ))
            }
        }
        if let Some(e) = err {
            return Err(e);
        }
        if let Some(sc) = &self.scale {
            for (jj, j) in cols.enumerate() {
                let f = T::from_f64(sc[j]);
                for ii in 0..rows.len() {
                    out[(ii, jj)] *= f;
                }
            }
        }
        Ok(())
    }
}

impl BlockSource for ItemMatrix<'_> {
    fn rows(&self) -> usize {
        self.len
    }
    fn cols(&self) -> usize {
        self.items
    }
    fn read_block(
        &self,
        rows: Range<usize>,
        cols: Range<usize>,
        out: MatMut<'_, f64>,
    ) -> Result<()> {
        self.read_into(rows, cols, out)
    }
    fn read_block_f32(
        &self,
        rows: Range<usize>,
        cols: Range<usize>,
        out: MatMut<'_, f32>,
    ) -> Result<()> {
        self.read_into(rows, cols, out)
    }
    /// Items are stored one after another, so columns `cols` are one byte range.
    fn prefetch(&self, cols: Range<usize>) {
        let size = self.len * self.file.header.dtype.size();
        self.file
            .will_need(vec![(cols.start * size, cols.len() * size)]);
    }
}

/// One array of a library that the build writes in chunks (`chunks/KIND-NNNNNN.bsa`) and the
/// merge joins into one file (`joined`). The build and the merge read their shapes from here.
struct Part {
    /// The chunk files' prefix.
    kind: &'static str,
    /// The array name inside a chunk file.
    chunk_name: &'static str,
    /// The joined file, relative to the library directory, and its array name.
    joined: &'static str,
    name: &'static str,
    dtype: Dtype,
    items: usize,
    len: usize,
}

/// The chunked arrays of a profile's library: the geometries' binned columns and light lobes
/// (one chunk build writes them all: with `lobe_precision = "half"` the lobes are two arrays,
/// their cluster headers and their moments) and, last, the materials' prefiltered tables.
fn parts(prof: &LibraryProfile, geometries: usize, materials: usize) -> Vec<Part> {
    let layout = gamma_layout(prof);
    let k = prof.geometry.lobe_clusters;
    let record = record_len(&layout, k);
    let mut parts = vec![Part {
        kind: "geometry",
        chunk_name: "gamma-chunk",
        joined: "geometry/gamma.bsa",
        name: "gamma",
        dtype: prof.geometry.gamma_precision.dtype(),
        items: geometries,
        len: layout.rows(),
    }];
    match prof.geometry.lobe_precision {
        LobePrecision::Single => parts.push(Part {
            kind: "lobes",
            chunk_name: "lobes-chunk",
            joined: "geometry/lobes.bsa",
            name: "light-lobes",
            dtype: Dtype::F32,
            items: geometries,
            len: record,
        }),
        LobePrecision::Half => parts.extend([
            Part {
                kind: "lobe-heads",
                chunk_name: "lobe-heads-chunk",
                joined: "geometry/lobe-heads.bsa",
                name: "light-lobe-heads",
                dtype: Dtype::F32,
                items: geometries,
                len: k * crate::lightlobes::HEAD,
            },
            Part {
                kind: "lobes",
                chunk_name: "lobes-chunk",
                joined: "geometry/lobes.bsa",
                name: "light-lobes-half",
                dtype: Dtype::F16,
                items: geometries,
                len: crate::lobecodec::half_len(record, k),
            },
        ]),
    }
    parts.push(Part {
        kind: "material",
        chunk_name: "prefiltered-chunk",
        joined: "material/prefiltered.bsa",
        name: "prefiltered",
        dtype: Dtype::F32,
        items: materials,
        len: table_len(prof),
    });
    parts
}

impl Part {
    /// Items in chunk `k`.
    fn chunk_items(&self, chunk: usize, k: usize) -> usize {
        chunk.min(self.items - k * chunk)
    }

    /// Chunk `k`, opened with its header, dtype and shape checked (and its checksum when
    /// `verify`).
    fn open_chunk(&self, dir: &Path, chunk: usize, k: usize, verify: bool) -> Result<ArrayFile> {
        ArrayFile::open(
            &chunk_path(dir, self.kind, k),
            &Expect {
                dtype: Some(self.dtype),
                shape: Some(&[self.chunk_items(chunk, k), self.len]),
                verify,
                ..Default::default()
            },
        )
        .map_err(|e| {
            e.within(format!(
                "merge: {} chunk {k} (build the missing shards first)",
                self.kind
            ))
        })
    }

    /// The joined array, its checksum verified: a merge that stopped after joining this part
    /// (and removed its chunks) left it, and neither the build nor the merge redo it.
    fn open_joined(&self, dir: &Path) -> Result<ArrayFile> {
        self.open_whole(dir, true)
    }

    /// The joined array with its name, type and shape checked (and its checksum when `verify`).
    fn open_whole(&self, dir: &Path, verify: bool) -> Result<ArrayFile> {
        ArrayFile::open(
            &dir.join(self.joined),
            &Expect {
                name: Some(self.name),
                dtype: Some(self.dtype),
                shape: Some(&[self.items, self.len]),
                verify,
            },
        )
    }

    /// The joined array that a build in this process has just written with checksum `sum`:
    /// its header, shape and checksum are checked, its data is not read again. Returns `sum`.
    fn open_built(&self, dir: &Path, sum: &str) -> Result<String> {
        let f = self.open_whole(dir, false)?;
        if f.header.checksum != sum {
            return Err(Error::new(
                f.path.display().to_string(),
                format!(
                    "checksum {} in the header, but this build wrote {sum}; the file was changed \
                     during the build — build again",
                    f.header.checksum
                ),
            ));
        }
        Ok(sum.to_string())
    }

    /// A writer of the joined file (`items × len`), to be filled in item order.
    fn create_joined(&self, dir: &Path) -> Result<ArrayWriter> {
        ArrayWriter::create(
            &dir.join(self.joined),
            self.name,
            self.dtype,
            &[self.items, self.len],
        )
    }

    /// Join the chunks into the joined file; returns its checksum. With `consume`, each chunk
    /// is removed once it is appended, so the merge needs the library's size in free disk once,
    /// not twice (123 GB for `paper`). Call [`Part::open_chunk`] on every chunk of every part
    /// first: a merge started before all shards are built then removes nothing.
    fn assemble(&self, dir: &Path, chunk: usize, consume: bool, bar: &Bar) -> Result<String> {
        let mut w = self.create_joined(dir)?;
        for k in 0..self.items.div_ceil(chunk) {
            let f = self.open_chunk(dir, chunk, k, true)?;
            w.write(f.bytes())?;
            if consume {
                let p = f.path.clone();
                drop(f);
                std::fs::remove_file(&p)
                    .map_err(|e| Error::io(&p, "remove the joined chunk", e))?;
            }
            bar.inc(1);
        }
        w.finish()
    }
}

fn mat_f32_rows(m: &Mat<f64>) -> Vec<f32> {
    // Stored item-major: [item][coordinate] (the transpose of `rank × n`).
    let mut v = Vec::with_capacity(m.nrows() * m.ncols());
    for j in 0..m.ncols() {
        for i in 0..m.nrows() {
            v.push(m[(i, j)] as f32);
        }
    }
    v
}

/// The manifest entry of a file written into `dir`.
fn entry(dir: &Path, rel: &str, checksum: String) -> ArrayEntry {
    ArrayEntry {
        path: rel.into(),
        checksum,
        bytes: std::fs::metadata(dir.join(rel))
            .map(|m| m.len())
            .unwrap_or(0),
    }
}

/// Write a whole array into `dir` and list it in `files`.
fn save(
    dir: &Path,
    rel: &str,
    name: &str,
    dtype: Dtype,
    shape: &[usize],
    bytes: &[u8],
    files: &mut Vec<ArrayEntry>,
) -> Result<()> {
    write_array(&dir.join(rel), name, dtype, shape, bytes)?;
    files.push(entry(dir, rel, crate::store::checksum(bytes)));
    Ok(())
}

fn save_f32(
    dir: &Path,
    rel: &str,
    name: &str,
    shape: &[usize],
    v: &[f32],
    files: &mut Vec<ArrayEntry>,
) -> Result<()> {
    save(dir, rel, name, Dtype::F32, shape, f32_bytes(v), files)
}

fn save_u32(
    dir: &Path,
    rel: &str,
    name: &str,
    v: &[u32],
    files: &mut Vec<ArrayEntry>,
) -> Result<()> {
    save(
        dir,
        rel,
        name,
        Dtype::U32,
        &[v.len()],
        bytemuck::cast_slice(v),
        files,
    )
}

/// Compress one item matrix and pick its representatives; writes `<kind>/coords.bsa`,
/// `<kind>/singular.bsa`, `<kind>/representatives.bsa` and `<kind>/x.bsa`. With
/// `search_energy` (materials only: an in-core SVD), the SVD keeps that much energy once, the
/// compression above is its truncation to the profile's energy (the same arrays as an SVD run
/// at that energy), and a second selection of representatives on the finer coordinates is
/// written as `<kind>/search-representatives.bsa` and `<kind>/search-x.bsa` (its report is the
/// second value).
///
/// With `normalise`, the SVD and the CX selection see every item's column scaled to unit norm,
/// so the energy and CX thresholds bound each item's *relative* error rather than the error of
/// the whole matrix, which the items with the largest values own. (Prefiltered tables span
/// orders of magnitude: a mirror-like material's peaks are 10⁴ times a rough one's, and without
/// this the rough materials' CX weights reconstruct almost nothing of them.) The stored
/// coordinates and CX weights are then scaled back, so they reconstruct the stored columns:
/// `b_j = Σ_k b_c(k) x̂_kj |b_j| / |b_c(k)|`.
#[allow(clippy::too_many_arguments)]
fn compress(
    dir: &Path,
    kind: &str,
    file: &ArrayFile,
    prof: &LibraryProfile,
    gram: bool,
    normalise: bool,
    search_energy: Option<f64>,
    files: &mut Vec<ArrayEntry>,
    stages: &Stages,
) -> Result<(CompressionReport, Option<CompressionReport>)> {
    let c = &prof.compression;
    let raw = ItemMatrix::new(file);
    let (b, norms) = if normalise {
        stages.stage(&format!("{kind} column norms"));
        let (b, n) = raw.unit_columns()?;
        (b, Some(n))
    } else {
        (raw, None)
    };
    stages.stage(&format!(
        "{kind} {} ({} × {})",
        if gram { "SVD" } else { "randomized SVD" },
        b.rows(),
        b.cols()
    ));
    let t = Instant::now();
    let (comp, fine) = if gram {
        match search_energy {
            Some(e) => {
                let fine = svd_gram(&b, e.max(c.material_energy), 4096, false)?;
                (fine.truncated(c.material_energy), Some(fine))
            }
            None => (svd_gram(&b, c.material_energy, 4096, false)?, None),
        }
    } else {
        let comp = rsvd_streaming_with(
            &b,
            &RsvdConfig {
                energy: c.geometry_energy,
                oversample: c.oversample,
                power_iters: c.power_iters,
                max_rank: c.max_rank.min(b.cols()).max(1),
                chunk: c.stream_chunk,
                seed: prof.seed,
                initial_rank: c.initial_rank,
                pilot: c.geometry_pilot.unwrap_or(0),
            },
            false,
            &|msg| stages.step(msg),
        )?;
        (comp, None)
    };
    let svd_seconds = t.elapsed().as_secs_f64();
    let n = comp.coords.ncols();
    let mut coords = comp.coords.clone();
    if let Some(nrm) = &norms {
        for j in 0..n {
            for r in 0..coords.nrows() {
                coords[(r, j)] *= nrm[j];
            }
        }
    }
    save_f32(
        dir,
        &format!("{kind}/coords.bsa"),
        &format!("{kind}-coords"),
        &[n, comp.rank],
        &mat_f32_rows(&coords),
        files,
    )?;
    let sv: Vec<f32> = comp.singular.iter().map(|&s| s as f32).collect();
    save_f32(
        dir,
        &format!("{kind}/singular.bsa"),
        &format!("{kind}-singular"),
        &[sv.len()],
        &sv,
        files,
    )?;
    stages.stage(&format!("{kind} CX (rank {})", comp.rank));
    let mut report = select(dir, kind, "", &comp, norms.as_deref(), prof, files)?;
    report.svd_seconds = svd_seconds;
    let search = match &fine {
        Some(fine) => {
            stages.stage(&format!("{kind} search CX (rank {})", fine.rank));
            Some(select(
                dir,
                kind,
                "search-",
                fine,
                norms.as_deref(),
                prof,
                files,
            )?)
        }
        None => None,
    };
    Ok((report, search))
}

/// Pick the representatives of one decomposition by CX and write
/// `<kind>/<prefix>representatives.bsa` and `<kind>/<prefix>x.bsa` (the weights scaled back by
/// the column `norms` the decomposition saw, see [`compress`]). The report's `svd_seconds` is 0.
fn select(
    dir: &Path,
    kind: &str,
    prefix: &str,
    comp: &crate::lowrank::Compressed,
    norms: Option<&[f64]>,
    prof: &LibraryProfile,
    files: &mut Vec<ArrayEntry>,
) -> Result<CompressionReport> {
    let c = &prof.compression;
    let t = Instant::now();
    let method = if c.cx_method == "leverage" {
        CxMethod::Leverage { seed: prof.seed }
    } else {
        CxMethod::PivotedQr
    };
    let sel = cx(
        comp.coords.as_ref(),
        c.cx_error,
        method,
        comp.coords.nrows().max(1) * 4,
    )?;
    let cx_seconds = t.elapsed().as_secs_f64();
    let n = comp.coords.ncols();
    let mut xw = sel.x.clone();
    if let Some(nrm) = norms {
        for j in 0..n {
            for (k, &ck) in sel.columns.iter().enumerate() {
                xw[(k, j)] *= if nrm[ck] > 0.0 { nrm[j] / nrm[ck] } else { 0.0 };
            }
        }
    }
    let cols: Vec<u32> = sel.columns.iter().map(|&j| j as u32).collect();
    save_u32(
        dir,
        &format!("{kind}/{prefix}representatives.bsa"),
        &format!("{kind}-{prefix}representatives"),
        &cols,
        files,
    )?;
    save_f32(
        dir,
        &format!("{kind}/{prefix}x.bsa"),
        &format!("{kind}-{prefix}x"),
        &[n, cols.len()],
        &mat_f32_rows(&xw),
        files,
    )?;
    // Error of the whole chain against B: the SVD's lost energy plus CX's error on the kept part.
    let lost = 1.0 - comp.kept_energy;
    let total_rel = (lost + sel.rel_error.powi(2) * comp.kept_energy)
        .max(0.0)
        .sqrt();
    Ok(CompressionReport {
        rank: comp.rank,
        energy_kept: comp.kept_energy,
        passes: comp.passes,
        pilot_columns: (comp.pilot_columns > 0).then_some(comp.pilot_columns),
        pilot_passes: (comp.pilot_columns > 0).then_some(comp.pilot_passes),
        representatives: cols.len(),
        cx_rel_error: sel.rel_error,
        total_rel_error: total_rel,
        method: c.cx_method.clone(),
        svd_seconds: 0.0,
        cx_seconds,
    })
}

/// Write the material solver's finer selection of representatives into the finished library
/// `dir` (`material/search-*.bsa`, replacing earlier entries of `files`) at the profile's
/// `compression.material_search_energy`: the material SVD is run again at that energy (seconds:
/// an in-core SVD of the prefiltered tables). `None` when the profile asks for none.
pub fn material_search_selection(
    dir: &Path,
    prof: &LibraryProfile,
    files: &mut Vec<ArrayEntry>,
    progress: &Progress,
) -> Result<Option<CompressionReport>> {
    let Some(e) = prof.compression.material_search_energy else {
        return Ok(None);
    };
    let mfile = ArrayFile::open(&dir.join("material/prefiltered.bsa"), &Expect::default())?;
    let (b, norms) = ItemMatrix::new(&mfile).unit_columns()?;
    let stages = progress.stages("refit");
    stages.stage(&format!("material SVD ({} × {})", b.rows(), b.cols()));
    let t = Instant::now();
    let fine = svd_gram(&b, e.max(prof.compression.material_energy), 4096, false)?;
    let svd_seconds = t.elapsed().as_secs_f64();
    stages.stage(&format!("material search CX (rank {})", fine.rank));
    files.retain(|f| !f.path.starts_with("material/search-"));
    let mut report = select(dir, "material", "search-", &fine, Some(&norms), prof, files)?;
    stages.finish();
    report.svd_seconds = svd_seconds;
    Ok(Some(report))
}

/// Peak resident memory of this process so far, in MiB (Linux; 0 elsewhere).
pub fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map(|kb| kb / 1024.0)
        .unwrap_or(0.0)
}

/// Join every chunk of `dir`, compress, and write the manifest. `times` carries the build's
/// times when the merge follows a build in the same process; `built` lists the joined arrays
/// that build wrote and their checksums ([`BuildReport::joined`]), taken as they are (header,
/// shape and checksum compared, the data not read again).
pub fn merge(
    dir: &Path,
    base: &Path,
    progress: &Progress,
    mut times: StageTimes,
    keep_chunks: bool,
    built: &[(&str, String)],
) -> Result<Manifest> {
    let ptext = std::fs::read_to_string(dir.join("profile.toml")).map_err(|e| {
        Error::io(
            &dir.join("profile.toml"),
            "read (is this a library build directory?)",
            e,
        )
    })?;
    let prof = LibraryProfile::parse(&ptext, &dir.join("profile.toml").display().to_string())?;
    let geos = geometry_items(&prof, base)?;
    let mats = material_items(&prof, base)?;
    let parts = parts(&prof, geos.len(), mats.len());
    let (rows, tlen) = (parts[0].len, parts[parts.len() - 1].len);
    let mut files = Vec::new();
    let t = Instant::now();
    // Each part is joined from its chunks when every chunk is there, with the right header and
    // shape; otherwise a verified joined array left by an earlier merge (which removed the
    // chunks it joined) stands for it; otherwise the merge stops, naming the first missing
    // chunk, before it joins (and removes) anything.
    let mut joined = Vec::new();
    for p in &parts {
        if let Some((_, sum)) = built.iter().find(|(rel, _)| *rel == p.joined) {
            joined.push(Some((p.open_built(dir, sum)?, false)));
            continue;
        }
        let missing = (0..p.items.div_ceil(prof.chunk))
            .find_map(|k| p.open_chunk(dir, prof.chunk, k, false).err());
        joined.push(match missing {
            None => None,
            Some(e) => match p.open_joined(dir) {
                Ok(f) => Some((f.header.checksum.clone(), true)),
                // The joined array is there but damaged, and an earlier merge removed its
                // chunks: no shard is missing, the part must be built again.
                Err(je) if dir.join(p.joined).exists() => {
                    return Err(Error::new(
                        je.context,
                        format!(
                            "{}; its chunks were removed when it was joined, so it cannot be \
                             merged again: rebuild the library with `biscale library build \
                             --profile {} --out {} --force`",
                            je.message.trim_end_matches("; rebuild the library"),
                            prof.name,
                            dir.display()
                        ),
                    ))
                }
                Err(_) => return Err(e),
            },
        });
    }
    let bar = progress.bar(
        parts
            .iter()
            .zip(&joined)
            .filter(|(_, j)| j.is_none())
            .map(|(p, _)| p.items.div_ceil(prof.chunk) as u64)
            .sum(),
        "merge: joining chunks",
    );
    for (p, done) in parts.iter().zip(joined) {
        let sum = match done {
            Some((sum, earlier)) => {
                if earlier {
                    progress.note(&format!(
                        "merge: {} was joined by an earlier merge; kept",
                        p.joined
                    ));
                }
                sum
            }
            None => p.assemble(dir, prof.chunk, !keep_chunks, &bar)?,
        };
        files.push(entry(dir, p.joined, sum));
    }
    bar.finish();
    times.assemble = t.elapsed().as_secs_f64();

    // Colours: each BRDF's own average colour and its colour-shift multipliers.
    let stages = progress.stages("merge");
    stages.stage("colours");
    let t = Instant::now();
    let lam: Vec<[f64; 3]> = mats
        .par_iter()
        .map(|m| {
            parse_material(&m.spec)
                .map(|mm| average_colour(&mm))
                .map_err(|e| e.within(format!("material item {}", m.index)))
        })
        .collect::<Result<_>>()?;
    let lam: Vec<f32> = lam.iter().flat_map(|c| c.map(|x| x as f32)).collect();
    save_f32(
        dir,
        "material/colour.bsa",
        "material-colour",
        &[mats.len(), 3],
        &lam,
        &mut files,
    )?;
    let shifts: Vec<f32> = (0..mats.len())
        .flat_map(|i| colour_shifts(&prof, i).into_iter().flatten())
        .collect();
    save_f32(
        dir,
        "material/colour-shifts.bsa",
        "material-colour-shifts",
        &[mats.len(), 1 + prof.material.colours, 3],
        &shifts,
        &mut files,
    )?;
    times.colours = t.elapsed().as_secs_f64();

    let mfile = ArrayFile::open(&dir.join("material/prefiltered.bsa"), &Expect::default())?;
    let (material, material_search) = compress(
        dir,
        "material",
        &mfile,
        &prof,
        true,
        true,
        prof.compression.material_search_energy,
        &mut files,
        &stages,
    )?;
    let gfile = ArrayFile::open(&dir.join("geometry/gamma.bsa"), &Expect::default())?;
    let (geometry, _) = compress(
        dir, "geometry", &gfile, &prof, false, false, None, &mut files, &stages,
    )?;
    stages.finish();
    times.compress = material.svd_seconds
        + material.cx_seconds
        + material_search.as_ref().map_or(0.0, |r| r.cx_seconds)
        + geometry.svd_seconds
        + geometry.cx_seconds;
    times.lobe_fit = fit_lobe_weights(dir, &prof, &mats, progress, &mut files)?;

    write_items(dir, &geos, &mats, &mut files)?;
    times.peak_rss_mib = peak_rss_mib();
    let mut manifest = Manifest {
        format: "biscale-library".into(),
        version: MANIFEST_VERSION,
        tool_version: env!("CARGO_PKG_VERSION").into(),
        profile: prof.name.clone(),
        profile_hash: prof.hash(),
        seed: prof.seed,
        geometries: geos.len(),
        materials: mats.len(),
        colours_per_material: 1 + prof.material.colours,
        gamma_rows: rows,
        table_len: tlen,
        material,
        material_search,
        geometry,
        files,
        build: times,
    };
    manifest.sort_files();
    manifest.write(dir)?;
    if !keep_chunks {
        let _ = std::fs::remove_dir_all(dir.join("chunks"));
    }
    Ok(manifest)
}

/// Store a finished library's light lobes in `f16` ([`crate::lobecodec`]) where they are `f32`
/// records: `geometry/lobe-heads.bsa` and a new `geometry/lobes.bsa`, each written to a
/// temporary file and renamed into place, and listed in `files`. The result is what a build
/// with `lobe_precision = "half"` writes (the same records, encoded the same way). Returns
/// whether anything was converted. The way back needs a rebuild: the `f32` records are gone.
pub fn convert_lobes_to_half(
    dir: &Path,
    lib: &super::Library,
    prof: &LibraryProfile,
    progress: &Progress,
    files: &mut Vec<ArrayEntry>,
) -> Result<bool> {
    let old = lib.geometry_lobes()?;
    if old.is_half() {
        return Ok(false);
    }
    let mut half = prof.clone();
    half.geometry.lobe_precision = LobePrecision::Half;
    let n = old.len();
    let parts = parts(&half, n, 0);
    let (heads, body) = (&parts[1], &parts[2]);
    let (mut wh, mut wb) = (heads.create_joined(dir)?, body.create_joined(dir)?);
    let bar = progress.bar(n as u64, "refit: light lobes to half precision");
    let (k, views) = (prof.geometry.lobe_clusters, old.layout.views.len());
    for start in (0..n).step_by(256) {
        let block: Vec<(Vec<f32>, Vec<half::f16>)> = (start..(start + 256).min(n))
            .into_par_iter()
            .map(|j| {
                let ll = old.read(j)?;
                let what = || format!("{} row {j}", old.path().display());
                let rec = ll
                    .record()
                    .ok_or_else(|| Error::new(what(), "not an f32 record"))?;
                crate::lobecodec::encode(rec, k, views).ok_or_else(|| {
                    Error::new(
                        what(),
                        "a light-lobe moment is beyond half precision's range; keep \
                         lobe_precision = \"single\"",
                    )
                })
            })
            .collect::<Result<_>>()?;
        for (h, b) in &block {
            wh.write(f32_bytes(h))?;
            wb.write(bytemuck::cast_slice(b))?;
        }
        bar.inc(block.len() as u64);
    }
    let (sh, sb) = (wh.finish()?, wb.finish()?);
    bar.finish();
    files.retain(|f| f.path != heads.joined && f.path != body.joined);
    files.push(entry(dir, heads.joined, sh));
    files.push(entry(dir, body.joined, sb));
    Ok(true)
}

/// The light-lobe records of `geometries` geometries of the library in `dir` (its manifest
/// need not exist yet).
fn open_lobes(
    dir: &Path,
    prof: &LibraryProfile,
    geometries: usize,
) -> Result<super::GeometryLobes> {
    super::GeometryLobes::open(
        |rel| ArrayFile::open(&dir.join(rel), &Expect::default()).map(std::sync::Arc::new),
        gamma_layout(prof),
        prof.geometry.lobe_clusters,
        geometries,
    )
}

/// Store a finished library's half-precision light lobes packed ([`crate::lobepack`]): a new
/// `geometry/lobes.bsa` (one run of words) and [`super::LOBE_OFFSETS`], each written to a
/// temporary file and renamed into place (the offsets first: a conversion stopped between
/// the two renames leaves the old records, which are one row per geometry and ignore them),
/// and listed in `files`. Every packed record is unpacked and compared with the record it
/// came from before it is written. Returns whether anything was converted (`false` where the
/// records are packed already).
pub fn convert_lobes_to_packed(
    dir: &Path,
    prof: &LibraryProfile,
    geometries: usize,
    progress: &Progress,
    files: &mut Vec<ArrayEntry>,
) -> Result<bool> {
    // Opened from the files (a conversion to half precision just before may have replaced
    // the records the library mapped).
    let old = open_lobes(dir, prof, geometries)?;
    if old.is_packed() {
        return Ok(false);
    }
    if !old.is_half() {
        return Err(Error::new(
            old.path().display().to_string(),
            "the records are f32: store them in half precision first (refit --half-lobes)",
        ));
    }
    let shape = crate::lightlobes::pack_shape(&old.layout, prof.geometry.lobe_clusters);
    let n = old.len();
    // Geometry `j`'s record packed, checked to unpack to itself.
    let packed = |j: usize| -> Result<Vec<half::f16>> {
        let what = || format!("{} row {j}", old.path().display());
        let lobes = old.read(j)?;
        let body = lobes
            .half_body()
            .ok_or_else(|| Error::new(what(), "not a half-precision record"))?;
        crate::lobepack::pack(body, &shape)
            .filter(|p| {
                crate::lobepack::unpack(p, &shape)
                    .is_some_and(|u| u.iter().zip(body).all(|(a, b)| a.to_bits() == b.to_bits()))
            })
            .ok_or_else(|| {
                Error::new(
                    what(),
                    "the record does not pack to itself (its zenith view nodes differ); keep \
                     the records unpacked",
                )
            })
    };
    // Two passes over the records: the header states the length, so the packed lengths
    // first, then the words.
    let blocks = |label: &str, each: &mut dyn FnMut(Vec<Vec<half::f16>>) -> Result<()>| {
        let bar = progress.bar(n as u64, label);
        for start in (0..n).step_by(256) {
            let block: Vec<Vec<half::f16>> = (start..(start + 256).min(n))
                .into_par_iter()
                .map(packed)
                .collect::<Result<_>>()?;
            let len = block.len() as u64;
            each(block)?;
            bar.inc(len);
        }
        bar.finish();
        Ok::<(), Error>(())
    };
    let mut offsets = vec![0u64];
    blocks("refit: packing the light lobes (sizes)", &mut |b| {
        for p in b {
            let last = offsets.last().copied().unwrap_or(0);
            offsets.push(last + p.len() as u64);
        }
        Ok(())
    })?;
    let words = offsets.last().copied().unwrap_or(0) as usize;
    // The offsets first: beside the old records (one row per geometry) they are not read.
    let orel = super::LOBE_OFFSETS;
    write_array(
        &dir.join(orel),
        "light-lobe-offsets",
        Dtype::U64,
        &[n + 1],
        bytemuck::cast_slice(&offsets),
    )?;
    let rel = "geometry/lobes.bsa";
    let mut w = ArrayWriter::create(&dir.join(rel), "light-lobes-packed", Dtype::F16, &[words])?;
    blocks("refit: packing the light lobes (words)", &mut |b| {
        b.iter().try_for_each(|p| w.write(bytemuck::cast_slice(p)))
    })?;
    let sum = w.finish()?;
    let osum = crate::store::checksum(bytemuck::cast_slice(&offsets));
    files.retain(|f| f.path != rel && f.path != orel);
    files.push(entry(dir, rel, sum));
    files.push(entry(dir, orel, osum));
    Ok(true)
}

/// Fit the geometry CX weights to the light lobes ([`super::lobefit`]), probed with the
/// material representatives' tables, and write `geometry/x-lobes.bsa` (listed in `files`; an
/// earlier entry of it is replaced). Needs the geometry and material arrays of the merge
/// (light lobes, representatives, `x.bsa`, prefiltered tables). Returns the seconds spent.
pub fn fit_lobe_weights(
    dir: &Path,
    prof: &LibraryProfile,
    mats: &[MaterialItem],
    progress: &Progress,
    files: &mut Vec<ArrayEntry>,
) -> Result<f64> {
    let t = Instant::now();
    let open = |rel: &str| ArrayFile::open(&dir.join(rel), &Expect::default());
    let x0 = open("geometry/x.bsa")?;
    let n = x0.header.shape.first().copied().unwrap_or(0);
    let lobes = open_lobes(dir, prof, n)?;
    let reps = open("geometry/representatives.bsa")?;
    let reps: Vec<usize> = reps.u32s()?.iter().map(|&k| k as usize).collect();
    let tables_file = open("material/prefiltered.bsa")?;
    let mreps = open("material/representatives.bsa")?;
    let pcfg = prefilter_config(prof);
    let tlen = table_len(prof);
    let tables = mreps
        .u32s()?
        .iter()
        .map(|&m| {
            let m = m as usize;
            let item = mats.get(m).ok_or_else(|| {
                Error::new(
                    mreps.path.display().to_string(),
                    format!("representative {m} is not a material of the library"),
                )
            })?;
            let mut data = vec![0f32; tlen];
            tables_file.read_data(m * tlen * 4, bytemuck::cast_slice_mut(&mut data))?;
            Prefiltered::from_table(&parse_material(&item.spec)?, &pcfg, data)
        })
        .collect::<Result<Vec<_>>>()?;
    let bar = progress.bar(
        n as u64,
        "merge: geometry weights fitted to the light lobes",
    );
    let x = super::lobefit::fit(&lobes, tables, &reps, x0.f32s()?, &|n| bar.inc(n as u64))?;
    bar.finish();
    files.retain(|f| f.path != "geometry/x-lobes.bsa");
    save_f32(
        dir,
        "geometry/x-lobes.bsa",
        "geometry-x-lobes",
        &[n, reps.len()],
        &x,
        files,
    )?;
    Ok(t.elapsed().as_secs_f64())
}

fn write_items(
    dir: &Path,
    geos: &[GeometryItem],
    mats: &[MaterialItem],
    files: &mut Vec<ArrayEntry>,
) -> Result<()> {
    for (rel, text) in [
        ("geometry/items.json", serde_json::to_string_pretty(geos)),
        ("material/items.json", serde_json::to_string_pretty(mats)),
    ] {
        let text =
            text.map_err(|e| Error::new(rel, format!("cannot encode the item list: {e}")))?;
        crate::atomic_write::write_bytes(&dir.join(rel), text.as_bytes())?;
        files.push(ArrayEntry {
            path: rel.into(),
            checksum: crate::store::checksum(text.as_bytes()),
            bytes: text.len() as u64,
        });
    }
    Ok(())
}
