//! Height patches from images: the paper's recipe (Sec. 5.2, Fig. 4), plus built-in textures.
//!
//! Recipe, for a patch side `m` (the paper's `m = 128`, [`PATCH`]):
//! 1. convert the image to grey (Rec. 709 luma, alpha ignored) with values in `[0, 1]`;
//! 2. crop the centred square (so the texture is not stretched) and resample it to `4m × 4m`
//!    (512 × 512 for `m = 128`), per axis: area average (box) when shrinking, bilinear when
//!    enlarging; deterministic;
//! 3. cut the `4 × 4` grid of non-overlapping `m × m` patches; patch index `p` in `0..16` is the
//!    patch at grid row `p / 4`, column `p % 4`, counted from the top-left (row = y, column = x);
//! 4. treat the patch as one period: remove the jump at its borders by the periodic-plus-smooth
//!    decomposition (Moisan 2011; the smooth part solves a Laplace equation driven by the border
//!    jumps), then FFT high-pass: every component whose radial frequency is below `cutoff_cycles`
//!    cycles per patch (and always the mean) is zeroed. The inverse FFT is periodic by
//!    construction, and because of step 4's first half it has no seam at the borders;
//! 5. histogram equalisation to `[0, 1]` (rank / (count − 1), ties share their mean rank);
//! 6. multiply by `amplitude` (grid units): heights lie in `[0, amplitude]`.
//!
//! The built-in textures ([`builtin_names`]) are synthetic `512 × 512` grey images made
//! deterministically from a seed with [`crate::rng::Rng`], so the recipe works with nothing
//! downloaded.

use crate::error::{Error, Result};
use crate::generators::{fbm_window, PeriodicNoise, Window};
use crate::rng::Rng;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;
use std::f64::consts::TAU;
use std::path::Path;

/// The paper's patch side.
pub const PATCH: usize = 128;
/// Side of the built-in images and of the resampled image for `PATCH` (the paper's 512).
pub const IMAGE: usize = 4 * PATCH;

/// A grey image, row-major `data[y * w + x]`, values nominally in `[0, 1]`.
#[derive(Debug, Clone, PartialEq)]
pub struct GreyImage {
    pub w: usize,
    pub h: usize,
    pub data: Vec<f64>,
}

impl GreyImage {
    pub fn at(&self, x: usize, y: usize) -> f64 {
        self.data[y * self.w + x]
    }
}

const BUILTINS: &[&str] = &[
    "cells", "cracks", "cobbles", "stripes", "marble", "wood", "clouds", "ridged", "speckle",
    "granite",
];

/// Names of the built-in synthetic textures.
pub fn builtin_names() -> &'static [&'static str] {
    BUILTINS
}

/// Load any PNG and convert it to grey in `[0, 1]` (Rec. 709 luma; alpha ignored).
pub fn load_grey(path: &Path) -> Result<GreyImage> {
    let reader = image::ImageReader::open(path)
        .map_err(|e| Error::io(path, "open the image", e))?
        .with_guessed_format()
        .map_err(|e| Error::io(path, "read the image", e))?;
    let img = reader.decode().map_err(|e| {
        Error::new(
            path.display().to_string(),
            format!("cannot decode the image (expected a PNG): {e}"),
        )
    })?;
    let g = img.to_luma32f();
    let (w, h) = (g.width() as usize, g.height() as usize);
    if w < 2 || h < 2 {
        // One row or column of pixels holds no texture in the other direction (a 1×1 image
        // used to give a flat surface without a word).
        return Err(Error::new(
            path.display().to_string(),
            format!("the image is {w}×{h} pixels; a texture needs at least 2×2"),
        ));
    }
    Ok(GreyImage {
        w,
        h,
        data: g
            .into_raw()
            .into_iter()
            .map(|v| (v as f64).clamp(0.0, 1.0))
            .collect(),
    })
}

