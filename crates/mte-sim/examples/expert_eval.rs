//! Scripted expert on the Diffusion Policy test seeds: `cargo run --release -p mte-sim
//! --example expert_eval -- [FIRST_SEED] [N]`; `TRAVEL_STEP` and `PUSH_STEP` (px) set the
//! expert's step sizes (defaults 45 and 8; the demonstrations used 20 and 6); `REPLAN=1` makes
//! it plan afresh at every step (with `resume_pushes`), a controller whose action is a
//! function of the state.
#![allow(clippy::print_stdout, clippy::unwrap_used)]
use mte_sim::{Expert, ExpertConfig, PushT, ResetStream};
use rand::SeedableRng;

fn main() {
    let args: Vec<u64> = std::env::args()
        .skip(1)
        .map(|a| a.parse().unwrap())
        .collect();
    let first = args.first().copied().unwrap_or(100_000);
    let n = args.get(1).copied().unwrap_or(50);
    let mut env = PushT::default();
    let travel = std::env::var("TRAVEL_STEP").map_or(45.0, |v| v.parse().unwrap());
    let push = std::env::var("PUSH_STEP").map_or(8.0, |v| v.parse().unwrap());
    let replan = std::env::var("REPLAN").is_ok_and(|v| v == "1");
    let mut expert = Expert::new(ExpertConfig {
        travel_step: travel,
        push_step: push,
        resume_pushes: replan,
        ..ExpertConfig::default()
    })
    .unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let (mut succ, mut sum_max) = (0, 0.0);
    let t0 = std::time::Instant::now();
    for seed in first..first + n {
        env.reset(seed, ResetStream::Legacy).unwrap();
        expert.reset();
        let mut max_cov: f64 = env.coverage();
        let mut ok = false;
        let mut steps = 0;
        for _ in 0..300 {
            if replan {
                expert.reset();
            }
            let a = expert.act(&env, &mut rng).unwrap();
            let info = env.step(a).unwrap();
            steps += 1;
            max_cov = max_cov.max(info.coverage);
            if info.is_success {
                ok = true;
                break;
            }
        }
        succ += ok as usize;
        sum_max += max_cov;
        println!("seed {seed}: success {ok} steps {steps} max_cov {max_cov:.3}");
    }
    println!(
        "success {succ}/{n}, mean max coverage {:.3}, {:.1} s",
        sum_max / n as f64,
        t0.elapsed().as_secs_f64()
    );
}
