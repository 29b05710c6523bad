//! One period of a periodic heightfield and its triangulation (design notes, Sec. 1).
//!
//! A heightmap of `w × h` samples `z[y][x]` is one period of a periodic surface: vertex
//! `(x, y, z[y mod h][x mod w])` in grid units, every cell `(x, y)–(x+1, y+1)` split into two flat
//! triangles by the diagonal from `(x, y)` to `(x+1, y+1)`. Heights are stored in grid units (one
//! unit = the spacing between samples), so every appearance computation is scale-free;
//! `cell_mm` carries the physical spacing for fabrication and export.

use crate::error::{Error, Result};
use crate::frame::Vec3;

/// A periodic heightfield, heights in grid units.
#[derive(Debug, Clone, PartialEq)]
pub struct Heightfield {
    w: usize,
    h: usize,
    z: Vec<f64>,
    /// Physical side of one grid cell in millimetres (patch size / w).
    pub cell_mm: f64,
    /// A readable name: the file or the procedural spec it came from.
    pub name: String,
}

/// One flat triangle of the triangulation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Facet {
    /// Unit normal, always with `n.z > 0` (a heightfield has no overhangs).
    pub n: Vec3,
    /// Area in grid units squared.
    pub area: f64,
    /// The three vertices, counter-clockwise seen from above, unwrapped (x in `[0, w+1]`).
    pub v: [Vec3; 3],
}

impl Facet {
    /// The centroids of the `s × s` subdivision of the triangle into congruent triangles: `s²`
    /// points, each standing for `area / s²`.
    pub fn stratified_points(&self, s: usize) -> Vec<Vec3> {
        let mut out = Vec::with_capacity(s.max(1).pow(2));
        self.stratified_points_into(s, &mut out);
        out
    }

    /// [`Self::stratified_points`] appended to `out`.
    pub fn stratified_points_into(&self, s: usize, out: &mut Vec<Vec3>) {
        let s = s.max(1);
        let inv = 1.0 / s as f64;
        let [a, b, c] = self.v;
        let (e1, e2) = (b - a, c - a);
        for i in 0..s {
            for j in 0..s - i {
                out.push(
                    a + e1 * ((i as f64 + 1.0 / 3.0) * inv) + e2 * ((j as f64 + 1.0 / 3.0) * inv),
                );
                if i + j + 1 < s {
                    out.push(
                        a + e1 * ((i as f64 + 2.0 / 3.0) * inv)
                            + e2 * ((j as f64 + 2.0 / 3.0) * inv),
                    );
                }
            }
        }
    }
}

/// A point on the surface with the index of its facet.
#[derive(Debug, Clone, Copy)]
pub struct SurfacePoint {
    pub p: Vec3,
    pub facet: u32,
}

/// `s²` stratified points per facet ([`Facet::stratified_points`]), contiguous per facet.
pub fn surface_points(facets: &[Facet], s: usize) -> Vec<SurfacePoint> {
    facets
        .iter()
        .enumerate()
        .flat_map(|(t, f)| {
            f.stratified_points(s)
                .into_iter()
                .map(move |p| SurfacePoint { p, facet: t as u32 })
        })
        .collect()
}

/// The largest height (in cells, grid units) a heightfield may have. A march looks out from a
/// height tolerance above its point that grows with the relief (1e-10 of it, for rounding); on a
/// surface `1e9` cells tall that is 0.2 cells, already about 1 % of what a view ray at 40° sees
/// of a wall near a crest, and rays at 89.9° start `6e11` cells from where they hit.
pub const MAX_HEIGHT: f64 = 1e9;

