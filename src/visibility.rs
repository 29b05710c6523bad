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
//! other distance limit is applied, so tall surfaces at 89.9° stay exact. Blocks of 8×8 cells (on a grid
//! of any size: where 8 does not divide a side, each distinct block of successive periods has
//! its own maximum) whose highest point cannot beat the best slope so far are skipped whole. Back-facing points are occluded by their own facet, which the first
//! breakpoint finds.
//!
//! Marches are short (a library build averages 3.5 cells per shadow test), so what each march
//! sets up matters: [`Azimuth`] and [`Direction`] carry a direction's reciprocals and line period,
//! prepared once per direction (`*_along`, `*_dir`); wrapping uses masks when the grid and
//! block counts are powers of two.

use crate::fastmath::floor;
use crate::frame::Vec3;
use crate::heightfield::Heightfield;
use crate::rng::R2;

/// Breakpoints closer than this (grid units) to the start are skipped: the start's own facet is
/// handled by the next breakpoint, and tiny `s` would amplify rounding in `(h - p_z)/s`.
const MIN_RUN: f64 = 1e-7;

/// The smallest slope the march resolves (about 89.99994°): thresholds and floors below it are
/// raised to it, which guarantees that every march ends (`(z_max - p_z)/s` falls below it).
pub const MIN_SLOPE: f64 = 1e-6;

/// A horizontal march direction and what every walk along it needs (the grid-line spacings,
/// the diagonal crossing factor, the line's period), computed once per direction rather than
/// once per march: a library build marches about 150,000 times per geometry, a few cells each.
#[derive(Debug, Clone, Copy)]
pub struct Azimuth {
    dx: f64,
    dy: f64,
    /// `1 / (dx - dy)`, 0 when the line is parallel to the cells' diagonals.
    inv_dd: f64,
    /// Distances between the vertical / horizontal grid lines along the line.
    step_x: f64,
    step_y: f64,
    /// Length after which the surface along the line repeats (infinite when it does not, within
    /// a few periods).
    period: f64,
}

/// A direction above the surface prepared for [`Visibility::visible_dir`] and
/// [`Visibility::first_hit_dir`]: its azimuth both ways and its slope `cot theta`.
#[derive(Debug, Clone, Copy)]
pub struct Direction {
    w: Vec3,
    /// `None` for the zenith (or below the horizon, for `first_hit`); otherwise the azimuth
    /// `(dx, dy)` as computed, its march data forwards and backwards, and the slope.
    along: Option<Along>,
}

#[derive(Debug, Clone, Copy)]
struct Along {
    dx: f64,
    dy: f64,
    fwd: Azimuth,
    back: Azimuth,
    m: f64,
    /// An upper bound of the surface's slope along the azimuth towards the direction
    /// ([`Visibility::slope_bound`]): when it is at most `m`, no point on the surface is shadowed.
    rise: f64,
}

/// Side, in cells, of the blocks a march skips whole when even their highest point cannot
/// occlude ([`Visibility::new`]), on a grid of any size.
const BLOCK: i64 = 8;

/// `x` modulo `n` (non-negative), with a mask when `n` is a power of two (`mask = n - 1`,
/// otherwise `-1`): `rem_euclid` is an integer division, and walks wrap at every cell.
#[inline]
fn wrap(x: i64, n: i64, mask: i64) -> i64 {
    if mask >= 0 {
        x & mask
    } else {
        x.rem_euclid(n)
    }
}

/// `floor(x)` as an integer, for `|x| < 2^63`.
#[inline]
fn ifloor(x: f64) -> i64 {
    let t = x as i64;
    t - ((t as f64) > x) as i64
}

fn pow2_mask(n: i64) -> i64 {
    if n > 0 && n & (n - 1) == 0 {
        n - 1
    } else {
        -1
    }
}

/// A periodic heightfield prepared for visibility queries.
pub struct Visibility<'a> {
    /// Borrowed ([`Visibility::new`]) or owned ([`Visibility::owned`]).
    hf: std::borrow::Cow<'a, Heightfield>,
    w: i64,
    h: i64,
    zmax: f64,
    zmin: f64,
    /// Height tolerance: a breakpoint must rise this much above the threshold line to occlude,
    /// so that points on the same plane (flat patches, straight groove walls) do not shadow
    /// each other. A height, not a slope: far breakpoints are judged as exactly as near ones (a
    /// slope tolerance proportional to the relief let marches over very tall surfaces run for
    /// ever without deciding).
    htol: f64,
    /// Side of the square blocks of cells whose maximum height lets the march skip them
    /// ([`BLOCK`]).
    bsize: i64,
    /// Distinct blocks per row and per column (`side / gcd(side, bsize)`).
    bw: i64,
    bh: i64,
    /// Highest surface point of each block (its cells' corners), row-major.
    bmax: Vec<f64>,
    /// Highest corner of each cell, row-major: a cell whose highest point cannot beat the
    /// march's best slope is stepped over without its corners (most cells of a march).
    cmax: Vec<f64>,
    /// The surface's steepest rise along each of the 8 azimuths `k · 45°` (from +x towards +y):
    /// the largest directional derivative of any facet ([`Visibility::slope_bound`]).
    slopes: [f64; 8],
    /// `log2(bsize)` and the power-of-two masks of the block counts ([`wrap`]).
    bshift: u32,
    bwmask: i64,
    bhmask: i64,
}

impl Visibility<'static> {
    /// The same as [`Visibility::new`], holding its heightfield (for a model that outlives the
    /// heightfield it was built from).
    pub fn owned(hf: Heightfield) -> Self {
        Visibility::prepare(std::borrow::Cow::Owned(hf))
    }
}

impl<'a> Visibility<'a> {
    pub fn new(hf: &'a Heightfield) -> Self {
        Visibility::prepare(std::borrow::Cow::Borrowed(hf))
    }

    fn prepare(hf: std::borrow::Cow<'a, Heightfield>) -> Self {
        let (lo, hi) = hf.min_max();
        let htol = 1e-10 * (1.0 + (hi - lo).abs()) + 64.0 * f64::EPSILON * hi.abs().max(lo.abs());
        let (w, h) = (hf.width() as i64, hf.height() as i64);
        // Blocks of BLOCK × BLOCK cells in unwrapped cell coordinates. Where BLOCK does not
        // divide a side, the blocks of successive periods hold different cells; the table keeps
        // every distinct one, `side / gcd(side, BLOCK)` per side (block `b` and `b + bw` hold
        // the same cells, `lcm(side, BLOCK)` apart). Each block's highest point is the maximum
        // of its cells' corners, over the rows' windows first, then the columns'.
        let bsize = BLOCK;
        let gcd = |mut a: i64, mut b: i64| {
            while b != 0 {
                (a, b) = (b, a % b);
            }
            a
        };
        let (bw, bh) = (w / gcd(w, bsize), h / gcd(h, bsize));
        let mut cell_max = vec![0.0; (w * h) as usize];
        // The largest of `±gx`, `±gy`, `±(gx + gy)`, `±(gx - gy)` over the facets' gradients.
        let mut rise = [f64::NEG_INFINITY; 8];
        for y in 0..h {
            for x in 0..w {
                let (z00, z10, z01, z11) = (
                    hf.at(x, y),
                    hf.at(x + 1, y),
                    hf.at(x, y + 1),
                    hf.at(x + 1, y + 1),
                );
                cell_max[(y * w + x) as usize] = z00.max(z10).max(z01).max(z11);
                // The lower-right facet, then the upper-left ([`Heightfield::cell_facets`]).
                for (gx, gy) in [(z10 - z00, z11 - z10), (z11 - z01, z01 - z00)] {
                    let g = [gx, gx + gy, gy, gy - gx, -gx, -gx - gy, -gy, gx - gy];
                    for (r, g) in rise.iter_mut().zip(g) {
                        *r = r.max(g);
                    }
                }
            }
        }
        let slopes: [f64; 8] = std::array::from_fn(|k| {
            if k % 2 == 1 {
                rise[k] * std::f64::consts::FRAC_1_SQRT_2
            } else {
                rise[k]
            }
        });
        let mut rows = vec![f64::NEG_INFINITY; (h * bw) as usize];
        for y in 0..h {
            for bx in 0..bw {
                let m = &mut rows[(y * bw + bx) as usize];
                for i in 0..bsize {
                    *m = m.max(cell_max[(y * w + (bx * bsize + i) % w) as usize]);
                }
            }
        }
        let mut bmax = vec![f64::NEG_INFINITY; (bw * bh) as usize];
        for by in 0..bh {
            for bx in 0..bw {
                let m = &mut bmax[(by * bw + bx) as usize];
                for j in 0..bsize {
                    *m = m.max(rows[(((by * bsize + j) % h) * bw + bx) as usize]);
                }
            }
        }
        Visibility {
            hf,
            w,
            h,
            zmax: hi,
            zmin: lo,
            htol,
            bsize,
            bw,
            bh,
            bmax,
            cmax: cell_max,
            slopes,
            bshift: bsize.trailing_zeros(),
            bwmask: pow2_mask(bw),
            bhmask: pow2_mask(bh),
        }
    }

