//! Precomputed libraries of small-scale geometries and materials (paper Sec. 4–5): what they hold,
//! how they are built (in one process or in shards), stored, compressed, found in the cache and
//! opened lazily.
//!
//! A library is one directory:
//!
//! ```text
//! manifest.json                 counts, shapes, compression, checksums, build times (written last)
//! profile.toml                  the canonical profile it was built from
//! geometry/items.json           every geometry: index, family, generator spec
//! geometry/gamma.bsa            f16 [geometries, rows]: binned BVNDF columns (crate::gamma);
//!                               uf8 (crate::uf8) with geometry.gamma_precision = "byte"
//! geometry/coords.bsa           f32 [geometries, rank]: SVD coordinates Sigma V^T
//! geometry/singular.bsa         f32: singular values
//! geometry/representatives.bsa  u32: CX column indices c(k)
//! geometry/x.bsa                f32 [geometries, c]: CX weights X (Eq. 11)
//! geometry/x-lobes.bsa          f32 [geometries, c]: the same refitted to the light lobes (lobefit)
//! geometry/lobes.bsa            f16 [geometries, moments]: light lobes (crate::lightlobes) in
//!                               half precision (crate::lobecodec); with
//!                               geometry.lobe_precision = "single" (and in libraries built
//!                               before it), f32 [geometries, record], the records themselves
//! geometry/lobe-heads.bsa       f32 [geometries, 5 × clusters]: the half-precision records'
//!                               cluster headers
//! material/...                  the same for materials, with prefiltered.bsa (f32 [materials,
//!                               table]) instead of gamma.bsa, and colour.bsa / colour-shifts.bsa
//! chunks/                       build work of shards (and of --keep-chunks), removed after the merge
//! */.NAME.bsa.partial(.log)     a one-process build's joined array while it grows (store::PartialArray)
//! ```
//!
//! [`Library::open`] reads only the manifest; each array is mapped and checked the first time a
//! run asks for it, and the library records what was read so runs can say so in their log.

pub mod bench;
pub mod build;
pub mod commands;
pub mod items;
pub mod lobefit;
pub mod manifest;
pub mod profile;
pub mod progress;

use crate::error::{Error, Result};
use crate::gamma::GammaLayout;
use crate::lightlobes::LightLobes;
use crate::store::{ArrayFile, Dtype, Expect};
use build::{merge, Shard};
use half::f16;
use items::{GeometryItem, MaterialItem};
use manifest::{Manifest, ShardTimes, StageTimes};
use profile::LibraryProfile;
use progress::Progress;
use std::borrow::Cow;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// Build a whole library into `dir` in this process (all chunks, then the merge). `base` is the
/// profile file's directory: relative `texture_dirs` / `merl_dirs` are resolved against it and
/// stored absolute. If `dir` already holds the finished library of this profile, it is returned
/// as it is ("already built; nothing to do"), unless `force` is set.
pub fn build_all(
    prof: &LibraryProfile,
    base: &Path,
    dir: &Path,
    progress: &Progress,
    keep_chunks: bool,
    force: bool,
) -> Result<Manifest> {
    let t = Instant::now();
    // Without chunk files to keep, the chunks go straight into the joined arrays.
    let rep = if keep_chunks {
        build::build_shard(prof, base, dir, Shard::ALL, force, progress)?
    } else {
        build::build_joined(prof, base, dir, force, progress)?
    };
    if rep.already_built {
        return Manifest::read(dir);
    }
    let times = StageTimes {
        geometry_seconds: rep.geometry_seconds,
        material_seconds: rep.material_seconds,
        threads: rayon::current_num_threads(),
        shards_in_process: 1,
        ..Default::default()
    };
    let mut m = merge(dir, base, progress, times, keep_chunks, &rep.joined)?;
    m.build.total_seconds = t.elapsed().as_secs_f64();
    m.write(dir)?;
    Ok(m)
}

