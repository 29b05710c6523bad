//! The fabrication stage end to end: shipped profiles load and bad ones fail with the file and the
//! key; the milling simulation against closed forms; feature widths of grooves of known width;
//! the scale window; costs; exported STL solids checked by the Manifold kernel and read back with
//! stl_io; determinism; no partial files; OBJ import.

mod common;

use biscale::fab::catalogue::{Tool, ToolKind};
use biscale::fab::export::stl_bytes;
use biscale::fab::mesh::{solid, verify, TileGrid};
use biscale::fab::{
    check_detail, export_detail, import_obj, load_profile, millability, CheckOptions, Decimation,
    FabPaths,
};
use biscale::generators::parse_generator;
use biscale::heightfield::Heightfield;
use common::TestDir;
use std::path::Path;

fn paths() -> FabPaths {
    FabPaths::new(Path::new(env!("CARGO_MANIFEST_DIR")))
}

fn gen(spec: &str) -> Heightfield {
    parse_generator(spec).unwrap().build().unwrap()
}

fn ball(d: f64) -> Tool {
    Tool {
        name: "t".into(),
        kind: ToolKind::Ball,
        diameter_mm: d,
        flute_length_mm: 100.0,
    }
}

/// A heightfield from a profile along x, constant along y.
fn profile_x(w: usize, h: usize, f: impl Fn(usize) -> f64) -> Heightfield {
    let z = (0..w * h).map(|i| f(i % w)).collect();
    Heightfield::new(w, h, z, 1.0, "test").unwrap()
}

// ---------------------------------------------------------------- profiles

#[test]
fn every_shipped_profile_loads() {
    let p = paths();
    let names = p.shipped_profiles().unwrap();
    assert!(names.len() >= 8, "{names:?}");
    for n in &names {
        let pr = load_profile(n, &p).unwrap_or_else(|e| panic!("{n}: {e}"));
        assert!(pr.base_thickness_mm > 0.0 && pr.min_feature_mm > 0.0, "{n}");
        assert_eq!(pr.machine.kind() == "mill", pr.tool.is_some(), "{n}");
    }
    let pr = load_profile("cnc-ball1-aluminium", &p).unwrap();
    assert_eq!(pr.tool.as_ref().unwrap().diameter_mm, 1.0);
    assert_eq!(pr.material.name, "aluminium-6061");
    for (n, d) in [
        ("cnc-ball0.5-wax", 0.5),
        ("cnc-ball3-wood", 3.0),
        ("cnc-ball0.5-aluminium", 0.5),
    ] {
        assert_eq!(load_profile(n, &p).unwrap().tool.unwrap().diameter_mm, d);
    }
}

const GOOD: &str = "machine = \"mill-3axis\"\ntool = \"ball-1mm\"\nmaterial = \"machining-wax\"\nstepover_mm = 0.1\n\
base_thickness_mm = 3.0\nmin_feature_mm = 0.3\nmax_deviation_frac = 0.1\nviewing_distance_mm = 1000.0\n\
max_period_arcmin = 1.0\nweight_material = 1.0\nweight_time_per_h = 30.0\n";

fn load_text(dir: &Path, file: &str, text: &str) -> Result<biscale::fab::Profile, String> {
    let f = dir.join(file);
    std::fs::write(&f, text).unwrap();
    load_profile(f.to_str().unwrap(), &paths()).map_err(|e| e.to_string())
}

