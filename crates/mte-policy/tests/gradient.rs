//! The observation gradient of the training loss (what PGD needs) against central finite
//! differences on a tiny network, in float64 so the comparison is not limited by rounding.

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use mte_policy::config::{DiffusionConfig, ObsKind};
use mte_policy::{DiffusionPolicy, ObsBatch, Stats, StatsMap};

mod common;

fn tiny() -> (DiffusionPolicy, VarMap) {
    let c = DiffusionConfig::cpu(ObsKind::Keypoints)
        .with_overrides(&serde_json::json!({"down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8}))
        .expect("valid");
    let mut stats = StatsMap::new();
    let mm = |lo: f32, hi: f32, n: usize| Stats {
        min: vec![lo; n],
        max: vec![hi; n],
        ..Default::default()
    };
    stats.insert("observation.state".into(), mm(0.0, 512.0, 2));
    stats.insert("observation.environment_state".into(), mm(0.0, 512.0, 16));
    stats.insert("action".into(), mm(0.0, 512.0, 2));
    let vm = VarMap::new();
    let vb = mte_policy::init::seeded_var_builder(&vm, 1, DType::F64, &Device::Cpu);
    (DiffusionPolicy::new(c, stats, vb).expect("policy"), vm)
}

#[test]
fn observation_gradient_matches_finite_differences() {
    let (p, _vm) = tiny();
    let dev = Device::Cpu;
    let state = common::randn(1, &[1, 2, 2], 0.5, DType::F64);
    let env = common::randn(2, &[1, 2, 16], 0.5, DType::F64);
    let x0 = common::randn(3, &[3, 16, 2], 0.5, DType::F64);
    let eps = common::randn(4, &[3, 16, 2], 1.0, DType::F64);
    let ts = [3usize, 40, 97];
    let obs = ObsBatch {
        state: state.clone(),
        env: Some(env.clone()),
        image: None,
    };
    let (loss, g) = p.observation_gradient(&obs, &x0, &eps, &ts).expect("grad");
    assert!(loss.is_finite() && loss > 0.0);
    let loss_at = |s: &Tensor, e: &Tensor| -> f64 {
        let o = ObsBatch {
            state: s.clone(),
            env: Some(e.clone()),
            image: None,
        };
        let cond = p
            .global_cond(&o)
            .expect("cond")
            .repeat((3, 1))
            .expect("rep");
        p.loss(&cond, &x0, &eps, &ts, None)
            .expect("loss")
            .to_scalar::<f64>()
            .expect("s")
    };
    let h = 1e-5;
    let gs: Vec<f64> = g.state.flatten_all().expect("f").to_vec1().expect("v");
    let ge: Vec<f64> = g
        .env
        .expect("env grad")
        .flatten_all()
        .expect("f")
        .to_vec1()
        .expect("v");
    let sv: Vec<f64> = state.flatten_all().expect("f").to_vec1().expect("v");
    let ev: Vec<f64> = env.flatten_all().expect("f").to_vec1().expect("v");
    let mut checked = 0;
    for (which, base, grad) in [(0, &sv, &gs), (1, &ev, &ge)] {
        for i in (0..base.len()).step_by(3) {
            let bump = |d: f64| {
                let mut v = base.clone();
                v[i] += d;
                let t = Tensor::from_vec(v, if which == 0 { (1, 2, 2) } else { (1, 2, 16) }, &dev)
                    .expect("t");
                if which == 0 {
                    loss_at(&t, &env)
                } else {
                    loss_at(&state, &t)
                }
            };
            let fd = (bump(h) - bump(-h)) / (2.0 * h);
            let an = grad[i];
            assert!(
                (fd - an).abs() <= 1e-6 + 1e-4 * fd.abs(),
                "input {which} coord {i}: fd {fd} vs autodiff {an}"
            );
            checked += 1;
        }
    }
    assert!(checked >= 8);
    // Not vacuous: the gradient is not zero.
    assert!(gs.iter().chain(&ge).any(|v| v.abs() > 1e-8));
}
