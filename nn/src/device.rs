//! Devices and precisions as the command line names them (`cpu`, `cuda`, `cuda:N`; `f32`,
//! `bf16`). The binary parses a [`DeviceSpec`], opens it once with [`DeviceSpec::open`] and
//! passes the [`Device`] down; no library picks a device on its own.
//!
//! Each device is opened once per process: every `Device::new_cuda` is a new device (its own
//! context, handles and kernels), and candle refuses to combine tensors of two of them.

use crate::error::NnError;
use candle_core::{DType, Device, DeviceLocation};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// A device named on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DeviceSpec {
    /// The CPU.
    Cpu,
    /// CUDA GPU number N (`cuda` = `cuda:0`).
    Cuda(usize),
}

impl FromStr for DeviceSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "cpu" => Ok(Self::Cpu),
            "cuda" => Ok(Self::Cuda(0)),
            _ => s
                .strip_prefix("cuda:")
                .and_then(|n| n.parse().ok())
                .map(Self::Cuda)
                .ok_or_else(|| format!("unknown device {s:?}: expected cpu, cuda or cuda:N")),
        }
    }
}

impl fmt::Display for DeviceSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Cpu => write!(f, "cpu"),
            Self::Cuda(n) => write!(f, "cuda:{n}"),
        }
    }
}

impl DeviceSpec {
    /// The default: the first GPU when built with `cuda` and one opens, else the CPU
    /// (candle's `cuda_is_available` only says how the binary was built, so the GPU is
    /// opened to find out; it stays open for the process).
    pub fn default_for_build() -> Self {
        if cfg!(feature = "cuda") && open_cuda(0).is_ok() {
            Self::Cuda(0)
        } else {
            Self::Cpu
        }
    }

    /// The device, opened on first use and shared by every later call in the process; a
    /// clear error when this build or this machine has no such device.
    pub fn open(&self) -> Result<Device, NnError> {
        match *self {
            Self::Cpu => Ok(Device::Cpu),
            Self::Cuda(n) => open_cuda(n),
        }
    }
}

#[cfg(feature = "cuda")]
fn open_cuda(ordinal: usize) -> Result<Device, NnError> {
    use std::collections::HashMap;
    use std::sync::Mutex;
    static OPEN: Mutex<Option<HashMap<usize, Device>>> = Mutex::new(None);
    let mut open = OPEN.lock().expect("device table lock");
    let table = open.get_or_insert_with(HashMap::new);
    if let Some(device) = table.get(&ordinal) {
        return Ok(device.clone());
    }
    let device = Device::new_cuda(ordinal).map_err(|e| {
        NnError::Device(format!(
            "cannot open cuda:{ordinal} ({e}); pass --device cpu on a machine without that GPU"
        ))
    })?;
    keep_freed_memory(&device)
        .map_err(|e| NnError::Device(format!("cuda:{ordinal}: its memory pool: {e}")))?;
    table.insert(ordinal, device.clone());
    Ok(device)
}

/// The device's stream-ordered memory pool, with the context bound to this thread.
#[cfg(feature = "cuda")]
fn memory_pool(
    device: &Device,
) -> candle_core::Result<candle_core::cuda::cudarc::driver::sys::CUmemoryPool> {
    let cuda = device.as_cuda_device()?;
    let stream = cuda.cuda_stream();
    let context = stream.context();
    context.bind_to_thread().map_err(candle_core::Error::wrap)?;
    // SAFETY: the context's own device.
    unsafe {
        candle_core::cuda::cudarc::driver::result::device::get_default_mem_pool(context.cu_device())
    }
    .map_err(candle_core::Error::wrap)
}

/// Keep freed memory in the pool for reuse (release threshold at its maximum), as PyTorch's
/// caching allocator does: at the default threshold of 0 the pool returns it to the driver
/// at every synchronisation, and every step allocates it anew.
#[cfg(feature = "cuda")]
fn keep_freed_memory(device: &Device) -> candle_core::Result<()> {
    use candle_core::cuda::cudarc::driver::{result::mem_pool, sys};
    let pool = memory_pool(device)?;
    let mut threshold = u64::MAX;
    let attr = sys::CUmemPool_attribute::CU_MEMPOOL_ATTR_RELEASE_THRESHOLD;
    // SAFETY: a valid pool; the attribute is a u64.
    unsafe { mem_pool::set_attribute(pool, attr, (&mut threshold as *mut u64).cast()) }
        .map_err(candle_core::Error::wrap)
}

