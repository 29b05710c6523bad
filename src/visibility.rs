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
//! other distance limit is applied, so tall surfaces at 89.9° stay exact. Blocks of 8×8 cells (4×4
//! or 2×2 when the size does not divide by 8) whose highest point cannot beat the best slope so far
//! are skipped whole. Back-facing points are occluded by their own facet, which the first
//! breakpoint finds.

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
    /// Side of the square blocks of cells whose maximum height lets the march skip them (1: none).
    bsize: i64,
    /// Blocks per row and per column.
    bw: i64,
    bh: i64,
    /// Highest surface point of each block (its cells' corners), row-major.
    bmax: Vec<f64>,
}

impl<'a> Visibility<'a> {
    pub fn new(hf: &'a Heightfield) -> Self {
        let (lo, hi) = hf.min_max();
        let tol = 1e-10 * (1.0 + (hi - lo).abs());
        let (w, h) = (hf.width() as i64, hf.height() as i64);
        let bsize = [8i64, 4, 2].into_iter().find(|b| w % b == 0 && h % b == 0).unwrap_or(1);
        let (bw, bh) = (w / bsize, h / bsize);
        let mut bmax = vec![f64::NEG_INFINITY; (bw * bh) as usize];
        for y in 0..h {
            for x in 0..w {
                let m = hf.at(x, y).max(hf.at(x + 1, y)).max(hf.at(x, y + 1)).max(hf.at(x + 1, y + 1));
                let b = &mut bmax[((y / bsize) * bw + x / bsize) as usize];
                *b = b.max(m);
            }
        }
        Visibility { hf, w, h, zmax: hi, tol, bsize, bw, bh, bmax }
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
        let bs = self.bsize;
        let (mut cur_bx, mut cur_by) = ((cx as i64).div_euclid(bs), (cy as i64).div_euclid(bs));
        // Distance at which the ray entered the current cell.
        let mut s_in = 0.0f64;
        loop {
            // Entering a new block: skip it whole if even its highest point cannot beat `best`
            // (every point of the block is at least `s_in` away).
            if bs > 1 {
                let (bx, by) = ((cx as i64).div_euclid(bs), (cy as i64).div_euclid(bs));
                if bx != cur_bx || by != cur_by {
                    cur_bx = bx;
                    cur_by = by;
                    let bi = (by.rem_euclid(self.bh) * self.bw + bx.rem_euclid(self.bw)) as usize;
                    if s_in > MIN_RUN && self.bmax[bi] - pz <= best * s_in {
                        let edge = |p: f64, d: f64, b: i64| {
                            if d > 0.0 {
                                ((b + 1) * bs) as f64 - p
                            } else if d < 0.0 {
                                (b * bs) as f64 - p
                            } else {
                                f64::INFINITY
                            }
                        };
                        let ex = if dx != 0.0 { edge(px, dx, bx) / dx } else { f64::INFINITY };
                        let ey = if dy != 0.0 { edge(py, dy, by) / dy } else { f64::INFINITY };
                        let s_out = ex.min(ey);
                        if headroom <= best * s_out {
                            return best;
                        }
                        // Restart the cell walk just past the block's exit.
                        let probe = s_out + 1e-7;
                        cx = (px + probe * dx).floor();
                        cy = (py + probe * dy).floor();
                        ix = (cx as i64).rem_euclid(self.w);
                        iy = (cy as i64).rem_euclid(self.h);
                        tmax_x = if dx > 0.0 {
                            (cx + 1.0 - px) / dx
                        } else if dx < 0.0 {
                            (cx - px) / dx
                        } else {
                            f64::INFINITY
                        };
                        tmax_y = if dy > 0.0 {
                            (cy + 1.0 - py) / dy
                        } else if dy < 0.0 {
                            (cy - py) / dy
                        } else {
                            f64::INFINITY
                        };
                        s_in = s_out;
                        continue;
                    }
                }
            }
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
                if sd > MIN_RUN && sd >= s_in && sd < s_exit {
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
            s_in = s_exit;
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

    /// Brute-force horizon: the surface height at every breakpoint (crossings of x = i, y = j and
    /// x - y = k) up to distance `s_max`, through `Heightfield::surface_height`.
    fn brute_horizon(hf: &Heightfield, px: f64, py: f64, pz: f64, dx: f64, dy: f64, s_max: f64) -> f64 {
        let mut ss = Vec::new();
        let mut add = |p0: f64, d: f64| {
            if d.abs() < 1e-12 {
                return;
            }
            let (lo, hi) = if d > 0.0 { (p0, p0 + s_max * d) } else { (p0 + s_max * d, p0) };
            let mut k = lo.floor();
            while k <= hi.ceil() {
                let s = (k - p0) / d;
                if s > 1e-7 && s <= s_max {
                    ss.push(s);
                }
                k += 1.0;
            }
        };
        add(px, dx);
        add(py, dy);
        add(px - py, dx - dy);
        ss.iter()
            .map(|&s| (hf.surface_height(px + s * dx, py + s * dy) - pz) / s)
            .fold(f64::NEG_INFINITY, f64::max)
    }

    #[test]
    fn march_with_block_skipping_matches_brute_force() {
        let mut r = crate::rng::Rng::new(5);
        for &n in &[13usize, 16, 24] {
            let z: Vec<f64> = (0..n * n).map(|_| r.range(0.0, 3.0)).collect();
            let hf = Heightfield::new(n, n, z, 1.0, "rand").unwrap();
            let v = Visibility::new(&hf);
            for _ in 0..300 {
                let (px, py) = (r.range(0.0, n as f64), r.range(0.0, n as f64));
                let pz = hf.surface_height(px, py);
                let phi = r.range(0.0, std::f64::consts::TAU);
                let (dx, dy) = (phi.cos(), phi.sin());
                let floor = 0.05;
                let got = v.horizon(px, py, pz, dx, dy, floor, f64::INFINITY);
                let want = brute_horizon(&hf, px, py, pz, dx, dy, 3.0 / floor + 2.0).max(floor);
                assert!((got - want).abs() < 1e-9 * (1.0 + want.abs()), "n {n} p ({px},{py}) phi {phi}: {got} vs {want}");
            }
        }
    }
}