#[test]
fn bad_profiles_name_file_and_key() {
    let d = TestDir::new("fab-bad");
    assert!(load_text(&d, "good.toml", GOOD).is_ok());
    let cases: Vec<(&str, String, Vec<&str>)> = vec![
        (
            "unknown.toml",
            format!("{GOOD}stepover = 0.2\n"),
            vec!["unknown key `stepover`", "stepover_mm"],
        ),
        (
            "missing.toml",
            GOOD.replace("min_feature_mm = 0.3\n", ""),
            vec!["missing key `min_feature_mm`"],
        ),
        (
            "type.toml",
            GOOD.replace("base_thickness_mm = 3.0", "base_thickness_mm = \"thick\""),
            vec!["`base_thickness_mm`", "expected a number", "line 5"],
        ),
        (
            "negative.toml",
            GOOD.replace("base_thickness_mm = 3.0", "base_thickness_mm = -3.0"),
            vec!["`base_thickness_mm`", "positive"],
        ),
        (
            "zero.toml",
            GOOD.replace("stepover_mm = 0.1", "stepover_mm = 0"),
            vec!["`stepover_mm`", "positive"],
        ),
        (
            "tool.toml",
            GOOD.replace("ball-1mm", "ball-2mm"),
            vec!["key `tool`", "\"ball-2mm\"", "\"ball-1mm\"", "\"flat-3mm\""],
        ),
        (
            "mat.toml",
            GOOD.replace("machining-wax", "pla"),
            vec!["key `material`", "not worked by a mill"],
        ),
        (
            "frac.toml",
            GOOD.replace("max_deviation_frac = 0.1", "max_deviation_frac = 2"),
            vec!["`max_deviation_frac`", "(0, 1]"],
        ),
        (
            "syntax.toml",
            format!("{GOOD}weight_time_per_h = 3\n"),
            vec!["duplicate key"],
        ),
    ];
    for (file, text, want) in cases {
        let e = load_text(&d, file, &text).expect_err(file);
        assert!(e.contains(file), "{file}: {e}");
        for w in want {
            assert!(e.contains(w), "{file}: expected '{w}' in: {e}");
        }
    }
    // extends: a user profile overriding two keys of a shipped one.
    let p = load_text(
        &d,
        "mine.toml",
        "extends = \"cnc-ball1-aluminium\"\nstepover_mm = 0.05\nbase_thickness_mm = 6\n",
    )
    .unwrap();
    assert_eq!((p.stepover_mm, p.base_thickness_mm), (Some(0.05), 6.0));
    assert_eq!(p.tool.unwrap().name, "ball-1mm");
    assert_eq!(p.files.len(), 2);
    // A printer profile extending a mill profile: the mill's tool and stepover, inherited from
    // before the machine changed, are dropped; set beside the printer, they are an error.
    let p = load_text(
        &d,
        "to-sla.toml",
        "extends = \"cnc-ball1-aluminium\"\nmachine = \"sla-resin\"\nmaterial = \"sla-resin-standard\"\n",
    )
    .unwrap();
    assert!(p.tool.is_none() && p.stepover_mm.is_none());
    // The other keys are inherited as they were.
    assert_eq!(p.base_thickness_mm, 3.0);
    let e = load_text(
        &d,
        "to-sla-tool.toml",
        "extends = \"cnc-ball1-aluminium\"\nmachine = \"sla-resin\"\nmaterial = \"sla-resin-standard\"\ntool = \"ball-1mm\"\n",
    )
    .unwrap_err();
    assert!(
        e.contains("to-sla-tool.toml") && e.contains("`tool`"),
        "{e}"
    );
    // a bad override is reported in the user's file.
    let e = load_text(
        &d,
        "mine2.toml",
        "extends = \"cnc-ball1-aluminium\"\nmin_feature_mm = -1\n",
    )
    .unwrap_err();
    assert!(
        e.contains("mine2.toml") && e.contains("`min_feature_mm`"),
        "{e}"
    );
    // extends cycle and unknown parent.
    std::fs::write(d.join("a.toml"), "extends = \"b.toml\"\n").unwrap();
    std::fs::write(
        d.join("b.toml"),
        "extends = \"a.toml\"\nstepover_mm = 0.1\n",
    )
    .unwrap();
    let e = load_profile(d.join("a.toml").to_str().unwrap(), &paths())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("`extends`") && e.contains("cycle") && e.contains("b.toml"),
        "{e}"
    );
    let e = load_text(&d, "orphan.toml", "extends = \"cnc-ball9\"\n").unwrap_err();
    assert!(
        e.contains("orphan.toml") && e.contains("`extends`") && e.contains("cnc-ball1-aluminium"),
        "{e}"
    );
    let e = load_profile("no-such-profile", &paths())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("no-such-profile") && e.contains("sla-50um"),
        "{e}"
    );
}

