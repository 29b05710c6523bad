//! The solid of one tile: the periodic heightfield repeated over the requested tile, side walls
//! and a flat base, as one indexed triangle mesh in millimetres, and its checks.
//!
//! Tiling: the tile is `nx × ny` cells of the detail's sample spacing, `nx = floor(tile_x /
//! cell)` ([`whole_samples`]; a tile under one sample is refused), so its size is rounded down to
//! a whole sample (the size actually made is reported, and costed); the heightfield repeats
//! periodically from the corner `(0, 0)`, and a last period that does not fit is cropped. Heights: the lowest design point sits at `base_thickness_mm`
//! above the bottom face `z = 0`.
//!
//! Topology: the top surface (full resolution or [`super::decimate`]d), one wall quad (two
//! triangles) per top border edge down to `z = 0`, and a bottom fan from one extra vertex at the
//! bottom's centre to every border edge (no degenerate triangles, whatever the border's vertex
//! count). Every vertex is shared, every triangle is counter-clockwise seen from outside.
//!
//! Check ([`verify`]): the Manifold kernel (`manifold-rust`) must accept the mesh as a manifold
//! (status `NoError`) of genus 0, and the signed volume `Σ a·(b×c)/6` (the kernel reports only its
//! absolute value) must be positive.

use super::decimate::{corner_mask, leaf_triangles, Leaf};
use crate::error::{Error, Result};
use crate::heightfield::Heightfield;

/// The most samples (vertices before decimation) of one tile's mesh: 10 million. Building and
/// checking a mesh takes about 700 bytes per sample at its peak (a flat 50 × 50 mm tile of 10
/// million samples, undecimated: 20 million triangles, 7.0 GB peak RSS, 37 s; 4 million: 2.9
/// GB). The limit was 60 million, which the kernel killed for lack of memory on this 24 GB
/// machine; the scale window now keeps every detail's patch large enough to stay under it.
pub const MAX_MESH_SAMPLES: f64 = 10e6;

/// The top surface of a tile on its sample grid, heights in mm above the bottom face.
#[derive(Debug, Clone)]
pub struct TileGrid {
    /// Cells along x and y (`nx + 1` by `ny + 1` samples).
    pub nx: usize,
    pub ny: usize,
    pub cell_mm: f64,
    /// Row-major `(ny + 1) × (nx + 1)` heights in mm.
    pub z: Vec<f64>,
}

/// Samples of `cell` mm in a tile side of `t` mm, whole, rounded down (by a hair's tolerance, so
/// that 50 mm of 0.5 mm samples is 100 of them): the part made is never larger than asked for,
/// so a tile that fits the machine's travel still fits.
pub fn whole_samples(t: f64, cell: f64) -> f64 {
    (t / cell * (1.0 + 1e-9)).floor()
}

/// The tile side made of a `t` mm request for `hf` at patch size `patch_mm`: whole samples
/// ([`whole_samples`]), or `t` itself when it is less than one sample (which the export refuses).
pub fn made_tile_mm(hf: &Heightfield, patch_mm: f64, t: f64) -> f64 {
    let cell = patch_mm / hf.width() as f64;
    let k = whole_samples(t, cell);
    if k >= 1.0 {
        k * cell
    } else {
        t
    }
}

impl TileGrid {
    /// `hf` at patch size `patch_mm`, tiled over `tile_x_mm × tile_y_mm`, on a base of `base_mm`.
    pub fn new(
        hf: &Heightfield,
        patch_mm: f64,
        tile_x_mm: f64,
        tile_y_mm: f64,
        base_mm: f64,
    ) -> Result<TileGrid> {
        let cell = patch_mm / hf.width() as f64;
        let n = |t: f64, key: &str| -> Result<usize> {
            if !(t.is_finite() && t > 0.0) {
                return Err(Error::new(
                    key,
                    format!("must be a positive number of mm, got {t}"),
                ));
            }
            let k = whole_samples(t, cell);
            if k < 1.0 {
                return Err(Error::new(
                    key,
                    format!(
                        "{} mm is less than one sample of the surface ({} mm: the patch of {} mm \
                         over {} samples); make the tile larger",
                        crate::error::show_num(t),
                        crate::error::show_num(cell),
                        crate::error::show_num(patch_mm),
                        hf.width()
                    ),
                ));
            }
            if k > 200_000.0 {
                return Err(Error::new(
                    key,
                    format!("{t} mm is {k} samples of {cell} mm; too many for one mesh"),
                ));
            }
            Ok(k as usize)
        };
        let (nx, ny) = (n(tile_x_mm, "tile x")?, n(tile_y_mm, "tile y")?);
        if (nx as f64 + 1.0) * (ny as f64 + 1.0) > MAX_MESH_SAMPLES {
            return Err(Error::new(
                "tile",
                format!(
                    "{nx} × {ny} samples is too many for one mesh (at most {} million); use a \
                     larger patch or a smaller tile",
                    MAX_MESH_SAMPLES / 1e6
                ),
            ));
        }
        let (lo, _) = hf.min_max();
        let mut z = Vec::with_capacity((nx + 1) * (ny + 1));
        for y in 0..=ny {
            for x in 0..=nx {
                z.push(base_mm + (hf.at(x as i64, y as i64) - lo) * cell);
            }
        }
        Ok(TileGrid {
            nx,
            ny,
            cell_mm: cell,
            z,
        })
    }
    #[inline]
    pub fn idx(&self, x: usize, y: usize) -> usize {
        y * (self.nx + 1) + x
    }
    #[inline]
    pub fn coords(&self, i: usize) -> (usize, usize) {
        (i % (self.nx + 1), i / (self.nx + 1))
    }
    #[inline]
    pub fn z_at(&self, x: usize, y: usize) -> f64 {
        self.z[self.idx(x, y)]
    }
    /// As a (non-periodic) heightfield of `(nx + 1) × (ny + 1)` samples in grid units.
    pub fn to_heightfield(&self, name: &str) -> Result<Heightfield> {
        let z = self.z.iter().map(|v| v / self.cell_mm).collect();
        Heightfield::new(self.nx + 1, self.ny + 1, z, self.cell_mm, name)
    }
}