/// Merge the shards built into `dir` by `biscale library build --shard i/N`.
pub fn merge_shards(dir: &Path, progress: &Progress, keep_chunks: bool) -> Result<Manifest> {
    let t = Instant::now();
    let (_, base) = profile_of(dir)?;
    // The shards' own times, recorded beside their chunks (which the merge removes).
    let (shards, n, bad) = ShardTimes::collect(dir);
    for b in bad {
        progress.note(&format!(
            "merge: {b} is not a shard time record; its times are left out"
        ));
    }
    let mut times = StageTimes {
        geometry_seconds: shards.geometry_seconds,
        material_seconds: shards.material_seconds,
        threads: rayon::current_num_threads(),
        shards_merged: n,
        ..Default::default()
    };
    // Merging a finished library again (to rewrite a damaged item list, say) keeps the item
    // times its manifest recorded; the total is then this merge's.
    if n == 0 {
        if let Ok(old) = Manifest::read(dir) {
            times.geometry_seconds = old.build.geometry_seconds;
            times.material_seconds = old.build.material_seconds;
            times.shards_merged = old.build.shards_merged;
        }
    }
    let mut m = merge(dir, &base, progress, times, keep_chunks, &[])?;
    m.build.total_seconds = t.elapsed().as_secs_f64();
    m.write(dir)?;
    Ok(m)
}

/// The manifest of the finished library in `dir` if it was built from `prof` (its profile hash;
/// `prof`'s directories already resolved, see [`LibraryProfile::resolve_dirs`]), its
/// `profile.toml` agrees, and every file it lists is present with the listed size. `None`
/// otherwise: no manifest, another profile, or a damaged or incomplete directory.
pub fn finished(dir: &Path, prof: &LibraryProfile) -> Option<Manifest> {
    if !dir.join("manifest.json").is_file() {
        return None;
    }
    let lib = Library::open(dir).ok()?;
    let complete = lib.manifest.profile_hash == prof.hash()
        && lib
            .manifest
            .files
            .iter()
            .all(|f| std::fs::metadata(dir.join(&f.path)).is_ok_and(|m| m.len() == f.bytes));
    complete.then_some(lib.manifest)
}

/// The profile stored in a build directory. A build stores `texture_dirs` / `merl_dirs` as
/// absolute paths; relative ones (libraries from older builds) resolve against the directory.
fn profile_of(dir: &Path) -> Result<(LibraryProfile, PathBuf)> {
    let p = dir.join("profile.toml");
    let text = std::fs::read_to_string(&p)
        .map_err(|e| Error::io(&p, "read (is this a library directory?)", e))?;
    Ok((
        LibraryProfile::parse(&text, &p.display().to_string())?,
        dir.to_path_buf(),
    ))
}

/// The cache root: `--cache-dir`, else `$BISCALE_CACHE`, else `$XDG_CACHE_HOME/biscale`, else
/// `~/.cache/biscale`, else `outputs/cache`.
pub fn cache_root(explicit: Option<&Path>) -> PathBuf {
    if let Some(p) = explicit {
        return p.to_path_buf();
    }
    if let Some(p) = std::env::var_os("BISCALE_CACHE") {
        return PathBuf::from(p);
    }
    if let Some(p) = std::env::var_os("XDG_CACHE_HOME") {
        return PathBuf::from(p).join("biscale");
    }
    if let Some(h) = std::env::var_os("HOME") {
        return PathBuf::from(h).join(".cache").join("biscale");
    }
    PathBuf::from("outputs").join("cache")
}

/// Where the cache keeps the library of `prof`: named by profile and the hash of its contents.
pub fn cache_path(prof: &LibraryProfile, root: &Path) -> PathBuf {
    root.join("libraries")
        .join(format!("{}-{}", prof.name, &prof.hash()[..12]))
}

/// Profiles with more geometries than this are not built as a side effect of another command
/// ([`ensure`]): `paper16` (10,277, about 6 minutes on 2 cores) is, `paper4` (41,108, about
/// 20 minutes) and `paper` (about an hour) need `biscale library build`.
pub const AUTO_BUILD_MAX_GEOMETRIES: usize = 20_000;

