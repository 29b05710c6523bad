//! Library builds on the `tiny` profile: byte-identical rebuilds, sharded = one-process, resume
//! after a kill (of shards, and of a one-process build writing its joined arrays), finished libraries left alone (unless forced), relative texture directories in
//! sharded builds, corrupted and truncated files, refused directories, and lazy opening.

mod common;

use biscale::library::build::{build_joined, build_shard, Shard};
use biscale::library::profile::LibraryProfile;
use biscale::library::progress::Progress;
use biscale::library::{build_all, merge_shards, Library};
use common::TestDir;
use std::path::{Path, PathBuf};

const QUIET: Progress = Progress { quiet: true };

fn tiny() -> (LibraryProfile, PathBuf) {
    let (p, path) = LibraryProfile::load("tiny").unwrap();
    (p, path.parent().unwrap().to_path_buf())
}

/// `tiny` built as it is in `dirs[0]` and with `edit` in `dirs[1]`: the edited profile, the
/// profiles' directory and the two libraries.
fn tiny_two_ways(
    dirs: [&str; 2],
    edit: impl FnOnce(&mut LibraryProfile),
) -> (LibraryProfile, PathBuf, TestDir, TestDir) {
    let (p, base) = tiny();
    let mut q = p.clone();
    edit(&mut q);
    let (a, b) = (TestDir::new(dirs[0]), TestDir::new(dirs[1]));
    build_all(&p, &base, &a, &QUIET, false, false).unwrap();
    build_all(&q, &base, &b, &QUIET, false, false).unwrap();
    (q, base, a, b)
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
    out.push((
        "profile.toml".into(),
        std::fs::read(dir.join("profile.toml")).unwrap(),
    ));
    out
}

fn manifest_without_build(dir: &Path) -> serde_json::Value {
    let mut v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("manifest.json")).unwrap()).unwrap();
    v.as_object_mut().unwrap().remove("build");
    for part in ["geometry", "material", "material_search"] {
        if let Some(o) = v.get_mut(part).and_then(|p| p.as_object_mut()) {
            o.remove("svd_seconds");
            o.remove("cx_seconds");
        }
    }
    v
}

#[test]
fn same_profile_and_seed_give_identical_files_and_shards_equal_one_process() {
    let (p, base) = tiny();
    let a = TestDir::new("lib-a");
    let b = TestDir::new("lib-b");
    let m = build_all(&p, &base, &a, &QUIET, false, false).unwrap();
    assert_eq!(m.geometries, p.geometry_count());
    assert!(m.geometry.representatives >= 1 && m.material.representatives >= 1);
    // Three shards, built out of order, then merged.
    for i in [2, 0, 1] {
        build_shard(&p, &base, &b, Shard { index: i, count: 3 }, false, &QUIET).unwrap();
    }
    let mb = merge_shards(&b, &QUIET, false).unwrap();
    // The shards' times reach the merged manifest through their records beside the chunks.
    assert_eq!(mb.build.shards_merged, 3);
    assert!(mb.build.geometry_seconds > 0.0 && mb.build.material_seconds > 0.0);
    let (fa, fb) = (data_files(&a), data_files(&b));
    assert_eq!(fa.len(), fb.len());
    for ((na, ba), (nb, bb)) in fa.iter().zip(&fb) {
        assert_eq!(na, nb);
        assert!(
            ba == bb,
            "{na} differs between one-process and sharded builds"
        );
    }
    assert_eq!(manifest_without_build(&a), manifest_without_build(&b));
    assert!(
        !a.join("chunks").exists(),
        "chunks are removed after the merge"
    );
    // The same build again, from scratch: identical bytes.
    let c = TestDir::new("lib-c");
    build_all(&p, &base, &c, &QUIET, false, false).unwrap();
    assert_eq!(data_files(&a), data_files(&c));
}

#[test]
fn an_interrupted_build_resumes_and_a_damaged_chunk_is_rebuilt() {
    let (p, base) = tiny();
    let d = TestDir::new("lib-resume");
    // "Killed" after half the chunks: only shard 0 of 2 exists.
    let first = build_shard(&p, &base, &d, Shard { index: 0, count: 2 }, false, &QUIET).unwrap();
    assert!(first.chunks_built > 0);
    // A merge now names what is missing, and removes no chunk (a merge removes each chunk it
    // joins, but checks first that all are there).
    let count = || std::fs::read_dir(d.join("chunks")).unwrap().count();
    let before = count();
    let e = merge_shards(&d, &QUIET, false).err().unwrap().to_string();
    assert!(e.contains("chunk") && e.contains("missing shards"), "{e}");
    assert_eq!(
        count(),
        before,
        "a merge that cannot finish removes no chunk"
    );
    // Damage one finished chunk: the resumed build redoes only that one.
    let chunk = d.join("chunks").join("geometry-000000.bsa");
    let mut bytes = std::fs::read(&chunk).unwrap();
    let n = bytes.len();
    bytes[n - 3] ^= 0x11;
    std::fs::write(&chunk, &bytes).unwrap();
    let rep = build_shard(&p, &base, &d, Shard::ALL, false, &QUIET).unwrap();
    assert_eq!(rep.chunks_reused, first.chunks_built - 1);
    merge_shards(&d, &QUIET, false).unwrap();
    let clean = TestDir::new("lib-resume-clean");
    build_all(&p, &base, &clean, &QUIET, false, false).unwrap();
    assert_eq!(data_files(&d), data_files(&clean));
}

