//! Polynomial `acos` and `atan2` for table lookups, an inlined `exp` and `ln_1p` (full
//! precision) for the analytic lobes and the table's `kappa` coordinate, and an inlined exact
//! `floor` for the visibility walks (on the baseline x86-64 target `f64::floor` is a libm call,
//! 8 % of a compact BVNDF build). `acos` and `atan2`: the fast evaluator finds the prefiltered
//! table's coordinates of every lobe it reads ([`crate::prefilter`]), and libm's `acos` and
//! `atan2` were a fifth of that work. Both here are within 3e-8 rad of libm's, far below what a
//! multilinear table read at steps of degrees resolves; they are not for anything else. And
//! `dot` and `dot32`, dot products with partial sums, for the searches' per-item terms.
//! `atan2_upper` and `ln_1p_select` (the body of `ln_1p`) have no branches, so that loops over
//! eight lobes' table coordinates run in vector registers. And
//! `without_subnormals`, which runs the searches' `f32` products with subnormal numbers taken
//! as zero.

use std::f64::consts::{FRAC_PI_2, FRAC_PI_4, PI};

/// Run `f` on this thread with subnormal `f32`/`f64` results flushed to zero and subnormal
/// operands read as zero (the FTZ and DAZ bits of x86-64's MXCSR; restored afterwards, also on
/// unwinding; elsewhere `f` runs unchanged). For the searches' `f32` products: `paper4` has CX
/// weights down to 1e-20 and Gram cross terms below 1e-30 (two representatives bright at
/// different samples), whose products are subnormal, and this machine's processor computes
/// each of those about 50× slower than a normal product. On `paper4` the scan with the
/// light-lobe weights took 23–50 ms per block of 4096 items instead of 1–3 ms (timed with a
/// temporary print in `biscale validate --library outputs/lib-paper4 --cases 3
/// --library-targets --solvers geometry --no-exhaustive`), and the slowdown came and went with
/// the data. Values below 1.2e-38 are far below the `f32` rounding of the sums they enter;
/// nothing stored is computed under this.
///
/// Rust's documentation of `_mm_setcsr` calls a changed DAZ mode undefined behaviour: the
/// compiler assumes IEEE's default floating-point environment, so code compiled under that
/// assumption may see subnormals flushed where it expected them kept (constant folding, moved
/// operations). Only the closures given here run under it; they compute scores from which
/// nothing but rankings follow, with no floating-point value deciding a memory access, and
/// their answers were compared with the unflushed ones (docs/solvers.md). Flush-to-zero alone,
/// or the Gram matrix's subnormal entries zeroed, left the scans slow; the Gram product in
/// `f64`, which has no subnormals at these magnitudes, made the search slower still.
#[inline]
pub fn without_subnormals<T>(f: impl FnOnce() -> T) -> T {
    #[cfg(target_arch = "x86_64")]
    {
        /// Restores the saved control word when dropped.
        struct Restore(u32);
        impl Drop for Restore {
            fn drop(&mut self) {
                set_mxcsr(self.0);
            }
        }
        let saved = mxcsr();
        // Bit 15: flush to zero; bit 6: denormals are zero.
        set_mxcsr(saved | (1 << 15) | (1 << 6));
        let _restore = Restore(saved);
        f()
    }
    #[cfg(not(target_arch = "x86_64"))]
    f()
}

#[cfg(target_arch = "x86_64")]
#[inline]
fn mxcsr() -> u32 {
    let mut v: u32 = 0;
    // SAFETY: `stmxcsr` stores the 32-bit SSE control/status register to `v`, which is valid
    // for writes; every x86-64 processor has it.
    unsafe {
        std::arch::asm!("stmxcsr [{}]", in(reg) &mut v, options(nostack, preserves_flags));
    }
    v
}

#[cfg(target_arch = "x86_64")]
#[inline]
fn set_mxcsr(v: u32) {
    // SAFETY: `ldmxcsr` loads the control/status register from `v`, a valid value read by
    // `mxcsr` with only the FTZ and DAZ mode bits changed (both defined on every x86-64
    // processor with SSE2; the exception masks are left as they were).
    unsafe {
        std::arch::asm!("ldmxcsr [{}]", in(reg) &v, options(nostack, preserves_flags, readonly));
    }
}

/// `Σ term(a_i, b_i)` in `f32` with eight partial sums (vectorised), returned as `f64`: the
/// loop of [`dot32`] and [`dist2_32`].
#[inline(always)]
fn sum32(a: &[f32], b: &[f32], term: impl Fn(f32, f32) -> f32) -> f64 {
    let mut acc = [0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(&x, &y)| term(x, y))
        .sum();
    for (x, y) in ca.zip(cb) {
        for i in 0..8 {
            acc[i] += term(x[i], y[i]);
        }
    }
    (acc.iter().sum::<f32>() + tail) as f64
}