/// Open the cached library of `profile` (a name or a path), building it first if it is missing
/// or incomplete (a half-built one resumes) and no larger than [`AUTO_BUILD_MAX_GEOMETRIES`].
pub fn ensure(profile: &str, cache: Option<&Path>, progress: &Progress) -> Result<Library> {
    let (prof, ppath) = LibraryProfile::load(profile)?;
    let dir = cache_path(&prof, &cache_root(cache));
    if dir.join("manifest.json").exists() {
        progress.note(&format!("library: using {} ({})", dir.display(), prof.name));
        return Library::open(&dir);
    }
    let n = prof.geometry_count();
    if n > AUTO_BUILD_MAX_GEOMETRIES {
        return Err(Error::new(
            format!("library profile '{}'", prof.name),
            format!(
                "its library ({n} geometries) is not built in {}, and one that large (more than \
                 {AUTO_BUILD_MAX_GEOMETRIES} geometries) is not built as a side effect: build it \
                 first with `biscale library build --profile {profile}{}` (resumable, and it \
                 can be sharded over a cluster: docs/cluster), or pass --library DIR",
                dir.display(),
                cache.map_or(String::new(), |c| format!(" --cache-dir {}", c.display()))
            ),
        ));
    }
    progress.note(&format!(
        "library: building profile '{}' into {} (first use; later runs reuse it)",
        prof.name,
        dir.display()
    ));
    let base = ppath.parent().map(Path::to_path_buf).unwrap_or_default();
    build_all(&prof, &base, &dir, progress, false, false)?;
    Library::open(&dir)
}

/// The light lobes of every library geometry ([`crate::lightlobes`]), read from the mapped
/// arrays: `geometry/lobes.bsa` holds the `f32` records, or (`geometry.lobe_precision = "half"`,
/// [`crate::lobecodec`]) their moments in `f16` beside their headers in
/// `geometry/lobe-heads.bsa`, or (packed by `library refit --pack-lobes`, [`crate::lobepack`])
/// the packed records one after the other, where `geometry/lobe-offsets.bsa` says.
pub struct GeometryLobes {
    file: Arc<ArrayFile>,
    heads: Option<Arc<ArrayFile>>,
    /// For packed records: where each geometry's starts in `file`, one more at the end.
    offsets: Option<Arc<ArrayFile>>,
    pub layout: GammaLayout,
    clusters: usize,
    /// Elements per row of `file` (not packed).
    len: usize,
}

/// The cluster headers beside half-precision or packed records must be `f32` [geometries,
/// clusters × 5].
fn check_heads(h: &ArrayFile, geometries: usize, clusters: usize) -> Result<()> {
    let want = [geometries, clusters * crate::lightlobes::HEAD];
    if h.header.shape == want && h.header.dtype == Dtype::F32 {
        return Ok(());
    }
    Err(Error::new(
        h.path.display().to_string(),
        format!(
            "element type {:?} and shape {:?}: expected F32 {want:?} (geometries × cluster headers)",
            h.header.dtype, h.header.shape
        ),
    ))
}

/// The packed records' offsets, relative to a library's directory.
pub const LOBE_OFFSETS: &str = "geometry/lobe-offsets.bsa";

impl GeometryLobes {
    /// The records of `geometries` geometries in `file` (and `heads`, for the half-precision
    /// form; and `offsets`, for the packed form), their types and shapes checked against
    /// `layout` and `clusters`.
    pub fn new(
        file: Arc<ArrayFile>,
        heads: Option<Arc<ArrayFile>>,
        offsets: Option<Arc<ArrayFile>>,
        layout: GammaLayout,
        clusters: usize,
        geometries: usize,
    ) -> Result<Self> {
        if let (Some(o), Some(h)) = (&offsets, &heads) {
            return Self::packed(file, h.clone(), o.clone(), layout, clusters, geometries);
        }
        let record = crate::lightlobes::record_len(&layout, clusters);
        let shape = |f: &ArrayFile, want: [usize; 2], what: &str| {
            if f.header.shape == want {
                Ok(())
            } else {
                Err(Error::new(
                    f.path.display().to_string(),
                    format!(
                        "shape {:?} does not match the profile's {want:?} (geometries × {what})",
                        f.header.shape
                    ),
                ))
            }
        };
        let len = match (file.header.dtype, &heads) {
            (Dtype::F32, _) => {
                shape(&file, [geometries, record], "light-lobe record")?;
                record
            }
            (Dtype::F16, Some(h)) => {
                let len = crate::lobecodec::half_len(record, clusters);
                shape(
                    &file,
                    [geometries, len],
                    "half-precision light-lobe moments",
                )?;
                check_heads(h, geometries, clusters)?;
                len
            }
            (d, _) => {
                return Err(Error::new(
                    file.path.display().to_string(),
                    format!(
                        "element type {d:?}: expected F32 records, or F16 moments with \
                         geometry/lobe-heads.bsa beside them"
                    ),
                ))
            }
        };
        Ok(GeometryLobes {
            file,
            heads,
            offsets: None,
            layout,
            clusters,
            len,
        })
    }