    /// The march data of the horizontal unit direction `(dx, dy)`.
    pub fn azimuth(&self, dx: f64, dy: f64) -> Azimuth {
        let period = self.line_period(dx, dy).unwrap_or(f64::INFINITY);
        // A component this small (an axis azimuth computed as `cos(3π/2)`) moves the line by
        // less than a rounding step of the position over any march, so the cell found after a
        // restart could be the one just left, and a walk starting on a grid line would keep
        // re-entering it: take it as exactly zero.
        let snap = |d: f64| if d.abs() < 1e-9 { 0.0 } else { d };
        let (dx, dy) = (snap(dx), snap(dy));
        Azimuth {
            dx,
            dy,
            inv_dd: if dx == dy { 0.0 } else { 1.0 / (dx - dy) },
            step_x: 1.0 / dx.abs(),
            step_y: 1.0 / dy.abs(),
            period,
        }
    }

    /// The march data of direction `w` (towards the sky).
    pub fn direction(&self, w: Vec3) -> Direction {
        let st = (w.x * w.x + w.y * w.y).sqrt();
        let along = (st > 1e-12 && w.z > 0.0).then(|| {
            let (dx, dy) = (w.x / st, w.y / st);
            Along {
                dx,
                dy,
                fwd: self.azimuth(dx, dy),
                back: self.azimuth(-dx, -dy),
                m: w.z / st,
                rise: self.slope_bound(dx, dy),
            }
        });
        Direction { w, along }
    }

    /// An upper bound of the surface's rise per unit run along the horizontal unit direction
    /// `(dx, dy)`: `(dx, dy) = a u_k + b u_(k+1)` with `a, b >= 0` for the two of the 8 azimuths
    /// `u_k` around it, and a facet's directional derivative `g · (dx, dy)` is then at most
    /// `a` times the steepest along `u_k` plus `b` times the steepest along `u_(k+1)` (exact along
    /// the 8 azimuths themselves, at most 8 % over between them). The surface is continuous and
    /// linear on each facet, so it rises by at most that much per unit along any line.
    fn slope_bound(&self, dx: f64, dy: f64) -> f64 {
        use std::f64::consts::FRAC_PI_4;
        let k = ((dy.atan2(dx) / FRAC_PI_4).floor() as i64).rem_euclid(8) as usize;
        let unit = |k: usize| {
            let a = k as f64 * FRAC_PI_4;
            (a.cos(), a.sin())
        };
        let ((x0, y0), (x1, y1)) = (unit(k), unit((k + 1) % 8));
        let det = x0 * y1 - y0 * x1;
        let a = ((dx * y1 - dy * x1) / det).max(0.0);
        let b = ((x0 * dy - y0 * dx) / det).max(0.0);
        a * self.slopes[k] + b * self.slopes[(k + 1) % 8]
    }

    pub fn heightfield(&self) -> &Heightfield {
        &self.hf
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
        self.horizon_along(px, py, pz, &self.azimuth(dx, dy), floor, stop_above)
    }

    /// [`Visibility::horizon`] along a prepared azimuth.
    pub fn horizon_along(
        &self,
        px: f64,
        py: f64,
        pz: f64,
        az: &Azimuth,
        floor: f64,
        stop_above: f64,
    ) -> f64 {
        self.march(px, py, pz, az, floor, stop_above, &[]).0
    }

    /// The horizon slope of `(px, py, pz)` along `az` resolved only against `levels` (ascending
    /// slopes, at least one): returns the smallest level at or above the horizon slope `H`, or a
    /// value above the last level when `H` is above it. Counting the levels at or above the result
    /// counts those at or above `H`, which is all the compact BVNDF needs of a horizon (which
    /// polar nodes of the azimuth see the point), and the march ends sooner: once a breakpoint
    /// beats the best level so far, the best jumps to the next level up, so nothing nearer than
    /// `headroom / level` needs walking.
    pub fn horizon_level(&self, px: f64, py: f64, pz: f64, az: &Azimuth, levels: &[f64]) -> f64 {
        let (lo, hi) = match (levels.first(), levels.last()) {
            (Some(&lo), Some(&hi)) => (lo, hi),
            _ => return self.horizon_along(px, py, pz, az, 0.0, f64::INFINITY),
        };
        self.march(px, py, pz, az, lo, hi, levels).0
    }

    /// The march of [`Visibility::horizon_along`]: the best slope, and whether the march
    /// stopped because a breakpoint rose above `stop_above` by more than the height tolerance
    /// (`(h - p_z - htol) / s > stop_above`, the test of [`Visibility::visible_dir`]). With
    /// `levels` (ascending), a new best slope is raised to the next level at or above it
    /// ([`Visibility::horizon_level`]).
    #[allow(clippy::too_many_arguments)]
    fn march(
        &self,
        px: f64,
        py: f64,
        pz: f64,
        az: &Azimuth,
        floor: f64,
        stop_above: f64,
        levels: &[f64],
    ) -> (f64, bool) {
        let snap = |b: f64| levels.iter().copied().find(|&l| l >= b).unwrap_or(b);
        let mut best = floor.max(MIN_SLOPE);
        let headroom = self.zmax - pz;
        // On a line that repeats after `period`, later copies of a point are farther away, so
        // none beats the first period's best positive slope.
        let period = az.period;
        let mut walk = CellWalk::new(px, py, az, self.w, self.h);
        let mut cur_block = walk.block(self.bshift);
        loop {
            // Entering a new block: skip it whole if even its highest point cannot beat `best`
            // (every point of the block is at least `s_in` away).
            if self.bsize > 1 {
                let b = walk.block(self.bshift);
                if b != cur_block {
                    cur_block = b;
                    if walk.s_in > MIN_RUN && self.block_max(b) - pz <= best * walk.s_in {
                        let s_out = walk.block_exit(self.bsize, b);
                        if headroom <= best * s_out || s_out > period {
                            return (best, false);
                        }
                        walk.restart(s_out);
                        continue;
                    }
                }
            }
            let s_exit = walk.s_exit();
            // Every breakpoint of the cell is at least `s_in` away and at most its highest
            // corner: none beats `best` when that corner does not at `s_in` (the same test as
            // the blocks', per cell). Only the end test at the exit remains.
            if walk.s_in > MIN_RUN
                && self.cmax[(walk.iy * self.w + walk.ix) as usize] - pz <= best * walk.s_in
            {
                if s_exit > MIN_RUN && (headroom <= best * s_exit || s_exit > period) {
                    return (best, false);
                }
                walk.step();
                continue;
            }
            let c = self.corners(&walk);
            if let Some(sd) = walk.diagonal_crossing() {
                if sd > MIN_RUN {
                    // Slopes are compared as rises (`rise > best s`), dividing only when a
                    // breakpoint beats the best: most breakpoints do not.
                    let rise = walk.height_at(sd, &c) - pz;
                    if rise > best * sd {
                        best = rise / sd;
                        if best > stop_above + self.htol / sd {
                            return (best, true);
                        }
                        best = snap(best);
                    }
                }
            }
            if s_exit > MIN_RUN {
                let rise = walk.height_at(s_exit, &c) - pz;
                if rise > best * s_exit {
                    best = rise / s_exit;
                    if best > stop_above + self.htol / s_exit {
                        return (best, true);
                    }
                    best = snap(best);
                }
                // Nothing farther can rise above the best slope so far.
                if headroom <= best * s_exit || s_exit > period {
                    return (best, false);
                }
            }
            walk.step();
        }
    }

    /// The length after which the surface along the horizontal line with unit direction
    /// `(dx, dy)` repeats exactly, for the directions where that happens within a few periods:
    /// along the grid axes and the diagonals (up to rounding of 1e-12). `None` otherwise.
    fn line_period(&self, dx: f64, dy: f64) -> Option<f64> {
        let (ax, ay) = (dx.abs(), dy.abs());
        if ay <= 1e-12 * ax {
            Some(self.w as f64 / ax)
        } else if ax <= 1e-12 * ay {
            Some(self.h as f64 / ay)
        } else if (ax - ay).abs() <= 1e-12 * ax {
            let (mut a, mut b) = (self.w, self.h);
            while b != 0 {
                (a, b) = (b, a % b);
            }
            Some((self.w / a * self.h) as f64 / ax)
        } else {
            None
        }
    }

    /// The first surface point hit by the ray arriving from direction `w` (travelling along
    /// `-w`) that crosses the base plane `z = 0` at `(u, v)`: the point and its facet index (in
    /// the order of [`Heightfield::facets`]). `w` must point above the horizon.
    pub fn first_hit(&self, u: f64, v: f64, w: Vec3) -> (Vec3, usize) {
        self.first_hit_dir(u, v, &self.direction(w))
    }

    /// [`Visibility::first_hit`] from a prepared direction.
    pub fn first_hit_dir(&self, u: f64, v: f64, dir: &Direction) -> (Vec3, usize) {
        self.first_hit_with(u, v, dir, true)
    }

