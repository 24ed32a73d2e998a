//! The model-independent pieces of a training loop, shared by Diffusion Policy (and its
//! encoder pre-training) and ACT: the per-step random stream, the checkpoint schedule,
//! global gradient-norm clipping, the warm-up + cosine learning rate, the exponential moving
//! average of the weights and the loss trace a run reports from.

use std::collections::{HashMap, VecDeque};

use candle_core::backprop::GradStore;
use candle_core::{Tensor, Var};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::checkpoint::ck;
use crate::error::PolicyError;

/// The random stream of optimisation step `step` of a run seeded with `seed`: keyed by the
/// step, so a resumed run draws exactly what an uninterrupted one would have.
pub(crate) fn step_rng(seed: u64, step: usize) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed ^ (step as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
}

/// Whether a run of `total` steps writes a checkpoint after step `step` (1-based: the number
/// of steps done): every `every` steps (0: never), and always after the last.
pub(crate) fn checkpoint_due(step: usize, every: usize, total: usize) -> bool {
    step == total || (every > 0 && step.is_multiple_of(every))
}

/// Global gradient-norm clipping to `max`.
pub(crate) fn clip_gradients(
    grads: &mut GradStore,
    vars: &[(String, Var)],
    max: f64,
) -> Result<(), PolicyError> {
    let mut sq = 0f64;
    for (_, v) in vars {
        if let Some(g) = grads.get(v.as_tensor()) {
            sq += f64::from(g.sqr()?.sum_all()?.to_scalar::<f32>()?);
        }
    }
    let norm = sq.sqrt();
    if norm > max {
        let scale = max / (norm + 1e-6);
        for (_, v) in vars {
            if let Some(g) = grads.get(v.as_tensor()) {
                let g = (g * scale)?.detach();
                grads.insert(v.as_tensor(), g);
            }
        }
    }
    Ok(())
}

/// Learning rate at `step` (0-based): linear warm-up to `lr` over `warmup` steps, then cosine
/// decay to 0 at `total` (Diffusion Policy's schedule).
pub fn learning_rate(lr: f64, warmup: usize, total: usize, step: usize) -> f64 {
    if step < warmup {
        return lr * (step + 1) as f64 / warmup as f64;
    }
    let progress = (step - warmup) as f64 / (total.saturating_sub(warmup)).max(1) as f64;
    lr * 0.5 * (1.0 + (std::f64::consts::PI * progress.min(1.0)).cos())
}

/// The EMA decay after optimisation step `step` (0-based) under the ceiling `max`: the ramp
/// `min(max, (1 + step) / (10 + step))`, so early averages forget the initialisation fast.
pub(crate) fn ema_decay(max: f64, step: usize) -> f64 {
    max.min((1.0 + step as f64) / (10.0 + step as f64))
}

/// Detached copies of `vars`' values by name: an average's starting point (a plain clone would
/// share the variables' storage, which the optimiser overwrites in place).
pub(crate) fn weight_copies(
    vars: &[(String, Var)],
) -> Result<HashMap<String, Tensor>, PolicyError> {
    vars.iter()
        .map(|(k, v)| Ok((k.clone(), v.as_tensor().detach().copy()?)))
        .collect()
}

/// `ema <- decay ema + (1 - decay) weights` for the named variables `vars` (names that `ema`
/// lacks are skipped).
pub(crate) fn ema_update(
    ema: &mut HashMap<String, Tensor>,
    vars: &[(String, Var)],
    decay: f64,
) -> Result<(), PolicyError> {
    for (k, v) in vars {
        if let Some(prev) = ema.get_mut(k) {
            // detach: otherwise every EMA tensor keeps the previous one alive through the
            // autograd graph, and memory grows by a model copy per step.
            *prev = ((&*prev * decay)? + (v.as_tensor().detach() * (1.0 - decay))?)?.detach();
        }
    }
    Ok(())
}

/// AdamW's hyper-parameters (candle-nn's [`candle_nn::ParamsAdamW`], re-exported so callers
/// need not name the crate).
pub(crate) use candle_nn::ParamsAdamW;

