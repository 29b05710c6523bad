//! Compression and representative columns for the material and geometry libraries (paper
//! Sec. 4.1 and 5).
//!
//! A library is a matrix `B` whose columns are the discretised members (prefiltered `F` of a
//! material, BVNDF of a geometry). Before CX it is compressed by an SVD that keeps a fraction of
//! the energy `||B||_F^2`; the compressed coordinates `Sigma_r V_r^T` (one column per member)
//! preserve the inner products between members, so CX on them approximates CX on `B`:
//!
//! - [`svd_gram`]: few columns (material library): Gram matrix `B^T B` accumulated over row blocks,
//!   symmetric eigen-decomposition. Singular values below about `1e-8 sigma_1` are not resolved.
//! - [`rsvd_streaming`]: many columns (geometry library): randomized SVD with subspace (power)
//!   iterations, Halko, Martinsson & Tropp 2011, Alg. 4.4, streaming over column chunks so memory
//!   is `O((m + n) l)` for a sketch of width `l`. Its products with `B` run in single precision
//!   (`B` is stored in half or single precision; twice the rate of double), everything else
//!   (orthonormalisation, the small SVD) in double. With a *pilot* (`RsvdConfig::pilot`), the
//!   basis is found on evenly spaced columns only and every column is projected on it in one
//!   more pass: one pass over a matrix larger than memory instead of `2 + 2 power_iters`.
//! - [`cx`]: representative columns `A ~ A[:, cols] X`, by column-pivoted QR (deterministic,
//!   greedy) or by leverage-score sampling (Drineas, Mahoney & Muthukrishnan 2008).
//!
//! Matrices are read through [`BlockSource`] (e.g. memory-mapped arrays). Every result is
//! bit-identical for the same input and seed whatever the number of rayon threads: work is split
//! into tiles whose shapes depend only on the matrix size and the chunk arguments, every dense
//! kernel runs sequentially inside its tile (`Par::Seq`, never faer's global parallelism), and
//! partial results are summed in tile order.

use crate::error::{Error, Result};
use crate::rng::Rng;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::{householder, matmul::matmul, qr, svd as fsvd, triangular_solve};
use faer::reborrow::ReborrowMut;
use faer::{Accum, Conj, Mat, MatMut, MatRef, Par};
use rayon::prelude::*;
use std::ops::Range;

/// A matrix read in blocks (column chunks or row blocks), e.g. memory-mapped library arrays.
pub trait BlockSource: Sync {
    fn rows(&self) -> usize;
    fn cols(&self) -> usize;
    /// Fill `out` (rows.len() × cols.len()) with that block of the matrix.
    fn read_block(
        &self,
        rows: Range<usize>,
        cols: Range<usize>,
        out: MatMut<'_, f64>,
    ) -> Result<()>;
    /// A hint that the columns `cols` will be read soon (a source on disk starts reading them
    /// in the background, so a pass's reads overlap its products). By default nothing.
    fn prefetch(&self, _cols: Range<usize>) {}
    /// The same block in single precision, for the randomized SVD's products (the library's
    /// matrices are stored in half or single precision). By default read in double and rounded.
    fn read_block_f32(
        &self,
        rows: Range<usize>,
        cols: Range<usize>,
        mut out: MatMut<'_, f32>,
    ) -> Result<()> {
        let mut t = Mat::<f64>::zeros(rows.len(), cols.len());
        self.read_block(rows, cols, t.as_mut())?;
        for j in 0..t.ncols() {
            for i in 0..t.nrows() {
                out[(i, j)] = t[(i, j)] as f32;
            }
        }
        Ok(())
    }
}

/// A matrix held in memory (tests, small libraries).
pub struct InMemory(pub Mat<f64>);

impl BlockSource for InMemory {
    fn rows(&self) -> usize {
        self.0.nrows()
    }
    fn cols(&self) -> usize {
        self.0.ncols()
    }
    fn read_block(
        &self,
        rows: Range<usize>,
        cols: Range<usize>,
        mut out: MatMut<'_, f64>,
    ) -> Result<()> {
        let (m, n) = self.0.shape();
        if rows.start > rows.end
            || rows.end > m
            || cols.start > cols.end
            || cols.end > n
            || out.nrows() != rows.len()
            || out.ncols() != cols.len()
        {
            return Err(Error::new(
                "lowrank::InMemory::read_block",
                format!(
                    "block rows {rows:?} cols {cols:?} into a {}x{} buffer: expected a block \
                     inside the {m}x{n} matrix matching the buffer",
                    out.nrows(),
                    out.ncols()
                ),
            ));
        }
        out.copy_from(
            self.0
                .as_ref()
                .submatrix(rows.start, cols.start, rows.len(), cols.len()),
        );
        Ok(())
    }
}

/// A truncated SVD `B ~ U_r Sigma_r V_r^T` kept as the coordinates `Sigma_r V_r^T`.
#[derive(Debug, Clone)]
pub struct Compressed {
    /// Number of singular triplets kept.
    pub rank: usize,
    /// All singular values computed, descending (`n` for `svd_gram`, the sketch width for
    /// `rsvd_streaming`).
    pub singular: Vec<f64>,
    /// `||B||_F^2`.
    pub total_energy: f64,
    /// Fraction of `total_energy` kept: `sum_{i<rank} sigma_i^2 / total_energy`. For the
    /// randomized SVD this is exactly the energy of the projection `U_r U_r^T B`.
    pub kept_energy: f64,
    /// `rank × n`: `Sigma_r V_r^T`, the compressed coordinates of every column.
    pub coords: Mat<f64>,
    /// `m × rank` left singular vectors, when asked.
    pub u: Option<Mat<f64>>,
    /// Full passes made over `B` (each reads every entry once).
    pub passes: usize,
    /// Columns of the pilot the basis was found on (0: none, the basis is `B`'s own).
    pub pilot_columns: usize,
    /// Passes made over the pilot's columns (each reads `pilot_columns` columns of `B`).
    pub pilot_passes: usize,
}

impl Compressed {
    /// The same decomposition kept at a lower `energy`: its leading rows of `coords` (and
    /// columns of `u`), the rank picked by the same rule as the decomposition's own. The
    /// triplets are nested, so this equals a decomposition run at `energy` (bit for bit for
    /// [`svd_gram`]). An `energy` at or above the kept one returns a copy.
    pub fn truncated(&self, energy: f64) -> Compressed {
        let rank = pick_rank(&self.singular, energy, self.total_energy)
            .unwrap_or(self.rank)
            .min(self.rank)
            .max(1);
        Compressed {
            rank,
            singular: self.singular.clone(),
            total_energy: self.total_energy,
            kept_energy: kept(&self.singular, rank, self.total_energy),
            coords: self.coords.as_ref().subrows(0, rank).to_owned(),
            u: self
                .u
                .as_ref()
                .map(|u| u.as_ref().subcols(0, rank).to_owned()),
            passes: self.passes,
            pilot_columns: self.pilot_columns,
            pilot_passes: self.pilot_passes,
        }
    }
}

fn err(ctx: &str, msg: impl Into<String>) -> Error {
    Error::new(format!("lowrank::{ctx}"), msg)
}

fn ranges(n: usize, step: usize) -> Vec<Range<usize>> {
    (0..n)
        .step_by(step.max(1))
        .map(|s| s..(s + step).min(n))
        .collect()
}

/// Row-tile height for the streaming kernels: depends only on `m` (never on the thread count).
fn tile_rows(m: usize) -> usize {
    m.div_ceil(8).clamp(256, 8192)
}

fn check_shape(ctx: &str, b: &dyn BlockSource) -> Result<(usize, usize)> {
    let (m, n) = (b.rows(), b.cols());
    if m == 0 || n == 0 {
        return Err(err(
            ctx,
            format!("the matrix is {m}x{n}: expected at least one row and one column"),
        ));
    }
    Ok((m, n))
}

fn check_energy(ctx: &str, energy: f64) -> Result<()> {
    if energy > 0.0 && energy <= 1.0 {
        Ok(())
    } else {
        Err(err(
            ctx,
            format!("energy = {energy}: expected a fraction in (0, 1]"),
        ))
    }
}

