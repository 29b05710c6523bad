//! Library files on disk: self-describing, checksummed, memory-mappable array files.
//!
//! An array file is `MAGIC` (8 bytes, `BSCLARR\x01`), the header length (`u32`, little endian),
//! a JSON header padded with spaces so the data starts at a multiple of 64 bytes, then the raw
//! little-endian data. The header names the array, its element type, its shape (row-major) and the
//! xxh3-128 checksum of the data, so a file can be checked on its own; the library manifest repeats
//! the checksums. Files are written to a temporary file and renamed ([`crate::atomic_write`]);
//! large arrays are streamed ([`ArrayWriter`]) and their checksum patched in before the rename.
//! Opening maps the file ([`memmap2`]) and checks magic, version, name, type, shape, length and
//! (when asked) the checksum: a corrupted, truncated or mismatched file is an error naming it.

use crate::error::{Error, Result};
use memmap2::Mmap;
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::io::{Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use xxhash_rust::xxh3::Xxh3;

pub const MAGIC: &[u8; 8] = b"BSCLARR\x01";
pub const ARRAY_VERSION: u32 = 1;
const ALIGN: usize = 64;
/// Data at most this large is hashed through the map by [`ArrayFile::verify`] (the arrays a
/// run checks when it opens them, `library::VERIFY_BYTES`, and then reads through the map);
/// larger data in pieces copied out of the page cache.
pub const HASH_MAPPED_BYTES: usize = 128 << 20;
const EMPTY_SUM: &str = "00000000000000000000000000000000";

/// Element types of array files.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Dtype {
    /// The unsigned 8-bit float of [`crate::uf8`].
    UF8,
    F16,
    F32,
    F64,
    U32,
    U64,
}

impl Dtype {
    pub fn size(self) -> usize {
        match self {
            Dtype::UF8 => 1,
            Dtype::F16 => 2,
            Dtype::F32 | Dtype::U32 => 4,
            Dtype::F64 | Dtype::U64 => 8,
        }
    }
}

/// The JSON header of an array file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArrayHeader {
    pub format: String,
    pub version: u32,
    pub name: String,
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    /// xxh3-128 of the data bytes, 32 hex digits.
    pub checksum: String,
}

impl ArrayHeader {
    /// The header of an array whose checksum is not known yet (zero).
    fn unsealed(name: &str, dtype: Dtype, shape: &[usize]) -> Self {
        ArrayHeader {
            format: "biscale-array".into(),
            version: ARRAY_VERSION,
            name: name.into(),
            dtype,
            shape: shape.to_vec(),
            checksum: EMPTY_SUM.into(),
        }
    }
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    pub fn data_bytes(&self) -> usize {
        self.len() * self.dtype.size()
    }
}

fn header_bytes(h: &ArrayHeader) -> Result<Vec<u8>> {
    let json = serde_json::to_string(h)
        .map_err(|e| Error::new(&h.name, format!("cannot encode the array header: {e}")))?;
    let mut len = json.len();
    while (12 + len) % ALIGN != 0 {
        len += 1;
    }
    let mut out = Vec::with_capacity(12 + len);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(len as u32).to_le_bytes());
    out.extend_from_slice(json.as_bytes());
    out.resize(12 + len, b' ');
    Ok(out)
}

/// The checksum of `bytes` as 32 hex digits.
pub fn checksum(bytes: &[u8]) -> String {
    format!("{:032x}", xxhash_rust::xxh3::xxh3_128(bytes))
}

/// Write a whole array held in memory (atomically). `data` is the little-endian element bytes.
pub fn write_array(
    path: &Path,
    name: &str,
    dtype: Dtype,
    shape: &[usize],
    data: &[u8],
) -> Result<()> {
    let h = ArrayHeader {
        checksum: checksum(data),
        ..ArrayHeader::unsealed(name, dtype, shape)
    };
    if h.data_bytes() != data.len() {
        return Err(Error::new(
            path.display().to_string(),
            format!(
                "array '{name}': {} bytes given for shape {shape:?} of {dtype:?}",
                data.len()
            ),
        ));
    }
    let head = header_bytes(&h)?;
    crate::atomic_write::write_with(path, |w| {
        w.write_all(&head)?;
        w.write_all(data)
    })
}

