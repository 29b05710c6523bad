//! The packed form of a half-precision light-lobe record ([`crate::lobecodec`]): the same
//! numbers without the blocks that are zero and without the zenith's repeated view nodes, for
//! libraries whose records would not fit in memory otherwise (`biscale library refit
//! --pack-lobes`).
//!
//! A record's moments come in rows: the seen moments at one view node (3 numbers per
//! cluster), and the lit moments at one (light, view node) (9 per cluster). A cluster that a
//! light or a view does not reach, or that the geometry does not use, has a block of zeros
//! there: 41 % of the lit blocks and 34 % of the seen blocks of the `paper` library
//! (docs/solvers.md). And the first polar row of the view grid is the zenith, one direction
//! at every azimuth, so its `n_phi` nodes hold the same numbers. The packed record keeps one
//! zenith node and, per row, a bit mask of the clusters whose block is not zero, then only
//! those blocks:
//!
//! | part | length (16-bit words) | content |
//! |---|---|---|
//! | masks | `rows × ⌈K/16⌉` | bit `c % 16` of word `c / 16`: cluster `c`'s block is stored |
//! | blocks | 3 or 9 per set bit | the blocks, row after row, clusters in order |
//!
//! with `rows = U × (1 + L)`: the seen rows of the `U = V − n_phi + 1` distinct view nodes,
//! then the lit rows light by light. The words are stored as `f16` (the masks by their bits).
//! Nothing is rounded: unpacking gives the half-precision record bit for bit, which
//! [`pack`] checks.

use half::f16;

/// Numbers per cluster in a seen row and in a lit row.
const SEEN: usize = 3;
const LIT: usize = crate::bvndf::STRIDE;

/// The shape of a library's records.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shape {
    pub clusters: usize,
    pub lights: usize,
    /// View nodes of the grid, the zenith row's `n_phi` included.
    pub views: usize,
    pub n_phi: usize,
}

impl Shape {
    /// Distinct view nodes: the zenith row counts once.
    pub fn unique_views(&self) -> usize {
        self.views + 1 - self.n_phi.clamp(1, self.views.max(1))
    }

    /// The distinct node of view node `b`.
    #[inline]
    fn unique(&self, b: usize) -> usize {
        if b < self.n_phi {
            0
        } else {
            b + 1 - self.n_phi
        }
    }

    /// The row of the seen moments at view node `b`.
    #[inline]
    pub fn seen_row(&self, b: usize) -> usize {
        self.unique(b)
    }

    /// The row of the lit moments at light `l` and view node `b`.
    #[inline]
    pub fn lit_row(&self, l: usize, b: usize) -> usize {
        self.unique_views() * (1 + l) + self.unique(b)
    }

    fn rows(&self) -> usize {
        self.unique_views() * (1 + self.lights)
    }

    /// Numbers per cluster in row `r`.
    #[inline]
    pub fn width(&self, r: usize) -> usize {
        if r < self.unique_views() {
            SEEN
        } else {
            LIT
        }
    }

    /// Mask words per row.
    #[inline]
    fn mask_words(&self) -> usize {
        self.clusters.div_ceil(16)
    }

    /// Where row `r` starts in the half-precision body (`[view][cluster][3]`, then
    /// `[light][view][cluster][9]`), for a node `b` of that row.
    fn dense_start(&self, seen: bool, l: usize, b: usize) -> usize {
        let k = self.clusters;
        if seen {
            b * k * SEEN
        } else {
            self.views * k * SEEN + (l * self.views + b) * k * LIT
        }
    }

    /// Every row's dense start (at its first view node), in row order.
    fn dense_rows(&self) -> Vec<(usize, usize)> {
        let nodes: Vec<usize> = std::iter::once(0).chain(self.n_phi..self.views).collect();
        let mut rows = Vec::with_capacity(self.rows());
        rows.extend(nodes.iter().map(|&b| (self.dense_start(true, 0, b), SEEN)));
        for l in 0..self.lights {
            rows.extend(nodes.iter().map(|&b| (self.dense_start(false, l, b), LIT)));
        }
        rows
    }

    /// Numbers in a half-precision body of this shape.
    pub fn dense_len(&self) -> usize {
        self.views * self.clusters * (SEEN + self.lights * LIT)
    }
}

