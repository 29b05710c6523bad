//! Export of one detail for fabrication: a binary STL of the tiled solid (mm), a 16-bit PNG
//! heightmap of the tile's top surface, and a JSON sidecar giving the PNG's scale.
//!
//! Files `OUT/NAME.stl`, `OUT/NAME.png`, `OUT/NAME.json`, each written atomically
//! (temporary file + rename, [`crate::atomic_write`]); the STL is built in memory and checked
//! with the Manifold kernel ([`super::mesh::verify`]) before anything is written. STL facets
//! carry normals computed from their vertices; the 80-byte header is zero, so the same input
//! gives the same bytes.
//!
//! Decimation (optional, [`Decimation`]): a maximum height error in mm, a triangle budget
//! (the smallest error whose mesh fits the budget, by bisection over the error), or both (the
//! error bound, unless its mesh is over the budget: then the budget's, and the report says the
//! bound was not met); the report gives the triangle count before and after and the error
//! measured at every sample.

use super::decimate::{full_leaves, leaves_within};
use super::mesh::{solid, verify, Mesh, MeshCheck, TileGrid};
use super::profile::Profile;
use crate::atomic_write::write_bytes;
use crate::error::{Error, Result};
use crate::heightfield::Heightfield;
use crate::heightmap_io::write_png16;
use std::path::{Path, PathBuf};

/// How to simplify the top surface.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub enum Decimation {
    /// Largest allowed height error, mm.
    MaxErrorMm(f64),
    /// Largest triangle count of the whole solid.
    TriangleBudget(usize),
    /// Both: the bound's mesh when it fits the budget, else the budget's (a larger error).
    Both { max_error_mm: f64, budget: usize },
}

/// What an export wrote and measured.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ExportReport {
    pub stl: PathBuf,
    pub png: PathBuf,
    pub png_scale: PathBuf,
    pub patch_mm: f64,
    /// Tile actually made (rounded to whole samples), mm.
    pub tile_x_mm: f64,
    pub tile_y_mm: f64,
    pub sample_mm: f64,
    pub base_thickness_mm: f64,
    pub height_mm: f64,
    /// Triangles of the full-resolution solid, and of the one written.
    pub triangles_full: usize,
    pub triangles: usize,
    /// Largest height difference between the written surface and the design samples, mm.
    pub max_height_error_mm: f64,
    /// Whether every limit asked for was met: a triangle budget (a budget below the coarsest
    /// mesh cannot be), and with [`Decimation::Both`] also the error bound.
    pub budget_met: bool,
    pub check: MeshCheck,
}

/// The PNG sidecar: how to turn pixel values back into millimetres.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PngScale {
    pub heightmap: String,
    pub width_px: usize,
    pub height_px: usize,
    pub mm_per_pixel: f64,
    pub z_min_mm: f64,
    pub z_max_mm: f64,
    pub formula: String,
    pub orientation: String,
    pub base_thickness_mm: f64,
    pub patch_mm: f64,
}

/// Binary STL bytes of `m` (f32, facet normals from the vertices).
pub fn stl_bytes(m: &Mesh) -> Result<Vec<u8>> {
    let tris: Vec<stl_io::Triangle> = m
        .tris
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| m.verts[i as usize]);
            let (u, v) = (
                [b[0] - a[0], b[1] - a[1], b[2] - a[2]],
                [c[0] - a[0], c[1] - a[1], c[2] - a[2]],
            );
            let n = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            let n = if len > 0.0 {
                n.map(|x| (x / len) as f32)
            } else {
                [0.0; 3]
            };
            let f = |p: [f64; 3]| stl_io::Vector::new(p.map(|x| x as f32));
            stl_io::Triangle {
                normal: stl_io::Vector::new(n),
                vertices: [f(a), f(b), f(c)],
            }
        })
        .collect();
    let mut out = Vec::with_capacity(84 + 50 * tris.len());
    stl_io::write_stl(&mut out, tris.iter())
        .map_err(|e| Error::new("STL", format!("cannot encode: {e}")))?;
    Ok(out)
}

