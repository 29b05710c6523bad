//! Exact visibility on a periodic triangulated heightfield, neighbouring periods included.
//!
//! A point `p` on the surface sees direction `w = (theta, phi)` iff the ray `p + t w` never passes
//! below the surface. Along the horizontal azimuth `d = (cos phi, sin phi)` the ray rises with slope
//! `m = cot theta`, and the surface height along the line is piecewise linear with breakpoints where
//! the line crosses cell edges and cell diagonals. So `p` is visible iff the *horizon slope*
//! `H(p, d) = max_{s>0} (h(p + s d) - p_z) / s`, taken over those breakpoints only, is at most `m`.
//!
//! The march walks the periodic grid cell by cell (a 2-D DDA over wrapped indices), evaluates the
//! exact surface height at each breakpoint, and stops as soon as the answer is known: when a slope
//! above the threshold is found (occluded), or when even the highest point of the whole surface
//! could no longer reach the threshold (`(z_max - p_z)/s <= m`: visible). Rays therefore march at
//! most `(z_max - p_z) · tan(theta)` grid units, which is where grazing directions cost more; no
//! other distance limit is applied, so tall surfaces at 89.9° stay exact. Back-facing points are
//! occluded by their own facet, which the first breakpoint finds.

use crate::heightfield::Heightfield;

/// Breakpoints closer than this (grid units) to the start are skipped: the start's own facet is
/// handled by the next breakpoint, and tiny `s` would amplify rounding in `(h - p_z)/s`.
const MIN_RUN: f64 = 1e-7;

/// The smallest slope the march resolves (about 89.99994°): thresholds and floors below it are
/// raised to it, which guarantees that every march ends (`(z_max - p_z)/s` falls below it).
pub const MIN_SLOPE: f64 = 1e-6;

/// A periodic heightfield prepared for visibility queries.
pub struct Visibility<'a> {
    hf: &'a Heightfield,
    w: i64,
    h: i64,
    zmax: f64,
    /// Slope tolerance: a breakpoint must exceed the threshold by this much to occlude, so points
    /// on the same plane (flat patches, straight groove walls) do not shadow each other.
    tol: f64,
}

impl<'a> Visibility<'a> {
    pub fn new(hf: &'a Heightfield) -> Self {
        let (lo, hi) = hf.min_max();
        let tol = 1e-10 * (1.0 + (hi - lo).abs());
        Visibility {
            hf,
            w: hf.width() as i64,
            h: hf.height() as i64,
            zmax: hi,
            tol,
        }
    }

    pub fn heightfield(&self) -> &Heightfield {
        self.hf
    }

