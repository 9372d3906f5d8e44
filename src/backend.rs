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

impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let name = format!("{self:?}").to_lowercase();
        f.write_str(&name)
    }
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

/// Why a backend's device cannot be used.
#[derive(Debug, thiserror::Error)]
#[error("the {backend} backend found no usable device: {reason}")]
pub struct DeviceError {
    backend: Backend,
    reason: String,
}

impl Backend {
    /// The device, checked usable: on a GPU backend a first tensor is made and read back, so
    /// that a machine with no adapter (or a broken driver) is refused with a reason here rather
    /// than failing in the middle of a fit. The CPU backends are always usable.
    pub fn open(self) -> Result<Device, DeviceError> {
        let device = self.device();
        if matches!(self, Backend::Flex | Backend::Ndarray) {
            return Ok(device);
        }
        let probe = device.clone();
        // The runtime panics when it finds no adapter: caught here, and said in words.
        let outcome = std::panic::catch_unwind(move || {
            let one = burn::tensor::Tensor::<1>::from_data(burn::tensor::TensorData::new(vec![1.0f32], [1]), &probe);
            to_host(one + 1.0)
        });
        let reason = match outcome {
            Ok(Ok(values)) if values == [2.0] => return Ok(device),
            Ok(Ok(values)) => format!("1 + 1 came back as {values:?}"),
            Ok(Err(e)) => e.to_string(),
            Err(panic) => panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "the runtime stopped".into()),
        };
        let hint = "the graphics runtime says why above. Is a Vulkan, Metal or DirectX 12 driver installed? Without a GPU, Mesa's software Vulkan driver (Debian: mesa-vulkan-drivers) runs it, slowly";
        Err(DeviceError { backend: self, reason: format!("{reason}; {hint}") })
    }
}

/// The bytes `device`'s allocator holds reserved (its pools' pages, in use or kept for reuse),
/// where the device reports them: a GPU's. `None` on the CPU backends, whose tensors are the
/// process's own memory (`files::peak_memory_bytes`). After a step, which has read its losses
/// back, asking waits on nothing more.
pub fn device_memory_bytes(device: &Device) -> Option<u64> {
    if on_host(device) {
        return None;
    }
    device.memory_pool_usage().map(|usage| usage.bytes_reserved)
}

/// Whether `device` keeps its tensors in host memory (the CPU backends), where a host algorithm
/// reads them without a transfer; a GPU's would come down first.
pub fn on_host(device: &Device) -> bool {
    use burn::backend::DispatchDevice;
    matches!(device.clone().without_autodiff().as_dispatch(), DispatchDevice::Flex(_) | DispatchDevice::NdArray(_))
}

/// Why a tensor's values could not be copied to the host.
#[derive(Debug, thiserror::Error)]
#[error("copying a tensor's values to the host: {0}")]
pub struct HostError(String);

thread_local! {
    /// `to_host` calls on this thread (`reads_to_host`).
    static READS: std::cell::Cell<u64> = const { std::cell::Cell::new(0) };
}

/// How many times this thread has copied a tensor to the host (`to_host`): on a GPU each is a
/// wait for the device, so a test counts a piece of a step's reads by it.
pub fn reads_to_host() -> u64 {
    READS.with(|r| r.get())
}

/// A tensor's values on the host as f32, in row-major order: the one way tensors leave the
/// device.
pub fn to_host<const D: usize>(t: burn::tensor::Tensor<D>) -> Result<Vec<f32>, HostError> {
    READS.with(|r| r.set(r.get() + 1));
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
