//! ACT against LeRobot 0.4.4: a tiny ACT randomly initialised and saved by the real lerobot
//! (`tools/reference/lerobot_act_reference.py`, fixture `fixtures/act_tiny`, 56 kB) gives the
//! same actions in mte, at inference (latent zero) and in a training pass through the CVAE
//! encoder with padded actions and fixed reparameterisation noise.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use mte_policy::act::model::{ActInputs, VaeInput};
use mte_policy::act::{ActConfig, ActNet};

mod common;
use common::max_abs_diff;

fn fixture() -> (ActNet, HashMap<String, Tensor>) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/act_tiny");
    let config = ActConfig::from_file(&dir.join("config.json")).expect("config");
    let weights = candle_core::safetensors::load(dir.join("model.safetensors"), &Device::Cpu)
        .expect("weights");
    let io = candle_core::safetensors::load(dir.join("io.safetensors"), &Device::Cpu).expect("io");
    let vb = VarBuilder::from_tensors(weights, DType::F32, &Device::Cpu).pp("model");
    (ActNet::new(config, vb).expect("net"), io)
}

fn inputs(io: &HashMap<String, Tensor>) -> ActInputs<'_> {
    ActInputs {
        state: Some(&io["state"]),
        env: Some(&io["env"]),
        images: &[],
        features: &[],
    }
}

// Tolerance: float32 throughout, the same operations in a different summation order (candle's
// gemm against PyTorch's) through 2 encoder and 1 decoder layers of width 16, outputs of
// order 1: the gaps measured are a few 1e-7; 1e-5 leaves room for other CPUs' kernels while a
// wrong layer order, norm placement or head split moves outputs by more than 1e-2.
const TOL: f32 = 1e-5;

#[test]
fn inference_matches_lerobot() {
    let (net, io) = fixture();
    let out = net.forward(&inputs(&io), None, None).expect("forward");
    let gap = max_abs_diff(&out.actions, &io["actions"]);
    assert!(gap < TOL, "inference actions differ by {gap}");
    assert!(out.latent.is_none());
}

#[test]
fn training_pass_through_the_cvae_matches_lerobot() {
    let (net, io) = fixture();
    let vae = VaeInput {
        actions: &io["target"],
        is_pad: &io["is_pad"],
        eps: &io["eps"],
    };
    let out = net
        .forward(&inputs(&io), Some(&vae), None)
        .expect("forward");
    let (mu, ls) = out.latent.as_ref().expect("latent");
    for (name, got, want) in [
        ("mu", mu, &io["mu"]),
        ("log_sigma_x2", ls, &io["log_sigma_x2"]),
        ("actions", &out.actions, &io["train_actions"]),
    ] {
        let gap = max_abs_diff(got, want);
        assert!(gap < TOL, "{name} differs by {gap}");
    }
    // The guard: without the padding mask the CVAE sees the padded actions and mu moves.
    let unmasked = VaeInput {
        is_pad: &io["is_pad"].zeros_like().expect("zeros"),
        ..vae
    };
    let out2 = net
        .forward(&inputs(&io), Some(&unmasked), None)
        .expect("forward");
    let moved = max_abs_diff(
        out2.latent
            .as_ref()
            .expect("latent")
            .0
            .narrow(0, 1, 1)
            .as_ref()
            .expect("row"),
        io["mu"].narrow(0, 1, 1).as_ref().expect("row"),
    );
    assert!(moved > 1e-4, "the padding mask had no effect ({moved})");
}
