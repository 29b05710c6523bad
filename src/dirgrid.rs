//! A grid of directions over the upper hemisphere, with bilinear interpolation weights for any
//! direction: the nodes at which the compact BVNDF is tabulated.
//!
//! Nodes are `(theta_i, phi_j)` with `phi_j = j · 2 pi / n_phi`; theta nodes are denser towards
//! grazing angles, where visibility changes fastest. Between polar nodes the weights are linear in
//! the ray slope `cot(theta)` (linear in `tan(theta)` next to the zenith), in azimuth linear in phi.
//! Directions beyond the last theta node use the last node (their cosines are applied exactly
//! elsewhere).

use crate::frame::{angles_of, dir_from_rad, Vec3};
use std::f64::consts::TAU;

/// The last polar node of the libraries' grids (and of [`DirGrid::new`]).
pub const LAST_THETA_DEG: f64 = 88.5;

/// Polar nodes of a grid to the horizon ([`DirGrid::to`]) beyond the libraries' spacing.
pub const HORIZON_NODES: usize = 3;

#[derive(Debug, Clone, PartialEq)]
pub struct DirGrid {
    /// Polar angles in radians, increasing, starting at 0.
    pub thetas: Vec<f64>,
    pub n_phi: usize,
    /// `tan` of each polar node (the interpolation variable's nodes).
    tans: Vec<f64>,
    /// Every node's direction, node-major (read for every lobe the fast evaluator assembles).
    dirs: Vec<Vec3>,
}

impl DirGrid {
    /// The default grid: 10 polar nodes from 0° to 88.5° and 16 azimuths.
    pub fn standard() -> Self {
        Self::new(10, 16)
    }

    /// `n_theta` polar nodes from 0 to [`LAST_THETA_DEG`], spaced uniformly in `1 - cos`-like
    /// steps that tighten towards the horizon, and `n_phi` azimuths.
    pub fn new(n_theta: usize, n_phi: usize) -> Self {
        Self::to(n_theta, n_phi, LAST_THETA_DEG)
    }

    /// [`DirGrid::new`] with the last polar node at `last_deg` (below 90°). Up to
    /// [`LAST_THETA_DEG`] the spacing is scaled to end there. Beyond it, with at least 5
    /// nodes, the first `n_theta - 3` are those of `DirGrid::new(n_theta - 1, _)` (all of its
    /// nodes but its last two, which its spacing bunches within a fraction of a degree below
    /// 88.5°), and the last [`HORIZON_NODES`] are evenly spaced in the ray slope `cot(theta)`
    /// (the interpolation variable) from the node before them to `last_deg`: views between
    /// 88.5° and the horizon, which see only the tops of the relief, are resolved, and the nodes
    /// below are the same as in a grid of one node fewer to 88.5°.
    pub fn to(n_theta: usize, n_phi: usize, last_deg: f64) -> Self {
        let n_theta = n_theta.max(2);
        let last = last_deg.clamp(1.0, 89.99).to_radians();
        // theta = top · g(u), g(u) = sin(u pi/2)^0.75 spreads nodes towards the horizon.
        let spaced = |n: usize, top: f64| -> Vec<f64> {
            (0..n)
                .map(|i| {
                    let u = i as f64 / (n - 1) as f64;
                    top * (u * std::f64::consts::FRAC_PI_2).sin().powf(0.75)
                })
                .collect()
        };
        let library_last = LAST_THETA_DEG.to_radians();
        let thetas: Vec<f64> = if last <= library_last || n_theta < 2 + HORIZON_NODES {
            spaced(n_theta, last)
        } else {
            let mut t = spaced(n_theta - 1, library_last);
            t.truncate(n_theta - HORIZON_NODES);
            let m0 = 1.0 / t[t.len() - 1].tan();
            let m1 = 1.0 / last.tan();
            for k in 1..=HORIZON_NODES {
                let m = m0 + (m1 - m0) * k as f64 / HORIZON_NODES as f64;
                t.push((1.0 / m).atan());
            }
            t
        };
        let n_phi = n_phi.max(3);
        let phi = |j: usize| j as f64 * TAU / n_phi as f64;
        let dirs = thetas
            .iter()
            .flat_map(|&t| (0..n_phi).map(move |j| dir_from_rad(t, phi(j))))
            .collect();
        DirGrid {
            tans: thetas.iter().map(|t| t.tan()).collect(),
            thetas,
            n_phi,
            dirs,
        }
    }

