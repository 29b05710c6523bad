//! The facet normals of a heightfield's curved normal clusters, binned by direction: what the
//! fast evaluator sums, facet by facet, for glossy lobes too sharp for the prefiltered table
//! ([`crate::bvndf::CompactBvndf::sharp_fbar`]).
//!
//! A lobe much narrower than the spacing of a triangulated surface's facet normals (GGX
//! `alpha = 0.001` on smooth bumps) makes `fbar` a sum of spikes, one per facet whose normal
//! meets the half vector; a smooth vMF per cluster, or its sub-lobes, averages them away. Such a
//! lobe is non-zero only for normals within its support radius of the half vector
//! ([`crate::material::Lobe::support_radius`]), so only those facets are visited: the normals are
//! binned on a square grid over `(n_x, n_y)` (a cap of angle `r` around `h` lies within `r` of
//! `(h_x, h_y)` there), and facets of one cluster with the same normal, sub-lobe part and height
//! band are merged. Each entry keeps its cluster, part and band: the facet sum takes a facet's
//! visibility from them ([`crate::bvndf::CompactBvndf::sharp_fbar`]).

use crate::frame::Vec3;

/// Grid cells per side over `n_x, n_y ∈ [-1, 1]`.
const CELLS: usize = 64;

/// Facets binned by normal direction (planar clusters left out: their normal is exact already).
#[derive(Debug, Clone, PartialEq)]
pub struct FacetIndex {
    /// `start[c]..start[c + 1]`: the facets of cell `c` (row-major, `CELLS²` cells).
    start: Vec<u32>,
    normals: Vec<Vec3>,
    /// Areas in units of the base area.
    areas: Vec<f64>,
    cluster: Vec<u16>,
    /// Each entry's part of its cluster ([`crate::sublobes::cluster_shapes`]).
    part: Vec<u16>,
    /// Each entry's height band ([`crate::seen::facet_bands`]; 0 without bands).
    band: Vec<u8>,
    /// `ids[first[e]..first[e + 1]]`: the facets entry `e` merges (indices into
    /// [`crate::heightfield::Heightfield::facets`]).
    first: Vec<u32>,
    ids: Vec<u32>,
}

/// One entry of the index as [`FacetIndex::near`] gives it: facets of one cluster with the same
/// normal, sub-lobe part and height band.
#[derive(Debug, Clone, Copy)]
pub struct Near<'a> {
    pub n: Vec3,
    /// Their summed area, in units of the base area.
    pub area: f64,
    pub cluster: usize,
    pub part: u16,
    pub band: u8,
    /// The facets (indices into [`crate::heightfield::Heightfield::facets`]), ascending. On a
    /// heightfield's grid facets of one normal have one area, `area / facets.len()` each.
    pub facets: &'a [u32],
}

fn cell_of(v: f64) -> usize {
    (((v + 1.0) * 0.5 * CELLS as f64).floor().max(0.0) as usize).min(CELLS - 1)
}

impl FacetIndex {
    /// Index the facets (`normals`, `areas` in units of the base area, cluster `assign`, part of
    /// the cluster `part`, height band `band`) whose cluster `keep` accepts.
    pub fn build(
        normals: &[Vec3],
        areas: &[f64],
        assign: &[u16],
        part: &[u16],
        band: &[u8],
        keep: impl Fn(usize) -> bool,
    ) -> Self {
        let key = |n: &Vec3| cell_of(n.y) * CELLS + cell_of(n.x);
        let mut idx: Vec<usize> = (0..normals.len())
            .filter(|&i| keep(assign[i] as usize) && areas[i] > 0.0)
            .collect();
        idx.sort_by(|&a, &b| {
            let (na, nb) = (&normals[a], &normals[b]);
            (key(na), assign[a])
                .cmp(&(key(nb), assign[b]))
                .then(na.x.total_cmp(&nb.x))
                .then(na.y.total_cmp(&nb.y))
                .then(na.z.total_cmp(&nb.z))
        });
        let mut out = FacetIndex {
            start: vec![0; CELLS * CELLS + 1],
            normals: Vec::new(),
            areas: Vec::new(),
            cluster: Vec::new(),
            part: Vec::new(),
            band: Vec::new(),
            first: Vec::new(),
            ids: Vec::with_capacity(idx.len()),
        };
        let mut counts = vec![0u32; CELLS * CELLS];
        for &i in &idx {
            let (n, k) = (normals[i], assign[i]);
            let same = out.normals.last().is_some_and(|m| *m == n)
                && out.cluster.last().is_some_and(|c| *c == k)
                && out.part.last().is_some_and(|q| *q == part[i])
                && out.band.last().is_some_and(|h| *h == band[i]);
            if same {
                if let Some(a) = out.areas.last_mut() {
                    *a += areas[i];
                }
            } else {
                out.first.push(out.ids.len() as u32);
                out.normals.push(n);
                out.areas.push(areas[i]);
                out.cluster.push(k);
                out.part.push(part[i]);
                out.band.push(band[i]);
                counts[key(&n)] += 1;
            }
            out.ids.push(i as u32);
        }
        out.first.push(out.ids.len() as u32);
        for (c, n) in counts.iter().enumerate() {
            out.start[c + 1] = out.start[c] + n;
        }
        out
    }

