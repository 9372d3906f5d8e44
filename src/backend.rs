//! Which tensor backend a fit, render or benchmark runs on: a `Device` chosen at run time, so
//! a GPU backend stays a flag away.

use burn::tensor::Device;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// burn's pure-Rust CPU backend (default; the faster one here).
    Flex,
    /// burn-ndarray.
    Ndarray,
    /// burn's wgpu backend: the best GPU the machine offers (Vulkan, Metal or DX12), or a
    /// software driver where there is none. Built with the `gpu` feature.
    #[cfg(feature = "gpu")]
    Wgpu,
}

impl Backend {
    pub fn device(self) -> Device {
        match self {
            Backend::Flex => Device::flex().autodiff(),
            #[allow(deprecated)]
            Backend::Ndarray => Device::ndarray().autodiff(),
            #[cfg(feature = "gpu")]
            Backend::Wgpu => Device::wgpu(burn::tensor::DeviceKind::DefaultDevice).autodiff(),
        }
    }
}

/// Why a tensor's values could not be copied to the host.
#[derive(Debug, thiserror::Error)]
#[error("copying a tensor's values to the host: {0}")]
pub struct HostError(String);

/// A tensor's values on the host as f32, in row-major order: the one way tensors leave the
/// device.
pub fn to_host<const D: usize>(t: burn::tensor::Tensor<D>) -> Result<Vec<f32>, HostError> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().map_err(|e| HostError(format!("{e:?}")))
}

/// `to_host`, or as many NaNs as the tensor holds when the copy fails: where a caller cannot
/// stop, a failed copy shows as non-finite values (which fits and renders refuse), never as a
/// short or empty vector read as if it were data.
pub fn host_values<const D: usize>(t: burn::tensor::Tensor<D>) -> Vec<f32> {
    let n = t.shape().num_elements();
    to_host(t).unwrap_or_else(|_| vec![f32::NAN; n])
}

/// A one-value tensor's value (NaN when it holds none or the copy fails).
pub fn host_scalar<const D: usize>(t: burn::tensor::Tensor<D>) -> f32 {
    host_values(t).first().copied().unwrap_or(f32::NAN)
}