/// `f32` values as little-endian bytes.
pub fn f32_bytes(v: &[f32]) -> &[u8] {
    bytemuck::cast_slice(v)
}

/// A streamed array file: data appended in pieces, checksum patched into the header at the end,
/// then renamed into place. Dropped without [`ArrayWriter::finish`], it leaves nothing behind.
pub struct ArrayWriter {
    path: PathBuf,
    tmp: crate::atomic_write::TempPath,
    file: Option<std::io::BufWriter<File>>,
    header: ArrayHeader,
    hasher: Xxh3,
    written: usize,
}

impl ArrayWriter {
    pub fn create(path: &Path, name: &str, dtype: Dtype, shape: &[usize]) -> Result<Self> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, "create the directory", e))?;
        }
        let header = ArrayHeader::unsealed(name, dtype, shape);
        let (tmp, f) = crate::atomic_write::create_temp(path)?;
        let mut w = std::io::BufWriter::with_capacity(1 << 20, f);
        w.write_all(&header_bytes(&header)?)
            .map_err(|e| Error::io(&tmp, "write", e))?;
        Ok(ArrayWriter {
            path: path.to_path_buf(),
            tmp,
            file: Some(w),
            header,
            hasher: Xxh3::new(),
            written: 0,
        })
    }

    /// Append element bytes.
    pub fn write(&mut self, bytes: &[u8]) -> Result<()> {
        self.hasher.update(bytes);
        self.written += bytes.len();
        match self.file.as_mut() {
            Some(w) => w
                .write_all(bytes)
                .map_err(|e| Error::io(&self.tmp, "write", e)),
            None => Err(Error::new(
                self.path.display().to_string(),
                "writer already finished",
            )),
        }
    }

    /// Check the length, patch the checksum, flush to disk and rename into place.
    pub fn finish(mut self) -> Result<String> {
        let w = self.file.take().ok_or_else(|| {
            Error::new(self.path.display().to_string(), "writer already finished")
        })?;
        let sealed = seal(
            w,
            self.header.clone(),
            self.written,
            &self.hasher,
            &self.tmp,
            &self.path,
        );
        if sealed.is_err() {
            let _ = std::fs::remove_file(&self.tmp);
        }
        sealed
    }
}

