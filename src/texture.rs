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
use crate::generators::{fbm_field, PeriodicNoise};
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
    if w == 0 || h == 0 {
        return Err(Error::new(
            path.display().to_string(),
            "the image is empty (expected at least 1×1 pixels)",
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
    let wx = weights(side, size);
    // Horizontal pass: side rows × size columns.
    let mut tmp = vec![0.0; side * size];
    for y in 0..side {
        let row = &img.data[(y0 + y) * img.w + x0..(y0 + y) * img.w + x0 + side];
        for (x, ws) in wx.iter().enumerate() {
            tmp[y * size + x] = ws.iter().map(|&(i, w)| w * row[i]).sum();
        }
    }
    let mut data = vec![0.0; size * size];
    for (y, ws) in wx.iter().enumerate() {
        for &(i, w) in ws {
            let src = &tmp[i * size..(i + 1) * size];
            for (d, s) in data[y * size..(y + 1) * size].iter_mut().zip(src) {
                *d += w * s;
            }
        }
    }
    GreyImage {
        w: size,
        h: size,
        data,
    }
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
pub fn patch_heights_sized(
    img: &GreyImage,
    patch: usize,
    amplitude: f64,
    cutoff_cycles: f64,
    m: usize,
) -> Result<Vec<f64>> {
    let ctx = "texture patch";
    if img.w == 0 || img.h == 0 || img.data.len() != img.w * img.h {
        return Err(Error::new(
            ctx,
            format!(
                "image of {}×{} with {} samples (expected a non-empty image)",
                img.w,
                img.h,
                img.data.len()
            ),
        ));
    }
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
    let big = resample_square(img, 4 * m);
    let (py, px) = (patch / 4, patch % 4);
    let mut cut = Vec::with_capacity(m * m);
    for y in 0..m {
        let start = (py * m + y) * big.w + px * m;
        cut.extend_from_slice(&big.data[start..start + m]);
    }
    let hp = highpass(&cut, m, cutoff_cycles);
    Ok(equalise(&hp).into_iter().map(|v| v * amplitude).collect())
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

/// Periodic Voronoi on a `g × g` jittered grid over the unit square: per sample (F1, F2, cell id),
/// distances in cell units.
fn voronoi(
    n: usize,
    g: usize,
    rng: &mut Rng,
    warp: Option<(&[f64], &[f64], f64)>,
) -> Vec<(f64, f64, usize)> {
    let pts: Vec<(f64, f64)> = (0..g * g).map(|_| (rng.uniform(), rng.uniform())).collect();
    let gi = g as i64;
    let mut out = Vec::with_capacity(n * n);
    for y in 0..n {
        for x in 0..n {
            let (mut u, mut v) = (
                (x as f64 + 0.5) / n as f64 * g as f64,
                (y as f64 + 0.5) / n as f64 * g as f64,
            );
            if let Some((wx, wy, s)) = warp {
                u += s * wx[y * n + x];
                v += s * wy[y * n + x];
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
    }
    out
}

/// A built-in synthetic `512 × 512` grey texture in `[0, 1]`, deterministic for `(name, seed)`.
pub fn builtin_image(name: &str, seed: u64) -> Result<GreyImage> {
    let n = IMAGE;
    let mut rng = Rng::stream(seed, 0x7E47);
    let sub = |k: u64| seed.wrapping_mul(31).wrapping_add(k);
    let coord = |i: usize| (i as f64 + 0.5) / n as f64;
    let data = match name {
        "cells" => {
            let vor = voronoi(n, 16, &mut rng, None);
            vor.iter().map(|&(f1, _, _)| f1).collect()
        }
        "cracks" => {
            let wx = fbm_field(n, 4, 4, 0.5, 2.0, sub(1));
            let wy = fbm_field(n, 4, 4, 0.5, 2.0, sub(2));
            let vor = voronoi(n, 10, &mut rng, Some((&wx, &wy, 0.6)));
            vor.iter()
                .map(|&(f1, f2, _)| ((f2 - f1) * 5.0).min(1.0))
                .collect()
        }
        "cobbles" => {
            let vor = voronoi(n, 8, &mut rng, None);
            let tone: Vec<f64> = (0..64).map(|_| rng.range(0.6, 1.0)).collect();
            vor.iter()
                .map(|&(f1, f2, id)| tone[id] * (1.0 - f1 / f2).max(0.0).sqrt())
                .collect()
        }
        "stripes" => {
            let t = fbm_field(n, 4, 4, 0.5, 2.0, sub(3));
            (0..n * n)
                .map(|i| 0.5 + 0.5 * (TAU * (12.0 * coord(i % n) + 0.4 * t[i])).sin())
                .collect()
        }
        "marble" => {
            let t = fbm_field(n, 4, 6, 0.55, 2.0, sub(4));
            let turb: Vec<f64> = t.iter().map(|v| v.abs()).collect();
            (0..n * n)
                .map(|i| {
                    0.5 + 0.5
                        * (TAU * (3.0 * coord(i % n) + 2.0 * coord(i / n) + 2.5 * turb[i])).sin()
                })
                .collect()
        }
        "wood" => {
            let t = fbm_field(n, 4, 4, 0.5, 2.0, sub(5));
            let (cx, cy) = (rng.uniform(), rng.uniform());
            (0..n * n)
                .map(|i| {
                    // periodic distance to the ring centre
                    let dx = (coord(i % n) - cx + 0.5).rem_euclid(1.0) - 0.5;
                    let dy = (coord(i / n) - cy + 0.5).rem_euclid(1.0) - 0.5;
                    let r = (dx * dx + 4.0 * dy * dy).sqrt() * 14.0 + 0.8 * t[i];
                    r - r.floor()
                })
                .collect()
        }
        "clouds" => fbm_field(n, 4, 7, 0.55, 2.0, sub(6)),
        "ridged" => {
            let mut z = vec![0.0; n * n];
            let mut amp = 1.0;
            for o in 0..6u32 {
                let per = 4usize << o;
                let mut r = Rng::stream(sub(7), o as u64);
                let noise = PeriodicNoise::new(per, &mut r);
                for (i, zi) in z.iter_mut().enumerate() {
                    *zi += amp * (1.0 - noise.eval(coord(i % n), coord(i / n)).abs() * 2.0).powi(2);
                }
                amp *= 0.5;
            }
            z
        }
        "speckle" => {
            let mut z: Vec<f64> = fbm_field(n, 8, 3, 0.5, 2.0, sub(8))
                .iter()
                .map(|v| 0.2 * v)
                .collect();
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
                            let k = (y.rem_euclid(n as i64) as usize) * n
                                + x.rem_euclid(n as i64) as usize;
                            z[k] += a * (1.0 - d2);
                        }
                    }
                }
            }
            z
        }
        "granite" => {
            let white: Vec<f64> = (0..n * n).map(|_| rng.uniform()).collect();
            let base = fbm_field(n, 6, 4, 0.5, 2.0, sub(9));
            (0..n * n)
                .map(|i| {
                    let (x, y) = (i % n, i / n);
                    let mut s = 0.0;
                    for dy in [n - 1, 0, 1] {
                        for dx in [n - 1, 0, 1] {
                            s += white[((y + dy) % n) * n + (x + dx) % n];
                        }
                    }
                    s / 9.0 + 0.5 * base[i]
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
    Ok(GreyImage {
        w: n,
        h: n,
        data: normalise(data),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let dir = std::env::temp_dir().join(format!("biscale_tex_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
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
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
