//! A minimal PNG scatter plot (error against run time) for `biscale validate --plot`: axes with
//! ten ticks each (x from 0 to 1.1 × the largest x, y likewise), points joined in order. The
//! image carries no text; [`scatter_png`] returns the caption to print beside it.

use crate::error::{Error, Result};
use image::{Rgb, RgbImage};
use std::path::Path;

/// Plot `(x, y)` points (both axes linear from 0 to the maximum, padded 10 %).
pub fn scatter_png(
    path: &Path,
    pts: &[(f64, f64)],
    x_label: &str,
    y_label: &str,
) -> Result<String> {
    let (w, h, m) = (640u32, 480u32, 50u32);
    let mut img = RgbImage::from_pixel(w, h, Rgb([255, 255, 255]));
    let finite: Vec<(f64, f64)> = pts
        .iter()
        .copied()
        .filter(|p| p.0.is_finite() && p.1.is_finite())
        .collect();
    let xmax = finite.iter().map(|p| p.0).fold(0.0, f64::max).max(1e-9) * 1.1;
    let ymax = finite.iter().map(|p| p.1).fold(0.0, f64::max).max(1e-9) * 1.1;
    let to_px = |x: f64, y: f64| -> (i64, i64) {
        let px = m as f64 + x / xmax * (w - 2 * m) as f64;
        let py = (h - m) as f64 - y / ymax * (h - 2 * m) as f64;
        (px.round() as i64, py.round() as i64)
    };
    let put = |img: &mut RgbImage, x: i64, y: i64, c: Rgb<u8>| {
        if x >= 0 && y >= 0 && (x as u32) < w && (y as u32) < h {
            img.put_pixel(x as u32, y as u32, c);
        }
    };
    let black = Rgb([0, 0, 0]);
    for x in m..w - m {
        put(&mut img, x as i64, (h - m) as i64, black);
    }
    for y in m..h - m {
        put(&mut img, m as i64, y as i64, black);
    }
    for k in 0..=10 {
        let (tx, _) = to_px(xmax / 1.1 * k as f64 / 10.0, 0.0);
        let (_, ty) = to_px(0.0, ymax / 1.1 * k as f64 / 10.0);
        for d in 0..6 {
            put(&mut img, tx, (h - m) as i64 + d, black);
            put(&mut img, m as i64 - d, ty, black);
        }
    }
    let red = Rgb([200, 30, 30]);
    let mut prev: Option<(i64, i64)> = None;
    for &(x, y) in &finite {
        let (px, py) = to_px(x, y);
        for dx in -3..=3 {
            for dy in -3..=3 {
                put(&mut img, px + dx, py + dy, red);
            }
        }
        if let Some((qx, qy)) = prev {
            let n = ((px - qx).abs().max((py - qy).abs())).max(1);
            for s in 0..=n {
                put(
                    &mut img,
                    qx + (px - qx) * s / n,
                    qy + (py - qy) * s / n,
                    Rgb([120, 120, 120]),
                );
            }
        }
        prev = Some((px, py));
    }
    let mut bytes = Vec::new();
    image::DynamicImage::ImageRgb8(img)
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .map_err(|e| {
            Error::new(
                path.display().to_string(),
                format!("cannot encode the plot: {e}"),
            )
        })?;
    crate::atomic_write::write_bytes(path, &bytes)?;
    Ok(format!(
        "{}: x = {x_label} from 0 to {:.3} (ticks every {:.3}), y = {y_label} from 0 to {:.4} (ticks every {:.4})",
        path.display(),
        xmax,
        xmax / 11.0,
        ymax,
        ymax / 11.0
    ))
}
