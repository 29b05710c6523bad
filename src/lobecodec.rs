//! The half-precision form of a light-lobe record ([`crate::lightlobes`]): half the bytes of the
//! `f32` form, for libraries whose records are read from the disk (a geometry solve re-ranks
//! thousands of them).
//!
//! Plain `f16` moments would lose the lobes' widths: a tight cluster's mean resultant length is
//! `1 − r ≈ 1/kappa`, and `f16` keeps 11 bits. So each cluster's moments are stored about its
//! own centre `c`, in its frame `(t1, t2, c)` ([`crate::frame::frame_around`]), where the parts
//! that set the width are small numbers with their own exponents:
//!
//! | part | per cluster | content |
//! |---|---|---|
//! | head | 5 (`f32`, in a separate array) | the `f32` record's header, unchanged |
//! | seen | `V × 3` | `G1` of the area seen from `w_b`, in the cluster's frame |
//! | lit | `L × V × 9` | `A = tr G2`, then divided by `A`: `D = (t1·G1, t2·G1, c·G1 − A)`, and of `M = Rᵀ G2 R − A c cᵀ` `M11, M22, M12, M1c − D1, M2c − D2` |
//!
//! `tr M = 0` (unit normals), so `Mcc = −(M11 + M22)` is not stored. `D_c` and `M11 + M22` are
//! of the order of the cluster's spread squared, and `M1c − D1 = Σ A (n·t1)(n·c − 1)` of its
//! cube; each keeps `f16`'s relative precision (`2⁻¹¹`) of itself. `D1` and `M1c` are of the
//! order of the spread, and a lobe's mean resultant length `r = |G2 w| / (G1·w)` takes `D1` into
//! both its numerator and its denominator, where its rounding cancels. So the deficit `1 − r`,
//! which sets the lobe's width, is kept to a few `2⁻¹¹` of itself, not to `2⁻¹¹` of `A`.
//! Divided by `A`, the small parts do not depend on the record's units and stay above `f16`'s
//! smallest normal number (6.1e-5) down to spreads of about 0.6° (`θ²/2`); below that they are
//! kept to 6e-8 absolute, against `1/kappa ≈ α²/2 = 2e-4` for the libraries' sharpest
//! material lobes (GGX, Beckmann or Ward at `α = 0.02`). Multiplied by `A` ([`unscale`]) the
//! numbers are linear in the moments, so interpolated moments may be decoded once after the
//! interpolation. The layout of the seen and lit parts is the `f32` record's, without its
//! header: `[view][cluster][3]` then `[light][view][cluster][9]`.

use crate::bvndf::STRIDE;
use crate::frame::{frame_around, Vec3};
use crate::lightlobes::HEAD;
use half::f16;

/// A cluster's frame `(t1, t2, c)`, from its stored centre (the zero vector gives `+z`, as
/// [`crate::lightlobes`] reads it).
#[derive(Debug, Clone, Copy)]
pub struct Frame {
    pub t1: Vec3,
    pub t2: Vec3,
    pub c: Vec3,
}

impl Frame {
    /// The frame of a header entry `(x, y, z, planar, area)`.
    pub fn of_head(h: &[f32]) -> Self {
        let v = Vec3::new(h[0] as f64, h[1] as f64, h[2] as f64);
        let c = if v.norm() > 0.0 {
            v.normalized()
        } else {
            Vec3::Z
        };
        let (t1, t2) = frame_around(c);
        Frame { t1, t2, c }
    }

    /// Seen moments `G1` in this frame.
    pub fn seen_local(&self, g: &[f32]) -> [f64; 3] {
        let g = Vec3::new(g[0] as f64, g[1] as f64, g[2] as f64);
        [self.t1.dot(g), self.t2.dot(g), self.c.dot(g)]
    }

    /// Seen moments back in the macro frame.
    pub fn seen_global(&self, l: &[f64; 3]) -> Vec3 {
        self.t1 * l[0] + self.t2 * l[1] + self.c * l[2]
    }

    /// A lit entry `(G1, G2 as xx, yy, zz, xy, xz, yz)` in this frame's 9 numbers,
    /// `(A, D1, D2, Dc, M11, M22, M12, M1c − D1, M2c − D2)`, before [`scale`].
    pub fn lit_local(&self, e: &[f32]) -> [f64; STRIDE] {
        let e: [f64; STRIDE] = std::array::from_fn(|i| e[i] as f64);
        let g1 = Vec3::new(e[0], e[1], e[2]);
        let q = |w: Vec3| crate::bvndf::second_times(&e[3..], w);
        let a = e[3] + e[4] + e[5];
        let (q1, q2, qc) = (q(self.t1), q(self.t2), q(self.c));
        let (d1, d2) = (self.t1.dot(g1), self.t2.dot(g1));
        [
            a,
            d1,
            d2,
            self.c.dot(g1) - a,
            self.t1.dot(q1),
            self.t2.dot(q2),
            self.t1.dot(q2),
            self.t1.dot(qc) - d1,
            self.t2.dot(qc) - d2,
        ]
    }

