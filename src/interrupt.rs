//! Cleaning up after an interrupted run. The temporary files and directories this process is
//! writing (an atomic write's `.NAME.tmp-…`, a design's `.NAME.partial-PID`, an array file being
//! written) are registered while they exist; when the process is interrupted (SIGINT from
//! Ctrl-C, SIGTERM from `kill` or a batch system, SIGHUP from a closed terminal) a watcher
//! thread removes them, then ends the process by the same signal. What a killed run is meant to
//! leave stays: a library build's chunks and partial arrays are not registered (the next build
//! resumes from them). SIGKILL cannot be caught; a design run's leftovers are then removed by the
//! next run of the same scene.
//!
//! [`install`] is called once, by the command-line program, before any other thread starts: it
//! blocks the three signals in the calling thread (and so in every thread started later) and
//! starts the thread that waits for them. Without it (the library used from another program,
//! the tests) registration costs a lock and nothing else changes.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};

static PENDING: Mutex<Vec<(u64, PathBuf)>> = Mutex::new(Vec::new());
static NEXT: AtomicU64 = AtomicU64::new(0);

fn pending() -> MutexGuard<'static, Vec<(u64, PathBuf)>> {
    PENDING.lock().unwrap_or_else(|p| p.into_inner())
}

/// A registered temporary path: removed if the process is interrupted while this lives.
/// Dropping it unregisters the path (it does not remove it).
#[derive(Debug)]
pub struct Registered {
    id: u64,
}

impl Drop for Registered {
    fn drop(&mut self) {
        pending().retain(|(id, _)| *id != self.id);
    }
}

/// Register `path` (a file or a directory) for removal if the process is interrupted while the
/// returned guard lives. Register only what this process created and what is worthless without
/// it: a temporary name, never a destination.
pub fn register(path: &Path) -> Registered {
    let id = NEXT.fetch_add(1, Ordering::Relaxed);
    pending().push((id, path.to_path_buf()));
    Registered { id }
}

/// Remove every registered path (a directory with its contents) and forget them: what the
/// watcher does on a signal. Returns how many existed and were removed.
pub fn remove_registered() -> usize {
    let paths: Vec<PathBuf> = pending().drain(..).map(|(_, p)| p).collect();
    remove_all(&paths)
}

/// Remove `paths` (files, or directories with their contents); how many existed and went.
fn remove_all(paths: &[PathBuf]) -> usize {
    let mut removed = 0;
    for p in paths {
        let gone = match std::fs::symlink_metadata(p) {
            Ok(m) if m.is_dir() => std::fs::remove_dir_all(p).is_ok(),
            Ok(_) => std::fs::remove_file(p).is_ok(),
            Err(_) => false,
        };
        removed += gone as usize;
    }
    removed
}

/// The signals after which the watcher cleans up.
#[cfg(unix)]
const SIGNALS: [libc::c_int; 3] = [libc::SIGINT, libc::SIGTERM, libc::SIGHUP];

/// Block SIGINT, SIGTERM and SIGHUP in this thread (and so in every thread started after this
/// call) and start the thread that waits for them, removes the registered paths, and ends the
/// process by the signal it received (a shell then reports it as interrupted, status 130 for
/// Ctrl-C). Call once, in `main`, before any other thread starts. If the thread cannot be
/// started, the signals are unblocked again and keep their default action.
#[cfg(unix)]
pub fn install() {
    // SAFETY: `sigset_t` is plain data, initialised by `sigemptyset` before any other use; the
    // calls only read or write the set and this thread's signal mask.
    unsafe {
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        for s in SIGNALS {
            libc::sigaddset(&mut set, s);
        }
        if libc::pthread_sigmask(libc::SIG_BLOCK, &set, std::ptr::null_mut()) != 0 {
            return;
        }
        let watcher = std::thread::Builder::new()
            .name("biscale-interrupt".into())
            .spawn(move || watch(set));
        if watcher.is_err() {
            libc::pthread_sigmask(libc::SIG_UNBLOCK, &set, std::ptr::null_mut());
        }
    }
}

/// Without POSIX signals there is nothing to install: an interrupted run leaves its temporary
/// names (hidden, never a destination's).
#[cfg(not(unix))]
pub fn install() {}

#[cfg(unix)]
fn watch(set: libc::sigset_t) {
    loop {
        let mut sig: libc::c_int = 0;
        // SAFETY: `set` is a valid signal set, `sig` a valid out-pointer.
        if unsafe { libc::sigwait(&set, &mut sig) } != 0 {
            continue;
        }
        let removed = remove_registered();
        if removed > 0 {
            crate::library::progress::line(&format!(
                "biscale: interrupted: removed {removed} temporary output{} of this run",
                if removed == 1 { "" } else { "s" }
            ));
        }
        // End by the signal itself: its default action, unblocked in this thread, then raised
        // here. Should that return, exit with the shell's status for it.
        // SAFETY: resetting a signal's disposition and raising it in this thread; `set1` is
        // initialised by `sigemptyset`.
        unsafe {
            libc::signal(sig, libc::SIG_DFL);
            let mut set1: libc::sigset_t = std::mem::zeroed();
            libc::sigemptyset(&mut set1);
            libc::sigaddset(&mut set1, sig);
            libc::pthread_sigmask(libc::SIG_UNBLOCK, &set1, std::ptr::null_mut());
            libc::raise(sig);
            libc::_exit(128 + sig);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testdir::TestDir;

    #[test]
    fn registration_lasts_as_long_as_its_guard_and_removal_takes_directories() {
        // Other tests of this process write through registered temporary files at the same
        // time, so only this test's paths are looked at (the global removal would take theirs).
        let d = TestDir::new("interrupt");
        let (file, dir) = (d.join("a.tmp"), d.join("b.partial"));
        let listed = |p: &Path| pending().iter().any(|(_, q)| q == p);
        let a = register(&file);
        let b = register(&dir);
        assert!(listed(&file) && listed(&dir));
        drop(a);
        assert!(!listed(&file) && listed(&dir));
        drop(b);
        assert!(!listed(&dir));
        std::fs::write(&file, b"x").unwrap();
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        std::fs::write(dir.join("sub/f"), b"y").unwrap();
        let missing = d.join("never-made");
        assert_eq!(remove_all(&[file.clone(), dir.clone(), missing]), 2);
        assert!(!file.exists() && !dir.exists());
    }
}
