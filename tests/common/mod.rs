//! Scratch directories for the integration tests, which leave nothing behind in `/tmp`.
//! [`TestDir`] is the library's own `src/testdir.rs`, included by path (the tests cannot see the
//! library's `cfg(test)` items); [`shared_dir`] is for scratch that a whole test process shares
//! and so is never dropped.

#![allow(dead_code)] // each test file uses a part

#[path = "../../src/testdir.rs"]
mod testdir;
pub(crate) use testdir::TestDir;

use std::path::{Path, PathBuf};

/// `NAME-PID` under cargo's `target/tmp` (gone with `cargo clean`), for scratch held in a
/// `static` and so never dropped. It is removed first if there (the process id may be reused),
/// and so are the `NAME-PID` of earlier test processes that have ended (on Linux, where
/// `/proc/PID` tells; elsewhere they are left).
pub fn shared_dir(name: &str) -> PathBuf {
    let root = Path::new(env!("CARGO_TARGET_TMPDIR"));
    let prefix = format!("{name}-");
    let me = std::process::id();
    if cfg!(target_os = "linux") {
        for e in std::fs::read_dir(root).into_iter().flatten().flatten() {
            let file_name = e.file_name();
            let pid = file_name
                .to_str()
                .and_then(|n| n.strip_prefix(&prefix))
                .and_then(|p| p.parse::<u32>().ok());
            if let Some(pid) = pid {
                if pid != me && !Path::new(&format!("/proc/{pid}")).exists() {
                    let _ = std::fs::remove_dir_all(e.path());
                }
            }
        }
    }
    let d = root.join(format!("{name}-{me}"));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// The geometry solver's standard test case: the anisotropic Ward look of the paper's Fig. 7
/// with a glossy GGX fixed, K = 3 from a pool of 6 at two rotations, the fast final evaluator.
pub fn aniso_ward_geometry_case() -> (
    biscale::solve::Look,
    biscale::material::Material,
    biscale::solve::SolveOptions,
) {
    let look =
        biscale::solve::Look::from_spec("ward:ax=0.3,ay=0.08", Default::default(), None).unwrap();
    let mat = biscale::material::parse_material("ggx:alpha=0.1,f0=0.9").unwrap();
    let opt = biscale::solve::SolveOptions {
        k: 3,
        pool: 6,
        psi: 2,
        final_eval: biscale::solve::Final::Fast,
        ..Default::default()
    };
    (look, mat, opt)
}
