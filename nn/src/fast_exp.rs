//! A vectorisable eˣ: the loops that call it compile to vector code (in kernels built for the
//! CPU's widest vectors by [`crate::vectorised!`]) where libm's `expf` is one call per value.

/// Round-to-nearest shift for f32 (1.5 · 2²³).
const MAGIC: f32 = 12_582_912.0;

/// eˣ for x clamped to [−87, 87], in plain arithmetic so loops over it vectorise (libm's
/// `expf` calls were a third of the GRU scan and of the LM's cross-entropy): x = k·ln2 + r,
/// |r| ≤ ln2/2, eʳ by Cephes' `expf` polynomial (≈ 1 ulp), 2ᵏ from k's bits.
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    let x = x.clamp(-87.0, 87.0);
    let shifted = x * std::f32::consts::LOG2_E + MAGIC;
    let k = shifted - MAGIC;
    let r = (x - k * 0.693_359_4) + k * 2.121_944_4e-4;
    let mut p = 1.987_569_1e-4;
    for c in [
        1.398_199_9e-3,
        8.333_452e-3,
        4.166_579_6e-2,
        0.166_666_65,
        0.5,
    ] {
        p = p * r + c;
    }
    let e = p * r * r + r + 1.0;
    let bits = shifted.to_bits().wrapping_sub(MAGIC.to_bits());
    e * f32::from_bits(bits.wrapping_add(127) << 23)
}
