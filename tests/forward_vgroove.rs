//! Symmetric V-grooves against closed forms (acceptance check 4).
//!
//! Geometry: `vgroove:n=32,period=16,depth=4`. The generator's profile is
//! `z(x) = -depth (1 - |2t - 1|)` with `t` the phase of `x` in its period (src/generators.rs), i.e. a
//! pure symmetric V with no flat top: peaks at x = 0, 16, 32 (z = 0), valleys at x = 8, 24
//! (z = -4). Heights vary with x only, so both triangles of a cell are coplanar and the surface
//! has exactly two facet normals:
//!   left wall  (x in [0, 8]):  z = -m x,        n_L = (m, 0, 1)/s,
//!   right wall (x in [8, 16]): z = -m (16 - x), n_R = (-m, 0, 1)/s,
//! with slope m = depth / (period/2) = 0.5 and s = sqrt(1 + m²). Per period and per unit length
//! along y: A_base = 16, each wall has area A_f = 8 s (horizontal extent 8 / n_z).
//!
//! Torrance–Sparrow V-groove masking, directions w = (w_x, 0, w_z) in the cross-section plane.
//! The left wall faces +x. A ray leaving a point (x, -m x) of it towards +x clears the opposite
//! peak (16, 0) iff m x <= (16 - x) w_z / w_x, i.e. x <= x_b = 16 / (1 + m tan(theta)). The
//! visible part is the segment [0, x_b] measured from the wall's top, a fraction
//!   G_L(w) = min(1, x_b / 8) = min(1, 2 w_z / (w_z + m w_x)) = min(1, 2 (n·z)(w·z)/(n·w)),
//! and 0 when n_L·w <= 0 (back-facing). Towards -x (w_x < 0) the ray rises faster than the wall
//! (n_L·w > 0 means w_z > m |w_x|) and passes over the wall's own top, so G_L = 1 (the formula
//! gives >= 2, clamped to 1). The right wall is the mirror image: G_R(w) = G_L(mirrored w).
//!
//! Joint visibility: from any in-plane direction the visible part of a wall is a segment anchored
//! at the wall's top, so the part seen from both wi and wo is the shorter one:
//! J_f = min(G_f(wi), G_f(wo)). (The Torrance–Sparrow "opposite sides" rule max(0, G_i + G_o - 1)
//! never applies in a V cross-section: G_f < 1 only for directions on the side the facet faces,
//! so when wi and wo are on opposite sides one of the G is 1 and both rules give the same value.)
//!
//! Then, from the facet sum of the design notes, with a_v(wo) = A_base cos(theta_o) (check 2):
//!   fbar(wi, wo) = Σ_f A_f (n_f·wi)+ (n_f·wo)+ f_r(n_f, wi, wo) J_f / (A_base cos(theta_o)).
//!
//! Sample density: with the shadow boundary x_b (and x_b + 8 on the right wall) on a cell edge (an
//! integer x), every facet is lit and seen either whole or not at all, so every facet the exact
//! evaluator shades takes its exact share of the view rays (a facet whose vertices and edge
//! midpoints are all visible from both directions, `exact.rs`), for any s: the comparison tests
//! the facet sum, the ray march and the normalisation, not the sampling. The boundary lands on
//! x_b = 8 G = k (k = 1..7) when tan(theta) = (16/k - 1) / m; we use
//! k = 7, 6, 4, 2, 1 (theta = 68.7°, 73.3°, 80.5°, 85.9°, 88.1°) plus unshadowed angles, and s = 2.
//! The only error left is rounding, so the tolerance is 1e-9 (1e-6 for the mirror-like case,
//! whose half vector is rounded; the issue asks for 1e-3).

use biscale::bvndf::{BvndfConfig, CompactBvndf};
use biscale::exact::ExactEvaluator;
use biscale::fast;
use biscale::frame::{DirPair, Vec3};
use biscale::generators::parse_generator;
use biscale::heightfield::Heightfield;
use biscale::material::parse_material;
use biscale::prefilter::{PrefilterConfig, Prefiltered};
use std::f64::consts::PI;

