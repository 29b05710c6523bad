//! Heightmap files in and out, and the resolution of a `--geometry` argument (a file or a
//! procedural spec) into a [`Heightfield`].
//!
//! Input: a 2-D `.npy` (float32/float64, or the integer types [`crate::npy`] accepts) of shape
//! `H × W`, or an 8- or 16-bit greyscale PNG (8-bit values / 255, 16-bit / 65535, so stored values
//! are in `[0, 1]`; a grey+alpha PNG has its alpha ignored). RGB/RGBA PNGs are rejected: a colour
//! image is not a heightmap, and turning it into one is the texture recipe's job
//! (`texture:file=...`). The format is recognised from the file's first bytes. Row index = y,
//! column index = x.
//!
//! Physical meaning: stored value × `height_scale` is the height in millimetres, and
//! `patch_size_mm` is the physical side of the period along x. So `cell_mm = patch_size_mm / W` and
//! the height in grid units is `stored × height_scale / cell_mm`.
//!
//! Output: [`write_png16`] writes a 16-bit grey PNG normalised to the height range, through a
//! temporary file in the same directory and a rename.

use crate::error::{Error, Result};
use crate::generators::parse_generator;
use crate::heightfield::Heightfield;
use crate::npy::read_npy_2d;
use image::{DynamicImage, ImageBuffer, ImageFormat, Luma};
use std::io::Read;
use std::path::Path;

fn check_scales(ctx: &str, patch_size_mm: f64, height_scale: f64) -> Result<()> {
    if !(patch_size_mm.is_finite() && patch_size_mm > 0.0) {
        return Err(Error::new(
            ctx,
            format!("patch size must be a positive number of mm, got {patch_size_mm}"),
        ));
    }
    if !height_scale.is_finite() {
        return Err(Error::new(
            ctx,
            format!(
                "height scale must be a finite number (mm per stored unit), got {height_scale}"
            ),
        ));
    }
    Ok(())
}

/// Read the stored samples of a PNG: `(rows, cols, values in [0, 1])`.
fn read_png_grey(path: &Path) -> Result<(usize, usize, Vec<f64>)> {
    let ctx = path.display().to_string();
    let reader = image::ImageReader::open(path)
        .map_err(|e| Error::io(path, "open the PNG", e))?
        .with_guessed_format()
        .map_err(|e| Error::io(path, "read the PNG", e))?;
    let img = reader.decode().map_err(|e| {
        Error::new(
            &ctx,
            format!("cannot decode the PNG (expected an 8- or 16-bit grey PNG): {e}"),
        )
    })?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let data: Vec<f64> = match img {
        DynamicImage::ImageLuma8(b) => b.into_raw().into_iter().map(|v| v as f64 / 255.0).collect(),
        DynamicImage::ImageLuma16(b) => b.into_raw().into_iter().map(|v| v as f64 / 65535.0).collect(),
        DynamicImage::ImageLumaA8(b) => b.into_raw().chunks_exact(2).map(|c| c[0] as f64 / 255.0).collect(),
        DynamicImage::ImageLumaA16(b) => b.into_raw().chunks_exact(2).map(|c| c[0] as f64 / 65535.0).collect(),
        other => {
            return Err(Error::new(
                &ctx,
                format!(
                    "is a colour image ({:?} once decoded; a palette PNG decodes to colour); a heightmap \
                     must be an 8- or 16-bit greyscale PNG (convert it to grey, \
                     or use the texture recipe: --geometry texture:file=...)",
                    other.color()
                ),
            ))
        }
    };
    Ok((h, w, data))
}