    /// [`Visibility::first_hit_dir`], with the short rays' breakpoint scan ([`Breaks`]) or
    /// always by the walk.
    fn first_hit_with(&self, u: f64, v: f64, dir: &Direction, short: bool) -> (Vec3, usize) {
        let Some(al) = &dir.along else {
            let z = self.hf.surface_height(u, v);
            return (Vec3::new(u, v, z), self.facet_at(u, v));
        };
        let m = al.m.max(MIN_SLOPE);
        let (dx, dy) = (al.dx, al.dy);
        // Start where the ray is at the highest surface point; walk along -d, descending. The
        // start is taken back into the period (whole periods change nothing on a periodic
        // surface), so that a tall surface seen at a grazing angle, whose start lies `zmax / m`
        // away, is walked at small coordinates, where rounding stays far below a cell.
        let zs = self.zmax;
        let (wp, hp) = (self.w as f64, self.h as f64);
        let (qx, qy) = (
            (u + zs / m * dx).rem_euclid(wp),
            (v + zs / m * dy).rem_euclid(hp),
        );
        let mut walk = CellWalk::new(qx, qy, &al.back, self.w, self.h);
        let mut cur_block = walk.block(self.bshift);
        let g_at = |s: f64, h: f64| h - (zs - m * s);
        let mut prev_s = 0.0;
        let mut prev_g = g_at(0.0, self.hf.surface_height(qx, qy));
        // On a line that repeats after `period`, once a whole period has been seen without a hit
        // the ray can jump a whole number of periods, to just above the line's highest point.
        let period = Some(al.back.period).filter(|p| p.is_finite());
        let mut line_max = f64::NEG_INFINITY;
        let mut jumped = false;
        // Where the ray passes the surface between two breakpoints (`g0 < 0 <= g1`), in the
        // period like the start (the hit may lie far from it).
        let crossing = |s0: f64, g0: f64, s1: f64, g1: f64| {
            let s = if g1 > g0 {
                s0 + (s1 - s0) * (-g0 / (g1 - g0)).clamp(0.0, 1.0)
            } else {
                s1
            };
            Vec3::new(
                (qx - s * dx).rem_euclid(wp),
                (qy - s * dy).rem_euclid(hp),
                zs - m * s,
            )
        };
        let hit = |walk: &CellWalk, s0: f64, g0: f64, s1: f64, g1: f64| {
            let (fx, fy) = walk.local(0.5 * (s0 + s1));
            let tri = if fx >= fy { 0 } else { 1 };
            (
                crossing(s0, g0, s1, g1),
                2 * (walk.iy as usize * self.w as usize + walk.ix as usize) + tri,
            )
        };
        if prev_g >= 0.0 {
            return hit(&walk, 0.0, prev_g, 0.0, prev_g);
        }
        // The ray's height over the surface at a restart, where it was left to be found.
        let prev_g_at = |s: f64, g: f64| {
            if g.is_nan() {
                g_at(s, self.hf.surface_height(qx - s * dx, qy - s * dy))
            } else {
                g
            }
        };
        if short {
            if let Some(((s0, g0), (s1, g1))) = self.first_hit_short(qx, qy, prev_g, &al.back, m) {
                // The facet is the one under the segment between the two breakpoints.
                let mid = 0.5 * (s0 + s1);
                let facet = self.facet_at(qx - mid * dx, qy - mid * dy);
                return (crossing(s0, g0, s1, g1), facet);
            }
        }
        loop {
            // Where this step leaves the ray, and whether the walk restarts there (a skipped
            // block) or steps on (a walked cell).
            let (s_now, skipped) = 'step: {
                if self.bsize > 1 {
                    let b = walk.block(self.bshift);
                    if b != cur_block {
                        cur_block = b;
                        let s_out = walk.block_exit(self.bsize, b);
                        // The ray is lowest at the block's exit; skip if it stays above the
                        // block. (During the first period of a repeating line, whose exact
                        // maximum the jump below needs, only a block no higher than the line's
                        // maximum so far: skipping it cannot change that maximum.)
                        let bmax = self.block_max(b);
                        if walk.s_in > 0.0
                            && (period.is_none() || jumped || bmax <= line_max)
                            && bmax < zs - m * s_out
                        {
                            break 'step (s_out, true);
                        }
                    }
                }
                let c = self.corners(&walk);
                let s_exit = walk.s_exit();
                // The cell's breakpoints in order: its diagonal (if the line crosses it), its exit.
                for s in [walk.diagonal_crossing(), Some(s_exit)]
                    .into_iter()
                    .flatten()
                {
                    let h = walk.height_at(s, &c);
                    line_max = line_max.max(h);
                    let g = g_at(s, h);
                    if g >= 0.0 {
                        let g0 = prev_g_at(prev_s, prev_g);
                        return hit(&walk, prev_s, g0, s, g);
                    }
                    prev_s = s;
                    prev_g = g;
                }
                (s_exit, false)
            };
            let mut restart = skipped.then_some(s_now);
            if let Some(l) = period {
                if !jumped && s_now > l {
                    jumped = true;
                    // Whole periods during which the ray stays above the line's maximum.
                    let k = (((zs - line_max) / m - s_now) / l).floor();
                    if k >= 1.0 {
                        restart = Some(s_now + k * l);
                    }
                }
            }
            match restart {
                Some(s) => {
                    walk.restart(s);
                    prev_s = s;
                    // Found only if the next breakpoint is the hit (most restarts are followed
                    // by another skip).
                    prev_g = f64::NAN;
                }
                None => walk.step(),
            }
        }
    }

    /// Index of the facet containing base point `(x, y)`.
    fn facet_at(&self, x: f64, y: f64) -> usize {
        let (cx, cy) = (floor(x), floor(y));
        let ix = (cx as i64).rem_euclid(self.w) as usize;
        let iy = (cy as i64).rem_euclid(self.h) as usize;
        2 * (iy * self.w as usize + ix) + if x - cx >= y - cy { 0 } else { 1 }
    }

    fn block_max(&self, (bx, by): (i64, i64)) -> f64 {
        self.bmax
            [(wrap(by, self.bh, self.bhmask) * self.bw + wrap(bx, self.bw, self.bwmask)) as usize]
    }

    /// Corner heights `[z00, z10, z01, z11]` of the walk's current cell.
    #[inline]
    fn corners(&self, walk: &CellWalk) -> [f64; 4] {
        let z = self.hf.samples();
        let wu = self.w as usize;
        let ix1 = if walk.ix + 1 == self.w {
            0
        } else {
            walk.ix + 1
        } as usize;
        let iy1 = if walk.iy + 1 == self.h {
            0
        } else {
            walk.iy + 1
        } as usize;
        let (ix, iy) = (walk.ix as usize, walk.iy as usize);
        [
            z[iy * wu + ix],
            z[iy * wu + ix1],
            z[iy1 * wu + ix],
            z[iy1 * wu + ix1],
        ]
    }

    /// Whether surface point `(px, py, pz)` sees unit direction `w` (which must have `w.z > 0`).
    pub fn visible(&self, px: f64, py: f64, pz: f64, w: Vec3) -> bool {
        self.visible_dir(px, py, pz, &self.direction(w))
    }

    /// [`Visibility::visible`] towards a prepared direction.
    pub fn visible_dir(&self, px: f64, py: f64, pz: f64, dir: &Direction) -> bool {
        match &dir.along {
            // Straight up: nothing on a heightfield is above the zenith ray.
            None => dir.w.z > 0.0,
            // No facet rises along the azimuth faster than the ray: from a point on the surface
            // (or above it) the surface stays under the ray (rising at most `rise · s + (h(p) -
            // pz)`, short of `m · s` plus the height tolerance an occluder must clear). Near
            // the zenith, on gentle reliefs, no point is shadowed and none is traced.
            Some(al)
                if al.rise <= al.m && pz >= self.hf.surface_height(px, py) - 0.5 * self.htol =>
            {
                true
            }
            Some(al) => self.visible_traced(px, py, pz, al),
        }
    }

    /// [`Visibility::visible_dir`] by tracing the ray: a scan of its breakpoints when it is
    /// short, else a walk.
    fn visible_traced(&self, px: f64, py: f64, pz: f64, al: &Along) -> bool {
        match self.shadowed_short(px, py, pz, &al.fwd, al.m) {
            Some(s) => !s,
            None => !self.march(px, py, pz, &al.fwd, al.m, al.m, &[]).1,
        }
    }

    /// The shadow test of [`Visibility::visible_dir`] for a short ray, without a walk
    /// ([`Breaks`]): occluded iff a breakpoint up to the distance where the ray clears the
    /// highest point rises above it by more than the height tolerance (and above the walk's
    /// starting slope `mm`, which differs from `m` only beyond 89.99994°). Whether one does
    /// not depend on the order in which they are visited. `None` (take the walk) when the ray
    /// is long (there the walk's block skipping pays).
    #[inline]
    fn shadowed_short(&self, px: f64, py: f64, pz: f64, az: &Azimuth, m: f64) -> Option<bool> {
        /// Breakpoints beyond which the walk is used.
        const MAX_BREAKS: i64 = 48;
        let mm = m.max(MIN_SLOPE);
        let headroom = self.zmax - pz;
        if headroom <= 0.0 {
            return Some(false);
        }
        // No breakpoint beyond `headroom / mm` rises above `mm s`.
        let br = Breaks::new(self, px, py, az, headroom / mm, MAX_BREAKS)?;
        let htol = self.htol;
        let occludes = |(s, h): (f64, f64)| {
            let rise = h - pz;
            s > MIN_RUN && rise > mm * s && rise > m * s + htol
        };
        let found = (0..br.n[0]).any(|i| occludes(br.at::<0>(i)))
            || (0..br.n[1]).any(|i| occludes(br.at::<1>(i)))
            || (0..br.n[2]).any(|i| occludes(br.at::<2>(i)));
        Some(found)
    }

    /// The first hit of [`Visibility::first_hit_dir`] without a walk ([`Breaks`]), from the
    /// start `(qx, qy)` at height `zmax` (below the surface there: `g0 < 0`) along the back
    /// azimuth `az`: the first breakpoint where the ray is at or below the surface, over the
    /// three families, and the last breakpoint before it (or the start), between which the ray
    /// crosses one facet. `None` (take the walk) when the descent is long.
    fn first_hit_short(
        &self,
        qx: f64,
        qy: f64,
        g0: f64,
        az: &Azimuth,
        m: f64,
    ) -> Option<((f64, f64), (f64, f64))> {
        const MAX_BREAKS: i64 = 512;
        let zs = self.zmax;
        // Below the lowest point by then; one more crossing of each axis brings its breakpoint.
        let s_lim = (zs - self.zmin) / m + az.step_x.min(az.step_y);
        let br = Breaks::new(self, qx, qy, az, s_lim, MAX_BREAKS)?;
        let g_at = |(s, h): (f64, f64)| (s, h - (zs - m * s));
        // Each family's first breakpoint at or below the surface, up to the best so far.
        let mut hit = (f64::INFINITY, 0.0);
        let mut scan = |n: i64, at: &dyn Fn(i64) -> (f64, f64)| {
            for i in 0..n {
                let (s, g) = g_at(at(i));
                if s >= hit.0 {
                    break;
                }
                if g >= 0.0 {
                    hit = (s, g);
                    break;
                }
            }
        };
        scan(br.n[0], &|i| br.at::<0>(i));
        scan(br.n[1], &|i| br.at::<1>(i));
        scan(br.n[2], &|i| br.at::<2>(i));
        if !hit.0.is_finite() {
            return None;
        }
        // The breakpoint before it: the latest of each family's last one before it.
        let mut prev = (0.0, g0);
        for (s, g) in [
            br.before::<0>(hit.0).map(|i| g_at(br.at::<0>(i))),
            br.before::<1>(hit.0).map(|i| g_at(br.at::<1>(i))),
            br.before::<2>(hit.0).map(|i| g_at(br.at::<2>(i))),
        ]
        .into_iter()
        .flatten()
        {
            if s > prev.0 {
                prev = (s, g);
            }
        }
        Some((prev, hit))
    }
}