impl Heightfield {
    /// A heightfield from row-major samples `z[y * w + x]` in grid units. Rejects empty,
    /// mis-sized or non-finite data, and heights beyond [`MAX_HEIGHT`], with a message naming `name`.
    pub fn new(
        w: usize,
        h: usize,
        z: Vec<f64>,
        cell_mm: f64,
        name: impl Into<String>,
    ) -> Result<Self> {
        let name = name.into();
        if w < 2 || h < 2 {
            return Err(Error::new(
                &name,
                format!("a heightmap needs at least 2×2 samples, got {w}×{h}"),
            ));
        }
        if z.len() != w * h {
            return Err(Error::new(
                &name,
                format!("expected {} samples for {w}×{h}, got {}", w * h, z.len()),
            ));
        }
        if let Some(i) = z.iter().position(|v| !v.is_finite()) {
            return Err(Error::new(
                &name,
                format!(
                    "height at row {}, column {} is {} (expected a finite number)",
                    i / w,
                    i % w,
                    z[i]
                ),
            ));
        }
        if !(cell_mm.is_finite() && cell_mm > 0.0) {
            return Err(Error::new(
                &name,
                format!("cell size must be a positive number of mm, got {cell_mm}"),
            ));
        }
        if let Some(i) = z.iter().position(|v| v.abs() > MAX_HEIGHT) {
            return Err(Error::new(
                &name,
                format!(
                    "height at row {}, column {} is {:.3e} cells ({:.3e} mm): heights must lie within \
                     ±{MAX_HEIGHT:e} cells (the side of one sample), beyond which rays at grazing \
                     angles cannot be followed cell by cell in double precision; scale the map \
                     down (--height-scale) or, if one cell of {:.3e} mm is too small, give a larger \
                     patch (--patch-size)",
                    i / w,
                    i % w,
                    z[i],
                    z[i] * cell_mm,
                    cell_mm
                ),
            ));
        }
        Ok(Heightfield {
            w,
            h,
            z,
            cell_mm,
            name,
        })
    }

    /// A flat patch of `w × h` samples.
    pub fn flat(w: usize, h: usize) -> Self {
        Heightfield {
            w,
            h,
            z: vec![0.0; w * h],
            cell_mm: 1.0,
            name: "flat".into(),
        }
    }

    pub fn width(&self) -> usize {
        self.w
    }
    pub fn height(&self) -> usize {
        self.h
    }
    /// Row-major samples in grid units.
    pub fn samples(&self) -> &[f64] {
        &self.z
    }
    /// Area of one period's base in grid units squared (`A_base`).
    pub fn base_area(&self) -> f64 {
        (self.w * self.h) as f64
    }

    /// Sample at integer coordinates, wrapped periodically.
    #[inline]
    pub fn at(&self, x: i64, y: i64) -> f64 {
        let xi = x.rem_euclid(self.w as i64) as usize;
        let yi = y.rem_euclid(self.h as i64) as usize;
        self.z[yi * self.w + xi]
    }