/// Per destination index, the source indices and weights of a 1-D resampling.
fn weights(src: usize, dst: usize) -> Vec<Vec<(usize, f64)>> {
    let scale = src as f64 / dst as f64;
    (0..dst)
        .map(|d| {
            if dst <= src {
                // Box: the destination pixel covers [a, b) in source pixels.
                let (a, b) = (d as f64 * scale, (d + 1) as f64 * scale);
                let mut out = Vec::new();
                let mut i = a.floor() as usize;
                while (i as f64) < b && i < src {
                    let ov = (b.min(i as f64 + 1.0) - a.max(i as f64)).max(0.0);
                    if ov > 0.0 {
                        out.push((i, ov / (b - a)));
                    }
                    i += 1;
                }
                out
            } else {
                let pos = ((d as f64 + 0.5) * scale - 0.5).clamp(0.0, (src - 1) as f64);
                let i0 = pos.floor() as usize;
                let f = pos - i0 as f64;
                let i1 = (i0 + 1).min(src - 1);
                vec![(i0, 1.0 - f), (i1, f)]
            }
        })
        .collect()
}

/// Crop the centred square and resample it to `size × size`.
pub fn resample_square(img: &GreyImage, size: usize) -> GreyImage {
    let side = img.w.min(img.h);
    let (x0, y0) = ((img.w - side) / 2, (img.h - side) / 2);
    GreyImage {
        w: size,
        h: size,
        data: resample_block(side, size, (0, 0), size, |x, y| {
            img.data[(y0 + y) * img.w + x0 + x]
        }),
    }
}

/// Source indices (first, last) that the destination indices `weights[d0..d0 + m]` read.
fn source_span(weights: &[Vec<(usize, f64)>]) -> (usize, usize) {
    let mut idx = weights.iter().flatten().map(|&(i, _)| i);
    let first = idx.next().unwrap_or(0);
    idx.fold((first, first), |(lo, hi), i| (lo.min(i), hi.max(i)))
}

/// The `m × m` block at destination `(dx0, dy0)` of the `size × size` resampling of a square
/// source of side `side` whose pixel `(x, y)` is `src(x, y)`: only the source rows and columns
/// the block reads are read, and every destination value is computed as the whole resampling
/// computes it (a horizontal pass, then a vertical one).
fn resample_block(
    side: usize,
    size: usize,
    (dx0, dy0): (usize, usize),
    m: usize,
    src: impl Fn(usize, usize) -> f64,
) -> Vec<f64> {
    let wts = weights(side, size);
    let (cols, rows) = (&wts[dx0..dx0 + m], &wts[dy0..dy0 + m]);
    let (ylo, yhi) = source_span(rows);
    // Horizontal pass over the source rows the block reads: those rows × m columns.
    let mut tmp = vec![0.0; (yhi + 1 - ylo) * m];
    for (ys, row) in (ylo..=yhi).zip(tmp.chunks_mut(m)) {
        for (t, ws) in row.iter_mut().zip(cols) {
            *t = ws.iter().map(|&(i, w)| w * src(i, ys)).sum();
        }
    }
    let mut data = vec![0.0; m * m];
    for (y, ws) in rows.iter().enumerate() {
        for &(i, w) in ws {
            let s = &tmp[(i - ylo) * m..(i - ylo + 1) * m];
            for (d, s) in data[y * m..(y + 1) * m].iter_mut().zip(s) {
                *d += w * s;
            }
        }
    }
    data
}

/// In-place 2-D FFT of an `n × n` row-major array (rows, then columns via a transpose).
fn fft2(buf: &mut [Complex<f64>], n: usize, inverse: bool) {
    let mut planner = FftPlanner::<f64>::new();
    let fft = if inverse {
        planner.plan_fft_inverse(n)
    } else {
        planner.plan_fft_forward(n)
    };
    fft.process(buf);
    transpose(buf, n);
    fft.process(buf);
    transpose(buf, n);
}

