//! The vector extension the CPU row kernels run with, chosen at run time: each kernel body is
//! compiled once per level ([`vectorised!`]) and the widest level this CPU has runs it. The
//! bodies use no fused multiply-add and no reassociated sums, so every level gives the same
//! bits (each kernel's test checks it on the levels of the machine it runs on).

/// A level of x86-64 vector extensions, narrowest first.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Isa {
    /// The target's baseline (SSE2 on x86-64; every other architecture).
    Baseline,
    /// AVX2 with FMA (256-bit vectors).
    Avx2Fma,
    /// AVX-512F with AVX2 and FMA (512-bit vectors).
    Avx512,
}

impl Isa {
    /// Its name in the bench's machine record (`avx512`, `avx2`, `baseline`).
    pub fn name(self) -> &'static str {
        match self {
            Isa::Baseline => "baseline",
            Isa::Avx2Fma => "avx2",
            Isa::Avx512 => "avx512",
        }
    }
}

/// The widest level this CPU has, detected once: every kernel call reads it (twice, with its
/// check), so it is one load rather than three feature detections.
pub fn isa() -> Isa {
    static LEVEL: std::sync::OnceLock<Isa> = std::sync::OnceLock::new();
    *LEVEL.get_or_init(detect)
}

fn detect() -> Isa {
    #[cfg(target_arch = "x86_64")]
    {
        let avx2_fma =
            std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma");
        if avx2_fma && std::is_x86_feature_detected!("avx512f") {
            return Isa::Avx512;
        }
        if avx2_fma {
            return Isa::Avx2Fma;
        }
    }
    Isa::Baseline
}

/// Every level this CPU can run, narrowest first (the kernels' agreement tests run each).
pub fn available() -> Vec<Isa> {
    [Isa::Baseline, Isa::Avx2Fma, Isa::Avx512]
        .into_iter()
        .filter(|&level| level <= isa())
        .collect()
}

/// Runs `kernel` at every level this CPU has and asserts that the bits of what it returns
/// agree with the baseline's (the agreement tests of the [`vectorised!`] kernels).
pub fn assert_levels_agree(kernel: impl Fn(Isa) -> Vec<u32>) {
    let want = kernel(Isa::Baseline);
    for level in available() {
        assert!(kernel(level) == want, "{level:?} differs from the baseline");
    }
}

/// The bits of `values`, to compare kernels' outputs exactly.
pub fn bits(values: &[f32]) -> Vec<u32> {
    values.iter().map(|v| v.to_bits()).collect()
}

/// `vectorised!(fn NAME / NAME_AT(ARGS) -> RET = BODY;)` defines `NAME(ARGS)`, which runs the
/// `#[inline(always)]` function `BODY` compiled for the widest [`Isa`] this CPU has, and
/// `NAME_AT(isa, ARGS)`, which runs it compiled for `isa` (panics if the CPU lacks it).
#[macro_export]
macro_rules! vectorised {
    ($(#[$meta:meta])* $vis:vis fn $name:ident / $at:ident ($($arg:ident: $ty:ty),* $(,)?)
        $(-> $ret:ty)? = $body:path;) => {
        $(#[$meta])*
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            $at($crate::simd::isa(), $($arg),*)
        }

        #[doc = concat!("[`", stringify!($name), "`] compiled for `isa`.")]
        $vis fn $at(isa: $crate::simd::Isa, $($arg: $ty),*) $(-> $ret)? {
            assert!(isa <= $crate::simd::isa(), "{isa:?}: this CPU lacks it");
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx2,fma")]
                fn avx512($($arg: $ty),*) $(-> $ret)? {
                    $body($($arg),*)
                }
                #[target_feature(enable = "avx2,fma")]
                fn avx2($($arg: $ty),*) $(-> $ret)? {
                    $body($($arg),*)
                }
                match isa {
                    // SAFETY: the CPU has the level's features (asserted above).
                    $crate::simd::Isa::Avx512 => return unsafe { avx512($($arg),*) },
                    // SAFETY: as above.
                    $crate::simd::Isa::Avx2Fma => return unsafe { avx2($($arg),*) },
                    $crate::simd::Isa::Baseline => {}
                }
            }
            $body($($arg),*)
        }
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    #[inline(always)]
    fn scaled_exp_body(dst: &mut [f32], src: &[f32]) {
        for (d, s) in dst.iter_mut().zip(src) {
            *d = crate::fast_exp::exp(*s) * 0.5 + *s;
        }
    }

    vectorised!(fn scaled_exp / scaled_exp_at(dst: &mut [f32], src: &[f32]) = scaled_exp_body;);

    /// The levels are ordered from the baseline to the widest, and a body gives the same bits
    /// at each (the dispatching function runs the widest).
    #[test]
    fn every_level_gives_the_same_bits() {
        let levels = available();
        assert_eq!(levels[0], Isa::Baseline);
        assert_eq!(*levels.last().unwrap(), isa());
        let src: Vec<f32> = (0..1000).map(|i| (i as f32 - 500.0) * 0.173).collect();
        let mut widest = vec![0f32; src.len()];
        scaled_exp(&mut widest, &src);
        assert_levels_agree(|level| {
            let mut got = vec![0f32; src.len()];
            scaled_exp_at(level, &mut got, &src);
            assert!(level != isa() || got == widest);
            bits(&got)
        });
    }
}