/// `Σ a_i b_i` in `f32` with eight partial sums (vectorised), returned as `f64`: the binned
/// response's dot products ([`crate::gamma::Response`]), the joint scan's linear terms and the
/// clamped rescoring's, where `f32` is the data's own precision.
#[inline]
pub fn dot32(a: &[f32], b: &[f32]) -> f64 {
    sum32(a, b, |x, y| x * y)
}

/// `Σ (a_i − b_i)²` in `f32` with eight partial sums (vectorised), returned as `f64`: the
/// compressed search's clamped errors, where `f32` is the data's own precision.
#[inline]
pub fn dist2_32(a: &[f32], b: &[f32]) -> f64 {
    sum32(a, b, |x, y| (x - y) * (x - y))
}

/// `Σ a_i b_i` in `f64` over the shorter of the two, with eight partial sums so that the loop
/// runs in vector registers (the sum's rounding differs from a sequential one's in the last
/// bits). For the compressed search's per-item terms, where a sequential sum waited on each
/// addition.
#[inline]
pub fn dot<A: Copy + Into<f64>, B: Copy + Into<f64>>(a: &[A], b: &[B]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f64; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(&x, &y)| x.into() * y.into())
        .sum();
    for (x, y) in ca.zip(cb) {
        for i in 0..8 {
            acc[i] += x[i].into() * y[i].into();
        }
    }
    acc.iter().sum::<f64>() + tail
}

/// `x.floor()`, exactly, without a library call: a truncating conversion corrected for negative
/// non-integers. Beyond `2^52` every `f64` is an integer (and NaN or infinities pass through).
#[inline]
pub fn floor(x: f64) -> f64 {
    if x.abs() < 4_503_599_627_370_496.0 {
        let t = x as i64 as f64;
        if t > x {
            t - 1.0
        } else {
            t
        }
    } else {
        x
    }
}

/// `acos(x)` for `x` in `[-1, 1]` (clamped), within 3e-8 rad (Abramowitz & Stegun 4.4.45).
#[inline]
pub fn acos(x: f64) -> f64 {
    let x = x.clamp(-1.0, 1.0);
    let a = x.abs();
    let p = 1.570_796_305_0
        + a * (-0.214_598_801_6
            + a * (0.088_978_987_4
                + a * (-0.050_174_304_6
                    + a * (0.030_891_881_0
                        + a * (-0.017_088_125_6 + a * (0.006_670_090_1 + a * -0.001_262_491_1))))));
    let r = (1.0 - a).sqrt() * p;
    if x >= 0.0 {
        r
    } else {
        PI - r
    }
}

/// `atan(t)` for `t` in `[0, 1]`: reduced to `|u| <= tan(pi/8)` and summed to `u^15`
/// (truncation below 2e-8).
#[inline]
fn atan_unit(t: f64) -> f64 {
    let (base, u) = if t > std::f64::consts::SQRT_2 - 1.0 {
        (FRAC_PI_4, (t - 1.0) / (t + 1.0))
    } else {
        (0.0, t)
    };
    let u2 = u * u;
    let s = 1.0
        - u2 * (1.0 / 3.0
            - u2 * (1.0 / 5.0
                - u2 * (1.0 / 7.0
                    - u2 * (1.0 / 9.0
                        - u2 * (1.0 / 11.0 - u2 * (1.0 / 13.0 - u2 * (1.0 / 15.0)))))));
    base + u * s
}

/// `atan2(y, x)` for `y >= 0` (the upper half plane, `[0, pi]`), within 3e-8 rad; 0 at the
/// origin.
#[inline]
pub fn atan2_upper(y: f64, x: f64) -> f64 {
    // Without branches (both orders of the quotient computed and one selected), so that loops
    // over it run in vector registers (`prefilter::coords_soa`).
    let ax = x.abs();
    let swap = !(y <= ax);
    let (n, d) = if swap { (ax, y) } else { (y, ax) };
    let r = atan_unit(n / d);
    let a = if swap { FRAC_PI_2 - r } else { r };
    let a = if x >= 0.0 { a } else { PI - a };
    if y > 0.0 || ax > 0.0 {
        a
    } else {
        0.0
    }
}

