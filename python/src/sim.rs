//! Native PushT for Python: one environment (`PushT`) and a batch stepped in Rust
//! (`VecPushT`). The gymnasium environment in `mte/envs.py` builds gym-pusht's observation
//! types on top of these.

use mte_sim::render::Renderer;
use mte_sim::{PushT, ResetStream, State, StepInfo, VecEnv};
use numpy::{PyArray1, PyArray2, PyArray3, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::err;

fn stream(name: &str) -> PyResult<ResetStream> {
    name.parse().map_err(err)
}

/// `info` as gym-pusht reports it, plus `reward` and the step count.
fn info<'py>(py: Python<'py>, s: &StepInfo, goal: [f64; 3]) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("reward", s.reward)?;
    d.set_item("coverage", s.coverage)?;
    d.set_item("is_success", s.is_success)?;
    d.set_item("steps", s.steps)?;
    d.set_item("pos_agent", PyArray1::from_slice(py, &s.pos_agent))?;
    d.set_item("vel_agent", PyArray1::from_slice(py, &s.vel_agent))?;
    let p = s.block_pose;
    d.set_item("block_pose", PyArray1::from_slice(py, &[p.x, p.y, p.theta]))?;
    d.set_item("goal_pose", PyArray1::from_slice(py, &goal))?;
    d.set_item("n_contacts", s.n_contacts)?;
    Ok(d)
}

/// One native PushT environment (gym-pusht 0.1.8's physics, bit-exact seeded resets).
#[pyclass(name = "PushT", module = "mte._native")]
pub struct PyPushT {
    env: PushT,
    renderer: Renderer,
}

#[pymethods]
impl PyPushT {
    #[new]
    fn new() -> Self {
        let env = PushT::default();
        let renderer = Renderer::new(env.goal());
        Self { env, renderer }
    }

    /// Seeded reset; `stream` is `"pcg64"` (gym-pusht >= 0.1.6) or `"legacy"` (Diffusion
    /// Policy's seeds). Returns the state observation `[agent_x, agent_y, block_x, block_y,
    /// block_angle]` (angle wrapped to `[0, 2 pi)`, as gym-pusht observes it).
    #[pyo3(signature = (seed, stream = "pcg64"))]
    fn reset<'py>(
        &mut self,
        py: Python<'py>,
        seed: u64,
        stream: &str,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        self.env.reset(seed, self::stream(stream)?).map_err(err)?;
        Ok(PyArray1::from_slice(py, &self.env.state_obs()))
    }

    /// Resets to a given state `[agent_x, agent_y, block_x, block_y, block_angle]` (px, rad).
    fn reset_to_state(&mut self, state: [f64; 5]) -> PyResult<()> {
        self.env.reset_to(State::from_array(state)).map_err(err)
    }

    /// One control step towards the target `action = [x, y]` (px); returns gym-pusht's
    /// `info` dict (with `reward`).
    fn step<'py>(&mut self, py: Python<'py>, action: [f64; 2]) -> PyResult<Bound<'py, PyDict>> {
        let s = py.allow_threads(|| self.env.step(action)).map_err(err)?;
        let g = self.env.goal();
        info(py, &s, [g.x, g.y, g.theta])
    }

    /// The state `[agent_x, agent_y, block_x, block_y, block_angle]`.
    fn state<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.env.state_obs())
    }

    /// The block's 8 keypoints as 16 values (gym-pusht's `environment_state`), px.
    fn keypoints<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.env.keypoints())
    }

    fn agent_pos<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, &self.env.agent_pos())
    }

    fn coverage(&self) -> f64 {
        self.env.coverage()
    }

    /// The observation frame (`height x width x 3` uint8, as gym-pusht renders it).
    #[pyo3(signature = (width = 96, height = 96))]
    fn pixels<'py>(
        &mut self,
        py: Python<'py>,
        width: usize,
        height: usize,
    ) -> PyResult<Bound<'py, PyArray3<u8>>> {
        let (env, renderer) = (&self.env, &mut self.renderer);
        let mut out = vec![0u8; width * height * 3];
        py.allow_threads(|| {
            renderer.observation_with_contacts_into(
                &env.scene(),
                env.contact_segments(),
                width,
                height,
                &mut out,
            )
        })
        .map_err(err)?;
        frame(py, out, height, width)
    }

    /// gym-pusht's `render()` frame (visualisation, with the last action's marker).
    #[pyo3(signature = (width = 680, height = 680))]
    fn render<'py>(
        &mut self,
        py: Python<'py>,
        width: usize,
        height: usize,
    ) -> PyResult<Bound<'py, PyArray3<u8>>> {
        let (env, renderer) = (&self.env, &mut self.renderer);
        let out = py
            .allow_threads(|| {
                renderer.visualization_with_contacts(
                    &env.scene(),
                    env.contact_segments(),
                    env.last_action(),
                    width,
                    height,
                )
            })
            .map_err(err)?;
        frame(py, out, height, width)
    }
}

