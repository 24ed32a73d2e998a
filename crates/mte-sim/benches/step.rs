//! PushT step throughput, on the workload of `shared/reference/peer-bench/bench_pusht.py`:
//! 300-step episodes, seeds incremented per episode, pre-drawn uniform random actions in
//! [0, 512]^2 (drawing them is not timed). A second workload pushes the block every step
//! (actions at the block's centre of gravity plus noise), where the contact solver runs.
//!
//! `cargo bench -p mte-sim --bench step` — divan reports time per 300-step episode and
//! items/s = steps/s.

use divan::counter::ItemsCount;
use mte_sim::render::Renderer;
use mte_sim::{PhysicsConfig, PushT, ResetStream};
use rand::{Rng, SeedableRng};

const EP_LEN: usize = 300;

fn main() {
    divan::main();
}

fn uniform_actions(seed: u64) -> Vec<[f64; 2]> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..EP_LEN)
        .map(|_| [rng.random_range(0.0..512.0), rng.random_range(0.0..512.0)])
        .collect()
}

#[divan::bench(args = [true, false])]
fn state_uniform_actions(bencher: divan::Bencher, skip_free_flight: bool) {
    let config = PhysicsConfig {
        skip_free_flight,
        ..PhysicsConfig::default()
    };
    let mut env = PushT::new(config);
    let actions: Vec<Vec<[f64; 2]>> = (0..16).map(uniform_actions).collect();
    let mut ep = 0u64;
    bencher.counter(ItemsCount::new(EP_LEN)).bench_local(|| {
        ep += 1;
        env.reset(ep, ResetStream::Pcg64).ok();
        let acts = &actions[(ep % 16) as usize];
        let mut cov = 0.0;
        for a in acts {
            if let Ok(info) = env.step(*a) {
                cov += info.coverage;
            }
        }
        cov
    });
}

#[divan::bench]
fn state_pushing(bencher: divan::Bencher) {
    let mut env = PushT::default();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut ep = 0u64;
    bencher.counter(ItemsCount::new(EP_LEN)).bench_local(|| {
        ep += 1;
        env.reset(ep, ResetStream::Pcg64).ok();
        let mut contacts = 0;
        for _ in 0..EP_LEN {
            let c = env.block_pose().cog();
            let a = [
                c[0] + rng.random_range(-40.0..40.0),
                c[1] + rng.random_range(-40.0..40.0),
            ];
            if let Ok(info) = env.step(a) {
                contacts += info.n_contacts;
            }
        }
        contacts
    });
}

/// gym-pusht's `pixels_agent_pos` observation: each step also renders the 96 x 96 frame.
#[divan::bench]
fn pixels_96_uniform_actions(bencher: divan::Bencher) {
    let mut env = PushT::default();
    let mut renderer = Renderer::new(env.goal());
    let mut frame = vec![0u8; 96 * 96 * 3];
    let actions: Vec<Vec<[f64; 2]>> = (0..16).map(uniform_actions).collect();
    let mut ep = 0u64;
    bencher.counter(ItemsCount::new(EP_LEN)).bench_local(|| {
        ep += 1;
        env.reset(ep, ResetStream::Pcg64).ok();
        let mut sum = 0u64;
        for a in &actions[(ep % 16) as usize] {
            if env.step(*a).is_ok() {
                let (scene, contacts) = (env.scene(), env.contact_segments());
                if renderer
                    .observation_with_contacts_into(&scene, contacts, 96, 96, &mut frame)
                    .is_ok()
                {
                    sum += u64::from(frame[96 * 48 * 3 + 48 * 3]);
                }
            }
        }
        sum
    });
}

/// One tick of `n` environments: `VecEnv` (the pool from `n >= PARALLEL_MIN_ENVS`) against a
/// plain loop on one thread, uniform random actions, a reset every 300 ticks. 300 samples of 3
/// ticks cover three whole episodes: a tick costs several times more once the blocks are in
/// contact than in the first 100 ticks (divan's default sample count), where a pool's fixed
/// cost per tick weighs most.
#[divan::bench(args = [2, 16], sample_count = 300, sample_size = 3)]
fn vec_env_tick(bencher: divan::Bencher, n: usize) {
    let mut v = mte_sim::VecEnv::new(n, PhysicsConfig::default());
    let acts: Vec<Vec<[f64; 2]>> = (0..n as u64).map(uniform_actions).collect();
    let mut t = 0usize;
    bencher.counter(ItemsCount::new(n)).bench_local(|| {
        if t.is_multiple_of(EP_LEN) {
            let seeds: Vec<u64> = (0..n as u64).map(|i| i + t as u64).collect();
            v.reset(&seeds, ResetStream::Pcg64).ok();
        }
        let a: Vec<[f64; 2]> = acts.iter().map(|e| e[t % EP_LEN]).collect();
        t += 1;
        v.step(&a).map(|i| i.len()).unwrap_or(0)
    });
}

#[divan::bench(args = [2, 16], sample_count = 300, sample_size = 3)]
fn plain_loop_tick(bencher: divan::Bencher, n: usize) {
    let mut envs: Vec<PushT> = (0..n).map(|_| PushT::default()).collect();
    let acts: Vec<Vec<[f64; 2]>> = (0..n as u64).map(uniform_actions).collect();
    let mut t = 0usize;
    bencher.counter(ItemsCount::new(n)).bench_local(|| {
        if t.is_multiple_of(EP_LEN) {
            for (i, e) in envs.iter_mut().enumerate() {
                e.reset(i as u64 + t as u64, ResetStream::Pcg64).ok();
            }
        }
        let mut steps = 0;
        for (e, a) in envs.iter_mut().zip(&acts) {
            steps += usize::from(e.step(a[t % EP_LEN]).is_ok());
        }
        t += 1;
        steps
    });
}