    pub fn len(&self) -> usize {
        self.thetas.len() * self.n_phi
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Node index of `(theta index, phi index)`.
    #[inline]
    pub fn node(&self, it: usize, jp: usize) -> usize {
        it * self.n_phi + jp
    }

    #[inline]
    pub fn direction(&self, node: usize) -> Vec3 {
        self.dirs[node]
    }

    pub fn phi(&self, jp: usize) -> f64 {
        jp as f64 * TAU / self.n_phi as f64
    }

    /// Up to four `(node, weight)` pairs, weights summing to 1, bilinear in `(theta, phi)`.
    pub fn weights(&self, w: Vec3) -> [(usize, f64); 4] {
        let (theta, phi) = angles_of(w);
        let nt = self.thetas.len();
        let (it, ft) = if theta >= self.thetas[nt - 1] {
            (nt - 2, 1.0)
        } else {
            let mut i = 0;
            while i + 2 < nt && theta >= self.thetas[i + 1] {
                i += 1;
            }
            // Interpolate in the ray slope m = cot(theta), the variable in which visibility is a
            // threshold (a point is visible iff m exceeds its horizon slope), so the visible share
            // of an area is the CDF of its horizon slopes; from the zenith use tan(theta) = 1/m.
            // tan(theta) from the direction itself (theta below the last node here, so w.z > 0).
            let tan_w = (w.x * w.x + w.y * w.y).sqrt() / w.z;
            let t = if i == 0 {
                tan_w / self.tans[1]
            } else {
                let (m0, m1) = (1.0 / self.tans[i], 1.0 / self.tans[i + 1]);
                (m0 - 1.0 / tan_w) / (m0 - m1)
            };
            (i, t.clamp(0.0, 1.0))
        };
        let x = phi / TAU * self.n_phi as f64;
        let xf = crate::fastmath::floor(x);
        let j0 = (xf as usize) % self.n_phi;
        let fp = x - xf;
        let j1 = (j0 + 1) % self.n_phi;
        [
            (self.node(it, j0), (1.0 - ft) * (1.0 - fp)),
            (self.node(it, j1), (1.0 - ft) * fp),
            (self.node(it + 1, j0), ft * (1.0 - fp)),
            (self.node(it + 1, j1), ft * fp),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::dir_from_deg;

    #[test]
    fn weights_reproduce_nodes_and_sum_to_one() {
        let g = DirGrid::standard();
        for node in 0..g.len() {
            let w = g.weights(g.direction(node));
            let s: f64 = w.iter().map(|x| x.1).sum();
            assert!((s - 1.0).abs() < 1e-12);
            let on: f64 = w.iter().filter(|x| x.0 == node).map(|x| x.1).sum();
            // at the zenith all azimuth nodes are the same direction
            if node >= g.n_phi {
                assert!((on - 1.0).abs() < 1e-9, "node {node}: {w:?}");
            }
        }
        let w = g.weights(dir_from_deg(89.9, 359.9));
        assert!(w.iter().all(|x| x.1.is_finite() && x.1 >= 0.0));
    }

    #[test]
    fn a_grid_to_the_horizon_interpolates_beyond_the_libraries_last_node() {
        let g = DirGrid::to(25, 40, 89.9);
        assert!((g.thetas[24].to_degrees() - 89.9).abs() < 1e-9);
        assert_eq!(DirGrid::new(10, 16).thetas[9], LAST_THETA_DEG.to_radians());
        // Below the horizon nodes, the libraries' spacing of one node fewer; the horizon nodes
        // even in the ray slope.
        assert_eq!(g.thetas[..22], DirGrid::new(24, 40).thetas[..22]);
        let m: Vec<f64> = g.thetas[21..].iter().map(|t| 1.0 / t.tan()).collect();
        for k in 1..3 {
            assert!(
                ((m[k - 1] - m[k]) - (m[k] - m[k + 1])).abs() < 1e-12,
                "{m:?}"
            );
        }
        assert!(g.thetas.windows(2).all(|w| w[0] < w[1]));
        // A view at 89.5° lies between the last two polar rows, not on the last one.
        let w = g.weights(dir_from_deg(89.5, 0.0));
        let last_row: f64 = w.iter().filter(|x| x.0 >= 24 * 40).map(|x| x.1).sum();
        assert!(last_row > 0.0 && last_row < 1.0, "{w:?}");
        // Beyond the last node: its row alone.
        let w = g.weights(dir_from_deg(89.95, 10.0));
        let last_row: f64 = w.iter().filter(|x| x.0 >= 24 * 40).map(|x| x.1).sum();
        assert!((last_row - 1.0).abs() < 1e-12, "{w:?}");
    }
}
