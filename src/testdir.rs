//! Scratch directories for unit tests: [`TestDir`] makes a fresh, empty directory of the test's
//! own under the system temporary directory and removes it when dropped, so a test leaves
//! nothing behind in `/tmp`, even when it fails half-way (unwinding drops it). The integration
//! tests include this file by path (`tests/common/mod.rs`), so its items are `pub(crate)`: crate
//! wide in the library, and in each test crate.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

static COUNTER: AtomicUsize = AtomicUsize::new(0);

/// A directory `biscale-TAG-PID-N` under [`std::env::temp_dir`], removed on drop. `N` counts the
/// directories of this process, so tests running in parallel never share one.
#[derive(Debug)]
pub(crate) struct TestDir(PathBuf);

impl TestDir {
    pub(crate) fn new(tag: &str) -> TestDir {
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let p = std::env::temp_dir().join(format!("biscale-{tag}-{}-{n}", std::process::id()));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap_or_else(|e| panic!("create {}: {e}", p.display()));
        TestDir(p)
    }

    pub(crate) fn path(&self) -> &Path {
        &self.0
    }
}

/// So that a `TestDir` goes wherever a `&Path` does: `&dir`, `dir.join(...)`.
impl std::ops::Deref for TestDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for TestDir {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl Drop for TestDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}