/// Read a block and check that it holds finite values; returns its sum of squares.
fn read_tile(
    ctx: &str,
    b: &dyn BlockSource,
    rows: Range<usize>,
    cols: Range<usize>,
) -> Result<(Mat<f64>, f64)> {
    checked_tile(ctx, rows, cols, |r, c, out| b.read_block(r, c, out))
}

/// [`read_tile`] in single precision (the streaming products); the sum of squares in double.
fn read_tile_f32(
    ctx: &str,
    b: &dyn BlockSource,
    rows: Range<usize>,
    cols: Range<usize>,
) -> Result<(Mat<f32>, f64)> {
    checked_tile(ctx, rows, cols, |r, c, out| b.read_block_f32(r, c, out))
}

fn checked_tile<T: Copy + Default + Into<f64> + std::fmt::Display>(
    ctx: &str,
    rows: Range<usize>,
    cols: Range<usize>,
    read: impl FnOnce(Range<usize>, Range<usize>, MatMut<'_, T>) -> Result<()>,
) -> Result<(Mat<T>, f64)> {
    let mut t = Mat::from_fn(rows.len(), cols.len(), |_, _| T::default());
    read(rows.clone(), cols.clone(), t.as_mut())
        .map_err(|e| e.within(format!("lowrank::{ctx}")))?;
    let mut ss = 0.0;
    for j in 0..t.ncols() {
        for (i, &x) in t.col_as_slice(j).iter().enumerate() {
            let v: f64 = x.into();
            if !v.is_finite() {
                return Err(err(
                    ctx,
                    format!(
                        "entry ({}, {}) of the matrix is {x}: expected finite values",
                        rows.start + i,
                        cols.start + j
                    ),
                ));
            }
            ss += v * v;
        }
    }
    Ok((t, ss))
}

fn to_f32(a: MatRef<'_, f64>) -> Mat<f32> {
    Mat::from_fn(a.nrows(), a.ncols(), |i, j| a[(i, j)] as f32)
}

fn to_f64(a: MatRef<'_, f32>) -> Mat<f64> {
    Mat::from_fn(a.nrows(), a.ncols(), |i, j| a[(i, j)] as f64)
}

// ---- dense kernels, all sequential inside (determinism) ----

fn mm(dst: MatMut<'_, f64>, acc: Accum, lhs: MatRef<'_, f64>, rhs: MatRef<'_, f64>) {
    matmul(dst, acc, lhs, rhs, 1.0, Par::Seq);
}

fn mm32(dst: MatMut<'_, f32>, acc: Accum, lhs: MatRef<'_, f32>, rhs: MatRef<'_, f32>) {
    matmul(dst, acc, lhs, rhs, 1.0f32, Par::Seq);
}

/// Thin SVD `a = U diag(s) V^T`, singular values descending.
fn thin_svd(ctx: &str, a: MatRef<'_, f64>) -> Result<(Mat<f64>, Vec<f64>, Mat<f64>)> {
    let (m, n) = a.shape();
    let k = m.min(n);
    let (mut u, mut v) = (Mat::zeros(m, k), Mat::zeros(n, k));
    let mut s = faer::diag::Diag::<f64>::zeros(k);
    let thin = fsvd::ComputeSvdVectors::Thin;
    let mut buf = MemBuffer::new(fsvd::svd_scratch::<f64>(
        m,
        n,
        thin,
        thin,
        Par::Seq,
        Default::default(),
    ));
    fsvd::svd(
        a,
        s.as_mut(),
        Some(u.as_mut()),
        Some(v.as_mut()),
        Par::Seq,
        MemStack::new(&mut buf),
        Default::default(),
    )
    .map_err(|e| {
        err(
            ctx,
            format!("the SVD of a {m}x{n} matrix did not converge ({e:?})"),
        )
    })?;
    Ok((u, s.column_vector().iter().copied().collect(), v))
}

/// Orthonormal basis of the columns of `y` (m ≥ l): thin Q of a Householder QR.
fn orthonormalize(mut y: Mat<f64>) -> Mat<f64> {
    let (m, l) = y.shape();
    let bs = qr::no_pivoting::factor::recommended_block_size::<f64>(m, l);
    let mut coeff = Mat::<f64>::zeros(bs, l);
    let mut buf = MemBuffer::new(qr::no_pivoting::factor::qr_in_place_scratch::<f64>(
        m,
        l,
        bs,
        Par::Seq,
        Default::default(),
    ));
    qr::no_pivoting::factor::qr_in_place(
        y.as_mut(),
        coeff.as_mut(),
        Par::Seq,
        MemStack::new(&mut buf),
        Default::default(),
    );
    // Householder basis: unit lower trapezoid.
    for j in 0..l {
        for i in 0..j {
            y[(i, j)] = 0.0;
        }
        y[(j, j)] = 1.0;
    }
    let mut q = Mat::<f64>::identity(m, l);
    let mut buf = MemBuffer::new(
        householder::apply_block_householder_sequence_on_the_left_in_place_scratch::<f64>(m, bs, l),
    );
    householder::apply_block_householder_sequence_on_the_left_in_place_with_conj(
        y.as_ref(),
        coeff.as_ref(),
        Conj::No,
        q.as_mut(),
        Par::Seq,
        MemStack::new(&mut buf),
    );
    q
}

/// Flip singular pairs so the largest-|.| entry of each column of `v` is positive.
fn fix_signs(mut v: MatMut<'_, f64>, mut u: Option<MatMut<'_, f64>>) {
    for j in 0..v.ncols() {
        let mut best = (0.0f64, 0usize);
        for i in 0..v.nrows() {
            if v[(i, j)].abs() > best.0 {
                best = (v[(i, j)].abs(), i);
            }
        }
        if v[(best.1, j)] < 0.0 {
            v.rb_mut().col_mut(j).iter_mut().for_each(|x| *x = -*x);
            if let Some(u) = u.as_mut() {
                u.rb_mut().col_mut(j).iter_mut().for_each(|x| *x = -*x);
            }
        }
    }
}

/// Smallest rank whose energy reaches `energy * total` (None if rounding keeps the sum below).
fn pick_rank(s: &[f64], energy: f64, total: f64) -> Option<usize> {
    let mut acc = 0.0;
    for (i, x) in s.iter().enumerate() {
        acc += x * x;
        if acc >= energy * total {
            return Some(i + 1);
        }
    }
    None
}

fn kept(s: &[f64], rank: usize, total: f64) -> f64 {
    s[..rank].iter().map(|x| x * x).sum::<f64>() / total
}

/// `diag(s) V^T` for the first `r` columns of `v` (n × ≥r).
fn coords_of(s: &[f64], v: MatRef<'_, f64>, r: usize) -> Mat<f64> {
    Mat::from_fn(r, v.nrows(), |i, j| s[i] * v[(j, i)])
}

/// An orthonormal basis (`n × d`, columns) of the row space of `b` (`m × n`): the leading right
/// singular vectors whose squared singular values hold `energy` of `||b||_F^2`. Projecting a
/// combination of `b`'s rows on it loses at most `1 - energy` of the rows' energy overall, so
/// scans over many such combinations run in `d` instead of `n` dimensions. An all-zero `b` gives
/// an error.
pub fn row_basis(b: Mat<f64>, energy: f64) -> Result<Mat<f64>> {
    let m = b.nrows().max(1);
    let c = svd_gram(&InMemory(b), energy, m, false)?;
    Ok(Mat::from_fn(c.coords.ncols(), c.rank, |i, j| {
        let s = c.singular[j];
        if s > 0.0 {
            c.coords[(j, i)] / s
        } else {
            0.0
        }
    }))
}

/// In-core SVD through the Gram matrix `G = B^T B` (`n × n`), for matrices with few columns
/// (material library: `m ~ 300k`, `n <= ~5000`). `B` is read in blocks of `row_block` rows; `G`
/// is accumulated block after block, its column tiles updated in parallel. `sigma = sqrt(eig(G))`;
/// the rank is the smallest whose `sum sigma_i^2 >= energy ||B||_F^2`. With `want_u`, a second
/// pass computes `U_r = B V_r Sigma_r^{-1}`. Signs: the largest-|.| entry of each `v_i` is
/// positive.
pub fn svd_gram(
    b: &dyn BlockSource,
    energy: f64,
    row_block: usize,
    want_u: bool,
) -> Result<Compressed> {
    const CTX: &str = "svd_gram";
    let (m, n) = check_shape(CTX, b)?;
    check_energy(CTX, energy)?;
    if row_block == 0 {
        return Err(err(
            CTX,
            "row_block = 0: expected a positive number of rows per block",
        ));
    }
    // Lower-trapezoidal column tiles of G: tile t holds G[j0.., j0..j1].
    const W: usize = 64;
    let col_tiles = ranges(n, W);
    let mut g_tiles: Vec<Mat<f64>> = col_tiles
        .iter()
        .map(|c| Mat::zeros(n - c.start, c.len()))
        .collect();
    for rows in ranges(m, row_block) {
        let (x, _) = read_tile(CTX, b, rows, 0..n)?;
        g_tiles
            .par_iter_mut()
            .zip(col_tiles.par_iter())
            .for_each(|(g, c)| {
                let lhs = x.as_ref().subcols(c.start, n - c.start).transpose();
                mm(
                    g.as_mut(),
                    Accum::Add,
                    lhs,
                    x.as_ref().subcols(c.start, c.len()),
                );
            });
    }
    let mut g = Mat::<f64>::zeros(n, n);
    for (t, c) in g_tiles.iter().zip(&col_tiles) {
        for jj in 0..c.len() {
            let j = c.start + jj;
            for i in j..n {
                let v = t[(i - c.start, jj)];
                g[(i, j)] = v;
                g[(j, i)] = v;
            }
        }
    }
    let total: f64 = (0..n).map(|i| g[(i, i)]).sum();
    if total <= 0.0 {
        return Err(err(
            CTX,
            "the matrix is all zeros: expected something to compress",
        ));
    }
    let mut evec = Mat::<f64>::zeros(n, n);
    let mut eval = faer::diag::Diag::<f64>::zeros(n);
    let mut buf = MemBuffer::new(faer::linalg::evd::self_adjoint_evd_scratch::<f64>(
        n,
        faer::linalg::evd::ComputeEigenvectors::Yes,
        Par::Seq,
        Default::default(),
    ));
    faer::linalg::evd::self_adjoint_evd(
        g.as_ref(),
        eval.as_mut(),
        Some(evec.as_mut()),
        Par::Seq,
        MemStack::new(&mut buf),
        Default::default(),
    )
    .map_err(|e| {
        err(
            CTX,
            format!("the eigen-decomposition of the {n}x{n} Gram matrix failed ({e:?})"),
        )
    })?;
    // Ascending eigenvalues -> descending singular values.
    let ev: Vec<f64> = eval.column_vector().iter().copied().collect();
    let singular: Vec<f64> = ev.iter().rev().map(|&l| l.max(0.0).sqrt()).collect();
    let rank = pick_rank(&singular, energy, total)
        .unwrap_or_else(|| singular.iter().filter(|&&s| s > 0.0).count().max(1));
    let mut v = Mat::from_fn(n, rank, |i, j| evec[(i, n - 1 - j)]);
    fix_signs(v.as_mut(), None);
    let coords = coords_of(&singular, v.as_ref(), rank);
    let u = if want_u {
        let scaled = Mat::from_fn(n, rank, |i, j| {
            if singular[j] > 0.0 {
                v[(i, j)] / singular[j]
            } else {
                0.0
            }
        });
        let blocks = ranges(m, row_block);
        let parts = blocks
            .par_iter()
            .map(|rows| -> Result<Mat<f64>> {
                let (x, _) = read_tile(CTX, b, rows.clone(), 0..n)?;
                let mut p = Mat::zeros(rows.len(), rank);
                mm(p.as_mut(), Accum::Replace, x.as_ref(), scaled.as_ref());
                Ok(p)
            })
            .collect::<Result<Vec<_>>>()?;
        let mut u = Mat::<f64>::zeros(m, rank);
        for (p, rows) in parts.iter().zip(&blocks) {
            u.as_mut().subrows_mut(rows.start, rows.len()).copy_from(p);
        }
        Some(u)
    } else {
        None
    };
    let kept_energy = kept(&singular, rank, total);
    Ok(Compressed {
        rank,
        singular,
        total_energy: total,
        kept_energy,
        coords,
        u,
        passes: 1 + want_u as usize,
        pilot_columns: 0,
        pilot_passes: 0,
    })
}

/// Settings of [`rsvd_streaming`].
#[derive(Debug, Clone)]
pub struct RsvdConfig {
    /// Fraction of `||B||_F^2` to keep, in (0, 1].
    pub energy: f64,
    /// Extra sketch columns beyond the rank guess (Halko et al. suggest 5–10).
    pub oversample: usize,
    /// Subspace iterations (each costs two passes over `B`).
    pub power_iters: usize,
    /// Largest rank returned; the sketch grows (doubling from 64) up to it.
    pub max_rank: usize,
    /// Columns per streamed chunk.
    pub chunk: usize,
    /// Rank the first sketch is sized for (0: 64). A guess at or above the rank needed saves the
    /// restart, i.e. `2 + 2 power_iters` passes over `B`.
    pub initial_rank: usize,
    /// Seed of the Gaussian test matrix (stream `k` for chunk `k`).
    pub seed: u64,
    /// Columns of the pilot (0, or at least the number of columns: none). With a pilot the
    /// randomized SVD above runs on `pilot` evenly spaced columns of `B` (column `j n / pilot`
    /// for `j < pilot`); then one pass projects every column of `B` on the pilot's whole
    /// sketch basis (`l` vectors: the rank the pilot needs plus the oversampling, a margin for
    /// the columns it did not see), and the rank is picked from the projection's singular
    /// values against `||B||_F^2` (so `kept_energy` is exact for the whole matrix). Where that
    /// basis cannot keep `energy` of the whole matrix, the randomized SVD runs on all of `B`.
    pub pilot: usize,
}

/// `B X` (`m × l`) and `||B||_F^2`: chunks of columns in order, row tiles of each chunk in
/// parallel. The products run in single precision (twice the double-precision rate; the
/// matrix is stored in half or single precision anyway), accumulated per row tile.
fn times_right(
    ctx: &str,
    b: &dyn BlockSource,
    x: MatRef<'_, f64>,
    chunk: usize,
) -> Result<(Mat<f64>, f64)> {
    let (m, n) = (b.rows(), b.cols());
    let l = x.ncols();
    let x = to_f32(x);
    let row_tiles = ranges(m, tile_rows(m));
    let mut parts: Vec<(Mat<f32>, f64)> = row_tiles
        .iter()
        .map(|r| (Mat::zeros(r.len(), l), 0.0))
        .collect();
    let chunks = ranges(n, chunk);
    if let Some(first) = chunks.first() {
        b.prefetch(first.clone());
    }
    for (k, cols) in chunks.iter().enumerate() {
        if let Some(next) = chunks.get(k + 1) {
            b.prefetch(next.clone());
        }
        let cols = cols.clone();
        parts
            .par_iter_mut()
            .zip(row_tiles.par_iter())
            .try_for_each(|((y, ss), rows)| -> Result<()> {
                let (t, s) = read_tile_f32(ctx, b, rows.clone(), cols.clone())?;
                *ss += s;
                mm32(
                    y.as_mut(),
                    Accum::Add,
                    t.as_ref(),
                    x.subrows(cols.start, cols.len()),
                );
                Ok(())
            })?;
    }
    let mut y = Mat::<f64>::zeros(m, l);
    let mut total = 0.0;
    for ((p, s), rows) in parts.iter().zip(&row_tiles) {
        y.as_mut()
            .subrows_mut(rows.start, rows.len())
            .copy_from(to_f64(p.as_ref()));
        total += s;
    }
    Ok((y, total))
}

/// `B^T Q` (`n × l`) and `||B||_F^2`: chunks of columns in parallel, row tiles of each chunk in
/// order, in single precision as [`times_right`].
fn times_left_t(
    ctx: &str,
    b: &dyn BlockSource,
    q: MatRef<'_, f64>,
    chunk: usize,
) -> Result<(Mat<f64>, f64)> {
    let (m, n) = (b.rows(), b.cols());
    let l = q.ncols();
    let q = to_f32(q);
    let chunks = ranges(n, chunk);
    let row_tiles = ranges(m, tile_rows(m));
    let parts = chunks
        .par_iter()
        .map(|cols| -> Result<(Mat<f32>, f64)> {
            // Threads take runs of consecutive chunks: the next one is likely this thread's.
            b.prefetch(cols.clone());
            b.prefetch(cols.end..(cols.end + chunk).min(n));
            let mut z = Mat::zeros(cols.len(), l);
            let mut ss = 0.0;
            for rows in &row_tiles {
                let (t, s) = read_tile_f32(ctx, b, rows.clone(), cols.clone())?;
                ss += s;
                mm32(
                    z.as_mut(),
                    Accum::Add,
                    t.as_ref().transpose(),
                    q.subrows(rows.start, rows.len()),
                );
            }
            Ok((z, ss))
        })
        .collect::<Result<Vec<_>>>()?;
    let mut z = Mat::<f64>::zeros(n, l);
    let mut total = 0.0;
    for ((p, ss), cols) in parts.iter().zip(&chunks) {
        z.as_mut()
            .subrows_mut(cols.start, cols.len())
            .copy_from(to_f64(p.as_ref()));
        total += ss;
    }
    Ok((z, total))
}

/// Randomized SVD with subspace iterations (Halko et al. 2011, Alg. 4.4), streaming over column
/// chunks of `cfg.chunk` columns: memory `O((m + n) l)` for a sketch of width `l`, never `O(m n)`.
///
/// Passes: `Y = B Omega` (and `||B||_F^2`), then `power_iters` times `Z = orth(B^T Q)`,
/// `Q = orth(B Z)`, then `C^T = B^T Q` and the SVD of the small `C`. The sketch starts at
/// `l = min(initial_rank, max_rank) + oversample` (`initial_rank` 0 means 64); when the energy needs more than `l - oversample`
/// values it doubles (restarting) until `max_rank`, after which `max_rank` is kept and
/// `kept_energy` says honestly how much that is. Each attempt makes `2 + 2 power_iters` passes.
/// With `cfg.pilot`, those passes read the pilot's columns only, and one more pass reads `B`.
pub fn rsvd_streaming(b: &dyn BlockSource, cfg: &RsvdConfig, want_u: bool) -> Result<Compressed> {
    rsvd_streaming_with(b, cfg, want_u, &|_| {})
}

/// [`rsvd_streaming`], calling `on_pass` after every pass over `B` with a line saying where it
/// is: the attempt, the pass of that attempt, the sketch width, the mean time per pass and the
/// time left in the attempt (a pass over a large matrix takes minutes).
pub fn rsvd_streaming_with(
    b: &dyn BlockSource,
    cfg: &RsvdConfig,
    want_u: bool,
    on_pass: &dyn Fn(&str),
) -> Result<Compressed> {
    let basis = if want_u { Basis::Rank } else { Basis::None };
    rsvd_basis(b, cfg, basis, on_pass)
}

/// Which left singular vectors [`rsvd_basis`] returns in `Compressed::u`.
#[derive(Clone, Copy, PartialEq)]
enum Basis {
    None,
    /// The `rank` kept.
    Rank,
    /// All of the sketch's `l` (a pilot's basis: the columns past the rank are its margin).
    Sketch,
}

fn rsvd_basis(
    b: &dyn BlockSource,
    cfg: &RsvdConfig,
    basis: Basis,
    on_pass: &dyn Fn(&str),
) -> Result<Compressed> {
    const CTX: &str = "rsvd_streaming";
    let (m, n) = check_shape(CTX, b)?;
    check_energy(CTX, cfg.energy)?;
    if cfg.chunk == 0 || cfg.max_rank == 0 {
        return Err(err(
            CTX,
            format!(
                "chunk = {}, max_rank = {}: expected both positive",
                cfg.chunk, cfg.max_rank
            ),
        ));
    }
    if cfg.pilot > 0 && cfg.pilot < n {
        return rsvd_pilot(b, cfg, basis != Basis::None, on_pass);
    }
    let full = m.min(n);
    let kmax = cfg.max_rank.min(full);
    let mut guess = kmax.min(if cfg.initial_rank == 0 {
        64
    } else {
        cfg.initial_rank
    });
    let mut passes = 0;
    let per_attempt = 2 + 2 * cfg.power_iters;
    let mut attempt = 0;
    loop {
        let l = (guess + cfg.oversample).min(full);
        attempt += 1;
        let started = std::time::Instant::now();
        let mut in_attempt = 0;
        let mut tick = || {
            in_attempt += 1;
            let per = started.elapsed().as_secs_f64() / in_attempt as f64;
            on_pass(&format!(
                "attempt {attempt}, pass {in_attempt}/{per_attempt} (sketch of {l} columns), {per:.1} s per pass, {:.0} s left in this attempt",
                per * (per_attempt - in_attempt) as f64
            ));
        };
        let chunks = ranges(n, cfg.chunk);
        let mut omega = Mat::<f64>::zeros(n, l);
        for (k, cols) in chunks.iter().enumerate() {
            let mut rng = Rng::stream(cfg.seed, k as u64);
            for i in cols.clone() {
                for j in 0..l {
                    omega[(i, j)] = rng.normal();
                }
            }
        }
        let (y, total) = times_right(CTX, b, omega.as_ref(), cfg.chunk)?;
        passes += 1;
        tick();
        if total <= 0.0 {
            return Err(err(
                CTX,
                "the matrix is all zeros: expected something to compress",
            ));
        }
        let mut q = orthonormalize(y);
        for _ in 0..cfg.power_iters {
            let z = orthonormalize(times_left_t(CTX, b, q.as_ref(), cfg.chunk)?.0);
            tick();
            q = orthonormalize(times_right(CTX, b, z.as_ref(), cfg.chunk)?.0);
            tick();
            passes += 2;
        }
        let ct = times_left_t(CTX, b, q.as_ref(), cfg.chunk)?.0; // n × l = C^T
        passes += 1;
        tick();
        // C^T = W S Uhat^T, so C = Uhat S W^T: right singular vectors of B ~ W, left ~ Q Uhat.
        let (mut w, s, mut uhat) = thin_svd(CTX, ct.as_ref())?;
        let trusted = if l == full { l } else { guess };
        let found = pick_rank(&s, cfg.energy, total);
        let rank = match found {
            Some(r) if r <= trusted => r,
            _ if guess < kmax && l < full => {
                guess = (2 * guess).min(kmax);
                continue;
            }
            _ => found.unwrap_or(l).min(kmax),
        };
        fix_signs(w.as_mut(), Some(uhat.as_mut()));
        let coords = coords_of(&s, w.as_ref(), rank);
        let width = match basis {
            Basis::None => 0,
            Basis::Rank => rank,
            Basis::Sketch => uhat.ncols(),
        };
        let u = (width > 0).then(|| {
            let mut u = Mat::zeros(m, width);
            mm(
                u.as_mut(),
                Accum::Replace,
                q.as_ref(),
                uhat.as_ref().subcols(0, width),
            );
            u
        });
        let kept_energy = kept(&s, rank, total);
        return Ok(Compressed {
            rank,
            singular: s,
            total_energy: total,
            kept_energy,
            coords,
            u,
            passes,
            pilot_columns: 0,
            pilot_passes: 0,
        });
    }
}

/// Some columns of a matrix, in order: `B[:, cols]`.
struct Columns<'a> {
    b: &'a dyn BlockSource,
    cols: Vec<usize>,
}