/// `e^x`, within 2 ulp of libm's for `|x| <= 708` (libm's own beyond): `x = k ln 2 + r` with
/// `|r| <= ln 2 / 2`, a degree-13 Taylor polynomial in `r` (truncation below 1e-17) and `2^k`
/// from the exponent bits. Inlined, it avoids libm's call and error handling: the microfacet and
/// Ward lobes call it at every point lobe the solvers read, and libm's `exp` was a fifth of a
/// general solve's samples.
#[inline]
pub fn exp(x: f64) -> f64 {
    if !(x.abs() <= 708.0) {
        return x.exp();
    }
    const LN2_HI: f64 = 6.931_471_803_691_238e-1;
    const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
    let k = (x * std::f64::consts::LOG2_E).round();
    let r = (x - k * LN2_HI) - k * LN2_LO;
    let mut p = 1.0 / 6_227_020_800.0;
    for d in [
        479_001_600.0,
        39_916_800.0,
        3_628_800.0,
        362_880.0,
        40_320.0,
        5_040.0,
        720.0,
        120.0,
        24.0,
        6.0,
        2.0,
        1.0,
        1.0,
    ] {
        p = p * r + 1.0 / d;
    }
    p * f64::from_bits(((k as i64 + 1023) as u64) << 52)
}

/// `ln(1 + x)` for `x >= 0`, within 1e-15 of libm's (libm's own for other input): the exponent
/// from the bits of `1 + x`, `ln m = 2 atanh((m - 1)/(m + 1))` summed to the 17th power for the
/// mantissa in `[sqrt(1/2), sqrt(2))`. The prefiltered table's `kappa` coordinate is log-spaced,
/// and libm's `log1p` was a tenth of a general solve's samples.
#[inline]
pub fn ln_1p(x: f64) -> f64 {
    if !(0.0..1e300).contains(&x) {
        return x.ln_1p();
    }
    ln_1p_select(x)
}

