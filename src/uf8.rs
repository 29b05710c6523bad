//! `uf8`: the unsigned 8-bit float a library may store its binned BVNDF columns in
//! (`geometry.gamma_precision = "byte"`, array dtype `uf8`), half the bytes of `f16`.
//!
//! A byte `e m` (4 exponent bits `e`, 4 mantissa bits `m`, bias 14, no sign, no infinity or
//! NaN) is the value `2^(e − 14) · (1 + m/16)` for `e ≥ 1` and the subnormal `2^(−13) · m/16`
//! for `e = 0`. So it spans `2⁻¹⁷` (the smallest positive value) to `3.875` (byte 255), 16
//! values per octave above `2⁻¹³`; rounding to the nearest (ties to even) is within `2⁻⁵`
//! (3.1 %) of a value in the normal range. The binned columns suit it: they are area shares,
//! never negative and under 1, whose rounding errors are independent from entry to entry and
//! mostly cancel in the sums over normal nodes that `fbar` is (`docs/library.md`, "The binned
//! columns in one byte"). Larger values are stored as 3.875 and smaller ones round to zero or
//! to a subnormal.

/// The largest value a byte holds (byte 255).
pub const MAX: f32 = 3.875;

/// The value of every byte, in order.
static TABLE: [f32; 256] = table();

const fn table() -> [f32; 256] {
    let mut t = [0f32; 256];
    let mut b = 1;
    while b < 256 {
        let (e, m) = ((b >> 4) as u32, (b & 15) as u32);
        t[b] = if e >= 1 {
            // 2^(e − 14) · (1 + m/16): the f32 exponent field e − 14 + 127, mantissa m.
            f32::from_bits(((e + 113) << 23) | (m << 19))
        } else {
            // m · 2⁻¹⁷: with its leading bit at p, 2^(p − 17) · (m / 2^p).
            let p = 31 - m.leading_zeros();
            f32::from_bits(((p + 110) << 23) | ((m - (1 << p)) << (23 - p)))
        };
        b += 1;
    }
    t
}

/// The value of byte `b`.
#[inline]
pub fn decode(b: u8) -> f32 {
    TABLE[b as usize]
}

/// The nearest byte to `v` (ties to even); negative values and NaN give 0, values over
/// [`MAX`] give 255.
pub fn encode(v: f32) -> u8 {
    if !(v > 0.0) {
        return 0;
    }
    if v >= MAX {
        return 255;
    }
    const MIN_NORMAL: f32 = 1.0 / 8192.0; // 2⁻¹³
    if v < MIN_NORMAL {
        // Subnormals are a fixed step of 2⁻¹⁷: the nearest multiple (16 is 2⁻¹³, byte 16).
        return (v * 131_072.0).round_ties_even() as u8;
    }
    let bits = v.to_bits();
    let e = (bits >> 23) - 113; // the byte's exponent, 1..=15
    let frac = bits & 0x7f_ffff;
    let mut code = (e << 4) | (frac >> 19);
    let rest = frac & 0x7_ffff;
    if rest > 0x4_0000 || (rest == 0x4_0000 && code & 1 == 1) {
        // A carry out of the mantissa moves to the next exponent, as it should.
        code += 1;
    }
    code.min(255) as u8
}

/// Encode a slice.
pub fn encode_all(src: &[f32]) -> Vec<u8> {
    src.iter().map(|&v| encode(v)).collect()
}

/// Decode a slice into `dst` (the same length).
pub fn decode_into<T: From<f32>>(src: &[u8], dst: &mut [T]) {
    for (o, &b) in dst.iter_mut().zip(src) {
        *o = T::from(TABLE[b as usize]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_byte_decodes_to_its_value_and_encodes_back() {
        for b in 0..=255u8 {
            let (e, m) = ((b >> 4) as i32, (b & 15) as f64);
            let want = if e == 0 {
                m / 16.0 * 2f64.powi(-13)
            } else {
                2f64.powi(e - 14) * (1.0 + m / 16.0)
            };
            assert_eq!(decode(b) as f64, want, "byte {b}");
            assert_eq!(encode(decode(b)), b, "byte {b}");
        }
        assert_eq!(decode(255), MAX);
        assert_eq!(decode(1), 2f32.powi(-17));
        // Increasing: the bytes are ordered like their values.
        assert!((1..=255u8).all(|b| decode(b) > decode(b - 1)));
    }

    #[test]
    fn rounding_is_to_the_nearest_byte_within_a_32nd() {
        let mut x = 1e-7f32;
        while x < 4.5 {
            let b = encode(x);
            let d = (decode(b) - x).abs();
            // No other byte is nearer.
            for c in [b.saturating_sub(1), b.saturating_add(1)] {
                assert!(d <= (decode(c) - x).abs(), "{x}: byte {b}, {c} is nearer");
            }
            if (1.0 / 8192.0..=MAX).contains(&x) {
                assert!(d <= x / 32.0, "{x}: {} off", d / x);
            }
            x *= 1.0137;
        }
        // Ties go to the even byte; out-of-range input is clamped.
        let mid = 0.5 * (decode(32) + decode(33));
        assert_eq!(encode(mid), 32);
        let mid = 0.5 * (decode(33) + decode(34));
        assert_eq!(encode(mid), 34);
        assert_eq!(encode(-1.0), 0);
        assert_eq!(encode(f32::NAN), 0);
        assert_eq!(encode(f32::INFINITY), 255);
        assert_eq!(encode(1e9), 255);
        assert_eq!(encode(2f32.powi(-19)), 0);
    }
}