impl Columns<'_> {
    /// Read the view's columns `cols` one source column at a time into `out`'s columns.
    fn read_each<T>(
        &self,
        cols: Range<usize>,
        mut out: MatMut<'_, T>,
        mut read: impl FnMut(Range<usize>, MatMut<'_, T>) -> Result<()>,
    ) -> Result<()> {
        if cols.end > self.cols.len() || out.ncols() != cols.len() {
            return Err(err(
                "Columns::read_block",
                format!(
                    "columns {cols:?} into a buffer of {} columns: expected columns inside the \
                     view's {} matching the buffer",
                    out.ncols(),
                    self.cols.len()
                ),
            ));
        }
        for (o, j) in cols.enumerate() {
            let c = self.cols[j];
            read(c..c + 1, out.rb_mut().subcols_mut(o, 1))?;
        }
        Ok(())
    }
}

impl BlockSource for Columns<'_> {
    fn rows(&self) -> usize {
        self.b.rows()
    }
    fn cols(&self) -> usize {
        self.cols.len()
    }
    fn read_block(
        &self,
        rows: Range<usize>,
        cols: Range<usize>,
        out: MatMut<'_, f64>,
    ) -> Result<()> {
        self.read_each(cols, out, |c, o| self.b.read_block(rows.clone(), c, o))
    }
    fn read_block_f32(
        &self,
        rows: Range<usize>,
        cols: Range<usize>,
        out: MatMut<'_, f32>,
    ) -> Result<()> {
        self.read_each(cols, out, |c, o| self.b.read_block_f32(rows.clone(), c, o))
    }
    fn prefetch(&self, cols: Range<usize>) {
        for &c in self.cols.get(cols).unwrap_or(&[]) {
            self.b.prefetch(c..c + 1);
        }
    }
}

