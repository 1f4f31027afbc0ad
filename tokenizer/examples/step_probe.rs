use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use std::time::Instant;
use tokenizer::{ConvConfig, ConvDecoder, ConvEncoder, FsqConfig, FsqQuantizer};

fn main() {
    let batch: usize = std::env::args()
        .nth(1)
        .map(|s| s.parse().unwrap())
        .unwrap_or(64);
    let config = ConvConfig::default();
    let map = VarMap::new();
    let vb = VarBuilder::from_varmap(&map, DType::F32, &Device::Cpu);
    let enc = ConvEncoder::new(&config, vb.pp("encoder")).unwrap();
    let fsq = FsqQuantizer::new(
        &FsqConfig {
            dim: 512,
            levels: vec![8, 5, 5, 5],
            bound: Default::default(),
        },
        vb.pp("quant"),
    )
    .unwrap();
    let dec = ConvDecoder::new(&config, vb.pp("decoder")).unwrap();
    let x = Tensor::randn(0f32, 1.0, (batch, 64, 263), &Device::Cpu).unwrap();
    for i in 0..4 {
        let t0 = Instant::now();
        let q = fsq.forward(&enc.forward(&x).unwrap()).unwrap().quantized;
        let y = dec.forward(&q).unwrap();
        let loss = (y - &x).unwrap().abs().unwrap().mean_all().unwrap();
        let t1 = Instant::now();
        let _g = loss.backward().unwrap();
        let t2 = Instant::now();
        println!(
            "step {i}: fwd {:.3}s bwd {:.3}s",
            (t1 - t0).as_secs_f64(),
            (t2 - t1).as_secs_f64()
        );
    }
}
