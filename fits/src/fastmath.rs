//! Branch-free `exp` and `ln` for the parametric objective's inner loop: plain arithmetic and
//! bit operations that the compiler vectorises, accurate to a few ulp on the ranges used.

/// 1.5·2^52: adding it rounds a float of magnitude < 2^51 to an integer in its low bits.
const MAGIC: f64 = 6_755_399_441_055_744.0;
/// ln 2 split (fdlibm): LN2_HI has trailing zero bits, so k·LN2_HI is exact.
const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
/// ln 2 − LN2_HI.
const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);
const LOG2E: f64 = std::f64::consts::LOG2_E;

/// eˣ for x in [−708, 708] (callers check the range).
#[inline(always)]
pub fn exp(x: f64) -> f64 {
    // x = k·ln2 + r, |r| ≤ ln2/2; eʳ by its Taylor series to r¹³ (error < 1e-17).
    let shifted = x * LOG2E + MAGIC;
    let k = shifted - MAGIC;
    let r = (x - k * LN2_HI) - k * LN2_LO;
    let mut p = 1.0 / 6_227_020_800.0;
    for c in [
        1.0 / 479_001_600.0,
        1.0 / 39_916_800.0,
        1.0 / 3_628_800.0,
        1.0 / 362_880.0,
        1.0 / 40_320.0,
        1.0 / 5_040.0,
        1.0 / 720.0,
        1.0 / 120.0,
        1.0 / 24.0,
        1.0 / 6.0,
        0.5,
        1.0,
        1.0,
    ] {
        p = p * r + c;
    }
    // 2^k from k's integer bits (the low mantissa bits of `shifted`).
    let ki = shifted.to_bits().wrapping_sub(MAGIC.to_bits());
    f64::from_bits(ki.wrapping_add(1023) << 52) * p
}

/// ln x for positive, normal, finite x (callers check).
#[inline(always)]
pub fn ln(x: f64) -> f64 {
    let bits = x.to_bits();
    // The biased exponent as a float without an int→float conversion (which does not vectorise).
    let biased = f64::from_bits(MAGIC.to_bits() + (bits >> 52)) - MAGIC;
    let m = f64::from_bits((bits & 0x000f_ffff_ffff_ffff) | 0x3ff0_0000_0000_0000);
    // Fold m ∈ [1, 2) into [√½, √2).
    let big = m > std::f64::consts::SQRT_2;
    let m = if big { m * 0.5 } else { m };
    let e = biased - 1023.0 + if big { 1.0 } else { 0.0 };
    // ln m = 2·atanh(z), z = (m − 1)/(m + 1), |z| ≤ 0.1716: odd series to z²³ (error < 1e-18).
    let z = (m - 1.0) / (m + 1.0);
    let z2 = z * z;
    let mut p = 1.0 / 23.0;
    for c in [
        1.0 / 21.0,
        1.0 / 19.0,
        1.0 / 17.0,
        1.0 / 15.0,
        1.0 / 13.0,
        1.0 / 11.0,
        1.0 / 9.0,
        1.0 / 7.0,
        1.0 / 5.0,
        1.0 / 3.0,
        1.0,
    ] {
        p = p * z2 + c;
    }
    e * LN2_HI + (2.0 * z * p + e * LN2_LO)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ulps(a: f64, b: f64) -> u64 {
        (a.to_bits() as i64 - b.to_bits() as i64).unsigned_abs()
    }

    #[test]
    fn exp_matches_std_to_a_few_ulp() {
        let mut worst = 0;
        for i in 0..=200_000 {
            let x = -708.0 + 1416.0 * i as f64 / 200_000.0;
            worst = worst.max(ulps(exp(x), x.exp()));
        }
        for x in [
            0.0,
            1e-12,
            -1e-12,
            0.5,
            -0.5,
            1.0,
            std::f64::consts::LN_2,
            30.0,
        ] {
            worst = worst.max(ulps(exp(x), x.exp()));
        }
        assert!(worst <= 4, "worst {worst} ulp");
        assert_eq!(exp(0.0), 1.0);
    }

    #[test]
    fn ln_matches_std_to_a_few_ulp() {
        let mut worst = 0;
        for i in 0..=200_000 {
            let x = 10f64.powf(-300.0 + 600.0 * i as f64 / 200_000.0);
            worst = worst.max(ulps(ln(x), x.ln()));
        }
        for i in 0..=100_000 {
            let x = 0.5 + 2.0 * i as f64 / 100_000.0;
            let (a, b) = (ln(x), x.ln());
            assert!(
                (a - b).abs() <= 4.0 * f64::EPSILON * b.abs().max(1e-300) || (a - b).abs() < 1e-16,
                "{x}: {a} vs {b}"
            );
        }
        assert!(worst <= 4, "worst {worst} ulp");
        assert_eq!(ln(1.0), 0.0);
    }
}