    /// The records of `geometries` geometries, their arrays opened by `open` (a path relative
    /// to the library's directory): `geometry/lobes.bsa`, and `geometry/lobe-heads.bsa` beside
    /// half-precision or packed records, and [`LOBE_OFFSETS`] beside packed ones (whose
    /// `lobes.bsa` is one run of words).
    pub fn open(
        open: impl Fn(&str) -> Result<Arc<ArrayFile>>,
        layout: GammaLayout,
        clusters: usize,
        geometries: usize,
    ) -> Result<Self> {
        let file = open("geometry/lobes.bsa")?;
        let heads = (file.header.dtype == Dtype::F16)
            .then(|| open("geometry/lobe-heads.bsa"))
            .transpose()?;
        let offsets = (file.header.shape.len() == 1)
            .then(|| open(LOBE_OFFSETS))
            .transpose()?;
        Self::new(file, heads, offsets, layout, clusters, geometries)
    }

    /// [`Self::new`] for packed records: `file` one run of `f16` words, `offsets` `u64`
    /// (`geometries + 1`, from 0 to the run's length, never decreasing).
    fn packed(
        file: Arc<ArrayFile>,
        heads: Arc<ArrayFile>,
        offsets: Arc<ArrayFile>,
        layout: GammaLayout,
        clusters: usize,
        geometries: usize,
    ) -> Result<Self> {
        let bad = |f: &ArrayFile, m: String| Err(Error::new(f.path.display().to_string(), m));
        if file.header.dtype != Dtype::F16 || file.header.shape.len() != 1 {
            return bad(
                &file,
                format!(
                    "element type {:?} and shape {:?}: packed light-lobe records are one run of \
                     F16 words",
                    file.header.dtype, file.header.shape
                ),
            );
        }
        if offsets.header.shape != [geometries + 1] || offsets.header.dtype != Dtype::U64 {
            return bad(
                &offsets,
                format!(
                    "element type {:?} and shape {:?}: expected U64 [{}] (geometries + 1)",
                    offsets.header.dtype,
                    offsets.header.shape,
                    geometries + 1
                ),
            );
        }
        let o = offsets.u64s()?;
        if o.first() != Some(&0)
            || o.last() != Some(&(file.header.shape[0] as u64))
            || o.windows(2).any(|w| w[0] > w[1])
        {
            return bad(
                &offsets,
                format!(
                    "the offsets must run from 0 to {} (the words of {}) without decreasing",
                    file.header.shape[0],
                    file.path.display()
                ),
            );
        }
        check_heads(&heads, geometries, clusters)?;
        Ok(GeometryLobes {
            file,
            heads: Some(heads),
            offsets: Some(offsets),
            layout,
            clusters,
            len: 0,
        })
    }

    /// Whether the records are the packed form.
    pub fn is_packed(&self) -> bool {
        self.offsets.is_some()
    }

    /// Geometry `j`'s elements in `file`.
    fn span(&self, j: usize) -> Result<std::ops::Range<usize>> {
        let missing = || Error::new(self.what(j), "no such geometry");
        match &self.offsets {
            None => Ok(j * self.len..(j + 1) * self.len),
            Some(o) => {
                let o = o.u64s()?;
                match (o.get(j), o.get(j + 1)) {
                    (Some(&a), Some(&b)) => Ok(a as usize..b as usize),
                    _ => Err(missing()),
                }
            }
        }
    }