fn transpose(buf: &mut [Complex<f64>], n: usize) {
    for y in 0..n {
        for x in y + 1..n {
            buf.swap(y * n + x, x * n + y);
        }
    }
}

/// Signed frequency of FFT index `k` of length `n`.
fn freq(k: usize, n: usize) -> f64 {
    if k <= n / 2 {
        k as f64
    } else {
        k as f64 - n as f64
    }
}

/// The periodic component of an `n × n` patch (border jumps removed) with every frequency below
/// `cutoff_cycles` cycles per patch, and the mean, removed. The result has zero mean.
pub fn highpass(patch: &[f64], n: usize, cutoff_cycles: f64) -> Vec<f64> {
    let mut u: Vec<Complex<f64>> = patch.iter().map(|&v| Complex::new(v, 0.0)).collect();
    // Border-jump image of the periodic-plus-smooth decomposition.
    let mut v = vec![Complex::new(0.0, 0.0); n * n];
    for j in 0..n {
        let d = patch[(n - 1) * n + j] - patch[j];
        v[j].re += d;
        v[(n - 1) * n + j].re -= d;
        let d = patch[j * n + n - 1] - patch[j * n];
        v[j * n].re += d;
        v[j * n + n - 1].re -= d;
    }
    fft2(&mut u, n, false);
    fft2(&mut v, n, false);
    for q in 0..n {
        for r in 0..n {
            let i = q * n + r;
            let (fq, fr) = (freq(q, n), freq(r, n));
            if (fq * fq + fr * fr).sqrt() < cutoff_cycles.max(0.5) {
                u[i] = Complex::new(0.0, 0.0);
                continue;
            }
            let den = 2.0 * (TAU * q as f64 / n as f64).cos()
                + 2.0 * (TAU * r as f64 / n as f64).cos()
                - 4.0;
            u[i] -= v[i] / den;
        }
    }
    fft2(&mut u, n, true);
    let s = 1.0 / (n * n) as f64;
    u.iter().map(|c| c.re * s).collect()
}

/// Histogram equalisation to `[0, 1]`: each sample becomes its rank / (count − 1), equal samples
/// sharing their mean rank. A single sample maps to 0.5.
pub fn equalise(v: &[f64]) -> Vec<f64> {
    let n = v.len();
    if n < 2 {
        return vec![0.5; n];
    }
    let mut idx: Vec<usize> = (0..n).collect();
    idx.sort_by(|&a, &b| v[a].total_cmp(&v[b]).then(a.cmp(&b)));
    let mut out = vec![0.0; n];
    let mut i = 0;
    while i < n {
        let mut j = i + 1;
        while j < n && v[idx[j]] == v[idx[i]] {
            j += 1;
        }
        let rank = (i + j - 1) as f64 / 2.0 / (n - 1) as f64;
        for &k in &idx[i..j] {
            out[k] = rank;
        }
        i = j;
    }
    out
}

/// The paper's recipe with `128 × 128` patches from a `512 × 512` resampling: heights (grid units,
/// row-major, `128 × 128`) in `[0, amplitude]`. See the module documentation for the steps.
pub fn patch_heights(
    img: &GreyImage,
    patch: usize,
    amplitude: f64,
    cutoff_cycles: f64,
) -> Result<Vec<f64>> {
    patch_heights_sized(img, patch, amplitude, cutoff_cycles, PATCH)
}

