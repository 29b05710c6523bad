//! Pictures for the design report: spheres shaded with a large-scale BRDF (target and
//! approximation side by side), a shaded relief of one heightfield period, and in-plane BRDF
//! slices. Images are linear RGB `[f32; 3]` until [`write_png_rgb`] tone maps them; no image
//! carries text, the slice plot returns a caption instead. Nothing here lets NaN reach a PNG.

use crate::error::{Error, Result};
use crate::frame::{dir_from_deg, Vec3};
use crate::heightfield::Heightfield;
use rayon::prelude::*;
use std::path::Path;

/// Constant ambient radiance (times the colour) added to every sphere pixel.
pub const AMBIENT: f64 = 0.02;
/// Linear value of the background around the sphere (dark grey).
pub const BACKGROUND: f32 = 0.01;

/// A BRDF given as `fbar(wi, wo)` in a local frame (normal +z), cos(theta_i) included.
pub type Fbar<'a> = &'a (dyn Fn(Vec3, Vec3) -> f64 + Sync);

/// Render a unit sphere, `size × size` pixels, row 0 at the top. Orthographic camera on +z looking
/// down −z, so the view direction is `wo = +z` in world space; image right = world +x, image up =
/// world +y. One directional light towards `light` (world, normalised here) of unit irradiance.
/// At each point the shading frame is `t = normalize(Y × N)` (fallback `X × N` at N = ±Y),
/// `b = N × t`, `n = N`; at the centre it coincides with the world frame. Radiance =
/// `exposure · (max(fbar(wi_local, wo_local), 0) + AMBIENT) · colour`; a non-finite `fbar` counts
/// as 0, pixels off the sphere get [`BACKGROUND`]. Returns linear RGB.
pub fn sphere(
    fbar: Fbar,
    size: usize,
    light: Vec3,
    colour: [f64; 3],
    exposure: f64,
) -> Vec<[f32; 3]> {
    let l = light.normalized();
    let l_ok = l.x.is_finite() && l.y.is_finite() && l.z.is_finite() && l.norm() > 0.5;
    let mut img = vec![[BACKGROUND; 3]; size * size];
    img.par_chunks_mut(size.max(1))
        .enumerate()
        .for_each(|(row, line)| {
            let y = 1.0 - 2.0 * (row as f64 + 0.5) / size as f64;
            for (col, px) in line.iter_mut().enumerate() {
                let x = 2.0 * (col as f64 + 0.5) / size as f64 - 1.0;
                let r2 = x * x + y * y;
                if r2 >= 1.0 {
                    continue;
                }
                let n = Vec3::new(x, y, (1.0 - r2).sqrt());
                let mut t = Vec3::new(0.0, 1.0, 0.0).cross(n);
                if t.norm() < 1e-9 {
                    t = Vec3::new(1.0, 0.0, 0.0).cross(n);
                }
                let t = t.normalized();
                let b = n.cross(t);
                let local = |w: Vec3| Vec3::new(w.dot(t), w.dot(b), w.dot(n));
                let wo = local(Vec3::Z);
                let wi = local(l);
                let lit = l_ok && wo.z > 1e-9 && wi.z > 0.0;
                let f = if lit { fin(fbar(wi, wo)).max(0.0) } else { 0.0 };
                for c in 0..3 {
                    px[c] = fin(exposure * (f + AMBIENT) * colour[c]) as f32;
                }
            }
        });
    img
}

/// Place square images `(pixels, side)` in a row, left to right, `gap` black pixels apart and
/// centred vertically; the rest is black. Returns `(pixels, width, height)`. A short pixel slice
/// reads as black where it ends.
pub fn side_by_side(images: &[(&[[f32; 3]], usize)], gap: usize) -> (Vec<[f32; 3]>, usize, usize) {
    let h = images.iter().map(|&(_, s)| s).max().unwrap_or(0);
    let w = images.iter().map(|&(_, s)| s).sum::<usize>() + gap * images.len().saturating_sub(1);
    let mut out = vec![[0.0f32; 3]; w * h];
    let mut x0 = 0;
    for &(px, s) in images {
        let y0 = (h - s) / 2;
        for y in 0..s {
            for x in 0..s {
                out[(y0 + y) * w + x0 + x] = px.get(y * s + x).copied().unwrap_or([0.0; 3]);
            }
        }
        x0 += s + gap;
    }
    (out, w, h)
}