#[test]
fn bad_catalogue_names_file_section_and_key() {
    let d = TestDir::new("fab-cat");
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("constraints");
    std::fs::create_dir_all(d.join("constraints")).unwrap();
    std::fs::create_dir_all(d.join("profiles/fabrication")).unwrap();
    std::fs::copy(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("profiles/fabrication/cnc-ball1-wax.toml"),
        d.join("profiles/fabrication/p.toml"),
    )
    .unwrap();
    for f in ["tools.toml", "machines.toml", "materials.toml"] {
        std::fs::copy(src.join(f), d.join("constraints").join(f)).unwrap();
    }
    let p = FabPaths::new(&d);
    assert!(load_profile("p", &p).is_ok());
    // Found from a scene in `d` (whatever the working directory), with the shipped names still
    // reachable from the user's own profiles directory.
    std::fs::write(
        d.join("profiles/fabrication/mine.toml"),
        "extends = \"cnc-ball1-aluminium\"\nbase_thickness_mm = 4\n",
    )
    .unwrap();
    let here = FabPaths::for_scene(Some(&d));
    let mine = load_profile("mine", &here).unwrap();
    assert_eq!(mine.base_thickness_mm, 4.0);
    assert!(load_profile("cnc-ball3-wood", &here).is_ok());
    assert!(
        mine.catalogues.iter().all(|c| c.starts_with(&*d)),
        "{:?}",
        mine.catalogues
    );
    let tools = std::fs::read_to_string(src.join("tools.toml")).unwrap();
    let cases = [
        (
            tools.replacen("diameter_mm = 3.0", "diameter_mm = -3.0", 1),
            vec!["tools.toml", "[ball-3mm]", "`diameter_mm`", "positive"],
        ),
        (
            tools.replacen("kind = \"flat\"", "kind = \"bull\"", 1),
            vec!["tools.toml", "[flat-1mm]", "`kind`", "\"ball\" or \"flat\""],
        ),
        (
            tools.replacen("flute_length_mm = 3.0", "flute_mm = 3.0", 1),
            vec!["tools.toml", "[ball-1mm]", "unknown key `flute_mm`"],
        ),
        (
            tools.replacen("\n[\"ball-0.5mm\"]\n", "\n[ball-0.5mm]\n", 1),
            vec!["tools.toml", "[ball-0.5mm] (line", "write [\"ball-0.5mm\"]"],
        ),
    ];
    for (text, want) in cases {
        std::fs::write(d.join("constraints/tools.toml"), text).unwrap();
        let e = load_profile("p", &p).unwrap_err().to_string();
        for w in want {
            assert!(e.contains(w), "expected '{w}' in: {e}");
        }
    }
    std::fs::copy(src.join("tools.toml"), d.join("constraints/tools.toml")).unwrap();
    let m = std::fs::read_to_string(src.join("machines.toml")).unwrap();
    std::fs::write(
        d.join("constraints/machines.toml"),
        m.replacen(
            "plunge_mm_per_min = 300.0",
            "plunge_mm_per_min = 300.0\nnozzle_mm = 0.4",
            1,
        ),
    )
    .unwrap();
    let e = load_profile("p", &p).unwrap_err().to_string();
    assert!(
        e.contains("machines.toml")
            && e.contains("[mill-3axis]")
            && e.contains("`nozzle_mm` does not apply"),
        "{e}"
    );
}

// ---------------------------------------------------------------- milling closed forms

/// V grooves of half-angle `a` (between flank and vertical), bottom on a sample: a ball of radius
/// r touching both flanks has its centre at r / sin a above the bottom, so it leaves the bottom
/// filled by r (1 / sin a − 1). Sampling the tool positions and the surface on a grid of spacing
/// c moves the two maxima/minima of the closing by at most c² / (8 r sin³ a) each (second-order
/// error of a smooth maximum), 0.0013 mm at a = 30°, c = 0.05 mm, r = 1 mm.
#[test]
fn v_groove_deviation_matches_closed_form() {
    let (w, period) = (256usize, 64usize);
    let patch = 12.8; // c = 0.05 mm
    let r = 1.0;
    for a_deg in [30.0f64, 45.0, 60.0] {
        let a = a_deg.to_radians();
        let depth = (period as f64 / 2.0) / a.tan(); // grid units
        let hf = profile_x(w, 8, |x| {
            depth * ((2.0 * (x % period) as f64 / period as f64) - 1.0).abs()
        });
        let sim = millability::mill(&hf, patch, &ball(2.0 * r), None).unwrap();
        let want = r * (1.0 / a.sin() - 1.0);
        let c = 0.05;
        let tol = 2.0 * c * c / (8.0 * r * a.sin().powi(3));
        let got = sim.report.max_deviation_mm;
        assert!(
            (got - want).abs() <= tol,
            "a = {a_deg}°: {got} vs {want} (tol {tol})"
        );
        assert_eq!(sim.report.refine, 1);
    }
}

/// Ball of radius r resting in the trough of z = A cos(kx) (trough at x = π/k): tangent at ±t
/// where the normal through (t, z(t)) passes the centre; solved by bisection on t.
fn sine_trough_fill(amp: f64, k: f64, r: f64) -> f64 {
    // x measured from the trough: z = -A cos(k x); normal direction (-z', 1).
    let z = |x: f64| -amp * (k * x).cos();
    let dz = |x: f64| amp * k * (k * x).sin();
    // centre on x = 0 at height z(t) + r / sqrt(1 + z'^2); its x: t - r z' / sqrt(1 + z'^2) = 0
    let f = |t: f64| t - r * dz(t) / (1.0 + dz(t) * dz(t)).sqrt();
    let (mut lo, mut hi) = (1e-12, std::f64::consts::PI / (2.0 * k));
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if f(mid) < 0.0 {
            lo = mid
        } else {
            hi = mid
        }
    }
    let t = 0.5 * (lo + hi);
    let zc = z(t) + r / (1.0 + dz(t) * dz(t)).sqrt();
    zc - r - z(0.0)
}