/// Load a heightmap file (`.npy` or grey PNG) as a [`Heightfield`] in grid units; see the module
/// documentation for the physical meaning of `patch_size_mm` and `height_scale`.
pub fn load_heightmap(path: &Path, patch_size_mm: f64, height_scale: f64) -> Result<Heightfield> {
    let ctx = path.display().to_string();
    check_scales(&ctx, patch_size_mm, height_scale)?;
    let mut magic = [0u8; 8];
    let got = std::fs::File::open(path)
        .and_then(|mut f| {
            let mut n = 0;
            while n < magic.len() {
                let k = f.read(&mut magic[n..])?;
                if k == 0 {
                    break;
                }
                n += k;
            }
            Ok(n)
        })
        .map_err(|e| Error::io(path, "open the heightmap", e))?;
    let (rows, cols, stored) = if got >= 6 && &magic[..6] == b"\x93NUMPY" {
        read_npy_2d(path)?
    } else if got >= 8 && magic == *b"\x89PNG\r\n\x1a\n" {
        read_png_grey(path)?
    } else {
        return Err(Error::new(
            ctx,
            "is neither a NumPy .npy file nor a PNG (expected a heightmap in one of these)",
        ));
    };
    if rows < 2 || cols < 2 {
        return Err(Error::new(
            ctx,
            format!("a heightmap needs at least 2×2 samples, got {rows}×{cols}"),
        ));
    }
    if let Some(i) = stored.iter().position(|v| !v.is_finite()) {
        return Err(Error::new(
            ctx,
            format!(
                "sample at row {}, column {} is {} (expected a finite number)",
                i / cols,
                i % cols,
                stored[i]
            ),
        ));
    }
    let cell_mm = patch_size_mm / cols as f64;
    let k = height_scale / cell_mm;
    let z: Vec<f64> = stored.iter().map(|v| v * k).collect();
    if let Some(i) = z.iter().position(|v| !v.is_finite()) {
        return Err(Error::new(
            ctx,
            format!(
                "sample at row {}, column {} overflows after scaling to grid cells (height scale \
                 {}, patch size {} mm: {} mm per cell)",
                i / cols,
                i % cols,
                crate::error::show_num(height_scale),
                crate::error::show_num(patch_size_mm),
                crate::error::show_num(cell_mm)
            ),
        ));
    }
    Heightfield::new(cols, rows, z, cell_mm, ctx)
}

/// Whether a geometry reference names a file (an existing file; otherwise, unless it is a
/// generator's name or starts with one and a colon, as `texture:file=wood.png` does, an existing
/// directory or a name ending in `.npy`, `.png` or `.obj`) rather than a procedural spec.
pub fn is_heightmap_file(spec: &str) -> bool {
    let t = spec.trim();
    if Path::new(t).is_file() {
        return true;
    }
    let head = t.split_once(':').map_or(t, |(head, _)| head);
    if crate::generators::list()
        .iter()
        .any(|(name, _)| *name == head)
    {
        return false;
    }
    if Path::new(t).is_dir() {
        return true; // so that loading it says it is a directory
    }
    let lower = t.to_ascii_lowercase();
    [".npy", ".png", ".obj"].iter().any(|e| lower.ends_with(e))
}

/// Samples along x of an OBJ resampled to a heightfield (the generators' default resolution).
pub const OBJ_SAMPLES: usize = 128;

/// A `--geometry` argument: an existing file, or anything ending in `.npy`/`.png`, is loaded with
/// [`load_heightmap`]; otherwise it is a procedural spec (see [`crate::generators`]) whose grid
/// heights are multiplied by `height_scale` and whose `cell_mm` is `patch_size_mm / n`.
pub fn resolve_geometry(spec: &str, patch_size_mm: f64, height_scale: f64) -> Result<Heightfield> {
    if spec.trim().to_ascii_lowercase().ends_with(".obj") {
        // One period in mm with its own size (`patch_size_mm` does not apply), resampled.
        check_scales(spec, patch_size_mm, height_scale)?;
        let hf = crate::fab::import_obj(Path::new(spec), OBJ_SAMPLES)?;
        let z: Vec<f64> = hf.samples().iter().map(|v| v * height_scale).collect();
        return Heightfield::new(hf.width(), hf.height(), z, hf.cell_mm, hf.name.clone());
    }
    if is_heightmap_file(spec) {
        return load_heightmap(Path::new(spec), patch_size_mm, height_scale);
    }
    check_scales(spec, patch_size_mm, height_scale)?;
    let hf = parse_generator(spec)?.build()?;
    let cell_mm = patch_size_mm / hf.width() as f64;
    let z: Vec<f64> = hf.samples().iter().map(|v| v * height_scale).collect();
    Heightfield::new(hf.width(), hf.height(), z, cell_mm, hf.name.clone())
}