impl Drop for ArrayWriter {
    fn drop(&mut self) {
        if self.file.is_some() {
            self.file = None;
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// An array file streamed in units (a library build's chunks) that survives the process writing
/// it. The data goes to `.NAME.partial` beside the destination, behind the header it will have
/// (checksum zero); once a unit's bytes are written, a line of `.NAME.partial.log` records its
/// length and xxh3-64. Opened again (after a kill, say), it reads the units already there once,
/// checks each against its line, cuts off whatever follows the last good one and continues from
/// there, so a line is never trusted without its data. [`PartialArray::finish`] checks the
/// length, patches the checksum into the header, syncs, renames into place and removes the log:
/// the result is byte for byte what [`write_array`] makes of the same data. The log is locked
/// while open, so two processes never append to one partial file. Dropped without `finish`, the
/// partial file and its log stay, to be resumed ([`PartialArray::discard`] removes them).
pub struct PartialArray {
    path: PathBuf,
    partial: PathBuf,
    log_path: PathBuf,
    file: Option<std::io::BufWriter<File>>,
    /// Held open for its lock.
    log: File,
    header: ArrayHeader,
    hasher: Xxh3,
    written: usize,
    units: usize,
}

impl PartialArray {
    fn side_paths(path: &Path) -> (PathBuf, PathBuf) {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        (
            path.with_file_name(format!(".{name}.partial")),
            path.with_file_name(format!(".{name}.partial.log")),
        )
    }

    fn first_line(header: &ArrayHeader) -> Result<String> {
        serde_json::to_string(header)
            .map_err(|e| Error::new(&header.name, format!("cannot encode the array header: {e}")))
    }

    /// The units (lengths and xxh3-64) that the log of `path`'s partial file lists for this
    /// array, unchecked against the data; empty when there is no log or it is for another array.
    /// A torn last line (a kill while it was written) ends the list.
    fn logged(path: &Path, header: &ArrayHeader) -> Result<Vec<(usize, u64)>> {
        let (_, log) = Self::side_paths(path);
        let text = match std::fs::read(&log) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(Error::io(&log, "read the partial array's log", e)),
        };
        let text = String::from_utf8_lossy(&text);
        let mut lines = text.split_inclusive('\n');
        if lines.next().map(|l| l.trim_end()) != Some(Self::first_line(header)?.as_str()) {
            return Ok(Vec::new());
        }
        let mut out = Vec::new();
        for line in lines {
            let Some(line) = line.strip_suffix('\n') else {
                break;
            };
            let parsed = line.split_once(' ').and_then(|(n, h)| {
                (h.len() == 16)
                    .then(|| Some((n.parse().ok()?, u64::from_str_radix(h, 16).ok()?)))
                    .flatten()
            });
            match parsed {
                Some(u) => out.push(u),
                None => break,
            }
        }
        Ok(out)
    }

    /// How many units the log of `path`'s partial file lists (see [`PartialArray::open`]).
    pub fn logged_units(path: &Path, name: &str, dtype: Dtype, shape: &[usize]) -> Result<usize> {
        Ok(Self::logged(path, &ArrayHeader::unsealed(name, dtype, shape))?.len())
    }

    /// Open the partial file of `path` for this array, keeping at most its first `keep` units
    /// (those whose data matches the log), or start it afresh.
    pub fn open(
        path: &Path,
        name: &str,
        dtype: Dtype,
        shape: &[usize],
        keep: usize,
    ) -> Result<Self> {
        use std::io::{BufReader, Read};
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, "create the directory", e))?;
        }
        let (partial, log_path) = Self::side_paths(path);
        let header = ArrayHeader::unsealed(name, dtype, shape);
        let mut log = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&log_path)
            .map_err(|e| Error::io(&log_path, "open the partial array's log", e))?;
        match log.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                return Err(Error::new(
                    path.display().to_string(),
                    format!(
                        "another process is writing this array (its log {} is locked); wait for \
                         that build to finish or stop it",
                        log_path.display()
                    ),
                ))
            }
            Err(std::fs::TryLockError::Error(e)) => {
                return Err(Error::io(&log_path, "lock the partial array's log", e))
            }
        }
        let head = header_bytes(&header)?;
        let mut units = Self::logged(path, &header)?;
        units.truncate(keep);
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&partial)
            .map_err(|e| Error::io(&partial, "open the partial array", e))?;
        let io = |e: std::io::Error| Error::io(&partial, "read the partial array", e);
        // The units already written, checked against the log as they are hashed.
        let mut hasher = Xxh3::new();
        let mut good = 0;
        let mut written = 0;
        if !units.is_empty() {
            let mut r = BufReader::with_capacity(1 << 20, &mut file);
            let mut got = vec![0u8; head.len()];
            if r.read_exact(&mut got).is_ok() && got == head {
                let mut buf = Vec::new();
                for &(n, sum) in &units {
                    buf.resize(n, 0);
                    match r.read_exact(&mut buf) {
                        Ok(()) if xxhash_rust::xxh3::xxh3_64(&buf) == sum => {
                            hasher.update(&buf);
                            good += 1;
                            written += n;
                        }
                        Ok(()) => break,
                        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => break,
                        Err(e) => return Err(io(e)),
                    }
                }
            }
        }
        units.truncate(good);
        // Cut the data and the log back to the good units.
        let wio = |e: std::io::Error| Error::io(&partial, "write the partial array", e);
        file.set_len((head.len() + written) as u64).map_err(wio)?;
        file.seek(SeekFrom::Start(0)).map_err(wio)?;
        file.write_all(&head).map_err(wio)?;
        file.seek(SeekFrom::Start((head.len() + written) as u64))
            .map_err(wio)?;
        let mut text = Self::first_line(&header)?;
        text.push('\n');
        for (n, sum) in &units {
            text.push_str(&format!("{n} {sum:016x}\n"));
        }
        let lio = |e: std::io::Error| Error::io(&log_path, "write the partial array's log", e);
        log.set_len(0).map_err(lio)?;
        log.seek(SeekFrom::Start(0)).map_err(lio)?;
        log.write_all(text.as_bytes()).map_err(lio)?;
        Ok(PartialArray {
            path: path.to_path_buf(),
            partial,
            log_path,
            file: Some(std::io::BufWriter::with_capacity(1 << 20, file)),
            log,
            header,
            hasher,
            written,
            units: good,
        })
    }

    /// The units in the partial file (after [`PartialArray::open`]'s checks, and those appended).
    pub fn units(&self) -> usize {
        self.units
    }

    /// Append one unit: its bytes go to the partial file (flushed to the operating system, so a
    /// killed process loses nothing of it), then its line to the log.
    pub fn append(&mut self, bytes: &[u8]) -> Result<()> {
        let io = |e: std::io::Error| Error::io(&self.partial, "write the partial array", e);
        let w = self.file.as_mut().ok_or_else(|| {
            Error::new(self.path.display().to_string(), "writer already finished")
        })?;
        w.write_all(bytes).map_err(io)?;
        w.flush().map_err(io)?;
        self.hasher.update(bytes);
        self.written += bytes.len();
        let line = format!(
            "{} {:016x}\n",
            bytes.len(),
            xxhash_rust::xxh3::xxh3_64(bytes)
        );
        self.log
            .write_all(line.as_bytes())
            .map_err(|e| Error::io(&self.log_path, "write the partial array's log", e))?;
        self.units += 1;
        Ok(())
    }

    /// Check the length, patch the checksum, flush to disk, rename into place and remove the
    /// log. Returns the checksum.
    pub fn finish(mut self) -> Result<String> {
        let w = self.file.take().ok_or_else(|| {
            Error::new(self.path.display().to_string(), "writer already finished")
        })?;
        let sum = seal(
            w,
            self.header.clone(),
            self.written,
            &self.hasher,
            &self.partial,
            &self.path,
        )?;
        std::fs::remove_file(&self.log_path)
            .map_err(|e| Error::io(&self.log_path, "remove the finished array's log", e))?;
        Ok(sum)
    }

    /// Remove the partial file of `path` and its log, if there are any.
    pub fn discard(path: &Path) -> Result<()> {
        let (partial, log) = Self::side_paths(path);
        for p in [partial, log] {
            match std::fs::remove_file(&p) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(Error::io(&p, "remove the partial array", e)),
            }
        }
        Ok(())
    }
}