    /// Whether the records are the half-precision form.
    pub fn is_half(&self) -> bool {
        self.heads.is_some()
    }

    /// How many geometries.
    pub fn len(&self) -> usize {
        match &self.offsets {
            Some(o) => o.header.shape.first().map_or(0, |n| n.saturating_sub(1)),
            None => self.file.header.shape.first().copied().unwrap_or(0),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The records' file (for messages).
    pub fn path(&self) -> &Path {
        &self.file.path
    }

    fn what(&self, j: usize) -> String {
        format!("{} row {j}", self.file.path.display())
    }

    /// Geometry `j`'s lobes from its `f32` record.
    fn single<'a>(&'a self, j: usize, rec: Cow<'a, [f32]>) -> Result<LightLobes<'a>> {
        LightLobes::from_record(&self.layout, self.clusters, rec, &self.what(j))
    }

    /// Geometry `j`'s lobes from its half-precision (or packed) header and moments.
    fn half<'a>(
        &'a self,
        j: usize,
        head: &[f32],
        body: Cow<'a, [f16]>,
        index: Option<&'a crate::lobepack::Index>,
    ) -> Result<LightLobes<'a>> {
        if self.is_packed() {
            LightLobes::from_packed_indexed(
                &self.layout,
                self.clusters,
                head,
                body,
                index,
                &self.what(j),
            )
        } else {
            LightLobes::from_half(&self.layout, self.clusters, head, body, &self.what(j))
        }
    }

    /// Geometry `j`'s lobes (borrowed from the mapping; nothing is copied).
    pub fn get(&self, j: usize) -> Result<LightLobes<'_>> {
        self.get_indexed(j, None)
    }

    /// Where geometry `j`'s packed record's rows lie (`None` for records that are not packed):
    /// for [`Self::get_indexed`], when one record is read many times (a target look).
    pub fn index(&self, j: usize) -> Result<Option<crate::lobepack::Index>> {
        if !self.is_packed() {
            return Ok(None);
        }
        let words = self
            .file
            .f16s()?
            .get(self.span(j)?)
            .ok_or_else(|| Error::new(self.what(j), "no such geometry"))?;
        crate::lobepack::Index::new(
            words,
            &crate::lightlobes::pack_shape(&self.layout, self.clusters),
        )
        .map(Some)
        .ok_or_else(|| Error::new(self.what(j), "the packed record does not match its masks"))
    }

    /// [`Self::get`] with the packed record's index made before ([`Self::index`]).
    pub fn get_indexed<'a>(
        &'a self,
        j: usize,
        index: Option<&'a crate::lobepack::Index>,
    ) -> Result<LightLobes<'a>> {
        let rows = self.span(j)?;
        let missing = || Error::new(self.what(j), "no such geometry");
        match &self.heads {
            None => {
                let rec = self.file.f32s()?.get(rows).ok_or_else(missing)?;
                self.single(j, Cow::Borrowed(rec))
            }
            Some(h) => {
                let k = self.clusters * crate::lightlobes::HEAD;
                let head = h.f32s()?.get(j * k..(j + 1) * k).ok_or_else(missing)?;
                let body = self.file.f16s()?.get(rows).ok_or_else(missing)?;
                self.half(j, head, Cow::Borrowed(body), index)
            }
        }
    }

    /// Geometry `j`'s lobes copied out with positioned reads (a pass over every geometry
    /// through the map would keep the whole file resident).
    pub fn read(&self, j: usize) -> Result<LightLobes<'_>> {
        let rows = self.span(j)?;
        let at = rows.start * self.file.header.dtype.size();
        match &self.heads {
            None => {
                let mut rec = vec![0f32; self.len];
                self.file
                    .read_data(at, bytemuck::cast_slice_mut(&mut rec))?;
                self.single(j, Cow::Owned(rec))
            }
            Some(h) => {
                let k = self.clusters * crate::lightlobes::HEAD;
                let mut head = vec![0f32; k];
                h.read_data(j * k * 4, bytemuck::cast_slice_mut(&mut head))?;
                let mut body = vec![f16::ZERO; rows.len()];
                self.file
                    .read_data(at, bytemuck::cast_slice_mut(&mut body))?;
                self.half(j, &head, Cow::Owned(body), None)
            }
        }
    }

    /// Start reading the records of geometries `js` into memory without waiting for them
    /// ([`ArrayFile::will_need`]), before a pass that reads them all, in the order two
    /// workers splitting `js` in halves reach the records (from the start and from the middle,
    /// alternately). (The headers, 20 bytes per cluster, are left to the reads themselves.)
    /// No hint is given when a sample of the records ([`RESIDENT_SAMPLE`] of them, spread over
    /// `js`) is in memory whole: the records of a library that fits in memory are there after
    /// its first passes, and the hint would only have the kernel look up each of their pages
    /// on a thread beside the solve's own (on `paper`, 4,096 records of 26 pages each: about
    /// 10 ms of a geometry solve, docs/solvers.md).
    pub fn will_need(&self, js: &[usize]) {
        let size = self.file.header.dtype.size();
        let half = js.len().div_ceil(2);
        let ranges: Vec<(usize, usize)> = (0..half)
            .flat_map(|i| [js.get(i), js.get(half + i)])
            .flatten()
            .filter_map(|&j| self.span(j).ok())
            .map(|r| (r.start * size, r.len() * size))
            .collect();
        let every = (ranges.len() / RESIDENT_SAMPLE).max(1);
        let sample: Vec<(usize, usize)> = ranges.iter().step_by(every).copied().collect();
        if !self.file.resident(&sample) {
            self.file.will_need(ranges);
        }
    }
}