/// Pack a half-precision body of shape `s`. `None` where the zenith row's nodes differ (the
/// record could not be unpacked to itself) or the body's length is not the shape's.
pub fn pack(body: &[f16], s: &Shape) -> Option<Vec<f16>> {
    if body.len() != s.dense_len() || s.n_phi == 0 || s.views < s.n_phi || s.clusters == 0 {
        return None;
    }
    let k = s.clusters;
    // The zenith's nodes must be copies of its first.
    let same = |a: usize, b: usize, len: usize| {
        body[a..a + len]
            .iter()
            .zip(&body[b..b + len])
            .all(|(x, y)| x.to_bits() == y.to_bits())
    };
    for b in 1..s.n_phi {
        if !same(
            s.dense_start(true, 0, 0),
            s.dense_start(true, 0, b),
            k * SEEN,
        ) {
            return None;
        }
        for l in 0..s.lights {
            if !same(
                s.dense_start(false, l, 0),
                s.dense_start(false, l, b),
                k * LIT,
            ) {
                return None;
            }
        }
    }
    let rows = s.dense_rows();
    let mw = s.mask_words();
    let mut masks = vec![0u16; rows.len() * mw];
    let mut blocks = Vec::new();
    for (r, &(start, w)) in rows.iter().enumerate() {
        for c in 0..k {
            let blk = &body[start + c * w..start + (c + 1) * w];
            if blk.iter().any(|x| x.to_bits() != 0) {
                masks[r * mw + c / 16] |= 1 << (c % 16);
                blocks.extend_from_slice(blk);
            }
        }
    }
    let mut out: Vec<f16> = masks.into_iter().map(f16::from_bits).collect();
    out.extend(blocks);
    Some(out)
}

/// Where each row of a packed record lies: its mask words and the start of its blocks.
#[derive(Debug, Clone)]
pub struct Index {
    shape: Shape,
    /// Per row, the start of its blocks in the packed words; one more entry at the end.
    starts: Vec<u32>,
}

impl Index {
    /// The index of the packed record `words` of shape `s`; `None` if its length does not
    /// match its masks (a corrupted or foreign record).
    pub fn new(words: &[f16], s: &Shape) -> Option<Self> {
        let (rows, mw) = (s.rows(), s.mask_words());
        let head = rows * mw;
        // Every start fits in 32 bits when the record's length does.
        if words.len() < head || s.clusters > mw * 16 || u32::try_from(words.len()).is_err() {
            return None;
        }
        let masks: &[u16] = bytemuck::cast_slice(&words[..head]);
        // A bit beyond the last cluster is not a record of this shape (one OR over every row's
        // last word, not a test per row).
        let spare = mw * 16 - s.clusters;
        if spare > 0 {
            let last = masks[mw - 1..].iter().step_by(mw).fold(0, |a, &m| a | m);
            if last >> (16 - spare) != 0 {
                return None;
            }
        }
        // The starts are running sums of each row's set bits times its width. A search reads
        // one record's index per pooled geometry, thousands per solve: the rows' lengths are
        // found in one loop, then summed in another.
        let mut starts = vec![0u32; rows + 1];
        for (r, row) in masks.chunks_exact(mw).enumerate() {
            let set: u32 = row.iter().map(|m| m.count_ones()).sum();
            starts[r + 1] = set * s.width(r) as u32;
        }
        // (In 64 bits: a start past 32 bits, from a corrupted mask, makes the end differ from
        // the record's length, and the index is refused.)
        let mut at = head as u64;
        for v in &mut starts {
            at += u64::from(*v);
            *v = at as u32;
        }
        (at == words.len() as u64).then_some(Index { shape: *s, starts })
    }

    pub fn shape(&self) -> &Shape {
        &self.shape
    }

    /// The length of the record it indexes.
    pub fn words(&self) -> usize {
        self.starts.last().map_or(0, |&w| w as usize)
    }

    /// Row `r`'s blocks written into `out` (`clusters × width` numbers, zeros where none is
    /// stored), converted to `f32`.
    #[inline]
    pub fn fill(&self, words: &[f16], r: usize, out: &mut [f32]) {
        match self.shape.width(r) {
            SEEN => self.fill_w::<SEEN>(words, r, out),
            _ => self.fill_w::<LIT>(words, r, out),
        }
    }

    /// [`Self::fill`] for rows of width `W`: with the width a constant, each block's move and
    /// each gap's zeros are a few register moves rather than calls to `memmove` and `memset`
    /// (a row has up to 16 blocks, and the solvers' re-rank fills eight rows per sample).
    #[inline]
    fn fill_w<const W: usize>(&self, words: &[f16], r: usize, out: &mut [f32]) {
        use half::slice::HalfFloatSliceExt;
        let mw = self.shape.mask_words();
        let data = &words[self.span(r)];
        let k = self.shape.clusters;
        let all = k * W;
        if data.len() == all {
            // Every block stored: the row is the dense numbers.
            data.convert_to_f32_slice(&mut out[..all]);
            return;
        }
        // The row's blocks converted at once (8 numbers per instruction with F16C) into the end
        // of `out`, then each moved down to its cluster's place, in cluster order, and the gaps
        // zeroed. A block's place is never above where it was converted to (at most as many
        // clusters follow it as blocks do), and a gap never reaches a block not yet moved.
        let tail = all - data.len();
        data.convert_to_f32_slice(&mut out[tail..all]);
        let masks = &words[r * mw..(r + 1) * mw];
        let mut from = tail;
        for c in 0..k {
            let to = c * W;
            if masks[c / 16].to_bits() >> (c % 16) & 1 != 0 {
                out.copy_within(from..from + W, to);
                from += W;
            } else {
                out[to..to + W].fill(0.0);
            }
        }
    }

    /// The packed words of row `r` (its blocks), for prefetching.
    #[inline]
    pub fn span(&self, r: usize) -> std::ops::Range<usize> {
        self.starts[r] as usize..self.starts[r + 1] as usize
    }
}