    pub fn min_max(&self) -> (f64, f64) {
        self.z
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            })
    }

    /// Height of the triangulated surface at any `(x, y)` in grid units (periodic).
    pub fn surface_height(&self, x: f64, y: f64) -> f64 {
        let (cx, cy) = (crate::fastmath::floor(x), crate::fastmath::floor(y));
        let (fx, fy) = (x - cx, y - cy);
        let (ix, iy) = (cx as i64, cy as i64);
        let z00 = self.at(ix, iy);
        let z11 = self.at(ix + 1, iy + 1);
        if fx >= fy {
            let z10 = self.at(ix + 1, iy);
            z00 + (z10 - z00) * fx + (z11 - z10) * fy
        } else {
            let z01 = self.at(ix, iy + 1);
            z00 + (z11 - z01) * fx + (z01 - z00) * fy
        }
    }

    /// The two facets of cell `(x, y)`: index 0 is the lower-right triangle `(x,y),(x+1,y),(x+1,y+1)`,
    /// index 1 the upper-left `(x,y),(x+1,y+1),(x,y+1)`.
    pub fn cell_facets(&self, x: usize, y: usize) -> [Facet; 2] {
        let (xi, yi) = (x as i64, y as i64);
        let (xf, yf) = (x as f64, y as f64);
        let v00 = Vec3::new(xf, yf, self.at(xi, yi));
        let v10 = Vec3::new(xf + 1.0, yf, self.at(xi + 1, yi));
        let v11 = Vec3::new(xf + 1.0, yf + 1.0, self.at(xi + 1, yi + 1));
        let v01 = Vec3::new(xf, yf + 1.0, self.at(xi, yi + 1));
        let mk = |a: Vec3, b: Vec3, c: Vec3| {
            let cr = (b - a).cross(c - a);
            let len = cr.norm();
            Facet {
                n: cr * (1.0 / len),
                area: 0.5 * len,
                v: [a, b, c],
            }
        };
        [mk(v00, v10, v11), mk(v00, v11, v01)]
    }

    /// Facet `i` of [`Self::facets`] alone.
    pub fn facet(&self, i: usize) -> Facet {
        let cell = i / 2;
        self.cell_facets(cell % self.w, cell / self.w)[i % 2]
    }

    /// Every facet of one period, in the order cell `(x, y)` row-major, lower-right then upper-left.
    pub fn facets(&self) -> Vec<Facet> {
        let mut out = Vec::with_capacity(2 * self.w * self.h);
        for y in 0..self.h {
            for x in 0..self.w {
                out.extend_from_slice(&self.cell_facets(x, y));
            }
        }
        out
    }

    /// A copy with every height multiplied by `s` (scale-free amplitude change).
    pub fn scaled(&self, s: f64) -> Heightfield {
        Heightfield {
            z: self.z.iter().map(|v| v * s).collect(),
            ..self.clone()
        }
    }

    /// Rotate the period by a multiple of 90° about +z (exact, no resampling): `quarter_turns`
    /// counter-clockwise turns.
    pub fn rotated_quarter(&self, quarter_turns: u32) -> Heightfield {
        let mut cur = self.clone();
        for _ in 0..(quarter_turns % 4) {
            // new(x', y') = old(x, y) with x' = -y, y' = x  (counter-clockwise)
            let (w, h) = (cur.w, cur.h);
            let mut z = vec![0.0; w * h];
            for y in 0..h {
                for x in 0..w {
                    let nx = (h - y) % h;
                    let ny = x;
                    z[ny * h + nx] = cur.z[y * w + x];
                }
            }
            cur = Heightfield {
                w: h,
                h: w,
                z,
                ..cur
            };
        }
        cur
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn facet_areas_project_to_base() {
        let hf = Heightfield::new(3, 2, vec![0.0, 1.0, 0.5, 2.0, -1.0, 0.25], 1.0, "t").unwrap();
        let fs = hf.facets();
        let projected: f64 = fs.iter().map(|f| f.area * f.n.z).sum();
        assert!((projected - hf.base_area()).abs() < 1e-12);
        // The area-weighted normals of a periodic surface sum to A_base · z.
        let s = fs.iter().fold(Vec3::default(), |acc, f| acc + f.n * f.area);
        assert!(s.x.abs() < 1e-12 && s.y.abs() < 1e-12);
    }

    #[test]
    fn surface_height_matches_vertices_and_facets() {
        let hf = Heightfield::new(3, 2, vec![0.0, 1.0, 0.5, 2.0, -1.0, 0.25], 1.0, "t").unwrap();
        assert_eq!(hf.surface_height(1.0, 1.0), -1.0);
        assert_eq!(hf.surface_height(4.0, 3.0), -1.0);
        for f in hf.facets() {
            let c = (f.v[0] + f.v[1] + f.v[2]) * (1.0 / 3.0);
            assert!((hf.surface_height(c.x, c.y) - c.z).abs() < 1e-12);
        }
    }

    #[test]
    fn rejects_non_finite() {
        let e = Heightfield::new(2, 2, vec![0.0, f64::NAN, 0.0, 0.0], 1.0, "a.npy").unwrap_err();
        assert!(e.to_string().contains("a.npy") && e.to_string().contains("row 0, column 1"));
    }

    #[test]
    fn quarter_rotation() {
        let hf = Heightfield::new(3, 2, vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0], 1.0, "t").unwrap();
        let r = hf.rotated_quarter(1);
        assert_eq!((r.width(), r.height()), (2, 3));
        // point (x=1, y=0) goes to (x'=0, y'=1)
        assert_eq!(r.at(0, 1), hf.at(1, 0));
        assert_eq!(hf.rotated_quarter(4), hf);
    }

    #[test]
    fn point_counts_and_weights() {
        let hf = Heightfield::flat(3, 3);
        let f = hf.facets();
        for s in 1..5 {
            let pts = surface_points(&f, s);
            assert_eq!(pts.len(), f.len() * s * s);
            // every point lies inside its facet's xy footprint
            for sp in &pts {
                let fa = &f[sp.facet as usize];
                let (mnx, mxx) =
                    fa.v.iter()
                        .fold((9.0f64, -9.0f64), |(a, b), v| (a.min(v.x), b.max(v.x)));
                assert!(sp.p.x > mnx && sp.p.x < mxx);
            }
        }
    }
}
