//! Writing files so that a reader never sees half of one: write a temporary file in the same
//! directory, flush it to disk, then rename it over the destination.
//!
//! Temporary names are `.NAME.tmp-HOST-PID-NONCE-COUNT`: the host name (from `/etc/hostname`,
//! when readable), the process id, a per-process nonce drawn from the clock when the process
//! first writes, and a per-process counter. Processes that share a process id on a shared volume
//! (Kubernetes pods are all PID 1) therefore never write the same temporary file, and the file is
//! created exclusively (`create_new`), so a collision is retried under another name rather than
//! shared.

use crate::error::{Error, Result};
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::OnceLock;

static COUNTER: AtomicU64 = AtomicU64::new(0);

/// `HOST-PID-NONCE` for this process, computed once.
fn process_tag() -> &'static str {
    static TAG: OnceLock<String> = OnceLock::new();
    TAG.get_or_init(|| {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0);
        let local = 0u8;
        let mut seed = Vec::with_capacity(32);
        seed.extend_from_slice(&nanos.to_le_bytes());
        seed.extend_from_slice(&std::process::id().to_le_bytes());
        // The stack address differs between runs under address-space randomisation.
        seed.extend_from_slice(&(&local as *const u8 as usize).to_le_bytes());
        let nonce = xxhash_rust::xxh3::xxh3_64(&seed);
        let host: String = std::fs::read_to_string("/etc/hostname")
            .unwrap_or_default()
            .trim()
            .chars()
            .filter(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
            .take(32)
            .collect();
        let pid = std::process::id();
        if host.is_empty() {
            format!("{pid}-{nonce:016x}")
        } else {
            format!("{host}-{pid}-{nonce:016x}")
        }
    })
}

/// A fresh temporary name next to `path`: `.NAME.tmp-HOST-PID-NONCE-COUNT`.
/// Check, before any work, that a directory can hold output: `dir` is a directory, or does not
/// exist and its nearest existing ancestor is one (it is made when the output is written), and
/// that directory lets us create an entry (a probe directory, removed at once). `what` names
/// the option in the error.
pub fn check_output_dir(dir: &Path, what: &str) -> Result<()> {
    let writable = |d: &Path| -> Result<()> {
        let probe = d.join(format!(".biscale-probe-{}", std::process::id()));
        match std::fs::create_dir(&probe) {
            Ok(()) => {
                let _ = std::fs::remove_dir(&probe);
                Ok(())
            }
            Err(e) => Err(Error::new(
                what,
                format!(
                    "cannot write in {} ({e}), so {} cannot be written",
                    if d.as_os_str().is_empty() {
                        Path::new(".")
                    } else {
                        d
                    }
                    .display(),
                    dir.display()
                ),
            )),
        }
    };
    let mut p = dir;
    loop {
        if p.as_os_str().is_empty() {
            return writable(p); // the working directory
        }
        if p.exists() {
            return if p.is_dir() {
                writable(p)
            } else {
                Err(Error::new(
                    what,
                    format!(
                        "{} is not a directory, so {} cannot be written",
                        p.display(),
                        dir.display()
                    ),
                ))
            };
        }
        match p.parent() {
            Some(up) => p = up,
            None => return Ok(()),
        }
    }
}

pub fn temp_path(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    path.with_file_name(format!(".{name}.tmp-{}-{n}", process_tag()))
}

/// A temporary file's name, registered for removal if the process is interrupted
/// ([`crate::interrupt`]) for as long as this lives. Dropping it neither removes nor renames the
/// file: the writer does one or the other first.
#[derive(Debug)]
pub struct TempPath {
    path: PathBuf,
    _registered: crate::interrupt::Registered,
}

impl std::ops::Deref for TempPath {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.path
    }
}

impl AsRef<Path> for TempPath {
    fn as_ref(&self) -> &Path {
        &self.path
    }
}