const M: f64 = 0.5;
const SPEC: &str = "vgroove:n=32,period=16,depth=4";

fn groove() -> Heightfield {
    let hf = parse_generator(SPEC).unwrap().build().unwrap();
    // Guard the assumptions of the derivation: a pure V of slope 0.5, two periods per 32 samples.
    for x in 0..32i64 {
        let t = (x % 16) as f64;
        let want = -M * if t <= 8.0 { t } else { 16.0 - t };
        assert_eq!(hf.at(x, 5), want, "vgroove profile at x={x}");
    }
    hf
}

fn s() -> f64 {
    (1.0 + M * M).sqrt()
}
fn n_left() -> Vec3 {
    Vec3::new(M, 0.0, 1.0) * (1.0 / s())
}
fn n_right() -> Vec3 {
    Vec3::new(-M, 0.0, 1.0) * (1.0 / s())
}

/// In-plane direction at signed angle `a` (degrees) from +z towards +x. Built exactly in the
/// plane (w_y = 0), so the phi = 180° side carries no rounding in y.
fn inplane(a_deg: f64) -> Vec3 {
    let a = a_deg.to_radians();
    Vec3::new(a.sin(), 0.0, a.cos())
}

/// The Torrance–Sparrow visible fraction of the facet with normal `n` from in-plane `w`.
fn g_ts(n: Vec3, w: Vec3) -> f64 {
    let nw = n.dot(w);
    if nw <= 0.0 {
        return 0.0;
    }
    (2.0 * n.z * w.z / nw).min(1.0)
}

/// Closed-form fbar: Σ_f A_f (n·wi)(n·wo) f_r(n) min(G_i, G_o) / (A_base cos(theta_o)).
fn fbar_closed(wi: Vec3, wo: Vec3, fr: impl Fn(Vec3) -> f64) -> f64 {
    let a_f = 8.0 * s();
    let a_base = 16.0;
    let mut sum = 0.0;
    for n in [n_left(), n_right()] {
        let (ci, co) = (n.dot(wi), n.dot(wo));
        if ci <= 0.0 || co <= 0.0 {
            continue;
        }
        let j = g_ts(n, wi).min(g_ts(n, wo));
        sum += a_f * ci * co * fr(n) * j;
    }
    sum / (a_base * wo.z)
}

/// theta (degrees) at which the left wall's shadow boundary from +x is x_b = k (an integer).
fn theta_aligned(k: f64) -> f64 {
    ((16.0 / k - 1.0) / M).atan().to_degrees()
}

/// Signed in-plane angles: unshadowed ones and grid-aligned shadow boundaries, both sides.
fn signed_angles() -> Vec<f64> {
    let mut v = vec![0.0, 20.0, -35.0, 50.0, -60.0];
    for k in [7.0, 6.0, 4.0, 2.0, 1.0] {
        let t = theta_aligned(k);
        v.push(t);
        v.push(-t);
    }
    v
}

/// The direction pairs of signed in-plane angles.
fn in_plane_pairs(pairs: &[(f64, f64)]) -> Vec<DirPair> {
    pairs
        .iter()
        .map(|&(i, o)| DirPair {
            wi: inplane(i),
            wo: inplane(o),
        })
        .collect()
}

fn lambert_pairs() -> Vec<(f64, f64)> {
    let a = signed_angles();
    let mut out = Vec::new();
    for &i in &a {
        for &o in &a {
            out.push((i, o));
        }
    }
    out
}

/// Worst and RMS relative error of the exact evaluator (`s` rays per cell side) against the
/// closed form over `lambert_pairs()`; pairs whose closed form is 0 must give exactly 0.
fn lambert_errors(s: usize) -> (f64, (f64, f64), f64) {
    let hf = groove();
    let albedo = 0.8;
    let mat = parse_material("lambert:albedo=0.8").unwrap();
    let ev = ExactEvaluator::new(&hf, s);
    let pairs = lambert_pairs();
    let dp = in_plane_pairs(&pairs);
    let got = ev.fbar(&mat, &dp);
    let mut worst = (0.0f64, (0.0, 0.0));
    let (mut num, mut den) = (0.0, 0.0);
    for (k, p) in dp.iter().enumerate() {
        let want = fbar_closed(p.wi, p.wo, |_| albedo / PI);
        if want == 0.0 {
            assert_eq!(
                got[k], 0.0,
                "{:?}: exact {:e}, closed form 0",
                pairs[k], got[k]
            );
            continue;
        }
        let e = ((got[k] - want) / want).abs();
        if e > worst.0 {
            worst = (e, pairs[k]);
        }
        num += (got[k] - want).powi(2);
        den += want * want;
    }
    (worst.0, worst.1, (num / den).sqrt())
}

