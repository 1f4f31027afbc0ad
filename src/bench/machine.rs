//! The machine a bench ran on, recorded beside every figure: CPU model, topology, caches (as
//! the OS and as gemm read them), the vector instruction sets detected at run time and this
//! machine's fp32 FMA peak measured now (the MFU denominator, and the ceiling no executor can
//! pass).

use serde::{Deserialize, Serialize};
use std::sync::OnceLock;
use std::time::Instant;

/// The fp32 FMA peak of this machine at the clock it runs vector code at now.
#[derive(Debug, Clone)]
pub struct FmaPeak {
    /// GFLOP/s on all of the pool's threads (an FMA counts as two FLOPs).
    pub gflops: f64,
    /// The vectors it ran with: `avx512`, `avx2` (x86), `scalar`, else their width in bits.
    pub isa: String,
    /// Threads that ran FMAs at once (the rayon pool's).
    pub threads: usize,
}

/// Independent accumulator chains per thread: enough to cover the FMA latency on two pipes.
const CHAINS: usize = 12;

/// The chains' multiplier and addend (a chain stays near 1, far from overflow and denormals).
const FMA_B: f32 = 0.999_999_9;
const FMA_C: f32 = 1e-7;

/// `self.0` rounds of one FMA on each of `CHAINS` vector registers, then the sum of every
/// lane (so the work is kept): one kernel, run with the widest vectors the CPU has (pulp, the
/// SIMD layer gemm dispatches through, chooses them at run time).
struct FmaChains(u64);

impl pulp::WithSimd for FmaChains {
    /// The sum, and the f32 lanes of the vectors it ran with.
    type Output = (f32, usize);

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) -> (f32, usize) {
        // Opaque starts, multiplier and addend: the compiler cannot merge the equal chains
        // into one or fold them away.
        let starts = std::hint::black_box([1.0f32; CHAINS]);
        let b = simd.splat_f32s(std::hint::black_box(FMA_B));
        let c = simd.splat_f32s(std::hint::black_box(FMA_C));
        let mut acc = starts.map(|x| simd.splat_f32s(x));
        for _ in 0..self.0 {
            for a in acc.iter_mut() {
                *a = simd.mul_add_f32s(*a, b, c);
            }
        }
        let sum = acc.iter().map(|&a| simd.reduce_sum_f32s(a)).sum();
        (sum, std::mem::size_of::<S::f32s>() / 4)
    }
}

/// `iters` rounds of [`FmaChains`] with the widest vectors this CPU has: the sum and the lanes.
fn fma_chains(iters: u64) -> (f32, usize) {
    pulp::Arch::new().dispatch(FmaChains(iters))
}

/// The name of `lanes`-wide f32 vectors (x86's instruction sets by name, as gemm's kernels).
fn vector_isa(lanes: usize) -> String {
    match (cfg!(target_arch = "x86_64"), lanes) {
        (true, 16) => "avx512".into(),
        (true, 8) => "avx2".into(),
        (_, 1) => "scalar".into(),
        _ => format!("{}-bit", 32 * lanes),
    }
}

/// GFLOP/s of [`fma_chains`] on every pool thread at once, `iters` rounds each; the lanes.
fn fma_rate(iters: u64) -> (f64, usize) {
    let started = Instant::now();
    let runs = rayon::broadcast(|_| fma_chains(std::hint::black_box(iters)));
    let seconds = started.elapsed().as_secs_f64();
    let lanes = std::hint::black_box(runs)[0].1;
    let flops = (rayon::current_num_threads() * CHAINS * lanes * 2) as f64 * iters as f64;
    (flops / seconds / 1e9, lanes)
}

/// This machine's fp32 FMA peak now (about half a second): the best of three runs of 0.15 s on
/// every pool thread (`../shared/bench/peak_fma.c`'s method).
pub fn measure_fma_peak() -> FmaPeak {
    let threads = rayon::current_num_threads();
    let probe = 100_000;
    let (rate, lanes) = fma_rate(probe);
    let per_thread = rate * 1e9 / (threads * CHAINS * lanes * 2) as f64;
    let iters = ((0.15 * per_thread) as u64).max(probe);
    let gflops = (0..3).map(|_| fma_rate(iters).0).fold(0.0, f64::max);
    FmaPeak {
        gflops,
        isa: vector_isa(lanes),
        threads,
    }
}

/// [`measure_fma_peak`] once per process: the peak a bench starts from.
pub fn fma_peak() -> &'static FmaPeak {
    static PEAK: OnceLock<FmaPeak> = OnceLock::new();
    PEAK.get_or_init(measure_fma_peak)
}