#[test]
fn sine_fills_only_where_curvature_exceeds_the_tool() {
    let (w, period) = (512usize, 128usize);
    let patch = 12.8; // c = 0.025 mm, period 3.2 mm
    let k = std::f64::consts::TAU / (period as f64 * 0.025);
    let r = 0.5;
    for (curv_ratio, label) in [(4.0, "sharp"), (0.5, "gentle")] {
        let amp_mm = curv_ratio / (r * k * k); // trough curvature A k² = ratio / r
        let amp = amp_mm / 0.025;
        let hf = profile_x(w, 4, |x| {
            amp * (std::f64::consts::TAU * x as f64 / period as f64).cos()
        });
        let sim = millability::mill(&hf, patch, &ball(2.0 * r), None).unwrap();
        let got = sim.report.max_deviation_mm;
        if curv_ratio > 1.0 {
            let want = sine_trough_fill(amp_mm, k, r);
            assert!(want > 0.01, "{want}");
            assert!(
                (got - want).abs() < 0.002 + 0.01 * want,
                "{label}: {got} vs {want}"
            );
        } else {
            // the ball fits everywhere: only grid sampling error (c²/8r ≈ 1.6e-4 mm) remains
            assert!(got < 5e-4, "{label}: {got}");
        }
    }
}

#[test]
fn flat_is_untouched_and_wraparound_is_periodic() {
    let flat = Heightfield::flat(64, 64);
    for t in [
        ball(1.0),
        Tool {
            kind: ToolKind::Flat,
            ..ball(1.0)
        },
    ] {
        let s = millability::mill(&flat, 10.0, &t, None).unwrap();
        assert_eq!(
            (s.report.max_deviation_mm, s.report.rms_deviation_mm),
            (0.0, 0.0)
        );
    }
    // A groove straddling x = 0 is milled like the same groove in the middle, shifted.
    let g = |x: usize| if (x + 64 - 30) % 64 < 6 { -3.0 } else { 0.0 };
    let a = profile_x(64, 16, g);
    let b = profile_x(64, 16, |x| g((x + 32) % 64));
    let (sa, sb) = (
        millability::mill(&a, 8.0, &ball(0.6), None).unwrap(),
        millability::mill(&b, 8.0, &ball(0.6), None).unwrap(),
    );
    assert!(sa.report.max_deviation_mm > 0.01);
    assert!((sa.report.max_deviation_mm - sb.report.max_deviation_mm).abs() < 1e-12);
    for y in 0..16i64 {
        for x in 0..64i64 {
            assert!((sa.made.at(x, y) - sb.made.at(x - 32, y)).abs() < 1e-12);
        }
    }
}

#[test]
fn flat_end_fills_grooves_narrower_than_it() {
    // 4-sample groove, 0.1 mm samples: 0.3 mm floor, 0.5 mm at the top; depth 0.3 mm.
    let hf = profile_x(64, 8, |x| if (20..24).contains(&x) { -3.0 } else { 0.0 });
    let flat = |d: f64| Tool {
        kind: ToolKind::Flat,
        ..ball(d)
    };
    let wide = millability::mill(&hf, 6.4, &flat(1.0), None).unwrap();
    assert!(
        (wide.report.max_deviation_mm - 0.3).abs() < 1e-9,
        "{}",
        wide.report.max_deviation_mm
    );
    let thin = millability::mill(&hf, 6.4, &flat(0.1), None).unwrap();
    assert!(thin.report.max_deviation_mm < 0.3);
}

// ---------------------------------------------------------------- features

#[test]
fn feature_widths_of_known_grooves() {
    // flat-floored grooves of `n` low samples (walls one sample wide), depth 8, tolerance 10 %:
    // measured across 0.8 above the floor: (n − 1) + 2 · 0.1 samples wide. Resolution 1/4 sample
    // (widths up to 7 samples) or 1/2 sample (up to 17).
    for n in [3usize, 6, 11] {
        let hf = profile_x(
            128,
            16,
            |x| if (40..40 + n).contains(&x) { -8.0 } else { 0.0 },
        );
        let f = biscale::fab::features::measure(&hf, 0.1);
        let want = (n - 1) as f64 + 0.2;
        let v = f.valley_cells.unwrap();
        assert!(f.valley_resolution_cells <= 0.5);
        assert!(
            (v - want).abs() <= f.valley_resolution_cells,
            "n = {n}: {v} vs {want}"
        );
        // the land between grooves is a ridge 128 − n samples wide: wider than half the period
        assert!(
            f.ridge_cells.is_none_or(|r| r > 40.0),
            "{:?}",
            f.ridge_cells
        );
        let mm = f.at_patch(128, 12.8);
        assert!((mm.valley_mm.unwrap() - v * 0.1).abs() < 1e-12);
    }
    // a ridge of 5 samples on a flat floor: measured 0.8 below its crest.
    let hf = profile_x(128, 16, |x| if (60..65).contains(&x) { 8.0 } else { 0.0 });
    let f = biscale::fab::features::measure(&hf, 0.1);
    assert!(
        (f.ridge_cells.unwrap() - 4.2).abs() <= f.ridge_resolution_cells,
        "{:?}",
        f
    );
    // a flat patch has no features.
    let f = biscale::fab::features::measure(&Heightfield::flat(32, 32), 0.1);
    assert_eq!((f.valley_cells, f.ridge_cells), (None, None));
}