/// The file beside a run's weights that holds its optimiser's state, so that a resumed run
/// continues exactly as an uninterrupted one (bit for bit on the same machine).
pub(crate) const OPTIMIZER_STATE: &str = "optimizer_state.safetensors";

/// AdamW (decoupled weight decay) whose moment estimates can be saved and restored.
///
/// The arithmetic is candle-nn 0.9's `AdamW`, operation for operation (a test checks the two
/// agree bit for bit), so runs made before it are reproduced; unlike candle's, its state is
/// readable ([`AdamW::state`]) and restorable ([`AdamW::restore`]).
pub(crate) struct AdamW {
    params: ParamsAdamW,
    /// Steps taken (the bias corrections' exponent).
    step_t: usize,
    slots: Vec<Slot>,
}

/// One optimised variable and its first and second moment estimates.
struct Slot {
    name: String,
    var: Var,
    m: Var,
    v: Var,
}

impl AdamW {
    /// Zero moments for every variable of `vars` (named; the names key the saved state).
    pub(crate) fn new(vars: &[(String, Var)], params: ParamsAdamW) -> Result<Self, PolicyError> {
        let slots = vars
            .iter()
            .map(|(name, var)| {
                let zeros = || Var::zeros(var.shape(), var.dtype(), var.device());
                Ok(Slot {
                    name: name.clone(),
                    var: var.clone(),
                    m: zeros()?,
                    v: zeros()?,
                })
            })
            .collect::<Result<_, PolicyError>>()?;
        Ok(Self {
            params,
            step_t: 0,
            slots,
        })
    }

    pub(crate) fn set_learning_rate(&mut self, lr: f64) {
        self.params.lr = lr;
    }

    /// One step on the gradients in `grads` (a variable without a gradient is left alone).
    pub(crate) fn step(&mut self, grads: &GradStore) -> Result<(), PolicyError> {
        self.step_t += 1;
        let p = &self.params;
        let (b1, b2) = (p.beta1, p.beta2);
        let scale_m = 1.0 / (1.0 - b1.powi(self.step_t as i32));
        let scale_v = 1.0 / (1.0 - b2.powi(self.step_t as i32));
        for s in &self.slots {
            let Some(g) = grads.get(s.var.as_tensor()) else {
                continue;
            };
            let m = ((s.m.as_tensor() * b1)? + (g * (1.0 - b1))?)?;
            let v = ((s.v.as_tensor() * b2)? + (g.sqr()? * (1.0 - b2))?)?;
            let decayed = (s.var.as_tensor() * (1.0 - p.lr * p.weight_decay))?;
            let update = ((&m * scale_m)? / ((&v * scale_v)?.sqrt()? + p.eps)?)?;
            let theta = (decayed - (update * p.lr)?)?;
            s.m.set(&m)?;
            s.v.set(&v)?;
            s.var.set(&theta)?;
        }
        Ok(())
    }

    /// The state as named tensors under `prefix`: `{prefix}step` (the step count, `[1]`,
    /// i64), `{prefix}m.{name}` and `{prefix}v.{name}` per variable.
    pub(crate) fn state(&self, prefix: &str) -> Result<Vec<(String, Tensor)>, PolicyError> {
        let dev = self.slots.first().map(|s| s.var.device().clone());
        let step = Tensor::new(
            &[self.step_t as i64],
            &dev.unwrap_or(candle_core::Device::Cpu),
        )?;
        let mut out = vec![(format!("{prefix}step"), step)];
        for s in &self.slots {
            out.push((format!("{prefix}m.{}", s.name), s.m.as_tensor().clone()));
            out.push((format!("{prefix}v.{}", s.name), s.v.as_tensor().clone()));
        }
        Ok(out)
    }

