//! Error-bounded simplification of a tile's top surface: a quadtree of square leaves over the
//! sample grid that keeps every tile border and every leaf border watertight.
//!
//! A leaf of side 1 sample is the full-resolution cell with its two triangles (diagonal from
//! `(x, y)` to `(x+1, y+1)`, as in `docs/conventions.md`). A larger leaf (side `2^k`) is a fan from
//! its centre sample to every used vertex on its border: its four corners and the corners of any
//! smaller neighbouring leaf that lie on its edges (T-junction vertices), so neighbouring leaves
//! share every edge and no crack opens. All vertices are original samples, so heights at vertices
//! are exact.
//!
//! A node becomes a leaf when it lies inside the grid and the fan of its four corners and centre
//! is within the tolerance at every sample it covers; otherwise it splits. Because T-junction
//! vertices change a fan, the error of the final mesh is then **measured** at every sample (each
//! sample interpolated on the triangle that covers it); leaves over the tolerance are split and
//! the mesh rebuilt until none is. The measured maximum is reported.

use super::mesh::TileGrid;
use std::collections::HashSet;

/// A square leaf: corner sample `(x0, y0)` and side in samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Leaf {
    pub x0: usize,
    pub y0: usize,
    pub size: usize,
}

/// Every cell as a leaf (no simplification).
pub fn full_leaves(g: &TileGrid) -> Vec<Leaf> {
    let mut v = Vec::with_capacity(g.nx * g.ny);
    for y0 in 0..g.ny {
        for x0 in 0..g.nx {
            v.push(Leaf { x0, y0, size: 1 });
        }
    }
    v
}

/// Plane `z = a + b x + c y` through three grid points.
fn plane(g: &TileGrid, p: [(usize, usize); 3]) -> Option<(f64, f64, f64)> {
    let q: Vec<(f64, f64, f64)> = p
        .iter()
        .map(|&(x, y)| (x as f64, y as f64, g.z_at(x, y)))
        .collect();
    let (x1, y1, z1) = (q[1].0 - q[0].0, q[1].1 - q[0].1, q[1].2 - q[0].2);
    let (x2, y2, z2) = (q[2].0 - q[0].0, q[2].1 - q[0].1, q[2].2 - q[0].2);
    let det = x1 * y2 - x2 * y1;
    if det.abs() < 1e-12 {
        return None;
    }
    let b = (z1 * y2 - z2 * y1) / det;
    let c = (x1 * z2 - x2 * z1) / det;
    Some((q[0].2 - b * q[0].0 - c * q[0].1, b, c))
}

/// Max error of the 4-triangle fan (corners + centre) of a node, stopping early above `tol`.
fn coarse_error(g: &TileGrid, x0: usize, y0: usize, s: usize, tol: f64) -> f64 {
    let (cx, cy) = (x0 + s / 2, y0 + s / 2);
    let c = [(x0, y0), (x0 + s, y0), (x0 + s, y0 + s), (x0, y0 + s)];
    let mut planes = [(0.0, 0.0, 0.0); 4];
    for k in 0..4 {
        match plane(g, [(cx, cy), c[k], c[(k + 1) % 4]]) {
            Some(p) => planes[k] = p,
            None => return f64::INFINITY,
        }
    }
    let mut worst = 0.0f64;
    for y in y0..=y0 + s {
        for x in x0..=x0 + s {
            let (dx, dy) = (x as i64 - cx as i64, y as i64 - cy as i64);
            // triangles: 0 south (y0 edge), 1 east, 2 north, 3 west
            let k = if dy.abs() >= dx.abs() {
                if dy < 0 {
                    0
                } else {
                    2
                }
            } else if dx > 0 {
                1
            } else {
                3
            };
            let (a, b, cc) = planes[k];
            let e = (g.z_at(x, y) - (a + b * x as f64 + cc * y as f64)).abs();
            if e > worst {
                worst = e;
                if worst > tol {
                    return worst;
                }
            }
        }
    }
    worst
}

fn split(
    g: &TileGrid,
    x0: usize,
    y0: usize,
    s: usize,
    tol: f64,
    forced: &HashSet<Leaf>,
    out: &mut Vec<Leaf>,
) {
    if x0 >= g.nx || y0 >= g.ny {
        return;
    }
    let inside = x0 + s <= g.nx && y0 + s <= g.ny;
    let leaf = Leaf { x0, y0, size: s };
    if inside && (s == 1 || (!forced.contains(&leaf) && coarse_error(g, x0, y0, s, tol) <= tol)) {
        out.push(leaf);
        return;
    }
    let h = s / 2;
    for (dx, dy) in [(0, 0), (h, 0), (0, h), (h, h)] {
        split(g, x0 + dx, y0 + dy, h, tol, forced, out);
    }
}