/// How far before the lowest ray's own hit (in units of the grid) a line sweep starts
/// ([`Visibility::seen_facets`]): a few breakpoints, so that rounding in where the walk and the
/// sweep put the hit cannot start the sweep past it.
const SWEEP_LEAD: f64 = 2.0;

/// Base-plane origins `(u, v)` of about `rays` view rays over one `w × h` period: one per
/// `step × step` block of cells, jittered by two irrational sequences so rows and columns do not
/// line up with grooves. The compact BVNDF and the library's binned BVNDF sample views with it.
pub fn ray_lattice(w: usize, h: usize, rays: usize) -> Vec<(f64, f64)> {
    let step = (((w * h) as f64 / rays.max(1) as f64).sqrt().round() as usize).max(1);
    let (nx, ny) = (w.div_ceil(step), h.div_ceil(step));
    let jitter = |k: usize, g: f64| (0.5 + k as f64 * g).fract();
    let mut out = Vec::with_capacity(nx * ny);
    for j in 0..ny {
        for i in 0..nx {
            out.push((
                (i as f64 + jitter(j, 0.618_033_988_749_895)) * step as f64,
                (j as f64 + jitter(i, 0.414_213_562_373_095)) * step as f64,
            ));
        }
    }
    out
}

/// Where [`Visibility::seen_facets`] puts its rays' crossings of `z = 0` for a view of unit
/// horizontal direction `(dx, dy)`: `lines` parallel lines along that azimuth, through
/// `(x_i, 0)` (or `(0, y_i)` when the azimuth is nearer the x axis), each with `per_line`
/// crossings `(x_i, 0) + s_k (dx, dy)`, `0 <= s_k < len`. Sheared along the view, one period
/// is still one period: every point of the torus is `(x, 0) + s (dx, dy)` for exactly one
/// `x` in `[0, W)` and `s` in `[0, H / |dy|)`, so the crossings are uniform over it (stratified
/// across and along the lines, each line and each crossing jittered within its stratum by
/// irrational offsets).
#[derive(Debug, Clone, Copy)]
pub(crate) struct LineRays {
    pub lines: usize,
    pub per_line: usize,
    /// `true`: lines through `(x_i, 0)`, `x_i = (i + j_i) W / lines`; `false`: `(0, y_i)`.
    by_x: bool,
    /// The span of one line's crossings, `H / |dy|` (or `W / |dx|`).
    len: f64,
    /// The spacing of the lines along their axis.
    gap: f64,
}

impl LineRays {
    /// About `rays` crossings for a view along `(dx, dy)` on a `w × h` period, about as far
    /// apart across the lines as along them.
    pub(crate) fn new(w: usize, h: usize, dx: f64, dy: f64, rays: usize) -> Self {
        let (w, h) = (w as f64, h as f64);
        let by_x = dy.abs() >= dx.abs();
        let (across, along, d) = if by_x {
            (w, h, dy.abs())
        } else {
            (h, w, dx.abs())
        };
        // Lines `across / lines` apart along their axis are `d · across / lines` apart.
        let lines = ((rays as f64 * across * d * d / along).sqrt().round() as usize).max(1);
        let per_line = rays.div_ceil(lines).max(1);
        LineRays {
            lines,
            per_line,
            by_x,
            len: along / d,
            gap: across / lines as f64,
        }
    }

    pub(crate) fn count(&self) -> usize {
        self.lines * self.per_line
    }

    /// Line `i`'s point at `s = 0`.
    fn base(&self, i: usize) -> (f64, f64) {
        // Jittered within its stratum by an irrational offset: a line through the lattice's
        // vertices along an axis or a diagonal would run on facets' edges.
        let c = (i as f64 + ((i + 1) as f64 * 0.414_213_562_373_095).fract()) * self.gap;
        if self.by_x {
            (c, 0.0)
        } else {
            (0.0, c)
        }
    }

    /// Crossing `k` of line `i` for the view azimuth `(dx, dy)`.
    pub(crate) fn crossing(&self, i: usize, k: usize, dx: f64, dy: f64) -> (f64, f64) {
        let (bx, by) = self.base(i);
        let s = self.s(i, k);
        (bx + s * dx, by + s * dy)
    }

    /// Crossing `k` of line `i`: its distance along the line.
    fn s(&self, i: usize, k: usize) -> f64 {
        // Each crossing jittered within its stratum by the R2 sequence (irrational offsets): a
        // whole line at one offset samples every cell it crosses at the same place and aliases
        // with the lattice (on fBm at 4096 rays, the seen mean normal 3-4× as far off).
        let jitter = (0.5 + (i + 1) as f64 * R2.0 + (k + 1) as f64 * R2.1).fract();
        (k as f64 + jitter) * self.len / self.per_line as f64
    }
}