/// [`rsvd_streaming_with`] with a pilot (`0 < cfg.pilot < n`, see [`RsvdConfig::pilot`]): the
/// basis from the pilot's columns, then one pass projecting all of `B` on it.
fn rsvd_pilot(
    b: &dyn BlockSource,
    cfg: &RsvdConfig,
    want_u: bool,
    on_pass: &dyn Fn(&str),
) -> Result<Compressed> {
    const CTX: &str = "rsvd_streaming";
    let n = b.cols();
    let view = Columns {
        b,
        cols: (0..cfg.pilot).map(|j| j * n / cfg.pilot).collect(),
    };
    let p = view.cols.len();
    let pilot = rsvd_basis(
        &view,
        &RsvdConfig {
            pilot: 0,
            ..cfg.clone()
        },
        Basis::Sketch,
        &|msg| on_pass(&format!("pilot of {p} of {n} columns: {msg}")),
    )?;
    let full = || {
        rsvd_streaming_with(
            b,
            &RsvdConfig {
                pilot: 0,
                ..cfg.clone()
            },
            want_u,
            on_pass,
        )
    };
    let Some(basis) = pilot.u else {
        return full();
    };
    let started = std::time::Instant::now();
    // C^T = B^T U_p (n × r_p): every column's coordinates in the pilot's basis.
    let (ct, total) = times_left_t(CTX, b, basis.as_ref(), cfg.chunk)?;
    on_pass(&format!(
        "projection of all {n} columns on the pilot's {} basis vectors, {:.1} s",
        basis.ncols(),
        started.elapsed().as_secs_f64()
    ));
    if total <= 0.0 {
        return Err(err(
            CTX,
            "the matrix is all zeros: expected something to compress",
        ));
    }
    // C^T = W S Uhat^T: the SVD of the projection U_p U_p^T B, whose energy is exact.
    let (mut w, s, mut uhat) = thin_svd(CTX, ct.as_ref())?;
    let Some(rank) = pick_rank(&s, cfg.energy, total) else {
        on_pass(&format!(
            "the pilot's basis keeps {:.4} % of the energy of all columns, below {:.4} %: \
             the randomized SVD runs on all of them",
            100.0 * kept(&s, s.len(), total),
            100.0 * cfg.energy
        ));
        return full();
    };
    fix_signs(w.as_mut(), Some(uhat.as_mut()));
    let coords = coords_of(&s, w.as_ref(), rank);
    let u = want_u.then(|| {
        let mut u = Mat::zeros(basis.nrows(), rank);
        mm(
            u.as_mut(),
            Accum::Replace,
            basis.as_ref(),
            uhat.as_ref().subcols(0, rank),
        );
        u
    });
    let kept_energy = kept(&s, rank, total);
    Ok(Compressed {
        rank,
        singular: s,
        total_energy: total,
        kept_energy,
        coords,
        u,
        passes: 1,
        pilot_columns: p,
        pilot_passes: pilot.passes,
    })
}