    /// Restores what [`AdamW::state`] wrote under `prefix` from `saved` (read from `path`); a
    /// missing entry or a shape that differs from the variable's is an error naming it.
    pub(crate) fn restore(
        &mut self,
        prefix: &str,
        saved: &HashMap<String, Tensor>,
        path: &std::path::Path,
    ) -> Result<(), PolicyError> {
        let missing = |key: &str| {
            ck(
                path,
                format!(
                    "no `{key}` in the optimiser state (was the run started with other \
                     trainable variables? delete the file to resume with fresh moments)"
                ),
            )
        };
        let step_key = format!("{prefix}step");
        self.step_t = stored_count(saved, &step_key, path)?.ok_or_else(|| missing(&step_key))?;
        for s in &self.slots {
            for (moment, var) in [("m", &s.m), ("v", &s.v)] {
                let key = format!("{prefix}{moment}.{}", s.name);
                let t = saved.get(&key).ok_or_else(|| missing(&key))?;
                if t.dims() != var.dims() {
                    let (saved, wanted) = (t.dims(), var.dims());
                    return Err(ck(
                        path,
                        format!("`{key}` has shape {saved:?}, the variable {wanted:?}"),
                    ));
                }
                var.set(&t.to_dtype(var.dtype())?.to_device(var.device())?)?;
            }
        }
        Ok(())
    }
}