impl Visibility<'_> {
    /// The facet first hit by each of about `rays` parallel rays from `dir` (`w.z > 0`), their
    /// crossings of `z = 0` uniform over one period ([`LineRays`]): calls `hit(facet)` once per
    /// ray and returns the number of rays. The rays of one line of crossings lie in one
    /// vertical plane, and ray `k` (crossing at `s_k`, rising `m` per unit towards the view)
    /// first meets the surface at the largest `s` where `h(s) >= m (s - s_k)`: the later the
    /// crossing, the farther the hit. So one sweep down each line's profile, breakpoint by
    /// breakpoint ([`Breaks`], its three families merged), resolves all of its rays in order,
    /// where a ray each would walk its own descent: at grazing views on tall surfaces the
    /// descents are hundreds of cells long and overlap. The sweep starts just before the hit
    /// of the line's first ray to land, found by that ray's own walk, which skips the blocks it
    /// passes above: no ray meets the surface before it. The hits are those of
    /// [`Visibility::first_hit_dir`] from the same crossings (test
    /// `line_sweeps_hit_the_facets_of_single_rays`). At the zenith the rays are cast one by
    /// one. Grids of any size are swept (those that are not a power of two wrap by integer
    /// division; a 100² map used to cast singly, and built 7× slower than a 128² one).
    pub fn seen_facets(&self, dir: &Direction, rays: usize, mut hit: impl FnMut(usize)) -> usize {
        self.seen_facets_by_ray(dir, rays, |_, _, f, _| hit(f))
    }

    /// [`Visibility::seen_facets`], telling which ray hit where: `hit(line, k, facet, point)`
    /// for crossing `k` of line `line` ([`LineRays::crossing`]; at the zenith, `line` 0 and `k`
    /// the index in [`ray_lattice`]), `point` unwrapped along the sweep.
    pub(crate) fn seen_facets_by_ray(
        &self,
        dir: &Direction,
        rays: usize,
        mut hit: impl FnMut(usize, usize, usize, Vec3),
    ) -> usize {
        let Some(al) = &dir.along else {
            let origins = ray_lattice(self.w as usize, self.h as usize, rays);
            for (k, &(u, v)) in origins.iter().enumerate() {
                hit(
                    0,
                    k,
                    self.facet_at(u, v),
                    Vec3::new(u, v, self.hf.surface_height(u, v)),
                );
            }
            return origins.len();
        };
        let lr = LineRays::new(self.w as usize, self.h as usize, al.dx, al.dy, rays);
        let m = al.m.max(MIN_SLOPE);
        let (zmax, zmin) = (self.zmax, self.zmin);
        for i in 0..lr.lines {
            let (bx, by) = lr.base(i);
            let crossing = |k: usize| lr.crossing(i, k, al.dx, al.dy);
            // The sweep goes back along the line (direction -d) from where the last ray is at
            // zmax to where the first ray is below zmin. The last ray is the lowest and lands
            // first: before its hit no ray meets the surface, and a sweep from zmax would pass
            // every breakpoint of its descent, `(zmax - z) / m` long, for nothing (4 to 7 times
            // the rest of the sweep's breakpoints on tall bumps, fBm and pyramids,
            // docs/forward-model.md). Its own walk skips the blocks it passes above, so the sweep
            // starts a little before that hit, taken back into the period.
            let s_last = lr.s(i, lr.per_line - 1);
            let (ul, vl) = crossing(lr.per_line - 1);
            let (land, _) = self.first_hit_dir(ul, vl, dir);
            let r0 = ((zmax - land.z) / m - SWEEP_LEAD).max(0.0);
            let s_top = s_last + zmax / m - r0;
            let span = s_top - (lr.s(i, 0) + zmin / m);
            let (px, py) = (
                (bx + s_top * al.dx).rem_euclid(self.w as f64),
                (by + s_top * al.dy).rem_euclid(self.h as f64),
            );
            let Some(br) = Breaks::new(self, px, py, &al.back, span, i64::MAX) else {
                for k in 0..lr.per_line {
                    let (u, v) = crossing(k);
                    let (p, f) = self.first_hit_dir(u, v, dir);
                    hit(i, k, f, p);
                }
                continue;
            };
            // Ray k's height at distance r of the sweep: m (s_top - r - s_k), for s_k = lr.s(i, k)
            // (kept for the next ray down, `s_next`, as the sweep compares it at every
            // breakpoint).
            let mut k = lr.per_line;
            let ray_z = |s_k: f64, r: f64| m * (s_top - r - s_k);
            let mut s_next = lr.s(i, k - 1);
            let mut prev = (0.0, self.hf.surface_height(px, py));
            let mut idx = [0i64; 3];
            let at = |f: usize, j: i64| -> (f64, f64) {
                if j >= br.n[f] {
                    return (f64::INFINITY, 0.0);
                }
                match f {
                    0 => br.at::<0>(j),
                    1 => br.at::<1>(j),
                    _ => br.at::<2>(j),
                }
            };
            let mut next = [at(0, 0), at(1, 0), at(2, 0)];
            // On a line that repeats after `period` (the grid axes and diagonals), once a whole
            // period has been swept its highest point is known, and while the lowest ray left is
            // a whole period's descent or more above it, whole periods are skipped: along a gap
            // between tall bumps, or along a groove, rays would otherwise sweep their whole
            // descent, `relief / m` cells (the time grew with the height: a 16² field of bumps
            // 1e4 high took 35 s, and one 1e6 high minutes). Each family has a whole number of
            // breakpoints per period, so the sweep resumes at the same breakpoints, a whole
            // number of periods on.
            let period = Some(al.back.period).filter(|l| l.is_finite() && *l > 0.0);
            let per_period = period.map(|l| {
                let mut c = [0i64; 3];
                for (f, c) in c.iter_mut().enumerate() {
                    if br.n[f] > 0 {
                        *c = (l / br.step[f]).round() as i64;
                    }
                }
                c
            });
            let mut line_max = prev.1;
            let mut swept_period = false;
            while k > 0 {
                let f = if next[0].0 <= next[1].0 {
                    if next[0].0 <= next[2].0 {
                        0
                    } else {
                        2
                    }
                } else if next[1].0 <= next[2].0 {
                    1
                } else {
                    2
                };
                let last = next[f].0 > span;
                let cur = if last {
                    // The end of the span, past the last breakpoint: every ray is below zmin.
                    let r = span.max(prev.0);
                    (r, self.hf.surface_height(px - r * al.dx, py - r * al.dy))
                } else {
                    idx[f] += 1;
                    let c = next[f];
                    next[f] = at(f, idx[f]);
                    c
                };
                // Every ray whose height the surface reaches in this segment (one facet).
                let mid = 0.5 * (prev.0 + cur.0);
                let mut facet = None;
                while k > 0 && (prev.1 >= ray_z(s_next, prev.0) || cur.1 >= ray_z(s_next, cur.0)) {
                    k -= 1;
                    let s_k = s_next;
                    if k > 0 {
                        s_next = lr.s(i, k - 1);
                    }
                    let f = *facet
                        .get_or_insert_with(|| self.facet_at(px - mid * al.dx, py - mid * al.dy));
                    let (g0, g1) = (prev.1 - ray_z(s_k, prev.0), cur.1 - ray_z(s_k, cur.0));
                    let r = if g0 >= 0.0 {
                        prev.0
                    } else {
                        prev.0 + (cur.0 - prev.0) * (-g0 / (g1 - g0)).clamp(0.0, 1.0)
                    };
                    hit(
                        i,
                        k,
                        f,
                        Vec3::new(px - r * al.dx, py - r * al.dy, ray_z(s_k, r)),
                    );
                }
                if last {
                    // Rays left by rounding at the span's end (none expected): one by one.
                    for j in 0..k {
                        let (u, v) = crossing(j);
                        let (p, f) = self.first_hit_dir(u, v, dir);
                        hit(i, j, f, p);
                    }
                    break;
                }
                if let (Some(l), Some(per)) = (period, per_period) {
                    if !swept_period {
                        line_max = line_max.max(cur.1);
                        swept_period = cur.0 > l;
                    } else if k > 0 {
                        let n = ((ray_z(s_next, cur.0) - line_max) / (m * l)).floor();
                        if (1.0..1e15).contains(&n) {
                            for f in 0..3 {
                                idx[f] += n as i64 * per[f];
                                next[f] = at(f, idx[f]);
                            }
                            prev = (cur.0 + n * l, cur.1);
                            continue;
                        }
                    }
                }
                prev = cur;
            }
        }
        lr.count()
    }
}

/// The breakpoints of the horizontal half-line `p + s d`, `0 < s <= s_lim`, without a walk.
/// The surface height along the line is linear between the line's crossings of three families
/// of lines: `x = k`, `y = k` and the cells' diagonals `x - y = k` (family 0, 1, 2). Each family's
/// crossings are an arithmetic sequence in `s`, and the height at each is interpolated along
/// one triangle edge (a vertical, horizontal or diagonal edge), so a breakpoint costs a few
/// operations and no branch, where a walk's next cell, triangle and diagonal are each a coin
/// toss for the branch predictor. For the short rays that most tests cast.
struct Breaks<'a> {
    z: &'a [f64],
    /// The grid's size and its power-of-two masks ([`wrap`]).
    w: i64,
    h: i64,
    wmask: i64,
    hmask: i64,
    px: f64,
    py: f64,
    dx: f64,
    dy: f64,
    /// Per family: the first integer crossed, its direction (±1), the distance between
    /// crossings, the coordinate at `s = 0` (`px`, `py`, `px - py`), and the count.
    k0: [f64; 3],
    sg: [f64; 3],
    step: [f64; 3],
    c: [f64; 3],
    n: [i64; 3],
}

impl<'a> Breaks<'a> {
    /// `None` when there are more than `max` breakpoints.
    #[inline]
    fn new(
        vis: &'a Visibility,
        px: f64,
        py: f64,
        az: &Azimuth,
        s_lim: f64,
        max: i64,
    ) -> Option<Self> {
        if !s_lim.is_finite() {
            return None;
        }
        let (dx, dy) = (az.dx, az.dy);
        let du = if az.inv_dd == 0.0 { 0.0 } else { dx - dy };
        let c = [px, py, px - py];
        let dc = [dx, dy, du];
        let step = [az.step_x, az.step_y, az.inv_dd.abs()];
        let (mut k0, mut sg, mut n) = ([0.0; 3], [0.0; 3], [0i64; 3]);
        for f in 0..3 {
            let end = c[f] + s_lim * dc[f];
            if dc[f] > 0.0 {
                let k = ifloor(c[f]) + 1;
                (k0[f], sg[f], n[f]) = (k as f64, 1.0, (ifloor(end) - k + 1).max(0));
            } else if dc[f] < 0.0 {
                let k = -ifloor(-c[f]) - 1;
                (k0[f], sg[f], n[f]) = (k as f64, -1.0, (k + ifloor(-end) + 1).max(0));
            }
        }
        if n[0] + n[1] + n[2] > max {
            return None;
        }
        Some(Breaks {
            z: vis.hf.samples(),
            w: vis.w,
            h: vis.h,
            wmask: pow2_mask(vis.w),
            hmask: pow2_mask(vis.h),
            px,
            py,
            dx,
            dy,
            k0,
            sg,
            step,
            c,
            n,
        })
    }