/// Create a new temporary file next to `path` (never one that already exists), registered for
/// removal if the process is interrupted before it is renamed or removed.
pub fn create_temp(path: &Path) -> Result<(TempPath, File)> {
    let mut last = None;
    for _ in 0..8 {
        let tmp = temp_path(path);
        match File::create_new(&tmp) {
            // Registered once it is ours: a name another process holds is never removed.
            Ok(f) => {
                let registered = crate::interrupt::register(&tmp);
                return Ok((
                    TempPath {
                        path: tmp,
                        _registered: registered,
                    },
                    f,
                ));
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => last = Some((tmp, e)),
            Err(e) => {
                return Err(Error::new(
                    path.display().to_string(),
                    format!("cannot create the temporary file {}: {e}", tmp.display()),
                ))
            }
        }
    }
    match last {
        Some((tmp, e)) => Err(Error::io(
            &tmp,
            "create a temporary file (8 fresh names were all taken)",
            e,
        )),
        None => Err(Error::new(
            path.display().to_string(),
            "cannot create a temporary file",
        )),
    }
}

/// Create `path` holding `bytes` unless it already exists: `Ok(true)` if this call created it,
/// `Ok(false)` if it was there (its contents are left as they are). The bytes go to a temporary
/// file first, which is then hard-linked to `path`, so of several processes creating the same
/// file at once exactly one wins, and a reader never sees half of it. On a file system without
/// hard links, the temporary file is renamed instead (then the last of simultaneous creators
/// wins).
pub fn create_exclusive(path: &Path, bytes: &[u8]) -> Result<bool> {
    if let Some(dir) = path.parent() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, "create the directory", e))?;
        }
    }
    let (tmp, mut f) = create_temp(path)?;
    let written = f.write_all(bytes).and_then(|_| f.sync_all());
    drop(f);
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(Error::io(path, "write", e));
    }
    let linked = std::fs::hard_link(&tmp, path);
    let result = match linked {
        Ok(()) => Ok(true),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(false),
        Err(_) if path.exists() => Ok(false),
        Err(_) => {
            return std::fs::rename(&tmp, path).map(|_| true).map_err(|e| {
                let _ = std::fs::remove_file(&tmp);
                Error::io(path, "rename the finished temporary file onto", e)
            });
        }
    };
    let _ = std::fs::remove_file(&tmp);
    result
}

/// Write `bytes` to `path` atomically (temporary file + rename).
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    write_with(path, |w| w.write_all(bytes))
}

/// Where a write to `path` lands: `path` itself, or, when it is a symbolic link, the file the
/// link names (followed through up to 40 links; a link whose target does not exist yet names
/// the file to create). Renaming a temporary file over a link would replace the link itself.
fn destination(path: &Path) -> PathBuf {
    let mut p = path.to_path_buf();
    for _ in 0..40 {
        match std::fs::symlink_metadata(&p) {
            Ok(m) if m.file_type().is_symlink() => match std::fs::read_link(&p) {
                Ok(target) => {
                    p = match p.parent() {
                        Some(dir) if target.is_relative() => dir.join(target),
                        _ => target,
                    }
                }
                Err(_) => break,
            },
            _ => break,
        }
    }
    p
}

/// Whether `path` is something other than a regular file or a directory that a write should
/// go into rather than replace: a device (`/dev/null`), a named pipe, a socket.
fn is_special(path: &Path) -> bool {
    use std::os::unix::fs::FileTypeExt;
    std::fs::metadata(path).is_ok_and(|m| {
        let t = m.file_type();
        t.is_char_device() || t.is_block_device() || t.is_fifo() || t.is_socket()
    })
}