/// Finish a streamed array: check that `written` bytes fill `header`'s shape, patch the checksum
/// of `hasher` into the header at the start of the temporary file `tmp`, sync it and rename it
/// onto `path`. Returns the checksum.
fn seal(
    w: std::io::BufWriter<File>,
    mut header: ArrayHeader,
    written: usize,
    hasher: &Xxh3,
    tmp: &Path,
    path: &Path,
) -> Result<String> {
    if written != header.data_bytes() {
        return Err(Error::new(
            path.display().to_string(),
            format!(
                "array '{}': wrote {written} bytes, the shape {:?} needs {}",
                header.name,
                header.shape,
                header.data_bytes()
            ),
        ));
    }
    let sum = format!("{:032x}", hasher.digest128());
    header.checksum = sum.clone();
    let head = header_bytes(&header)?;
    let io = |e: std::io::Error| Error::io(tmp, "write", e);
    let mut f = w.into_inner().map_err(|e| io(e.into_error()))?;
    f.seek(SeekFrom::Start(0)).map_err(io)?;
    f.write_all(&head).map_err(io)?;
    f.sync_all().map_err(io)?;
    std::fs::rename(tmp, path)
        .map_err(|e| Error::io(path, "rename the finished temporary file onto", e))?;
    Ok(sum)
}

/// An open (memory-mapped) array file.
pub struct ArrayFile {
    pub path: PathBuf,
    pub header: ArrayHeader,
    /// Whether the data was checked against its checksum when opened.
    pub verified: bool,
    map: Mmap,
    offset: usize,
    /// The file itself, for streaming reads that should not map pages ([`ArrayFile::read_data`]).
    file: File,
}

/// What the caller expects of an array file; `None` accepts anything.
#[derive(Debug, Clone, Default)]
pub struct Expect<'a> {
    pub name: Option<&'a str>,
    pub dtype: Option<Dtype>,
    pub shape: Option<&'a [usize]>,
    /// Verify the data checksum (reads every byte once).
    pub verify: bool,
}