#[test]
fn a_killed_one_process_build_resumes_its_joined_arrays_and_copies_shard_chunks_in() {
    let (p, base) = tiny();
    let clean = TestDir::new("lib-kill-clean");
    build_all(&p, &base, &clean, &QUIET, false, false).unwrap();
    // Kill -9 the command-line build once its geometry arrays hold a chunk (or later: the
    // timing does not matter to what is checked).
    let d = TestDir::new("lib-kill");
    let log = d.join("geometry/.gamma.bsa.partial.log");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_biscale"))
        .args(["library", "build", "--profile", "tiny", "--quiet", "--out"])
        .arg(d.path())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let units = |log: &Path| {
        std::fs::read_to_string(log)
            .map(|t| t.lines().count().saturating_sub(1))
            .unwrap_or(0)
    };
    let mut seen = 0;
    while child.try_wait().unwrap().is_none() {
        // A chunk counts once both of its arrays have logged it.
        seen = units(&log).min(units(&d.join("geometry/.lobes.bsa.partial.log")));
        if seen >= 1 {
            child.kill().unwrap();
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    child.wait().unwrap();
    let rep = build_joined(&p, &base, &d, false, &QUIET).unwrap();
    if !d.join("geometry/gamma.bsa").exists() {
        panic!("the resumed build did not finish the binned columns");
    }
    assert!(
        rep.chunks_reused >= seen,
        "the {seen} logged chunks were built again ({} reused)",
        rep.chunks_reused
    );
    merge_shards(&d, &QUIET, false).unwrap();
    assert_eq!(data_files(&d), data_files(&clean));
    assert!(
        !log.exists() && !d.join("geometry/.gamma.bsa.partial").exists(),
        "a finished array leaves no partial file or log"
    );

    // Chunks of an earlier sharded build are copied into the arrays, not built again, and
    // removed once the arrays are finished.
    let s = TestDir::new("lib-shard-then-one");
    let half = build_shard(&p, &base, &s, Shard { index: 1, count: 2 }, false, &QUIET).unwrap();
    let rep = build_joined(&p, &base, &s, false, &QUIET).unwrap();
    assert_eq!(rep.chunks_reused, half.chunks_built);
    assert_eq!(
        std::fs::read_dir(s.join("chunks")).unwrap().count(),
        0,
        "copied chunks are removed"
    );
    merge_shards(&s, &QUIET, false).unwrap();
    assert_eq!(data_files(&s), data_files(&clean));
}

#[test]
fn a_merge_stopped_after_joining_resumes_without_rebuilding_the_joined_parts() {
    let (p, base) = tiny();
    let clean = TestDir::new("lib-join-clean");
    build_all(&p, &base, &clean, &QUIET, true, false).unwrap();
    let n_geo_chunks = p.geometry_count().div_ceil(p.chunk);
    // The state of a merge killed while joining the light lobes: the binned columns are joined
    // and their chunks removed, the first light-lobe chunk is joined (removed) but the lobes'
    // joined file was never renamed into place, nothing is compressed, no manifest.
    let d = TestDir::new("lib-join-stopped");
    build_shard(&p, &base, &d, Shard::ALL, false, &QUIET).unwrap();
    std::fs::create_dir_all(d.join("geometry")).unwrap();
    std::fs::copy(
        clean.join("geometry/gamma.bsa"),
        d.join("geometry/gamma.bsa"),
    )
    .unwrap();
    for k in 0..n_geo_chunks {
        std::fs::remove_file(d.join(format!("chunks/geometry-{k:06}.bsa"))).unwrap();
    }
    std::fs::remove_file(d.join("chunks/lobes-000000.bsa")).unwrap();
    // A merge now cannot finish (a light-lobe chunk is gone) and says which.
    let e = merge_shards(&d, &QUIET, false).err().unwrap().to_string();
    assert!(e.contains("lobes chunk 0"), "{e}");
    // The resumed build rebuilds that one chunk only: the joined binned columns stand for theirs.
    let rep = build_shard(&p, &base, &d, Shard::ALL, false, &QUIET).unwrap();
    assert_eq!(rep.chunks_built, 1);
    merge_shards(&d, &QUIET, false).unwrap();
    assert_eq!(data_files(&d), data_files(&clean));
    assert_eq!(manifest_without_build(&d), manifest_without_build(&clean));
    // A corrupted joined array does not stand for anything: its chunks are built again.
    let gamma = d.join("geometry/gamma.bsa");
    let mut bytes = std::fs::read(&gamma).unwrap();
    let n = bytes.len();
    bytes[n - 5] ^= 0x22;
    std::fs::write(&gamma, &bytes).unwrap();
    std::fs::remove_file(d.join("manifest.json")).unwrap();
    let rep = build_shard(&p, &base, &d, Shard::ALL, false, &QUIET).unwrap();
    assert_eq!(rep.chunks_built, n_geo_chunks);
    merge_shards(&d, &QUIET, false).unwrap();
    assert_eq!(data_files(&d), data_files(&clean));
}

#[test]
fn corrupted_truncated_and_foreign_files_are_named_errors_and_opening_is_lazy() {
    let (p, base) = tiny();
    let d = TestDir::new("lib-bad");
    build_all(&p, &base, &d, &QUIET, false, false).unwrap();
    let lib = Library::open(&d).unwrap();
    assert!(lib.reads().is_empty(), "open reads only the manifest");
    let items = lib.geometry_items().unwrap();
    assert_eq!(items.len(), p.geometry_count());
    lib.array("geometry/x.bsa").unwrap();
    let reads = lib.reads().join(" ");
    assert!(
        !reads.contains("material/"),
        "a geometry-only run read {reads}"
    );

    // Corrupt one byte of the geometry matrix.
    let g = d.join("geometry/gamma.bsa");
    let good = std::fs::read(&g).unwrap();
    let mut bad = good.clone();
    let n = bad.len();
    bad[n / 2] ^= 0x5a;
    std::fs::write(&g, &bad).unwrap();
    let e = Library::open(&d)
        .unwrap()
        .array("geometry/gamma.bsa")
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("gamma.bsa") && e.contains("checksum"), "{e}");
    // A merge cannot redo it (its chunks went when it was joined) and says to rebuild, not to
    // build missing shards.
    let e = merge_shards(&d, &QUIET, false).err().unwrap().to_string();
    assert!(
        e.contains("gamma.bsa") && e.contains("--force") && !e.contains("missing shards"),
        "{e}"
    );
    // Truncate it.
    std::fs::write(&g, &good[..n - 1000]).unwrap();
    let e = Library::open(&d)
        .unwrap()
        .array("geometry/gamma.bsa")
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("gamma.bsa") && e.contains("truncated"), "{e}");
    std::fs::write(&g, &good).unwrap();
    // A file from another build (valid on its own, wrong for this manifest).
    let other = TestDir::new("lib-bad-other");
    let mut q = p.clone();
    q.seed = 2;
    build_all(&q, &base, &other, &QUIET, false, false).unwrap();
    std::fs::copy(other.join("geometry/x.bsa"), d.join("geometry/x.bsa")).unwrap();
    let e = Library::open(&d)
        .unwrap()
        .array("geometry/x.bsa")
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("x.bsa") && e.contains("manifest"), "{e}");
    // Building another profile into the same directory is refused, and leaves no chunks/.
    let e = build_all(&q, &base, &d, &QUIET, false, false)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("another profile"), "{e}");
    assert!(
        !d.join("chunks").exists(),
        "a refused build created chunks/"
    );
    let e = build_shard(&q, &base, &d, Shard { index: 1, count: 4 }, true, &QUIET)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("another profile"), "{e}");
    assert!(
        !d.join("chunks").exists(),
        "a refused shard created chunks/"
    );
    assert!(
        d.join("manifest.json").exists(),
        "a refused forced build removed the manifest"
    );
    // A damaged manifest.
    std::fs::write(d.join("manifest.json"), b"{\"format\": 3").unwrap();
    let e = Library::open(&d).err().unwrap().to_string();
    assert!(e.contains("manifest.json"), "{e}");
}