/// `v`, or 0 when it is not finite.
fn fin(v: f64) -> f64 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

/// Luminance of linear RGB (Rec. 709 weights).
fn luminance(p: [f32; 3]) -> f64 {
    0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64
}

/// The exposure that maps the 99th percentile of the positive finite luminances to 0.9; 1 when
/// there is none.
pub fn auto_exposure(pixels: &[[f32; 3]]) -> f64 {
    let mut l: Vec<f64> = pixels
        .iter()
        .map(|&p| luminance(p))
        .filter(|v| v.is_finite() && *v > 0.0)
        .collect();
    if l.is_empty() {
        return 1.0;
    }
    l.sort_by(f64::total_cmp);
    let p99 = l[((l.len() - 1) as f64 * 0.99).round() as usize];
    Some(0.9 / p99).filter(|e| e.is_finite()).unwrap_or(1.0)
}

/// The sRGB transfer function of a linear value in `[0, 1]`.
fn srgb(v: f64) -> f64 {
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// Encode 8-bit RGB rows as PNG and write it atomically.
fn encode_png(path: &Path, w: usize, h: usize, rgb: Vec<u8>) -> Result<()> {
    let err = |m: String| Error::new(path.display().to_string(), m);
    let (w32, h32) = (u32::try_from(w), u32::try_from(h));
    let img = match (w32, h32) {
        (Ok(a), Ok(b)) if a > 0 && b > 0 => image::RgbImage::from_raw(a, b, rgb),
        _ => None,
    }
    .ok_or_else(|| {
        err(format!(
            "cannot make a {w}×{h} image (need a positive size)"
        ))
    })?;
    let mut bytes = Vec::new();
    image::DynamicImage::ImageRgb8(img)
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .map_err(|e| err(format!("cannot encode the PNG: {e}")))?;
    crate::atomic_write::write_bytes(path, &bytes)
}

/// Tone map linear RGB (multiply by `exposure`, clamp to `[0, 1]`, sRGB gamma; non-finite → 0)
/// and write an 8-bit PNG atomically. `pixels` must hold `w × h` values, row 0 at the top.
pub fn write_png_rgb(
    path: &Path,
    pixels: &[[f32; 3]],
    w: usize,
    h: usize,
    exposure: f64,
) -> Result<()> {
    let err = |m: String| Error::new(path.display().to_string(), m);
    if pixels.len() != w * h {
        return Err(err(format!("{} pixels for a {w}×{h} image", pixels.len())));
    }
    if !(exposure.is_finite() && exposure >= 0.0) {
        return Err(err(format!(
            "exposure must be a finite number ≥ 0, got {exposure}"
        )));
    }
    let rgb = pixels
        .iter()
        .flat_map(|p| p.iter())
        .map(|&v| (srgb(fin(v as f64 * exposure).clamp(0.0, 1.0)) * 255.0).round() as u8)
        .collect();
    encode_png(path, w, h, rgb)
}

/// A shaded relief of one period of `hf`: the longer side is `size_px` pixels (aspect kept), image
/// up = +y. Grey = 0.65 · hillshade + 0.35 · normalised height, where the hillshade is `N·L` of the
/// triangulated surface (slope by central differences over one pixel, at least ¼ cell) for a light
/// from the upper left at 45° elevation. Grey values are written as display values (no gamma).
pub fn heightfield_png(path: &Path, hf: &Heightfield, size_px: usize) -> Result<()> {
    if size_px == 0 {
        return Err(Error::new(
            path.display().to_string(),
            "image size must be > 0",
        ));
    }
    let (gw, gh) = (hf.width() as f64, hf.height() as f64);
    let scale = size_px as f64 / gw.max(gh);
    let (w, h) = (
        ((gw * scale).round() as usize).max(1),
        ((gh * scale).round() as usize).max(1),
    );
    let (lo, hi) = hf.min_max();
    let step = (1.0 / scale).max(0.25) * 0.5;
    let l = Vec3::new(-0.5, 0.5, std::f64::consts::FRAC_1_SQRT_2);
    let mut rgb = vec![0u8; w * h * 3];
    rgb.par_chunks_mut(w * 3)
        .enumerate()
        .for_each(|(row, line)| {
            let y = gh - (row as f64 + 0.5) / h as f64 * gh;
            for col in 0..w {
                let x = (col as f64 + 0.5) / w as f64 * gw;
                let gx = (hf.surface_height(x + step, y) - hf.surface_height(x - step, y))
                    / (2.0 * step);
                let gy = (hf.surface_height(x, y + step) - hf.surface_height(x, y - step))
                    / (2.0 * step);
                let shade = Vec3::new(-gx, -gy, 1.0).normalized().dot(l).max(0.0);
                let hn = if hi > lo {
                    (hf.surface_height(x, y) - lo) / (hi - lo)
                } else {
                    0.5
                };
                let g = fin(0.65 * shade + 0.35 * hn).clamp(0.0, 1.0);
                line[col * 3..col * 3 + 3].fill((g * 255.0).round() as u8);
            }
        });
    encode_png(path, w, h, rgb)
}

/// Curve colours in order, with the names the caption uses.
const PALETTE: [([u8; 3], &str); 6] = [
    ([210, 40, 40], "red"),
    ([40, 80, 210], "blue"),
    ([30, 150, 60], "green"),
    ([230, 140, 20], "orange"),
    ([140, 50, 170], "purple"),
    ([20, 160, 170], "teal"),
];

/// In-plane BRDF slices. One panel per `theta_i_deg` (phi_i = 0), left to right, each
/// `size = (width, height)` pixels, 10 white pixels apart. In a panel x is theta_o from −89° to
/// +89°: negative theta_o means phi_o = 0 (the light's side, back-scattering), positive means
/// phi_o = 180° (the mirror side; the specular direction is theta_o = +theta_i). y is
/// log10(brdf), brdf = fbar / cos(theta_i), clamped to `[1e-3 · max, max]` with `max` the largest
/// finite value over all curves and panels (same scale everywhere). Axes and ticks are black (x
/// every 30°, y every power of ten); light grey vertical lines mark theta_o = 0 and theta_o =
/// theta_i. Curve k is drawn in colour k of red, blue, green, orange, purple, teal (cycling);
/// non-finite values break the line. Returns the caption for the report.
pub fn brdf_slices_png(
    path: &Path,
    curves: &[(&str, Fbar)],
    theta_i_deg: &[f64],
    size: (usize, usize),
) -> Result<String> {
    let err = |m: String| Error::new(path.display().to_string(), m);
    if curves.is_empty() || theta_i_deg.is_empty() {
        return Err(err("need at least one curve and one incident angle".into()));
    }
    if let Some(t) = theta_i_deg.iter().find(|t| !(**t >= 0.0 && **t < 90.0)) {
        return Err(err(format!("incident angle {t}° is outside [0°, 90°)")));
    }
    let ((pw, ph), m) = (size, 20usize);
    if pw < 2 * m + 10 || ph < 2 * m + 10 {
        return Err(err(format!("panel {pw}×{ph} is too small (need ≥ 50×50)")));
    }
    let n_s = pw - 2 * m;
    let theta_o = |s: usize| -89.0 + 178.0 * s as f64 / (n_s - 1) as f64;
    // values[panel][curve][sample] of brdf = fbar / cos(theta_i)
    let values: Vec<Vec<Vec<f64>>> = theta_i_deg
        .iter()
        .map(|&ti| {
            let (wi, ci) = (dir_from_deg(ti, 0.0), ti.to_radians().cos());
            let slice = |f: Fbar| -> Vec<f64> {
                let wo = |to: f64| dir_from_deg(to.abs(), if to < 0.0 { 0.0 } else { 180.0 });
                (0..n_s)
                    .into_par_iter()
                    .map(|s| f(wi, wo(theta_o(s))) / ci)
                    .collect()
            };
            curves.iter().map(|&(_, f)| slice(f)).collect()
        })
        .collect();
    let finite = values.iter().flatten().flatten().filter(|v| v.is_finite());
    let vmax = finite.fold(0.0f64, |a, &b| a.max(b));
    let all_zero = vmax <= 0.0 || !vmax.is_finite();
    let vmax = if all_zero { 1.0 } else { vmax };
    let (ylo, yhi) = ((vmax * 1e-3).log10(), vmax.log10());

    let (gap, n_p) = (10usize, theta_i_deg.len());
    let (w, h) = (n_p * pw + gap * (n_p - 1), ph);
    let mut rgb = vec![255u8; w * h * 3];
    // A straight segment from a to b (pixels), `thick` pixels tall.
    let mut seg = |a: (i64, i64), b: (i64, i64), c: [u8; 3], thick: i64| {
        let n = (b.0 - a.0).abs().max((b.1 - a.1).abs()).max(1);
        for i in 0..=n {
            let (x, y0) = (a.0 + (b.0 - a.0) * i / n, a.1 + (b.1 - a.1) * i / n);
            for y in y0..y0 + thick {
                if x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h {
                    let i = (y as usize * w + x as usize) * 3;
                    rgb[i..i + 3].copy_from_slice(&c);
                }
            }
        }
    };
    let (black, grey) = ([0u8; 3], [200u8; 3]);
    let (x_axis, y_top) = ((ph - m) as i64, m as i64);
    for (p, &ti) in theta_i_deg.iter().enumerate() {
        let x0 = (p * (pw + gap) + m) as i64;
        let px_of = |deg: f64| x0 + ((deg + 89.0) / 178.0 * (n_s - 1) as f64).round() as i64;
        let py_of = |v: f64| {
            let t = ((v.max(vmax * 1e-3).log10() - ylo) / (yhi - ylo)).clamp(0.0, 1.0);
            x_axis - (t * (x_axis - y_top) as f64).round() as i64
        };
        for deg in [0.0, ti] {
            seg((px_of(deg), y_top), (px_of(deg), x_axis), grey, 1);
        }
        seg((x0, x_axis), (x0 + n_s as i64, x_axis), black, 1);
        seg((x0, y_top), (x0, x_axis), black, 1);
        for deg in [-60.0, -30.0, 0.0, 30.0, 60.0] {
            seg((px_of(deg), x_axis), (px_of(deg), x_axis + 5), black, 1);
        }
        for dec in (ylo.ceil() as i64)..=((yhi + 1e-9).floor() as i64) {
            let ty = py_of(10f64.powi(dec as i32));
            seg((x0 - 5, ty), (x0, ty), black, 1);
        }
        for (k, v) in values[p].iter().enumerate() {
            let mut prev: Option<(i64, i64)> = None;
            for (s, &val) in v.iter().enumerate() {
                let q = (x0 + s as i64, py_of(val));
                if val.is_finite() {
                    seg(prev.unwrap_or(q), q, PALETTE[k % PALETTE.len()].0, 2);
                }
                prev = Some(q).filter(|_| val.is_finite());
            }
        }
    }
    encode_png(path, w, h, rgb)?;

    let angles: Vec<String> = theta_i_deg.iter().map(|t| format!("{t}°")).collect();
    let names: Vec<String> = (0..curves.len())
        .map(|k| {
            let bad = values
                .iter()
                .flat_map(|p| &p[k])
                .filter(|v| !v.is_finite())
                .count();
            let bad = if bad > 0 {
                format!(" ({bad} non-finite values left out)")
            } else {
                String::new()
            };
            format!("{} = {}{bad}", curves[k].0, PALETTE[k % PALETTE.len()].1)
        })
        .collect();
    Ok(format!(
        "In-plane BRDF slices, one panel per incident angle, left to right: theta_i = {} (phi_i = 0). \
         x: theta_o from -89° to +89° (negative: phi_o = 0, the light's side; positive: phi_o = 180°, \
         the mirror side), ticks every 30°, grey lines at theta_o = 0 and theta_o = theta_i. \
         y: log10 of brdf = fbar / cos(theta_i) from {:.3e} to {:.3e}{}, ticks at powers of ten, \
         same scale in every panel. Curves: {}.",
        angles.join(", "),
        vmax * 1e-3,
        vmax,
        if all_zero { " (no positive finite value)" } else { "" },
        names.join(", ")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testdir::TestDir;

    #[test]
    fn lambertian_sphere_has_cosine_falloff() {
        let albedo = 0.8;
        let lam = |wi: Vec3, _wo: Vec3| albedo / std::f64::consts::PI * wi.z.max(0.0);
        let colour = [1.0, 0.5, 0.25];
        let s = 65;
        let img = sphere(&lam, s, Vec3::Z, colour, 1.0);
        for (row, col) in [(32, 32), (32, 10), (5, 40), (50, 20)] {
            let (x, y) = (
                2.0 * (col as f64 + 0.5) / s as f64 - 1.0,
                1.0 - 2.0 * (row as f64 + 0.5) / s as f64,
            );
            let nz = (1.0 - x * x - y * y).sqrt();
            for c in 0..3 {
                let want = (albedo / std::f64::consts::PI * nz + AMBIENT) * colour[c];
                assert!((img[row * s + col][c] as f64 - want).abs() < 1e-6);
            }
        }
        // Light from +x: the left half (N·L < 0) gets only the ambient term.
        let img = sphere(&lam, s, Vec3::new(1.0, 0.0, 0.0), colour, 1.0);
        for c in 0..3 {
            assert!((img[32 * s + 10][c] as f64 - AMBIENT * colour[c]).abs() < 1e-7);
            assert!(img[32 * s + 54][c] as f64 > 2.0 * AMBIENT * colour[c]);
        }
        assert_eq!(img[0], [BACKGROUND; 3]);
    }

    #[test]
    fn pngs_are_written_with_their_dimensions() {
        let lam = |wi: Vec3, _wo: Vec3| wi.z / std::f64::consts::PI;
        let a = sphere(&lam, 40, Vec3::new(1.0, 1.0, 1.0), [1.0; 3], 1.0);
        let b = sphere(&lam, 30, Vec3::Z, [1.0, 0.8, 0.6], 1.0);
        let (img, w, h) = side_by_side(&[(&a, 40), (&b, 30)], 4);
        assert_eq!((w, h), (74, 40));
        let e = auto_exposure(&img);
        assert!(e.is_finite() && e > 0.0);
        let d = TestDir::new("render-dims");
        let p = d.join("spheres.png");
        write_png_rgb(&p, &img, w, h, e).unwrap();
        let r = image::open(&p).unwrap();
        assert_eq!((r.width(), r.height()), (74, 40));
        assert!(write_png_rgb(&p, &img, w + 1, h, e).is_err());

        let z: Vec<f64> = (0..16 * 8).map(|i| ((i % 16) as f64 * 0.7).sin()).collect();
        let hf = Heightfield::new(16, 8, z, 0.1, "test").unwrap();
        let p = d.join("relief.png");
        heightfield_png(&p, &hf, 64).unwrap();
        let r = image::open(&p).unwrap();
        assert_eq!((r.width(), r.height()), (64, 32));
    }

    #[test]
    fn non_finite_fbar_never_gives_nan() {
        let bad = |wi: Vec3, _wo: Vec3| if wi.x > 0.1 { f64::NAN } else { f64::INFINITY };
        let img = sphere(&bad, 33, Vec3::new(1.0, 0.0, 1.0), [1.0; 3], 1.0);
        assert!(img.iter().flatten().all(|v| v.is_finite()));
        let nan_img = vec![[f32::NAN, f32::INFINITY, -1.0]; 4];
        assert_eq!(auto_exposure(&nan_img), 1.0);
        let d = TestDir::new("render-nan");
        let p = d.join("nan.png");
        write_png_rgb(&p, &nan_img, 2, 2, 1.0).unwrap();
        let r = image::open(&p).unwrap().to_rgb8();
        assert!(r.pixels().all(|px| px.0 == [0, 0, 0]));
        let cap = brdf_slices_png(
            &d.join("s.png"),
            &[("broken", &bad)],
            &[0.0, 45.0],
            (120, 90),
        );
        assert!(cap.unwrap().contains("no positive finite value"));
    }

    #[test]
    fn slices_caption_names_every_curve() {
        let lam = |wi: Vec3, _wo: Vec3| 0.5 / std::f64::consts::PI * wi.z;
        let glossy = |wi: Vec3, wo: Vec3| {
            let h = (wi + wo).normalized();
            wi.z * (0.1 + 20.0 * h.z.powi(50))
        };
        let holes = |wi: Vec3, wo: Vec3| if wo.x > 0.5 { f64::NAN } else { lam(wi, wo) };
        let tmp = TestDir::new("render-slices");
        let p = tmp.join("slices.png");
        let curves: [(&str, Fbar); 3] = [("target", &glossy), ("approx", &lam), ("holes", &holes)];
        let cap = brdf_slices_png(&p, &curves, &[0.0, 30.0, 60.0], (200, 150)).unwrap();
        assert!(
            cap.contains("target = red") && cap.contains("approx = blue"),
            "{cap}"
        );
        assert!(cap.contains("holes = green (") && cap.contains("non-finite values left out"));
        let r = image::open(&p).unwrap();
        assert_eq!((r.width(), r.height()), (3 * 200 + 2 * 10, 150));
        assert!(brdf_slices_png(&p, &curves, &[90.0], (200, 150)).is_err());
    }
}