/// The (possibly decimated) solid of a tile, the measured height error and whether every limit
/// asked for was met.
pub fn tile_solid(g: &TileGrid, decimate: Option<Decimation>) -> Result<(Mesh, f64, bool)> {
    let relief = g.z.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
        - g.z.iter().cloned().fold(f64::INFINITY, f64::min);
    let bound = |e: f64| -> Result<(Mesh, f64)> {
        if !(e.is_finite() && e >= 0.0) {
            return Err(Error::new(
                "decimation",
                format!("the maximum height error must be a number of mm >= 0, got {e}"),
            ));
        }
        let (leaves, err) = leaves_within(g, e);
        Ok((solid(g, &leaves), err))
    };
    match decimate {
        None => Ok((solid(g, &full_leaves(g)), 0.0, true)),
        Some(Decimation::MaxErrorMm(e)) => {
            let (m, err) = bound(e)?;
            Ok((m, err, true))
        }
        Some(Decimation::Both {
            max_error_mm,
            budget,
        }) => {
            let (m, err) = bound(max_error_mm)?;
            if m.tris.len() <= budget {
                return Ok((m, err, true));
            }
            let (m, err, _) = tile_solid(g, Some(Decimation::TriangleBudget(budget)))?;
            Ok((m, err, false))
        }
        Some(Decimation::TriangleBudget(n)) => {
            let full = solid(g, &full_leaves(g));
            if full.tris.len() <= n {
                return Ok((full, 0.0, true));
            }
            let (mut lo, mut hi) = (0.0f64, relief.max(1e-9));
            let (leaves, err) = leaves_within(g, hi);
            let mut best = (solid(g, &leaves), err);
            if best.0.tris.len() > n {
                return Ok((best.0, best.1, false));
            }
            for _ in 0..14 {
                let mid = if lo > 0.0 {
                    (lo * hi).sqrt()
                } else {
                    hi * 0.01
                };
                let (leaves, err) = leaves_within(g, mid);
                let m = solid(g, &leaves);
                if m.tris.len() <= n {
                    hi = mid;
                    best = (m, err);
                } else {
                    lo = mid;
                }
                if lo > 0.0 && hi / lo < 1.05 {
                    break;
                }
            }
            Ok((best.0, best.1, true))
        }
    }
}

fn check_name(name: &str) -> Result<()> {
    if name.is_empty() || name.contains(['/', '\\']) || name.starts_with('.') {
        return Err(Error::new(
            name,
            "an export name must be a plain file name (no directories, not starting with '.')",
        ));
    }
    Ok(())
}

/// Export `hf` at patch size `patch_mm`, tiled to `tile_mm` (x, y), on the profile's base, into
/// `out_dir` as `name.stl`, `name.png` and `name.json`.
pub fn export_detail(
    hf: &Heightfield,
    profile: &Profile,
    patch_mm: f64,
    tile_mm: (f64, f64),
    out_dir: &Path,
    name: &str,
    decimate: Option<Decimation>,
) -> Result<ExportReport> {
    check_name(name)?;
    if !(patch_mm.is_finite() && patch_mm > 0.0) {
        return Err(Error::new(
            "patch size",
            format!("must be a positive number of mm, got {patch_mm}"),
        ));
    }
    let base = profile.base_thickness_mm;
    let g = TileGrid::new(hf, patch_mm, tile_mm.0, tile_mm.1, base)?;
    let triangles_full = 2 * g.nx * g.ny + 6 * (g.nx + g.ny);
    let (mesh, err, budget_met) = tile_solid(&g, decimate)?;
    let stl = out_dir.join(format!("{name}.stl"));
    let check = verify(&mesh, &stl.display().to_string())?;
    let bytes = stl_bytes(&mesh)?;
    let top = g.to_heightfield(&format!("{name} tile"))?;
    let png = out_dir.join(format!("{name}.png"));
    let json = out_dir.join(format!("{name}.json"));
    write_bytes(&stl, &bytes)?;
    let (zmin, zmax) = write_png16(&png, &top)?;
    let scale = PngScale {
        heightmap: format!("{name}.png"),
        width_px: g.nx + 1,
        height_px: g.ny + 1,
        mm_per_pixel: g.cell_mm,
        z_min_mm: zmin,
        z_max_mm: zmax,
        formula:
            "z_mm = z_min_mm + value / 65535 * (z_max_mm - z_min_mm), measured from the bottom face"
                .into(),
        orientation: "column = x, row = y (first row y = 0), pixel (i, j) at (i, j) * mm_per_pixel"
            .into(),
        base_thickness_mm: base,
        patch_mm,
    };
    let text = serde_json::to_string_pretty(&scale)
        .map_err(|e| Error::new(json.display().to_string(), e.to_string()))?;
    write_bytes(&json, format!("{text}\n").as_bytes())?;
    let hi = g.z.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    Ok(ExportReport {
        stl,
        png,
        png_scale: json,
        patch_mm,
        tile_x_mm: g.nx as f64 * g.cell_mm,
        tile_y_mm: g.ny as f64 * g.cell_mm,
        sample_mm: g.cell_mm,
        base_thickness_mm: base,
        height_mm: hi,
        triangles_full,
        triangles: mesh.tris.len(),
        max_height_error_mm: err,
        budget_met,
        check,
    })
}
