//! Which tensor backend a fit, render or benchmark runs on: a `Device` chosen at run time, so
//! a GPU backend stays a flag away.

use burn::tensor::Device;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// burn's pure-Rust CPU backend (default; the faster one here).
    Flex,
    /// burn-ndarray.
    Ndarray,
}

impl Backend {
    pub fn device(self) -> Device {
        match self {
            Backend::Flex => Device::flex().autodiff(),
            #[allow(deprecated)]
            Backend::Ndarray => Device::ndarray().autodiff(),
        }
    }
}