// ---------------------------------------------------------------- scale window, check, cost

#[test]
fn scale_window_and_check() {
    let p = load_profile("cnc-ball1-aluminium", &paths()).unwrap();
    let hf = gen("vgroove");
    let far = CheckOptions {
        tile_mm: (50.0, 50.0),
        patch_mm: None,
        viewing_distance_mm: Some(500_000.0),
    };
    let r = check_detail(&hf, &p, &far).unwrap();
    assert!(r.feasible, "{:?}", r.rejections);
    assert!(r.patch_mm >= r.window.lo_mm && r.patch_mm <= r.window.hi_mm);
    assert!((r.patch_mm - (r.window.lo_mm * r.window.hi_mm).sqrt()).abs() < 1e-9);
    // The process bound of a V groove (period 16, depth 4 samples: half-angle a = atan 2) is in
    // closed form: r (1/sin a − 1) <= 0.1 · relief = 0.1 · 4 · patch / 128.
    let a = 2.0f64.atan();
    let want = 0.5 * (1.0 / a.sin() - 1.0) * 128.0 / (0.1 * 4.0);
    let lo = r
        .window
        .lower
        .iter()
        .find(|b| b.name == "process")
        .unwrap()
        .patch_mm;
    assert!(lo >= want * 0.99 && lo <= want * 1.03, "{lo} vs {want}");
    let at_lo = millability::simulate(&hf, lo, &p).unwrap().report;
    assert!(at_lo.max_deviation_mm <= p.max_deviation_frac * at_lo.relief_mm + 1e-12);
    let below = millability::simulate(&hf, lo / 1.05, &p).unwrap().report;
    assert!(below.max_deviation_mm > p.max_deviation_frac * below.relief_mm);
    // The feature bound: valleys measured 0.4 samples above the V bottom are 2 · 0.4 · tan a wide.
    let f = r
        .window
        .lower
        .iter()
        .find(|b| b.name == "features")
        .unwrap()
        .patch_mm;
    let fw = 0.3 * 128.0 / (2.0 * 0.4 * a.tan());
    assert!((f - fw).abs() <= fw * 0.25 / 1.6, "{f} vs {fw}");
    // at 2 m viewing distance, one arc minute is 0.58 mm: rejected with both bounds named.
    let near = CheckOptions {
        viewing_distance_mm: Some(2000.0),
        ..far
    };
    let r = check_detail(&hf, &p, &near).unwrap();
    assert!(!r.feasible);
    // The scale window's rejection message.
    let window_rejection = |r: &biscale::fab::FabReport| -> String {
        r.rejections
            .iter()
            .find(|x| x.code == "scale_window")
            .unwrap()
            .message
            .clone()
    };
    let msg = window_rejection(&r);
    assert!(
        msg.contains("arc minute") && msg.contains("at least 21.9") && msg.contains("at most 0.58"),
        "{msg}"
    );
    // A tile must hold one whole period: the V groove needs at least 21.9 mm, a 10 mm tile
    // cannot show it.
    let small = CheckOptions {
        tile_mm: (10.0, 30.0),
        ..far
    };
    let r = check_detail(&hf, &p, &small).unwrap();
    let tile = r.window.upper.iter().find(|b| b.name == "tile").unwrap();
    assert_eq!(tile.patch_mm, 10.0);
    let msg = window_rejection(&r);
    assert!(msg.contains("at least one period"), "{msg}");
    // A flat detail has no period to see: its patch is the mesh bound's, the smallest at which
    // the 50 mm tile's mesh keeps within its samples (it used to get the viewing bound's 0.58
    // mm, and a tile of 11,000² samples that the export refused after the whole search).
    let flat = Heightfield::flat(128, 128);
    let r = check_detail(&flat, &p, &near).unwrap();
    assert!(r.feasible, "{:?}", r.rejections);
    assert!(r
        .window
        .upper
        .iter()
        .all(|b| b.name != "viewing" && b.name != "tile"));
    let mesh = r.window.lower.iter().find(|b| b.name == "mesh").unwrap();
    assert_eq!(r.patch_mm, mesh.patch_mm);
    let side = (50.0 * 128.0 / r.patch_mm).ceil();
    assert!(
        (side + 1.0) * (side + 1.0) <= biscale::fab::mesh::MAX_MESH_SAMPLES,
        "{side}"
    );
    // cost terms
    let c = check_detail(
        &hf,
        &p,
        &CheckOptions {
            patch_mm: Some(20.0),
            ..far
        },
    )
    .unwrap()
    .cost;
    assert!(c.material_cost > 0.0 && c.time_h > 0.0 && c.stock_cm3 > 0.0);
    assert!(
        (c.total - (p.weight_material * c.material_cost + p.weight_time_per_h * c.time_h)).abs()
            < 1e-9
    );
    assert!((c.area_cm2 - 25.0).abs() < 1e-12);
    // The cost is of the tile made: whole samples, rounded down (21 mm over 128 samples: 304
    // samples of 0.1640625 mm in 50 mm, 49.875 mm), as the export makes it.
    assert_eq!(hf.width(), 128);
    let c = check_detail(
        &hf,
        &p,
        &CheckOptions {
            patch_mm: Some(21.0),
            ..far
        },
    )
    .unwrap()
    .cost;
    let made = 304.0 * 21.0 / 128.0;
    assert!((c.tile_x_mm - made).abs() < 1e-12 && (c.tile_y_mm - made).abs() < 1e-12);
    assert!(
        (c.area_cm2 - made * made / 100.0).abs() < 1e-12,
        "{}",
        c.area_cm2
    );
    // printers have a model too
    let sla = load_profile("sla-50um", &paths()).unwrap();
    let r = check_detail(
        &hf,
        &sla,
        &CheckOptions {
            patch_mm: Some(10.0),
            ..far
        },
    )
    .unwrap();
    assert!(
        r.millability.max_deviation_mm <= 0.05 / 2.0 + 0.05,
        "{:?}",
        r.millability
    );
    assert!(r.cost.time_h > 0.0);
}