/// Records [`GeometryLobes::will_need`] checks are in memory before it gives its hint.
pub const RESIDENT_SAMPLE: usize = 32;

/// The value in `cell`, made by `make` on first use (a failure is returned, not cached).
fn cached<T>(
    cell: &std::sync::OnceLock<Arc<T>>,
    make: impl FnOnce() -> Result<T>,
) -> Result<Arc<T>> {
    if let Some(v) = cell.get() {
        return Ok(v.clone());
    }
    let v = Arc::new(make()?);
    Ok(cell.get_or_init(|| v).clone())
}

/// Arrays at most this large are checksummed whenever a run opens them.
pub const VERIFY_BYTES: usize = 128 << 20;

/// An opened library: the manifest, and arrays mapped on first use.
pub struct Library {
    pub dir: PathBuf,
    pub manifest: Manifest,
    pub profile: LibraryProfile,
    arrays: Mutex<BTreeMap<String, Arc<ArrayFile>>>,
    reads: Mutex<Vec<String>>,
    /// The item lists, parsed (and checked against the manifest) on first use.
    geometry_items: std::sync::OnceLock<Arc<Vec<GeometryItem>>>,
    material_items: std::sync::OnceLock<Arc<Vec<MaterialItem>>>,
    /// Checksum every array on open, whatever its size (`library verify`).
    pub verify_all_arrays: bool,
}

impl Library {
    /// Read the manifest and the profile; no array is touched.
    pub fn open(dir: &Path) -> Result<Self> {
        if dir.exists() && !dir.is_dir() {
            return Err(Error::new(
                dir.display().to_string(),
                "is a file, not a library directory (a library is the directory `biscale library \
                 build --out DIR` makes)",
            ));
        }
        if !dir.is_dir() {
            return Err(Error::new(
                dir.display().to_string(),
                "no such library directory (build one with `biscale library build --profile P \
                 --out DIR`, or leave --library out to use the cached build of the profile)",
            ));
        }
        let manifest = Manifest::read(dir)?;
        let (profile, _) = profile_of(dir)?;
        if profile.hash() != manifest.profile_hash {
            return Err(Error::new(
                dir.join("profile.toml").display().to_string(),
                "does not match manifest.json (profile hash differs): the library is inconsistent; rebuild it",
            ));
        }
        Ok(Library {
            dir: dir.to_path_buf(),
            manifest,
            profile,
            arrays: Mutex::new(BTreeMap::new()),
            reads: Mutex::new(Vec::new()),
            geometry_items: std::sync::OnceLock::new(),
            material_items: std::sync::OnceLock::new(),
            verify_all_arrays: false,
        })
    }

