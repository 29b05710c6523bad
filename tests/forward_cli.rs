//! The `forward` command line (acceptance check 6): nonsense input fails with a message naming the
//! input and what was expected, a non-zero exit code and no output file; the happy path writes
//! `theta_i,phi_i,theta_o,phi_o,fbar,brdf` with `brdf = fbar / cos(theta_i)`, for both methods and
//! for a `.npy` heightmap whose fbar does not change when patch size and height scale are scaled
//! together (BVNDFs are scale-free).

mod common;

use biscale::npy::write_npy_f64;
use common::TestDir;
use std::path::{Path, PathBuf};
use std::process::Command;

const PAIRS: &str =
    "theta_i,phi_i,theta_o,phi_o\n0,0,0,0\n30,0,30,180\n60,10,45,200\n85,0,89,90\n89.9,0,30,180\n";

fn write_pairs(dir: &Path) -> PathBuf {
    let p = dir.join("pairs.csv");
    std::fs::write(&p, PAIRS).unwrap();
    p
}

/// Run `biscale forward` with `args`; returns (success, exit code, stdout, stderr).
fn forward(args: &[&str]) -> (bool, Option<i32>, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_biscale"))
        .arg("forward")
        .args(args)
        .output()
        .expect("run the biscale binary");
    (
        out.status.success(),
        out.status.code(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Files in `dir` (names), to check that a failed run left nothing behind.
fn listing(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// A failing run: non-zero exit, stderr names every string in `must_name`, no output file, and
/// no temporary file left in the directory.
fn expect_failure(dir: &Path, args: &[&str], out: &Path, must_name: &[&str]) {
    let before = listing(dir);
    let (okay, code, _stdout, stderr) = forward(args);
    assert!(!okay, "{args:?} succeeded; stderr: {stderr}");
    assert!(
        matches!(code, Some(c) if c != 0),
        "{args:?}: exit code {code:?}"
    );
    for s in must_name {
        assert!(
            stderr.contains(s),
            "{args:?}: message does not name '{s}': {stderr}"
        );
    }
    assert!(
        !stderr.contains("panicked"),
        "{args:?}: a panic, not a message: {stderr}"
    );
    assert!(!out.exists(), "{args:?}: output file {out:?} was created");
    assert_eq!(listing(dir), before, "{args:?}: files appeared in {dir:?}");
}

#[test]
fn nonsense_input_is_rejected_clearly() {
    let dir = TestDir::new("fwdcli-bad");
    let pairs = write_pairs(&dir);
    let pairs_s = pairs.to_str().unwrap();
    let out = dir.join("out.csv");
    let out_s = out.to_str().unwrap();
    let base = |geo: &str, mat: &str, pairs: &str| -> Vec<String> {
        [
            "--geometry",
            geo,
            "--material",
            mat,
            "--pairs",
            pairs,
            "--method",
            "exact",
            "--out",
            out_s,
            "-q",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    let run = |args: Vec<String>, names: &[&str]| {
        let a: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
        expect_failure(&dir, &a, &out, names);
    };

    // Negative roughness: names the flag, the parameter and the accepted range.
    run(
        base("vgroove:n=16", "ggx:alpha=-0.1", pairs_s),
        &["--material", "alpha=-0.1", "expected"],
    );
    // Unknown model.
    run(
        base("vgroove:n=16", "velvet:sheen=1", pairs_s),
        &["velvet", "unknown material model", "expected"],
    );
    // Nonexistent heightmap.
    let missing = dir.join("missing.npy");
    run(
        base(missing.to_str().unwrap(), "lambert:albedo=0.5", pairs_s),
        &["missing.npy"],
    );
    // Corrupt .npy: the magic, then garbage.
    let corrupt = dir.join("corrupt.npy");
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&[0xff, 0x7f]);
    bytes.extend_from_slice(b"{'descr': '<f8', 'shape': (garbage");
    std::fs::write(&corrupt, &bytes).unwrap();
    run(
        base(corrupt.to_str().unwrap(), "lambert:albedo=0.5", pairs_s),
        &["corrupt.npy"],
    );
    // Not an .npy at all (text with an .npy name).
    let text = dir.join("text.npy");
    std::fs::write(&text, "hello").unwrap();
    run(
        base(text.to_str().unwrap(), "lambert:albedo=0.5", pairs_s),
        &["text.npy", "expected"],
    );
    // A .npy containing NaN: names the file and the sample.
    let nan = dir.join("nan.npy");
    let mut z = vec![0.0; 16];
    z[6] = f64::NAN;
    write_npy_f64(&nan, 4, 4, &z).unwrap();
    run(
        base(nan.to_str().unwrap(), "lambert:albedo=0.5", pairs_s),
        &["nan.npy", "row 1, column 2", "finite"],
    );
    // Wrong CSV header.
    let bad_header = dir.join("bad_header.csv");
    std::fs::write(&bad_header, "theta_in,phi_i,theta_o,phi_o\n30,0,30,180\n").unwrap();
    run(
        base(
            "vgroove:n=16",
            "lambert:albedo=0.5",
            bad_header.to_str().unwrap(),
        ),
        &["bad_header.csv", "theta_i,phi_i,theta_o,phi_o"],
    );
    // theta over 90°.
    let over = dir.join("over90.csv");
    std::fs::write(&over, "theta_i,phi_i,theta_o,phi_o\n30,0,95,180\n").unwrap();
    run(
        base("vgroove:n=16", "lambert:albedo=0.5", over.to_str().unwrap()),
        &["over90.csv", "line 2", "theta_o", "95", "90"],
    );
    // theta exactly 90° (at the horizon) is not above the surface either.
    let at90 = dir.join("at90.csv");
    std::fs::write(&at90, "theta_i,phi_i,theta_o,phi_o\n90,0,30,180\n").unwrap();
    run(
        base("vgroove:n=16", "lambert:albedo=0.5", at90.to_str().unwrap()),
        &["at90.csv", "theta_i"],
    );
    // The output path is a directory.
    let outdir = dir.join("an_output_dir");
    std::fs::create_dir(&outdir).unwrap();
    let mut a = base("vgroove:n=16", "lambert:albedo=0.5", pairs_s);
    let i = a.iter().position(|s| s == "--out").unwrap();
    a[i + 1] = outdir.to_str().unwrap().to_string();
    run(a, &["an_output_dir", "directory"]);
    assert!(
        listing(&outdir).is_empty(),
        "files written into the directory"
    );
    // The output path's parent is a file.
    let mut a = base("vgroove:n=16", "lambert:albedo=0.5", pairs_s);
    a[i + 1] = pairs.join("o.csv").to_str().unwrap().to_string();
    run(a, &["pairs.csv"]);
    // The output's directory does not exist: refused, and not created.
    let mut a = base("vgroove:n=16", "lambert:albedo=0.5", pairs_s);
    let missing = dir.join("no_such_dir");
    a[i + 1] = missing.join("o.csv").to_str().unwrap().to_string();
    run(a, &["--out", "no_such_dir", "does not exist"]);
    assert!(!missing.exists(), "the missing directory was created");
    // Lobe counts out of range name the option and the range.
    for opt in ["--clusters", "--sub-lobes"] {
        let mut a = base("vgroove:n=16", "lambert:albedo=0.5", pairs_s);
        a.extend([opt.to_string(), "0".to_string()]);
        run(a, &[opt, "1..=64"]);
    }
    // The grid's last polar node must lie below the horizon.
    for bad in ["90", "-1", "x"] {
        let mut a = base("vgroove:n=16", "lambert:albedo=0.5", pairs_s);
        a.extend(["--last-theta".to_string(), bad.to_string()]);
        run(a, &["--last-theta", "45..=89.99"]);
    }
    // A grid whose table cannot fit in memory (8192 directions, 64 clusters: about 150 GB)
    // is refused before it is built, naming the options and the sizes.
    let mut a = base("vgroove:n=16", "lambert:albedo=0.5", pairs_s);
    let m = a.iter().position(|s| s == "--method").unwrap();
    a[m + 1] = "fast".to_string();
    a.extend(
        ["--n-theta", "64", "--n-phi", "128", "--clusters", "64"]
            .iter()
            .map(|s| s.to_string()),
    );
    run(a, &["--n-theta", "--n-phi", "GB"]);
}

/// Options out of their ranges fail before any work (no library is opened or built), naming the
/// option and the range, for the solver commands as for `forward`.
#[test]
fn solver_options_out_of_range_fail_before_any_work() {
    let cases: &[(&[&str], &str)] = &[
        (&["solve", "--beta", "2"], "[0, 1]"),
        (&["solve", "--beta", "nan"], "[0, 1]"),
        (&["solve", "--stop-below", "nan"], "[0, 1]"),
        (&["solve", "--bound", "-1"], "[0.000001, 10]"),
        (&["solve", "-k", "0"], "[1, 1000]"),
        (&["solve", "--psi", "0"], "[1, 360]"),
        (&["solve", "--pool", "0"], "[1, 100000000]"),
        (&["solve", "--starts", "0"], "[1, 1000]"),
        (&["solve", "--beam", "0"], "[1, 1000]"),
        (&["solve", "--veds", "0"], "[1, 1000]"),
        (&["validate", "--starts", "0"], "[1, 1000]"),
        (&["validate", "--pool", "0"], "[1, 100000000]"),
        (&["solve", "--brightness", "0"], "[0.000001, 1000000]"),
        (&["solve", "--contrast", "1e308"], "[0, 1000]"),
        (&["validate", "--cases", "0"], "[1, 1000000]"),
        (&["forward", "--exact-samples", "0"], "[1, 16]"),
    ];
    for (args, range) in cases {
        let out = Command::new(env!("CARGO_BIN_EXE_biscale"))
            .args(*args)
            .output()
            .expect("run the biscale binary");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(
            err.contains(args[1]) && err.contains(range) && !err.contains("panicked"),
            "{args:?}: {err}"
        );
    }
}

/// Parse a forward CSV: header and rows of six numbers.
fn read_out(path: &Path) -> (String, Vec<[f64; 6]>) {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header = lines.next().unwrap().to_string();
    let rows = lines
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.trim().parse().unwrap()).collect();
            assert_eq!(v.len(), 6, "row {l}");
            [v[0], v[1], v[2], v[3], v[4], v[5]]
        })
        .collect();
    (header, rows)
}

/// The CSV carries 10 significant digits ({:.9e}), so brdf and fbar / cos(theta_i) agree to ~1e-9
/// relative; 1e-8 leaves room for the rounding of both printed numbers.
fn check_brdf_column(rows: &[[f64; 6]], what: &str) {
    assert_eq!(rows.len(), 5, "{what}: one row per pair");
    for r in rows {
        let (fbar, brdf) = (r[4], r[5]);
        assert!(
            fbar.is_finite() && fbar >= 0.0 && brdf.is_finite(),
            "{what}: {r:?}"
        );
        let want = fbar / r[0].to_radians().cos();
        assert!(
            (brdf - want).abs() <= 1e-8 * want.abs().max(1e-300),
            "{what}: brdf {brdf} vs fbar/cos(theta_i) {want} in row {r:?}"
        );
    }
    // at least one pair lights something
    assert!(rows.iter().any(|r| r[4] > 0.0), "{what}: all fbar are 0");
}

#[test]
fn happy_path_exact_and_fast() {
    let dir = TestDir::new("fwdcli-ok");
    let pairs = write_pairs(&dir);
    for method in ["exact", "fast"] {
        let out = dir.join(format!("O_{method}.csv"));
        let (okay, _, _, stderr) = forward(&[
            "--geometry",
            "vgroove:n=32",
            "--material",
            "lambert:albedo=0.5",
            "--pairs",
            pairs.to_str().unwrap(),
            "--method",
            method,
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(okay, "{method}: {stderr}");
        if method == "exact" {
            // The log gives the rays and the estimated error of the automatic choice.
            assert!(
                stderr.contains("2×2: ") && stderr.contains("--exact-tol"),
                "{stderr}"
            );
        }
        let (header, rows) = read_out(&out);
        assert_eq!(header, "theta_i,phi_i,theta_o,phi_o,fbar,brdf");
        check_brdf_column(&rows, method);
        // the angle columns echo the pairs file
        assert_eq!(rows[2][..4], [60.0, 10.0, 45.0, 200.0]);
    }
    // `--out -` is standard output (run in the test's directory: no file named `-` appears).
    let out = Command::new(env!("CARGO_BIN_EXE_biscale"))
        .current_dir(&*dir)
        .args([
            "forward",
            "--geometry",
            "vgroove:n=32",
            "--material",
            "lambert:albedo=0.5",
        ])
        .args(["--pairs", pairs.to_str().unwrap(), "--out", "-", "--quiet"])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && stdout.starts_with("theta_i,phi_i,theta_o,phi_o,fbar,brdf"),
        "{stdout}"
    );
    assert!(!dir.join("-").exists());
}

/// Standard output that goes away (`| head`) ends the output quietly; a full disk there is an
/// error naming standard output; neither panics.
#[test]
fn results_to_a_closed_or_full_standard_output() {
    let dir = TestDir::new("fwdcli-stdout");
    // 20,000 pairs: about 1 MB of CSV, more than a pipe holds.
    let mut csv = String::from("theta_i,phi_i,theta_o,phi_o\n");
    for k in 0..20_000 {
        csv.push_str(&format!(
            "{},{},{},{}\n",
            k % 80,
            k % 360,
            (k / 7) % 80,
            (k * 3) % 360
        ));
    }
    let pairs = dir.join("many.csv");
    std::fs::write(&pairs, csv).unwrap();
    let args = [
        "forward",
        "--geometry",
        "flat:n=4",
        "--material",
        "lambert:albedo=0.5",
        "--method",
        "exact",
        "--pairs",
        pairs.to_str().unwrap(),
        "-q",
    ];
    let mut child = Command::new(env!("CARGO_BIN_EXE_biscale"))
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // Read the first line, then close the pipe.
    let mut out = child.stdout.take().unwrap();
    let mut first = [0u8; 64];
    let _ = std::io::Read::read(&mut out, &mut first).unwrap();
    drop(out);
    let done = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&done.stderr);
    assert!(done.status.success(), "{:?}: {stderr}", done.status);
    assert!(!stderr.contains("panicked"), "{stderr}");
    if let Ok(full) = std::fs::OpenOptions::new().write(true).open("/dev/full") {
        let done = Command::new(env!("CARGO_BIN_EXE_biscale"))
            .args(args)
            .stdout(full)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&done.stderr);
        assert_eq!(done.status.code(), Some(2), "{stderr}");
        assert!(
            stderr.contains("standard output") && !stderr.contains("panicked"),
            "{stderr}"
        );
    }
}

#[test]
fn npy_heightmap_is_scale_free() {
    let dir = TestDir::new("fwdcli-npy");
    let pairs = write_pairs(&dir);
    // A smooth periodic bump field, values in "mm at height scale 1".
    let n = 24;
    let mut z = vec![0.0; n * n];
    for y in 0..n {
        for x in 0..n {
            let (u, v) = (
                std::f64::consts::TAU * x as f64 / n as f64,
                std::f64::consts::TAU * y as f64 / n as f64,
            );
            z[y * n + x] = 0.3 * (u.sin() * (2.0 * v).cos() + 0.5 * (u + v).cos());
        }
    }
    let hm = dir.join("hm.npy");
    write_npy_f64(&hm, n, n, &z).unwrap();
    // The fast method rebuilds its prefiltered table per run (~0.6 s for Lambert, ~2.5 s for a
    // glossy sum in release), so it gets the cheaper material and two scalings.
    for (method, material, scalings) in [
        (
            "exact",
            "ggx:alpha=0.3+lambert:albedo=0.2",
            &[("5", "1"), ("10", "2"), ("0.5", "0.1")][..],
        ),
        ("fast", "lambert:albedo=0.5", &[("5", "1"), ("10", "2")][..]),
    ] {
        let mut results = Vec::new();
        // (patch size mm, height scale): grid heights = stored × scale / (patch / n), equal for all.
        for &(patch, hs) in scalings {
            let out = dir.join(format!("O_{method}_{patch}.csv"));
            let (okay, _, _, stderr) = forward(&[
                "--geometry",
                hm.to_str().unwrap(),
                "--patch-size",
                patch,
                "--height-scale",
                hs,
                "--material",
                material,
                "--pairs",
                pairs.to_str().unwrap(),
                "--method",
                method,
                "--out",
                out.to_str().unwrap(),
                "-q",
            ]);
            assert!(okay, "{method} {patch} {hs}: {stderr}");
            let (header, rows) = read_out(&out);
            assert_eq!(header, "theta_i,phi_i,theta_o,phi_o,fbar,brdf");
            check_brdf_column(&rows, method);
            results.push(rows);
        }
        // The relief must matter (otherwise the check is vacuous): a flatter patch differs.
        let out = dir.join(format!("O_{method}_flatter.csv"));
        let (okay, _, _, stderr) = forward(&[
            "--geometry",
            hm.to_str().unwrap(),
            "--patch-size",
            "10",
            "--height-scale",
            "1",
            "--material",
            material,
            "--pairs",
            pairs.to_str().unwrap(),
            "--method",
            method,
            "--out",
            out.to_str().unwrap(),
            "-q",
        ]);
        assert!(okay, "{stderr}");
        let flatter = read_out(&out).1;
        // Same grid heights up to the last bit of the scale factor: fbar agrees to the printed
        // precision (1e-9 relative).
        for rows in &results[1..] {
            for (a, b) in rows.iter().zip(&results[0]) {
                assert!(
                    (a[4] - b[4]).abs() <= 1e-9 * b[4].abs().max(1e-300),
                    "{method}: fbar changed when patch size and height scale scaled together: {a:?} vs {b:?}"
                );
            }
        }
        assert!(
            flatter
                .iter()
                .zip(&results[0])
                .any(|(a, b)| (a[4] - b[4]).abs() > 1e-6 * b[4].abs()),
            "{method}: halving the relief changed nothing; the scale check would be vacuous"
        );
    }
}

/// The fast method's build settings are the user's: `--n-theta`, `--n-phi`, `--points`,
/// `--seen-rays` and `--last-theta` reach
/// the compact BVNDF (its log names them), and a coarser grid changes the answer only a little
/// up to 85° (both are estimates of the same fbar).
#[test]
fn fast_build_settings_reach_the_bvndf() {
    let dir = TestDir::new("fwdcli-fast-settings");
    let pairs = write_pairs(&dir);
    let run = |extra: &[&str]| -> (String, Vec<f64>) {
        let mut args = vec![
            "--geometry",
            "vgroove:n=32,depth=6",
            "--material",
            "ggx:alpha=0.3",
            "--pairs",
            pairs.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let (ok, _, stdout, stderr) = forward(&args);
        assert!(ok, "{stderr}");
        let fbar = stdout
            .lines()
            .skip(1)
            .map(|l| l.split(',').nth(4).unwrap().parse::<f64>().unwrap())
            .collect();
        (stderr, fbar)
    };
    let (log_default, default) = run(&[]);
    // 25 polar nodes × 40 azimuths, the last three beyond 88.5°.
    assert!(
        log_default.contains("1000 directions (25 polar nodes to 89.9°)"),
        "{log_default}"
    );
    let (log_fine, fine) = run(&[
        "--n-theta",
        "10",
        "--n-phi",
        "16",
        "--points",
        "16384",
        "--seen-rays",
        "0",
        "--last-theta",
        "88.5",
    ]);
    assert!(
        log_fine.contains("160 directions (10 polar nodes to 88.5°)"),
        "{log_fine}"
    );
    assert!(
        log_fine.contains("16384 surface points, 0 seen rays"),
        "{log_fine}"
    );
    assert_ne!(default, fine);
    // Up to 85° (the first three pairs); beyond 88.5° the coarse grid repeats its last row.
    for (a, b) in default.iter().zip(&fine).take(3) {
        assert!((a - b).abs() <= 0.1 * b.abs().max(1e-3), "{a} vs {b}");
    }
}

/// The progress lines of `forward` (plain lines per tenth, as stderr is not a terminal here):
/// every bar's count never goes back and its last line reaches its length (the exact method's
/// bar counts each pair from each end); `-q` prints none.
#[test]
fn progress_lines_count_every_step_and_never_go_back() {
    let dir = TestDir::new("fwdcli-progress");
    let pairs = write_pairs(&dir);
    let pairs = pairs.to_str().unwrap();
    let n_pairs = PAIRS.lines().count() - 1;
    // `(label, position, length)` of every progress line.
    let bars = |stderr: &str| -> Vec<(String, u64, u64)> {
        stderr
            .lines()
            .filter_map(|l| {
                let (label, rest) = l.rsplit_once(": ")?;
                let count = rest.split_whitespace().next()?;
                let (pos, len) = count.split_once('/')?;
                Some((label.to_string(), pos.parse().ok()?, len.parse().ok()?))
            })
            .collect()
    };
    let check = |stderr: &str, want: &[&str]| {
        let lines = bars(stderr);
        for label in want {
            let mine: Vec<_> = lines.iter().filter(|(l, _, _)| l == label).collect();
            assert!(!mine.is_empty(), "no line of '{label}' in {stderr}");
            assert!(
                mine.windows(2)
                    .all(|w| w[0].1 <= w[1].1 && w[0].2 <= w[1].2),
                "'{label}' went back: {mine:?}"
            );
            let last = mine[mine.len() - 1];
            assert_eq!(
                last.1, last.2,
                "'{label}' did not end at its length: {mine:?}"
            );
        }
        lines
    };
    let geometry = ["--geometry", "bumps:n=16", "--material", "ggx:alpha=0.2"];
    let mut args = geometry.to_vec();
    args.extend([
        "--pairs",
        pairs,
        "--method",
        "exact",
        "--exact-samples",
        "2",
    ]);
    let (ok, _, _, stderr) = forward(&args);
    assert!(ok, "{stderr}");
    let lines = check(&stderr, &["exact: pairs (from each end)"]);
    assert_eq!(lines.last().unwrap().2, 2 * n_pairs as u64);
    let mut args = geometry.to_vec();
    args.extend(["--pairs", pairs, "--method", "fast"]);
    let (ok, _, _, stderr) = forward(&args);
    assert!(ok, "{stderr}");
    check(
        &stderr,
        &[
            "compact BVNDF: seen areas (directions)",
            "compact BVNDF: horizons (facets)",
        ],
    );
    args.push("-q");
    let (ok, _, _, stderr) = forward(&args);
    assert!(ok && stderr.is_empty(), "{stderr}");
}