/// Write `hf` as a 16-bit grey PNG, 0 = lowest and 65535 = highest sample (a flat field is all 0),
/// via a temporary file in the same directory and a rename. Returns the (min, max) height in mm
/// (grid height × `cell_mm`), which a reader needs to undo the normalisation.
pub fn write_png16(path: &Path, hf: &Heightfield) -> Result<(f64, f64)> {
    let (lo, hi) = hf.min_max();
    let (w, h) = (hf.width(), hf.height());
    if w > u32::MAX as usize || h > u32::MAX as usize {
        return Err(Error::new(
            path.display().to_string(),
            format!("{w}×{h} is too large for a PNG"),
        ));
    }
    let span = hi - lo;
    let px: Vec<u16> = hf
        .samples()
        .iter()
        .map(|&v| {
            if span > 0.0 {
                ((v - lo) / span * 65535.0).round().clamp(0.0, 65535.0) as u16
            } else {
                0
            }
        })
        .collect();
    let buf: ImageBuffer<Luma<u16>, Vec<u16>> = ImageBuffer::from_raw(w as u32, h as u32, px)
        .ok_or_else(|| {
            Error::new(
                path.display().to_string(),
                "internal: PNG buffer size mismatch",
            )
        })?;
    let mut bytes = std::io::Cursor::new(Vec::new());
    buf.write_to(&mut bytes, ImageFormat::Png).map_err(|e| {
        Error::new(
            path.display().to_string(),
            format!("cannot encode the PNG: {e}"),
        )
    })?;
    crate::atomic_write::write_bytes(path, &bytes.into_inner())?;
    Ok((lo * hf.cell_mm, hi * hf.cell_mm))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::npy::write_npy_f64;
    use crate::testdir::TestDir;

    #[test]
    fn a_generator_spec_naming_an_image_is_not_a_heightmap_file() {
        assert!(!is_heightmap_file("texture:file=wood.png,patch=1"));
        assert!(!is_heightmap_file("texture:file=wood.png"));
        assert!(is_heightmap_file("wood.png"));
        assert!(is_heightmap_file("maps/relief.NPY"));
        assert!(!is_heightmap_file("bumps:n=32"));
    }

    #[test]
    fn npy_units() {
        let d = TestDir::new("hmio-npy");
        let p = d.join("h.npy");
        // 2 rows × 4 columns, stored heights 0..0.7
        let data: Vec<f64> = (0..8).map(|i| i as f64 * 0.1).collect();
        write_npy_f64(&p, 2, 4, &data).unwrap();
        let hf = load_heightmap(&p, 8.0, 2.0).unwrap();
        assert_eq!((hf.width(), hf.height()), (4, 2));
        assert_eq!(hf.cell_mm, 2.0);
        // stored 0.5 × 2 mm / 2 mm per cell = 0.5 grid units at row 1, column 1
        assert!((hf.at(1, 1) - 0.5).abs() < 1e-12);
        let e = load_heightmap(&p, 0.0, 1.0).unwrap_err().to_string();
        assert!(e.contains("h.npy") && e.contains("patch size"), "{e}");
        let e = load_heightmap(&p, 1.0, f64::INFINITY)
            .unwrap_err()
            .to_string();
        assert!(e.contains("height scale"), "{e}");
        let mut bad = data.clone();
        bad[6] = f64::NAN;
        write_npy_f64(&p, 2, 4, &bad).unwrap();
        let e = load_heightmap(&p, 8.0, 1.0).unwrap_err().to_string();
        assert!(e.contains("h.npy") && e.contains("row 1, column 2"), "{e}");
    }

    #[test]
    fn png_8_and_16_bit() {
        let d = TestDir::new("hmio-png");
        let p8 = d.join("a8.png");
        image::GrayImage::from_fn(4, 3, |x, y| Luma([(x * 50 + y) as u8]))
            .save(&p8)
            .unwrap();
        let hf = load_heightmap(&p8, 4.0, 1.0).unwrap();
        assert_eq!((hf.width(), hf.height(), hf.cell_mm), (4, 3, 1.0));
        assert!((hf.at(3, 2) - 152.0 / 255.0).abs() < 1e-12);
        let p16 = d.join("a16.png");
        let b: ImageBuffer<Luma<u16>, Vec<u16>> =
            ImageBuffer::from_fn(3, 2, |x, y| Luma([(x * 30000 + y) as u16]));
        b.save(&p16).unwrap();
        let hf = load_heightmap(&p16, 1.5, 1.0).unwrap();
        assert!((hf.at(2, 1) - 60001.0 / 65535.0 / 0.5).abs() < 1e-12);
        let prgb = d.join("rgb.png");
        image::RgbImage::new(3, 3).save(&prgb).unwrap();
        let e = load_heightmap(&prgb, 1.0, 1.0).unwrap_err().to_string();
        assert!(e.contains("rgb.png") && e.contains("grey"), "{e}");
        let junk = d.join("junk.png");
        std::fs::write(&junk, b"\x89PNG\r\n\x1a\nbroken").unwrap();
        let e = load_heightmap(&junk, 1.0, 1.0).unwrap_err().to_string();
        assert!(e.contains("junk.png"), "{e}");
        let txt = d.join("notes.txt");
        std::fs::write(&txt, b"hello").unwrap();
        let e = load_heightmap(&txt, 1.0, 1.0).unwrap_err().to_string();
        assert!(e.contains("notes.txt") && e.contains("neither"), "{e}");
        let e = load_heightmap(&d.join("missing.npy"), 1.0, 1.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing.npy"), "{e}");
    }

    #[test]
    fn png16_round_trip_and_resolve() {
        let d = TestDir::new("hmio-rt");
        let hf = resolve_geometry("sine:n=32,period=8,amplitude=2", 16.0, 0.5).unwrap();
        assert_eq!(hf.cell_mm, 0.5);
        assert!((hf.min_max().1 - 1.0).abs() < 1e-12);
        assert!(hf.name.starts_with("sine:n=32"));
        let p = d.join("out.png");
        let (lo, hi) = write_png16(&p, &hf).unwrap();
        assert!((lo + 0.5).abs() < 1e-12 && (hi - 0.5).abs() < 1e-12);
        let leftovers: Vec<_> = std::fs::read_dir(d.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(leftovers.len(), 1, "{leftovers:?}");
        // Reload: stored [0,1] × (hi - lo) mm is the height above the minimum.
        let back = resolve_geometry(p.to_str().unwrap(), 16.0, hi - lo).unwrap();
        for (a, b) in hf.samples().iter().zip(back.samples()) {
            assert!(((a - hf.min_max().0) - b).abs() < 1e-4 / 0.5, "{a} {b}");
        }
        let e = resolve_geometry("nosuch:n=3", 1.0, 1.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("nosuch") && e.contains("vgroove"), "{e}");
        let e = resolve_geometry("/no/such/file.npy", 1.0, 1.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("/no/such/file.npy"), "{e}");
        let e = resolve_geometry("flat", -1.0, 1.0).unwrap_err().to_string();
        assert!(e.contains("patch size"), "{e}");
        let flat = resolve_geometry("flat:n=8", 1.0, 1.0).unwrap();
        assert_eq!(write_png16(&d.join("flat.png"), &flat).unwrap(), (0.0, 0.0));
    }
}
