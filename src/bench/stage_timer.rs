//! The stage timer of `bench train` on a GPU: a [`StageClock`] that waits for the device at
//! the end of each stage of the GPU executor's step and adds the time since the previous one
//! to that stage. Steps run slower while it times them, so the bench times them apart.

use candle_core::{Device, Result};
use lm::prefix_lm::{LmBatch, PrefixLm, StageClock};
use std::cell::RefCell;
use std::collections::BTreeMap;
use std::time::Instant;

/// Seconds per stage, summed over the steps timed.
struct StageTimer {
    device: Device,
    last: RefCell<Instant>,
    seconds: RefCell<BTreeMap<&'static str, f64>>,
}

impl StageClock for StageTimer {
    fn stage_done(&self, stage: &'static str) -> Result<()> {
        self.device.synchronize()?;
        let now = Instant::now();
        let secs = (now - self.last.replace(now)).as_secs_f64();
        *self.seconds.borrow_mut().entry(stage).or_insert(0.0) += secs;
        Ok(())
    }
}

/// Mean milliseconds per training step of each stage of `model`'s step on `batch`, over
/// `steps` steps (one stage, `step`, for executors other than the GPU one).
pub(super) fn stage_ms(
    model: &PrefixLm,
    batch: &LmBatch,
    steps: usize,
) -> Result<BTreeMap<String, f64>> {
    let timer = StageTimer {
        device: model.device().clone(),
        last: RefCell::new(Instant::now()),
        seconds: RefCell::default(),
    };
    for _ in 0..steps {
        model.device().synchronize()?;
        timer.last.replace(Instant::now());
        model.loss_and_grads_timed(batch, &timer)?;
    }
    let per_step = 1e3 / steps.max(1) as f64;
    Ok(timer
        .seconds
        .into_inner()
        .into_iter()
        .map(|(stage, secs)| (stage.to_string(), secs * per_step))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use lm::prefix_lm::{init_model, Compute, Executor, PrefixLmConfig};
    use nn::device::Precision;

    fn model_and_batch(executor: Executor) -> (PrefixLm, LmBatch) {
        let config = PrefixLmConfig::new(16, 2, 2, 12, 8);
        let (model, _) = init_model(&config, 3, &Device::Cpu).unwrap();
        let model = model.with_compute(Compute {
            executor: Some(executor),
            precision: Precision::F32,
        });
        let text = [0.1f32; 16];
        let batch = LmBatch::new(&config, &[&text[..]], &[(&[1u32, 2, 3][..], true)]);
        (model, batch)
    }

    #[test]
    fn the_gpu_executor_step_splits_into_its_stages() {
        let (model, batch) = model_and_batch(Executor::Gpu);
        let ms = stage_ms(&model, &batch, 2).unwrap();
        assert_eq!(ms.len(), 11, "{:?}", ms.keys());
        assert!(ms.contains_key("backward: output product, attention"));
        assert!(ms.values().all(|v| v.is_finite() && *v >= 0.0), "{ms:?}");
    }

    #[test]
    fn other_executors_time_one_stage() {
        let (model, batch) = model_and_batch(Executor::Cpu);
        let ms = stage_ms(&model, &batch, 1).unwrap();
        assert_eq!(ms.keys().collect::<Vec<_>>(), ["step"]);
    }
}