/// An indexed triangle mesh in mm.
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    pub verts: Vec<[f64; 3]>,
    pub tris: Vec<[u32; 3]>,
}

impl Mesh {
    /// `Σ a·(b×c) / 6`: positive for a closed mesh wound counter-clockwise seen from outside.
    pub fn signed_volume(&self) -> f64 {
        let mut v = 0.0;
        for t in &self.tris {
            let [a, b, c] = t.map(|i| self.verts[i as usize]);
            let cr = [
                b[1] * c[2] - b[2] * c[1],
                b[2] * c[0] - b[0] * c[2],
                b[0] * c[1] - b[1] * c[0],
            ];
            v += a[0] * cr[0] + a[1] * cr[1] + a[2] * cr[2];
        }
        v / 6.0
    }
}

/// The closed solid of a tile whose top surface is made of `leaves`.
pub fn solid(g: &TileGrid, leaves: &[Leaf]) -> Mesh {
    let mask = corner_mask(g, leaves);
    let mut top = Vec::with_capacity(2 * leaves.len());
    for l in leaves {
        leaf_triangles(g, l, &mask, &mut top);
    }
    // Compact the used grid vertices in grid order (deterministic).
    let mut used = vec![u32::MAX; g.z.len()];
    for t in &top {
        for &i in t {
            used[i] = 0;
        }
    }
    let mut verts = Vec::new();
    for (i, u) in used.iter_mut().enumerate() {
        if *u == 0 {
            *u = verts.len() as u32;
            let (x, y) = g.coords(i);
            verts.push([x as f64 * g.cell_mm, y as f64 * g.cell_mm, g.z[i]]);
        }
    }
    let mut tris: Vec<[u32; 3]> = top.iter().map(|t| t.map(|i| used[i])).collect();
    // The tile's border, counter-clockwise seen from above.
    let mut border = Vec::new();
    let push = |b: &mut Vec<usize>, x: usize, y: usize| {
        let i = g.idx(x, y);
        if used[i] != u32::MAX {
            b.push(i);
        }
    };
    for x in 0..g.nx {
        push(&mut border, x, 0);
    }
    for y in 0..g.ny {
        push(&mut border, g.nx, y);
    }
    for x in (1..=g.nx).rev() {
        push(&mut border, x, g.ny);
    }
    for y in (1..=g.ny).rev() {
        push(&mut border, 0, y);
    }
    let bottom0 = verts.len() as u32;
    for &i in &border {
        let (x, y) = g.coords(i);
        verts.push([x as f64 * g.cell_mm, y as f64 * g.cell_mm, 0.0]);
    }
    let centre = verts.len() as u32;
    verts.push([
        0.5 * g.nx as f64 * g.cell_mm,
        0.5 * g.ny as f64 * g.cell_mm,
        0.0,
    ]);
    let n = border.len();
    for k in 0..n {
        let (a, b) = (used[border[k]], used[border[(k + 1) % n]]);
        let (ab, bb) = (bottom0 + k as u32, bottom0 + ((k + 1) % n) as u32);
        tris.push([ab, bb, b]);
        tris.push([ab, b, a]);
        tris.push([centre, bb, ab]);
    }
    Mesh { verts, tris }
}

/// What the Manifold kernel says about a mesh.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct MeshCheck {
    pub triangles: usize,
    pub vertices: usize,
    pub genus: i32,
    /// Signed volume in mm³ (positive = outward winding).
    pub signed_volume_mm3: f64,
    /// The kernel's (absolute) volume, mm³.
    pub manifold_volume_mm3: f64,
}

/// Check `m` is a closed 2-manifold of genus 0 with positive signed volume; `what` names it in
/// errors.
pub fn verify(m: &Mesh, what: &str) -> Result<MeshCheck> {
    use manifold_rust::manifold::Manifold;
    use manifold_rust::types::{Error as MErr, MeshGLP};
    let mesh = MeshGLP::<f64, u32> {
        num_prop: 3,
        vert_properties: m.verts.iter().flat_map(|v| v.iter().copied()).collect(),
        tri_verts: m.tris.iter().flat_map(|t| t.iter().copied()).collect(),
        ..Default::default()
    };
    let man = Manifold::from_mesh_glp(&mesh);
    let status = man.status();
    if status != MErr::NoError {
        return Err(Error::new(what, format!("the Manifold kernel rejects the mesh: {status:?} (internal error: the export must be a closed 2-manifold)")));
    }
    let check = MeshCheck {
        triangles: m.tris.len(),
        vertices: m.verts.len(),
        genus: man.genus(),
        signed_volume_mm3: m.signed_volume(),
        manifold_volume_mm3: man.volume(),
    };
    if check.genus != 0 {
        return Err(Error::new(
            what,
            format!(
                "the mesh has genus {} (internal error: expected 0)",
                check.genus
            ),
        ));
    }
    if check.signed_volume_mm3.is_nan() || check.signed_volume_mm3 <= 0.0 {
        return Err(Error::new(
            what,
            format!(
                "signed volume {} mm³ (internal error: expected > 0, outward winding)",
                check.signed_volume_mm3
            ),
        ));
    }
    Ok(check)
}
