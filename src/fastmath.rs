//! Polynomial `acos` and `atan2` for table lookups: the fast evaluator finds the prefiltered
//! table's coordinates of every lobe it reads ([`crate::prefilter`]), and libm's `acos` and
//! `atan2` were a fifth of that work. Both here are within 3e-8 rad of libm's, far below what a
//! multilinear table read at steps of degrees resolves; they are not for anything else.

use std::f64::consts::{FRAC_PI_2, FRAC_PI_4, PI};

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
    let ax = x.abs();
    if !(y > 0.0 || ax > 0.0) {
        return 0.0;
    }
    let a = if y <= ax {
        atan_unit(y / ax)
    } else {
        FRAC_PI_2 - atan_unit(ax / y)
    };
    if x >= 0.0 {
        a
    } else {
        PI - a
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