/// The exact evaluator against the closed form. The pairs' shadow and occlusion edges lie on grid
/// lines (or there are none), so every facet is seen and lit whole or not at all, and a facet seen
/// and lit whole takes its exact share of the rays (`exact.rs`): every pair agrees to rounding, at
/// 2×2 and at 8×8 rays per cell. (When every facet still counted its rays, the worst pair at
/// 2×2, a shadow edge across a wall seen at 60° with the light at 86–88°, was 2e-2 off.)
#[test]
fn lambertian_vgroove_matches_torrance_sparrow_closed_form() {
    let (worst2, at2, rms2) = lambert_errors(2);
    eprintln!("V-groove Lambert exact s=2: worst {worst2:.2e} at {at2:?}, RMS {rms2:.2e}");
    assert!(rms2 < 1e-9, "RMS {rms2}");
    assert!(worst2 < 1e-9, "worst {worst2} at {at2:?}");
    let (worst8, at8, rms8) = lambert_errors(8);
    eprintln!("V-groove Lambert exact s=8: worst {worst8:.2e} at {at8:?}, RMS {rms8:.2e}");
    assert!(worst8 < 1e-9, "worst {worst8} at {at8:?}");
}

/// Independent GGX (Walter et al. 2007) with separable Smith G and F = 1 (f0 = 1).
fn ggx_fr(alpha: f64, n: Vec3, wi: Vec3, wo: Vec3) -> f64 {
    let (ci, co) = (n.dot(wi), n.dot(wo));
    if ci <= 0.0 || co <= 0.0 {
        return 0.0;
    }
    let h = (wi + wo).normalized();
    let ch = n.dot(h);
    // 1 - ch² as |n × h|², exact near ch = 1.
    let sin2 = n.cross(h).dot(n.cross(h));
    let a2 = alpha * alpha;
    let den = sin2 + ch * ch * a2;
    let d = a2 / (PI * den * den);
    let g1 = |c: f64| {
        let t2 = (1.0 - c * c).max(0.0) / (c * c);
        2.0 / (1.0 + (1.0 + a2 * t2).sqrt())
    };
    d * g1(ci) * g1(co) / (4.0 * ci * co)
}

