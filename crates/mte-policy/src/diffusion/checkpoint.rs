//! LeRobot-compatible checkpoints: a directory with `config.json` (LeRobot's schema) and
//! `model.safetensors` (LeRobot's key names), with normalisation statistics either inside
//! `model.safetensors` (old layout: `normalize_inputs.buffer_<feature>.<stat>`, …) or in
//! the processor files of LeRobot >= 0.4 (new layout:
//! `policy_preprocessor_step_<i>_normalizer_processor.safetensors` and
//! `policy_postprocessor_step_<i>_unnormalizer_processor.safetensors`, flat keys
//! `<feature>.<stat>`). We write the new layout.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};

use crate::config::DiffusionConfig;
use crate::error::PolicyError;
use crate::model::{DiffusionPolicy, StatsMap};
use crate::normalize::Stats;

/// Weights file name.
pub const WEIGHTS: &str = "model.safetensors";
/// Config file name.
pub const CONFIG: &str = "config.json";
/// Normaliser statistics file we write (LeRobot 0.4 preprocessor step 3).
pub const PRE_STATS: &str = "policy_preprocessor_step_3_normalizer_processor.safetensors";
/// Unnormaliser statistics file we write (LeRobot 0.4 postprocessor step 0).
pub const POST_STATS: &str = "policy_postprocessor_step_0_unnormalizer_processor.safetensors";