    /// The heights at `(ix, iy)` and at the next sample along `(ex, ey)` (one step along x, y
    /// or the diagonal), each index wrapped once ([`wrap`]: a mask on power-of-two grids, an
    /// integer division otherwise).
    #[inline]
    fn z2(&self, ix: i64, iy: i64, ex: bool, ey: bool) -> (f64, f64) {
        let w = self.w as usize;
        if (self.wmask | self.hmask) >= 0 {
            // Both masks: the libraries' grids, where this is most of a scan's work.
            let at = |x: i64, y: i64| ((y & self.hmask) as usize) * w + (x & self.wmask) as usize;
            return (
                self.z[at(ix, iy)],
                self.z[at(ix + ex as i64, iy + ey as i64)],
            );
        }
        self.z2_divided(ix, iy, ex, ey)
    }

    /// [`Breaks::z2`] on a grid that is not a power of two, out of line: inlined, its integer
    /// divisions slowed the power-of-two scans by about 13 % (one core, `bench library-speed`).
    #[inline(never)]
    fn z2_divided(&self, ix: i64, iy: i64, ex: bool, ey: bool) -> (f64, f64) {
        let w = self.w as usize;
        let (x0, y0) = (wrap(ix, self.w, self.wmask), wrap(iy, self.h, self.hmask));
        let next = |i: i64, n: i64| if i + 1 == n { 0 } else { i + 1 };
        let x1 = if ex { next(x0, self.w) } else { x0 };
        let y1 = if ey { next(y0, self.h) } else { y0 };
        (
            self.z[y0 as usize * w + x0 as usize],
            self.z[y1 as usize * w + x1 as usize],
        )
    }

    /// Breakpoint `i` of family `F`: its distance and the surface height there.
    #[inline]
    fn at<const F: usize>(&self, i: i64) -> (f64, f64) {
        let k = self.k0[F] + self.sg[F] * i as f64;
        let s = (k - self.c[F]) * self.sg[F] * self.step[F];
        let k = k as i64;
        let h = match F {
            0 => {
                let y = self.py + s * self.dy;
                let j = ifloor(y);
                let (a, b) = self.z2(k, j, false, true);
                a + (b - a) * (y - j as f64)
            }
            1 => {
                let x = self.px + s * self.dx;
                let j = ifloor(x);
                let (a, b) = self.z2(j, k, true, false);
                a + (b - a) * (x - j as f64)
            }
            _ => {
                let x = self.px + s * self.dx;
                let ix = ifloor(x);
                let (a, b) = self.z2(ix, ix - k, true, true);
                a + (b - a) * (x - ix as f64)
            }
        };
        (s, h)
    }

    /// The last breakpoint of family `F` before distance `s`, if any.
    #[inline]
    fn before<const F: usize>(&self, s: f64) -> Option<i64> {
        if self.n[F] == 0 {
            return None;
        }
        let s0 = (self.k0[F] - self.c[F]) * self.sg[F] * self.step[F];
        let mut i = (((s - s0) / self.step[F]).ceil() as i64 - 1).clamp(-1, self.n[F] - 1);
        // Rounding of the estimate: settle it on the breakpoints' own distances.
        while i >= 0 && self.at::<F>(i).0 >= s {
            i -= 1;
        }
        while i + 1 < self.n[F] && self.at::<F>(i + 1).0 < s {
            i += 1;
        }
        (i >= 0).then_some(i)
    }
}

/// A walk through the grid cells crossed by the horizontal half-line `p + s d`, `s >= 0`, with
/// unwrapped cell coordinates (for positions) and wrapped indices (for heights): a 2-D DDA.
struct CellWalk {
    px: f64,
    py: f64,
    dx: f64,
    dy: f64,
    w: i64,
    h: i64,
    /// Power-of-two masks of `w` and `h` ([`wrap`]).
    wmask: i64,
    hmask: i64,
    /// Unwrapped lower-left corner of the current cell.
    cx: f64,
    cy: f64,
    /// The same corner as integers (kept beside the floats: a block is found per cell, and
    /// converting the floats each time costs more than the cell's own test).
    ucx: i64,
    ucy: i64,
    /// The walk's cell steps along x and y (+1 or -1).
    sx: i64,
    sy: i64,
    /// Wrapped cell indices.
    ix: i64,
    iy: i64,
    /// Distances at which the walk crosses the next vertical / horizontal grid line.
    tmax_x: f64,
    tmax_y: f64,
    /// Distance at which the walk entered the current cell.
    s_in: f64,
    /// See [`Azimuth`].
    inv_dd: f64,
    step_x: f64,
    step_y: f64,
}

impl CellWalk {
    fn new(px: f64, py: f64, az: &Azimuth, w: i64, h: i64) -> Self {
        let mut c = CellWalk {
            px,
            py,
            dx: az.dx,
            dy: az.dy,
            w,
            h,
            wmask: pow2_mask(w),
            hmask: pow2_mask(h),
            cx: 0.0,
            cy: 0.0,
            ucx: 0,
            ucy: 0,
            sx: if az.dx > 0.0 { 1 } else { -1 },
            sy: if az.dy > 0.0 { 1 } else { -1 },
            ix: 0,
            iy: 0,
            tmax_x: 0.0,
            tmax_y: 0.0,
            s_in: 0.0,
            inv_dd: az.inv_dd,
            step_x: az.step_x,
            step_y: az.step_y,
        };
        c.enter(0.0, 0.0);
        c
    }

    /// Put the walk in the cell containing the point at distance `probe`, entered at `s_in`.
    fn enter(&mut self, probe: f64, s_in: f64) {
        self.cx = floor(self.px + probe * self.dx);
        self.cy = floor(self.py + probe * self.dy);
        self.ucx = self.cx as i64;
        self.ucy = self.cy as i64;
        self.ix = wrap(self.ucx, self.w, self.wmask);
        self.iy = wrap(self.ucy, self.h, self.hmask);
        let next = |c: f64, p: f64, d: f64, step: f64| {
            if d > 0.0 {
                (c + 1.0 - p) * step
            } else if d < 0.0 {
                (p - c) * step
            } else {
                f64::INFINITY
            }
        };
        self.tmax_x = next(self.cx, self.px, self.dx, self.step_x);
        self.tmax_y = next(self.cy, self.py, self.dy, self.step_y);
        self.s_in = s_in;
    }

    /// Restart just past distance `s` (after skipping a block). The nudge past `s` grows with
    /// the coordinates' magnitude, so that it still moves the probe where a rounding unit of
    /// `px + s dx` exceeds 1e-7 (tall surfaces marched far at grazing angles).
    fn restart(&mut self, s: f64) {
        let scale = s.abs() + self.px.abs() + self.py.abs();
        self.enter(s + 1e-7f64.max(8.0 * f64::EPSILON * scale), s);
    }

    #[inline]
    fn s_exit(&self) -> f64 {
        self.tmax_x.min(self.tmax_y)
    }

    /// Local coordinates in the current cell of the point at distance `s`, clamped to `[0, 1]`.
    #[inline]
    fn local(&self, s: f64) -> (f64, f64) {
        (
            (self.px + s * self.dx - self.cx).clamp(0.0, 1.0),
            (self.py + s * self.dy - self.cy).clamp(0.0, 1.0),
        )
    }

    /// Surface height at distance `s` inside the current cell with corners `c`.
    #[inline]
    fn height_at(&self, s: f64, c: &[f64; 4]) -> f64 {
        let (fx, fy) = self.local(s);
        let [z00, z10, z01, z11] = *c;
        if fx >= fy {
            z00 + (z10 - z00) * fx + (z11 - z10) * fy
        } else {
            z00 + (z11 - z01) * fx + (z01 - z00) * fy
        }
    }

    /// Where the walk crosses the current cell's diagonal `(x - cx) = (y - cy)`, if inside it.
    #[inline]
    fn diagonal_crossing(&self) -> Option<f64> {
        if self.inv_dd == 0.0 {
            return None;
        }
        let sd = ((self.py - self.cy) - (self.px - self.cx)) * self.inv_dd;
        (sd >= self.s_in && sd < self.s_exit()).then_some(sd)
    }

    #[inline]
    fn step(&mut self) {
        self.s_in = self.s_exit();
        if self.tmax_x < self.tmax_y {
            let sx = self.sx;
            self.tmax_x += self.step_x;
            self.cx += sx as f64;
            self.ucx += sx;
            self.ix += sx;
            if self.ix == self.w {
                self.ix = 0;
            } else if self.ix < 0 {
                self.ix = self.w - 1;
            }
        } else {
            let sy = self.sy;
            self.tmax_y += self.step_y;
            self.cy += sy as f64;
            self.ucy += sy;
            self.iy += sy;
            if self.iy == self.h {
                self.iy = 0;
            } else if self.iy < 0 {
                self.iy = self.h - 1;
            }
        }
    }