// ---------------------------------------------------------------- export

fn read_back(path: &Path) -> stl_io::IndexedMesh {
    let mut f = std::fs::File::open(path).unwrap();
    stl_io::read_stl(&mut f).unwrap()
}

#[test]
fn exported_tiles_are_closed_positive_and_deterministic() {
    let p = load_profile("cnc-ball1-wax", &paths()).unwrap();
    let d = TestDir::new("fab-export");
    for spec in ["bumps:n=64", "vgroove:n=64", "bricks:n=64", "fbm:n=64"] {
        let hf = gen(spec);
        for dec in [
            None,
            Some(Decimation::MaxErrorMm(0.02)),
            Some(Decimation::TriangleBudget(4000)),
            // Both: the bound's mesh fits the budget; then a bound no budget-sized mesh meets.
            Some(Decimation::Both {
                max_error_mm: 0.02,
                budget: 1_000_000,
            }),
            Some(Decimation::Both {
                max_error_mm: 1e-9,
                budget: 4000,
            }),
        ] {
            let r = export_detail(&hf, &p, 8.0, (20.0, 15.0), &d, "t", dec).unwrap();
            assert_eq!(r.check.genus, 0);
            assert!(r.check.signed_volume_mm3 > 0.0);
            assert!(
                (r.check.signed_volume_mm3 - r.check.manifold_volume_mm3).abs()
                    < 1e-6 * r.check.manifold_volume_mm3
            );
            assert!(
                (r.tile_x_mm - 20.0).abs() <= r.sample_mm
                    && (r.tile_y_mm - 15.0).abs() <= r.sample_mm
            );
            let m = read_back(&r.stl);
            m.validate()
                .unwrap_or_else(|e| panic!("{spec} {dec:?}: {e}"));
            assert_eq!(m.faces.len(), r.triangles);
            match dec {
                None => assert_eq!(
                    (r.triangles, r.max_height_error_mm),
                    (r.triangles_full, 0.0)
                ),
                Some(Decimation::MaxErrorMm(e)) => {
                    assert!(r.max_height_error_mm <= e && r.triangles < r.triangles_full)
                }
                Some(Decimation::TriangleBudget(n)) => {
                    assert!(r.budget_met && r.triangles <= n, "{spec}: {}", r.triangles)
                }
                // Both limits met, or (the bound's mesh over the budget) the budget kept at a
                // larger error, and said so.
                Some(Decimation::Both {
                    max_error_mm: e,
                    budget: n,
                }) => {
                    assert!(r.triangles <= n, "{spec}: {r:?}");
                    assert_eq!(r.budget_met, r.max_height_error_mm <= e, "{spec}: {r:?}");
                    if n == 4000 && spec != "vgroove:n=64" {
                        // (planar grooves meet any bound within 4000 triangles)
                        assert!(!r.budget_met, "{spec}: {r:?}");
                    }
                }
            }
            // the solid's volume is the base slab plus the relief under the triangulated top.
            let g = TileGrid::new(&hf, 8.0, 20.0, 15.0, p.base_thickness_mm).unwrap();
            let full = solid(&g, &biscale::fab::decimate::full_leaves(&g));
            if dec.is_none() {
                assert!(
                    (full.signed_volume() - r.check.signed_volume_mm3).abs()
                        < 1e-9 * full.signed_volume()
                );
            }
        }
    }
    // same input, same bytes
    let hf = gen("bumps:n=64");
    let a = export_detail(
        &hf,
        &p,
        8.0,
        (20.0, 20.0),
        &d,
        "a",
        Some(Decimation::MaxErrorMm(0.01)),
    )
    .unwrap();
    let b = export_detail(
        &hf,
        &p,
        8.0,
        (20.0, 20.0),
        &d,
        "b",
        Some(Decimation::MaxErrorMm(0.01)),
    )
    .unwrap();
    for (x, y) in [(&a.stl, &b.stl), (&a.png, &b.png)] {
        assert_eq!(std::fs::read(x).unwrap(), std::fs::read(y).unwrap());
    }
    let ja = std::fs::read_to_string(&a.png_scale).unwrap();
    assert_eq!(
        ja.replace("a.png", "b.png"),
        std::fs::read_to_string(&b.png_scale).unwrap()
    );
}

