//! Visually equivalent details (Sec. 7, Fig. 11): several *different* (geometry, material)
//! combinations that all reproduce the look within an error bound. The general solver's
//! exploration from many starts gives a pool; it is walked best first, and a combination is kept
//! only if its geometry and its material both differ from every kept one — by index, and by
//! their compressed library coordinates (cosine similarity below `max_similarity`), so two
//! near-identical grooves or two near-identical glossy lobes do not both count.

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
    let (pool, mut stats) = explore(lib, look, opt, g)?;
    let gc = lib.array("geometry/coords.bsa")?;
    let mc = lib.array("material/coords.bsa")?;
    let (gr, mr) = (gc.header.shape[1], mc.header.shape[1]);
    let (gc, mc) = (gc.f32s()?, mc.f32s()?);
    let grow = |j: usize| &gc[j * gr..(j + 1) * gr];
    let mrow = |m: usize| &mc[m * mr..(m + 1) * mr];
    let mut kept = Vec::new();
    let mut tried = 0;
    for c in pool {
        if kept.len() >= count || tried >= 4 * count.max(1) {
            break;
        }
        let (Some(j), Some(m)) = (c.geometry, c.material) else {
            continue;
        };
        let distinct = kept.iter().all(|k: &super::Candidate| {
            let (kj, km) = (
                k.geometry.unwrap_or(usize::MAX),
                k.material.unwrap_or(usize::MAX),
            );
            kj != j
                && km != m
                && cosine(grow(j), grow(kj)) < max_similarity
                && cosine(mrow(m), mrow(km)) < max_similarity
        });
        if !distinct {
            continue;
        }
        tried += 1;
        let fin = finalize(lib, look, vec![c], opt)?;
        if let Some(f) = fin.into_iter().next() {
            if f.error <= bound {
                kept.push(f);
            }
        }
    }
    stats.notes.push(format!(
        "{} visually equivalent details within {:.1} %",
        kept.len(),
        bound * 100.0
    ));
    Ok(SolveResult {
        candidates: kept,
        stats,
    })
}
