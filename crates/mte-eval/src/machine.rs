//! The machine an experiment ran on, recorded in every run's manifest.
//!
//! Why it matters: results are bit-identical only on one CPU model. The neural-network
//! kernels (candle's matrix products through the `gemm` crate, which sizes its blocks from
//! the CPU's caches and picks its microkernel from the CPU's extensions, and glibc's
//! transcendental functions, which have per-extension variants) round differently on
//! different CPUs, so a policy's chunks, and through the closed loop every later state,
//! differ in their last bits from one CPU to another. On one CPU they do not depend on the
//! thread count or the worker count (`tests/reproducible.rs` in `mte-cli`). A report names
//! the machines its records came from so that a reader can tell which figures to compare
//! bit for bit.

use serde::{Deserialize, Serialize};

/// What identifies a machine's floating-point behaviour.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Machine {
    /// CPU model as the OS reports it (`/proc/cpuinfo`'s `model name` on Linux), or
    /// `unknown`.
    pub cpu_model: String,
    /// Vector extensions the running CPU has that the kernels can use (`sse4.2`, `avx`,
    /// `avx2`, `fma`, `avx512f`, ...; `neon` on aarch64), in a fixed order.
    pub vector_extensions: Vec<String>,
    /// Logical CPUs available to the process.
    pub logical_cpus: usize,
    /// `std::env::consts::ARCH` and `OS`, as `arch-os`.
    pub target: String,
    /// Where the policies ran when not on this CPU (`cuda:0`); absent for CPU runs and in
    /// manifests written before it existed. GPU kernels round differently again, so records
    /// of one accelerator compare bit for bit only with records of the same one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub accelerator: Option<String>,
}

impl Machine {
    /// The machine this process runs on.
    pub fn detect() -> Self {
        Self {
            cpu_model: cpu_model().unwrap_or_else(|| "unknown".into()),
            vector_extensions: vector_extensions().into_iter().map(String::from).collect(),
            logical_cpus: std::thread::available_parallelism().map_or(1, |n| n.get()),
            target: format!("{}-{}", std::env::consts::ARCH, std::env::consts::OS),
            accelerator: None,
        }
    }

    /// This machine with its policies on `device`: the accelerator recorded where it is not
    /// the CPU.
    pub fn with_policies_on(self, device: mte_policy::ComputeDevice) -> Self {
        let accelerator = match device {
            mte_policy::ComputeDevice::Cpu => None,
            gpu => Some(gpu.to_string()),
        };
        Self {
            accelerator,
            ..self
        }
    }

    /// One line: `AMD EPYC (x86_64-linux, 2 logical cpus; avx avx2 fma ...)`, followed by
    /// `, policies on cuda:0` where they ran on an accelerator.
    pub fn summary(&self) -> String {
        format!(
            "{} ({}, {} logical cpus; {}){}",
            self.cpu_model,
            self.target,
            self.logical_cpus,
            if self.vector_extensions.is_empty() {
                "no vector extensions detected".to_string()
            } else {
                self.vector_extensions.join(" ")
            },
            self.accelerator
                .as_ref()
                .map_or(String::new(), |a| format!(", policies on {a}"))
        )
    }
}

/// `model name` (x86) or `Hardware`/`cpu model` (other Linux targets) of `/proc/cpuinfo`.
fn cpu_model() -> Option<String> {
    let text = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    parse_cpu_model(&text)
}

/// The first model line of a `/proc/cpuinfo` text.
fn parse_cpu_model(text: &str) -> Option<String> {
    text.lines().find_map(|line| {
        let (key, value) = line.split_once(':')?;
        let key = key.trim();
        let value = value.trim();
        (["model name", "Hardware", "cpu model"].contains(&key) && !value.is_empty())
            .then(|| value.to_string())
    })
}

/// Runtime-detected vector extensions, in a fixed order.
#[cfg(any(target_arch = "x86", target_arch = "x86_64"))]
fn vector_extensions() -> Vec<&'static str> {
    let mut v = Vec::new();
    macro_rules! check {
        ($($f:tt),*) => {$(
            if std::arch::is_x86_feature_detected!($f) {
                v.push($f);
            }
        )*};
    }
    check!(
        "sse4.2", "avx", "avx2", "fma", "f16c", "avx512f", "avx512bw", "avx512vl", "avx512dq"
    );
    v
}

/// Runtime-detected vector extensions, in a fixed order.
#[cfg(target_arch = "aarch64")]
fn vector_extensions() -> Vec<&'static str> {
    let mut v = Vec::new();
    if std::arch::is_aarch64_feature_detected!("neon") {
        v.push("neon");
    }
    if std::arch::is_aarch64_feature_detected!("sve") {
        v.push("sve");
    }
    v
}

/// Runtime-detected vector extensions (none known on this architecture).
#[cfg(not(any(target_arch = "x86", target_arch = "x86_64", target_arch = "aarch64")))]
fn vector_extensions() -> Vec<&'static str> {
    Vec::new()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_model_line_is_read_from_cpuinfo() {
        let text = "processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC 9R14\nflags\t: fpu\n\
                    processor\t: 1\nmodel name\t: AMD EPYC 9R14\n";
        assert_eq!(parse_cpu_model(text).as_deref(), Some("AMD EPYC 9R14"));
        assert_eq!(parse_cpu_model("processor : 0\nmodel name :   \n"), None);
        assert_eq!(parse_cpu_model(""), None);
    }

    #[test]
    fn the_detected_machine_is_consistent_with_the_compile_target() {
        let m = Machine::detect();
        assert!(m.logical_cpus >= 1);
        assert!(m.target.starts_with(std::env::consts::ARCH), "{}", m.target);
        // Extensions the binary was compiled to require are always detected at run time.
        if cfg!(target_feature = "sse4.2") {
            assert!(m.vector_extensions.iter().any(|e| e == "sse4.2"), "{m:?}");
        }
        // AVX-512 implies AVX2 on every CPU that has it.
        if m.vector_extensions.iter().any(|e| e == "avx512f") {
            assert!(m.vector_extensions.iter().any(|e| e == "avx2"), "{m:?}");
        }
        let s = m.summary();
        assert!(s.contains(&m.cpu_model) && s.contains(&m.target), "{s}");
        let back: Machine =
            serde_json::from_str(&serde_json::to_string(&m).expect("json")).expect("round trip");
        assert_eq!(back, m);
        assert!(
            !serde_json::to_string(&m)
                .expect("json")
                .contains("accelerator")
        );
    }

    #[test]
    fn an_accelerator_is_recorded_and_older_manifests_read_without_one() {
        let cpu = Machine::detect().with_policies_on(mte_policy::ComputeDevice::Cpu);
        assert_eq!(cpu, Machine::detect());
        let gpu = Machine::detect().with_policies_on(mte_policy::ComputeDevice::Cuda(0));
        assert_eq!(gpu.accelerator.as_deref(), Some("cuda:0"));
        assert!(
            gpu.summary().ends_with(", policies on cuda:0"),
            "{}",
            gpu.summary()
        );
        let json = serde_json::to_string(&gpu).expect("json");
        assert_eq!(serde_json::from_str::<Machine>(&json).expect("back"), gpu);
        let old =
            r#"{"cpu_model":"X","vector_extensions":[],"logical_cpus":2,"target":"x86_64-linux"}"#;
        let m: Machine = serde_json::from_str(old).expect("an older manifest's machine");
        assert_eq!(m.accelerator, None);
        // A CPU run and a GPU run on one host are two machines (merge_machines keeps both).
        assert_ne!(Machine::detect(), gpu);
    }
}