impl ArrayFile {
    pub fn open(path: &Path, expect: &Expect) -> Result<Self> {
        let ctx = path.display().to_string();
        let bad = |m: String| Error::new(ctx.clone(), m);
        let f = File::open(path).map_err(|e| Error::io(path, "open the library array", e))?;
        // SAFETY: the map is read-only; library files are written once (temporary + rename) and
        // never modified in place, so the mapped bytes do not change under us.
        let map = unsafe { Mmap::map(&f) }.map_err(|e| Error::io(path, "memory-map", e))?;
        if map.len() < 12 || &map[..8] != MAGIC {
            return Err(bad(
                "not a biscale array file (bad magic bytes); the library is corrupted — rebuild it"
                    .into(),
            ));
        }
        let hlen = u32::from_le_bytes([map[8], map[9], map[10], map[11]]) as usize;
        if 12 + hlen > map.len() {
            return Err(bad(format!(
                "truncated: the header needs {} bytes, the file has {}",
                12 + hlen,
                map.len()
            )));
        }
        let header: ArrayHeader = serde_json::from_slice(map[12..12 + hlen].trim_ascii_end())
            .map_err(|e| bad(format!("unreadable array header: {e}")))?;
        if header.format != "biscale-array" || header.version != ARRAY_VERSION {
            return Err(bad(format!(
                "array format '{}' version {} (this biscale reads biscale-array version {ARRAY_VERSION})",
                header.format, header.version
            )));
        }
        if let Some(n) = expect.name {
            if header.name != n {
                return Err(bad(format!(
                    "holds array '{}', expected '{n}'",
                    header.name
                )));
            }
        }
        if let Some(d) = expect.dtype {
            if header.dtype != d {
                return Err(bad(format!(
                    "element type {:?}, expected {d:?}",
                    header.dtype
                )));
            }
        }
        if let Some(s) = expect.shape {
            if header.shape != s {
                return Err(bad(format!(
                    "shape {:?}, expected {s:?} (built with other settings?)",
                    header.shape
                )));
            }
        }
        let offset = 12 + hlen;
        let want = offset + header.data_bytes();
        if map.len() != want {
            return Err(bad(format!(
                "{}: the file has {} bytes but its header promises {want}; the library is \
                 corrupted — rebuild it",
                if map.len() < want {
                    "truncated"
                } else {
                    "too long"
                },
                map.len()
            )));
        }
        let mut file = ArrayFile {
            path: path.to_path_buf(),
            header,
            verified: false,
            map,
            offset,
            file: f,
        };
        if expect.verify {
            file.verify()?;
            file.verified = true;
        }
        Ok(file)
    }

    /// Check the data against the header's checksum.
    pub fn verify(&mut self) -> Result<()> {
        // Data up to HASH_MAPPED_BYTES is hashed through the map: a run that checks such an
        // array reads it through the map next, and pages mapped now are not faulted in again
        // (a 16 MB buffer of copies instead took a page fault per 4 KB written). Larger data is
        // read in pieces, not through the map: hashing a file larger than memory through the
        // map would make every page of it resident in this process (the same digest as
        // [`checksum`] of the whole).
        const PIECE: usize = 16 << 20;
        let n = self.header.data_bytes();
        let mut h = Xxh3::new();
        if let Some(data) = self.bytes().get(..n).filter(|_| n <= HASH_MAPPED_BYTES) {
            h.update(data);
            return self.check_digest(h);
        }
        let mut buf = vec![0u8; PIECE.min(n)];
        for start in (0..n).step_by(PIECE) {
            let piece = &mut buf[..PIECE.min(n - start)];
            self.read_data(start, piece)?;
            h.update(piece);
        }
        self.check_digest(h)
    }

    /// Compare a digest of the whole data with the header's checksum.
    fn check_digest(&mut self, h: Xxh3) -> Result<()> {
        let got = format!("{:032x}", h.digest128());
        if got != self.header.checksum {
            return Err(Error::new(
                self.path.display().to_string(),
                format!(
                    "checksum mismatch (file {got}, header {}): the data is corrupted; rebuild the library",
                    self.header.checksum
                ),
            ));
        }
        self.verified = true;
        Ok(())
    }