#[test]
fn png_sidecar_gives_heights_in_mm() {
    let p = load_profile("cnc-ball1-wax", &paths()).unwrap();
    let d = TestDir::new("fab-png");
    let hf = gen("sine:n=32");
    let r = export_detail(&hf, &p, 4.0, (6.0, 5.0), &d, "s", None).unwrap();
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&r.png_scale).unwrap()).unwrap();
    let (zmin, zmax, mmpp) = (
        j["z_min_mm"].as_f64().unwrap(),
        j["z_max_mm"].as_f64().unwrap(),
        j["mm_per_pixel"].as_f64().unwrap(),
    );
    assert!((mmpp - 0.125).abs() < 1e-12 && (zmin - p.base_thickness_mm).abs() < 1e-12);
    let img = image::open(&r.png).unwrap().into_luma16();
    let g = TileGrid::new(&hf, 4.0, 6.0, 5.0, p.base_thickness_mm).unwrap();
    assert_eq!(
        (img.width() as usize, img.height() as usize),
        (g.nx + 1, g.ny + 1)
    );
    for (x, y, v) in img.enumerate_pixels() {
        let z = zmin + v.0[0] as f64 / 65535.0 * (zmax - zmin);
        assert!((z - g.z_at(x as usize, y as usize)).abs() <= (zmax - zmin) / 65535.0);
    }
}

#[test]
fn no_partial_file_when_the_directory_cannot_be_made() {
    let p = load_profile("cnc-ball1-wax", &paths()).unwrap();
    let d = TestDir::new("fab-nowrite");
    let blocker = d.join("file");
    std::fs::write(&blocker, b"x").unwrap();
    let e = export_detail(
        &gen("bumps:n=32"),
        &p,
        4.0,
        (8.0, 8.0),
        &blocker.join("out"),
        "t",
        None,
    )
    .unwrap_err();
    assert!(e.to_string().contains("out"), "{e}");
    assert_eq!(std::fs::read_dir(&d).unwrap().count(), 1);
    assert!(export_detail(&gen("bumps:n=32"), &p, 4.0, (8.0, 8.0), &d, "../x", None).is_err());
}

#[test]
fn inside_out_mesh_is_caught() {
    let g = TileGrid::new(&gen("bumps:n=16"), 4.0, 4.0, 4.0, 1.0).unwrap();
    let mut m = solid(&g, &biscale::fab::decimate::full_leaves(&g));
    assert!(verify(&m, "ok").is_ok());
    for t in &mut m.tris {
        t.swap(1, 2);
    }
    let e = verify(&m, "flipped").unwrap_err().to_string();
    assert!(e.contains("signed volume"), "{e}");
    assert!(!stl_bytes(&m).unwrap().is_empty());
}

// ---------------------------------------------------------------- OBJ import

fn write_obj(path: &Path, hf: &Heightfield, extra: &str) {
    let (w, h) = (hf.width(), hf.height());
    let mut s = String::new();
    for y in 0..=h {
        for x in 0..=w {
            s.push_str(&format!(
                "v {} {} {}\n",
                x as f64 * hf.cell_mm,
                y as f64 * hf.cell_mm,
                hf.at(x as i64, y as i64) * hf.cell_mm
            ));
        }
    }
    let id = |x: usize, y: usize| y * (w + 1) + x + 1;
    for y in 0..h {
        for x in 0..w {
            s.push_str(&format!(
                "f {} {} {}\nf {} {} {}\n",
                id(x, y),
                id(x + 1, y),
                id(x + 1, y + 1),
                id(x, y),
                id(x + 1, y + 1),
                id(x, y + 1)
            ));
        }
    }
    s.push_str(extra);
    std::fs::write(path, s).unwrap();
}