/// [`ln_1p`] without branches, for loops the compiler runs in vector registers (the
/// prefiltered table's coordinates of eight lobes at once, `prefilter::coords_soa`): `ln_1p`
/// itself for `x` in `[0, 1e300)`, and NaN for NaN; other input is outside its domain. Both
/// formulas (a cubic below 1e-4) are computed and one is selected; the exponent is read with the
/// `2^52` trick instead of an integer conversion, which AVX2 has no vector instruction for.
#[inline]
pub fn ln_1p_select(x: f64) -> f64 {
    let bits = (1.0 + x).to_bits();
    let e0 = f64::from_bits(((bits >> 52) & 0x7ff) | 0x4330_0000_0000_0000)
        - 4_503_599_627_370_496.0
        - 1023.0;
    let m0 = f64::from_bits((bits & 0x000f_ffff_ffff_ffff) | (1023u64 << 52));
    let big = m0 > std::f64::consts::SQRT_2;
    let m = if big { m0 * 0.5 } else { m0 };
    let e = if big { e0 + 1.0 } else { e0 };
    let t = (m - 1.0) / (m + 1.0);
    let t2 = t * t;
    let mut p = 1.0 / 17.0;
    for d in [15.0, 13.0, 11.0, 9.0, 7.0, 5.0, 3.0, 1.0] {
        p = p * t2 + 1.0 / d;
    }
    let main = e * std::f64::consts::LN_2 + 2.0 * t * p;
    let small = x * (1.0 - x * (0.5 - x * (1.0 / 3.0)));
    let r = if x < 1e-4 { small } else { main };
    if x.is_nan() {
        x
    } else {
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn without_subnormals_flushes_inside_and_restores_outside() {
        // Opaque to the optimiser, so that the products happen at run time.
        let tiny = std::hint::black_box(1e-30f32);
        let small = std::hint::black_box(1e-10f32);
        assert!(
            (tiny * small).is_subnormal(),
            "the default keeps subnormals"
        );
        let inside = without_subnormals(|| std::hint::black_box(tiny) * small);
        if cfg!(target_arch = "x86_64") {
            assert_eq!(inside, 0.0);
            let sub = std::hint::black_box(f32::MIN_POSITIVE / 4.0);
            assert_eq!(
                without_subnormals(|| std::hint::black_box(sub) * std::hint::black_box(1.0f32)),
                0.0
            );
        }
        assert!(
            (std::hint::black_box(tiny) * small).is_subnormal(),
            "restored afterwards"
        );
        // Normal arithmetic is untouched.
        assert_eq!(
            without_subnormals(|| std::hint::black_box(3.0f32) * 0.5),
            1.5
        );
        // Restored when the closure unwinds.
        let r = std::panic::catch_unwind(|| without_subnormals(|| panic!("inside")));
        assert!(r.is_err());
        assert!((std::hint::black_box(tiny) * small).is_subnormal());
    }

    #[test]
    fn ln_1p_agrees_with_libm() {
        let mut worst: f64 = 0.0;
        for i in 0..=200_000 {
            // 0 and 1e-12 to 1e12, log-spaced.
            let x = if i == 0 {
                0.0
            } else {
                10f64.powf(-12.0 + 24.0 * i as f64 / 200_000.0)
            };
            let (a, b) = (ln_1p(x), x.ln_1p());
            worst = worst.max((a - b).abs() / b.max(1.0));
        }
        assert!(worst < 1e-15, "ln_1p: worst difference {worst:e}");
        assert!(ln_1p(f64::NAN).is_nan());
        assert_eq!(ln_1p(f64::INFINITY), f64::INFINITY);
    }

    #[test]
    fn dot_equals_a_sequential_sum_to_rounding() {
        for n in [0usize, 1, 7, 8, 9, 99, 490] {
            let a: Vec<f32> = (0..n).map(|i| ((i * 37 % 11) as f32 - 5.0) / 3.0).collect();
            let b: Vec<f64> = (0..n).map(|i| ((i * 13 % 7) as f64 - 3.0) * 0.7).collect();
            let want: f64 = a.iter().zip(&b).map(|(&x, &y)| x as f64 * y).sum();
            let scale: f64 = a.iter().zip(&b).map(|(&x, &y)| (x as f64 * y).abs()).sum();
            assert!(
                (dot(&a, &b) - want).abs() <= 1e-14 * scale.max(1.0),
                "n = {n}"
            );
        }
        // The shorter slice sets the length.
        assert_eq!(dot(&[1.0f32, 2.0, 3.0], &[1.0f64, 1.0]), 3.0);
        // dot32: the same sums in f32 (the lengths here cover the tail and the 8-wide body).
        for n in [0usize, 5, 8, 21] {
            let a: Vec<f32> = (0..n).map(|i| (i % 5) as f32 * 0.25 - 0.5).collect();
            let b: Vec<f32> = (0..n).map(|i| (i % 3) as f32 - 1.0).collect();
            let want: f64 = a.iter().zip(&b).map(|(&x, &y)| (x * y) as f64).sum();
            assert!((dot32(&a, &b) - want).abs() < 1e-5, "n = {n}");
        }
    }

    #[test]
    fn floor_equals_libm() {
        let mut r = crate::rng::Rng::new(3);
        let mut xs = vec![
            0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            -1e-300,
            1e-300,
            4_503_599_627_370_495.5,
            -4_503_599_627_370_495.5,
            4_503_599_627_370_496.0,
            -9.3e18,
            1e300,
            f64::MAX,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        xs.extend((0..100_000).map(|i| r.range(-1e3, 1e3) * 10f64.powi(i % 12)));
        for x in xs {
            // Equal as numbers (the sign of a zero result may differ, which no caller sees).
            assert_eq!(floor(x), x.floor(), "floor({x})");
        }
        assert!(floor(f64::NAN).is_nan());
    }

    #[test]
    fn exp_within_two_ulp_of_libm() {
        let mut worst: f64 = 0.0;
        for i in 0..=200_000 {
            let x = -745.0 + 1455.0 * i as f64 / 200_000.0;
            let (a, b) = (exp(x), x.exp());
            if b > 0.0 && b.is_finite() {
                worst = worst.max(((a - b) / b).abs());
            } else {
                assert_eq!(a, b, "exp({x})");
            }
        }
        assert!(worst < 4.5e-16, "exp: worst relative difference {worst:e}");
        assert_eq!(exp(0.0), 1.0);
        assert_eq!(exp(f64::NEG_INFINITY), 0.0);
        assert!(exp(f64::NAN).is_nan());
    }

    #[test]
    fn agree_with_libm() {
        let mut worst: f64 = 0.0;
        for i in 0..=20000 {
            let x = -1.0 + 2.0 * i as f64 / 20000.0;
            worst = worst.max((acos(x) - x.acos()).abs());
        }
        assert!(worst < 3e-8, "acos {worst}");
        let mut worst: f64 = 0.0;
        for i in 0..=400 {
            for j in 0..=400 {
                let (x, y) = (-1.0 + 2.0 * i as f64 / 400.0, j as f64 / 400.0);
                worst = worst.max((atan2_upper(y, x) - y.atan2(x)).abs());
            }
        }
        assert!(worst < 3e-8, "atan2 {worst}");
        assert_eq!(atan2_upper(0.0, 0.0), 0.0);
        assert_eq!(atan2_upper(0.0, -1.0), PI);
        assert_eq!(acos(2.0), 0.0);
    }
}