#[test]
fn a_finished_library_is_not_rebuilt_unless_forced() {
    let (p, base) = tiny();
    let d = TestDir::new("lib-finished");
    let m = build_all(&p, &base, &d, &QUIET, false, false).unwrap();
    let manifest = std::fs::read(d.join("manifest.json")).unwrap();
    let files = data_files(&d);
    // Again: nothing is recomputed (the chunks are gone, so a rebuild would recreate them and
    // rewrite the manifest's build times).
    let again = build_all(&p, &base, &d, &QUIET, false, false).unwrap();
    assert_eq!(again.files, m.files);
    assert_eq!(std::fs::read(d.join("manifest.json")).unwrap(), manifest);
    assert!(
        !d.join("chunks").exists(),
        "an already-built library was rebuilt"
    );
    // A shard build into the finished library does nothing either.
    let rep = build_shard(&p, &base, &d, Shard { index: 1, count: 3 }, false, &QUIET).unwrap();
    assert!(rep.already_built);
    assert_eq!(rep.chunks_built + rep.chunks_reused, 0);
    assert!(!d.join("chunks").exists());
    assert_eq!(std::fs::read(d.join("manifest.json")).unwrap(), manifest);
    // A library missing a file it lists is not finished: it is merged again, from its joined
    // arrays (their checksums hold), without building a chunk.
    std::fs::remove_file(d.join("material/x.bsa")).unwrap();
    let rep = build_shard(&p, &base, &d, Shard::ALL, false, &QUIET).unwrap();
    assert!(!rep.already_built);
    assert_eq!(
        rep.chunks_built, 0,
        "the joined arrays stand for the chunks"
    );
    merge_shards(&d, &QUIET, false).unwrap();
    assert_eq!(data_files(&d), files);
    // Without them it is rebuilt from chunks.
    std::fs::remove_file(d.join("material/x.bsa")).unwrap();
    std::fs::remove_file(d.join("material/prefiltered.bsa")).unwrap();
    build_all(&p, &base, &d, &QUIET, true, false).unwrap();
    assert!(
        d.join("chunks/material-000000.bsa").exists(),
        "the damaged library was not rebuilt"
    );
    assert_eq!(data_files(&d), files);
    std::fs::remove_dir_all(d.join("chunks")).unwrap();
    // Forced: everything is built again, to the same bytes.
    let manifest = std::fs::read(d.join("manifest.json")).unwrap();
    build_all(&p, &base, &d, &QUIET, true, true).unwrap();
    assert!(
        d.join("chunks").exists(),
        "a forced build reused the finished library"
    );
    assert_ne!(std::fs::read(d.join("manifest.json")).unwrap(), manifest);
    assert_eq!(data_files(&d), files);
    // A forced shard build removes the manifest: the directory is not a finished library again
    // until the merge.
    build_shard(&p, &base, &d, Shard { index: 0, count: 2 }, true, &QUIET).unwrap();
    assert!(!d.join("manifest.json").exists());
    assert!(Library::open(&d).is_err());
    build_shard(&p, &base, &d, Shard { index: 1, count: 2 }, false, &QUIET).unwrap();
    merge_shards(&d, &QUIET, false).unwrap();
    assert_eq!(data_files(&d), files);
}