/// The half-precision body a packed record stands for (for checks).
pub fn unpack(words: &[f16], s: &Shape) -> Option<Vec<f16>> {
    let ix = Index::new(words, s)?;
    let mut body = vec![f16::ZERO; s.dense_len()];
    let k = s.clusters;
    let mut row = vec![0f32; k * LIT];
    let mut put = |start: usize, r: usize, w: usize| {
        ix.fill(words, r, &mut row[..k * w]);
        for (d, &x) in body[start..start + k * w].iter_mut().zip(&row[..k * w]) {
            *d = f16::from_f32(x);
        }
    };
    for b in 0..s.views {
        put(s.dense_start(true, 0, b), s.seen_row(b), SEEN);
    }
    for l in 0..s.lights {
        for b in 0..s.views {
            put(s.dense_start(false, l, b), s.lit_row(l, b), LIT);
        }
    }
    Some(body)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shape(clusters: usize) -> Shape {
        Shape {
            clusters,
            lights: 2,
            views: 3 * 4,
            n_phi: 4,
        }
    }

    /// A body with zero blocks, equal zenith nodes and awkward values (−0, subnormals).
    fn body(s: &Shape, seed: u32) -> Vec<f16> {
        let mut b = vec![f16::ZERO; s.dense_len()];
        let mut x = seed;
        for (i, v) in b.iter_mut().enumerate() {
            x = x.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            *v = match x >> 28 {
                0..=5 => f16::ZERO,
                6 => f16::NEG_ZERO,
                7 => f16::from_bits(1),
                _ => f16::from_f32((x >> 8) as f32 / 1e6 - 3.0 + i as f32 * 1e-3),
            };
        }
        // Whole zero blocks, and the zenith's copies.
        let k = s.clusters;
        for c in (0..k).step_by(3) {
            let st = s.dense_start(false, 1, 5) + c * LIT;
            b[st..st + LIT].fill(f16::ZERO);
        }
        for bn in 1..s.n_phi {
            let (a, d) = (s.dense_start(true, 0, 0), s.dense_start(true, 0, bn));
            let src = b[a..a + k * SEEN].to_vec();
            b[d..d + k * SEEN].copy_from_slice(&src);
            for l in 0..s.lights {
                let (a, d) = (s.dense_start(false, l, 0), s.dense_start(false, l, bn));
                let src = b[a..a + k * LIT].to_vec();
                b[d..d + k * LIT].copy_from_slice(&src);
            }
        }
        b
    }

    #[test]
    fn packing_is_lossless_and_smaller() {
        for k in [1, 5, 16, 17, 40] {
            let s = shape(k);
            let b = body(&s, k as u32);
            let p = pack(&b, &s).expect("packs");
            assert!(p.len() < b.len(), "k {k}: {} of {}", p.len(), b.len());
            let u = unpack(&p, &s).expect("unpacks");
            assert!(
                u.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
                "k {k}"
            );
            // Every row's fill equals the dense numbers.
            let ix = Index::new(&p, &s).expect("index");
            let mut out = vec![0f32; k * LIT];
            for l in 0..s.lights {
                for bn in 0..s.views {
                    ix.fill(&p, s.lit_row(l, bn), &mut out);
                    let st = s.dense_start(false, l, bn);
                    for (x, y) in out.iter().zip(&b[st..st + k * LIT]) {
                        assert_eq!(x.to_bits(), y.to_f32().to_bits());
                    }
                }
            }
        }
    }

    #[test]
    fn a_record_that_would_not_unpack_to_itself_is_refused() {
        let s = shape(6);
        let mut b = body(&s, 9);
        // Zenith nodes that differ.
        let d = s.dense_start(false, 1, 2);
        b[d] = f16::from_f32(1234.0);
        assert!(pack(&b, &s).is_none());
        assert!(pack(&b[1..], &s).is_none());
        // A packed record cut short, lengthened, or with a bit past the last cluster.
        let p = pack(&body(&s, 9), &s).expect("packs");
        assert!(Index::new(&p[..p.len() - 1], &s).is_none());
        let mut longer = p.clone();
        longer.push(f16::ONE);
        assert!(Index::new(&longer, &s).is_none());
        let mut stray = p.clone();
        stray[0] = f16::from_bits(stray[0].to_bits() | 1 << 15);
        assert!(Index::new(&stray, &s).is_none());
        // ... in any row: here the last lit row's mask.
        let last = s.rows() * s.mask_words() - 1;
        let mut stray = p;
        stray[last] = f16::from_bits(stray[last].to_bits() | 1 << 15);
        assert!(Index::new(&stray, &s).is_none());
        // Two mask words per row (17 clusters): a bit past the last cluster in a later row.
        let s17 = shape(17);
        let mut p17 = pack(&body(&s17, 3), &s17).expect("packs");
        assert!(Index::new(&p17, &s17).is_some());
        let w = 5 * s17.mask_words() + 1;
        p17[w] = f16::from_bits(p17[w].to_bits() | 1 << 1);
        assert!(Index::new(&p17, &s17).is_none());
    }
}
