//! How much of the scripted expert's behaviour is hidden commitment: along its own episodes,
//! at every step, the targets it goes on to execute (the rest of the primitive it committed
//! to, then its next plans) against the targets a fresh expert would execute from the same
//! exact state (no memory of the plan in progress), with and without `resume_pushes`.
//!
//! `cargo run --release -p mte-sim --example expert_commitment -- [FIRST_SEED] [N] [ROWS]`
//! (defaults: 100000, 20 seeds, 15 rows: a Diffusion Policy chunk's executable rows). The
//! expert is the demonstrations' (`--travel-step 20 --push-step 6`). Prints, per variant,
//! the mean distance (px) between the two target sequences over the compared rows, the share
//! of steps where it exceeds 10 px, and the share where the very next target differs by more
//! than 10 px; and, at the steps inside a committed primitive, the share where the fresh
//! expert's first primitive ends more than 10 px from where the committed one ends (a
//! different decision, not only a different path to the same end).
#![allow(clippy::print_stdout, clippy::unwrap_used)]
use mte_sim::{Expert, ExpertConfig, PushT, ResetStream, Snapshot};
use rand::SeedableRng;

fn demo_config(resume_pushes: bool) -> ExpertConfig {
    ExpertConfig {
        travel_step: 20.0,
        push_step: 6.0,
        resume_pushes,
        ..ExpertConfig::default()
    }
}

/// The targets a fresh expert executes from `snap` for `rows` steps, and where its first
/// primitive ends.
fn fresh_targets(snap: &Snapshot, rows: usize, resume: bool) -> (Vec<[f64; 2]>, [f64; 2]) {
    let mut env = PushT::default();
    env.restore(snap).unwrap();
    let mut expert = Expert::new(demo_config(resume)).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut end = None;
    let targets = (0..rows)
        .map(|_| {
            let a = expert.act(&env, &mut rng).unwrap();
            end.get_or_insert_with(|| expert.planned().last().copied().unwrap_or(a));
            env.step(a).unwrap();
            a
        })
        .collect();
    (targets, end.unwrap())
}

#[derive(Default)]
struct Tally {
    steps: usize,
    dist_sum: f64,
    far: usize,
    first_far: usize,
    /// Steps inside a committed primitive, and those where the fresh primitive ends more
    /// than 10 px from the committed one's end.
    mid: usize,
    other_end: usize,
}

fn main() {
    let args: Vec<u64> = std::env::args()
        .skip(1)
        .map(|a| a.parse().unwrap())
        .collect();
    let first = args.first().copied().unwrap_or(100_000);
    let n = args.get(1).copied().unwrap_or(20);
    let rows = args.get(2).copied().unwrap_or(15) as usize;
    let t0 = std::time::Instant::now();
    let mut tallies = [Tally::default(), Tally::default()];
    for seed in first..first + n {
        let mut env = PushT::default();
        env.reset(seed, ResetStream::Legacy).unwrap();
        let mut expert = Expert::new(demo_config(false)).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
        let mut episode = Vec::new();
        for _ in 0..300 {
            // Where the committed primitive ends, when one is in progress.
            let committed_end = expert.planned().last().copied();
            let a = expert.act(&env, &mut rng).unwrap();
            episode.push((env.snapshot(), a, committed_end));
            if env.step(a).unwrap().is_success {
                break;
            }
        }
        for t in 0..episode.len() {
            let done: Vec<[f64; 2]> = episode[t..].iter().take(rows).map(|s| s.1).collect();
            for (tally, resume) in tallies.iter_mut().zip([false, true]) {
                let (fresh, fresh_end) = fresh_targets(&episode[t].0, done.len(), resume);
                if let Some(end) = episode[t].2 {
                    tally.mid += 1;
                    let d = (end[0] - fresh_end[0]).hypot(end[1] - fresh_end[1]);
                    tally.other_end += usize::from(d > 10.0);
                }
                let d: Vec<f64> = done
                    .iter()
                    .zip(&fresh)
                    .map(|(a, b)| (a[0] - b[0]).hypot(a[1] - b[1]))
                    .collect();
                let mean = d.iter().sum::<f64>() / d.len() as f64;
                tally.steps += 1;
                tally.dist_sum += mean;
                tally.far += usize::from(mean > 10.0);
                tally.first_far += usize::from(d[0] > 10.0);
            }
        }
    }
    for (tally, name) in tallies
        .iter()
        .zip(["fresh expert", "fresh expert, resume_pushes"])
    {
        let s = tally.steps as f64;
        println!(
            "{name}: {} steps of {n} episodes, mean distance over {rows} rows {:.1} px, \
             > 10 px at {:.1}% of steps, next target > 10 px at {:.1}%; of the {} steps inside \
             a committed primitive, the fresh primitive ends > 10 px from it at {:.1}%",
            tally.steps,
            tally.dist_sum / s,
            100.0 * tally.far as f64 / s,
            100.0 * tally.first_far as f64 / s,
            tally.mid,
            100.0 * tally.other_end as f64 / tally.mid.max(1) as f64,
        );
    }
    println!("{:.0} s", t0.elapsed().as_secs_f64());
}
