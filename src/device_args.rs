//! `--device`: the one place a command chooses where its networks run.

use candle_core::Device;
use nn::device::DeviceSpec;

/// The device flag every command that trains or runs a network takes.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct DeviceArgs {
    /// Where the networks run: cpu, cuda or cuda:N (default: the first GPU when built with
    /// `--features cuda` and one is present, else the CPU).
    #[arg(long, value_name = "cpu|cuda[:N]")]
    pub device: Option<DeviceSpec>,
}

impl DeviceArgs {
    /// The device asked for, or the build's default.
    pub fn spec(&self) -> DeviceSpec {
        self.device.unwrap_or_else(DeviceSpec::default_for_build)
    }

    /// The device, opened (a clear error when this build or machine lacks it).
    pub fn open(&self) -> anyhow::Result<Device> {
        Ok(self.spec().open()?)
    }
}
