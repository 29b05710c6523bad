//! Library builds on the `tiny` profile: byte-identical rebuilds, sharded = one-process, resume
//! after a kill, corrupted and truncated files, and lazy opening.

use biscale::library::build::{build_shard, Shard};
use biscale::library::profile::LibraryProfile;
use biscale::library::progress::Progress;
use biscale::library::{build_all, merge_shards, Library};
use std::path::{Path, PathBuf};

const QUIET: Progress = Progress { quiet: true };

fn fresh(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("biscale-lib-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn tiny() -> (LibraryProfile, PathBuf) {
    let (p, path) = LibraryProfile::load("tiny").unwrap();
    (p, path.parent().unwrap().to_path_buf())
}

/// Every file of a library except the manifest (whose `build` section holds times).
fn data_files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for sub in ["geometry", "material"] {
        let mut names: Vec<_> = std::fs::read_dir(dir.join(sub))
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        names.sort();
        for p in names {
            out.push((
                p.strip_prefix(dir).unwrap().display().to_string(),
                std::fs::read(&p).unwrap(),
            ));
        }
    }
    out.push(("profile.toml".into(), std::fs::read(dir.join("profile.toml")).unwrap()));
    out
}

fn manifest_without_build(dir: &Path) -> serde_json::Value {
    let mut v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("manifest.json")).unwrap()).unwrap();
    v.as_object_mut().unwrap().remove("build");
    for part in ["geometry", "material"] {
        let o = v[part].as_object_mut().unwrap();
        o.remove("svd_seconds");
        o.remove("cx_seconds");
    }
    v
}

#[test]
fn same_profile_and_seed_give_identical_files_and_shards_equal_one_process() {
    let (p, base) = tiny();
    let a = fresh("a");
    let b = fresh("b");
    let m = build_all(&p, &base, &a, &QUIET, false).unwrap();
    assert_eq!(m.geometries, p.geometry_count());
    assert!(m.geometry.representatives >= 1 && m.material.representatives >= 1);
    // Three shards, built out of order, then merged.
    for i in [2, 0, 1] {
        build_shard(&p, &base, &b, Shard { index: i, count: 3 }, &QUIET).unwrap();
    }
    merge_shards(&b, &QUIET, false).unwrap();
    let (fa, fb) = (data_files(&a), data_files(&b));
    assert_eq!(fa.len(), fb.len());
    for ((na, ba), (nb, bb)) in fa.iter().zip(&fb) {
        assert_eq!(na, nb);
        assert!(ba == bb, "{na} differs between one-process and sharded builds");
    }
    assert_eq!(manifest_without_build(&a), manifest_without_build(&b));
    assert!(!a.join("chunks").exists(), "chunks are removed after the merge");
    // The same build again, from scratch: identical bytes.
    let c = fresh("c");
    build_all(&p, &base, &c, &QUIET, false).unwrap();
    assert_eq!(data_files(&a), data_files(&c));
    for d in [a, b, c] {
        let _ = std::fs::remove_dir_all(d);
    }
}

#[test]
fn an_interrupted_build_resumes_and_a_damaged_chunk_is_rebuilt() {
    let (p, base) = tiny();
    let d = fresh("resume");
    // "Killed" after half the chunks: only shard 0 of 2 exists.
    let first = build_shard(&p, &base, &d, Shard { index: 0, count: 2 }, &QUIET).unwrap();
    assert!(first.chunks_built > 0);
    // A merge now names what is missing.
    let e = merge_shards(&d, &QUIET, true).err().unwrap().to_string();
    assert!(e.contains("chunk") && e.contains("missing shards"), "{e}");
    // Damage one finished chunk: the resumed build redoes only that one.
    let chunk = d.join("chunks").join("geometry-000000.bsa");
    let mut bytes = std::fs::read(&chunk).unwrap();
    let n = bytes.len();
    bytes[n - 3] ^= 0x11;
    std::fs::write(&chunk, &bytes).unwrap();
    let rep = build_shard(&p, &base, &d, Shard::ALL, &QUIET).unwrap();
    assert_eq!(rep.chunks_reused, first.chunks_built - 1);
    merge_shards(&d, &QUIET, false).unwrap();
    let clean = fresh("resume-clean");
    build_all(&p, &base, &clean, &QUIET, false).unwrap();
    assert_eq!(data_files(&d), data_files(&clean));
    let _ = std::fs::remove_dir_all(d);
    let _ = std::fs::remove_dir_all(clean);
}

#[test]
fn corrupted_truncated_and_foreign_files_are_named_errors_and_opening_is_lazy() {
    let (p, base) = tiny();
    let d = fresh("bad");
    build_all(&p, &base, &d, &QUIET, false).unwrap();
    let lib = Library::open(&d).unwrap();
    assert!(lib.reads().is_empty(), "open reads only the manifest");
    let items = lib.geometry_items().unwrap();
    assert_eq!(items.len(), p.geometry_count());
    lib.array("geometry/x.bsa").unwrap();
    let reads = lib.reads().join(" ");
    assert!(!reads.contains("material/"), "a geometry-only run read {reads}");

    // Corrupt one byte of the geometry matrix.
    let g = d.join("geometry/gamma.bsa");
    let good = std::fs::read(&g).unwrap();
    let mut bad = good.clone();
    let n = bad.len();
    bad[n / 2] ^= 0x5a;
    std::fs::write(&g, &bad).unwrap();
    let e = Library::open(&d).unwrap().array("geometry/gamma.bsa").err().unwrap().to_string();
    assert!(e.contains("gamma.bsa") && e.contains("checksum"), "{e}");
    // Truncate it.
    std::fs::write(&g, &good[..n - 1000]).unwrap();
    let e = Library::open(&d).unwrap().array("geometry/gamma.bsa").err().unwrap().to_string();
    assert!(e.contains("gamma.bsa") && e.contains("truncated"), "{e}");
    std::fs::write(&g, &good).unwrap();
    // A file from another build (valid on its own, wrong for this manifest).
    let other = fresh("bad-other");
    let mut q = p.clone();
    q.seed = 2;
    build_all(&q, &base, &other, &QUIET, false).unwrap();
    std::fs::copy(other.join("geometry/x.bsa"), d.join("geometry/x.bsa")).unwrap();
    let e = Library::open(&d).unwrap().array("geometry/x.bsa").err().unwrap().to_string();
    assert!(e.contains("x.bsa") && e.contains("manifest"), "{e}");
    // Building another profile into the same directory is refused.
    let e = build_all(&q, &base, &d, &QUIET, false).err().unwrap().to_string();
    assert!(e.contains("another profile"), "{e}");
    // A damaged manifest.
    std::fs::write(d.join("manifest.json"), b"{\"format\": 3").unwrap();
    let e = Library::open(&d).err().unwrap().to_string();
    assert!(e.contains("manifest.json"), "{e}");
    let _ = std::fs::remove_dir_all(d);
    let _ = std::fs::remove_dir_all(other);
}