/// How [`cx`] chooses columns.
#[derive(Debug, Clone, Copy)]
pub enum CxMethod {
    /// Sampling without replacement by rank-k leverage scores (Drineas et al. 2008).
    Leverage { seed: u64 },
    /// The pivots of a column-pivoted QR (deterministic, greedy).
    PivotedQr,
}

/// A CX decomposition `A ~ A[:, columns] X`.
#[derive(Debug, Clone)]
pub struct Cx {
    /// Indices into `0..n`, in selection order.
    pub columns: Vec<usize>,
    /// `c × n` weights.
    pub x: Mat<f64>,
    /// `||A - A[:, columns] X||_F / ||A||_F`, measured.
    pub rel_error: f64,
}

/// `C X` (any product `a b`: sequential, so deterministic whatever the thread count).
pub fn reconstruct(a_cols: MatRef<'_, f64>, x: MatRef<'_, f64>) -> Mat<f64> {
    let mut out = Mat::zeros(a_cols.nrows(), x.ncols());
    mm(out.as_mut(), Accum::Replace, a_cols, x);
    out
}

fn gather(a: MatRef<'_, f64>, cols: &[usize]) -> Mat<f64> {
    Mat::from_fn(a.nrows(), cols.len(), |i, j| a[(i, cols[j])])
}

/// `||A - A[:, cols] X||_F / norm_a`, over fixed column tiles in parallel, summed in order.
fn rel_residual(a: MatRef<'_, f64>, cols: &[usize], x: MatRef<'_, f64>, norm_a: f64) -> f64 {
    let c = gather(a, cols);
    let tiles = ranges(a.ncols(), 2048);
    let parts: Vec<f64> = tiles
        .par_iter()
        .map(|t| {
            let mut r = a.subcols(t.start, t.len()).to_owned();
            matmul(
                r.as_mut(),
                Accum::Add,
                c.as_ref(),
                x.subcols(t.start, t.len()),
                -1.0,
                Par::Seq,
            );
            let mut ss = 0.0;
            for j in 0..r.ncols() {
                ss += r.col_as_slice(j).iter().map(|v| v * v).sum::<f64>();
            }
            ss
        })
        .collect();
    parts.iter().sum::<f64>().sqrt() / norm_a
}

/// CX decomposition of `a` (`r × n`, e.g. `Compressed::coords`, paper Sec. 4.1/5.1): the fewest
/// columns (at most `max_cols`) whose span reconstructs `a` to `max_rel_error` in Frobenius norm.
/// If that cannot be met, the best found at `max_cols` is returned with its measured error.
pub fn cx(a: MatRef<'_, f64>, max_rel_error: f64, method: CxMethod, max_cols: usize) -> Result<Cx> {
    const CTX: &str = "cx";
    let (r, n) = a.shape();
    if r == 0 || n == 0 {
        return Err(err(
            CTX,
            format!("the matrix is {r}x{n}: expected at least one row and one column"),
        ));
    }
    if !(max_rel_error >= 0.0 && max_rel_error.is_finite()) || max_cols == 0 {
        let msg = format!(
            "max_rel_error = {max_rel_error}, max_cols = {max_cols}: expected a finite error \
             >= 0 and at least one column"
        );
        return Err(err(CTX, msg));
    }
    let mut ss = 0.0;
    for j in 0..n {
        for i in 0..r {
            let v = a[(i, j)];
            if !v.is_finite() {
                return Err(err(
                    CTX,
                    format!("entry ({i}, {j}) is {v}: expected finite values"),
                ));
            }
            ss += v * v;
        }
    }
    if ss == 0.0 {
        return Err(err(
            CTX,
            "the matrix is all zeros: expected columns to choose from",
        ));
    }
    let norm_a = ss.sqrt();
    match method {
        CxMethod::PivotedQr => cx_pivoted(a, max_rel_error, max_cols, norm_a),
        CxMethod::Leverage { seed } => cx_leverage(a, max_rel_error, max_cols, norm_a, seed),
    }
}