/// The recipe for an `m × m` patch cut from a `4m × 4m` resampling (`m = 128` is the paper's).
/// Only the part of the resampling the patch covers is computed.
pub fn patch_heights_sized(
    img: &GreyImage,
    patch: usize,
    amplitude: f64,
    cutoff_cycles: f64,
    m: usize,
) -> Result<Vec<f64>> {
    if img.w == 0 || img.h == 0 || img.data.len() != img.w * img.h {
        return Err(Error::new(
            "texture patch",
            format!(
                "image of {}×{} with {} samples (expected a non-empty image)",
                img.w,
                img.h,
                img.data.len()
            ),
        ));
    }
    check_patch(patch, amplitude, cutoff_cycles, m)?;
    let side = img.w.min(img.h);
    let (x0, y0) = ((img.w - side) / 2, (img.h - side) / 2);
    let cut = resample_block(side, 4 * m, patch_origin(patch, m), m, |x, y| {
        img.data[(y0 + y) * img.w + x0 + x]
    });
    Ok(recipe_tail(&cut, m, amplitude, cutoff_cycles))
}

/// The recipe on built-in texture `name` (seed `seed`): only the pixels of the `512 × 512`
/// image that the patch's resampling reads are made (about a sixteenth of them), and without
/// the image's normalisation to `[0, 1]` ([`builtin_image`]), which the result does not see:
/// the high-pass is linear and removes the mean, and the equalisation keeps only ranks. A
/// library of 40,000 texture patches made whole images for every one of them.
pub fn builtin_patch_heights(
    name: &str,
    seed: u64,
    patch: usize,
    amplitude: f64,
    cutoff_cycles: f64,
    m: usize,
) -> Result<Vec<f64>> {
    check_patch(patch, amplitude, cutoff_cycles, m)?;
    let size = 4 * m;
    let (dx0, dy0) = patch_origin(patch, m);
    let wts = weights(IMAGE, size);
    let (xlo, xhi) = source_span(&wts[dx0..dx0 + m]);
    let (ylo, yhi) = source_span(&wts[dy0..dy0 + m]);
    let win = Window {
        x0: xlo,
        y0: ylo,
        w: xhi + 1 - xlo,
        h: yhi + 1 - ylo,
    };
    let src = builtin_window(name, seed, win)?;
    let cut = resample_block(IMAGE, size, (dx0, dy0), m, |x, y| {
        src[(y - ylo) * win.w + (x - xlo)]
    });
    Ok(recipe_tail(&cut, m, amplitude, cutoff_cycles))
}

/// Top-left corner, in the `4m × 4m` resampling, of patch `patch` (row `patch / 4`, column
/// `patch % 4`).
fn patch_origin(patch: usize, m: usize) -> (usize, usize) {
    ((patch % 4) * m, (patch / 4) * m)
}

/// Steps 4–6 of the recipe on a cut `m × m` patch.
fn recipe_tail(cut: &[f64], m: usize, amplitude: f64, cutoff_cycles: f64) -> Vec<f64> {
    let hp = highpass(cut, m, cutoff_cycles);
    equalise(&hp).into_iter().map(|v| v * amplitude).collect()
}

fn check_patch(patch: usize, amplitude: f64, cutoff_cycles: f64, m: usize) -> Result<()> {
    let ctx = "texture patch";
    if patch >= 16 {
        return Err(Error::new(
            ctx,
            format!("patch index {patch} (expected 0..15: a 4×4 grid, row-major)"),
        ));
    }
    if !(amplitude.is_finite() && amplitude >= 0.0) {
        return Err(Error::new(
            ctx,
            format!("amplitude {amplitude} (expected a finite number >= 0)"),
        ));
    }
    if !(cutoff_cycles.is_finite() && cutoff_cycles >= 0.0) {
        return Err(Error::new(
            ctx,
            format!("cutoff {cutoff_cycles} (expected a finite number of cycles >= 0)"),
        ));
    }
    if !(2..=1024).contains(&m) {
        return Err(Error::new(
            ctx,
            format!("patch side {m} (expected 2 to 1024 samples)"),
        ));
    }
    Ok(())
}

fn normalise(mut v: Vec<f64>) -> Vec<f64> {
    let (lo, hi) = v
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
    let s = if hi > lo { 1.0 / (hi - lo) } else { 0.0 };
    v.iter_mut().for_each(|x| *x = (*x - lo) * s);
    v
}