    /// The lit entry in the macro frame of a planar cluster (every normal equal to `c`, so
    /// `D` and `M` vanish) whose lit area is `a`: `(a c, a c cᵀ)`.
    #[inline]
    pub fn planar_global(&self, a: f64) -> [f64; STRIDE] {
        crate::bvndf::moments(self.c).map(|x| a * x)
    }

    /// A lit entry in this frame (as [`Self::lit_local`] gives it, or a weighted sum of such
    /// entries) back in the macro frame (`G1`, then `G2` as xx, yy, zz, xy, xz, yz).
    pub fn lit_global(&self, l: &[f64; STRIDE]) -> [f64; STRIDE] {
        let [a, d1, d2, dc, m11, m22, m12, e1c, e2c] = *l;
        let (m1c, m2c) = (d1 + e1c, d2 + e2c);
        let (t1, t2, c) = (self.t1, self.t2, self.c);
        let g1 = t1 * d1 + t2 * d2 + c * (a + dc);
        // G2 = R M' Rᵀ (R's columns t1, t2, c; M' symmetric, of trace A since the normals are
        // unit vectors, which gives its last entry): with u_k = M' row k applied to R's
        // columns, G2 = t1 u1ᵀ + t2 u2ᵀ + c ucᵀ.
        let mcc = a - m11 - m22;
        let u1 = t1 * m11 + t2 * m12 + c * m1c;
        let u2 = t1 * m12 + t2 * m22 + c * m2c;
        let uc = t1 * m1c + t2 * m2c + c * mcc;
        [
            g1.x,
            g1.y,
            g1.z,
            t1.x * u1.x + t2.x * u2.x + c.x * uc.x,
            t1.y * u1.y + t2.y * u2.y + c.y * uc.y,
            t1.z * u1.z + t2.z * u2.z + c.z * uc.z,
            t1.x * u1.y + t2.x * u2.y + c.x * uc.y,
            t1.x * u1.z + t2.x * u2.z + c.x * uc.z,
            t1.y * u1.z + t2.y * u2.z + c.y * uc.z,
        ]
    }
}

/// A cluster's lit moments in its frame (as [`Frame::lit_local`] gives them, or a weighted sum
/// of such), read by [`crate::bvndf::assemble_lobes`] without turning them to the macro frame:
/// `wo` is turned into the frame instead.
pub struct Local<'f> {
    pub frame: &'f Frame,
    pub l: [f64; STRIDE],
}

impl Local<'_> {
    /// `wo` in the frame.
    #[inline]
    fn w(&self, wo: Vec3) -> [f64; 3] {
        [
            self.frame.t1.dot(wo),
            self.frame.t2.dot(wo),
            self.frame.c.dot(wo),
        ]
    }
}

impl crate::bvndf::ClusterMoments for Local<'_> {
    #[inline]
    fn projected(&self, wo: Vec3) -> f64 {
        let [a, d1, d2, dc, ..] = self.l;
        let w = self.w(wo);
        d1 * w[0] + d2 * w[1] + (a + dc) * w[2]
    }

    #[inline]
    fn second(&self, wo: Vec3) -> Vec3 {
        let [a, d1, d2, _, m11, m22, m12, e1c, e2c] = self.l;
        let (m1c, m2c, mcc) = (d1 + e1c, d2 + e2c, a - m11 - m22);
        let w = self.w(wo);
        let f = self.frame;
        f.t1 * (m11 * w[0] + m12 * w[1] + m1c * w[2])
            + f.t2 * (m12 * w[0] + m22 * w[1] + m2c * w[2])
            + f.c * (m1c * w[0] + m2c * w[1] + mcc * w[2])
    }

    fn global(&self) -> [f64; STRIDE] {
        self.frame.lit_global(&self.l)
    }
}

/// A lit entry in a cluster's frame as stored: `A`, then the rest divided by `A` (zero where
/// `A` is not positive).
pub fn scale(l: &[f64; STRIDE]) -> [f16; STRIDE] {
    let a = l[0];
    let s = if a > 0.0 { 1.0 / a } else { 0.0 };
    std::array::from_fn(|i| to_half(if i == 0 { a.max(0.0) } else { l[i] * s }))
}

/// `f16` of `x` through `f32`, as F16C converts (a build with or without F16C then writes the
/// same bytes; straight from `f64` the software path would round once, F16C twice).
fn to_half(x: f64) -> f16 {
    f16::from_f32(x as f32)
}

/// A stored lit entry (`f16`, or already converted to `f32`) back to [`Frame::lit_local`]'s
/// numbers (multiplied by its `A`).
#[inline]
pub fn unscale<T: Copy>(e: &[T]) -> [f64; STRIDE]
where
    f64: From<T>,
{
    let a = f64::from(e[0]);
    std::array::from_fn(|i| if i == 0 { a } else { f64::from(e[i]) * a })
}

/// Length in `f16` of the encoded part of a record (the `f32` record without its header).
pub fn half_len(record_len: usize, clusters: usize) -> usize {
    record_len - clusters * HEAD
}