    /// Map `rel` (a path listed in the manifest), checking its header, its length and — for arrays
    /// up to [`VERIFY_BYTES`] — its checksum, once. Larger arrays (the geometry matrix, tens of
    /// GB at paper scale) are checked by `biscale library verify`; a solve reads only a few of
    /// their columns.
    pub fn array(&self, rel: &str) -> Result<Arc<ArrayFile>> {
        if let Some(a) = self.arrays.lock().ok().and_then(|m| m.get(rel).cloned()) {
            return Ok(a);
        }
        let entry = self
            .manifest
            .files
            .iter()
            .find(|e| e.path == rel)
            .ok_or_else(|| {
                Error::new(
                    self.dir.join("manifest.json").display().to_string(),
                    format!("lists no file '{rel}'"),
                )
            })?;
        let mut f = ArrayFile::open(&self.dir.join(rel), &Expect::default())?;
        if self.verify_all_arrays || f.header.data_bytes() <= VERIFY_BYTES {
            f.verify()?;
        }
        if f.header.checksum != entry.checksum {
            return Err(Error::new(
                f.path.display().to_string(),
                format!("checksum {} differs from the manifest's {}: files from different builds; rebuild", f.header.checksum, entry.checksum),
            ));
        }
        let f = Arc::new(f);
        if let Ok(mut r) = self.reads.lock() {
            let unchecked = if f.verified {
                ""
            } else {
                ", mapped without a checksum pass: `biscale library verify` checks it"
            };
            r.push(format!(
                "{rel} ({:.1} MB{unchecked})",
                f.header.data_bytes() as f64 / 1e6
            ));
        }
        if let Ok(mut m) = self.arrays.lock() {
            m.insert(rel.into(), f.clone());
        }
        Ok(f)
    }

    /// What this run has read so far (for the log).
    pub fn reads(&self) -> Vec<String> {
        self.reads.lock().map(|r| r.clone()).unwrap_or_default()
    }

    fn json<T: serde::de::DeserializeOwned>(&self, rel: &str) -> Result<T> {
        let p = self.dir.join(rel);
        let bytes = std::fs::read(&p).map_err(|e| Error::io(&p, "read", e))?;
        if let Some(e) = self.manifest.files.iter().find(|e| e.path == rel) {
            if crate::store::checksum(&bytes) != e.checksum {
                return Err(Error::new(
                    p.display().to_string(),
                    format!(
                        "checksum differs from the manifest: the file was changed; \
                         `biscale library merge {}` writes the item lists again from its \
                         profile.toml",
                        self.dir.display()
                    ),
                ));
            }
        }
        if let Ok(mut r) = self.reads.lock() {
            r.push(format!("{rel} ({:.1} kB)", bytes.len() as f64 / 1e3));
        }
        serde_json::from_slice(&bytes)
            .map_err(|e| Error::new(p.display().to_string(), format!("corrupted item list: {e}")))
    }

    /// The geometry items (`geometry/items.json`, read and checked once per opened library).
    pub fn geometry_items(&self) -> Result<Arc<Vec<GeometryItem>>> {
        cached(&self.geometry_items, || self.json("geometry/items.json"))
    }

    /// The material items (`material/items.json`, read and checked once per opened library).
    pub fn material_items(&self) -> Result<Arc<Vec<MaterialItem>>> {
        cached(&self.material_items, || self.json("material/items.json"))
    }

    pub fn gamma_layout(&self) -> GammaLayout {
        build::gamma_layout(&self.profile)
    }

    /// The geometries' binned BVNDF columns (`geometry/gamma.bsa`), read one column at a time
    /// in whatever precision the library stores them.
    pub fn binned_columns(&self) -> Result<BinnedColumns> {
        Ok(BinnedColumns {
            file: self.array("geometry/gamma.bsa")?,
            rows: self.gamma_layout().rows(),
        })
    }