/// The most memory the GPU's pool has had allocated since the last call (bytes; the
/// counterpart of PyTorch's `max_memory_allocated`), its mark then reset; `None` off a GPU.
pub fn gpu_peak_allocated(device: &Device) -> candle_core::Result<Option<u64>> {
    #[cfg(feature = "cuda")]
    if device.is_cuda() {
        use candle_core::cuda::cudarc::driver::{result::mem_pool, sys};
        let pool = memory_pool(device)?;
        let attr = sys::CUmemPool_attribute::CU_MEMPOOL_ATTR_USED_MEM_HIGH;
        let (mut high, mut zero) = (0u64, 0u64);
        // SAFETY: a valid pool; the attribute is a u64 (reset by writing 0).
        unsafe {
            mem_pool::get_attribute(pool, attr, (&mut high as *mut u64).cast())
                .and_then(|_| mem_pool::set_attribute(pool, attr, (&mut zero as *mut u64).cast()))
        }
        .map_err(candle_core::Error::wrap)?;
        return Ok(Some(high));
    }
    let _ = device;
    Ok(None)
}

#[cfg(not(feature = "cuda"))]
fn open_cuda(ordinal: usize) -> Result<Device, NnError> {
    Err(NnError::Device(format!(
        "cuda:{ordinal} asked for, but this binary was built without CUDA: rebuild with \
         --features cuda (scripts/build-cuda.sh) or pass --device cpu"
    )))
}

/// The name a device is recorded under: `cpu`, `cuda:N` (or `metal:N`).
pub fn device_name(device: &Device) -> String {
    match device.location() {
        DeviceLocation::Cpu => "cpu".into(),
        DeviceLocation::Cuda { gpu_id } => format!("cuda:{gpu_id}"),
        DeviceLocation::Metal { gpu_id } => format!("metal:{gpu_id}"),
    }
}

/// The arithmetic of a training step: all f32, or bf16 products from f32 master weights
/// (f32 optimiser state, f32 accumulation in norms, softmax and the loss).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// f32 throughout.
    #[default]
    F32,
    /// bf16 matrix products (weights cast from their f32 masters at every step).
    Bf16,
}

impl Precision {
    /// The dtype of the matrix products.
    pub fn compute_dtype(self) -> DType {
        match self {
            Self::F32 => DType::F32,
            Self::Bf16 => DType::BF16,
        }
    }
}

impl FromStr for Precision {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "f32" => Ok(Self::F32),
            "bf16" => Ok(Self::Bf16),
            _ => Err(format!("unknown precision {s:?}: expected f32 or bf16")),
        }
    }
}

impl fmt::Display for Precision {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::F32 => "f32",
            Self::Bf16 => "bf16",
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn device_names_parse_and_print_back() {
        for (text, spec) in [
            ("cpu", DeviceSpec::Cpu),
            ("cuda:0", DeviceSpec::Cuda(0)),
            ("cuda:3", DeviceSpec::Cuda(3)),
        ] {
            assert_eq!(text.parse::<DeviceSpec>(), Ok(spec));
            assert_eq!(spec.to_string(), text);
        }
        assert_eq!("cuda".parse::<DeviceSpec>(), Ok(DeviceSpec::Cuda(0)));
        for bad in ["gpu", "cuda:", "cuda:x", "CPU"] {
            let err = bad.parse::<DeviceSpec>().unwrap_err();
            assert!(err.contains("expected cpu, cuda or cuda:N"), "{err}");
        }
        assert_eq!(device_name(&DeviceSpec::Cpu.open().unwrap()), "cpu");
        assert_eq!("bf16".parse::<Precision>(), Ok(Precision::Bf16));
        assert!("fp16".parse::<Precision>().is_err());
    }

    #[cfg(not(feature = "cuda"))]
    #[test]
    fn a_gpu_without_cuda_is_a_clear_error() {
        let err = DeviceSpec::Cuda(0).open().unwrap_err().to_string();
        assert!(err.contains("built without CUDA"), "{err}");
        assert!(err.contains("--device cpu"), "{err}");
    }
}