/// Periodic Voronoi (Worley) distances of the `n × n` image's pixels in `win`: nearest and
/// second-nearest feature distance and the nearest feature's index, with one random feature per
/// cell of a `g × g` lattice (all drawn from `rng`, whatever the window), optionally warped by
/// `warp = (wx, wy, strength)` given over the window.
fn voronoi(
    n: usize,
    g: usize,
    rng: &mut Rng,
    warp: Option<(&[f64], &[f64], f64)>,
    win: Window,
) -> Vec<(f64, f64, usize)> {
    let pts: Vec<(f64, f64)> = (0..g * g).map(|_| (rng.uniform(), rng.uniform())).collect();
    let gi = g as i64;
    let mut out = Vec::with_capacity(win.w * win.h);
    for (k, (x, y)) in win.samples().enumerate() {
        let (mut u, mut v) = (
            (x as f64 + 0.5) / n as f64 * g as f64,
            (y as f64 + 0.5) / n as f64 * g as f64,
        );
        if let Some((wx, wy, s)) = warp {
            u += s * wx[k];
            v += s * wy[k];
        }
        let (cu, cv) = (u.floor() as i64, v.floor() as i64);
        let (mut f1, mut f2, mut id) = (f64::INFINITY, f64::INFINITY, 0);
        for dj in -1..=1 {
            for di in -1..=1 {
                let (ci, cj) = (cu + di, cv + dj);
                let k = (cj.rem_euclid(gi) * gi + ci.rem_euclid(gi)) as usize;
                let (px, py) = (ci as f64 + pts[k].0, cj as f64 + pts[k].1);
                let d = ((px - u).powi(2) + (py - v).powi(2)).sqrt();
                if d < f1 {
                    f2 = f1;
                    f1 = d;
                    id = k;
                } else if d < f2 {
                    f2 = d;
                }
            }
        }
        out.push((f1, f2, id));
    }
    out
}

/// A built-in synthetic `512 × 512` grey texture in `[0, 1]`, deterministic for `(name, seed)`.
pub fn builtin_image(name: &str, seed: u64) -> Result<GreyImage> {
    Ok(GreyImage {
        w: IMAGE,
        h: IMAGE,
        data: normalise(builtin_window(name, seed, Window::full(IMAGE))?),
    })
}

