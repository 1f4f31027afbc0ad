//! Reading the f32 values of CPU tensors and storages inside the fused ops (the convolution
//! here, the GRU of the later stages) without copying them when they are contiguous.

use candle_core::{CpuStorage, Layout, Result, Storage, StorageRef, Tensor};

/// The values of a contiguous f32 storage slice; `what` names the operand in the error.
pub fn contiguous_f32<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [f32]> {
    let (start, end) = l
        .contiguous_offsets()
        .ok_or_else(|| candle_core::Error::Msg(format!("fused op: {what} must be contiguous")))?;
    Ok(&s.as_slice::<f32>()?[start..end])
}

/// A copy of an f32 tensor's values in row-major order.
pub fn tensor_f32(t: &Tensor) -> Result<Vec<f32>> {
    t.contiguous()?.flatten_all()?.to_vec1::<f32>()
}

/// The values of an f32 tensor: borrowed from its storage when it is contiguous on the CPU
/// (copying every activation and gradient in the backward pass cost ~4% of a step), else
/// copied.
pub enum F32Values<'a> {
    /// Borrowed from the tensor's storage (start and end offsets).
    Borrowed(StorageRef<'a>, (usize, usize)),
    /// A row-major copy.
    Owned(Vec<f32>),
}

impl<'a> F32Values<'a> {
    /// The values of `t`.
    pub fn of(t: &'a Tensor) -> Result<Self> {
        let (storage, layout) = t.storage_and_layout();
        if let (Storage::Cpu(CpuStorage::F32(_)), Some(range)) =
            (&*storage, layout.contiguous_offsets())
        {
            return Ok(Self::Borrowed(storage, range));
        }
        drop(storage);
        Ok(Self::Owned(tensor_f32(t)?))
    }
}

impl std::ops::Deref for F32Values<'_> {
    type Target = [f32];

    fn deref(&self) -> &[f32] {
        match self {
            Self::Borrowed(storage, (start, end)) => match &**storage {
                Storage::Cpu(CpuStorage::F32(values)) => &values[*start..*end],
                _ => unreachable!("F32Values::of borrows f32 CPU storage only"),
            },
            Self::Owned(values) => values,
        }
    }
}