fn frame(
    py: Python<'_>,
    data: Vec<u8>,
    height: usize,
    width: usize,
) -> PyResult<Bound<'_, PyArray3<u8>>> {
    numpy::ndarray::Array3::from_shape_vec((height, width, 3), data)
        .map(|a| PyArray3::from_owned_array(py, a))
        .map_err(err)
}

/// `n` PushT environments stepped together in Rust (several threads from 8 environments
/// on); state observations only.
#[pyclass(name = "VecPushT", module = "mte._native")]
pub struct PyVecPushT {
    envs: VecEnv,
}

#[pymethods]
impl PyVecPushT {
    #[new]
    fn new(n: usize) -> PyResult<Self> {
        if n == 0 {
            return Err(err("num_envs 0: expected at least 1 environment"));
        }
        Ok(Self {
            envs: VecEnv::new(n, Default::default()),
        })
    }

    fn __len__(&self) -> usize {
        self.envs.len()
    }

    /// Resets environment `i` with `seeds[i]`; returns the `(n, 5)` states.
    #[pyo3(signature = (seeds, stream = "pcg64"))]
    fn reset<'py>(
        &mut self,
        py: Python<'py>,
        seeds: Vec<u64>,
        stream: &str,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        if seeds.len() != self.envs.len() {
            return Err(err(format!(
                "{} seeds for {} environments",
                seeds.len(),
                self.envs.len()
            )));
        }
        let stream = self::stream(stream)?;
        let envs = &mut self.envs;
        py.allow_threads(|| envs.reset(&seeds, stream))
            .map_err(err)?;
        Ok(self.states(py))
    }

    /// Steps environment `i` towards `actions[i]` (an `(n, 2)` array, px); returns the
    /// `(n, 5)` states, rewards, coverages and successes.
    #[allow(clippy::type_complexity)]
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        actions: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<(
        Bound<'py, PyArray2<f64>>,
        Bound<'py, PyArray1<f64>>,
        Bound<'py, PyArray1<f64>>,
        Bound<'py, PyArray1<bool>>,
    )> {
        let n = self.envs.len();
        if actions.shape() != [n, 2] {
            return Err(err(format!(
                "actions of shape {:?}: expected ({n}, 2)",
                actions.shape()
            )));
        }
        let a = actions.as_array();
        let acts: Vec<[f64; 2]> = (0..n).map(|i| [a[[i, 0]], a[[i, 1]]]).collect();
        let envs = &mut self.envs;
        let infos = py.allow_threads(|| envs.step(&acts)).map_err(err)?;
        let reward: Vec<f64> = infos.iter().map(|s| s.reward).collect();
        let coverage: Vec<f64> = infos.iter().map(|s| s.coverage).collect();
        let success: Vec<bool> = infos.iter().map(|s| s.is_success).collect();
        Ok((
            self.states(py),
            PyArray1::from_vec(py, reward),
            PyArray1::from_vec(py, coverage),
            PyArray1::from_vec(py, success),
        ))
    }
}

impl PyVecPushT {
    fn states<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let rows: Vec<Vec<f64>> = self.envs.observe(|e| e.state_obs().to_vec());
        PyArray2::from_vec2(py, &rows).expect("rows of 5")
    }
}