/// The peak around a timed piece of work: `before` (the peak the bench started from) and the
/// peak measured again after it, the larger kept. A shared machine's clock and neighbours move
/// within minutes, and a peak measured in a slow moment would put MFU above 100%. With
/// `--peak-gflops` (`given`) the flag's value stands.
pub fn peak_around(before: f64, given: bool) -> f64 {
    match given {
        true => before,
        false => before.max(measure_fma_peak().gflops),
    }
}

/// An MFU as a percentage, or why there is none.
pub fn mfu_text(mfu: Option<f64>) -> String {
    mfu.map_or(
        "n/a (the rate passed the peak measured around it)".into(),
        |m| format!("{:.1}%", 100.0 * m),
    )
}

/// MFU of `gflops` against `peak`; `None` where it would pass 100% (the peak was measured in
/// a disturbed moment, and no executor can pass it).
pub fn mfu(gflops: f64, peak: f64) -> Option<f64> {
    let share = gflops / peak;
    (share.is_finite() && share <= 1.0).then_some(share)
}

/// The fp32 peak MFU is measured against: `flag` where given, else this machine's FMA peak
/// measured now; with the words that say which.
pub fn mfu_peak(flag: Option<f64>) -> (f64, String) {
    match flag {
        Some(gflops) => (gflops, "--peak-gflops".into()),
        None => {
            let peak = fma_peak();
            let source = format!(
                "FMA peak measured now, {}, {} threads",
                peak.isa, peak.threads
            );
            (peak.gflops, source)
        }
    }
}

/// The machine a bench ran on (the `machine` of every bench's `--json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Machine {
    /// `/proc/cpuinfo`'s model name.
    pub cpu_model: Option<String>,
    /// Its vendor_id.
    pub vendor: Option<String>,
    /// Its cpu family.
    pub cpu_family: Option<String>,
    /// Its model (number).
    pub cpu_model_number: Option<String>,
    /// CPUs and cores.
    pub topology: Topology,
    /// Cache levels of CPU 0 as the OS reports them.
    pub caches: Vec<Cache>,
    /// The cache sizes gemm blocks for (L1, L2, L3), bytes per core.
    pub gemm_cache_bytes_per_core: Vec<usize>,
    /// The vector instruction sets detected at run time (x86 only; empty elsewhere).
    pub isa: Isa,
    /// The vectors gemm's kernels take ([`vector_isa`]'s names).
    pub gemm_kernels: String,
    /// The vectors our row kernels (exp, σ, GELU, softmax rows, AdamW) take (`nn::simd`).
    #[serde(default)]
    pub row_kernels: String,
    /// How weight-gradient products read their transposed left operand here
    /// (`nn::matmul::TransposedLhs`: "in-place" or "copied", measured at first use).
    #[serde(default)]
    pub transposed_lhs: String,
    /// This machine's fp32 FMA peak measured now, GFLOP/s ([`fma_peak`]).
    pub fma_peak_gflops: f64,
    /// The vectors that peak ran with.
    pub fma_peak_isa: String,
    /// Threads of the pool.
    pub threads: usize,
}

/// Logical CPUs online and the distinct (package, core) pairs among them.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Topology {
    /// Logical CPUs online.
    pub logical_cpus: usize,
    /// Distinct (package, core) pairs.
    pub physical_cores: usize,
    /// Logical CPUs per core (none without cores).
    pub threads_per_core: Option<f64>,
}

/// One cache level of CPU 0, as `/sys/devices/system/cpu/cpu0/cache/index*` words it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Cache {
    /// Level (1, 2, 3).
    pub level: String,
    /// Data, Instruction or Unified.
    #[serde(rename = "type")]
    pub kind: String,
    /// Size, e.g. "48K".
    pub size: String,
    /// Ways of associativity.
    pub ways: Option<String>,
    /// The CPUs sharing it, as a list.
    pub shared_by_cpus: Option<String>,
}

/// The x86 vector instruction sets detected at run time (absent elsewhere).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Isa {
    /// AVX-512 F.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub avx512f: Option<bool>,
    /// AVX2.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub avx2: Option<bool>,
    /// FMA.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub fma: Option<bool>,
}

/// Logical CPUs online and the distinct (package, core) pairs among them.
fn topology() -> Topology {
    let mut cores = std::collections::BTreeSet::new();
    let mut logical = 0;
    let cpus = std::fs::read_dir("/sys/devices/system/cpu")
        .into_iter()
        .flatten();
    for entry in cpus.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let numbered = name.strip_prefix("cpu").map(|n| n.parse::<u32>().is_ok());
        if numbered != Some(true) {
            continue;
        }
        let read = |f: &str| std::fs::read_to_string(entry.path().join("topology").join(f));
        if let (Ok(package), Ok(core)) = (read("physical_package_id"), read("core_id")) {
            logical += 1;
            cores.insert((package.trim().to_string(), core.trim().to_string()));
        }
    }
    Topology {
        logical_cpus: logical,
        physical_cores: cores.len(),
        threads_per_core: (!cores.is_empty()).then(|| logical as f64 / cores.len() as f64),
    }
}