    /// Distinct (cluster, normal) entries.
    pub fn len(&self) -> usize {
        self.normals.len()
    }

    pub fn is_empty(&self) -> bool {
        self.normals.is_empty()
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.start.len() * 4
            + self.normals.len() * (24 + 8 + 2 + 2 + 1 + 4)
            + self.ids.len() * 4
            + 4
    }

    /// Call `f` with every entry whose normal is within `radius` radians of the unit vector `h`.
    pub fn near<'s>(&'s self, h: Vec3, radius: f64, mut f: impl FnMut(Near<'s>)) {
        let cos_r = radius.cos();
        let (x0, x1) = (cell_of(h.x - radius), cell_of(h.x + radius));
        let (y0, y1) = (cell_of(h.y - radius), cell_of(h.y + radius));
        for cy in y0..=y1 {
            let row = cy * CELLS;
            let (s, e) = (
                self.start[row + x0] as usize,
                self.start[row + x1 + 1] as usize,
            );
            for i in s..e {
                let n = self.normals[i];
                if n.dot(h) >= cos_r {
                    f(Near {
                        n,
                        area: self.areas[i],
                        cluster: self.cluster[i] as usize,
                        part: self.part[i],
                        band: self.band[i],
                        facets: &self.ids[self.first[i] as usize..self.first[i + 1] as usize],
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn near_finds_exactly_the_facets_within_the_radius() {
        // A fan of normals at polar angles 0.01..0.6 rad in steps of 0.01, azimuths every 10°, two
        // clusters, each normal twice (merged).
        let mut normals = Vec::new();
        let mut assign = Vec::new();
        for i in 1..60 {
            for j in 0..36 {
                let (t, p) = (i as f64 * 0.01, (j as f64 * 10.0).to_radians());
                let n = Vec3::new(t.sin() * p.cos(), t.sin() * p.sin(), t.cos());
                for _ in 0..2 {
                    normals.push(n);
                    assign.push((j % 2) as u16);
                }
            }
        }
        let areas = vec![0.5; normals.len()];
        let part = vec![0u16; normals.len()];
        let band = vec![0u8; normals.len()];
        let ix = FacetIndex::build(&normals, &areas, &assign, &part, &band, |_| true);
        assert_eq!(ix.len(), normals.len() / 2);
        let h = Vec3::new(0.2, 0.1, 1.0).normalized();
        for r in [0.0, 0.03, 0.1, 0.5] {
            let mut got = Vec::new();
            ix.near(h, r, |e| {
                assert_eq!(e.area, 1.0);
                // Each entry merges the two facets of its normal, in order.
                assert_eq!(e.facets.len(), 2);
                assert_eq!(e.facets[1], e.facets[0] + 1);
                assert_eq!(normals[e.facets[0] as usize], e.n);
                got.push(e.n);
            });
            let want = (0..normals.len())
                .step_by(2)
                .filter(|&i| normals[i].dot(h) >= r.cos())
                .count();
            assert_eq!(got.len(), want, "radius {r}");
        }
        // A cluster left out is not indexed.
        assert_eq!(
            FacetIndex::build(&normals, &areas, &assign, &part, &band, |k| k == 0).len(),
            normals.len() / 4
        );
    }
}
