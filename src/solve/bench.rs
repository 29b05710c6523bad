//! `biscale bench scan`: the compressed search (stage 1 of every solver) on a library of the
//! paper's size, and how close it runs to this machine's memory bandwidth.
//!
//! The CX weights are synthetic (seeded), with the shape a paper-sized library would have; the
//! full search does not look at their values, so its time is the real one (the bounded search
//! of the geometry solver passes over items by their values: its row shows the mechanism's cost
//! on random weights, not a library's). The bandwidth is measured
//! the same way the search reads its input: every thread streaming through its share of a large
//! `f32` array.

use super::{
    auto_geometry_pool, rescore_share, search_errors, search_errors_multi, smallest, SEARCH_BLOCK,
    SEARCH_RESCORE,
};
use crate::bench::time;
use crate::error::{Error, Result};
use crate::frame::Vec3;
use crate::rng::Rng;
use crate::sampling::Samples;
use rayon::prelude::*;

/// Most synthetic weights `bench scan` will allocate (16 GiB of `f32`).
const MAX_WEIGHTS: usize = 1 << 32;

/// Bytes of the array streamed to measure the memory bandwidth (far beyond any cache).
const BANDWIDTH_BYTES: usize = 1 << 30;

/// Sum of `v`, read in parallel in blocks (the reduction keeps the reads from being optimised out).
fn stream_sum(v: &[f32]) -> f64 {
    v.par_chunks(1 << 16)
        .map(|c| c.iter().map(|&x| x as f64).sum::<f64>())
        .sum()
}

/// The scan table for `items` library items with `reps` representatives, at `samples` samples.
pub fn scan(items: usize, reps: usize, samples: usize, seed: u64) -> Result<String> {
    if items == 0 || reps == 0 || samples == 0 {
        return Err(Error::new(
            "bench scan",
            "--items, --reps and --samples must be at least 1",
        ));
    }
    if items.saturating_mul(reps) > MAX_WEIGHTS || reps.saturating_mul(samples) > MAX_WEIGHTS {
        return Err(Error::new(
            "bench scan",
            format!(
                "--items × --reps ({items} × {reps}) and --reps × --samples must stay within \
                 {MAX_WEIGHTS} (16 GiB of f32 weights)"
            ),
        ));
    }
    let threads = rayon::current_num_threads();
    let mut r = Rng::new(seed);
    let x: Vec<f32> = (0..items * reps)
        .map(|_| r.range(-0.5, 1.0) as f32)
        .collect();
    let a: Vec<Vec<f64>> = (0..reps)
        .map(|_| (0..samples).map(|_| r.uniform()).collect())
        .collect();
    let t: Vec<f64> = (0..samples).map(|_| r.uniform()).collect();
    let s = Samples {
        pairs: vec![(0, Vec3::new(0.0, 0.0, 1.0)); samples],
        lights: vec![Vec3::new(0.0, 0.0, 1.0)],
        weights: (0..samples).map(|_| r.range(0.5, 1.5)).collect(),
    };
    let (t1, e) = time(5, || search_errors(&s, &t, &a, &x, items, SEARCH_RESCORE));
    if e.iter().any(|v| !v.is_finite()) {
        return Err(Error::new(
            "bench scan",
            "the search returned a non-finite error",
        ));
    }
    // As the geometry solver ranks: only the best of its pools need be exact, the rest bounded.
    let keep = auto_geometry_pool(items).saturating_mul(1 + super::geometry::WIDEN);
    let (tk, ek) = time(5, || {
        search_errors_multi(
            &s,
            std::slice::from_ref(&t),
            &a,
            &x,
            items,
            SEARCH_RESCORE,
            keep,
            false,
        )
    });
    let same = smallest(&ek[0], keep.min(items)) == smallest(&e, keep.min(items));
    // Eight rotations of a target at one shared sample set, as the geometry solver searches.
    let t8: Vec<Vec<f64>> = (0..8)
        .map(|_| (0..samples).map(|_| r.uniform()).collect())
        .collect();
    let (t8, _) = time(3, || {
        std::hint::black_box(search_errors_multi(
            &s,
            &t8,
            &a,
            &x,
            items,
            rescore_share(8, 64),
            items * 8,
            false,
        ))
    });
    let big: Vec<f32> = (0..BANDWIDTH_BYTES / 4).map(|i| (i % 7) as f32).collect();
    let (tb, sum) = time(5, || stream_sum(&big));
    std::hint::black_box(sum);
    let bw = BANDWIDTH_BYTES as f64 / tb;
    let (tx, _) = time(5, || stream_sum(&x));
    let xbytes = (items * reps * 4) as f64;
    let floor = xbytes / bw;
    Ok(format!(
        "Compressed search (stage 1) on a synthetic library: {items} items × {reps} representatives, \
         {samples} samples, blocks of {SEARCH_BLOCK} items, {threads} threads, seed {seed}\n\n\
         | quantity | value |\n|---|---|\n\
         | CX weights read per search | {:.1} MB |\n\
         | memory bandwidth (parallel read of {} MiB) | {:.1} GB/s |\n\
         | bandwidth limit of one search (weights / bandwidth) | {:.2} ms |\n\
         | one pass over the weights alone (read and sum) | {:.2} ms |\n\
         | search, psi = 1 (median of 5) | {:.1} ms |\n\
         | search, psi = 1, only the best {keep} exact, the rest bounded (the geometry solver's rankings; median of 5) | {:.1} ms ({}) |\n\
         | search, psi = 8 (8 rotations of the target at shared samples, as the geometry solver searches, median of 3) | {:.1} ms |\n\
         | search time / bandwidth limit | {:.0}× |\n",
        xbytes / 1e6,
        BANDWIDTH_BYTES >> 20,
        bw / 1e9,
        floor * 1e3,
        tx * 1e3,
        t1 * 1e3,
        tk * 1e3,
        if same { "the same best entries" } else { "DIFFERENT best entries" },
        t8 * 1e3,
        t1 / floor,
    ))
}
