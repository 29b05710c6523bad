//! Visually equivalent details (Sec. 7, Fig. 11): several *different* (geometry, material)
//! combinations that all reproduce the look within an error bound. The general solver's
//! exploration from many starts gives a pool, walked best first in two passes. Two geometries
//! (or two materials) *differ* when their indices differ and their compressed library
//! coordinates have a cosine similarity below `max_similarity`, so two near-identical grooves or
//! two near-identical glossy lobes count as one.
//!
//! 1. A combination is kept if its geometry and its material both differ from every kept one:
//!    the most diverse set first.
//! 2. If that leaves fewer than asked, the rest of the pool is walked again and a combination is
//!    kept if, against every kept one, its geometry or its material differs — another groove for
//!    the same metal is another detail, but the same pair twice is not.
//!
//! The notes say how many details each pass kept. When none is within the bound, the closest
//! combination tried is returned instead, and a note says so.

use super::general::{explore, finalize, GeneralOptions};
use super::{Look, SolveOptions, SolveResult};
use crate::error::Result;
use crate::library::Library;

/// Cosine similarity of two coordinate rows.
fn cosine(a: &[f32], b: &[f32]) -> f64 {
    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        ab += (*x as f64) * (*y as f64);
        aa += (*x as f64) * (*x as f64);
        bb += (*y as f64) * (*y as f64);
    }
    if aa > 0.0 && bb > 0.0 {
        ab / (aa * bb).sqrt()
    } else {
        0.0
    }
}

/// Up to `count` diverse combinations within `bound` (relative error of the final evaluator).
pub fn solve(
    lib: &Library,
    look: &Look,
    opt: &SolveOptions,
    g: &GeneralOptions,
    count: usize,
    bound: f64,
    max_similarity: f64,
) -> Result<SolveResult> {
    // Every start and iteration: the details are drawn from all the combinations visited.
    let g = GeneralOptions {
        stop_below: 0.0,
        ..g.clone()
    };
    let (pool, mut stats) = explore(lib, look, opt, &g)?;
    let gc = lib.array("geometry/coords.bsa")?;
    let mc = lib.array("material/coords.bsa")?;
    let (gr, mr) = (gc.header.shape[1], mc.header.shape[1]);
    let (gc, mc) = (gc.f32s()?, mc.f32s()?);
    // Whether items `a` and `b` of a coordinate table with rows of `w` differ.
    let differ = |a: Option<usize>, b: Option<usize>, coords: &[f32], w: usize| match (a, b) {
        (Some(a), Some(b)) => {
            a != b
                && cosine(&coords[a * w..(a + 1) * w], &coords[b * w..(b + 1) * w]) < max_similarity
        }
        _ => a != b,
    };
    // Each combination is finalised alone, so no bar per call: the log's notes say what was kept.
    let one = SolveOptions {
        progress: crate::library::progress::Progress { quiet: true },
        ..opt.clone()
    };
    let mut kept: Vec<super::Candidate> = Vec::new();
    let mut per_pass = [0usize; 2];
    // Finalised combinations over the bound are not evaluated twice.
    let mut rejected: Vec<(Option<usize>, Option<usize>)> = Vec::new();
    // The closest combination over the bound, shown when none is within it.
    let mut closest: Option<super::Candidate> = None;
    for (pass, strict) in [true, false].into_iter().enumerate() {
        let mut tried = 0;
        for c in &pool {
            if kept.len() >= count || tried >= 4 * count.max(1) {
                break;
            }
            if c.geometry.is_none() || c.material.is_none() {
                continue;
            }
            let key = (c.geometry, c.material);
            if rejected.contains(&key) {
                continue;
            }
            let ok = kept.iter().all(|k| {
                let g = differ(c.geometry, k.geometry, gc, gr);
                let m = differ(c.material, k.material, mc, mr);
                if strict {
                    g && m
                } else {
                    g || m
                }
            });
            if !ok {
                continue;
            }
            tried += 1;
            let fin = finalize(lib, look, vec![c.clone()], &one)?;
            match fin.into_iter().next() {
                Some(f) if f.error <= bound => {
                    kept.push(f);
                    per_pass[pass] += 1;
                }
                f => {
                    if let Some(f) = f.filter(|f| f.error.is_finite()) {
                        if closest.as_ref().is_none_or(|b| f.error < b.error) {
                            closest = Some(f);
                        }
                    }
                    rejected.push(key)
                }
            }
        }
    }
    stats.notes.push(format!(
        "{} visually equivalent details within {:.1} %: {} differing from all others in both geometry and material, {} more in one of the two",
        kept.len(),
        bound * 100.0,
        per_pass[0],
        per_pass[1]
    ));
    if kept.is_empty() {
        if let Some(c) = closest {
            stats.notes.push(format!(
                "no combination found within {:.1} %: the closest, at {:.1} %, is shown instead",
                bound * 100.0,
                c.error * 100.0
            ));
            kept.push(c);
        }
    }
    Ok(SolveResult {
        candidates: kept,
        stats,
    })
}