/// Write through `fill` into a temporary file, then rename it to `path`. On any error the
/// temporary file is removed and `path` is left as it was. A symbolic link is followed (the
/// file it names is replaced, not the link), and a device or a named pipe at `path` (such as
/// `/dev/null`) is written to directly, as a shell's redirection would, not replaced by a file.
pub fn write_with(
    path: &Path,
    fill: impl FnOnce(&mut std::io::BufWriter<File>) -> std::io::Result<()>,
) -> Result<()> {
    let path = &destination(path);
    if is_special(path) {
        let f = std::fs::OpenOptions::new()
            .write(true)
            .open(path)
            .map_err(|e| Error::io(path, "open for writing", e))?;
        let mut w = std::io::BufWriter::new(f);
        return fill(&mut w)
            .and_then(|_| w.flush())
            .map_err(|e| Error::io(path, "write", e));
    }
    if let Some(dir) = path.parent() {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, "create the directory", e))?;
        }
    }
    let (tmp, f) = create_temp(path)?;
    let result = (|| -> std::io::Result<()> {
        let mut w = std::io::BufWriter::new(f);
        fill(&mut w)?;
        let f = w.into_inner().map_err(|e| e.into_error())?;
        f.sync_all()?;
        Ok(())
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(Error::io(path, "write", e));
    }
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        Error::io(path, "rename the finished temporary file onto it", e)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testdir::TestDir;

    #[test]
    fn output_directories_under_a_file_are_refused_before_any_work() {
        let d = crate::testdir::TestDir::new("outdir");
        let file = d.join("f.csv");
        std::fs::write(&file, "x").unwrap();
        assert!(check_output_dir(&d, "--outputs").is_ok());
        assert!(check_output_dir(&d.join("new/deeper"), "--outputs").is_ok());
        let e = check_output_dir(&file, "--outputs")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("--outputs") && e.contains("f.csv") && e.contains("not a directory"),
            "{e}"
        );
        let e = check_output_dir(&file.join("sub"), "--plot")
            .unwrap_err()
            .to_string();
        assert!(e.contains("--plot"), "{e}");
        assert!(check_output_dir(Path::new(""), "--out").is_ok());
        // A directory that takes no new entry is found before any work (the design used to
        // fail only when it wrote its outputs).
        if Path::new("/proc/self").exists() {
            let e = check_output_dir(Path::new("/proc/biscale-out"), "--outputs")
                .unwrap_err()
                .to_string();
            assert!(e.contains("--outputs") && e.contains("/proc"), "{e}");
        }
        assert_eq!(
            std::fs::read_dir(&*d).unwrap().count(),
            1,
            "the probes are removed"
        );
    }

    #[test]
    fn failed_write_leaves_nothing() {
        let dir = TestDir::new("aw");
        let p = dir.join("out.csv");
        let r = write_with(&p, |w| {
            w.write_all(b"partial")?;
            Err(std::io::Error::other("boom"))
        });
        assert!(r.is_err());
        assert!(!p.exists());
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
        write_bytes(&p, b"ok").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"ok");
    }

    #[test]
    fn links_are_followed_and_pipes_written_into() {
        let dir = TestDir::new("aw-special");
        // A symbolic link: the file it names is replaced, the link stays a link.
        let target = dir.join("target.csv");
        std::fs::write(&target, "old").unwrap();
        let link = dir.join("link.csv");
        std::os::unix::fs::symlink("target.csv", &link).unwrap();
        write_bytes(&link, b"new").unwrap();
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        assert_eq!(std::fs::read(&target).unwrap(), b"new");
        // A named pipe is written into, not replaced by a file.
        let fifo = dir.join("fifo.csv");
        let made = std::process::Command::new("mkfifo").arg(&fifo).status();
        if made.is_ok_and(|s| s.success()) {
            let reader = {
                let fifo = fifo.clone();
                std::thread::spawn(move || std::fs::read(&fifo).unwrap())
            };
            write_bytes(&fifo, b"through the pipe").unwrap();
            assert_eq!(reader.join().unwrap(), b"through the pipe");
            use std::os::unix::fs::FileTypeExt;
            assert!(std::fs::metadata(&fifo).unwrap().file_type().is_fifo());
        }
        // Nothing else was left in the directory.
        let mut names: Vec<String> = std::fs::read_dir(&*dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert!(names.iter().all(|n| !n.contains(".tmp-")), "{names:?}");
    }

    #[test]
    fn temporary_names_are_unique_beyond_the_process_id() {
        let p = Path::new("/some/dir/gamma.bsa");
        let (a, b) = (temp_path(p), temp_path(p));
        assert_ne!(a, b);
        assert_eq!(a.parent(), p.parent());
        let name = a.file_name().unwrap().to_string_lossy().into_owned();
        assert!(name.starts_with(".gamma.bsa.tmp-"), "{name}");
        let pid = std::process::id().to_string();
        // HOST-PID-NONCE-COUNT (HOST may be absent): the pid is followed by a 16-digit nonce.
        let parts: Vec<&str> = name.rsplit('-').collect();
        assert!(parts[0].parse::<u64>().is_ok(), "{name}: no counter");
        assert!(
            parts[1].len() == 16 && u64::from_str_radix(parts[1], 16).is_ok(),
            "{name}: no nonce"
        );
        assert_eq!(parts[2], pid, "{name}: no pid");
    }

    #[test]
    fn exactly_one_of_simultaneous_exclusive_creators_wins() {
        let tmp = TestDir::new("aw-excl");
        // Not made here: the creators make it.
        let dir = tmp.join("d");
        let p = dir.join("profile.toml");
        let wins: Vec<(u8, bool)> = std::thread::scope(|s| {
            let hs: Vec<_> = (0..8u8)
                .map(|t| {
                    let p = &p;
                    s.spawn(move || (t, create_exclusive(p, &[t; 1000]).unwrap()))
                })
                .collect();
            hs.into_iter().map(|h| h.join().unwrap()).collect()
        });
        let winners: Vec<u8> = wins.iter().filter(|w| w.1).map(|w| w.0).collect();
        assert_eq!(winners.len(), 1, "{wins:?}");
        assert_eq!(std::fs::read(&p).unwrap(), vec![winners[0]; 1000]);
        assert!(!create_exclusive(&p, b"later").unwrap());
        assert_eq!(std::fs::read(&p).unwrap(), vec![winners[0]; 1000]);
        assert_eq!(
            std::fs::read_dir(&dir).unwrap().count(),
            1,
            "temporary files left"
        );
    }

    #[test]
    fn concurrent_writers_to_one_path_never_share_a_temporary_file() {
        let dir = TestDir::new("aw-conc");
        let p = dir.join("profile.toml");
        std::thread::scope(|s| {
            for t in 0..8u8 {
                let p = &p;
                s.spawn(move || {
                    for _ in 0..20 {
                        write_bytes(p, &[t; 4096]).unwrap();
                    }
                });
            }
        });
        let got = std::fs::read(&p).unwrap();
        assert_eq!(got.len(), 4096);
        assert!(got.iter().all(|&b| b == got[0]), "a file mixed two writers");
        // Only the destination is left.
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
    }
}