    /// The horizon slope of point `(px, py, pz)` (on the surface) along unit azimuth `(dx, dy)`:
    /// returns `max(floor, H)` exactly when `H <= stop_above`, and some value above `stop_above`
    /// otherwise (the march stops as soon as it knows). `floor` is raised to [`MIN_SLOPE`]; the
    /// march ends when no farther point can beat the best slope so far, which is at least `floor`.
    #[allow(clippy::too_many_arguments)]
    pub fn horizon(
        &self,
        px: f64,
        py: f64,
        pz: f64,
        dx: f64,
        dy: f64,
        floor: f64,
        stop_above: f64,
    ) -> f64 {
        let mut best = floor.max(MIN_SLOPE);
        let headroom = self.zmax - pz;
        // Unwrapped cell and wrapped indices.
        let mut cx = px.floor();
        let mut cy = py.floor();
        let mut ix = (cx as i64).rem_euclid(self.w);
        let mut iy = (cy as i64).rem_euclid(self.h);
        let sx: i64 = if dx > 0.0 { 1 } else { -1 };
        let sy: i64 = if dy > 0.0 { 1 } else { -1 };
        let inv_dx = if dx != 0.0 {
            1.0 / dx.abs()
        } else {
            f64::INFINITY
        };
        let inv_dy = if dy != 0.0 {
            1.0 / dy.abs()
        } else {
            f64::INFINITY
        };
        let mut tmax_x = if dx > 0.0 {
            (cx + 1.0 - px) * inv_dx
        } else if dx < 0.0 {
            (px - cx) * inv_dx
        } else {
            f64::INFINITY
        };
        let mut tmax_y = if dy > 0.0 {
            (cy + 1.0 - py) * inv_dy
        } else if dy < 0.0 {
            (py - cy) * inv_dy
        } else {
            f64::INFINITY
        };
        let ddiag = dx - dy;
        let z = self.hf.samples();
        let wu = self.w as usize;
        loop {
            let s_exit = tmax_x.min(tmax_y);
            // Corners of the current (wrapped) cell.
            let ix1 = if ix + 1 == self.w { 0 } else { ix + 1 } as usize;
            let iy1 = if iy + 1 == self.h { 0 } else { iy + 1 } as usize;
            let (ixu, iyu) = (ix as usize, iy as usize);
            let z00 = z[iyu * wu + ixu];
            let z10 = z[iyu * wu + ix1];
            let z01 = z[iy1 * wu + ixu];
            let z11 = z[iy1 * wu + ix1];
            // Diagonal crossing inside this cell: (px + s dx - cx) = (py + s dy - cy).
            if ddiag != 0.0 {
                let sd = ((py - cy) - (px - cx)) / ddiag;
                if sd > MIN_RUN && sd < s_exit {
                    let f = (px + sd * dx - cx).clamp(0.0, 1.0);
                    let hgt = z00 + (z11 - z00) * f;
                    let slope = (hgt - pz) / sd;
                    if slope > best {
                        best = slope;
                        if best > stop_above + self.tol {
                            return best;
                        }
                    }
                }
            }
            // Exit point of the cell.
            if s_exit > MIN_RUN {
                let fx = (px + s_exit * dx - cx).clamp(0.0, 1.0);
                let fy = (py + s_exit * dy - cy).clamp(0.0, 1.0);
                let hgt = if fx >= fy {
                    z00 + (z10 - z00) * fx + (z11 - z10) * fy
                } else {
                    z00 + (z11 - z01) * fx + (z01 - z00) * fy
                };
                let slope = (hgt - pz) / s_exit;
                if slope > best {
                    best = slope;
                    if best > stop_above + self.tol {
                        return best;
                    }
                }
                // Nothing farther can rise above max(best, threshold).
                let bound = headroom / s_exit;
                if bound <= best {
                    return best;
                }
            }
            // Step to the next cell.
            if tmax_x < tmax_y {
                tmax_x += inv_dx;
                cx += sx as f64;
                ix += sx;
                if ix == self.w {
                    ix = 0;
                } else if ix < 0 {
                    ix = self.w - 1;
                }
            } else {
                tmax_y += inv_dy;
                cy += sy as f64;
                iy += sy;
                if iy == self.h {
                    iy = 0;
                } else if iy < 0 {
                    iy = self.h - 1;
                }
            }
        }
    }

    /// Whether surface point `(px, py, pz)` sees unit direction `w` (which must have `w.z > 0`).
    pub fn visible(&self, px: f64, py: f64, pz: f64, w: crate::frame::Vec3) -> bool {
        let st = (w.x * w.x + w.y * w.y).sqrt();
        if st <= 0.0 {
            return true; // straight up: nothing on a heightfield is above the zenith ray
        }
        let m = w.z / st;
        let (dx, dy) = (w.x / st, w.y / st);
        self.horizon(px, py, pz, dx, dy, m, m) <= m + self.tol
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::dir_from_deg;

    fn vgroove(n: usize, depth: f64) -> Heightfield {
        // one symmetric V per period along x: z = depth * |x - n/2| / (n/2)
        let mut z = vec![0.0; n * n];
        for y in 0..n {
            for x in 0..n {
                z[y * n + x] = depth * ((x as f64 - n as f64 / 2.0).abs() / (n as f64 / 2.0));
            }
        }
        Heightfield::new(n, n, z, 1.0, "v").unwrap()
    }

    #[test]
    fn flat_sees_everything() {
        let hf = Heightfield::flat(8, 8);
        let v = Visibility::new(&hf);
        for t in [0.0, 45.0, 89.9] {
            assert!(v.visible(3.3, 4.1, 0.0, dir_from_deg(t, 37.0)));
        }
    }

    #[test]
    fn vgroove_bottom_shadowed_at_grazing() {
        // walls of slope 1 (45°): the groove bottom sees directions with theta < 45° across the groove.
        let hf = vgroove(16, 8.0);
        let v = Visibility::new(&hf);
        let (px, py) = (8.0, 3.5);
        let pz = hf.surface_height(px, py);
        assert!(v.visible(px, py, pz, dir_from_deg(40.0, 0.0)));
        assert!(!v.visible(px, py, pz, dir_from_deg(50.0, 0.0)));
        assert!(!v.visible(px, py, pz, dir_from_deg(50.0, 180.0)));
        // along the groove nothing blocks
        assert!(v.visible(px, py, pz, dir_from_deg(89.0, 90.0)));
        // the horizon slope is exactly 1
        let hzn = v.horizon(px, py, pz, 1.0, 0.0, 0.0, f64::INFINITY);
        assert!((hzn - 1.0).abs() < 1e-12, "{hzn}");
    }
}
