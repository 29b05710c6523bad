//! End-to-end checks of the geometry inputs: every procedural generator resolves through
//! `resolve_geometry`, exports to `.npy` and 16-bit PNG, and loads back with the same samples.

mod common;

use biscale::generators::{list, parse_generator};
use biscale::heightmap_io::{load_heightmap, resolve_geometry, write_png16};
use biscale::npy::write_npy_f64;
use common::TestDir;

#[test]
fn every_generator_exports_and_reloads() {
    let dir = TestDir::new("geometry-rt");
    let patch_mm = 6.4;
    for (name, _) in list() {
        let spec = format!("{name}:n=32");
        let hf = resolve_geometry(&spec, patch_mm, 1.0).unwrap();
        assert_eq!((hf.width(), hf.height()), (32, 32), "{spec}");
        assert!((hf.cell_mm - patch_mm / 32.0).abs() < 1e-15);
        assert_eq!(hf.name, parse_generator(&spec).unwrap().name());

        // .npy of heights in mm, reloaded with height_scale 1: identical grid heights.
        let mm: Vec<f64> = hf.samples().iter().map(|z| z * hf.cell_mm).collect();
        let p = dir.join(format!("{name}.npy"));
        write_npy_f64(&p, 32, 32, &mm).unwrap();
        let back = load_heightmap(&p, patch_mm, 1.0).unwrap();
        for (a, b) in hf.samples().iter().zip(back.samples()) {
            assert!((a - b).abs() < 1e-12, "{spec}: {a} vs {b}");
        }

        // 16-bit PNG normalised to [min, max] mm: reload scaled by the span, offset by min.
        let q = dir.join(format!("{name}.png"));
        let (lo, hi) = write_png16(&q, &hf).unwrap();
        let back = resolve_geometry(q.to_str().unwrap(), patch_mm, hi - lo).unwrap();
        let tol = (hi - lo) / hf.cell_mm / 65535.0;
        for (a, b) in hf.samples().iter().zip(back.samples()) {
            let want = a - lo / hf.cell_mm;
            assert!((want - b).abs() <= tol + 1e-12, "{spec}: {want} vs {b}");
        }
    }
}

#[test]
fn height_scale_multiplies_procedural_heights() {
    let a = resolve_geometry("pyramids:n=16,period=8,height=2", 1.0, 1.0).unwrap();
    let b = resolve_geometry("pyramids:n=16,period=8,height=2", 1.0, 2.5).unwrap();
    for (x, y) in a.samples().iter().zip(b.samples()) {
        assert_eq!(x * 2.5, *y);
    }
}