pub(crate) fn ck(path: &Path, reason: impl Into<String>) -> PolicyError {
    PolicyError::Checkpoint {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

/// Sets each variable of `varmap` whose name `key_of` maps to a key from `tensors[key]`
/// (read from `path`, named in errors); variables `key_of` maps to `None` are left as they
/// are. A missing key or a different shape is an error naming the key, the variable and the
/// shape the policy expects. Returns how many variables were set.
pub(crate) fn set_variables(
    varmap: &VarMap,
    path: &Path,
    tensors: &HashMap<String, Tensor>,
    key_of: impl Fn(&str) -> Option<String>,
) -> Result<usize, PolicyError> {
    let vars = varmap
        .data()
        .lock()
        .map_err(|_| crate::error::config_err("varmap", "poisoned", "unlocked"))?;
    let mut set = 0;
    for (name, var) in vars.iter() {
        let Some(key) = key_of(name) else {
            continue;
        };
        let t = tensors.get(&key).ok_or_else(|| {
            let why = format!(
                "no tensor `{key}`, expected one of shape {:?} for the policy's `{name}` ({} tensors in the file)",
                var.dims(),
                tensors.len()
            );
            ck(path, why)
        })?;
        if t.shape() != var.shape() {
            let why = format!(
                "`{key}` has shape {:?}, the policy's `{name}` expects {:?}",
                t.dims(),
                var.dims()
            );
            return Err(ck(path, why));
        }
        var.set(t)?;
        set += 1;
    }
    Ok(set)
}

pub(crate) fn read_tensors(
    path: &Path,
    device: &Device,
) -> Result<HashMap<String, Tensor>, PolicyError> {
    candle_core::safetensors::load(path, device)
        .map_err(|e| ck(path, format!("cannot read safetensors: {e}")))
}

fn set_stat(
    stats: &mut StatsMap,
    feature: &str,
    stat: &str,
    t: &Tensor,
) -> Result<(), PolicyError> {
    let v: Vec<f32> = t.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
    let s = stats.entry(feature.to_string()).or_default();
    match stat {
        "min" => s.min = v,
        "max" => s.max = v,
        "mean" => s.mean = v,
        "std" => s.std = v,
        _ => {}
    }
    Ok(())
}

/// Statistics from flat `<feature>.<stat>` keys.
fn stats_from_flat(map: &HashMap<String, Tensor>, stats: &mut StatsMap) -> Result<(), PolicyError> {
    for (k, t) in map {
        if let Some((feature, stat)) = k.rsplit_once('.') {
            set_stat(stats, feature, stat, t)?;
        }
    }
    Ok(())
}

/// Statistics from the old in-model buffers `normalize_inputs.buffer_observation_state.min`
/// (feature dots written as underscores after `buffer_`).
fn stats_from_old(
    map: &HashMap<String, Tensor>,
    config: &DiffusionConfig,
    stats: &mut StatsMap,
) -> Result<(), PolicyError> {
    let names: Vec<&String> = config
        .input_features
        .keys()
        .chain(config.output_features.keys())
        .collect();
    for (k, t) in map {
        for prefix in [
            "normalize_inputs.buffer_",
            "normalize_targets.buffer_",
            "unnormalize_outputs.buffer_",
        ] {
            if let Some(rest) = k.strip_prefix(prefix)
                && let Some((feat, stat)) = rest.rsplit_once('.')
                && let Some(name) = names.iter().find(|n| n.replace('.', "_") == feat)
            {
                set_stat(stats, name, stat, t)?;
            }
        }
    }
    Ok(())
}

/// Load a checkpoint directory onto `device`. Errors name the missing or misshapen key.
pub fn load(dir: &Path, device: &Device) -> Result<DiffusionPolicy, PolicyError> {
    let (config, weights, stats) = read_checkpoint(dir, device)?;
    let wpath = dir.join(WEIGHTS);
    let vb = VarBuilder::from_tensors(weights, DType::F32, device);
    DiffusionPolicy::new(config, stats, vb).map_err(|e| match e {
        PolicyError::Candle(err) => ck(&wpath, err.to_string()),
        other => other,
    })
}

/// A checkpoint directory's config, weights (LeRobot key names) and statistics (from either
/// layout).
fn read_checkpoint(
    dir: &Path,
    device: &Device,
) -> Result<(DiffusionConfig, HashMap<String, Tensor>, StatsMap), PolicyError> {
    let config = DiffusionConfig::from_file(&dir.join(CONFIG))?;
    let wpath = dir.join(WEIGHTS);
    let weights = read_tensors(&wpath, device)?;
    let mut stats = StatsMap::new();
    stats_from_old(&weights, &config, &mut stats)?;
    read_processor_stats(dir, device, &mut stats)?;
    Ok((config, weights, stats))
}

/// A checkpoint directory's normalisation statistics (from either layout), e.g. to keep a
/// warm start's scaling when training on data whose ranges differ.
///
/// # Errors
/// As [`load`]: a missing or unreadable config, weights or processor file.
pub fn read_stats(dir: &Path) -> Result<StatsMap, PolicyError> {
    Ok(read_checkpoint(dir, &Device::Cpu)?.2)
}

/// Adds the statistics of LeRobot >= 0.4's processor files in `dir` to `stats`.
pub(crate) fn read_processor_stats(
    dir: &Path,
    device: &Device,
    stats: &mut StatsMap,
) -> Result<(), PolicyError> {
    let mut files: Vec<_> = std::fs::read_dir(dir)
        .map_err(|source| PolicyError::Io {
            path: dir.to_path_buf(),
            source,
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name().and_then(|n| n.to_str()).is_some_and(|n| {
                n.ends_with(".safetensors")
                    && (n.contains("_normalizer_processor")
                        || n.contains("_unnormalizer_processor"))
            })
        })
        .collect();
    files.sort();
    for f in files {
        stats_from_flat(&read_tensors(&f, device)?, stats)?;
    }
    Ok(())
}

/// Load a checkpoint as trainable variables: the policy and the [`VarMap`] holding its
/// weights under LeRobot's key names (for fine-tuning; [`load`] gives constants).
pub fn load_trainable(
    dir: &Path,
    device: &Device,
) -> Result<(DiffusionPolicy, VarMap), PolicyError> {
    let (config, weights, stats) = read_checkpoint(dir, device)?;
    let wpath = dir.join(WEIGHTS);
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, device);
    let policy = DiffusionPolicy::new(config, stats, vb)?;
    let vars = varmap
        .data()
        .lock()
        .map_err(|_| ck(&wpath, "variable map poisoned"))?;
    for (name, var) in vars.iter() {
        let t = weights
            .get(name)
            .ok_or_else(|| ck(&wpath, format!("missing {name}")))?;
        var.set(t).map_err(|e| ck(&wpath, format!("{name}: {e}")))?;
    }
    drop(vars);
    Ok((policy, varmap))
}

/// Save `config`, `weights` (LeRobot key names) and `stats` as a new-layout directory.
pub fn save(
    dir: &Path,
    config: &DiffusionConfig,
    weights: &HashMap<String, Tensor>,
    stats: &StatsMap,
) -> Result<(), PolicyError> {
    write_config(dir, config)?;
    candle_core::safetensors::save(weights, dir.join(WEIGHTS))?;
    save_stats(dir, stats)
}

/// Creates `dir` and writes `config` as `config.json`.
pub(crate) fn write_config(dir: &Path, config: &impl serde::Serialize) -> Result<(), PolicyError> {
    std::fs::create_dir_all(dir).map_err(|source| PolicyError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let json = serde_json::to_string_pretty(config).map_err(|source| PolicyError::Json {
        path: dir.join(CONFIG),
        source,
    })?;
    std::fs::write(dir.join(CONFIG), json + "\n").map_err(|source| PolicyError::Io {
        path: dir.join(CONFIG),
        source,
    })
}

/// Writes `stats` as LeRobot 0.4's normaliser and unnormaliser processor files.
pub(crate) fn save_stats(dir: &Path, stats: &StatsMap) -> Result<(), PolicyError> {
    let flat = |filter: &dyn Fn(&str) -> bool| -> Result<HashMap<String, Tensor>, PolicyError> {
        let mut m = HashMap::new();
        for (name, s) in stats.iter().filter(|(n, _)| filter(n)) {
            let Stats {
                min,
                max,
                mean,
                std,
            } = s;
            for (stat, v) in [("min", min), ("max", max), ("mean", mean), ("std", std)] {
                if !v.is_empty() {
                    m.insert(
                        format!("{name}.{stat}"),
                        Tensor::from_vec(v.clone(), v.len(), &Device::Cpu)?,
                    );
                }
            }
        }
        Ok(m)
    };
    candle_core::safetensors::save(&flat(&|_| true)?, dir.join(PRE_STATS))?;
    candle_core::safetensors::save(&flat(&|n| n == "action")?, dir.join(POST_STATS))?;
    Ok(())
}

#[cfg(test)]
mod set_variables_tests {
    use super::*;
    use candle_nn::Init;

    fn varmap() -> VarMap {
        let vm = VarMap::new();
        for (name, shape) in [("a", (2, 3)), ("b", (4, 1))] {
            vm.get(shape, name, Init::Const(0.0), DType::F32, &Device::Cpu)
                .expect("var");
        }
        vm
    }

    fn tensors(entries: &[(&str, (usize, usize), f32)]) -> HashMap<String, Tensor> {
        entries
            .iter()
            .map(|&(k, shape, v)| {
                let t = (Tensor::ones(shape, DType::F32, &Device::Cpu).expect("t") * f64::from(v))
                    .expect("scaled");
                (k.to_string(), t)
            })
            .collect()
    }

    fn sum(vm: &VarMap, name: &str) -> f32 {
        let vars = vm.data().lock().expect("lock");
        vars[name]
            .as_tensor()
            .sum_all()
            .and_then(|s| s.to_scalar())
            .expect("sum")
    }

    /// Mapped names are set from their keys, unmapped ones are left alone and counted out.
    #[test]
    fn sets_mapped_variables_and_skips_the_rest() {
        let vm = varmap();
        let ts = tensors(&[("m.a", (2, 3), 2.0), ("m.b", (4, 1), 5.0)]);
        let n = set_variables(&vm, Path::new("w.safetensors"), &ts, |n| {
            (n == "a").then(|| format!("m.{n}"))
        })
        .expect("set");
        assert_eq!(n, 1);
        assert_eq!(sum(&vm, "a"), 12.0);
        assert_eq!(sum(&vm, "b"), 0.0);
    }

    /// A missing key names the key, the variable and its shape; another shape names both.
    #[test]
    fn names_a_missing_key_and_a_wrong_shape() {
        let vm = varmap();
        let path = Path::new("w.safetensors");
        let e = set_variables(&vm, path, &tensors(&[("a", (2, 3), 1.0)]), |n| {
            Some(n.to_string())
        })
        .expect_err("b is missing");
        let msg = e.to_string();
        assert!(
            msg.contains("no tensor `b`") && msg.contains("[4, 1]"),
            "{msg}"
        );
        assert!(msg.contains("w.safetensors"), "{msg}");
        let ts = tensors(&[("a", (3, 2), 1.0), ("b", (4, 1), 1.0)]);
        let e = set_variables(&vm, path, &ts, |n| Some(n.to_string())).expect_err("shape");
        let msg = e.to_string();
        assert!(msg.contains("[3, 2]") && msg.contains("[2, 3]"), "{msg}");
    }
}