    pub fn bytes(&self) -> &[u8] {
        &self.map[self.offset..]
    }

    /// Ask the operating system to start reading the data byte ranges `(start, len)` into the
    /// page cache now, in the given order (`posix_fadvise(POSIX_FADV_WILLNEED)`, issued from a
    /// thread of its own, since queueing the reads can take a while), so that later reads find
    /// them there: the randomized SVD's next block, or the thousands of light-lobe records a
    /// search's re-rank is about to read from a file larger than memory, which the disk then
    /// serves together instead of one page fault at a time. A hint: nothing is mapped into this
    /// process, and a range past the data or a refusal is ignored.
    pub fn will_need(&self, ranges: Vec<(usize, usize)>) {
        use std::os::fd::AsRawFd;
        let n = self.header.data_bytes();
        let base = self.offset;
        let ranges: Vec<(libc::off_t, libc::off_t)> = ranges
            .into_iter()
            .filter(|&(start, len)| start < n && len > 0)
            .map(|(start, len)| {
                (
                    (base + start) as libc::off_t,
                    len.min(n - start) as libc::off_t,
                )
            })
            .collect();
        if ranges.is_empty() {
            return;
        }
        let Ok(f) = self.file.try_clone() else {
            return;
        };
        // A thread that cannot be made is a hint not given.
        let _ = std::thread::Builder::new().spawn(move || {
            for (off, len) in ranges {
                // SAFETY: `f` is an open file descriptor owned by this thread; the call only
                // reads its arguments.
                unsafe { libc::posix_fadvise(f.as_raw_fd(), off, len, libc::POSIX_FADV_WILLNEED) };
            }
        });
    }

    /// Whether every page of the data byte ranges `(start, len)` is in memory (`mincore` on the
    /// map): reading them then waits for no disk. `false` where the system cannot tell; ranges
    /// past the data and empty ones count as in memory.
    pub fn resident(&self, ranges: &[(usize, usize)]) -> bool {
        // SAFETY: `sysconf` only reads its argument.
        let page = match unsafe { libc::sysconf(libc::_SC_PAGESIZE) } {
            p if p > 0 => p as usize,
            _ => return false,
        };
        let n = self.header.data_bytes();
        let base = self.map.as_ptr() as usize;
        let mut pages = Vec::new();
        for &(start, len) in ranges {
            if start >= n || len == 0 {
                continue;
            }
            // The map's byte range of the data range, widened to whole pages (the map starts
            // at a page boundary, and its last page is mapped whole).
            let from = (self.offset + start) / page;
            let to = (self.offset + start + len.min(n - start)).div_ceil(page);
            pages.resize(to - from, 0u8);
            // SAFETY: pages `from..to` of the map lie within it (its last page is mapped whole);
            // `mincore` writes one byte per page into `pages`, which holds that many.
            let rc = unsafe {
                libc::mincore(
                    (base + from * page) as *mut libc::c_void,
                    (to - from) * page,
                    pages.as_mut_ptr(),
                )
            };
            if rc != 0 || pages.iter().any(|p| p & 1 == 0) {
                return false;
            }
        }
        true
    }

    /// Copy data bytes `start..start + buf.len()` into `buf` with a positioned read instead of
    /// through the map. For streaming passes over arrays larger than memory: pages read through
    /// the map stay in this process's resident set (a randomized SVD over the 14 GB binned
    /// matrix of `paper4` through the map peaked at 15 GB of RSS for 1.5 GB of its own), while a
    /// read copies from the page cache and maps nothing.
    pub fn read_data(&self, start: usize, buf: &mut [u8]) -> Result<()> {
        use std::os::unix::fs::FileExt;
        if start + buf.len() > self.header.data_bytes() {
            return Err(Error::new(
                self.path.display().to_string(),
                format!(
                    "read of bytes {start}..{} past the data's {} bytes",
                    start + buf.len(),
                    self.header.data_bytes()
                ),
            ));
        }
        self.file
            .read_exact_at(buf, (self.offset + start) as u64)
            .map_err(|e| Error::io(&self.path, "read the library array", e))
    }