#[test]
fn relative_texture_dirs_are_stored_absolute_so_a_sharded_merge_finds_them() {
    let root = TestDir::new("lib-reltex");
    let pdir = root.join("profiles");
    std::fs::create_dir_all(pdir.join("tex")).unwrap();
    let img =
        image::GrayImage::from_fn(64, 64, |x, y| image::Luma([((x * 7 + y * 3) % 256) as u8]));
    img.save(pdir.join("tex").join("stripes.png")).unwrap();
    let (mut p, _) = tiny();
    p.name = "reltex".into();
    // Keep the build small: the texture family only, from the relative directory "tex".
    p.geometry.family.retain(|f| f.generator == "texture");
    p.geometry.family[0].builtin_textures = false;
    p.geometry.family[0].texture_dirs = vec![PathBuf::from("tex")];
    p.geometry.family[0].count = 2;
    let text = p.canonical();
    assert!(text.contains("\"tex\""), "{text}");
    let ppath = pdir.join("reltex.toml");
    std::fs::write(&ppath, text).unwrap();

    let (loaded, path) = LibraryProfile::load(ppath.to_str().unwrap()).unwrap();
    let abs = std::path::absolute(pdir.join("tex")).unwrap();
    assert_eq!(loaded.geometry.family[0].texture_dirs, vec![abs.clone()]);
    let base = path.parent().unwrap().to_path_buf();
    // Shards, then a separate merge, which reads only the stored profile.
    let lib = root.join("lib");
    for i in 0..2 {
        build_shard(
            &loaded,
            &base,
            &lib,
            Shard { index: i, count: 2 },
            false,
            &QUIET,
        )
        .unwrap();
    }
    let stored = std::fs::read_to_string(lib.join("profile.toml")).unwrap();
    assert!(stored.contains(&abs.display().to_string()), "{stored}");
    let m = merge_shards(&lib, &QUIET, false).unwrap();
    assert_eq!(m.geometries, 2);
    let items = Library::open(&lib).unwrap().geometry_items().unwrap();
    let png = abs.join("stripes.png").display().to_string();
    assert!(items[0].spec.contains(&png), "{items:?}");
    // The profile as written (relative dirs), built in one process against its own directory,
    // gives the same library.
    let one = root.join("one");
    build_all(&p, &base, &one, &QUIET, false, false).unwrap();
    assert_eq!(data_files(&lib), data_files(&one));
}