/// Writes the optimisers' states, each under its group prefix, with the run's `step`, to
/// `dir/`[`OPTIMIZER_STATE`].
pub(crate) fn save_optimizers(
    dir: &std::path::Path,
    step: usize,
    groups: &[(&str, &AdamW)],
) -> Result<(), PolicyError> {
    std::fs::create_dir_all(dir).map_err(|source| PolicyError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut all: HashMap<String, Tensor> = HashMap::new();
    all.insert(
        "run.step".into(),
        Tensor::new(&[step as i64], &candle_core::Device::Cpu)?,
    );
    for (prefix, opt) in groups {
        for (k, t) in opt.state(prefix)? {
            all.insert(k, t.to_device(&candle_core::Device::Cpu)?);
        }
    }
    candle_core::safetensors::save(&all, dir.join(OPTIMIZER_STATE))?;
    Ok(())
}

/// Restores the optimisers from `dir/`[`OPTIMIZER_STATE`] if the file exists (runs saved
/// before it existed resume with fresh moments); a file written at a step other than the
/// run's `step` is an error (it would pair moments with the wrong weights).
pub(crate) fn restore_optimizers(
    dir: &std::path::Path,
    step: usize,
    groups: &mut [(&str, &mut AdamW)],
) -> Result<(), PolicyError> {
    let path = dir.join(OPTIMIZER_STATE);
    if !path.exists() {
        return Ok(());
    }
    let saved = candle_core::safetensors::load(&path, &candle_core::Device::Cpu)?;
    let at = stored_count(&saved, "run.step", &path)?;
    if at != Some(step) {
        let at = at.map_or_else(|| "unknown".to_string(), |s| s.to_string());
        return Err(ck(
            &path,
            format!(
                "optimiser state of step {at}, the run's weights are of step {step}; delete it to resume with fresh moments"
            ),
        ));
    }
    for (prefix, opt) in groups.iter_mut() {
        opt.restore(prefix, &saved, &path)?;
    }
    Ok(())
}

/// The count (a step) stored under `key` in an optimiser state, `None` when absent; anything
/// but one value ≥ 0 is an error naming what is there.
fn stored_count(
    saved: &HashMap<String, Tensor>,
    key: &str,
    path: &std::path::Path,
) -> Result<Option<usize>, PolicyError> {
    let Some(t) = saved.get(key) else {
        return Ok(None);
    };
    match t.flatten_all()?.to_vec1::<i64>()?.as_slice() {
        [n] if *n >= 0 => Ok(Some(*n as usize)),
        other => Err(ck(
            path,
            format!("`{key}` holds {other:?}, expected one step count ≥ 0"),
        )),
    }
}

/// The losses of a run: the first 50 and the last 100 steps.
#[derive(Debug, Default)]
pub(crate) struct LossTrace {
    first: Vec<f32>,
    recent: VecDeque<f32>,
}

impl LossTrace {
    /// Records one step's loss.
    pub(crate) fn push(&mut self, l: f32) {
        if self.first.len() < 50 {
            self.first.push(l);
        }
        self.recent.push_back(l);
        if self.recent.len() > 100 {
            self.recent.pop_front();
        }
    }

    /// The first (up to) 50 losses.
    pub(crate) fn first(&self) -> &[f32] {
        &self.first
    }

    /// The last (up to) 100 losses.
    pub(crate) fn recent(&mut self) -> &[f32] {
        self.recent.make_contiguous()
    }

    /// The mean of the last (up to) 100 losses; `None` when no step was recorded (a run
    /// resumed at its last step).
    pub(crate) fn recent_mean(&self) -> Option<f32> {
        let n = self.recent.len();
        (n > 0).then(|| self.recent.iter().sum::<f32>() / n as f32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    #[test]
    fn step_streams_are_keyed_by_seed_and_step() {
        let draw = |seed, step| step_rng(seed, step).random::<u64>();
        assert_eq!(draw(7, 3), draw(7, 3));
        assert_ne!(draw(7, 3), draw(7, 4));
        assert_ne!(draw(7, 3), draw(8, 3));
    }

    #[test]
    fn checkpoints_fall_on_the_period_and_the_last_step() {
        let due: Vec<usize> = (1..=10).filter(|&s| checkpoint_due(s, 4, 10)).collect();
        assert_eq!(due, vec![4, 8, 10]);
        let last_only: Vec<usize> = (1..=5).filter(|&s| checkpoint_due(s, 0, 5)).collect();
        assert_eq!(last_only, vec![5]);
    }

    #[test]
    fn the_trace_keeps_the_first_50_and_the_last_100() {
        let mut t = LossTrace::default();
        assert_eq!(t.recent_mean(), None);
        for i in 0..300 {
            t.push(i as f32);
        }
        assert_eq!(t.first(), (0..50).map(|i| i as f32).collect::<Vec<_>>());
        assert_eq!(t.recent(), (200..300).map(|i| i as f32).collect::<Vec<_>>());
        assert_eq!(t.recent_mean(), Some(249.5));
    }

    #[test]
    fn the_learning_rate_warms_up_linearly_then_decays_to_zero() {
        let lr = |s| learning_rate(1.0, 10, 110, s);
        assert!((lr(0) - 0.1).abs() < 1e-12 && (lr(9) - 1.0).abs() < 1e-12);
        assert!((lr(10) - 1.0).abs() < 1e-12, "the peak right after warm-up");
        assert!((lr(60) - 0.5).abs() < 1e-12, "half way down at mid-decay");
        assert!(
            lr(110).abs() < 1e-12 && lr(500).abs() < 1e-12,
            "zero at and past the end"
        );
        assert!((1..110).all(|s| lr(s) <= lr(s - 1) + 1e-12 || s < 10));
    }

    #[test]
    fn the_ema_ramps_its_decay_and_averages_the_named_weights() -> Result<(), PolicyError> {
        assert!((ema_decay(0.999, 0) - 0.1).abs() < 1e-12);
        assert_eq!(ema_decay(0.999, 1_000_000), 0.999);
        let dev = candle_core::Device::Cpu;
        let w = Var::from_vec(vec![4f32, 8.0], 2, &dev)?;
        let mut ema: HashMap<String, Tensor> =
            [("w".to_string(), Tensor::from_vec(vec![0f32, 0.0], 2, &dev)?)].into();
        let vars = vec![
            ("w".to_string(), w),
            ("absent".to_string(), Var::from_vec(vec![1f32], 1, &dev)?),
        ];
        ema_update(&mut ema, &vars, 0.75)?;
        assert_eq!(ema["w"].to_vec1::<f32>()?, vec![1.0, 2.0]);
        assert_eq!(ema.len(), 1, "a variable the average lacks is not added");
        Ok(())
    }

    /// Two copies of the same weights, one under candle-nn's AdamW and one under ours, the
    /// same loss for three steps: the weights agree bit for bit; a save and restore in the
    /// middle changes nothing; a missing moment is a typed error.
    #[test]
    fn adamw_matches_candles_bit_for_bit_and_restores_exactly() -> Result<(), PolicyError> {
        use candle_nn::Optimizer as _;
        let dev = candle_core::Device::Cpu;
        let init: Vec<f32> = (0..12).map(|i| (i as f32 * 0.37).sin()).collect();
        let var = || Var::from_vec(init.clone(), (3, 4), &dev);
        let target = Tensor::from_vec((0..12).map(|i| i as f32 / 7.0).collect(), (3, 4), &dev)?;
        let loss = |w: &Var| -> Result<Tensor, PolicyError> {
            Ok((w.as_tensor() - &target)?.sqr()?.sum_all()?)
        };
        let params = ParamsAdamW {
            lr: 0.05,
            weight_decay: 0.1,
            ..ParamsAdamW::default()
        };
        let (theirs_w, ours_w, resumed_w) = (var()?, var()?, var()?);
        let mut theirs = candle_nn::AdamW::new(vec![theirs_w.clone()], params.clone())?;
        let mut ours = AdamW::new(&[("w".to_string(), ours_w.clone())], params.clone())?;
        let mut resumed = AdamW::new(&[("w".to_string(), resumed_w.clone())], params.clone())?;
        for step in 0..3 {
            theirs.step(&loss(&theirs_w)?.backward()?)?;
            ours.step(&loss(&ours_w)?.backward()?)?;
            if step == 1 {
                // What a resume does: fresh weights and optimiser, then the saved state.
                let saved: HashMap<String, Tensor> = ours.state("g.")?.into_iter().collect();
                resumed_w.set(ours_w.as_tensor())?;
                resumed = AdamW::new(&[("w".to_string(), resumed_w.clone())], params.clone())?;
                resumed.restore("g.", &saved, std::path::Path::new("mem"))?;
                assert_eq!(resumed.step_t, 2);
            } else if step == 2 {
                resumed.step(&loss(&resumed_w)?.backward()?)?;
            }
        }
        let flat = |w: &Var| w.as_tensor().flatten_all()?.to_vec1::<f32>();
        assert_eq!(flat(&ours_w)?, flat(&theirs_w)?);
        assert_eq!(flat(&resumed_w)?, flat(&theirs_w)?);
        assert_ne!(flat(&ours_w)?, init, "the weights moved");
        let mut fresh = AdamW::new(&[("other".to_string(), var()?)], params)?;
        let saved: HashMap<String, Tensor> = ours.state("g.")?.into_iter().collect();
        let e = fresh
            .restore("g.", &saved, std::path::Path::new("mem"))
            .expect_err("no moments of `other`");
        assert!(e.to_string().contains("g.m.other"), "{e}");
        Ok(())
    }

    #[test]
    fn clipping_scales_the_global_norm_down_to_the_bound() -> Result<(), PolicyError> {
        let dev = candle_core::Device::Cpu;
        let a = Var::from_vec(vec![1f32, 2.0], 2, &dev)?;
        let b = Var::from_vec(vec![3f32], 1, &dev)?;
        // Loss 3a0 + 4b0 gives gradient (3, 0) and (4): global norm 5.
        let loss = ((a.as_tensor().narrow(0, 0, 1)? * 3.0)? + (b.as_tensor() * 4.0)?)?;
        let vars = vec![("a".to_string(), a.clone()), ("b".to_string(), b.clone())];
        let norm = |g: &GradStore| -> Result<f64, PolicyError> {
            let mut sq = 0.0;
            for (_, v) in &vars {
                let g = g.get(v.as_tensor()).expect("a gradient");
                sq += f64::from(g.sqr()?.sum_all()?.to_scalar::<f32>()?);
            }
            Ok(sq.sqrt())
        };
        let mut grads = loss.sum_all()?.backward()?;
        clip_gradients(&mut grads, &vars, 10.0)?;
        assert!(
            (norm(&grads)? - 5.0).abs() < 1e-5,
            "below the bound: unchanged"
        );
        clip_gradients(&mut grads, &vars, 1.0)?;
        assert!((norm(&grads)? - 1.0).abs() < 1e-5, "clipped to the bound");
        let ga = grads
            .get(a.as_tensor())
            .expect("a gradient")
            .to_vec1::<f32>()?;
        assert!((ga[0] - 0.6).abs() < 1e-5 && ga[1] == 0.0, "{ga:?}");
        Ok(())
    }
}