/// Encode an `f32` record of `clusters` clusters and `views` view nodes: its header
/// (unchanged) and its moments in half precision. `None` if a moment is out of `f16`'s range
/// (a seen or lit area over 65,504 times the base area).
pub fn encode(record: &[f32], clusters: usize, views: usize) -> Option<(Vec<f32>, Vec<f16>)> {
    let head = record[..clusters * HEAD].to_vec();
    let frames: Vec<Frame> = head.chunks(HEAD).map(Frame::of_head).collect();
    let body = &record[clusters * HEAD..];
    let (seen, lit) = body.split_at(views * clusters * 3);
    let mut out = Vec::with_capacity(body.len());
    for (k, g) in seen.chunks(3).enumerate() {
        out.extend(frames[k % clusters].seen_local(g).map(to_half));
    }
    for (k, e) in lit.chunks(STRIDE).enumerate() {
        out.extend(scale(&frames[k % clusters].lit_local(e)));
    }
    out.iter().all(|x| x.is_finite()).then_some((head, out))
}

/// The `f32` record that `encode` stored (to `f16`'s precision in the cluster frames).
pub fn decode(head: &[f32], body: &[f16], clusters: usize, views: usize) -> Vec<f32> {
    let frames: Vec<Frame> = head.chunks(HEAD).map(Frame::of_head).collect();
    let (seen, lit) = body.split_at(views * clusters * 3);
    let mut out = head.to_vec();
    for (k, g) in seen.chunks(3).enumerate() {
        let l = std::array::from_fn(|i| g[i].to_f64());
        let v = frames[k % clusters].seen_global(&l);
        out.extend([v.x as f32, v.y as f32, v.z as f32]);
    }
    for (k, e) in lit.chunks(STRIDE).enumerate() {
        let l = unscale(e);
        out.extend(frames[k % clusters].lit_global(&l).map(|x| x as f32));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bvndf::moments;
    use crate::frame::dir_from_deg;

    /// Moments of a few unit normals around `c`, spread `deg` degrees.
    fn cluster(c: Vec3, deg: f64, w: f64) -> ([f32; 3], [f32; STRIDE]) {
        let (t1, t2) = frame_around(c);
        let s = deg.to_radians();
        let mut seen = [0.0; 3];
        let mut lit = [0.0; STRIDE];
        for (k, (a, b)) in [(1.0, 0.0), (-0.5, 0.8), (-0.3, -0.9), (0.2, 0.1)]
            .iter()
            .enumerate()
        {
            let n = (c + t1 * (s * a) + t2 * (s * b)).normalized();
            let m = moments(n);
            let wk = w * (1.0 + k as f64) / 4.0;
            for (x, y) in seen.iter_mut().zip(n.to_array()) {
                *x += wk * y;
            }
            for (x, y) in lit.iter_mut().zip(m) {
                *x += wk * y;
            }
        }
        (seen.map(|x| x as f32), lit.map(|x| x as f32))
    }

    /// The mean resultant length `|G2 w| / (G1·w)` that sets a lobe's kappa.
    fn resultant(e: &[f64], w: Vec3) -> f64 {
        let m = crate::bvndf::second_times(&e[3..], w);
        m.norm() / (e[0] * w.x + e[1] * w.y + e[2] * w.z)
    }

    #[test]
    fn tight_clusters_keep_their_spread_and_planar_ones_stay_planar() {
        let wo = dir_from_deg(70.0, 20.0);
        for (c, deg) in [
            (dir_from_deg(0.0, 0.0), 0.0),
            (dir_from_deg(30.0, 200.0), 0.2),
            (dir_from_deg(60.0, 80.0), 0.5),
            (dir_from_deg(85.0, 10.0), 3.0),
            (dir_from_deg(10.0, 300.0), 20.0),
        ] {
            let (seen, lit) = cluster(c, deg, 0.07);
            let mut rec = vec![c.x as f32, c.y as f32, c.z as f32, 0.0, 0.07];
            rec.extend(seen);
            rec.extend(lit);
            let (head, body) = encode(&rec, 1, 1).expect("in range");
            assert_eq!(body.len(), half_len(rec.len(), 1));
            let back = decode(&head, &body, 1, 1);
            assert_eq!(back[..HEAD], rec[..HEAD]);
            // Every moment to f16's precision of the entry's scale.
            for (a, b) in back[HEAD..].iter().zip(&rec[HEAD..]) {
                assert!((a - b).abs() <= 1e-3 * 0.07, "{a} against {b}");
            }
            // The resultant's deficit, which sets kappa, to a few of f16's epsilons of itself
            // (decoded in f64, as the lobes are).
            let f = Frame::of_head(&head);
            let local = unscale(&body[3..]);
            let exact: Vec<f64> = lit.iter().map(|&x| x as f64).collect();
            let d0 = 1.0 - resultant(&exact, wo);
            let d1 = 1.0 - resultant(&f.lit_global(&local), wo);
            let tol = 4e-3 * d0 + 1e-9;
            assert!(
                (d0 - d1).abs() <= tol,
                "{deg}°: 1 - r {d0:e} against {d1:e}"
            );
        }
    }
}