/// Which grid vertices are corners of some leaf (the only border vertices used).
pub fn corner_mask(g: &TileGrid, leaves: &[Leaf]) -> Vec<bool> {
    let mut m = vec![false; (g.nx + 1) * (g.ny + 1)];
    for l in leaves {
        for (x, y) in [
            (l.x0, l.y0),
            (l.x0 + l.size, l.y0),
            (l.x0 + l.size, l.y0 + l.size),
            (l.x0, l.y0 + l.size),
        ] {
            m[g.idx(x, y)] = true;
        }
    }
    m
}

/// The leaf's border vertices counter-clockwise seen from above, starting at `(x0, y0)`.
pub fn border_loop(g: &TileGrid, l: &Leaf, mask: &[bool]) -> Vec<usize> {
    let (x0, y0, s) = (l.x0, l.y0, l.size);
    let mut v = Vec::new();
    let mut push = |x: usize, y: usize, always: bool| {
        let i = g.idx(x, y);
        if always || mask[i] {
            v.push(i);
        }
    };
    for x in x0..x0 + s {
        push(x, y0, x == x0);
    }
    for y in y0..y0 + s {
        push(x0 + s, y, y == y0);
    }
    for x in (x0 + 1..=x0 + s).rev() {
        push(x, y0 + s, x == x0 + s);
    }
    for y in (y0 + 1..=y0 + s).rev() {
        push(x0, y, y == y0 + s);
    }
    v
}

/// Top triangles of one leaf (grid vertex indices, counter-clockwise seen from above).
pub fn leaf_triangles(g: &TileGrid, l: &Leaf, mask: &[bool], out: &mut Vec<[usize; 3]>) {
    if l.size == 1 {
        let (a, b) = (g.idx(l.x0, l.y0), g.idx(l.x0 + 1, l.y0));
        let (c, d) = (g.idx(l.x0 + 1, l.y0 + 1), g.idx(l.x0, l.y0 + 1));
        out.push([a, b, c]);
        out.push([a, c, d]);
        return;
    }
    let c = g.idx(l.x0 + l.size / 2, l.y0 + l.size / 2);
    let lp = border_loop(g, l, mask);
    for k in 0..lp.len() {
        out.push([c, lp[k], lp[(k + 1) % lp.len()]]);
    }
}

/// Largest |surface − triangle| over the samples covered by `tris` (grid index triangles).
pub fn measured_error(g: &TileGrid, tris: &[[usize; 3]]) -> f64 {
    let mut worst = 0.0f64;
    for t in tris {
        let p: Vec<(usize, usize)> = t.iter().map(|&i| g.coords(i)).collect();
        let Some((a, b, c)) = plane(g, [p[0], p[1], p[2]]) else {
            continue;
        };
        let (xmin, xmax) = (
            p.iter().map(|q| q.0).min().unwrap_or(0),
            p.iter().map(|q| q.0).max().unwrap_or(0),
        );
        let (ymin, ymax) = (
            p.iter().map(|q| q.1).min().unwrap_or(0),
            p.iter().map(|q| q.1).max().unwrap_or(0),
        );
        let f = |q: (usize, usize), r: (usize, usize), x: usize, y: usize| -> i64 {
            (r.0 as i64 - q.0 as i64) * (y as i64 - q.1 as i64)
                - (r.1 as i64 - q.1 as i64) * (x as i64 - q.0 as i64)
        };
        for y in ymin..=ymax {
            for x in xmin..=xmax {
                if f(p[0], p[1], x, y) >= 0 && f(p[1], p[2], x, y) >= 0 && f(p[2], p[0], x, y) >= 0
                {
                    let e = (g.z_at(x, y) - (a + b * x as f64 + c * y as f64)).abs();
                    worst = worst.max(e);
                }
            }
        }
    }
    worst
}

/// Leaves whose mesh is within `tol` mm of every sample (measured), and that measured error.
pub fn leaves_within(g: &TileGrid, tol: f64) -> (Vec<Leaf>, f64) {
    let root = g.nx.max(g.ny).next_power_of_two();
    let mut forced: HashSet<Leaf> = HashSet::new();
    for _ in 0..64 {
        let mut leaves = Vec::new();
        split(g, 0, 0, root, tol, &forced, &mut leaves);
        let mask = corner_mask(g, &leaves);
        let mut worst = 0.0f64;
        let mut bad = 0;
        let mut tris = Vec::new();
        for l in &leaves {
            if l.size == 1 {
                continue;
            }
            tris.clear();
            leaf_triangles(g, l, &mask, &mut tris);
            let e = measured_error(g, &tris);
            if e > tol {
                forced.insert(*l);
                bad += 1;
            }
            worst = worst.max(e);
        }
        if bad == 0 {
            return (leaves, worst);
        }
    }
    (full_leaves(g), 0.0)
}