#[test]
fn light_lobe_weights_fit_the_probes_at_least_as_well_as_the_binned_fit_and_refit_is_identical() {
    use biscale::library::lobefit::Probes;
    let (p, base) = tiny();
    let d = TestDir::new("lib-lobefit");
    build_all(&p, &base, &d, &QUIET, false, false).unwrap();
    let lib = Library::open(&d).unwrap();
    assert!(lib.has("geometry/x-lobes.bsa"));
    let reps = lib.array("geometry/representatives.bsa").unwrap();
    let reps = reps.u32s().unwrap();
    let (x, xl) = (
        lib.array("geometry/x.bsa").unwrap(),
        lib.array("geometry/x-lobes.bsa").unwrap(),
    );
    let (x, xl) = (x.f32s().unwrap(), xl.f32s().unwrap());
    assert_eq!(x.len(), xl.len());
    assert!(xl.iter().all(|w| w.is_finite()));
    // The probes of the fit: the library's representative materials.
    let mats = lib.material_items().unwrap();
    let mreps = lib.array("material/representatives.bsa").unwrap();
    let tables = mreps
        .u32s()
        .unwrap()
        .iter()
        .map(|&m| {
            let m = m as usize;
            let mat = biscale::material::parse_material(&mats[m].spec).unwrap();
            biscale::solve::material_prefiltered(&lib, &mat, Some(m)).unwrap()
        })
        .collect();
    // A library material's table is read in place: the entries of its row of the array, and a
    // material past the last is an error naming the file.
    let all = lib.array("material/prefiltered.bsa").unwrap();
    let (all, tlen) = (all.f32s().unwrap(), lib.manifest.table_len);
    let ggx = biscale::material::parse_material("ggx:alpha=0.2").unwrap();
    for m in [0, mats.len() - 1] {
        let pf = biscale::solve::material_prefiltered(&lib, &ggx, Some(m)).unwrap();
        assert_eq!(pf.table(), &all[m * tlen..(m + 1) * tlen]);
    }
    let e = biscale::solve::material_prefiltered(&lib, &ggx, Some(mats.len()))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("prefiltered.bsa") && e.contains("no material"),
        "{e}"
    );
    let layout = lib.gamma_layout();
    let probes = Probes::with_tables(&layout, tables);
    let lobes = lib.geometry_lobes().unwrap();
    let rv: Vec<Vec<f64>> = reps
        .iter()
        .map(|&r| probes.values(&lobes.get(r as usize).unwrap()))
        .collect();
    let c = reps.len();
    // Residual of the combination of the representatives' probe values with weights `w`
    // against the geometry's own (unscaled: the fit scales each material's block, so compare
    // the sum over blocks loosely, with a margin).
    let residual = |own: &[f64], w: &[f32]| -> f64 {
        let mut d = 0.0;
        for (i, o) in own.iter().enumerate() {
            let v: f64 = (0..c).map(|k| w[k] as f64 * rv[k][i]).sum();
            d += (v - o) * (v - o);
        }
        let n: f64 = own.iter().map(|o| o * o).sum();
        (d / n.max(1e-300)).sqrt()
    };
    let (mut better, mut n) = (0, 0);
    for j in 0..lib.manifest.geometries {
        let own = probes.values(&lobes.get(j).unwrap());
        let (e0, e1) = (
            residual(&own, &x[j * c..(j + 1) * c]),
            residual(&own, &xl[j * c..(j + 1) * c]),
        );
        assert!(
            e1 <= e0 * 1.05 + 1e-6,
            "geometry {j}: refit {e1} vs binned fit {e0}"
        );
        if e0 > 1e-3 {
            better += (e1 < 0.9 * e0) as usize;
            n += 1;
        }
    }
    assert!(
        better * 2 >= n,
        "the refit improved only {better} of the {n} geometries the binned fit misses"
    );
    // Refitting the finished library gives the same bytes.
    let before = std::fs::read(d.join("geometry/x-lobes.bsa")).unwrap();
    biscale::library::commands::refit(&d, None, false, false, true).unwrap();
    assert_eq!(
        std::fs::read(d.join("geometry/x-lobes.bsa")).unwrap(),
        before
    );
    assert!(Library::open(&d).unwrap().has("geometry/x-lobes.bsa"));
}