/// Cache levels of CPU 0 as the OS reports them.
fn caches() -> Vec<Cache> {
    (0..8)
        .map_while(|i| {
            let dir = format!("/sys/devices/system/cpu/cpu0/cache/index{i}");
            let read = |f: &str| std::fs::read_to_string(format!("{dir}/{f}")).ok();
            let (level, kind, size) = (read("level")?, read("type")?, read("size")?);
            Some(Cache {
                level: level.trim().into(),
                kind: kind.trim().into(),
                size: size.trim().into(),
                ways: read("ways_of_associativity").map(|s| s.trim().to_string()),
                shared_by_cpus: read("shared_cpu_list").map(|s| s.trim().to_string()),
            })
        })
        .collect()
}

/// The machine a bench ran on: CPU model and vendor, topology, caches, the vector instruction
/// sets the kernels can choose from (detected at run time) and the ones gemm and our element-wise
/// kernels take, the cache sizes gemm blocks for, the FMA peak measured now, threads.
pub fn machine() -> Machine {
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let field = |name: &str| {
        cpuinfo
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_once(':'))
            .map(|(_, v)| v.trim().to_string())
    };
    #[cfg(target_arch = "x86_64")]
    let isa = Isa {
        avx512f: Some(std::arch::is_x86_feature_detected!("avx512f")),
        avx2: Some(std::arch::is_x86_feature_detected!("avx2")),
        fma: Some(std::arch::is_x86_feature_detected!("fma")),
    };
    #[cfg(not(target_arch = "x86_64"))]
    let isa = Isa::default();
    // gemm (x86-v4 feature on) takes its AVX-512 kernels where the CPU has them.
    let gemm_lanes = match (isa.avx512f, isa.avx2) {
        (Some(true), _) => 16,
        (_, Some(true)) => 8,
        _ => 1,
    };
    let gemm_caches: Vec<usize> = gemm_common::cache::CACHE_INFO
        .iter()
        .map(|c| c.cache_bytes)
        .collect();
    let peak = fma_peak();
    Machine {
        cpu_model: field("model name"),
        vendor: field("vendor_id"),
        cpu_family: field("cpu family"),
        cpu_model_number: field("model\t"),
        topology: topology(),
        caches: caches(),
        gemm_cache_bytes_per_core: gemm_caches,
        isa,
        gemm_kernels: vector_isa(gemm_lanes),
        row_kernels: nn::simd::isa().name().into(),
        transposed_lhs: nn::matmul::TransposedLhs::chosen().name().into(),
        fma_peak_gflops: peak.gflops,
        fma_peak_isa: peak.isa.clone(),
        threads: rayon::current_num_threads(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A rate above the peak measured around it has no MFU; a peak given by flag is kept, one
    /// measured is raised to the larger of before and after.
    #[test]
    fn mfu_never_passes_the_peak_measured_around_the_work() {
        assert_eq!(mfu(50.0, 100.0), Some(0.5));
        assert_eq!(mfu(102.6, 100.0), None);
        assert_eq!(mfu(1.0, 0.0), None);
        assert!(mfu_text(None).starts_with("n/a"));
        assert_eq!(mfu_text(Some(0.367)), "36.7%");
        assert_eq!(peak_around(1e9, true), 1e9);
        assert_eq!(peak_around(1e9, false), 1e9, "no CPU reaches 10^18 FLOP/s");
        assert!(
            peak_around(1e-9, false) > 1.0,
            "measured again: a real rate"
        );
    }

    #[test]
    fn the_fma_chains_compute_the_scalar_recurrence_in_every_lane() {
        let x = (0..3).fold(1.0f32, |x, _| x.mul_add(FMA_B, FMA_C));
        let (sum, lanes) = fma_chains(3);
        let expected = x * (CHAINS * lanes) as f32;
        // The lanes are summed in a tree, so to rounding.
        assert!(
            (sum - expected).abs() <= 1e-5 * expected,
            "{sum} vs {expected}"
        );
    }

    #[test]
    fn the_machine_record_names_its_topology_and_peak() {
        let m = machine();
        let topology = &m.topology;
        assert!(topology.logical_cpus >= 1, "{m:?}");
        assert!(topology.physical_cores <= topology.logical_cpus, "{m:?}");
        assert_eq!(m.gemm_cache_bytes_per_core.len(), 3);
        assert!(m.fma_peak_gflops > 0.0, "{m:?}");
    }
}