#[test]
fn obj_heightfields_import_and_overhangs_are_rejected() {
    let d = TestDir::new("fab-obj");
    let mut hf = gen("bumps:n=16");
    hf.cell_mm = 0.25;
    let f = d.join("ok.obj");
    write_obj(&f, &hf, "");
    let back = import_obj(&f, 16).unwrap();
    let (lo, _) = hf.min_max();
    for y in 0..16 {
        for x in 0..16 {
            assert!((back.at(x, y) - (hf.at(x, y) - lo)).abs() < 1e-9);
        }
    }
    // As a `--geometry` / `fixed_geometry` file: resampled to 128 samples along x, the period
    // (4 mm) from the file, heights times the height scale.
    let g = biscale::heightmap_io::resolve_geometry(f.to_str().unwrap(), 10.0, 2.0).unwrap();
    assert_eq!((g.width(), g.height()), (128, 128));
    assert!((g.cell_mm * 128.0 - 4.0).abs() < 1e-12, "{}", g.cell_mm);
    let (glo, ghi) = g.min_max();
    let (a, b) = back.min_max();
    assert!(((ghi - glo) * g.cell_mm - 2.0 * (b - a) * back.cell_mm).abs() < 1e-9);
    // a downward face (a slab under the surface) and a second sheet above it
    let n = 17 * 17;
    let f = d.join("down.obj");
    write_obj(
        &f,
        &hf,
        &format!(
            "v 1 1 -5\nv 1 2 -5\nv 2 1 -5\nf {} {} {}\n",
            n + 1,
            n + 2,
            n + 3
        ),
    );
    let e = import_obj(&f, 16).unwrap_err().to_string();
    assert!(
        e.contains("down.obj") && e.contains("downward") && e.contains("overhang"),
        "{e}"
    );
    let f = d.join("sheet.obj");
    write_obj(
        &f,
        &hf,
        &format!(
            "v 1 1 50\nv 2 1 50\nv 1 2 50\nf {} {} {}\n",
            n + 1,
            n + 2,
            n + 3
        ),
    );
    let e = import_obj(&f, 16).unwrap_err().to_string();
    assert!(
        e.contains("sheet.obj") && e.contains("not a heightfield"),
        "{e}"
    );
}

/// The timing table of `biscale bench fab` (about 30 s: it exports 5 mm tiles of 3.3 million
/// triangles, so it is not part of the default test run). It asserts its rows, nothing about
/// time: `cargo test --release --test fabrication bench -- --ignored --nocapture`.
#[test]
#[ignore]
fn bench_table_prints_every_row() {
    let p = load_profile("cnc-ball1-aluminium", &paths()).unwrap();
    let t = biscale::fab::bench::bench_fab(&p, 1).unwrap();
    println!("{t}");
    for row in ["| bumps | 10 mm |", "| fbm | 40 mm |", "≤ 30000 triangles"] {
        assert!(t.contains(row), "missing {row:?} in\n{t}");
    }
}

#[test]
fn the_tile_made_is_never_larger_than_asked_and_one_sample_at_least() {
    // sine:n=32 at a 4 mm patch: samples of 0.125 mm.
    let hf = gen("sine:n=32");
    let g = TileGrid::new(&hf, 4.0, 6.0, 5.0, 1.0).unwrap();
    assert_eq!((g.nx, g.ny), (48, 40), "exact multiples are kept");
    // 37.3 mm is 298.4 samples: 298 of them (37.25 mm), not 298.5 rounded up.
    let g = TileGrid::new(&hf, 4.0, 37.3, 12.1, 1.0).unwrap();
    assert!(g.nx as f64 * g.cell_mm <= 37.3 && g.ny as f64 * g.cell_mm <= 12.1);
    assert_eq!((g.nx, g.ny), (298, 96));
    let e = TileGrid::new(&hf, 4.0, 0.01, 5.0, 1.0)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("tile x") && e.contains("less than one sample"),
        "{e}"
    );
}

#[test]
fn a_mill_cuts_in_whole_steps_of_its_resolution() {
    let hf = gen("bumps:n=64");
    let exact = millability::mill(&hf, 8.0, &ball(1.0), None).unwrap();
    let fine = millability::mill_in_steps(&hf, 8.0, &ball(1.0), None, Some(1e-9)).unwrap();
    assert!((fine.report.max_deviation_mm - exact.report.max_deviation_mm).abs() < 1e-6);
    // A step coarser than part of the relief: the tool stops at whole steps above the design,
    // so the made surface stays above it (no gouge) and departs further from it.
    let step = 0.25 * exact.report.relief_mm;
    let coarse = millability::mill_in_steps(&hf, 8.0, &ball(1.0), None, Some(step)).unwrap();
    for (m, e) in coarse.made_fine.z.iter().zip(&exact.made_fine.z) {
        assert!(*m >= *e - 1e-9, "made {m} below the exact cut {e}");
    }
    assert!(coarse.report.max_deviation_mm > exact.report.max_deviation_mm + 0.1 * step);
}