    /// Unwrapped block of side `2^shift` holding the current cell.
    #[inline]
    fn block(&self, shift: u32) -> (i64, i64) {
        (self.ucx >> shift, self.ucy >> shift)
    }

    /// Distance at which the walk leaves block `(bx, by)` of side `bs` (multiplied by the
    /// prepared `1 / |d|` rather than divided: a march skips more blocks than it walks cells).
    fn block_exit(&self, bs: i64, (bx, by): (i64, i64)) -> f64 {
        let edge = |p: f64, d: f64, step: f64, b: i64| {
            if d > 0.0 {
                (((b + 1) * bs) as f64 - p) * step
            } else if d < 0.0 {
                (p - (b * bs) as f64) * step
            } else {
                f64::INFINITY
            }
        };
        edge(self.px, self.dx, self.step_x, bx).min(edge(self.py, self.dy, self.step_y, by))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::dir_from_deg;

    /// Every kind of relief the libraries hold, at sizes the tests trace quickly.
    const RELIEFS: [&str; 6] = [
        "vgroove:n=32,period=16,depth=8",
        "bumps:n=64,count=5,radius=9,height=4,seed=2",
        "bricks:n=64,length=32,height=16,mortar=3,depth=4",
        "fbm:n=64,cells=4,octaves=5,persistence=0.6,lacunarity=2,amplitude=3,seed=5",
        "weave:n=64,period=16,height=2",
        "pyramids:n=64,period=16,height=6",
    ];

    /// Test azimuth `i` in degrees: every `every`-th one along an axis or a diagonal (in turn),
    /// whose lines repeat, the others drawn from `r`.
    fn azimuth_deg(i: usize, every: usize, r: &mut crate::rng::Rng) -> f64 {
        if i.is_multiple_of(every) {
            45.0 * (i / every % 8) as f64
        } else {
            r.range(0.0, 360.0)
        }
    }

    fn relief(spec: &str) -> Heightfield {
        crate::generators::parse_generator(spec)
            .unwrap()
            .build()
            .unwrap()
    }

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
    fn brute_horizon(
        hf: &Heightfield,
        px: f64,
        py: f64,
        pz: f64,
        dx: f64,
        dy: f64,
        s_max: f64,
    ) -> f64 {
        let mut ss = Vec::new();
        let mut add = |p0: f64, d: f64| {
            if d.abs() < 1e-12 {
                return;
            }
            let (lo, hi) = if d > 0.0 {
                (p0, p0 + s_max * d)
            } else {
                (p0 + s_max * d, p0)
            };
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
    fn horizon_levels_count_as_the_exact_horizon() {
        // The compact BVNDF's question: how many polar nodes' slopes are at or above the
        // horizon. `horizon_level` must answer it as the exact horizon does, on rough ground and
        // on flat ground with spikes (long marches, skipped blocks).
        let mut r = crate::rng::Rng::new(11);
        let levels = [0.026, 0.044, 0.096, 0.185, 0.315, 0.6, 1.2, 3.0];
        let count = |h: f64| levels.iter().filter(|&&l| l >= h).count();
        for &(n, spiky) in &[(16usize, false), (32, true), (13, false)] {
            let z: Vec<f64> = (0..n * n)
                .map(|_| {
                    if !spiky || r.range(0.0, 1.0) < 0.03 {
                        r.range(0.0, 3.0)
                    } else {
                        0.0
                    }
                })
                .collect();
            let hf = Heightfield::new(n, n, z, 1.0, "rand").unwrap();
            let v = Visibility::new(&hf);
            for i in 0..600 {
                let (px, py) = (r.range(0.0, n as f64), r.range(0.0, n as f64));
                let pz = hf.surface_height(px, py);
                let phi = if i % 3 == 0 {
                    std::f64::consts::FRAC_PI_4 * (i % 8) as f64
                } else {
                    r.range(0.0, std::f64::consts::TAU)
                };
                let az = v.azimuth(phi.cos(), phi.sin());
                // From the lowest level up, as the build asks (floor: the column's own node).
                let from = i % levels.len();
                let got = v.horizon_level(px, py, pz, &az, &levels[from..]);
                let exact = v.horizon_along(px, py, pz, &az, levels[from], f64::INFINITY);
                assert_eq!(
                    count(got),
                    count(exact),
                    "n {n} p ({px},{py},{pz}) phi {phi} levels from {from}: {got} vs {exact}"
                );
            }
        }
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
                assert!(
                    (got - want).abs() < 1e-9 * (1.0 + want.abs()),
                    "n {n} p ({px},{py}) phi {phi}: {got} vs {want}"
                );
            }
        }
    }

    #[test]
    fn axis_azimuths_with_rounding_noise_end_and_match_the_exact_axis() {
        // (cos 270°, sin 270°) = (-1.8e-16, -1): from a vertex, a block skip used to restart the
        // walk in the cell it had just left, for ever.
        let hf = relief("bumps:n=64,count=4,radius=8,height=6,seed=3");
        let v = Visibility::new(&hf);
        for deg in [90.0f64, 180.0, 270.0] {
            let (dx, dy) = (deg.to_radians().cos(), deg.to_radians().sin());
            let (ex, ey) = (dx.round(), dy.round());
            for y in 0..64 {
                for x in 0..64 {
                    let (px, py, pz) = (x as f64, y as f64, hf.at(x, y));
                    let a = v.horizon(px, py, pz, dx, dy, 0.026, f64::INFINITY);
                    let b = v.horizon(px, py, pz, ex, ey, 0.026, f64::INFINITY);
                    assert!((a - b).abs() < 1e-9, "{deg}° at ({x}, {y}): {a} vs {b}");
                    let w = Vec3::new(-0.05 * dx, -0.05 * dy, 1.0).normalized();
                    let (p, _) = v.first_hit(px, py, w);
                    assert!(p.z.is_finite());
                }
            }
        }
    }

    #[test]
    fn line_sweeps_hit_the_facets_of_single_rays() {
        // Every ray of a line sweep against its own first hit, on the reliefs of the test
        // below, a tall fBm and two taller reliefs, from the zenith to 88.5°, along the axes
        // and diagonals too:
        // the same facet, but for a hit within 1e-9 of the facet's edge.
        let mut r = crate::rng::Rng::new(23);
        for spec in [
            "vgroove:n=32,period=16,depth=8",
            "bumps:n=64,count=5,radius=9,height=4,seed=2",
            "bricks:n=64,length=32,height=16,mortar=3,depth=4",
            "fbm:n=64,amplitude=16,seed=5",
            "weave:n=64,period=16,height=2",
            "pyramids:n=64,period=16,height=6",
            // Not a power of two (indices wrapped by integer division), flat and tall.
            "bumps:n=48,count=5,radius=9,height=4,seed=2",
            "vgroove:n=48,period=16,depth=300",
            // Tall: the sweeps along the axes and diagonals skip whole periods (a groove
            // seen along its length, the gaps between bumps).
            "vgroove:n=32,period=16,depth=3000",
            "bumps:n=32,count=3,radius=5,height=800,seed=2",
        ] {
            let hf = relief(spec);
            let v = Visibility::new(&hf);
            let (mut rays, mut edge) = (0, 0);
            for i in 0..40 {
                let phi = if i % 3 == 0 {
                    45.0 * (i / 3 % 8) as f64
                } else {
                    r.range(0.0, 360.0)
                };
                let theta = [0.0, 30.0, 70.0, 85.0, 88.5][i % 5];
                let dir = v.direction(crate::frame::dir_from_deg(theta, phi));
                let n = v.seen_facets_by_ray(&dir, 512, |line, k, f, p| {
                    let (u, w) = match &dir.along {
                        Some(al) => LineRays::new(hf.width(), hf.height(), al.dx, al.dy, 512)
                            .crossing(line, k, al.dx, al.dy),
                        None => ray_lattice(hf.width(), hf.height(), 512)[k],
                    };
                    let (b, fb) = v.first_hit_dir(u, w, &dir);
                    rays += 1;
                    // The sweep's hit is a contact of this ray: on the ray, on the surface
                    // (within rounding), in (or on the edge of) the facet it names.
                    let (pw, ph) = (hf.width() as f64, hf.height() as f64);
                    let on_ray = Vec3::new(u, w, 0.0) + dir.w * (p.z / dir.w.z);
                    let wrap = |d: f64, n: f64| d - n * (d / n).round();
                    let along = wrap(p.x - on_ray.x, pw).hypot(wrap(p.y - on_ray.y, ph));
                    let q = Vec3::new(p.x.rem_euclid(pw), p.y.rem_euclid(ph), p.z);
                    let on_surface = (hf.surface_height(q.x, q.y) - p.z).abs();
                    assert!(
                        along < 1e-6 * (1.0 + p.z.abs()),
                        "{spec}: off the ray by {along}"
                    );
                    assert!(
                        on_surface < 1e-9 * (1.0 + p.z.abs()),
                        "{spec}: {on_surface} off the surface"
                    );
                    let facet = &hf.facets()[f];
                    let (lo, hi) = facet.v.iter().fold(
                        (Vec3::new(1e9, 1e9, 0.0), Vec3::new(-1e9, -1e9, 0.0)),
                        |(lo, hi), c| {
                            (
                                Vec3::new(lo.x.min(c.x), lo.y.min(c.y), 0.0),
                                Vec3::new(hi.x.max(c.x), hi.y.max(c.y), 0.0),
                            )
                        },
                    );
                    let qx = q.x
                        + pw * ((lo.x - q.x) / pw)
                            .ceil()
                            .max(0.0)
                            .min(((hi.x - q.x) / pw).floor().max(0.0));
                    let qy = q.y
                        + ph * ((lo.y - q.y) / ph)
                            .ceil()
                            .max(0.0)
                            .min(((hi.y - q.y) / ph).floor().max(0.0));
                    let tol = 1e-9;
                    assert!(
                        qx >= lo.x - tol
                            && qx <= hi.x + tol
                            && qy >= lo.y - tol
                            && qy <= hi.y + tol,
                        "{spec} theta {theta} phi {phi}: hit {p:?} outside facet {:?}",
                        facet.v
                    );
                    // And the first: the walk's hit is no higher, and where they differ (a
                    // facet's edge, or a ray grazing a ridge at its height) they are rare.
                    // Within rounding, relative to the height as above (a tall groove's hits
                    // lie thousands of units down).
                    assert!(
                        b.z <= p.z + 1e-9 * (1.0 + p.z.abs()),
                        "{spec} theta {theta} phi {phi}: walk {b:?} above sweep {p:?}"
                    );
                    if f != fb {
                        edge += 1;
                    }
                });
                assert!(n > 400, "{spec}: {n} rays");
            }
            assert!(edge * 1000 <= rays, "{spec}: {edge} of {rays} on edges");
        }
    }

    #[test]
    fn gentle_slopes_shadow_nothing_and_the_bound_holds() {
        // The slope bound is at least every facet's rise along the azimuth (equal to the
        // steepest along the 8 azimuths of the table), and where it is under the ray's slope
        // the early answer (lit) is the traced one, for points on the surface and above it.
        let mut r = crate::rng::Rng::new(29);
        let (mut early, mut checked) = (0, 0);
        let gentle = ["sine:n=48,period=12,amplitude=1", "flat:n=16"];
        for spec in RELIEFS.into_iter().chain(gentle) {
            let hf = relief(spec);
            let v = Visibility::new(&hf);
            let facets = hf.facets();
            for i in 0..48 {
                let phi = azimuth_deg(i, 4, &mut r);
                let (dx, dy) = (phi.to_radians().cos(), phi.to_radians().sin());
                let steepest = facets
                    .iter()
                    .map(|f| -(f.n.x * dx + f.n.y * dy) / f.n.z)
                    .fold(f64::NEG_INFINITY, f64::max);
                let bound = v.slope_bound(dx, dy);
                assert!(
                    bound >= steepest - 1e-12,
                    "{spec} at {phi}°: {bound} < {steepest}"
                );
                if i % 4 == 0 {
                    assert!((bound - steepest).abs() <= 1e-12 * (1.0 + steepest.abs()));
                }
                for theta in [10.0, 30.0, 45.0, 60.0, 75.0] {
                    let dir = v.direction(crate::frame::dir_from_deg(theta, phi));
                    let al = dir.along.unwrap();
                    for _ in 0..40 {
                        let (x, y) = (
                            r.range(0.0, hf.width() as f64),
                            r.range(0.0, hf.height() as f64),
                        );
                        let z = hf.surface_height(x, y) + [0.0, 0.0, 1e-3, 0.5][checked % 4];
                        let got = v.visible_dir(x, y, z, &dir);
                        assert_eq!(got, v.visible_traced(x, y, z, &al), "{spec} {theta} {phi}");
                        if al.rise <= al.m {
                            assert!(got);
                            early += 1;
                        }
                        checked += 1;
                    }
                }
            }
        }
        assert!(early > checked / 10, "{early} of {checked}");
    }

    #[test]
    fn breakpoint_scans_answer_as_the_walks() {
        // The short rays' scans (`Breaks`) against the walks, on every kind of relief the
        // libraries hold, from grazing to steep, along the axes and diagonals too: the same
        // shadows, and the same first hits up to rounding (a hit within 1e-9 of a facet's
        // edge may be given to either facet). Also on two grids that are not a power of two,
        // whose scans wrap by integer division.
        let mut r = crate::rng::Rng::new(17);
        let (mut hits, mut shadows, mut short_hits) = (0, 0, 0);
        let odd = [
            "bumps:n=48,count=5,radius=9,height=4,seed=2",
            "pyramids:n=40,period=10,height=5",
        ];
        for spec in RELIEFS.iter().chain(&odd) {
            let hf = relief(spec);
            let v = Visibility::new(&hf);
            let n = hf.width() as f64;
            for i in 0..1500 {
                let phi = if i % 3 == 0 {
                    45.0 * (i / 3 % 8) as f64
                } else {
                    r.range(0.0, 360.0)
                };
                let dir = v.direction(crate::frame::dir_from_deg(r.range(0.0, 85.0), phi));
                let (u, w) = (r.range(0.0, n), r.range(0.0, n));
                let (a, fa) = v.first_hit_with(u, w, &dir, true);
                let (b, fb) = v.first_hit_with(u, w, &dir, false);
                assert!((a - b).norm() < 1e-9, "{spec} {i}: {a:?} vs {b:?}");
                if fa != fb {
                    let f = &hf.facets()[fb];
                    let q = Vec3::new(b.x.rem_euclid(n), b.y.rem_euclid(n), b.z);
                    let on_edge = (0..3).any(|e| {
                        let (p0, p1) = (f.v[e], f.v[(e + 1) % 3]);
                        let t = (q - p0).dot(p1 - p0) / (p1 - p0).dot(p1 - p0);
                        ((p0 + (p1 - p0) * t.clamp(0.0, 1.0)) - q).norm() < 1e-9
                    });
                    assert!(on_edge, "{spec} {i}: facet {fa} vs {fb} at {b:?}");
                }
                hits += 1;
                short_hits += (a == b) as usize;
                // Shadows from the hit and from a random surface point.
                let light = v.direction(crate::frame::dir_from_deg(
                    r.range(0.0, 80.0),
                    if i % 4 == 0 {
                        90.0
                    } else {
                        r.range(0.0, 360.0)
                    },
                ));
                let (x, y) = (r.range(0.0, n), r.range(0.0, n));
                for (px, py, pz) in [(b.x, b.y, b.z), (x, y, hf.surface_height(x, y))] {
                    let al = light.along.unwrap();
                    let walk = !v.march(px, py, pz, &al.fwd, al.m, al.m, &[]).1;
                    assert_eq!(v.visible_dir(px, py, pz, &light), walk, "{spec} {i}");
                    shadows += 1;
                }
            }
        }
        assert_eq!((hits, shadows), (12000, 24000));
        // Most hits agree to the last bit: the two compute the same breakpoints.
        assert!(short_hits > hits / 2, "{short_hits} of {hits}");
    }

    #[test]
    fn first_hit_is_on_the_surface_visible_and_first() {
        let mut r = crate::rng::Rng::new(9);
        for &n in &[16usize, 13, 32] {
            // Random heights, and for n = 32 sparse spikes over flat ground (blocks to skip).
            let z: Vec<f64> = (0..n * n)
                .map(|_| {
                    if n == 32 {
                        if r.range(0.0, 1.0) < 0.03 {
                            r.range(0.0, 3.0)
                        } else {
                            0.0
                        }
                    } else {
                        r.range(0.0, 3.0)
                    }
                })
                .collect();
            let hf = Heightfield::new(n, n, z, 1.0, "rand").unwrap();
            let v = Visibility::new(&hf);
            let facets = hf.facets();
            for i in 0..800 {
                // Half the views along the axes and diagonals, whose lines repeat (the walk
                // jumps whole periods there), some at grazing angles over flat ground.
                let phi = azimuth_deg(i, 2, &mut r);
                let w = crate::frame::dir_from_deg(r.range(0.0, 88.5), phi);
                let (u, vv) = (r.range(0.0, n as f64), r.range(0.0, n as f64));
                let (p, f) = v.first_hit(u, vv, w);
                // on the surface, on its facet's plane
                assert!((p.z - hf.surface_height(p.x, p.y)).abs() < 1e-9, "{p:?}");
                let fa = facets[f];
                let pw = Vec3::new(p.x.rem_euclid(n as f64), p.y.rem_euclid(n as f64), p.z);
                assert!(fa.n.dot(pw - fa.v[0]).abs() < 1e-7, "facet {f} {p:?}");
                // on the ray through (u, v, 0)
                let t = p.z / w.z;
                let base = p - w * t;
                let wrap = |a: f64| (a - u - ((a - u) / n as f64).round() * n as f64).abs();
                assert!(
                    wrap(base.x) < 1e-7
                        && (base.y - vv - ((base.y - vv) / n as f64).round() * n as f64).abs()
                            < 1e-7
                );
                // nothing above the ray before the hit, and the hit sees w
                for k in 1..200 {
                    let q = p + w * (k as f64 * 0.05);
                    assert!(
                        hf.surface_height(q.x, q.y) <= q.z + 1e-9,
                        "occluded before the hit"
                    );
                }
                assert!(v.visible(p.x, p.y, p.z, w));
            }
        }
    }
}