/// The material solver's finer representatives: written by the build when the profile asks
/// (`compression.material_search_energy`), left out when it does not, and added to such a
/// library by `library refit --material-search-energy`, which makes it the library the changed
/// profile builds (the same files, the same manifest but for times). A bad energy is refused
/// naming the key, before anything is written.
#[test]
fn the_material_search_selection_is_built_or_refitted_to_the_same_files() {
    use biscale::library::commands::refit;
    let (p, base) = tiny();
    let e = p.compression.material_search_energy;
    assert!(e.is_some(), "the tiny profile asks for the finer selection");
    let with = TestDir::new("lib-search-with");
    build_all(&p, &base, &with, &QUIET, false, false).unwrap();
    let lib = Library::open(&with).unwrap();
    let (coarse, fine) = (
        &lib.manifest.material,
        lib.manifest.material_search.as_ref(),
    );
    let fine = fine.unwrap();
    assert!(fine.rank > coarse.rank && fine.representatives > coarse.representatives);
    assert!(fine.total_rel_error < coarse.total_rel_error);
    assert!(lib.has("material/search-x.bsa") && lib.has("material/search-representatives.bsa"));

    let mut p0 = p.clone();
    p0.compression.material_search_energy = None;
    let without = TestDir::new("lib-search-without");
    build_all(&p0, &base, &without, &QUIET, false, false).unwrap();
    let lib0 = Library::open(&without).unwrap();
    assert!(lib0.manifest.material_search.is_none());
    assert!(!without.join("material/search-x.bsa").exists());
    // The coarse selection does not depend on the finer one (the SVD is truncated, not rerun).
    for f in [
        "material/x.bsa",
        "material/representatives.bsa",
        "material/coords.bsa",
    ] {
        assert_eq!(
            std::fs::read(with.join(f)).unwrap(),
            std::fs::read(without.join(f)).unwrap(),
            "{f}"
        );
    }
    let bad = refit(&without, Some(0.5), false, false, true)
        .unwrap_err()
        .to_string();
    assert!(bad.contains("compression.material_search_energy"), "{bad}");
    assert!(Library::open(&without)
        .unwrap()
        .manifest
        .material_search
        .is_none());
    refit(&without, e, false, false, true).unwrap();
    assert_eq!(data_files(&without), data_files(&with));
    assert_eq!(
        manifest_without_build(&without),
        manifest_without_build(&with)
    );
    Library::open(&without).unwrap().verify_all().unwrap();
}

#[test]
fn a_geometry_pilot_keeps_the_energy_in_one_pass_and_shards_still_equal_one_process() {
    // Six times tiny's geometries (its 29 span 19 directions at 99 %: too few for a pilot).
    let (mut whole_p, base) = tiny();
    for f in &mut whole_p.geometry.family {
        f.count *= 6;
    }
    let mut p = whole_p.clone();
    p.compression.geometry_pilot = Some(128);
    let a = TestDir::new("lib-pilot-a");
    let m = build_all(&p, &base, &a, &QUIET, false, false).unwrap();
    let g = &m.geometry;
    // The basis came from 128 of the 174 geometries, then one pass over all of them; the energy
    // kept is the whole matrix's.
    assert_eq!(
        (g.pilot_columns, g.passes),
        (Some(128), 1),
        "{g:?} (the pilot's basis fell back to the whole matrix)"
    );
    assert!(g.pilot_passes.unwrap() >= 2 + 2 * p.compression.power_iters);
    assert!(g.energy_kept >= p.compression.geometry_energy, "{g:?}");
    let whole = TestDir::new("lib-pilot-none");
    let mw = build_all(&whole_p, &base, &whole, &QUIET, false, false).unwrap();
    assert!(mw.geometry.pilot_columns.is_none() && mw.geometry.passes >= 6);
    // No rank-r projection keeps more than the leading r singular values (Eckart–Young), so
    // the pilot's rank is at least the whole matrix's (whose randomized SVD is within rounding
    // of the leading values); the columns the pilot did not see cost it more (71 against 52
    // here, 103 against 99 on `paper4`, docs/library.md).
    assert!(
        g.rank + 1 >= mw.geometry.rank,
        "{} against {}",
        g.rank,
        mw.geometry.rank
    );
    // The pilot is a part of the merge: a sharded build still equals the one-process build.
    let b = TestDir::new("lib-pilot-b");
    for i in [1, 0] {
        build_shard(&p, &base, &b, Shard { index: i, count: 2 }, false, &QUIET).unwrap();
    }
    merge_shards(&b, &QUIET, false).unwrap();
    assert_eq!(data_files(&a), data_files(&b));
    assert_eq!(manifest_without_build(&a), manifest_without_build(&b));
}

/// The light lobes in half precision (the default, `geometry.lobe_precision = "half"`) and in
/// `f32` (`"single"`, and libraries built before the option) give the same `fbar` to well
/// under the 1 % of an exact recovery, in about half the bytes; both forms open.
/// 210 pairs at the library's lights (30 views each, to 87°), where records are compared.
fn probe_pairs(lib: &Library) -> biscale::lightlobes::LightPairs {
    let layout = lib.gamma_layout();
    let pairs = (0..7)
        .flat_map(|l| {
            let wi = layout.lights[l];
            (0..30).map(move |k| biscale::frame::DirPair {
                wi,
                wo: biscale::frame::dir_from_deg(3.0 * k as f64, 37.0 * k as f64),
            })
        })
        .collect();
    biscale::lightlobes::LightPairs::new(&layout, pairs)
}

/// A sharp and a broad material's prefiltered tables, to compare records with.
fn probe_tables() -> Vec<(&'static str, biscale::prefilter::Prefiltered)> {
    ["ggx:alpha=0.02,f0=0.9", "blinn:n=60+lambert:albedo=0.2"]
        .into_iter()
        .map(|m| {
            let mat = biscale::material::parse_material(m).unwrap();
            (
                m,
                biscale::prefilter::Prefiltered::build(&mat, &Default::default()),
            )
        })
        .collect()
}

