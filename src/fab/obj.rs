//! Importing OBJ microgeometry (read with `tobj`) as a periodic heightfield.
//!
//! The OBJ holds one period of the surface, in millimetres, with +z up: its bounding rectangle in
//! x and y is the period. It is resampled on a grid of `samples_x` samples along x (spacing
//! `cell = period_x / samples_x`) and `round(period_y / cell)` along y, at `x = x_min + i · cell`
//! (the far edge `x_max` is the next period's first sample). Each sample takes the height of the
//! upward-facing triangle above it.
//!
//! It must be a heightfield: a triangle facing downward, or two upward triangles at different
//! heights above one sample, is an overhang (an undercut for a 3-axis mill) and is rejected with
//! the face and position; vertical faces (zero area seen from above) are ignored; a sample no
//! triangle covers is a hole and is rejected too.

use crate::error::{Error, Result};
use crate::heightfield::Heightfield;
use std::path::Path;

/// Load `path` and resample it to a heightfield `samples_x` samples wide.
pub fn import_obj(path: &Path, samples_x: usize) -> Result<Heightfield> {
    let ctx = path.display().to_string();
    if !(2..=8192).contains(&samples_x) {
        return Err(Error::new(
            &ctx,
            format!("samples along x must be in 2..=8192, got {samples_x}"),
        ));
    }
    let opts = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        ignore_points: true,
        ignore_lines: true,
    };
    // tobj's error for a file it cannot open drops the system's reason; opening it here keeps
    // it ("No such file or directory", "Permission denied", "Is a directory").
    std::fs::File::open(path)
        .and_then(|f| {
            if f.metadata()?.is_dir() {
                Err(std::io::Error::other("it is a directory"))
            } else {
                Ok(())
            }
        })
        .map_err(|e| Error::io(path, "read the OBJ", e))?;
    let (models, _materials) = tobj::load_obj(path, &opts).map_err(|e| {
        Error::new(
            &ctx,
            format!("cannot read the OBJ: {e} (expected a Wavefront OBJ with faces)"),
        )
    })?;
    let mut tris: Vec<[[f64; 3]; 3]> = Vec::new();
    let mut face_of: Vec<(String, usize)> = Vec::new();
    for m in &models {
        let p = &m.mesh.positions;
        for (f, t) in m.mesh.indices.chunks_exact(3).enumerate() {
            let v = |i: u32| -> Result<[f64; 3]> {
                let i = i as usize * 3;
                if i + 2 >= p.len() {
                    return Err(Error::new(
                        &ctx,
                        format!("model '{}' face {f}: vertex index out of range", m.name),
                    ));
                }
                Ok([p[i], p[i + 1], p[i + 2]])
            };
            tris.push([v(t[0])?, v(t[1])?, v(t[2])?]);
            face_of.push((m.name.clone(), f));
        }
    }
    if tris.is_empty() {
        return Err(Error::new(
            &ctx,
            "has no faces (expected a triangulated surface)",
        ));
    }
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for t in &tris {
        for v in t {
            for k in 0..3 {
                if !v[k].is_finite() {
                    return Err(Error::new(&ctx, "has a vertex that is not a finite number"));
                }
                lo[k] = lo[k].min(v[k]);
                hi[k] = hi[k].max(v[k]);
            }
        }
    }
    let (lx, ly) = (hi[0] - lo[0], hi[1] - lo[1]);
    let cell = lx / samples_x as f64;
    if cell.is_nan() || cell <= 0.0 || ly.is_nan() || ly <= 0.0 {
        return Err(Error::new(
            &ctx,
            "is flat in x or y (expected a surface patch spanning an x-y rectangle)",
        ));
    }
    let ny = (ly / cell).round() as usize;
    if !(2..=8192).contains(&ny) {
        return Err(Error::new(
            &ctx,
            format!("its y extent gives {ny} samples (expected 2..=8192); change the sample count"),
        ));
    }
    let nx = samples_x;
    let mut z = vec![f64::NAN; nx * ny];
    let eps_h = 1e-6 * (hi[2] - lo[2]).abs().max(lx).max(ly);
    for (ti, t) in tris.iter().enumerate() {
        let (a, b, c) = (t[0], t[1], t[2]);
        let nz = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
        let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let e2 = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let n = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            nz,
        ];
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        if len == 0.0 || nz.abs() <= 1e-9 * len {
            continue; // degenerate or vertical: no area seen from above
        }
        if nz < 0.0 {
            let (name, f) = &face_of[ti];
            return Err(Error::new(
                &ctx,
                format!(
                    "model '{name}' face {f} faces downward (normal z = {:.3}): an overhang or undercut that a 3-axis tool \
                     cannot cut; the microgeometry must be a heightfield (export only its top surface, +z up)",
                    nz / len
                ),
            ));
        }
        let to_i = |v: f64, o: f64| (v - o) / cell;
        let (xs, ys) = (
            [to_i(a[0], lo[0]), to_i(b[0], lo[0]), to_i(c[0], lo[0])],
            [to_i(a[1], lo[1]), to_i(b[1], lo[1]), to_i(c[1], lo[1])],
        );
        let x0 = xs
            .iter()
            .cloned()
            .fold(f64::INFINITY, f64::min)
            .ceil()
            .max(0.0) as usize;
        let x1 = (xs
            .iter()
            .cloned()
            .fold(f64::NEG_INFINITY, f64::max)
            .floor()
            .max(0.0) as usize)
            .min(nx - 1);
        let y0 = ys
            .iter()
            .cloned()
            .fold(f64::INFINITY, f64::min)
            .ceil()
            .max(0.0) as usize;
        let y1 = (ys
            .iter()
            .cloned()
            .fold(f64::NEG_INFINITY, f64::max)
            .floor()
            .max(0.0) as usize)
            .min(ny - 1);
        let area = (xs[1] - xs[0]) * (ys[2] - ys[0]) - (ys[1] - ys[0]) * (xs[2] - xs[0]);
        let tol = 1e-9 * area.abs().max(1.0);
        for y in y0..=y1 {
            for x in x0..=x1 {
                let (px, py) = (x as f64, y as f64);
                let w0 = (xs[1] - px) * (ys[2] - py) - (ys[1] - py) * (xs[2] - px);
                let w1 = (xs[2] - px) * (ys[0] - py) - (ys[2] - py) * (xs[0] - px);
                let w2 = (xs[0] - px) * (ys[1] - py) - (ys[0] - py) * (xs[1] - px);
                if w0 < -tol || w1 < -tol || w2 < -tol {
                    continue;
                }
                let h = (w0 * a[2] + w1 * b[2] + w2 * c[2]) / area;
                let slot = &mut z[y * nx + x];
                if slot.is_nan() {
                    *slot = h;
                } else if (*slot - h).abs() > eps_h {
                    let (name, f) = &face_of[ti];
                    return Err(Error::new(
                        &ctx,
                        format!(
                            "is not a heightfield at x = {:.4}, y = {:.4} mm: model '{name}' face {f} lies over another \
                             surface ({:.4} vs {:.4} mm), an overhang a 3-axis tool cannot cut",
                            lo[0] + px * cell,
                            lo[1] + py * cell,
                            h,
                            *slot
                        ),
                    ));
                }
            }
        }
    }
    if let Some(i) = z.iter().position(|v| v.is_nan()) {
        return Err(Error::new(
            &ctx,
            format!(
                "has a hole: no face covers x = {:.4}, y = {:.4} mm (expected a surface covering its whole x-y rectangle)",
                lo[0] + (i % nx) as f64 * cell,
                lo[1] + (i / nx) as f64 * cell
            ),
        ));
    }
    let zg = z.iter().map(|v| (v - lo[2]) / cell).collect();
    Heightfield::new(nx, ny, zg, cell, ctx)
}