    fn typed<T: bytemuck::Pod>(&self, d: Dtype) -> Result<&[T]> {
        if self.header.dtype != d {
            return Err(Error::new(
                self.path.display().to_string(),
                format!("element type {:?}, expected {d:?}", self.header.dtype),
            ));
        }
        bytemuck::try_cast_slice(self.bytes()).map_err(|e| {
            Error::new(
                self.path.display().to_string(),
                format!("misaligned data: {e}"),
            )
        })
    }

    pub fn f32s(&self) -> Result<&[f32]> {
        self.typed(Dtype::F32)
    }
    pub fn f64s(&self) -> Result<&[f64]> {
        self.typed(Dtype::F64)
    }
    pub fn u32s(&self) -> Result<&[u32]> {
        self.typed(Dtype::U32)
    }
    pub fn u64s(&self) -> Result<&[u64]> {
        self.typed(Dtype::U64)
    }
    pub fn f16s(&self) -> Result<&[half::f16]> {
        self.typed(Dtype::F16)
    }
    /// The bytes of a `uf8` array ([`crate::uf8::decode`] gives their values).
    pub fn uf8s(&self) -> Result<&[u8]> {
        self.typed(Dtype::UF8)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testdir::TestDir;

    #[test]
    fn round_trip_and_streamed_equals_whole() {
        let d = TestDir::new("store-rt");
        let v: Vec<f32> = (0..1000).map(|i| i as f32 * 0.5).collect();
        write_array(&d.join("a.bsa"), "a", Dtype::F32, &[10, 100], f32_bytes(&v)).unwrap();
        let mut w = ArrayWriter::create(&d.join("b.bsa"), "a", Dtype::F32, &[10, 100]).unwrap();
        for c in v.chunks(77) {
            w.write(f32_bytes(c)).unwrap();
        }
        w.finish().unwrap();
        let a = std::fs::read(d.join("a.bsa")).unwrap();
        let b = std::fs::read(d.join("b.bsa")).unwrap();
        assert_eq!(a, b);
        let f = ArrayFile::open(
            &d.join("a.bsa"),
            &Expect {
                verify: true,
                shape: Some(&[10, 100]),
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(f.f32s().unwrap(), &v[..]);
        assert_eq!(f.offset % ALIGN, 0);
        // Read-ahead hints change nothing, in range, past the data or empty.
        let ranges = vec![(0, 4000), (1200, 10_000), (4000, 1), (9999, 5), (0, 0)];
        f.will_need(ranges.clone());
        assert_eq!(f.f32s().unwrap(), &v[..]);
        // Just read whole: in memory, past the data or not.
        assert!(f.resident(&ranges));
        assert!(f.resident(&[]));
    }

    #[test]
    fn corruption_truncation_and_mismatch_are_named_errors() {
        let d = TestDir::new("store-bad");
        let p = d.join("a.bsa");
        let v: Vec<f32> = (0..256).map(|i| i as f32).collect();
        write_array(&p, "gamma", Dtype::F32, &[256], f32_bytes(&v)).unwrap();
        let e = ArrayFile::open(
            &p,
            &Expect {
                name: Some("coords"),
                ..Default::default()
            },
        )
        .err()
        .unwrap();
        assert!(
            e.to_string().contains("a.bsa") && e.to_string().contains("expected 'coords'"),
            "{e}"
        );
        let e = ArrayFile::open(
            &p,
            &Expect {
                shape: Some(&[255]),
                ..Default::default()
            },
        )
        .err()
        .unwrap();
        assert!(e.to_string().contains("shape"), "{e}");
        let mut bytes = std::fs::read(&p).unwrap();
        let n = bytes.len();
        bytes[n - 5] ^= 0x40;
        std::fs::write(&p, &bytes).unwrap();
        let e = ArrayFile::open(
            &p,
            &Expect {
                verify: true,
                ..Default::default()
            },
        )
        .err()
        .unwrap();
        assert!(e.to_string().contains("checksum mismatch"), "{e}");
        std::fs::write(&p, &bytes[..n - 100]).unwrap();
        let e = ArrayFile::open(&p, &Expect::default()).err().unwrap();
        let want = format!(
            "{}: truncated: the file has {} bytes but its header promises {n}; the library is \
             corrupted — rebuild it",
            p.display(),
            n - 100
        );
        assert_eq!(e.to_string(), want);
        let mut long = bytes.clone();
        long.push(0);
        std::fs::write(&p, &long).unwrap();
        let e = ArrayFile::open(&p, &Expect::default()).err().unwrap();
        assert!(e.to_string().contains(": too long: the file has"), "{e}");
        std::fs::write(&p, b"hello").unwrap();
        let e = ArrayFile::open(&p, &Expect::default()).err().unwrap();
        assert!(e.to_string().contains("magic"), "{e}");
    }

    #[test]
    fn a_partial_array_resumes_after_its_last_good_unit_and_equals_the_whole() {
        let d = TestDir::new("store-partial");
        let p = d.join("a.bsa");
        let v: Vec<f32> = (0..1000).map(|i| (i as f32).sin()).collect();
        let units: Vec<&[f32]> = v.chunks(100).collect();
        write_array(
            &d.join("whole.bsa"),
            "a",
            Dtype::F32,
            &[10, 100],
            f32_bytes(&v),
        )
        .unwrap();
        let whole = std::fs::read(d.join("whole.bsa")).unwrap();
        let open = |keep| PartialArray::open(&p, "a", Dtype::F32, &[10, 100], keep);
        // "Killed" after four units: dropped without finish.
        {
            let mut w = open(usize::MAX).unwrap();
            assert_eq!(w.units(), 0);
            for u in &units[..4] {
                w.append(f32_bytes(u)).unwrap();
            }
            // A second process cannot write the same array meanwhile.
            let e = open(usize::MAX).err().unwrap().to_string();
            assert!(e.contains("a.bsa") && e.contains("locked"), "{e}");
        }
        assert_eq!(
            PartialArray::logged_units(&p, "a", Dtype::F32, &[10, 100]).unwrap(),
            4
        );
        assert_eq!(
            PartialArray::logged_units(&p, "a", Dtype::F32, &[10, 101]).unwrap(),
            0,
            "a log of another shape lists nothing"
        );
        // Damage the third unit's data and tear the log's last line: two units survive.
        let (partial, log) = PartialArray::side_paths(&p);
        let mut bytes = std::fs::read(&partial).unwrap();
        let n = bytes.len();
        bytes[n - 400 - 7] ^= 0x10;
        std::fs::write(&partial, &bytes).unwrap();
        let text = std::fs::read_to_string(&log).unwrap();
        std::fs::write(&log, &text[..text.len() - 5]).unwrap();
        {
            let w = open(usize::MAX).unwrap();
            assert_eq!(w.units(), 2);
        }
        // Keeping fewer than there are cuts back to that many.
        let mut w = open(1).unwrap();
        assert_eq!(w.units(), 1);
        for u in &units[1..] {
            w.append(f32_bytes(u)).unwrap();
        }
        let sum = w.finish().unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), whole);
        assert_eq!(sum, checksum(f32_bytes(&v)));
        assert!(!partial.exists() && !log.exists());
        // A wrong length is refused and leaves the partial file to be resumed or discarded.
        let mut w = PartialArray::open(&d.join("b.bsa"), "b", Dtype::F32, &[4], 0).unwrap();
        w.append(&[0u8; 8]).unwrap();
        let e = w.finish().err().unwrap().to_string();
        assert!(e.contains("b.bsa") && e.contains("needs 16"), "{e}");
        PartialArray::discard(&d.join("b.bsa")).unwrap();
        let mut left: Vec<_> = std::fs::read_dir(&d)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        left.sort();
        assert_eq!(left, ["a.bsa", "whole.bsa"]);
    }

    #[test]
    fn unfinished_writer_leaves_nothing() {
        let d = TestDir::new("store-drop");
        {
            let mut w = ArrayWriter::create(&d.join("x.bsa"), "x", Dtype::F32, &[4]).unwrap();
            w.write(&[0u8; 8]).unwrap();
        }
        assert_eq!(std::fs::read_dir(&d).unwrap().count(), 0);
        let mut w = ArrayWriter::create(&d.join("x.bsa"), "x", Dtype::F32, &[4]).unwrap();
        w.write(&[0u8; 8]).unwrap();
        assert!(w.finish().is_err());
        assert_eq!(std::fs::read_dir(&d).unwrap().count(), 0);
    }
}