fn cx_pivoted(a: MatRef<'_, f64>, tol: f64, max_cols: usize, norm_a: f64) -> Result<Cx> {
    let (r, n) = a.shape();
    let size = r.min(n);
    let mut qr_mat = a.to_owned();
    let bs = qr::no_pivoting::factor::recommended_block_size::<f64>(r, n);
    let mut coeff = Mat::<f64>::zeros(bs, size);
    let (mut fwd, mut bwd) = (vec![0usize; n], vec![0usize; n]);
    let mut buf = MemBuffer::new(qr::col_pivoting::factor::qr_in_place_scratch::<usize, f64>(
        r,
        n,
        bs,
        Par::Seq,
        Default::default(),
    ));
    qr::col_pivoting::factor::qr_in_place(
        qr_mat.as_mut(),
        coeff.as_mut(),
        &mut fwd,
        &mut bwd,
        Par::Seq,
        MemStack::new(&mut buf),
        Default::default(),
    );
    // R is the upper trapezoid; column j of A P is column fwd[j] of A. Keeping the first c pivots
    // leaves ||R[c.., c..]||_F = sqrt(sum_{i >= c} ||R[i, i..]||^2).
    let row_ss: Vec<f64> = (0..size)
        .map(|i| (i..n).map(|j| qr_mat[(i, j)].powi(2)).sum())
        .collect();
    let mut tail = vec![0.0; size + 1];
    for i in (0..size).rev() {
        tail[i] = tail[i + 1] + row_ss[i];
    }
    let r00 = qr_mat[(0, 0)].abs();
    let numerical_rank = (0..size)
        .take_while(|&i| qr_mat[(i, i)].abs() > 1e-13 * r00)
        .count()
        .max(1);
    let cmax = max_cols.min(numerical_rank);
    let c = (1..=cmax)
        .find(|&c| tail[c].sqrt() <= tol * norm_a)
        .unwrap_or(cmax);
    // X P = [I, R11^{-1} R12].
    let mut t = qr_mat.as_ref().submatrix(0, c, c, n - c).to_owned();
    triangular_solve::solve_upper_triangular_in_place(
        qr_mat.as_ref().submatrix(0, 0, c, c),
        t.as_mut(),
        Par::Seq,
    );
    let mut x = Mat::<f64>::zeros(c, n);
    for (k, &col) in fwd.iter().enumerate() {
        if k < c {
            x[(k, col)] = 1.0;
        } else {
            for i in 0..c {
                x[(i, col)] = t[(i, k - c)];
            }
        }
    }
    let columns = fwd[..c].to_vec();
    let rel_error = rel_residual(a, &columns, x.as_ref(), norm_a);
    Ok(Cx {
        columns,
        x,
        rel_error,
    })
}

/// `(g + mu I)⁻¹` of a symmetric positive semi-definite `g` (`mu > 0`), through its SVD
/// (sequential: deterministic whatever the thread count).
pub fn ridge_inverse(g: MatRef<'_, f64>, mu: f64) -> Result<Mat<f64>> {
    let (u, s, v) = thin_svd("ridge_inverse", g)?;
    let vs = Mat::from_fn(v.nrows(), s.len(), |i, j| v[(i, j)] / (s[j] + mu));
    let mut out = Mat::zeros(v.nrows(), u.nrows());
    mm(
        out.as_mut(),
        Accum::Replace,
        vs.as_ref(),
        u.as_ref().transpose(),
    );
    Ok(out)
}

/// `X = C^+ A` with a rank-truncated pseudoinverse of `C = A[:, cols]`, and its error.
fn fit_columns(a: MatRef<'_, f64>, cols: &[usize], norm_a: f64) -> Result<Cx> {
    let c = gather(a, cols);
    let (u, s, v) = thin_svd("cx", c.as_ref())?;
    let cut = s.first().copied().unwrap_or(0.0) * 1e-12 * (c.nrows().max(c.ncols()) as f64);
    let k = s.iter().take_while(|&&x| x > cut).count();
    let mut uta = Mat::zeros(k, a.ncols());
    mm(
        uta.as_mut(),
        Accum::Replace,
        u.as_ref().subcols(0, k).transpose(),
        a,
    );
    let vs = Mat::from_fn(cols.len(), k, |i, j| v[(i, j)] / s[j]);
    let x = reconstruct(vs.as_ref(), uta.as_ref());
    let rel_error = rel_residual(a, cols, x.as_ref(), norm_a);
    Ok(Cx {
        columns: cols.to_vec(),
        x,
        rel_error,
    })
}