#[test]
fn half_precision_light_lobes_match_the_f32_records_in_half_the_bytes() {
    use biscale::library::profile::LobePrecision;
    let (_, _, dh, ds) = tiny_two_ways(["lib-half", "lib-single"], |p| {
        assert_eq!(p.geometry.lobe_precision, LobePrecision::Half);
        p.geometry.lobe_precision = LobePrecision::Single;
    });
    let size = |d: &Path, rel: &str| std::fs::metadata(d.join(rel)).map_or(0, |m| m.len());
    let half_bytes = size(&dh, "geometry/lobes.bsa") + size(&dh, "geometry/lobe-heads.bsa");
    let single_bytes = size(&ds, "geometry/lobes.bsa");
    assert_eq!(size(&ds, "geometry/lobe-heads.bsa"), 0);
    assert!(
        (half_bytes as f64) < 0.52 * single_bytes as f64,
        "{half_bytes} against {single_bytes} bytes"
    );
    let (lh, ls) = (Library::open(&dh).unwrap(), Library::open(&ds).unwrap());
    let (gh, gs) = (lh.geometry_lobes().unwrap(), ls.geometry_lobes().unwrap());
    let at = probe_pairs(&lh);
    for (m, pf) in probe_tables() {
        for j in 0..lh.manifest.geometries {
            let (a, b) = (
                gs.get(j).unwrap().fbar(&pf, &at),
                gh.get(j).unwrap().fbar(&pf, &at),
            );
            assert_eq!(a, gs.read(j).unwrap().fbar(&pf, &at));
            assert_eq!(b, gh.read(j).unwrap().fbar(&pf, &at));
            let rel = biscale::bench::relative_rms(&b, &a);
            assert!(rel < 5e-4, "geometry {j}, {m}: half against f32 {rel}");
        }
    }
    // `library refit --half-lobes` turns the f32 library into the half-precision build.
    drop((gs, ls));
    biscale::library::commands::refit(&ds, None, true, false, true).unwrap();
    assert_eq!(data_files(&ds), data_files(&dh));
    assert_eq!(manifest_without_build(&ds), manifest_without_build(&dh));
    // Again: nothing left to convert, the same files.
    biscale::library::commands::refit(&ds, None, true, false, true).unwrap();
    assert_eq!(data_files(&ds), data_files(&dh));
}

#[test]
fn packed_light_lobes_are_the_half_records_numbers_in_fewer_bytes() {
    let (p, base) = tiny();
    let (dh, dp) = (
        TestDir::new("lib-pack-half"),
        TestDir::new("lib-pack-packed"),
    );
    build_all(&p, &base, &dh, &QUIET, false, false).unwrap();
    build_all(&p, &base, &dp, &QUIET, false, false).unwrap();
    biscale::library::commands::refit(&dp, None, false, true, true).unwrap();
    let size = |d: &Path, rel: &str| std::fs::metadata(d.join(rel)).map_or(0, |m| m.len());
    let (half, packed) = (
        size(&dh, "geometry/lobes.bsa"),
        size(&dp, "geometry/lobes.bsa") + size(&dp, "geometry/lobe-offsets.bsa"),
    );
    assert!(packed < half * 9 / 10, "{packed} against {half} bytes");
    let (lh, lp) = (Library::open(&dh).unwrap(), Library::open(&dp).unwrap());
    let (gh, gp) = (lh.geometry_lobes().unwrap(), lp.geometry_lobes().unwrap());
    assert!(gp.is_packed() && !gh.is_packed());
    assert_eq!(gp.len(), lh.manifest.geometries);
    let at = probe_pairs(&lh);
    // The same numbers, bit for bit, mapped or read.
    for (m, pf) in probe_tables() {
        for j in 0..lh.manifest.geometries {
            let a = gh.get(j).unwrap().fbar(&pf, &at);
            assert_eq!(a, gp.get(j).unwrap().fbar(&pf, &at), "geometry {j}, {m}");
            assert_eq!(a, gp.read(j).unwrap().fbar(&pf, &at), "geometry {j}, {m}");
            // With its index made once (a target look reads one record many times).
            let ix = gp.index(j).unwrap();
            assert!(ix.is_some() && gh.index(j).unwrap().is_none());
            let b = gp.get_indexed(j, ix.as_ref()).unwrap().fbar(&pf, &at);
            assert_eq!(a, b, "geometry {j}, {m}");
        }
    }
    assert!(gp.get(lh.manifest.geometries).is_err());
    // An index that does not fit the record is an error, not a misread.
    let other = (0..lh.manifest.geometries)
        .map(|j| gp.index(j).unwrap().unwrap())
        .find(|ix| ix.words() != gp.index(0).unwrap().unwrap().words())
        .expect("records of different lengths");
    assert!(gp.get_indexed(0, Some(&other)).is_err());
    // The weights refitted to them are the same bytes, and so is a solve's answer.
    let same =
        |rel: &str| std::fs::read(dh.join(rel)).unwrap() == std::fs::read(dp.join(rel)).unwrap();
    assert!(same("geometry/x-lobes.bsa") && same("geometry/lobe-heads.bsa"));
    let (look, mat, opt) = common::aniso_ward_geometry_case();
    let a = biscale::solve::geometry::solve(&lh, &look, &mat, "ggx", None, &opt).unwrap();
    let b = biscale::solve::geometry::solve(&lp, &look, &mat, "ggx", None, &opt).unwrap();
    let key = |r: &biscale::solve::SolveResult| -> Vec<(Option<usize>, f64, f64)> {
        r.candidates
            .iter()
            .map(|c| (c.geometry, c.rerank_error, c.error))
            .collect()
    };
    assert_eq!(key(&a), key(&b));
    drop((gp, lp));
    // Again: nothing left to pack, the same files; and every file matches the manifest.
    let files = data_files(&dp);
    biscale::library::commands::refit(&dp, None, false, true, true).unwrap();
    assert_eq!(files, data_files(&dp));
    biscale::library::commands::verify(&dp).unwrap();
    // Offsets that do not end at the records' length: an error naming the offsets.
    let off = dp.join("geometry/lobe-offsets.bsa");
    let o = biscale::store::ArrayFile::open(&off, &Default::default()).unwrap();
    let mut v = o.u64s().unwrap().to_vec();
    drop(o);
    *v.last_mut().unwrap() += 1;
    biscale::store::write_array(
        &off,
        "light-lobe-offsets",
        biscale::store::Dtype::U64,
        &[v.len()],
        bytemuck::cast_slice(&v),
    )
    .unwrap();
    let e = Library::open(&dp)
        .and_then(|l| l.geometry_lobes().map(|_| ()))
        .unwrap_err()
        .to_string();
    assert!(e.contains("lobe-offsets.bsa"), "{e}");
}

