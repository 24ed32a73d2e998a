//! Where a policy's tensors live: the CPU, or a CUDA GPU in a build with the `cuda` feature.
//!
//! The Diffusion Policy runs on any candle device: its fused CPU kernels
//! ([`crate::kernels`]) fall back to candle's own ops elsewhere. ACT is CPU-only for now.
//! The environment, the ensembler and the corruptions always run on the CPU; only the
//! policy's forward (and PGD's backward) move to the device.

use std::fmt;
use std::str::FromStr;

use candle_core::{Device, DeviceLocation};

use crate::error::PolicyError;

/// A compute device by name: `cpu`, `cuda` (GPU 0) or `cuda:N` (GPU `N`, CUDA's ordinal).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ComputeDevice {
    /// The CPU (candle's CPU backend with mte's fused kernels).
    #[default]
    Cpu,
    /// The CUDA GPU of this ordinal; needs a build with the `cuda` feature.
    Cuda(usize),
}

impl ComputeDevice {
    /// Whether this build can open CUDA devices (the crate's `cuda` feature).
    pub const CUDA_BUILT: bool = cfg!(feature = "cuda");

    /// Opens the device.
    ///
    /// # Errors
    /// [`PolicyError::Device`] for a CUDA device in a build without the `cuda` feature, or
    /// one the driver cannot open (no GPU of that ordinal, no driver), with candle's reason.
    pub fn open(self) -> Result<Device, PolicyError> {
        match self {
            Self::Cpu => Ok(Device::Cpu),
            Self::Cuda(_) if !Self::CUDA_BUILT => Err(PolicyError::Device {
                device: self.to_string(),
                reason: "this build has no CUDA support (build with the `cuda` feature)".into(),
            }),
            Self::Cuda(n) => Device::new_cuda(n).map_err(|e| PolicyError::Device {
                device: self.to_string(),
                reason: e.to_string(),
            }),
        }
    }

    /// The device at candle's `location`, the inverse of [`ComputeDevice::open`]; `None` for
    /// a location mte does not name (Metal).
    pub fn from_location(location: DeviceLocation) -> Option<Self> {
        match location {
            DeviceLocation::Cpu => Some(Self::Cpu),
            DeviceLocation::Cuda { gpu_id } => Some(Self::Cuda(gpu_id)),
            DeviceLocation::Metal { .. } => None,
        }
    }
}

impl fmt::Display for ComputeDevice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Cpu => f.write_str("cpu"),
            Self::Cuda(n) => write!(f, "cuda:{n}"),
        }
    }
}

impl FromStr for ComputeDevice {
    type Err = PolicyError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || crate::error::config_err("device", s, "cpu, cuda or cuda:N (N a GPU ordinal)");
        match s {
            "cpu" => Ok(Self::Cpu),
            "cuda" => Ok(Self::Cuda(0)),
            _ => {
                let n = s.strip_prefix("cuda:").ok_or_else(bad)?;
                n.parse().map(Self::Cuda).map_err(|_| bad())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_bad_names_are_refused() {
        for (text, dev) in [
            ("cpu", ComputeDevice::Cpu),
            ("cuda", ComputeDevice::Cuda(0)),
            ("cuda:3", ComputeDevice::Cuda(3)),
        ] {
            let parsed: ComputeDevice = text.parse().expect(text);
            assert_eq!(parsed, dev);
            let again: ComputeDevice = parsed.to_string().parse().expect("display parses");
            assert_eq!(again, dev);
        }
        for bad in ["gpu", "cuda:", "cuda:x", "cuda:-1", "CPU", ""] {
            let e = bad.parse::<ComputeDevice>().expect_err(bad).to_string();
            assert!(e.contains("cpu, cuda or cuda:N"), "{bad}: {e}");
            assert!(e.contains(&format!("{bad:?}")), "{bad}: {e}");
        }
    }

    #[test]
    fn locations_name_the_devices_they_open() {
        assert_eq!(
            ComputeDevice::from_location(DeviceLocation::Cpu),
            Some(ComputeDevice::Cpu)
        );
        let gpu = ComputeDevice::from_location(DeviceLocation::Cuda { gpu_id: 3 });
        assert_eq!(gpu, Some(ComputeDevice::Cuda(3)));
        assert_eq!(gpu.map(|d| d.to_string()).as_deref(), Some("cuda:3"));
        assert_eq!(
            ComputeDevice::from_location(DeviceLocation::Metal { gpu_id: 0 }),
            None
        );
    }

    #[test]
    fn cpu_opens_and_cuda_without_the_feature_is_a_typed_error() {
        assert!(ComputeDevice::Cpu.open().expect("cpu").is_cpu());
        if !ComputeDevice::CUDA_BUILT {
            match ComputeDevice::Cuda(0).open() {
                Err(PolicyError::Device { device, reason }) => {
                    assert_eq!(device, "cuda:0");
                    assert!(reason.contains("`cuda` feature"), "{reason}");
                }
                other => panic!("expected a device error, got {other:?}"),
            }
        }
    }
}