fn cx_leverage(
    a: MatRef<'_, f64>,
    tol: f64,
    max_cols: usize,
    norm_a: f64,
    seed: u64,
) -> Result<Cx> {
    let n = a.ncols();
    let (_, s, v) = thin_svd("cx", a)?;
    // k: the numerical rank at the threshold (best rank-k error <= tol).
    let total: f64 = s.iter().map(|x| x * x).sum();
    let mut k = s.len();
    let mut tail = 0.0;
    for i in (0..s.len()).rev() {
        tail += s[i] * s[i];
        if tail > tol * tol * total {
            break;
        }
        k = i;
    }
    let k = k.max(1);
    // Weighted sampling without replacement (Efraimidis & Spirakis): sort by Exp(1) / p_j.
    // Any prefix of this order is a sample of that size, so the error falls as c grows.
    let mut rng = Rng::new(seed);
    let mut keys: Vec<(f64, usize)> = (0..n)
        .map(|j| {
            let p = (0..k).map(|i| v[(j, i)].powi(2)).sum::<f64>() / k as f64;
            let e = -(1.0 - rng.uniform()).ln();
            (if p > 0.0 { e / p } else { f64::INFINITY }, j)
        })
        .collect();
    keys.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
    let order: Vec<usize> = keys.iter().map(|x| x.1).collect();
    let cmax = max_cols.min(n);
    // Doubling from k, then bisection between the last failure and the first success.
    let (mut lo, mut c) = (0, k.min(cmax));
    let mut best = loop {
        let fit = fit_columns(a, &order[..c], norm_a)?;
        if fit.rel_error <= tol || c == cmax {
            break fit;
        }
        lo = c;
        c = (2 * c).min(cmax);
    };
    if best.rel_error <= tol {
        let mut hi = c;
        while hi - lo > 1 {
            let mid = (lo + hi) / 2;
            let fit = fit_columns(a, &order[..mid], norm_a)?;
            if fit.rel_error <= tol {
                hi = mid;
                best = fit;
            } else {
                lo = mid;
            }
        }
    }
    Ok(best)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gaussian(m: usize, n: usize, seed: u64) -> Mat<f64> {
        let mut rng = Rng::new(seed);
        Mat::from_fn(m, n, |_, _| rng.normal())
    }

    /// `U diag(s) V^T` with random orthonormal `U`, `V`.
    fn with_spectrum(m: usize, n: usize, s: &[f64], seed: u64) -> Mat<f64> {
        let u = orthonormalize(gaussian(m, s.len(), seed));
        let v = orthonormalize(gaussian(n, s.len(), seed + 1));
        let us = Mat::from_fn(m, s.len(), |i, j| u[(i, j)] * s[j]);
        reconstruct(us.as_ref(), v.as_ref().transpose())
    }

    fn max_abs(a: MatRef<'_, f64>) -> f64 {
        let mut m = 0.0f64;
        for j in 0..a.ncols() {
            for i in 0..a.nrows() {
                m = m.max(a[(i, j)].abs());
            }
        }
        m
    }

    fn orthonormality_error(u: MatRef<'_, f64>) -> f64 {
        let g = reconstruct(u.transpose(), u);
        max_abs((g - Mat::<f64>::identity(u.ncols(), u.ncols())).as_ref())
    }

    fn bits(c: &Compressed) -> Vec<u64> {
        let mut v: Vec<u64> = c.singular.iter().map(|x| x.to_bits()).collect();
        for j in 0..c.coords.ncols() {
            v.extend(c.coords.col_as_slice(j).iter().map(|x| x.to_bits()));
        }
        if let Some(u) = &c.u {
            for j in 0..u.ncols() {
                v.extend(u.col_as_slice(j).iter().map(|x| x.to_bits()));
            }
        }
        v
    }

    #[test]
    fn a_truncated_decomposition_equals_one_run_at_the_lower_energy() {
        let s: Vec<f64> = (0..12).map(|i| 10.0 * 0.5f64.powi(i)).collect();
        let b = with_spectrum(300, 60, &s, 5);
        let fine = svd_gram(&InMemory(b.clone()), 0.999999, 64, true).unwrap();
        for energy in [0.9, 0.99, 0.999] {
            let direct = svd_gram(&InMemory(b.clone()), energy, 64, true).unwrap();
            let cut = fine.truncated(energy);
            assert!(
                cut.rank < fine.rank,
                "{energy}: {} vs {}",
                cut.rank,
                fine.rank
            );
            assert_eq!(cut.rank, direct.rank);
            assert_eq!(cut.kept_energy, direct.kept_energy);
            assert_eq!(cut.coords, direct.coords, "{energy}");
            assert_eq!(cut.u, direct.u, "{energy}");
        }
        // At or above the kept energy: the whole decomposition.
        assert_eq!(fine.truncated(1.0).rank, fine.rank);
    }

    #[test]
    fn svd_gram_matches_faer_svd() {
        // Rank 10 (sigma_i = 10 * 0.6^i) plus noise 1e-4: noise sigmas ~ 2.5e-3.
        let s: Vec<f64> = (0..10).map(|i| 10.0 * 0.6f64.powi(i)).collect();
        let mut b = with_spectrum(600, 80, &s, 3);
        let noise = gaussian(600, 80, 9);
        b += noise * faer::Scale(1e-4);
        let reference = b.as_ref().thin_svd().unwrap();
        let sref: Vec<f64> = reference.S().column_vector().iter().copied().collect();
        let c = svd_gram(&InMemory(b.clone()), 0.99999, 128, true).unwrap();
        assert_eq!(c.singular.len(), 80);
        // Through the Gram matrix the absolute error is ~ eps sigma_1^2 / sigma_i, i.e. ~1e-11
        // for the noise values (2.5e-3): 1e-8 relative holds for all of them here.
        let worst = sref
            .iter()
            .zip(&c.singular)
            .map(|(a, b)| (a - b).abs() / a)
            .fold(0.0, f64::max);
        eprintln!(
            "svd_gram: worst relative sigma error {worst:.2e}, rank {}, kept {:.8}",
            c.rank, c.kept_energy
        );
        assert!(worst < 1e-8);
        // Energy rule: the tail after sigma_8 is 6e-5 of the energy, the noise 3e-6.
        assert_eq!(c.rank, 10);
        assert!(c.kept_energy >= 0.99999);
        let total = b.squared_norm_l2();
        assert!((c.total_energy - total).abs() < 1e-12 * total);
        // coords = Sigma V^T = U^T B, and they match faer's V up to the sign convention.
        let u = c.u.as_ref().unwrap();
        assert!(orthonormality_error(u.as_ref()) < 1e-10);
        let utb = reconstruct(u.as_ref().transpose(), b.as_ref());
        assert!(max_abs((&utb - &c.coords).as_ref()) < 1e-10 * s[0]);
        for (i, &si) in sref.iter().enumerate().take(c.rank) {
            let v = reference.V().col(i);
            let sign = if (0..80).map(|j| v[j] * c.coords[(i, j)]).sum::<f64>() >= 0.0 {
                1.0
            } else {
                -1.0
            };
            let d = (0..80)
                .map(|j| (sign * si * v[j] - c.coords[(i, j)]).abs())
                .fold(0.0, f64::max);
            assert!(d < 1e-9 * s[0], "coords row {i} differs by {d}");
        }
        // The discarded energy is the residual of B ~ U coords.
        let resid = (&b - reconstruct(u.as_ref(), c.coords.as_ref())).squared_norm_l2();
        assert!((resid / total - (1.0 - c.kept_energy)).abs() < 1e-10);
    }

    fn pool(threads: usize) -> rayon::ThreadPool {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
    }

    /// The decomposition `c` of `b` is bit for bit the one computed on 1 and on 2 threads.
    fn same_on_one_and_two_threads(b: &InMemory, cfg: &RsvdConfig, c: &Compressed) {
        let one = pool(1).install(|| rsvd_streaming(b, cfg, true).unwrap());
        let two = pool(2).install(|| rsvd_streaming(b, cfg, true).unwrap());
        assert_eq!(bits(&one), bits(&two));
        assert_eq!(bits(&one), bits(c));
    }

    /// The randomized SVD's settings in these tests: `energy` and `pilot` vary.
    fn test_config(energy: f64, pilot: usize) -> RsvdConfig {
        RsvdConfig {
            energy,
            oversample: 10,
            power_iters: 2,
            max_rank: 400,
            chunk: 100,
            seed: 5,
            initial_rank: 0,
            pilot,
        }
    }

    #[test]
    fn rsvd_streaming_accurate_and_deterministic() {
        let s: Vec<f64> = (0..300).map(|i| 0.8f64.powi(i)).collect();
        let b = InMemory(with_spectrum(3000, 1500, &s, 11));
        let cfg = test_config(0.999999, 0);
        let c = rsvd_streaming(&b, &cfg, true).unwrap();
        let worst = (0..20)
            .map(|i| (c.singular[i] - s[i]).abs() / s[i])
            .fold(0.0, f64::max);
        eprintln!(
            "rsvd: rank {}, kept {:.9}, passes {}, worst rel. error of top 20 sigmas {worst:.2e}",
            c.rank, c.kept_energy, c.passes
        );
        assert!(worst < 1e-6);
        // 0.64^k <= 1e-6 first at k = 31.
        assert_eq!(c.rank, 31);
        assert!(c.kept_energy >= cfg.energy);
        assert_eq!(c.passes, 2 + 2 * cfg.power_iters);
        assert!(orthonormality_error(c.u.as_ref().unwrap().as_ref()) < 1e-12);
        // Run to run and across thread counts: bit-identical; the pass reports change nothing.
        let lines = std::sync::Mutex::new(Vec::new());
        let again = rsvd_streaming_with(&b, &cfg, true, &|m| {
            lines.lock().unwrap().push(m.to_string())
        })
        .unwrap();
        assert_eq!(bits(&c), bits(&again));
        let lines = lines.into_inner().unwrap();
        assert_eq!(lines.len(), c.passes, "{lines:?}");
        assert!(
            lines[0].starts_with("attempt 1, pass 1/6 (sketch of 74 columns)"),
            "{}",
            lines[0]
        );
        same_on_one_and_two_threads(&b, &cfg, &c);
        let g1 = pool(1).install(|| svd_gram(&b, 0.999, 256, true).unwrap());
        let g2 = pool(2).install(|| svd_gram(&b, 0.999, 256, true).unwrap());
        assert_eq!(bits(&g1), bits(&g2));
        // Too little rank allowed: the sketch doubles 64 -> 100 and reports what it keeps.
        let slow: Vec<f64> = (0..300).map(|i| 0.95f64.powi(i)).collect();
        let b2 = InMemory(with_spectrum(1200, 900, &slow, 12));
        let cfg2 = RsvdConfig {
            energy: 1.0 - 1e-12,
            max_rank: 100,
            ..cfg
        };
        let c2 = rsvd_streaming(&b2, &cfg2, false).unwrap();
        let exact_kept = slow[..100].iter().map(|x| x * x).sum::<f64>()
            / slow.iter().map(|x| x * x).sum::<f64>();
        eprintln!(
            "rsvd capped: rank {}, kept {:.9} (best possible {exact_kept:.9}), passes {}",
            c2.rank, c2.kept_energy, c2.passes
        );
        assert_eq!(c2.rank, 100);
        assert!(c2.kept_energy <= exact_kept + 1e-12 && c2.kept_energy > exact_kept - 1e-6);
        assert_eq!(c2.passes, 2 * (2 + 2 * cfg.power_iters));
    }

    #[test]
    fn a_pilot_finds_the_basis_in_one_pass_over_the_whole_matrix() {
        let s: Vec<f64> = (0..300).map(|i| 0.8f64.powi(i)).collect();
        let b = InMemory(with_spectrum(2000, 1500, &s, 13));
        let cfg = test_config(0.9999, 200);
        let whole = rsvd_streaming(
            &b,
            &RsvdConfig {
                pilot: 0,
                ..cfg.clone()
            },
            true,
        )
        .unwrap();
        let lines = std::sync::Mutex::new(Vec::new());
        let c = rsvd_streaming_with(&b, &cfg, true, &|m| {
            lines.lock().unwrap().push(m.to_string())
        })
        .unwrap();
        let lines = lines.into_inner().unwrap();
        eprintln!(
            "pilot: rank {} (whole: {}), kept {:.9} (whole: {:.9}), {lines:?}",
            c.rank, whole.rank, c.kept_energy, whole.kept_energy
        );
        // One pass over B, the pilot's six over its 200 columns, and the energy kept is B's.
        assert_eq!((c.passes, c.pilot_columns, c.pilot_passes), (1, 200, 6));
        assert_eq!(lines.len(), 7);
        assert!(lines[0].starts_with("pilot of 200 of 1500 columns: attempt 1, pass 1/6"));
        assert!(c.kept_energy >= cfg.energy);
        assert!(
            c.rank <= whole.rank + 1,
            "{} against {}",
            c.rank,
            whole.rank
        );
        assert!((c.total_energy - whole.total_energy).abs() < 1e-9 * whole.total_energy);
        // The coordinates are B's projected on U: U^T B, so U coords reconstructs B to the
        // energy not kept, and the leading singular values are B's.
        let u = c.u.as_ref().unwrap();
        assert!(orthonormality_error(u.as_ref()) < 1e-12);
        let mut r = b.0.clone();
        mm(r.as_mut(), Accum::Add, u.as_ref(), (-&c.coords).as_ref());
        let lost = r.squared_norm_l2() / c.total_energy;
        assert!((lost - (1.0 - c.kept_energy)).abs() < 1e-9, "{lost}");
        // Its singular values are those of the projection U U^T B, at most B's: the pilot's
        // basis is not exactly B's leading subspace, so they differ beyond rounding.
        let worst = (0..10)
            .map(|i| (c.singular[i] - s[i]).abs() / s[i])
            .fold(0.0, f64::max);
        eprintln!("worst rel. error of the top 10 sigmas: {worst:.2e}");
        assert!(worst < 1e-4);
        same_on_one_and_two_threads(&b, &cfg, &c);
        // Columns the pilot never sees that carry a direction of their own: its basis cannot
        // keep the energy, and the randomized SVD runs on the whole matrix instead.
        let mut odd = b.0.clone();
        for j in (1..1500).step_by(150) {
            // Column j is not a pilot column (those are multiples of 7.5).
            odd[(0, j)] += 50.0;
        }
        let odd = InMemory(odd);
        let lines = std::sync::Mutex::new(Vec::new());
        let f = rsvd_streaming_with(&odd, &cfg, false, &|m| {
            lines.lock().unwrap().push(m.to_string())
        })
        .unwrap();
        let lines = lines.into_inner().unwrap();
        assert_eq!((f.passes, f.pilot_columns), (6, 0), "{lines:?}");
        assert!(f.kept_energy >= cfg.energy);
        assert!(lines
            .iter()
            .any(|l| l.contains("the randomized SVD runs on all of them")));
    }

    #[test]
    fn cx_finds_representatives() {
        // 6 representatives; the other columns are their combinations or exact duplicates.
        let reps = gaussian(20, 6, 21);
        let w = gaussian(6, 200, 22);
        let mut a = reconstruct(reps.as_ref(), w.as_ref());
        for (k, j) in [3usize, 50, 77, 120, 150, 199].iter().enumerate() {
            a.col_mut(*j).copy_from(reps.col(k));
            a.col_mut(j - 1).copy_from(reps.col(k));
        }
        let norm_a = a.norm_l2();
        for method in [CxMethod::PivotedQr, CxMethod::Leverage { seed: 4 }] {
            let r = cx(a.as_ref(), 1e-8, method, 50).unwrap();
            eprintln!(
                "cx {method:?}: {} columns, rel. error {:.2e}",
                r.columns.len(),
                r.rel_error
            );
            assert!(r.rel_error <= 1e-8);
            let c = gather(a.as_ref(), &r.columns);
            let rec = (&a - reconstruct(c.as_ref(), r.x.as_ref())).norm_l2() / norm_a;
            assert!(rec <= 1e-8 && (rec - r.rel_error).abs() < 1e-12);
            if let CxMethod::PivotedQr = method {
                assert!(r.columns.len() <= 6);
                let again = cx(a.as_ref(), 1e-8, method, 50).unwrap();
                assert_eq!(again.columns, r.columns);
            }
        }
        // A threshold out of reach: the best at max_cols, honestly.
        let r = cx(a.as_ref(), 1e-8, CxMethod::PivotedQr, 3).unwrap();
        assert_eq!(r.columns.len(), 3);
        assert!(r.rel_error > 1e-3);
    }

    #[test]
    fn cx_methods_compared_at_one_and_a_half_percent() {
        // 3000 random smooth bumps sampled at 400 points, compressed to 99.999 % energy first.
        let mut rng = Rng::new(31);
        let (m, n) = (400, 3000);
        let params: Vec<(f64, f64, f64)> = (0..n)
            .map(|_| (rng.uniform(), rng.range(0.01, 0.2), rng.range(0.2, 1.0)))
            .collect();
        let b = Mat::from_fn(m, n, |i, j| {
            let (mu, s, amp) = params[j];
            let t = i as f64 / (m - 1) as f64;
            amp * (-(t - mu).powi(2) / (2.0 * s * s)).exp()
        });
        let c = svd_gram(&InMemory(b), 0.99999, 100, false).unwrap();
        let qr = cx(c.coords.as_ref(), 0.015, CxMethod::PivotedQr, n).unwrap();
        let lev = cx(c.coords.as_ref(), 0.015, CxMethod::Leverage { seed: 1 }, n).unwrap();
        eprintln!(
            "CX at 1.5 % on {}x{n} coords (99.999 % energy): pivoted QR {} columns \
             (error {:.5}), leverage {} columns (error {:.5})",
            c.rank,
            qr.columns.len(),
            qr.rel_error,
            lev.columns.len(),
            lev.rel_error
        );
        assert!(qr.rel_error <= 0.015 && lev.rel_error <= 0.015);
    }

    #[test]
    fn bad_input_is_a_clear_error() {
        let good = InMemory(gaussian(30, 10, 1));
        for e in [0.0, -0.1, 1.5, f64::NAN] {
            let err = svd_gram(&good, e, 8, false).unwrap_err();
            assert_eq!(err.context, "lowrank::svd_gram");
            assert!(err.message.contains("(0, 1]"), "{err}");
            let cfg = RsvdConfig {
                energy: e,
                oversample: 5,
                power_iters: 1,
                max_rank: 5,
                chunk: 4,
                seed: 0,
                initial_rank: 0,
                pilot: 0,
            };
            assert!(rsvd_streaming(&good, &cfg, false)
                .unwrap_err()
                .message
                .contains("(0, 1]"));
        }
        let empty = InMemory(Mat::zeros(0, 5));
        assert!(svd_gram(&empty, 0.9, 8, false)
            .unwrap_err()
            .message
            .contains("0x5"));
        let cfg = RsvdConfig {
            energy: 0.9,
            oversample: 5,
            power_iters: 1,
            max_rank: 5,
            chunk: 4,
            seed: 0,
            initial_rank: 0,
            pilot: 0,
        };
        assert!(rsvd_streaming(&empty, &cfg, false)
            .unwrap_err()
            .message
            .contains("0x5"));
        let mut nan = gaussian(30, 10, 1);
        nan[(17, 6)] = f64::NAN;
        let nan = InMemory(nan);
        let e = svd_gram(&nan, 0.9, 8, false).unwrap_err();
        assert!(
            e.message.contains("(17, 6)") && e.message.contains("finite"),
            "{e}"
        );
        let e = rsvd_streaming(&nan, &cfg, false).unwrap_err();
        assert_eq!(e.context, "lowrank::rsvd_streaming");
        assert!(e.message.contains("(17, 6)"), "{e}");
        assert!(cx(nan.0.as_ref(), 0.01, CxMethod::PivotedQr, 5)
            .unwrap_err()
            .message
            .contains("(17, 6)"));
        assert!(cx(
            Mat::<f64>::zeros(3, 4).as_ref(),
            0.01,
            CxMethod::PivotedQr,
            5
        )
        .unwrap_err()
        .message
        .contains("all zeros"));
        assert!(cx(good.0.as_ref(), f64::NAN, CxMethod::PivotedQr, 5).is_err());
        assert!(svd_gram(&InMemory(Mat::zeros(4, 3)), 0.9, 2, false)
            .unwrap_err()
            .message
            .contains("all zeros"));
        let mut out = Mat::<f64>::zeros(2, 2);
        assert!(good.read_block(29..31, 0..2, out.as_mut()).is_err());
    }
}