#[test]
fn byte_binned_columns_are_within_a_32nd_of_half_precision_and_the_solvers_read_them() {
    use biscale::library::profile::GammaPrecision;
    let (byte, base, dh, db) = tiny_two_ways(["lib-gamma-half", "lib-gamma-byte"], |p| {
        assert_eq!(p.geometry.gamma_precision, GammaPrecision::Half);
        p.geometry.gamma_precision = GammaPrecision::Byte;
    });
    let (lh, lb) = (Library::open(&dh).unwrap(), Library::open(&db).unwrap());
    let (ch, cb) = (lh.binned_columns().unwrap(), lb.binned_columns().unwrap());
    assert_eq!(ch.file.header.dtype, biscale::store::Dtype::F16);
    assert_eq!(cb.file.header.dtype, biscale::store::Dtype::UF8);
    assert_eq!(2 * cb.file.header.data_bytes(), ch.file.header.data_bytes());
    // Every entry within a 32nd of the half-precision one (which is itself within 2⁻¹¹ of the
    // traced value both were rounded from), or below the byte's smallest normal.
    for j in 0..lh.manifest.geometries {
        let (a, b) = (ch.column(j).unwrap(), cb.column(j).unwrap());
        for (i, (&h, &v)) in a.iter().zip(&b).enumerate() {
            assert!(
                (v - h).abs() <= h / 32.0 * 1.001 + 2f32.powi(-18),
                "geometry {j}, row {i}: half {h}, byte {v}"
            );
        }
    }
    // The light lobes and the materials are the same bytes; only the binned matrix and what
    // was computed from it differ.
    let same =
        |rel: &str| std::fs::read(dh.join(rel)).unwrap() == std::fs::read(db.join(rel)).unwrap();
    for rel in [
        "geometry/lobes.bsa",
        "geometry/lobe-heads.bsa",
        "material/prefiltered.bsa",
    ] {
        assert!(same(rel), "{rel}");
    }
    // The geometry solver reads the byte columns for its second ranking and finds the same
    // best geometry.
    let (look, mat, opt) = common::aniso_ward_geometry_case();
    let a = biscale::solve::geometry::solve(&lh, &look, &mat, "ggx", None, &opt).unwrap();
    let b = biscale::solve::geometry::solve(&lb, &look, &mat, "ggx", None, &opt).unwrap();
    assert!(lb.reads().join(" ").contains("geometry/gamma.bsa"));
    assert_eq!(a.candidates[0].geometry, b.candidates[0].geometry);
    assert!((a.candidates[0].error - b.candidates[0].error).abs() < 1e-9);
    // A rebuild gives the same bytes.
    let db2 = TestDir::new("lib-gamma-byte-2");
    build_all(&byte, &base, &db2, &QUIET, false, false).unwrap();
    assert_eq!(data_files(&db), data_files(&db2));
}