/// The pixels in `win` of built-in texture `name` before its normalisation to `[0, 1]`: each
/// computed as the whole image computes it (every random draw is made, whatever the window).
fn builtin_window(name: &str, seed: u64, win: Window) -> Result<Vec<f64>> {
    let n = IMAGE;
    let mut rng = Rng::stream(seed, 0x7E47);
    let sub = |k: u64| seed.wrapping_mul(31).wrapping_add(k);
    let coord = |i: usize| (i as f64 + 0.5) / n as f64;
    let fbm = |cells: usize, octaves: usize, persistence: f64, seed: u64| {
        fbm_window(n, cells, octaves, persistence, 2.0, seed, win)
    };
    let data = match name {
        "cells" => {
            let vor = voronoi(n, 16, &mut rng, None, win);
            vor.iter().map(|&(f1, _, _)| f1).collect()
        }
        "cracks" => {
            let wx = fbm(4, 4, 0.5, sub(1));
            let wy = fbm(4, 4, 0.5, sub(2));
            let vor = voronoi(n, 10, &mut rng, Some((&wx, &wy, 0.6)), win);
            vor.iter()
                .map(|&(f1, f2, _)| ((f2 - f1) * 5.0).min(1.0))
                .collect()
        }
        "cobbles" => {
            let vor = voronoi(n, 8, &mut rng, None, win);
            let tone: Vec<f64> = (0..64).map(|_| rng.range(0.6, 1.0)).collect();
            vor.iter()
                .map(|&(f1, f2, id)| tone[id] * (1.0 - f1 / f2).max(0.0).sqrt())
                .collect()
        }
        "stripes" => {
            let t = fbm(4, 4, 0.5, sub(3));
            win.samples()
                .zip(&t)
                .map(|((x, _), t)| 0.5 + 0.5 * (TAU * (12.0 * coord(x) + 0.4 * t)).sin())
                .collect()
        }
        "marble" => {
            let t = fbm(4, 6, 0.55, sub(4));
            win.samples()
                .zip(&t)
                .map(|((x, y), t)| {
                    0.5 + 0.5 * (TAU * (3.0 * coord(x) + 2.0 * coord(y) + 2.5 * t.abs())).sin()
                })
                .collect()
        }
        "wood" => {
            let t = fbm(4, 4, 0.5, sub(5));
            let (cx, cy) = (rng.uniform(), rng.uniform());
            win.samples()
                .zip(&t)
                .map(|((x, y), t)| {
                    // periodic distance to the ring centre
                    let dx = (coord(x) - cx + 0.5).rem_euclid(1.0) - 0.5;
                    let dy = (coord(y) - cy + 0.5).rem_euclid(1.0) - 0.5;
                    let r = (dx * dx + 4.0 * dy * dy).sqrt() * 14.0 + 0.8 * t;
                    r - r.floor()
                })
                .collect()
        }
        "clouds" => fbm(4, 7, 0.55, sub(6)),
        "ridged" => {
            let mut z = vec![0.0; win.w * win.h];
            let mut amp = 1.0;
            for o in 0..6u32 {
                let per = 4usize << o;
                let mut r = Rng::stream(sub(7), o as u64);
                let noise = PeriodicNoise::new(per, &mut r);
                for (zi, (x, y)) in z.iter_mut().zip(win.samples()) {
                    *zi += amp * (1.0 - noise.eval(coord(x), coord(y)).abs() * 2.0).powi(2);
                }
                amp *= 0.5;
            }
            z
        }
        "speckle" => {
            let mut z: Vec<f64> = fbm(8, 3, 0.5, sub(8)).iter().map(|v| 0.2 * v).collect();
            for _ in 0..4000 {
                let (cx, cy) = (rng.range(0.0, n as f64), rng.range(0.0, n as f64));
                let r = rng.range(1.0, 3.5);
                let a = rng.range(-1.0, 1.0);
                let ri = r.ceil() as i64;
                for dy in -ri..=ri {
                    for dx in -ri..=ri {
                        let (x, y) = (cx.floor() as i64 + dx, cy.floor() as i64 + dy);
                        let d2 = ((x as f64 + 0.5 - cx).powi(2) + (y as f64 + 0.5 - cy).powi(2))
                            / (r * r);
                        if d2 < 1.0 {
                            let (x, y) = (x.rem_euclid(n as i64), y.rem_euclid(n as i64));
                            if let Some(k) = win.index(x as usize, y as usize) {
                                z[k] += a * (1.0 - d2);
                            }
                        }
                    }
                }
            }
            z
        }
        "granite" => {
            let white: Vec<f64> = (0..n * n).map(|_| rng.uniform()).collect();
            let base = fbm(6, 4, 0.5, sub(9));
            win.samples()
                .zip(&base)
                .map(|((x, y), b)| {
                    let mut s = 0.0;
                    for dy in [n - 1, 0, 1] {
                        for dx in [n - 1, 0, 1] {
                            s += white[((y + dy) % n) * n + (x + dx) % n];
                        }
                    }
                    s / 9.0 + 0.5 * b
                })
                .collect()
        }
        _ => {
            return Err(Error::new(
                "texture",
                format!(
                    "unknown built-in texture '{name}' (expected one of: {})",
                    BUILTINS.join(", ")
                ),
            ))
        }
    };
    Ok(data)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testdir::TestDir;

    #[test]
    fn builtins_are_deterministic_distinct_and_in_range() {
        assert!(builtin_names().len() >= 8);
        let mut seen: Vec<Vec<f64>> = Vec::new();
        for name in builtin_names() {
            let a = builtin_image(name, 7).unwrap();
            assert_eq!(
                (a.w, a.h, a.data.len()),
                (IMAGE, IMAGE, IMAGE * IMAGE),
                "{name}"
            );
            assert!(a.data.iter().all(|v| (0.0..=1.0).contains(v)), "{name}");
            let b = builtin_image(name, 7).unwrap();
            assert!(
                a.data
                    .iter()
                    .zip(&b.data)
                    .all(|(x, y)| x.to_bits() == y.to_bits()),
                "{name} not deterministic"
            );
            assert!(!seen.contains(&a.data), "{name} equals another texture");
            seen.push(a.data);
        }
        assert_ne!(
            builtin_image("cells", 1).unwrap(),
            builtin_image("cells", 2).unwrap()
        );
        let e = builtin_image("bogus", 0).unwrap_err().to_string();
        assert!(e.contains("bogus") && e.contains("marble"), "{e}");
    }

    #[test]
    fn builtin_patches_make_only_their_window_and_equal_the_whole_image_recipe() {
        for name in builtin_names() {
            let raw = GreyImage {
                w: IMAGE,
                h: IMAGE,
                data: builtin_window(name, 5, Window::full(IMAGE)).unwrap(),
            };
            let img = builtin_image(name, 5).unwrap();
            // Box resampling by 2 (the libraries' 64), identity (the paper's 128), a box of
            // non-integer width and a bilinear enlargement.
            for (patch, m) in [(0, 64), (5, 64), (15, 128), (6, 37), (9, 200)] {
                let got = builtin_patch_heights(name, 5, patch, 3.0, 4.0, m).unwrap();
                let whole = patch_heights_sized(&raw, patch, 3.0, 4.0, m).unwrap();
                assert!(
                    got.iter()
                        .zip(&whole)
                        .all(|(a, b)| a.to_bits() == b.to_bits()),
                    "{name} patch {patch} m {m}"
                );
                // The image's normalisation to [0, 1], which the window leaves out, could move
                // heights only by rounding (the equalised ranks of near-ties); on these 50
                // patches it moves none.
                let norm = patch_heights_sized(&img, patch, 3.0, 4.0, m).unwrap();
                assert_eq!(got, norm, "{name} patch {patch} m {m}");
            }
        }
        assert!(builtin_patch_heights("bogus", 0, 0, 1.0, 4.0, 64)
            .unwrap_err()
            .to_string()
            .contains("bogus"));
        assert!(builtin_patch_heights("cells", 0, 16, 1.0, 4.0, 64).is_err());
    }

    #[test]
    fn patch_is_128_equalised_and_scaled() {
        let img = builtin_image("marble", 3).unwrap();
        let h = patch_heights(&img, 5, 4.0, 4.0).unwrap();
        assert_eq!(h.len(), PATCH * PATCH);
        let (lo, hi) = h
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                (a.min(x), b.max(x))
            });
        assert_eq!((lo, hi), (0.0, 4.0));
        // Equalised: the mean of a uniform histogram is amplitude / 2.
        let mean = h.iter().sum::<f64>() / h.len() as f64;
        assert!((mean - 2.0).abs() < 1e-6, "{mean}");
        assert_ne!(h, patch_heights(&img, 6, 4.0, 4.0).unwrap());
        assert!(patch_heights(&img, 16, 4.0, 4.0).is_err());
        assert!(patch_heights(&img, 0, f64::NAN, 4.0).is_err());
    }

    #[test]
    fn highpass_is_zero_mean_removes_low_frequencies_and_the_seam() {
        let n = 64;
        // A ramp (seam jump), a low-frequency wave and a high-frequency wave.
        let mut p = vec![0.0; n * n];
        for y in 0..n {
            for x in 0..n {
                let (u, v) = (x as f64 / n as f64, y as f64 / n as f64);
                p[y * n + x] = u + (TAU * 2.0 * v).sin() + 0.1 * (TAU * 16.0 * u).cos();
            }
        }
        let hp = highpass(&p, n, 4.0);
        let mean = hp.iter().sum::<f64>() / hp.len() as f64;
        assert!(mean.abs() < 1e-12, "{mean}");
        // Away from the borders what is left is the high-frequency wave. The border-jump correction
        // of the periodic-plus-smooth decomposition also treats the last-to-first step of the
        // sampled sine as a jump, which leaves an error of about 0.02 a few samples in.
        let mut max_err: f64 = 0.0;
        for y in 8..n - 8 {
            for x in 8..n - 8 {
                let want = 0.1 * (TAU * 16.0 * x as f64 / n as f64).cos();
                max_err = max_err.max((hp[y * n + x] - want).abs());
            }
        }
        assert!(max_err < 0.04, "{max_err}");
        // The input jumps by 1 at the x seam; the output has no step larger than its inner steps.
        let (mut inner, mut seam) = (0.0f64, 0.0f64);
        for y in 0..n {
            for x in 0..n {
                let d = (hp[y * n + (x + 1) % n] - hp[y * n + x]).abs();
                if x + 1 < n {
                    inner = inner.max(d);
                } else {
                    seam = seam.max(d);
                }
            }
        }
        assert!(seam <= inner, "seam {seam} inner {inner}");
    }

    #[test]
    fn resampling_and_equalisation() {
        let img = GreyImage {
            w: 6,
            h: 4,
            data: (0..24).map(|i| (i % 6) as f64 / 5.0).collect(),
        };
        let r = resample_square(&img, 2);
        // centred 4×4 square: columns 1..5, values 0.2..0.8; box average of 2 columns.
        assert!((r.at(0, 0) - 0.3).abs() < 1e-12 && (r.at(1, 1) - 0.7).abs() < 1e-12);
        let up = resample_square(
            &GreyImage {
                w: 2,
                h: 2,
                data: vec![0.0, 1.0, 0.0, 1.0],
            },
            8,
        );
        assert!(up.at(0, 0) == 0.0 && up.at(7, 0) == 1.0 && up.at(3, 0) > 0.0 && up.at(3, 0) < 0.5);
        assert_eq!(
            equalise(&[3.0, 1.0, 2.0, 2.0, 5.0]),
            vec![0.75, 0.0, 0.375, 0.375, 1.0]
        );
    }

    #[test]
    fn load_grey_errors_name_the_file() {
        let e = load_grey(Path::new("/nonexistent/x/tex.png"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("tex.png"), "{e}");
        let dir = TestDir::new("tex");
        let p = dir.join("junk.png");
        std::fs::write(&p, b"not a png at all").unwrap();
        let e = load_grey(&p).unwrap_err().to_string();
        assert!(e.contains("junk.png"), "{e}");
        // An RGB image is converted to grey.
        let rgb = image::RgbImage::from_fn(4, 3, |x, _| {
            image::Rgb([(x * 60) as u8, (x * 60) as u8, (x * 60) as u8])
        });
        let q = dir.join("rgb.png");
        rgb.save(&q).unwrap();
        let g = load_grey(&q).unwrap();
        assert_eq!((g.w, g.h), (4, 3));
        assert!((g.at(3, 2) - 180.0 / 255.0).abs() < 1e-3);
        // A single pixel (or a single row) is no texture: refused, naming the file.
        let one = dir.join("one.png");
        image::GrayImage::from_pixel(1, 1, image::Luma([90]))
            .save(&one)
            .unwrap();
        let e = load_grey(&one).unwrap_err().to_string();
        assert!(e.contains("one.png") && e.contains("at least 2×2"), "{e}");
    }
}