/// Mirror-like facets: GGX with alpha = 1e-3, wo = the mirror image of wi about a wall normal.
/// At h = n the GGX D is 1/(pi alpha²) (3.2e5), Smith G1(c) = 2/(1 + sqrt(1 + alpha² tan²)) ~ 1,
/// F = 1, so the lit wall contributes A_f c² · D G1² / (4 c²) · J and
///   fbar = A_f D G1(c)² J / (4 A_base cos(theta_o)) = s D G1² J / (8 cos(theta_o))
/// (the other wall's D is ~alpha⁴/sin⁴(53°) times smaller, < 1e-11 relative; it is included through
/// the same closed form anyway). The facet normals are exact, and the partly visible walls' edges
/// lie on grid lines, so every facet is seen and lit whole or not at all and takes its exact share
/// (`exact.rs`) at the default 2×2 rays per cell: what is left is rounding in h (~1e-9);
/// tolerance 1e-6. (Counting rays instead, the error was the sampling of J: 1.4e-4 at 8×8.)
#[test]
fn mirror_like_vgroove_matches_closed_form() {
    let hf = groove();
    let alpha = 1e-3;
    let mat = parse_material("ggx:alpha=0.001").unwrap();
    let ev = ExactEvaluator::new(&hf, 2);
    let beta = M.atan().to_degrees(); // wall tilt, 26.57°
                                      // Signed incident angles; reflected about n_L the outgoing angle is 2 beta - a_i. Chosen so
                                      // that the partially visible direction has a grid-aligned boundary (k = 6 and 4) or none.
    let t6 = theta_aligned(6.0);
    let t4 = theta_aligned(4.0);
    let cases_left = [30.0, t6, t4, 2.0 * beta - t4, 2.0 * beta - t6];
    let mut worst = 0.0f64;
    for (n, sign) in [(n_left(), 1.0), (n_right(), -1.0)] {
        for &a in &cases_left {
            let wi = inplane(sign * a);
            let wo = (n * (2.0 * n.dot(wi)) - wi).normalized();
            assert!(wo.z > 0.0);
            let c = n.dot(wi);
            let j = g_ts(n, wi).min(g_ts(n, wo));
            let d = 1.0 / (PI * alpha * alpha);
            let g1 = |c: f64| 2.0 / (1.0 + (1.0 + alpha * alpha * (1.0 - c * c) / (c * c)).sqrt());
            let main = s() * d * g1(c) * g1(c) * j / (8.0 * wo.z);
            let want = fbar_closed(wi, wo, |m| ggx_fr(alpha, m, wi, wo));
            assert!(
                (want / main - 1.0).abs() < 1e-9,
                "closed forms agree: {want} vs {main}"
            );
            let got = ev.fbar(&mat, &[DirPair { wi, wo }])[0];
            let e = (got / want - 1.0).abs();
            worst = worst.max(e);
            eprintln!(
                "mirror V-groove: wi {:+.2}°, wo {:+.2}°, J = {j:.4}: exact {got:.9e}, closed {want:.9e}, rel {e:.1e}",
                (sign * a),
                wo.x.atan2(wo.z).to_degrees()
            );
            assert!(
                e <= 1e-6,
                "wi {wi:?} wo {wo:?}: exact {got}, closed form {want}"
            );
        }
    }
    eprintln!("mirror V-groove: worst rel err {worst:.2e}");
}

/// The fast method on the Lambertian V-groove, against the same closed form. Reports the error;
/// asserts only that every value is finite and non-negative (the fast path's accuracy target is
/// not set by the issue for non-flat geometry).
#[test]
fn fast_lambertian_vgroove_error_report() {
    let hf = groove();
    let albedo = 0.8;
    let mat = parse_material("lambert:albedo=0.8").unwrap();
    let geo = CompactBvndf::build(&hf, &BvndfConfig::default());
    let pre = Prefiltered::build(&mat, &PrefilterConfig::default());
    let pairs = lambert_pairs();
    let dp = in_plane_pairs(&pairs);
    let got = fast::fbar(&geo, &pre, &dp);
    let mut errs: Vec<(f64, (f64, f64))> = Vec::new();
    let mut zero_bad = Vec::new();
    for (k, p) in dp.iter().enumerate() {
        assert!(got[k].is_finite() && got[k] >= 0.0, "fast fbar {}", got[k]);
        let want = fbar_closed(p.wi, p.wo, |_| albedo / PI);
        if want == 0.0 {
            if got[k] != 0.0 {
                zero_bad.push((pairs[k], got[k]));
            }
            continue;
        }
        errs.push((((got[k] - want) / want).abs(), pairs[k]));
    }
    errs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let med = errs[errs.len() / 2].0;
    let small: Vec<f64> = errs
        .iter()
        .filter(|e| e.1 .0.abs() <= 60.0 && e.1 .1.abs() <= 60.0)
        .map(|e| e.0)
        .collect();
    let small_max = small.iter().cloned().fold(0.0, f64::max);
    eprintln!(
        "V-groove Lambert fast: median rel err {med:.2e}, max {:.2e} at {:?}; max with |theta| <= 60°: {small_max:.2e}",
        errs.last().unwrap().0,
        errs.last().unwrap().1
    );
    eprintln!(
        "V-groove Lambert fast: {} pairs with closed form 0 got non-zero fast values, e.g. {:?}",
        zero_bad.len(),
        zero_bad.first()
    );
}