    /// The geometry CX weights to combine with the representatives' light-lobe values:
    /// `geometry/x-lobes.bsa` ([`lobefit`]: fitted to the light lobes) when the library has it,
    /// else `geometry/x.bsa` (fitted to the binned columns).
    pub fn geometry_lobe_weights(&self) -> Result<Arc<ArrayFile>> {
        if self.has("geometry/x-lobes.bsa") {
            self.array("geometry/x-lobes.bsa")
        } else {
            self.array("geometry/x.bsa")
        }
    }

    /// Whether the manifest lists the file `rel` (arrays added by later versions, such as
    /// `geometry/x-lobes.bsa`, are missing from older libraries).
    pub fn has(&self, rel: &str) -> bool {
        self.manifest.files.iter().any(|f| f.path == rel)
    }

    /// Every geometry's light lobes (`geometry/lobes.bsa`, and `geometry/lobe-heads.bsa` beside
    /// half-precision ones, mapped on first use).
    pub fn geometry_lobes(&self) -> Result<GeometryLobes> {
        GeometryLobes::open(
            |rel| self.array(rel),
            self.gamma_layout(),
            self.profile.geometry.lobe_clusters,
            self.manifest.geometries,
        )
    }

    /// Check every file against the manifest (reads everything).
    pub fn verify_all(&mut self) -> Result<usize> {
        self.verify_all_arrays = true;
        // Arrays already mapped without a checksum pass are mapped again, with it.
        if let Ok(mut m) = self.arrays.lock() {
            m.retain(|_, a| a.verified);
        }
        for e in &self.manifest.files {
            if e.path.ends_with(".json") {
                let _: serde_json::Value = self.json(&e.path)?;
            } else {
                self.array(&e.path)?;
            }
        }
        Ok(self.manifest.files.len())
    }
}

/// The binned BVNDF columns of a library's geometries (`geometry/gamma.bsa`: `f16`, or the
/// 8-bit [`crate::uf8`] of `geometry.gamma_precision = "byte"`).
pub struct BinnedColumns {
    pub file: Arc<ArrayFile>,
    pub rows: usize,
}

impl BinnedColumns {
    /// Column `j` (geometry `j`) as stored.
    fn stored(&self, j: usize) -> Result<StoredColumn<'_>> {
        let missing = || {
            Error::new(
                self.file.path.display().to_string(),
                format!("no column for geometry {j}"),
            )
        };
        let range = j * self.rows..(j + 1) * self.rows;
        Ok(match self.file.header.dtype {
            Dtype::UF8 => StoredColumn::Bytes(self.file.uf8s()?.get(range).ok_or_else(missing)?),
            _ => StoredColumn::Half(self.file.f16s()?.get(range).ok_or_else(missing)?),
        })
    }

    /// Column `j` (geometry `j`) in `f32`.
    pub fn column(&self, j: usize) -> Result<Vec<f32>> {
        use crate::gamma::ColumnElement;
        let mut out = vec![0f32; self.rows];
        match self.stored(j)? {
            StoredColumn::Bytes(c) => u8::to_f32s(c, &mut out),
            StoredColumn::Half(c) => f16::to_f32s(c, &mut out),
        }
        Ok(out)
    }

    /// `fbar` of geometry `j` at `resp`'s pairs ([`crate::gamma::Response::apply`] on its
    /// column), read from the stored column: only the row blocks the pairs use are converted,
    /// not the whole column as [`Self::column`] would (the same numbers).
    pub fn respond(&self, resp: &crate::gamma::Response, j: usize) -> Result<Vec<f64>> {
        Ok(match self.stored(j)? {
            StoredColumn::Bytes(c) => resp.apply(c),
            StoredColumn::Half(c) => resp.apply(c),
        })
    }
}

/// A binned column as the library stores it.
enum StoredColumn<'a> {
    Bytes(&'a [u8]),
    Half(&'a [f16]),
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testdir::TestDir;

    #[test]
    fn a_paper_scale_library_is_not_built_as_a_side_effect() {
        let cache = TestDir::new("ensure-paper");
        let e = ensure("paper", Some(&cache), &Progress { quiet: true })
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(
            e.contains("164431 geometries")
                && e.contains("biscale library build --profile paper --cache-dir"),
            "{e}"
        );
        // Nothing was started.
        assert!(!cache.join("libraries").exists());
    }
}
