//! `mte.policy`: an mte checkpoint (Diffusion Policy or ACT, LeRobot's layout) loaded behind
//! the policy seam, sampling chunks from numpy observations.

use mte_policy::policy::{ChunkPolicy, Observation, load_policy};
use numpy::{PyArray2, PyReadonlyArray1, PyReadonlyArray3};
use pyo3::prelude::*;
use pyo3::types::{PyAnyMethods, PyDict, PyDictMethods, PyList};
use rand::SeedableRng;

use crate::err;

/// A loaded policy.
#[pyclass(name = "Policy", module = "mte._native", frozen)]
pub struct PyPolicy {
    inner: Box<dyn ChunkPolicy + Send + Sync>,
}

fn vector(d: &Bound<'_, PyDict>, key: &str) -> PyResult<Option<Vec<f32>>> {
    match d.get_item(key)? {
        None => Ok(None),
        Some(v) if v.is_none() => Ok(None),
        Some(v) => {
            let a: PyReadonlyArray1<'_, f32> = v.extract().map_err(|_| {
                err(format!(
                    "observation[{key:?}]: expected a 1-D float32 array"
                ))
            })?;
            Ok(Some(a.as_slice().map_err(err)?.to_vec()))
        }
    }
}

/// The camera frame under `key` (`image`, `wrist_image`), if present.
fn frame(d: &Bound<'_, PyDict>, key: &str) -> PyResult<Option<Vec<u8>>> {
    match d.get_item(key)? {
        Some(v) if !v.is_none() => {
            let a: PyReadonlyArray3<'_, u8> = v.extract().map_err(|_| {
                err(format!(
                    "observation[{key:?}]: expected an (H, W, 3) uint8 array"
                ))
            })?;
            Ok(Some(a.as_slice().map_err(err)?.to_vec()))
        }
        _ => Ok(None),
    }
}

fn observation(d: &Bound<'_, PyDict>) -> PyResult<Observation> {
    let state = vector(d, "state")?
        .ok_or_else(|| err("observation without \"state\": expected the agent position (px)"))?;
    Ok(Observation {
        state,
        env_state: vector(d, "env_state")?,
        image: frame(d, "image")?,
        wrist_image: frame(d, "wrist_image")?,
    })
}

#[pymethods]
impl PyPolicy {
    /// Loads a checkpoint directory (`config.json` names the type).
    #[staticmethod]
    fn load(path: std::path::PathBuf) -> PyResult<Self> {
        Ok(Self {
            inner: load_policy(&path).map_err(err)?,
        })
    }

    /// The chunk `(horizon, action_dim)` for `history` (a list of `n_obs_steps` dicts with
    /// `state`, and `env_state` or `image` as the policy reads them), sampled with `seed`.
    fn predict<'py>(
        &self,
        py: Python<'py>,
        history: &Bound<'py, PyList>,
        seed: u64,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let obs: Vec<Observation> = history
            .iter()
            .map(|o| {
                observation(
                    o.downcast::<PyDict>()
                        .map_err(|_| err("history: expected a list of dicts"))?,
                )
            })
            .collect::<PyResult<_>>()?;
        let policy = &self.inner;
        let chunk = py
            .allow_threads(|| {
                let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
                policy.predict_chunk(&obs, &mut rng)
            })
            .map_err(err)?;
        let a = self.inner.action_dim();
        let rows: Vec<Vec<f32>> = chunk.chunks(a).map(<[f32]>::to_vec).collect();
        PyArray2::from_vec2(py, &rows).map_err(err)
    }

    #[getter]
    fn horizon(&self) -> usize {
        self.inner.horizon()
    }

    #[getter]
    fn n_obs_steps(&self) -> usize {
        self.inner.n_obs_steps()
    }

    #[getter]
    fn action_dim(&self) -> usize {
        self.inner.action_dim()
    }

    /// What the policy reads: `{"env_state": bool, "image": (width, height) or None}`.
    fn needs<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let n = self.inner.needs();
        let d = PyDict::new(py);
        d.set_item("env_state", n.env_state)?;
        d.set_item("image", n.image)?;
        d.set_item("wrist_image", n.wrist_image)?;
        Ok(d)
    }
}
